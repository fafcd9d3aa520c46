"""Batched RUL for a shard of assets: degradation onset, exponential trend by the engine, RUL.

The function of this module takes ONE padded batch of series (a shard) and returns per-asset
RUL quantiles; every step is vectorised over the assets of the shard, and nothing in an asset's
result depends on the other assets of the shard (shard-size invariance; tested to 1e-12).

1. **Onset** (first prediction time): the batched k-sigma moving-median rule of
   :func:`~prognos_torch.fleet.batch.ksigma_onset_batch`, after each asset's healthy window.
   Before onset the asset is reported as "no degradation detected yet" (``no_onset``) and no
   RUL number is given.
2. **Exponential trend** (Gebraeel et al., 2005): ``y = phi + theta exp(beta tau + eps)``,
   ``tau = t - t_onset``, i.e. ``z = log(s (y - phi)) = a + beta tau + eps`` with
   ``s = +1`` ("above") or ``-1`` ("below"): linear-Gaussian in the parameters
   ``x = [a, beta]``. They are the state of a random walk (``x_k = x_{k-1} + w``, default
   ``w = 0``: Gebraeel's Bayesian regression), measured by ``z_k = [1, tau_k] x_k + v`` with
   ``v ~ N(0, sigma^2)`` and ``sigma`` the spread of ``z`` over the asset's healthy baseline.
   The engine filters all assets of the shard in ONE ``filters.run`` call (EKF: exact Kalman
   filter for this linear model; NaN = missing, so padding and gaps only predict). The prior is
   ``a ~ N(baseline mean of z, prior_std[0]^2)``, ``beta ~ N(0, prior_std[1]^2)`` (default
   ``prior_std[1]``: one log unit per median sampling interval).

   ``phi`` is ``"auto"`` by default (below), one number for the fleet (0: the indicator grows
   multiplicatively from near zero, ``y = theta exp(beta tau + eps)``), or ``"baseline"``:
   each asset's healthy mean
   ``mu_0``, as :func:`~prognos_torch.workflow.prognose` takes it, for an indicator that rises
   from a healthy level with additive noise (a bearing's rms): ``d = s (y - mu_0) =
   exp(a + beta tau) + v``, ``v ~ N(0, sigma_0^2)`` with ``sigma_0`` the baseline std, on the
   data scale, where ``d`` may be near zero or negative. Its MAP is found by Gauss-Newton, each
   iteration one engine run on the pseudo-measurements ``z~ = g + (d - e^g) / e^g`` with noise
   ``sigma_0 / e^g`` linearised at the current ``g = a + beta tau``, its step halved until the
   objective does not grow; the posterior is the run linearised at the MAP (Laplace). The
   start is the regression of ``log d`` on the samples with ``d >= sigma_0`` (noise
   ``sigma_0 / d``, the delta method), which also centres the prior of ``a`` on the first of
   them; that regression alone is biased late (it keeps the early values that noise pushed
   up) and its intervals covered 0.66-0.70 of the truth where the MAP's cover 0.82-0.90
   (``docs/RESULTS.md``, fleets). With ``drift_std`` not 0 the linearisation points are the
   RTS-smoothed means (the iterated extended Kalman smoother). On an indicator with a healthy
   level ``phi = 0`` reads the early, slow part of the log curve as the trend and predicts
   late.

   ``"auto"`` (the default) fits both and keeps, per asset, the one under which the samples
   since onset
   (those with ``s y > 0``) are likelier on the data scale at the posterior mean:
   ``log(s y) ~ N(a + beta tau, sigma^2)`` with its Jacobian ``1 / (s y)`` for ``phi = 0``,
   ``s (y - mu_0) ~ N(exp(a + beta tau), sigma_0^2)`` for the baseline. Both have two
   parameters and noise fixed by the healthy window, so this is also the AIC and BIC choice.
   On fleets of both kinds it chose right on every asset (``docs/RESULTS.md``, fleets).
3. **Lack of fit** (``trend_misfit``): an F test of the residual variance about the posterior
   mean line since onset against the model's noise from the healthy window,
   ``F = (sum_k w_k r_k^2 / (m - 2)) / s_b^2`` on ``(m - 2, n_b - 1)`` degrees of freedom
   (``w_k`` the inverse of ``z_k``'s noise variance in units of ``s_b^2``: 1, or ``e^{2 g_k}``
   with ``phi="baseline"``, where ``w_k r_k^2`` is the squared data-scale residual);
   ``p < MISFIT_P`` = 1e-3 flags the asset. Exact for the default fixed parameters
   (``drift_std = 0``); the intervals of an asset whose data leave the model are too narrow.
4. **RUL**: ``samples`` draws of ``[a, beta]`` from the posterior at the asset's last row, each
   from the asset's own generator (seeded by :func:`asset_seed` from the fleet seed and the asset
   id: results do not depend on sharding). Each sampled trend crosses ``log(s (X - phi))`` at
   ``tau* = (log(s (X - phi)) - a) / beta`` if ``beta > 0`` (its first passage, in closed form)
   and never otherwise; ``RUL = max(0, tau* - tau_last)``. Paths that never cross are the
   censored mass (the model's horizon is unbounded: no cap is put on the crossing time).
   ``p_fail_within_horizon = P(RUL <= horizon)`` (``horizon=None``: ever). Quantiles are lower
   empirical quantiles over the samples with censored paths at +inf: NaN where the quantile lies
   beyond every crossing.

Flags (``;``-separated per asset): ``too_few_rows``, ``no_baseline`` (baseline window with fewer
than 3 samples, no spread, or non-positive ``s (y - phi)`` with a fixed ``phi``), ``no_onset``,
``threshold_on_healthy_side`` (the baseline mean is at or beyond the threshold: a falling
indicator with ``direction="above"``, say; no RUL), ``threshold_reached``
(the last observed value is at or beyond the threshold: RUL 0), ``few_degraded_points`` (fewer
than 3 usable samples after onset: the interval is wide), ``nonpositive_dropped`` (samples with
``s (y - phi) <= 0`` after onset were treated as missing; fixed ``phi``), ``far_extrapolation`` (median RUL
beyond ``extrapolation_limit`` times the observed degradation time: a guard rail),
``trend_misfit`` (the lack-of-fit test above), ``fit_past_threshold`` (the fitted trend at
the last observed row lies at or beyond the threshold, which the value there has not reached:
the model contradicts the data, no RUL), ``last_rows_missing`` (the last rows have no value:
the RUL counts from ``t_last``, and a crossing the trend puts in the unobserved stretch is a
RUL of 0),
``glitch_in_baseline`` (isolated values more than ``GLITCH_SCREEN`` = 20 noise std off their
neighbours in the healthy window widen its std ``GLITCH_WIDENING`` = 1.5 times or more, which can
delay the onset: ``prognose``'s glitch flag, :mod:`prognos_torch.prognosis.onset`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..core import GaussianBelief, StateSpaceModel
from ..core.validation import check_real, is_int, is_real
from ..filters import ekf, run
from ..filters.gaussian import GaussianFilter
from ..prognosis.onset import GLITCH_WIDENING
from .batch import PaddedBatch, check_min_rows, check_onset_rule, check_rows, ksigma_onset_batch

__all__ = [
    "exponential_trend_rul",
    "RUL_COLUMNS",
    "MISFIT_P",
]

#: p-value below which the exponential trend's lack-of-fit test flags an asset
#: (``trend_misfit``): about 1 asset in 1000 whose data follow the model
MISFIT_P = 1e-3

#: per-asset numeric outputs of a RUL method, in table order
RUL_COLUMNS = (
    "n_rows",
    "t_last",
    "onset_time",
    "rul_median",
    "rul_q05",
    "rul_q95",
    "p_fail_within_horizon",
    "censored_mass",
)


def _check_pair(v, name: str, what: str, positive: bool, optional_second: bool = False):
    """A pair of finite reals (``> 0`` if ``positive``, else ``>= 0``), its second ``None``
    where ``optional_second``: ``ValueError`` naming ``name`` and ``what`` it holds."""
    try:
        pair = tuple(v)
    except TypeError:
        pair = ()
    if len(pair) == 2:
        out = []
        for j, x in enumerate(pair):
            if x is None and j == 1 and optional_second:
                out.append(None)
                continue
            if getattr(x, "ndim", None) == 0 and hasattr(x, "item"):
                x = x.item()
            if not is_real(x) or not (0.0 < x < math.inf if positive else 0.0 <= x < math.inf):
                break
            out.append(float(x))
        else:
            return tuple(out)
    sign = "> 0" if positive else ">= 0"
    raise ValueError(f"{name} must be a pair of finite numbers {sign} ({what}), got {v!r}")


# --------------------------------------------------------------------------- trend + RUL
def _trend_model(chol_Q: Tensor, chol_R: Tensor) -> StateSpaceModel:
    """``x = [a, beta]`` random walk, ``z = a + beta tau`` with ``tau`` as the control."""

    def h(x, u, k):
        return x[..., :1] + x[..., 1:2] * u

    def jac_h(x, u, k):
        one = torch.ones_like(u)
        return torch.stack([one, u], dim=-1).expand(*x.shape[:-1], 1, 2)

    return StateSpaceModel(
        f=None,
        h=h,
        state_dim=2,
        obs_dim=1,
        chol_Q=chol_Q,
        chol_R=chol_R,
        control_dim=1,
        batched=True,
        jac_h=jac_h,
    )


def _lower_quantile(sorted_rul: Tensor, q: float) -> Tensor:
    """``sorted[ceil(q N) - 1]`` along the last axis; inf (beyond every crossing) -> NaN."""
    n = sorted_rul.shape[-1]
    j = min(n - 1, max(0, math.ceil(q * n - 1e-12) - 1))
    v = sorted_rul[..., j]
    return torch.where(torch.isinf(v), torch.full_like(v, math.nan), v)


def _lack_of_fit(
    zs: Tensor, taus: Tensor, weight: Tensor, mean: Tensor, zb_std: Tensor, nzb: Tensor
) -> Tensor:
    """p-value ``(B,)`` of the straight line ``z = a + beta tau`` through the log data since
    onset: ``F = (RSS / (m - 2)) / s_b^2`` against ``F(m - 2, n_b - 1)`` (an F test of the
    residual variance since onset against the healthy window's, the model's noise), RSS about
    the posterior mean at the last row (with fixed parameters the Bayesian regression's fit).
    NaN where ``m < 5`` or the baseline has fewer than 3 samples."""
    from scipy.stats import f as f_dist

    r = zs - (mean[:, :1] + mean[:, 1:] * taus)
    ok = ~torch.isnan(r)
    m = ok.sum(1)
    rss = torch.where(ok, r * r * weight, 0.0).sum(1)
    stat = (rss / (m - 2).clamp(min=1)) / (zb_std * zb_std)
    p = f_dist.sf(stat.cpu().numpy(), (m - 2).cpu().numpy(), (nzb - 1).cpu().numpy())
    p = torch.as_tensor(p, dtype=zs.dtype, device=zs.device)
    return torch.where((m >= 5) & (nzb >= 3) & (zb_std > 0), p, torch.nan)


def _linearised(ds: Tensor, g: Tensor, sigma0: Tensor) -> tuple[Tensor, Tensor]:
    """Gauss-Newton's pseudo-measurements of ``d = exp(g) + v``, ``v ~ N(0, sigma0^2)``, with
    ``g = a + beta tau`` at the linearisation point: ``z~ = g + (d - e^g) / e^g`` with noise
    ``sigma0 / e^g``; missing where ``d`` is or where ``e^g < 1e-8 sigma0`` (a measurement of
    relative weight below ``1e-16``). Returns ``z~`` and its weight ``e^{2g}`` in ``sigma0^2``
    units, both ``(B, T)``."""
    e = torch.exp(g.clamp(max=700.0))
    ok = ~torch.isnan(ds) & (e >= 1e-8 * sigma0[:, None])
    z = torch.where(ok, g + (ds - e) / torch.where(ok, e, 1.0), torch.nan)
    return z, torch.where(ok, e * e, 0.0)


def _objective(
    ds: Tensor, taus: Tensor, x: Tensor, sigma0: Tensor, m0: Tensor, sd: Tensor
) -> Tensor:
    """``sum_k ((d_k - e^{a + beta tau_k}) / sigma0)^2 + sum_i ((x_i - m0_i) / sd_i)^2`` for
    ``x`` ``(B, L, 2)`` (``L`` candidate steps): ``(B, L)``, inf where ``e^g`` overflows."""
    g = x[..., :1] + x[..., 1:] * taus[:, None, :]
    r = torch.where(torch.isnan(ds)[:, None, :], 0.0, ds[:, None, :] - torch.exp(g))
    r = r / sigma0[:, None, None]
    p = (x - m0[:, None, :]) / sd[:, None, :]
    return (r * r).sum(-1) + (p * p).sum(-1)


#: ``phi="baseline"``: Gauss-Newton iterations at most, step halvings per iteration, and the
#: step (in posterior std) below which it has converged
GN_ITERATIONS, GN_HALVINGS, GN_TOLERANCE = 50, 30, 1e-4


def _weighted_model(drift: Tensor, w: Tensor, sigma0: Tensor) -> StateSpaceModel:
    """The trend model whose measurement noise is ``sigma0 / sqrt(w)`` per row (``w`` ``(B,
    T)``, the inverse variance in ``sigma0^2`` units; 1 where ``w = 0``, a missing row): the
    delta method's ``sigma0 / d`` and Gauss-Newton's ``sigma0 / e^g`` alike."""
    chol_r = torch.where(w > 0, sigma0[:, None] / w.clamp(min=1e-300).sqrt(), 1.0)
    chol_r = chol_r.T[..., None, None].contiguous()  # (T, B, 1, 1)
    return _trend_model(drift, lambda k: chol_r[k - 1])


def _linearised_model(drift: Tensor, ds: Tensor, g: Tensor, sigma0: Tensor):
    """The trend model with Gauss-Newton's pseudo-measurement noise ``sigma0 / e^g`` per row,
    and the pseudo-measurements and weights of :func:`_linearised`."""
    z, w = _linearised(ds, g, sigma0)
    return _weighted_model(drift, w, sigma0), z, w


def _at(rows: Tensor, last: Tensor) -> Tensor:
    """``rows`` ``(T, B, ...)`` at each asset's row ``last`` ``(B,)``: ``(B, ...)``."""
    shape = (1, rows.shape[1], *rows.shape[2:])
    return rows.gather(0, last.reshape(1, -1, *([1] * (rows.dim() - 2))).expand(shape))[0]


class _DataScale(NamedTuple):
    """The data of the baseline trend's data-scale fit: ``d = s (y - mu_0)`` since onset and
    its clock ``tau`` ``(B, T)`` (NaN: missing), each asset's last row ``(B,)`` and healthy
    std ``sigma0`` ``(B,)``."""

    ds: Tensor
    taus: Tensor
    last: Tensor
    sigma0: Tensor


def _gauss_newton(
    filt: GaussianFilter,
    drift: Tensor,
    prior: GaussianBelief,
    prior_sd: Tensor,
    data: _DataScale,
    x: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """MAP of ``[a, beta]`` under ``d_k = exp(a + beta tau_k) + v_k``, ``v_k ~ N(0, sigma0^2)``,
    on the data scale (every observed sample since onset; none is left out, so none is selected
    by its noise) by Gauss-Newton from ``x`` ``(B, 2)``. Each iteration is one engine run on
    the pseudo-measurements of :func:`_linearised` (the Kalman filter's mean at the last row
    ``last`` ``(B,)`` is the linearised problem's MAP), its step halved until the objective
    :func:`_objective` does not grow; an asset leaves the iterations once its step is below
    ``GN_TOLERANCE`` posterior std (or no step lowers its objective: its rounding floor), so
    that the runs shrink to the assets still moving. With a drift (``drift_std`` not 0):
    :func:`_iterated_smoother`. Returns the mean and Cholesky factor at ``last`` of the run
    linearised at the optimum (Laplace), and that run's pseudo-measurements and weights
    ``(B, T)`` (for the lack-of-fit test)."""
    if bool((drift != 0).any()):
        return _iterated_smoother(filt, drift, prior, data, x)
    ds, taus, last, sigma0 = data
    B, T = ds.shape
    lam = 0.5 ** torch.arange(1, GN_HALVINGS + 1, dtype=x.dtype, device=x.device)  # (L,)
    x, mean = x.clone(), x.clone()
    chol = torch.zeros(B, 2, 2, dtype=x.dtype, device=x.device)
    z_all, w_all = torch.full_like(ds, math.nan), torch.zeros_like(ds)
    act = torch.arange(B, device=x.device)  # the assets still iterating
    for it in range(GN_ITERATIONS + 1):
        xa, da, ta, s0, la = x[act], ds[act], taus[act], sigma0[act], last[act]
        pa = GaussianBelief(prior.mean[act], prior.chol[act])
        model, z, w = _linearised_model(drift, da, xa[:, :1] + xa[:, 1:] * ta, s0)
        tr = run(filt, model, pa, z.T[..., None], ta.T[..., None])
        new, ch = _at(tr.means, la), _at(tr.chols, la)
        mean[act], chol[act], z_all[act], w_all[act] = new, ch, z, w
        step = new - xa
        # converged: every step below GN_TOLERANCE posterior std (the filter's rounding is a
        # floor under any absolute tolerance: about 1e-9 of a log unit, 1e-6 std at worst)
        moving = ~(step.abs() <= GN_TOLERANCE * ch.pow(2).sum(-1).sqrt()).all(-1)
        if it == GN_ITERATIONS or not bool(moving.any()):
            break
        # the largest 2^-i step (i = 0 .. GN_HALVINGS) that does not raise the objective:
        # the whole step first, the halvings only where it raises the objective
        sd_p, m0 = prior_sd[act], pa.mean
        j = _objective(da, ta, torch.stack([xa, new], 1), s0, m0, sd_p)  # (A, 2)
        take = (j[:, 1] <= j[:, 0]).to(x.dtype)
        up = (take == 0).nonzero()[:, 0]
        if up.numel():
            cand = xa[up, None, :] + lam[None, :, None] * step[up, None, :]
            down = _objective(da[up], ta[up], cand, s0[up], m0[up], sd_p[up]) <= j[up, :1]
            take[up] = torch.where(down.any(1), lam[down.to(torch.int64).argmax(1)], 0.0)
            moving[up] &= down.any(1)  # no step lowers the objective: its rounding floor
        x[act] = xa + take[:, None] * step
        act = act[moving]
    return mean, chol, z_all, w_all


def _iterated_smoother(
    filt: GaussianFilter, drift: Tensor, prior: GaussianBelief, data: _DataScale, x: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`_gauss_newton` with a drift: the linearisation points are the RTS-smoothed
    means, one per row (the iterated extended Kalman smoother), the steps whole, until every
    step of an asset is below ``GN_TOLERANCE`` smoothed std; a converged asset keeps its
    linearisation points (its result is then that of the iteration where it converged,
    whatever the other assets of the shard do: shard-size invariance)."""
    from ..filters.smooth import smooth

    ds, taus, last, sigma0 = data
    B, T = ds.shape
    path = x[None].expand(T, B, 2)  # linearisation point per row (T, B, 2)
    done = torch.zeros(B, dtype=torch.bool, device=x.device)
    for it in range(GN_ITERATIONS + 1):
        g = path[..., 0].T + path[..., 1].T * taus
        model, z, w = _linearised_model(drift, ds, g, sigma0)
        sm = smooth(filt, model, prior, z.T[..., None], taus.T[..., None])
        step = sm.means - path
        done |= (step.abs() <= GN_TOLERANCE * sm.chols.pow(2).sum(-1).sqrt()).all(-1).all(0)
        if it == GN_ITERATIONS or bool(done.all()):
            break
        path = torch.where(done[None, :, None], path, sm.means)
    return _at(sm.means, last), _at(sm.chols, last), z, w


def _sample_rul(
    mean: Tensor, chol: Tensor, seeds: list[int], samples: int, log_thr: Tensor,
    tau_last: Tensor, horizon: float | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """Step 4 of the module docstring: ``samples`` draws of ``[a, beta]`` from ``N(mean, chol
    chol^T)`` ``(B, 2)``, ``(B, 2, 2)``, each asset from its own generator (``seeds``), their
    closed-form first passage of ``log_thr`` ``(B, 1)`` after ``tau_last`` ``(B, 1)``. Returns
    the ``(B,)`` median, q05, q95 (lower empirical quantiles), censored mass and
    ``P(RUL <= horizon)``."""
    dt = mean.dtype
    eps = torch.stack(
        [
            torch.randn(samples, 2, generator=torch.Generator().manual_seed(sd), dtype=dt)
            for sd in seeds
        ]
    ).to(mean.device)
    theta = mean[:, None, :] + (chol[:, None, :, :] * eps[:, :, None, :]).sum(-1)
    a, b = theta[..., 0], theta[..., 1]
    cross = torch.where(b > 0, (log_thr - a) / torch.where(b > 0, b, 1.0), torch.inf)
    rul = torch.clamp(cross - tau_last, min=0.0)
    rul = torch.where(a + b * tau_last >= log_thr, torch.zeros_like(rul), rul)
    srt = rul.sort(-1).values
    censored = torch.isinf(rul).to(dt).mean(-1)
    if horizon is None:
        p_fail = 1.0 - censored
    else:
        p_fail = (rul <= float(horizon)).to(dt).mean(-1)
    q = [_lower_quantile(srt, level) for level in (0.5, 0.05, 0.95)]
    return q[0], q[1], q[2], censored, p_fail


def _flag_strings(checks: list[tuple[str, Tensor]], B: int) -> list[str]:
    """Per asset, the ``;``-separated names of the ``(B,)`` boolean ``checks`` it fails."""
    masks = [(name, m.cpu().numpy()) for name, m in checks]
    return [";".join(name for name, m in masks if m[i]) for i in range(B)]


def _prior_scales(t: Tensor, lengths: Tensor, prior_std: tuple) -> tuple[float, Tensor]:
    """The prior std of ``a`` (a number) and of ``beta`` ``(B,)``: ``prior_std[1]``, or with
    ``None`` one log unit per median sampling interval of each asset."""
    T = t.shape[1]
    step = torch.diff(t, dim=1)
    step = torch.where(torch.isnan(step), torch.inf, step)
    if T > 1:
        med_dt = torch.where(
            (lengths > 1),
            step.sort(1).values.gather(1, ((lengths - 2) // 2).clamp(min=0)[:, None])[:, 0],
            1.0,
        )
    else:  # a shard of one-row assets (flagged too_few_rows below)
        med_dt = torch.ones_like(t[:, 0])
    sa = float(prior_std[0])
    sb = (1.0 / med_dt) if prior_std[1] is None else torch.full_like(med_dt, float(prior_std[1]))
    return sa, sb


def exponential_trend_rul(
    batch: PaddedBatch,
    threshold: float,
    *,
    direction: str = "above",
    phi: float | str = "auto",
    horizon: float | None = None,
    samples: int = 1000,
    min_rows: int = 10,
    baseline: float = 0.3,
    k: float = 4.0,
    window: int = 5,
    consecutive: int = 5,
    drift_std: tuple[float, float] = (0.0, 0.0),
    prior_std: tuple[float, float | None] = (1.0, None),
    extrapolation_limit: float = 10.0,
    filt: GaussianFilter | None = None,
    return_posterior: bool = False,
) -> dict[str, object]:
    """RUL of every asset of a shard under the exponential trend model (module docstring).

    Args:
        batch: a :class:`PaddedBatch` (one shard).
        threshold: failure threshold ``X`` on the value.
        direction: ``"above"`` (failure when ``y >= X``) or ``"below"``.
        phi: ``"auto"`` (default): per asset the likelier of 0 and the baseline (module
            docstring); a number, the model's offset ``phi`` (``s (X - phi)`` must be
            positive); or ``"baseline"``: each asset's healthy mean. With ``"baseline"`` or ``"auto"`` the
            result holds ``"phi"`` ``(B,)``, the offset each asset used.
        horizon: time span for ``p_fail_within_horizon`` (``None``: ever).
        samples: posterior draws per asset.
        min_rows: fewer observed rows than this are flagged ``too_few_rows`` (no RUL); an
            int >= 1.
        baseline, k, window, consecutive: the onset rule.
        drift_std: random-walk std of ``[a, beta]`` per step (default 0: fixed parameters).
        prior_std: prior std of ``a`` and ``beta`` (``None``: one log unit per median interval).
        extrapolation_limit: guard rail for ``far_extrapolation``.
        filt: the engine configuration (default :func:`~prognos_torch.filters.ekf`).
        return_posterior: also return ``"posterior_mean"`` ``(B, 2)``, ``"posterior_chol"``
            ``(B, 2, 2)`` (of ``[a, beta]`` at the last row), ``"onset_index"`` ``(B,)``,
            ``"log_noise_std"`` ``(B,)`` (NaN with ``phi="baseline"``, whose noise is per
            sample), ``"misfit_p"`` ``(B,)`` (the lack-of-fit p-value) and
            ``"baseline_std"`` ``(B,)`` (the healthy window's std in data units) tensors.
    Returns:
        ``{column: (B,) float64 numpy array}`` for :data:`RUL_COLUMNS` and ``"flags"`` (list of
        ``;``-separated strings).
    """
    baseline, k, window, consecutive, direction = check_onset_rule(
        baseline, k, window, consecutive, direction
    )
    s = 1.0 if direction == "above" else -1.0
    thr = check_real(threshold, "threshold")
    drift_std = _check_pair(drift_std, "drift_std", "random-walk std of a and beta per step",
                            positive=False)  # fmt: skip
    prior_std = _check_pair(prior_std, "prior_std", "prior std of a and beta, or None",
                            positive=True, optional_second=True)  # fmt: skip
    if not is_real(extrapolation_limit) or not extrapolation_limit > 0:
        raise ValueError(
            f"extrapolation_limit must be a number > 0 (inf: no guard), got {extrapolation_limit!r}"
        )
    per_asset = isinstance(phi, str)
    if per_asset and phi not in ("baseline", "auto"):
        raise ValueError(f"phi must be a number, 'baseline' or 'auto', got {phi!r}")
    if phi == "auto":
        return _auto_phi(
            batch, thr, s, return_posterior,
            dict(direction=direction, horizon=horizon, samples=samples, min_rows=min_rows,
                 baseline=baseline, k=k, window=window, consecutive=consecutive,
                 drift_std=drift_std, prior_std=prior_std,
                 extrapolation_limit=extrapolation_limit, filt=filt),
        )  # fmt: skip
    if not per_asset and (not is_real(phi) or not math.isfinite(phi)):
        raise ValueError(f"phi must be a finite number, 'baseline' or 'auto', got {phi!r}")
    if not per_asset:  # (a NumPy float32 phi made s (X - phi), log_thr, float32)
        phi = float(phi)
    if not per_asset and not s * (thr - phi) > 0:
        side = "above" if s > 0 else "below"
        raise ValueError(
            f"threshold {thr:g} must lie {side} phi = {phi:g} for direction {direction!r} "
            "(the exponential model y = phi + theta exp(beta t) grows away from phi)"
        )
    if horizon is not None and not check_real(horizon, "horizon") > 0:
        raise ValueError(f"horizon must be a positive finite number or None, got {horizon!r}")
    if not is_int(samples) or samples < 1:
        raise ValueError(f"samples must be a positive int, got {samples!r}")
    samples = int(samples)
    min_rows = check_min_rows(min_rows)
    y, t, lengths = batch.values, batch.times, batch.lengths
    check_rows(y, t, lengths)
    B, T = y.shape
    dev, dt = y.device, y.dtype
    cols = torch.arange(T, device=dev)
    in_rows = cols < lengths[:, None]
    obs = ~torch.isnan(y) & in_rows
    n_obs = obs.sum(1)
    last_row = (lengths - 1).clamp(min=0)
    t_last = t.gather(1, last_row[:, None])[:, 0]
    # last observed value (for "threshold reached")
    last_obs = torch.where(obs, cols, torch.full_like(cols, -1)).amax(1)
    y_last = y.gather(1, last_obs.clamp(min=0)[:, None])[:, 0]

    on = ksigma_onset_batch(
        y,
        t,
        lengths,
        baseline=baseline,
        k=k,
        window=window,
        consecutive=consecutive,
        direction=direction,
        skip_window=True,
    )
    if per_asset:  # the healthy level; values within its std of it have no usable log
        phis = on.base_mean[:, None]
        d = s * (y - phis)
        usable_d = d >= on.base_std[:, None]
        # (a threshold on the level's healthy side is flagged below)
        log_thr = torch.log((s * (thr - phis)).clamp(min=torch.finfo(dt).tiny))
    else:
        d = s * (y - phi)
        usable_d = d > 0
        log_thr = torch.full((B, 1), math.log(s * (thr - phi)), dtype=dt, device=dev)
    z = torch.where(
        obs & usable_d, torch.log(torch.where(usable_d, d, torch.ones_like(d))), torch.nan
    )
    if per_asset:  # the baseline's noise in data units; z's noise is sigma0 / d per sample
        nzb = (on.in_baseline & obs).sum(1)
        zb_mean, zb_std = torch.zeros_like(on.base_mean), on.base_std
        base_ok = on.baseline_ok & (nzb >= 3) & (zb_std > 0)
    else:  # log-domain baseline: the measurement noise and the prior level of the trend
        zb_ok = on.in_baseline & ~torch.isnan(z)
        nzb = zb_ok.sum(1)
        zb_mean = torch.where(zb_ok, z, 0.0).sum(1) / nzb.clamp(min=1)
        zb_dev = torch.where(zb_ok, z - zb_mean[:, None], 0.0)
        zb_std = torch.sqrt((zb_dev * zb_dev).sum(1) / (nzb - 1).clamp(min=1))
        nonpos_base = (on.in_baseline & obs & (d <= 0)).any(1)
        base_ok = on.baseline_ok & (nzb >= 3) & (zb_std > 0) & ~nonpos_base
    enough = n_obs >= min_rows
    has_onset = (on.index >= 0) & base_ok & enough
    # a threshold on the healthy side of the baseline (a falling indicator with direction
    # "above", say): no RUL, a flag; the healthy asset would count as failed
    healthy_side = enough & on.baseline_ok & (s * (thr - on.base_mean) <= 0)
    reached = (s * (y_last - thr) >= 0) & (n_obs > 0) & ~healthy_side

    # post-onset samples, shifted so that each asset's onset row is step 0
    i0 = torch.where(has_onset, on.index, lengths)  # no onset: nothing to filter
    n_fit = (lengths - i0).clamp(min=0)
    Tf = max(int(n_fit.max()), 1)
    idx = i0[:, None] + torch.arange(Tf, device=dev)
    inside = idx < lengths[:, None]
    idx_c = idx.clamp(max=T - 1)
    t_on = torch.where(has_onset, on.time, torch.zeros_like(on.time))
    zs = torch.where(inside, z.gather(1, idx_c), torch.nan)
    taus = torch.where(inside, t.gather(1, idx_c) - t_on[:, None], 0.0)
    n_deg = (~torch.isnan(zs)).sum(1)
    if per_asset:  # (values within sigma0 of the level are missing by design: no flag)
        nonpos = torch.zeros_like(has_onset)
        ds = torch.where(inside, d.gather(1, idx_c), torch.nan)
        weight = torch.where(torch.isnan(zs), 0.0, ds * ds)  # 1 / var(z) in sigma0^2 units
    else:
        nonpos = (inside & obs.gather(1, idx_c) & (d.gather(1, idx_c) <= 0)).any(1)
        weight = torch.ones_like(zs)

    # prior and noise per asset
    sa, sb = _prior_scales(t, lengths, prior_std)
    if per_asset:  # prior level: the first usable value since onset (no log-domain baseline)
        first = (~torch.isnan(zs)).to(torch.int64).argmax(1, keepdim=True)
        a0 = torch.nan_to_num(zs.gather(1, first)[:, 0], nan=0.0)
    else:
        a0 = torch.where(base_ok, zb_mean, 0.0)
    m0 = torch.stack([a0, torch.zeros_like(a0)], -1)
    S0 = torch.zeros(B, 2, 2, dtype=dt, device=dev)
    S0[:, 0, 0] = sa
    S0[:, 1, 1] = sb
    drift = torch.diag(torch.tensor([float(v) for v in drift_std], dtype=dt, device=dev))
    if per_asset:  # per step: sigma0 / d, the delta method (1 where z is missing)
        model = _weighted_model(drift, weight, zb_std)
        sr = torch.full_like(zb_std, math.nan)  # (no single log-domain noise)
    else:
        sr = torch.where(base_ok, zb_std, 1.0)
        model = _trend_model(drift, sr[:, None, None])
    filt = filt or ekf()
    prior = GaussianBelief(m0, S0)
    tr = run(filt, model, prior, zs.T[..., None], taus.T[..., None])
    last = (n_fit - 1).clamp(min=0)
    mean, chol = _at(tr.means, last), _at(tr.chols, last)  # (B, 2), (B, 2, 2)
    if per_asset:  # the log regression above is the start of Gauss-Newton on the data scale
        ds = torch.where(inside & obs.gather(1, idx_c), d.gather(1, idx_c), torch.nan)
        prior_sd = torch.stack([torch.full_like(sb, sa), sb], -1)
        data = _DataScale(ds, taus, last, zb_std)
        mean, chol, zs, weight = _gauss_newton(filt, drift, prior, prior_sd, data, mean)
    misfit_p = _lack_of_fit(zs, taus, weight, mean, zb_std, nzb)

    med, q05, q95, censored, p_fail = _sample_rul(
        mean, chol, batch.seeds, samples, log_thr, (t_last - t_on)[:, None], horizon
    )
    far = torch.nan_to_num(med, nan=math.inf) > extrapolation_limit * (t_last - t_on).clamp(
        min=torch.finfo(dt).tiny
    )

    nan = torch.full((B,), math.nan, dtype=dt, device=dev)
    # the fitted trend at the last observed row already past the threshold that the value
    # there has not reached: the model contradicts the data (no RUL rather than a certain 0)
    t_obs = t.gather(1, last_obs.clamp(min=0)[:, None])[:, 0]
    g_obs = mean[:, 0] + mean[:, 1] * (t_obs - t_on)
    past = has_onset & ~reached & ~healthy_side & (g_obs >= log_thr[:, 0])
    usable = has_onset & ~reached & ~healthy_side & ~past
    out = {
        "n_rows": lengths.to(dt),
        "t_last": t_last,
        "onset_time": torch.where(has_onset, on.time, nan),
        "rul_median": torch.where(usable, med, nan),
        "rul_q05": torch.where(usable, q05, nan),
        "rul_q95": torch.where(usable, q95, nan),
        "p_fail_within_horizon": torch.where(usable, p_fail, nan),
        "censored_mass": torch.where(usable, censored, nan),
    }
    zero, one = torch.zeros_like(nan), torch.ones_like(nan)
    for key, val in (
        ("rul_median", zero),
        ("rul_q05", zero),
        ("rul_q95", zero),
        ("p_fail_within_horizon", one),
        ("censored_mass", zero),
    ):
        out[key] = torch.where(reached & enough, val, out[key])
    res: dict[str, object] = {key: v.cpu().numpy() for key, v in out.items()}
    checks = [
        ("too_few_rows", ~enough),
        ("no_baseline", enough & ~base_ok),
        ("threshold_on_healthy_side", healthy_side),
        ("threshold_reached", reached & enough),
        ("no_onset", enough & base_ok & (on.index < 0) & ~reached & ~healthy_side),
        ("glitch_in_baseline", enough & base_ok & (on.glitch_widening >= GLITCH_WIDENING)),
        ("few_degraded_points", has_onset & (n_deg < 3) & ~reached),
        ("nonpositive_dropped", has_onset & nonpos & ~reached),
        ("far_extrapolation", usable & far),
        ("trend_misfit", (usable | past) & (misfit_p < MISFIT_P)),
        ("fit_past_threshold", past),
        ("last_rows_missing", usable & (last_obs < lengths - 1)),
    ]
    res["flags"] = _flag_strings(checks, B)
    if return_posterior:
        res.update(
            posterior_mean=mean,
            posterior_chol=chol,
            onset_index=torch.where(has_onset, on.index, -1),
            log_noise_std=sr,
            misfit_p=misfit_p,
            baseline_std=on.base_std,
        )
    if per_asset:  # the offset each asset's trend used
        res["phi"] = on.base_mean.cpu().numpy()
    return res


def _data_log_likelihood(batch: PaddedBatch, post: dict, s: float, baseline_phi: bool) -> Tensor:
    """Log-likelihood ``(B,)`` of the samples since onset with ``s y > 0`` on the data scale,
    under the fitted trend at its posterior mean: ``phi = 0`` (``log(s y) ~ N(a + beta tau,
    sigma^2)``, with the Jacobian ``1 / (s y)``) or ``baseline_phi`` (``s (y - mu_0) ~
    N(exp(a + beta tau), sigma_0^2)``). NaN where the asset has no onset."""
    y, t, lengths = batch.values, batch.times, batch.lengths
    B, T = y.shape
    cols = torch.arange(T, device=y.device)
    i0 = post["onset_index"]
    t_on = t.gather(1, i0.clamp(min=0)[:, None])
    since = (cols >= i0[:, None]) & (cols < lengths[:, None]) & (i0[:, None] >= 0)
    ok = since & ~torch.isnan(y) & (s * y > 0)
    a, b = post["posterior_mean"][:, :1], post["posterior_mean"][:, 1:]
    g = a + b * (t - t_on)
    if baseline_phi:
        sd = post["baseline_std"][:, None]
        mu = torch.as_tensor(post["phi"], dtype=y.dtype, device=y.device)[:, None]
        r = (s * (y - mu) - torch.exp(g.clamp(max=700.0))) / sd
        ll = -0.5 * r * r - torch.log(sd)
    else:
        z = torch.log(torch.where(ok, s * y, 1.0))
        sd = post["log_noise_std"][:, None]
        r = (z - g) / sd
        ll = -0.5 * r * r - torch.log(sd) - z
    total = torch.where(ok, ll, 0.0).sum(1) - 0.5 * math.log(2 * math.pi) * ok.sum(1).to(y.dtype)
    return torch.where(i0 >= 0, total, torch.nan)


def _auto_phi(batch: PaddedBatch, thr: float, s: float, return_posterior: bool, kw: dict):
    """``phi="auto"``: both offsets fitted, and per asset the one whose fitted trend gives the
    data since onset the higher likelihood on the data scale (:func:`_data_log_likelihood`;
    two parameters each, so this is also the AIC and BIC choice). ``phi = 0`` cannot reach a
    threshold on the wrong side of zero: then the baseline serves every asset."""
    base = exponential_trend_rul(batch, thr, phi="baseline", return_posterior=True, **kw)
    if not s * thr > 0:
        zero = None
        pick = torch.ones(len(base["flags"]), dtype=torch.bool, device=batch.values.device)
    else:
        zero = exponential_trend_rul(batch, thr, phi=0.0, return_posterior=True, **kw)
        ll0 = _data_log_likelihood(batch, zero, s, False)
        llb = _data_log_likelihood(batch, base, s, True)
        # the baseline where it fits better, or where phi = 0 has no usable fit and it has;
        # with neither (no onset yet), where only phi = 0 lacks a baseline (values <= 0)
        dev = batch.values.device
        no_base = [torch.tensor(["no_baseline" in f.split(";") for f in r["flags"]],
                                dtype=torch.bool, device=dev) for r in (zero, base)]  # fmt: skip
        neither = torch.isnan(ll0) & torch.isnan(llb)
        pick = (llb > ll0) | (torch.isnan(ll0) & ~torch.isnan(llb))
        pick |= neither & no_base[0] & ~no_base[1]
    pick_np = pick.cpu().numpy()
    if zero is not None:
        zero["phi"] = np.zeros_like(base["phi"])
    out: dict[str, object] = {}
    for key, v in base.items():
        if zero is None:
            out[key] = v
        elif key == "flags":
            out[key] = [fb if pb else f0 for fb, f0, pb in zip(v, zero[key], pick_np)]
        elif isinstance(v, np.ndarray):
            out[key] = np.where(pick_np, v, zero[key])
        else:  # posterior tensors (B, ...)
            m = pick.reshape(-1, *([1] * (v.dim() - 1)))
            out[key] = torch.where(m, v, zero[key])
    if not return_posterior:
        for key in ("posterior_mean", "posterior_chol", "onset_index", "log_noise_std",
                    "misfit_p", "baseline_std"):  # fmt: skip
            out.pop(key)
    return out
