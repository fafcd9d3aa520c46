"""Degradation-trend models as state-space models estimated by the library's filter engine.

Three shapes of a degradation indicator ``y`` above a healthy level ``phi`` (the baseline mean of
:mod:`prognos_torch.prognosis.onset`), each a *local trend* on a transformed measurement ``z``
against a clock ``s``:

=============== ================================================ ======================= ===========
shape           model                                            ``z``                   ``s``
=============== ================================================ ======================= ===========
``exponential`` ``y = phi + theta exp(beta t + eps(t))``         ``log(y - phi)``        ``t``
                (Gebraeel et al. 2005)
``power``       ``y = phi + a (t - t_0)^b`` (Paris-law growth)   ``log(y - phi)``        ``log(t - t_0)``
``linear``      ``y = y_0 + beta t + eps(t)``                    ``y``                   ``t``
=============== ================================================ ======================= ===========

In each, the log form is linear-Gaussian: with the level ``L_k = log theta + beta t_k + eps(t_k)``
(exponential; the others alike) the state ``x = [L, beta]`` follows the exact discretisation of
a continuous-time integrated random walk over the step ``ds_k = s_k - s_{k-1}``::

    L_k    = L_{k-1} + ds_k beta_{k-1} + w_L                               (Brownian eps(t))
    beta_k = beta_{k-1} + w_beta                                          (parameter random walk)
    Q_k    = [[q_L ds + q_b ds^3 / 3, q_b ds^2 / 2], [q_b ds^2 / 2, q_b ds]]
    z_k    = L_k + v_k,   v_k ~ N(0, r + a_k)

so the parameter ``beta`` is a random-walk state beside the level (paper 000 Eq. 3-4, the
assistant model ``theta_k = theta_{k-1}`` plus noise), ``log theta`` is absorbed in the level, and
irregular sampling and recording gaps are exact: a gap is one long step whose ``Q`` grows with
it. ``a_k`` is the additive baseline noise ``sigma_0`` carried through the transform by the
delta method (``sigma_0^2 / (y_k - phi)^2`` for the log forms, ``sigma_0^2`` for the linear
one); values with ``y_k - phi < sigma_0`` have no usable logarithm and count as missing (NaN).
The predictive spread of the level grows like ``q_L h + q_b h^3 / 3`` with the horizon ``h``: that
is what keeps RUL intervals honest far from the data.

:func:`fit_trends` filters every shape at once with ONE call of :func:`~prognos_torch.filters.run`
(shapes and a grid of ``(q_L, q_b, r)`` are batch dimensions of the belief). By default
(``filter="ekf"``, or ``"sckf"``) the filter is an exact Kalman filter on this linear model
(tested to 1e-10); ``filter="stekf"`` (or :func:`strong_tracking_filter`) is the strong-tracking
EKF (:func:`~prognos_torch.filters.stekf`, SFEKF, paper 000 Eq. 7-12; on this linear model its
statistical and Taylor linearisations coincide, so it equals the STSCKF), whose fading factor
inflates the prior after the jumps that bearings show. The noise of each shape is the grid point
of highest filter log-likelihood (maximum likelihood over the grid; the grid is scaled by the
data's own increments, so it has no dimensional constants); :func:`~prognos_torch.workflow.prognose`
chooses it by a backtest instead where the series has crossed levels to backtest on.

:meth:`TrendFit.first_passage` samples the posterior at an origin from its square-root
covariance and simulates the exact discretisation forward (the same ``Q_k``) until every path
has crossed the threshold or the horizon ends; the crossing times form the RUL distribution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..core.random import standard_normal
from ..core.validation import (
    all_finite,
    check_float_tensor,
    check_nonneg_int,
    check_real,
    has_missing,
    is_int,
    is_real,
)
from ..filters import GaussianFilter, make_filter, stekf
from ..filters import run as run_filter

__all__ = [
    "TREND_SHAPES",
    "TrendNoise",
    "TrendFit",
    "trend_measurement",
    "integrated_rw_chol",
    "trend_transition",
    "local_trend_model",
    "noise_grid",
    "fit_trends",
    "path_grid",
    "Passage",
    "TrendPool",
    "simulate_first_passage",
    "STRONG_TRACKING_BETA",
    "strong_tracking_filter",
]

TREND_SHAPES = ("exponential", "power", "linear")
_LOG_SHAPES = ("exponential", "power")


@dataclass(frozen=True)
class TrendNoise:
    """Noise of the local trend model (batch dims ``(...)``; rates per unit of the clock ``s``).

    Attributes:
        level: ``q_L``, variance rate of the level's Brownian motion.
        slope: ``q_b``, variance rate of the slope's random walk.
        meas: ``r``, white measurement variance beyond the delta-method baseline noise.
        wander: ``w``, stationary variance of the Ornstein-Uhlenbeck wander ``c`` (0: none).
        tau: its correlation time (clock units, > 0).
    """

    level: Tensor
    slope: Tensor
    meas: Tensor
    wander: Tensor
    tau: Tensor

    def __getitem__(self, index) -> TrendNoise:
        return TrendNoise(*(v[index] for v in self._fields()))

    def _fields(self) -> tuple[Tensor, ...]:
        return (self.level, self.slope, self.meas, self.wander, self.tau)


# --------------------------------------------------------------------------- building blocks
def trend_measurement(
    shape: str, t: Tensor, y: Tensor, *, phi: float, sigma0: float, t0: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Measurement ``z``, clock ``s`` and delta-method variance ``a`` of a shape (module table).

    Args:
        shape: one of :data:`TREND_SHAPES`.
        t, y: ``(..., T)`` times and (oriented) indicator values.
        phi: healthy level; sigma0: baseline noise std; t0: power-law origin (``< t``).

    Returns:
        ``(z, s, a)``, each ``(..., T)``; ``z`` is NaN where ``y - phi < sigma0`` (log shapes).
    """
    if shape not in TREND_SHAPES:
        raise ValueError(f"shape must be one of {', '.join(TREND_SHAPES)}, got {shape!r}")
    if shape == "linear":
        return y.clone(), t.clone(), torch.full_like(y, sigma0**2)
    d = y - phi
    ok = d >= sigma0
    safe = torch.where(ok, d, torch.ones_like(d))
    z = torch.where(ok, safe.log(), torch.full_like(d, math.nan))
    a = torch.where(ok, (sigma0 / safe) ** 2, torch.zeros_like(d))
    s = t.clone() if shape == "exponential" else (t - t0).log()
    return z, s, a


def integrated_rw_chol(ds: Tensor, q_level: Tensor, q_slope: Tensor) -> Tensor:
    """Lower Cholesky factor ``(..., 2, 2)`` of the integrated-random-walk ``Q`` (module doc).

    Closed form: ``L11 = sqrt(Q11)``, ``L21 = Q21 / L11``, ``L22 = sqrt(Q22 - L21^2)``; a zero
    ``Q11`` (``ds = 0`` or no noise) gives zeros. Shapes broadcast.
    """
    ds, q_level, q_slope = torch.broadcast_tensors(ds, q_level, q_slope)
    q11 = q_level * ds + q_slope * ds**3 / 3.0
    q21 = q_slope * ds**2 / 2.0
    q22 = q_slope * ds
    l11 = q11.clamp(min=0).sqrt()
    pos = l11 > 0
    l21 = torch.where(pos, q21 / torch.where(pos, l11, torch.ones_like(l11)), torch.zeros_like(q21))
    l22 = (q22 - l21**2).clamp(min=0).sqrt()
    zero = torch.zeros_like(l11)
    return torch.stack([torch.stack([l11, zero], -1), torch.stack([l21, l22], -1)], -2)


def trend_transition(ds: Tensor, noise: TrendNoise) -> tuple[Tensor, Tensor]:
    """Per-step OU decay ``rho = exp(-ds / tau)`` and the process-noise factor ``(..., 3, 3)``.

    The factor is block-diagonal: :func:`integrated_rw_chol` for ``[L, beta]`` and
    ``sqrt(w (1 - rho^2))`` for the wander ``c`` (exact OU discretisation). Shapes broadcast.
    """
    rho = torch.exp(-ds / noise.tau)
    S2 = integrated_rw_chol(ds, noise.level, noise.slope)
    sc = (noise.wander * (1.0 - rho * rho)).clamp(min=0).sqrt()
    S = torch.zeros(*S2.shape[:-2], 3, 3, dtype=S2.dtype, device=S2.device)
    S[..., :2, :2] = S2
    S[..., 2, 2] = sc
    return rho.expand(S.shape[:-2]), S


def local_trend_model(chol_Q: Tensor, rho: Tensor, meas_var: Tensor) -> StateSpaceModel:
    """The local trend ``x = [L, beta, c]`` as a :class:`StateSpaceModel` (module docstring).

    ``f(x, u) = [L + ds beta, beta, rho c]`` with the control ``u_k = [ds_k, rho_k]`` (clock
    step and OU decay), ``h(x) = L + c``; analytic Jacobians (``batched=True``: any leading
    dims).

    Args:
        chol_Q: ``(T, ..., 3, 3)`` per-step process-noise factors (:func:`trend_transition`).
        rho: ``(T, ...)`` per-step OU decay (only used through ``u``; kept for the shape check).
        meas_var: ``(T, ...)`` per-step measurement variances ``r + a_k``.
    """
    if chol_Q.dim() < 3 or chol_Q.shape[-2:] != (3, 3):
        raise ValueError(f"chol_Q must have shape (T, ..., 3, 3), got {tuple(chol_Q.shape)}")
    for name, v in (("rho", rho), ("meas_var", meas_var)):
        if tuple(v.shape) != tuple(chol_Q.shape[:-2]):
            raise ValueError(
                f"{name} must have shape {tuple(chol_Q.shape[:-2])} (T, ...), got {tuple(v.shape)}"
            )
    chol_R = meas_var.clamp(min=0).sqrt()[..., None, None]
    T = chol_Q.shape[0]
    dt, dev = chol_Q.dtype, chol_Q.device
    H = torch.tensor([[1.0, 0.0, 1.0]], dtype=dt, device=dev)

    def step(k: int) -> int:
        if not 1 <= k <= T:
            raise IndexError(f"step k={k} outside the model's 1..{T}")
        return k - 1

    def f(x, u, k):
        return torch.stack(
            [x[..., 0] + u[..., 0] * x[..., 1], x[..., 1], u[..., 1] * x[..., 2]], -1
        )

    def jac_f(x, u, k):
        J = torch.zeros(*x.shape[:-1], 3, 3, dtype=x.dtype, device=x.device)
        J[..., 0, 0] = 1.0
        J[..., 0, 1] = u[..., 0]
        J[..., 1, 1] = 1.0
        J[..., 2, 2] = u[..., 1]
        return J

    def h(x, u, k):
        return x[..., :1] + x[..., 2:3]

    def jac_h(x, u, k):
        return H.expand(*x.shape[:-1], 1, 3)

    return StateSpaceModel(
        f=f,
        h=h,
        state_dim=3,
        obs_dim=1,
        chol_Q=lambda k: chol_Q[step(k)],
        chol_R=lambda k: chol_R[step(k)],
        control_dim=2,
        batched=True,
        jac_f=jac_f,
        jac_h=jac_h,
    )


def _floor_scale(z: Tensor) -> float:
    """A scale of ``z`` for positive floors that moves with its units (scale and offset): its
    range, else its magnitude, else 1 (a constant zero series)."""
    rng = float(z.max() - z.min())
    if rng > 0:
        return rng
    mag = float(z.abs().max())
    return mag if mag > 0 else 1.0


def noise_grid(z: Tensor, s: Tensor, a: Tensor) -> TrendNoise:
    """The noise grid searched by :func:`fit_trends`, scaled by the data (``(G,)``, G = 27).

    With ``v`` the robust variance (squared 1.4826 MAD) of the increments of ``z``, ``ds`` their
    median clock step, ``span`` the clock span, ``g = (max z - min z) / span`` the mean slope and
    ``u`` the robust variance of ``z`` about a straight line:

    * ``q_L in v / ds x {1e-3, 1e-2, 0.1}`` (``v`` at least ``(1e-6 x`` the range of ``z)^2``,
      a floor in the data's own units: the band never collapses);
    * ``q_b in g^2 / span x {1e-4, 1e-2, 0.3}`` (from a practically constant slope, Gebraeel's
      model, to one that wanders by about ``g / 2`` over the span);
    * wander: none, or ``w = u`` with ``tau in span x {0.03, 0.2}``;
    * ``r = max(v / 2 - median a, 1e-4 v)``: the white part of the increments not explained by
      the baseline noise.
    """
    ok = ~torch.isnan(z)
    zz, ss = z[ok], s[ok]
    if zz.numel() < 3:
        raise ValueError("a trend fit needs at least 3 usable values since onset")
    dz, ds = torch.diff(zz), torch.diff(ss)
    dsm = float(ds[ds > 0].median()) if bool((ds > 0).any()) else 1.0
    dev = (dz - dz.median()).abs().median() * 1.4826
    v = max(float(dev) ** 2, (1e-6 * _floor_scale(zz)) ** 2)  # unit-free positive floor
    span = max(float(ss[-1] - ss[0]), dsm)
    g = max(float(zz.max() - zz.min()), math.sqrt(v)) / span
    sc = ss - ss.mean()
    slope = float((sc * (zz - zz.mean())).sum() / (sc * sc).sum().clamp(min=1e-300))
    res = zz - zz.mean() - slope * sc
    u = max(float((res - res.median()).abs().median() * 1.4826) ** 2, v)
    r = max(v / 2.0 - float(a[ok].median()), 1e-4 * v)
    rows = []
    for ql in (1e-3, 1e-2, 0.1):
        for qb in (1e-4, 1e-2, 0.3):
            rows.append((ql * v / dsm, qb * g * g / span, r, 0.0, span))
            for tau in (0.03, 0.2):
                rows.append((ql * v / dsm, qb * g * g / span, r, u, tau * span))
    G = torch.tensor(rows, dtype=z.dtype, device=z.device)
    return TrendNoise(*G.unbind(-1))


#: Largest decay ``-log prod rho`` over a chunk for which the cumulative-product solution of the
#: OU recursion is used: beyond it ``exp(-log prod rho)`` nears the float64 range (e^709), and
#: its overflow would make the wander +-inf (spurious crossings at one step).
_OU_LOG_SPAN = 600.0


def _ou_by_decay_matrix(logr: Tensor, w: Tensor, c0: Tensor) -> Tensor:
    """``c_j = sum_{i <= j} exp(logr_j - logr_i) w_i + exp(logr_j) c_0`` for a fast-decaying OU
    (decay factors <= 1, no overflow): ``logr`` ``(B, c)``, ``w`` ``(B, N, c)``, ``c0``
    ``(B, N, 1)`` -> ``(B, N, c)``."""
    k = logr.shape[-1]
    lower = torch.ones(k, k, dtype=torch.bool, device=logr.device).tril()
    gap = logr[:, :, None] - logr[:, None, :]  # (B, c, c): logr_j - logr_i
    decay = torch.where(lower, gap, -math.inf).exp()
    return w @ decay.mT + torch.exp(logr)[:, None, :] * c0


def check_path_draws(generator, n_paths) -> None:
    """The draws of a first-passage simulation: a ``torch.Generator`` (``None`` would draw
    from the global stream) and ``n_paths`` an int ``>= 1``."""
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    if not is_int(n_paths) or n_paths < 1:
        raise ValueError(f"n_paths must be an int >= 1, got {n_paths!r}")


def check_path_times(x, name: str, device: torch.device) -> Tensor:
    """Times ``(J,)`` of the paths of a fit on ``device``: a floating tensor there, returned as
    float64 (a float32 grid was refused by the float64 ELM with an error on an unnamed ``x``,
    or had its first step taken from an origin rounded to float32; a grid on another device
    failed inside the simulation)."""
    x = check_float_tensor(x, name, "(J,)")
    if x.device != device:
        raise ValueError(f"{name} is on {x.device}, the fit on {device}: pass {name} on {device}")
    return x.to(torch.float64)


def check_path_grid(grid: Tensor, t_origin: float) -> None:
    """``grid`` ``(J,)``: finite, strictly increasing times after the origin ``t_origin`` (a
    step back or a NaN time gave the square root of a negative step, a path counted as
    diverged)."""
    if (grid.dim() != 1 or grid.numel() < 1 or not bool(grid[0] > t_origin)
            or not bool(torch.isfinite(grid).all()) or not bool((grid.diff() > 0).all())):  # fmt: skip
        raise ValueError("grid must be (J,) finite, strictly increasing times after the origin")


def check_obs_index(index, n: int, name: str = "index") -> int:
    """An observation index in ``[-n, n)`` as an int in ``[0, n)`` (a bool, a float or an
    index past either end is refused: ``n + 5`` must not read as ``5``)."""
    if not is_int(index):
        raise TypeError(f"{name} must be an int (an observation index), got {index!r}")
    if not -n <= index < n:
        raise ValueError(
            f"{name} must be an observation index in [-{n}, {n}) (the {n} values since onset), "
            f"got {index}"
        )
    return int(index) % n


def simulate_first_passage(
    means: Tensor,
    chols: Tensor,
    noise: TrendNoise,
    ds: Tensor,
    z_level: float,
    n_paths: int,
    generator: torch.Generator,
    *,
    keep: int = 0,
    chunk: int = 128,
) -> tuple[Tensor, Tensor | None]:
    """First step at which sampled paths of ``L + c`` reach ``z_level``, for a batch of beliefs.

    ``x_0 = m + S e`` (``e ~ N(0, I)``) per batch element, then the exact discretisation of
    the model over the clock steps ``ds`` ``(J,)``, chunk by chunk, stopping once every path has
    crossed. The crossing is of the observable level ``L + c`` (trend and wander, without the
    white measurement noise): what a moving median of the indicator follows.

    Args:
        means, chols: ``(B, 3)``, ``(B, 3, 3)`` beliefs on ``[L, beta, c]``.
        noise: :class:`TrendNoise` with ``(B,)`` fields.
        ds: ``(J,)`` clock steps of the prediction grid (``> 0``).
        z_level: the level to reach (measurement space).
        n_paths: paths per batch element.
        keep: also return ``L + c`` of the first ``keep`` paths of element 0, ``(keep, J)``.

    Returns:
        ``(first, levels)``: ``(B, N)`` int64 0-based grid step of the first crossing (``J``:
        none), and the kept levels or ``None``.
    """
    check_path_draws(generator, n_paths)
    keep = check_nonneg_int(keep, "keep")
    if math.isnan(z_level):
        raise ValueError("z_level is NaN: the level to reach must be a number")
    if ds.dim() != 1 or not bool((ds > 0).all()) or not bool(torch.isfinite(ds).all()):
        raise ValueError("ds must be (J,) finite clock steps > 0 (an increasing grid)")
    B, J = means.shape[0], ds.shape[0]
    dt, dev = means.dtype, means.device
    e = standard_normal((B, n_paths, 3), generator, dt, dev)
    x = means[:, None, :] + e @ chols.mT  # (B, N, 3)
    first = torch.full((B, n_paths), J, dtype=torch.int64, device=dev)
    if z_level == -math.inf:
        return torch.zeros_like(first), None
    kept = [] if keep > 0 else None
    done = torch.zeros(B, n_paths, dtype=torch.bool, device=dev)
    col = lambda v: v.reshape(B, 1)  # noqa: E731
    chunk = max(1, min(chunk, 2_000_000 // (B * n_paths)))  # bound the working memory
    j0 = 0
    while j0 < J and not bool(done.all()):
        j1 = min(J, j0 + chunk)
        d = ds[j0:j1]
        nb = TrendNoise(*(col(v) for v in noise._fields()))
        rho, SQ = trend_transition(d[None], nb)  # (B, c), (B, c, 3, 3)
        w = standard_normal((B, n_paths, j1 - j0, 3), generator, dt, dev)
        w = (SQ[:, None] @ w.unsqueeze(-1)).squeeze(-1)  # (B, N, c, 3)
        slope = x[..., 1:2] + torch.cumsum(w[..., 1], -1)  # beta after each step
        before = torch.cat([x[..., 1:2], slope[..., :-1]], -1)
        level = x[..., :1] + torch.cumsum(d * before + w[..., 0], -1)
        # OU: c_j = rho_j c_{j-1} + w_j, solved by cumulative products (rho > 0)
        logr = torch.cumsum(torch.log(rho.clamp(min=1e-300)), -1)[:, None, :]  # (B, 1, c)
        if bool((logr[..., -1] < -_OU_LOG_SPAN).any()):
            c = _ou_by_decay_matrix(logr[:, 0], w[..., 2], x[..., 2:3])
        else:
            c = torch.exp(logr) * (x[..., 2:3] + torch.cumsum(w[..., 2] * torch.exp(-logr), -1))
        obs = level + c
        hit = obs >= z_level
        step = torch.arange(j0, j1, device=dev)
        f = torch.where(hit, step, torch.full_like(step, J)).amin(-1)
        first = torch.where(done, first, f)
        done = done | (f < J)
        if kept is not None:
            kept.append(obs[0, :keep])
        x = torch.stack([level[..., -1], slope[..., -1], c[..., -1]], -1)
        j0 = j1
    levels = None
    if kept is not None:
        levels = torch.cat(kept, -1)
        if levels.shape[-1] < J:  # stopped early: every path had crossed
            levels = torch.cat([levels, levels[:, -1:].expand(-1, J - levels.shape[-1])], -1)
    return first, levels


@dataclass(frozen=True)
class Passage:
    """Sampled first passages of a level.

    Attributes:
        times: ``(N,)`` absolute first crossing times; ``inf`` where a path does not cross
            within the grid (censored) or diverges.
        paths: ``(keep, J)`` sample paths in oriented indicator units on the grid, or ``None``.
        diverged: ``(N,)`` bool, paths that left every sensible range (non-finite values or a
            fall far below the data) before crossing; counted as censored.
    """

    times: Tensor
    paths: Tensor | None
    diverged: Tensor


@dataclass(frozen=True)
class TrendPool:
    """An equal-weight mixture of trend models: its RUL distribution is the average of theirs.

    :meth:`first_passage` gives each member ``n_paths // k`` paths (the first also the
    ``n_paths mod k`` left over) and ``keep // k`` kept paths (the first also the remainder),
    and concatenates them in member order: a sample from the mixture with equal weights
    ``1 / k`` (to within the remainder). Members are anything with ``first_passage`` of the
    signature of :meth:`TrendFit.first_passage` (a trend shape, a learner trend, a pool).

    Attributes:
        members: the ``k >= 1`` pooled models.
    """

    members: tuple

    def __post_init__(self):
        if not isinstance(self.members, tuple) or not self.members:
            raise ValueError("members must be a non-empty tuple of trend models")

    def first_passage(
        self,
        index: int,
        level: float,
        grid: Tensor,
        n_paths: int,
        generator: torch.Generator,
        *,
        keep: int = 0,
    ) -> Passage:
        """Crossing times of ``level`` by the members' paths from the observation ``index``
        on ``grid`` ``(J,)``, ``n_paths`` in all, at least one per member (class docstring)."""
        k = len(self.members)
        if not is_int(n_paths) or n_paths < k:
            raise ValueError(
                f"n_paths must be an int >= the {k} members of the pool, got {n_paths!r}"
            )
        keep = check_nonneg_int(keep, "keep")  # (before it is shared out: 2.5 // k is a float)
        parts = []
        for j, f in enumerate(self.members):
            n = n_paths // k + (n_paths % k if j == 0 else 0)
            kj = keep // k + (keep % k if j == 0 else 0)
            parts.append(f.first_passage(index, level, grid, n, generator, keep=kj))
        if k == 1:
            return parts[0]
        kept = [p.paths for p in parts if p.paths is not None]
        return Passage(
            torch.cat([p.times for p in parts]),
            torch.cat(kept) if kept else None,
            torch.cat([p.diverged for p in parts]),
        )


@dataclass(frozen=True)
class TrendFit:
    """One trend shape filtered over the data since onset, for every point of the noise grid.

    Attributes:
        shape: one of :data:`TREND_SHAPES`.
        phi, sigma0, t0: healthy level, baseline noise std, power-law origin.
        t: ``(n,)`` observation times; y: ``(n,)`` oriented values; z, s, a: as
            :func:`trend_measurement`.
        grid: the :class:`TrendNoise` grid ``(G,)``.
        grid_means, grid_chols: ``(n, G, 3)``, ``(n, G, 3, 3)`` posteriors on ``[L, beta, c]``
            after each observation, per grid point.
        grid_log_likelihood: ``(G,)`` filter log-likelihoods.
        choice: the grid point in use (default: maximum likelihood; see :meth:`select`).
        prior: the initial belief (before the first observation).
        fading: ``(n, G)`` strong-tracking fading factors.
        filter: engine configuration name.
    """

    shape: str
    phi: float
    sigma0: float
    t0: float
    t: Tensor
    y: Tensor
    z: Tensor
    s: Tensor
    a: Tensor
    grid: TrendNoise
    grid_means: Tensor
    grid_chols: Tensor
    grid_log_likelihood: Tensor
    choice: int
    prior: GaussianBelief
    fading: Tensor
    filter: str

    # -- the chosen grid point -----------------------------------------------------
    @property
    def noise(self) -> TrendNoise:
        """The noise in use (0-dim tensors)."""
        g = self.choice
        return self.grid[g]

    @property
    def means(self) -> Tensor:
        """``(n, 3)`` posterior means of the chosen noise."""
        return self.grid_means[:, self.choice]

    @property
    def chols(self) -> Tensor:
        """``(n, 3, 3)`` posterior square roots of the chosen noise."""
        return self.grid_chols[:, self.choice]

    @property
    def log_likelihood(self) -> float:
        return float(self.grid_log_likelihood[self.choice])

    def select(self, choice: int) -> TrendFit:
        """The same fit with grid point ``choice`` in use."""
        G = self.grid.level.numel()
        if not 0 <= int(choice) < G:
            raise ValueError(f"choice must be in 0..{G - 1}, got {choice}")
        return replace(self, choice=int(choice))

    # -- transforms -------------------------------------------------------------
    def to_z(self, level: float) -> float:
        """An (oriented) indicator level in the model's measurement space; a level at or below
        the exponential's and power law's offset ``phi`` is reached at once (``-inf``)."""
        if not is_real(level) or not math.isfinite(level):
            raise ValueError(f"level must be a finite number, got {level!r}")
        if self.shape == "linear":
            return float(level)
        d = float(level) - self.phi
        return math.log(d) if d > 0 else -math.inf

    def to_y(self, z: Tensor) -> Tensor:
        """Back from the measurement space to (oriented) indicator units."""
        return z if self.shape == "linear" else self.phi + z.exp()

    def clock(self, t: Tensor) -> Tensor:
        """The clock ``s`` at times ``t``."""
        return t if self.shape != "power" else (t - self.t0).log()

    def belief(self, index: int) -> GaussianBelief:
        """Posterior on ``[L, beta, c]`` after observation ``index`` (``-1``: the last)."""
        i = check_obs_index(index, self.t.shape[0])
        return GaussianBelief(self.means[i], self.chols[i])

    def _steps(self, index: int, grid: Tensor) -> Tensor:
        t_origin = float(self.t[index])
        g64 = check_path_times(grid, "grid", self.grid_means.device)
        check_path_grid(g64, t_origin)
        ds = torch.diff(self.clock(torch.cat([g64.new_tensor([t_origin]), g64])))
        return ds.to(self.grid_means.dtype)  # (a float64 grid failed on a float32 fit)

    # -- prediction -------------------------------------------------------------
    def first_passage(
        self,
        index: int,
        level: float,
        grid: Tensor,
        n_paths: int,
        generator: torch.Generator,
        *,
        keep: int = 0,
    ) -> Passage:
        """Crossing times of ``level`` by sampled paths from the posterior at ``index``.

        ``n_paths`` draws ``x_0 = m + S e`` (``S`` the posterior square root) are propagated on
        the absolute time ``grid`` ``(J,)`` (``> t[index]``, increasing) by the exact
        discretisation of the model until every path has crossed
        (:func:`simulate_first_passage`).

        Returns:
            :class:`Passage`: the first grid time with ``L >= to_z(level)`` per path (``inf``:
            none) and, with ``keep > 0``, the first ``keep`` paths in oriented indicator units.
        """
        index = check_obs_index(index, self.t.shape[0])
        ds = self._steps(index, grid)
        first, levels = simulate_first_passage(
            self.means[index][None],
            self.chols[index][None],
            self.grid[self.choice : self.choice + 1],
            ds,
            self.to_z(level),
            n_paths,
            generator,
            keep=keep,
        )
        gpad = torch.cat([grid, grid.new_tensor([math.inf])])
        paths = None if levels is None else self.to_y(levels)
        diverged = torch.zeros(n_paths, dtype=torch.bool, device=grid.device)
        return Passage(gpad[first[0]], paths, diverged)

    def grid_first_passage(
        self, index: int, level: float, grid: Tensor, n_paths: int, generator: torch.Generator
    ) -> Tensor:
        """Crossing times ``(G, N)`` for every noise grid point at once (``inf``: none)."""
        index = check_obs_index(index, self.t.shape[0])
        ds = self._steps(index, grid)
        first, _ = simulate_first_passage(
            self.grid_means[index],
            self.grid_chols[index],
            self.grid,
            ds,
            self.to_z(level),
            n_paths,
            generator,
        )
        gpad = torch.cat([grid, grid.new_tensor([math.inf])])
        return gpad[first]


def path_grid(t_origin: float, horizon: float, dt: float, rel: float = 0.01) -> Tensor:
    """Future times ``t_origin + h_j`` up to ``horizon``: steps of ``dt`` until ``dt < rel h``,
    then geometric steps of ``rel`` of the elapsed horizon (relative resolution ``rel``)."""
    if not (0 < horizon < math.inf and 0 < dt < math.inf):
        raise ValueError(f"horizon and dt must be positive finite numbers, got {horizon}, {dt}")
    if not 0 < rel < math.inf:
        raise ValueError(f"rel must be a positive number (a relative resolution), got {rel}")
    if not math.isfinite(t_origin):
        raise ValueError(f"t_origin must be a finite time, got {t_origin}")
    h_switch = min(horizon, dt / rel)
    n_lin = max(1, int(math.ceil(h_switch / dt)))
    lin = torch.arange(1, n_lin + 1, dtype=torch.float64) * dt
    if lin[-1] >= horizon:
        hs = lin[lin <= horizon]
        if hs.numel() == 0 or hs[-1] < horizon:
            hs = torch.cat([hs, torch.tensor([horizon], dtype=torch.float64)])
    else:
        n_geo = int(math.ceil(math.log(horizon / float(lin[-1])) / math.log1p(rel)))
        geo = float(lin[-1]) * (1.0 + rel) ** torch.arange(1, n_geo + 1, dtype=torch.float64)
        hs = torch.cat([lin, geo.clamp(max=horizon)])
        hs = torch.unique(hs)
    out = t_origin + hs
    # a step of a few ulp of the horizon (its clamp) can vanish once added to a large origin:
    # drop such repeated times (a grid that was strictly increasing is unchanged)
    return torch.unique_consecutive(out)


# --------------------------------------------------------------------------- fitting
#: Weakening factor of the default strong tracking: the 99 % quantile of ``V_k / S_k`` under the
#: model (``rho = 0.95``; ``V_k = (rho V_{k-1} + e_k^2) / (1 + rho)``, ``e_k^2 / S_k ~ chi^2_1``,
#: simulated: 4.05). The fading factor exceeds 1 only where ``V_k > S_k + (beta - 1) R_k``, so on
#: about 1 % of the steps of data that follow the model (where ``R`` dominates ``S``) and at
#: the jumps that do not; with ``beta = 1`` (paper 000) it fires on ordinary noise (about 40 %
#: of the steps of the IMS health indicator).
STRONG_TRACKING_BETA = 4.0


def strong_tracking_filter() -> GaussianFilter:
    """The strong-tracking EKF (SFEKF, paper 000 Eq. 7-12) with ``rho = 0.95`` and the weakening
    factor :data:`STRONG_TRACKING_BETA`."""
    return stekf(rho=0.95, beta=STRONG_TRACKING_BETA)


def _prior(z: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    """A diffuse prior on ``[L, beta, c]`` scaled by the data: mean ``[z_first, 0, 0]``, std
    ``[10 sd(z), 10 (max z - min z) / span, sd(z)]`` (``(3,)``, ``(3, 3)``)."""
    ok = ~torch.isnan(z)
    zz, ss = z[ok], s[ok]
    sd = float(zz.std(correction=1)) if zz.numel() > 1 else 0.0
    sd = max(sd, 1e-6 * _floor_scale(zz))
    span = max(float(ss[-1] - ss[0]), 1e-12)
    rng = max(float(zz.max() - zz.min()), sd)
    mean = torch.tensor([float(zz[0]), 0.0, 0.0], dtype=z.dtype, device=z.device)
    std = torch.tensor([10.0 * sd, 10.0 * rng / span, sd], dtype=z.dtype, device=z.device)
    return mean, torch.diag(std)


def fit_trends(
    t: Tensor,
    y: Tensor,
    *,
    phi: float,
    sigma0: float,
    shapes: tuple[str, ...] = TREND_SHAPES,
    filter: str | GaussianFilter | None = None,
    noise: dict[str, TrendNoise] | None = None,
    prior: dict[str, GaussianBelief] | None = None,
) -> dict[str, TrendFit]:
    """Filter the trend shapes over ``(t, y)`` (data since onset, oriented) in one engine run.

    Args:
        t: ``(n,)`` strictly increasing times (the first is the onset sample).
        y: ``(n,)`` oriented indicator values (NaN: missing).
        phi: healthy level (baseline mean); sigma0: baseline noise std (> 0).
        shapes: subset of :data:`TREND_SHAPES`.
        filter: engine configuration: a name of :func:`~prognos_torch.filters.make_filter`
            (``"ekf"``, the default, and ``"sckf"`` are exact Kalman filters on this model;
            ``"stekf"``, ``"stsckf"``: strong tracking) or a :class:`GaussianFilter`, e.g.
            :func:`strong_tracking_filter`.
        noise: per shape, a fixed :class:`TrendNoise` (0-dim tensors) instead of the
            maximum-likelihood grid search.
        prior: per shape, the initial belief on ``[L, beta, c]`` (default: diffuse, data-scaled).

    Returns:
        ``{shape: TrendFit}``.
    """
    t = check_float_tensor(t, "t", "(n,)")  # (a list raised AttributeError, an integer
    y = check_float_tensor(y, "y", "(n,)")  # tensor failed in a median)
    if t.dim() != 1 or tuple(y.shape) != tuple(t.shape):
        raise ValueError(
            f"t and y must both have shape (n,), got {tuple(t.shape)}, {tuple(y.shape)}"
        )
    if isinstance(shapes, str):  # (its letters were read as shapes: "got 'e'")
        raise TypeError(f"shapes must be a tuple of shape names, got the text {shapes!r}")
    if y.device != t.device:
        raise ValueError(f"y is on {y.device}, t on {t.device}: pass both on one device")
    # one dtype (float32 y beside float64 t failed with 'expected scalar type Double')
    dt = torch.promote_types(t.dtype, y.dtype)
    t, y = t.to(dt), y.to(dt)
    n = t.shape[0]
    if n < 3:
        raise ValueError(f"a trend fit needs at least 3 values since onset, got {n}")
    # (a step back was taken as a negative clock step, its process noise clipped to zero; a NaN
    # time failed as 'us contains non-finite values')
    if not all_finite(t) or not bool((t.diff() > 0).all()):
        raise ValueError("t must be finite, strictly increasing times, shape (n,)")
    has_missing(y, "y")  # (inf failed as 'init.chol contains non-finite values')
    # (True was read as 1; a NaN phi gave 'no trend shape has 3 usable values')
    phi, sigma0 = check_real(phi, "phi"), check_real(sigma0, "sigma0")
    if not sigma0 > 0:
        raise ValueError(f"sigma0 must be positive, got {sigma0}")
    dtm = float(torch.diff(t).median())
    t0 = float(t[0]) - dtm
    per = []
    for shape in shapes:
        z, s, a = trend_measurement(shape, t, y, phi=phi, sigma0=sigma0, t0=t0)
        if int((~torch.isnan(z)).sum()) < 3:
            continue
        grid = noise[shape] if noise and shape in noise else noise_grid(z, s, a)
        # given noise levels and priors join the data's device (values unchanged)
        grid = TrendNoise(*(v.reshape(-1).to(z.device) for v in grid._fields()))
        if prior and shape in prior:
            m0, S0 = prior[shape].mean.to(z.device), prior[shape].chol.to(z.device)
            if tuple(m0.shape) != (3,) or tuple(S0.shape) != (3, 3):
                raise ValueError(
                    f"prior of {shape!r} must be on [L, beta, c] (mean (3,), chol (3, 3)), got "
                    f"{tuple(m0.shape)}, {tuple(S0.shape)}"
                )
        else:
            m0, S0 = _prior(z, s)
        per.append((shape, z, s, a, grid, m0, S0))
    if not per:
        raise ValueError(
            "no trend shape has 3 usable values since onset (values must exceed the healthy "
            "level by at least one baseline standard deviation)"
        )
    # one batch: every (shape, noise grid point)
    ys, us, SQs, rhos, Rs, m0s, S0s, sizes = [], [], [], [], [], [], [], []
    for _, z, s, a, grid, m0, S0 in per:
        G = grid.level.numel()
        ds = torch.diff(s, prepend=s[:1])  # the first step has ds = 0 (prior at the onset time)
        rho, SQ = trend_transition(ds[:, None], grid[None])
        SQs.append(SQ)
        rhos.append(rho)
        Rs.append(a[:, None] + grid.meas[None])
        ys.append(z[:, None, None].expand(n, G, 1))
        us.append(torch.stack([ds[:, None].expand(n, G), rho], -1))
        m0s.append(m0.expand(G, 3))
        S0s.append(S0.expand(G, 3, 3))
        sizes.append(G)
    model = local_trend_model(torch.cat(SQs, 1), torch.cat(rhos, 1), torch.cat(Rs, 1))
    belief = GaussianBelief(torch.cat(m0s).clone(), torch.cat(S0s).clone())
    if filter is None:
        filt = make_filter("ekf")
    elif isinstance(filter, GaussianFilter):
        filt = filter
    else:
        filt = make_filter(filter)
    with torch.inference_mode():
        traj = run_filter(filt, model, belief, torch.cat(ys, 1), torch.cat(us, 1))
    ll = traj.log_likelihoods.sum(0)
    out: dict[str, TrendFit] = {}
    start = 0
    for (shape, z, s, a, grid, m0, S0), G in zip(per, sizes):
        sl = slice(start, start + G)
        start += G
        g_ll = ll[sl].clone()
        best = int(torch.argmax(torch.nan_to_num(g_ll, nan=-math.inf)))
        out[shape] = TrendFit(
            shape=shape,
            phi=float(phi),
            sigma0=float(sigma0),
            t0=t0,
            t=t.clone(),
            y=y.clone(),
            z=z,
            s=s,
            a=a,
            grid=grid,
            grid_means=traj.means[:, sl].clone(),
            grid_chols=traj.chols[:, sl].clone(),
            grid_log_likelihood=g_ll,
            choice=best,
            prior=GaussianBelief(m0.clone(), S0.clone()),
            fading=traj.fading_factors[:, sl].clone(),
            filter=filt.name or str(filter),
        )
    return out
