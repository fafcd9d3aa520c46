"""A learner trend model that keeps learning online: an ELM of time trained by Kalman filtering.

The log degradation level of the exponential shape (:mod:`prognos_torch.prognosis.trends`,
``z = log(y - phi)``) is learned as a flexible function of the time since onset::

    z_k = g(tau_k; theta) + e_k,    g(tau; theta) = c_0 + c_1 tau + H(u(tau)) beta

with ``tau = (t - t_onset) / T`` (``T``: the time from onset to the last observation of the fit),
``u = 4 (2 tau - 1)``, ``H`` the fixed random sigmoid features of an ELM (paper 000 Eq.
47-48) and ``theta = [c_0, c_1, beta]``. The straight line is the exponential model; the ELM
bends it (acceleration, a knee, a plateau). Far beyond the data the sigmoids saturate and the
line dominates, so the model extrapolates like the exponential model with a learned offset.

``theta`` is the state of the library's optimiser face: a
:class:`~prognos_torch.optim.KalmanOptimizer` (EKF; the output is linear in ``theta``, so each
step is an exact recursive-least-squares update with a random walk, paper 003 Eq. 45-46) takes
one step per observation (or per block of observations for long series), so the model **keeps
learning while the asset degrades**; its posterior ``N(theta, P)`` is what the RUL paths sample:
``theta_i = theta + S e_i`` with ``S`` the optimiser's square-root covariance
(:meth:`~prognos_torch.optim.KalmanOptimizer.belief`). The observations are independent given
``theta``, so ``P`` shrinks like ``1 / n`` as data accrue, and the RUL interval with it.

Noise and prior (from the exponential :class:`~prognos_torch.prognosis.trends.TrendFit`): the
measurement variance is ``R = r + median(a) + w`` (white, baseline and wander variances of that
fit); the prior is ``theta ~ N(m, diag)`` with mean ``m = [z_1, 0, ..., 0]`` (``z_1``: the first
value since onset, so that a change of the data's units, a shift of ``z``, shifts ``g`` and
leaves the RUL unchanged) and std ``10 sd(z)`` for ``c_0``, ``3 (max z - min z)`` for ``c_1``
and ``(max z - min z) / sqrt(L / 4)`` for ``beta`` (so ``H beta`` can bend the line by about the
observed rise); the random walk ``Q = diag(R, R, R / (L / 4), ...) / n`` per
observation (the same per unit time however dense the sampling) lets ``g`` drift by about two
noise standard deviations over the observed span, so ``theta`` can follow a change of regime.

Paths (:meth:`LearnerTrendFit.first_passage`): ``theta`` starts from the optimiser's belief at
the origin (a snapshot taken while learning) and keeps its random walk (``Q`` per median
observation step), and a Brownian level term with the exponential fit's ``q_L`` is added, so the
band widens with the horizon and never collapses: ``z_j = g(tau_j; theta_j) + b_j``. Paths that
become non-finite are *diverged* and counted as censored.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..core.belief import GaussianBelief
from ..core.random import standard_normal
from ..core.validation import (
    broadcast_shape,
    check_count,
    check_nonneg,
    check_nonneg_int,
    check_seed,
    is_int,
)
from ..learners import ELM
from ..optim import KalmanOptimizer
from .trends import (
    Passage,
    TrendFit,
    TrendPool,
    check_obs_index,
    check_path_draws,
    check_path_grid,
    check_path_times,
)

__all__ = ["TimeELM", "LearnerTrendFit", "fit_learner_trend", "fit_learner_trends"]


class TimeELM(nn.Module):
    """``g(tau) = c_0 + c_1 tau + ELM(u(tau))`` of the module docstring.

    Input ``tau`` ``(..., 1)``, output ``(..., 1)``. Trainable: ``c`` ``(2, 1)`` and
    ``elm.beta`` (the ELM's random features are fixed).

    Args:
        n_hidden: ELM hidden nodes.
        generator: draws the ELM's random features.
    """

    def __init__(self, n_hidden: int = 10, generator: torch.Generator | None = None):
        super().__init__()
        self.c = nn.Parameter(torch.zeros(2, 1, dtype=torch.float64))
        self.elm = ELM(1, n_hidden, 1, "sigmoid", generator=generator)

    def features(self, tau: Tensor) -> Tensor:
        """``[1, tau, H(u(tau))]``: ``(...,)`` -> ``(..., 2 + L)``."""
        H = self.elm.hidden((4.0 * (2.0 * tau - 1.0)).unsqueeze(-1))
        return torch.cat([torch.ones_like(tau)[..., None], tau[..., None], H], -1)

    def weights(self, params: dict | None = None) -> Tensor:
        """``theta = [c_0, c_1, beta]`` as ``(..., 2 + L, 1)``."""
        params = params or {}
        c = params.get("c", self.c)
        beta = params.get("elm.beta", self.elm.beta)
        lead = broadcast_shape(c.shape[:-2], beta.shape[:-2])
        return torch.cat([c.expand(*lead, 2, 1), beta.expand(*lead, *beta.shape[-2:])], -2)

    def forward(self, tau: Tensor) -> Tensor:
        return self.features(tau[..., 0]) @ self.weights()

    def forward_with(self, params: dict[str, Tensor], tau: Tensor) -> Tensor:
        """``forward`` for parameters batched over leading dims; ``tau`` ``(B, 1)``."""
        return self.features(tau[..., 0]) @ self.weights(params)

    def forward_and_jacobian(self, params, tau: Tensor, names=None):
        """Output and its exact derivatives (the features: ``g`` is linear in ``theta``)."""
        names = ("c", "elm.beta") if names is None else tuple(names)
        if set(names) - {"c", "elm.beta"}:
            raise ValueError(f"TimeELM trains c and elm.beta only, got {names}")
        F = self.features(tau[..., 0])  # (B, 2 + L)
        W = self.weights(params)
        out = F @ W  # (..., B, 1)
        lead = out.shape[:-2]
        jac = {}
        if "c" in names:
            jac["c"] = F[:, None, :2, None].expand(*lead, *F.shape[:1], 1, 2, 1)
        if "elm.beta" in names:
            jac["elm.beta"] = F[:, None, 2:, None].expand(*lead, *F.shape[:1], 1, F.shape[1] - 2, 1)
        return out, jac


@dataclass
class LearnerTrendFit:
    """An online-trained :class:`TimeELM` with the parameter beliefs it had along the way.

    Attributes:
        module: the trained :class:`TimeELM` (weights at the posterior mean).
        optimizer: its :class:`~prognos_torch.optim.KalmanOptimizer` (belief, covariance).
        level_fit: the exponential :class:`~prognos_torch.prognosis.trends.TrendFit` whose
            measurements and noise it uses.
        t_onset, scale: ``tau = (t - t_onset) / scale``.
        snapshots: ``{observation index: GaussianBelief}`` parameter beliefs after the data up to
            that index (the last index is always present).
        trace: ``(steps,)`` trace of the parameter covariance after each optimiser step.
        seen: ``(steps,)`` observations used after each step.
        Q: ``(P,)`` random-walk variances per observation; dt_data: median time step of the data.
    """

    module: TimeELM
    optimizer: KalmanOptimizer
    level_fit: TrendFit
    t_onset: float
    scale: float
    snapshots: dict[int, GaussianBelief]
    trace: Tensor
    seen: Tensor
    Q: Tensor
    dt_data: float
    shape: str = "elm"

    @property
    def t(self) -> Tensor:
        return self.level_fit.t

    def to_z(self, level: float) -> float:
        return self.level_fit.to_z(level)

    def to_y(self, z: Tensor) -> Tensor:
        return self.level_fit.to_y(z)

    def tau(self, t: Tensor) -> Tensor:
        return (t - self.t_onset) / self.scale

    def predictive_std(self, t: Tensor, index: int = -1) -> Tensor:
        """Std of ``g(tau(t); theta)`` under the parameter belief at ``index`` (no walk):
        ``sqrt(f^T P f)`` with ``f`` the features, ``(J,)`` -> ``(J,)``."""
        b = self.parameter_belief(index)
        F = self.module.features(self.tau(check_path_times(t, "t", self.level_fit.z.device)))
        return (F @ b.chol).square().sum(-1).sqrt()

    def parameter_belief(self, index: int = -1) -> GaussianBelief:
        """The parameter belief after the data up to ``index`` (a snapshot)."""
        i = check_obs_index(index, self.level_fit.t.shape[0])
        if i not in self.snapshots:
            raise KeyError(f"no parameter snapshot at index {index}; have {sorted(self.snapshots)}")
        return self.snapshots[i]

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
        """Crossing times of ``level`` (module docstring); the signature of
        :meth:`TrendFit.first_passage`."""
        check_path_draws(generator, n_paths)
        keep = check_nonneg_int(keep, "keep")  # (2.5: an error on slice indices; True: 1)
        lf = self.level_fit
        zt = lf.to_z(level)
        i = check_obs_index(index, lf.t.shape[0])
        t_origin = float(lf.t[i])
        g64 = check_path_times(grid, "grid", lf.z.device)  # the times returned are grid's own
        check_path_grid(g64, t_origin)
        dt, dev = torch.float64, lf.z.device
        pb = self.parameter_belief(i)
        eb = standard_normal((n_paths, pb.mean.shape[-1]), generator, dt, dev)
        theta = pb.mean + eb @ pb.chol.mT  # (N, P): sampled from the optimiser's belief
        J = grid.shape[0]
        dts = torch.diff(torch.cat([g64.new_tensor([t_origin]), g64]))  # (J,)
        qv = self.Q.to(dt)  # (P,) random walk of theta per median observation step
        ql = float(lf.noise.level)
        walk = torch.zeros_like(theta)
        brown = torch.zeros(n_paths, dtype=dt, device=dev)
        first = torch.full((n_paths,), J, dtype=torch.int64, device=dev)
        diverged = torch.zeros(n_paths, dtype=torch.bool, device=dev)
        kept = []
        j0 = 0
        with torch.no_grad():
            while j0 < J and bool((first == J).any()):
                j1 = min(J, j0 + 64)
                d = dts[j0:j1]
                w = standard_normal((n_paths, j1 - j0, theta.shape[-1]), generator, dt, dev)
                w = walk[:, None] + torch.cumsum(w * (qv * d[:, None] / self.dt_data).sqrt(), 1)
                b = standard_normal((n_paths, j1 - j0), generator, dt, dev)
                b = brown[:, None] + torch.cumsum(b * (ql * d).sqrt(), 1)
                F = self.module.features(self.tau(g64[j0:j1]))  # (c, P)
                zc = ((theta[:, None, :] + w) * F[None]).sum(-1) + b  # (N, c)
                bad = ~torch.isfinite(zc)
                diverged |= bad.any(1) & (first == J)
                zc = torch.where(bad, torch.full_like(zc, -math.inf), zc)
                step = torch.arange(j0, j1, device=dev)
                f = torch.where(zc >= zt, step, torch.full_like(step, J)).amin(1)
                first = torch.where(first == J, f, first)
                if keep > 0:
                    kept.append(zc[:keep])
                walk, brown = w[:, -1], b[:, -1]
                j0 = j1
        gpad = torch.cat([grid, grid.new_tensor([math.inf])])
        times = gpad[first]
        if zt == -math.inf:
            times = torch.full((n_paths,), float(grid[0]), dtype=grid.dtype, device=dev)
        paths = None
        if keep > 0:
            z = torch.cat(kept, 1)
            if z.shape[1] < J:  # stopped early: every path had crossed
                z = torch.cat([z, z[:, -1:].expand(-1, J - z.shape[1])], 1)
            paths = lf.to_y(z)
        return Passage(times, paths, diverged & torch.isinf(times))


def fit_learner_trend(
    level_fit: TrendFit,
    *,
    n_hidden: int = 10,
    seed: int = 0,
    snapshots: tuple[int, ...] = (),
    max_steps: int = 400,
    drift: float = 1.0,
) -> LearnerTrendFit:
    """Train a :class:`TimeELM` online on the data of an exponential trend fit.

    The observations ``(tau_k, z_k)`` are fed to the Kalman optimiser in chronological order,
    one per step, or in at most ``max_steps`` equal blocks (block boundaries at the requested
    ``snapshots``, where the parameter belief is recorded).

    Args:
        level_fit: an exponential-shape :class:`~prognos_torch.prognosis.trends.TrendFit`.
        n_hidden: ELM hidden nodes; seed: seeds the ELM's random features.
        snapshots: observation indices at which to keep the parameter belief.
        max_steps: most optimiser steps (blocks).
        drift: multiplies the random walk ``Q`` (0: plain recursive least squares, ``P``
            shrinks monotonically).

    Returns:
        :class:`LearnerTrendFit`.
    """
    if not isinstance(level_fit, TrendFit):  # (a str failed on 'str' has no attribute 'shape')
        raise TypeError(f"level_fit must be a TrendFit, got {type(level_fit).__name__}")
    if level_fit.shape != "exponential":
        raise ValueError(f"level_fit must be the exponential shape, got {level_fit.shape!r}")
    seed = check_seed(seed)  # (1.7 was read as 1, "3" as 3, True as 1)
    # (0: a ZeroDivisionError; -1, 2.5 and True were taken)
    max_steps = check_count(max_steps, "max_steps", error=ValueError)
    # (inf was refused as 'Q contains non-finite values')
    check_nonneg(drift, "drift", numbers_only=True)
    z, t = level_fit.z, level_fit.t
    n = z.shape[0]
    if isinstance(snapshots, Tensor) and not snapshots.is_floating_point():
        snapshots = snapshots.flatten().tolist()  # (an integer tensor of indices)
    if not isinstance(snapshots, Iterable) or isinstance(snapshots, str):
        raise TypeError(f"snapshots must be a sequence of observation indices, got {snapshots!r}")
    # indices in [-n, n) (n + 2 was read as 2, 2.7 as 2, True as 1)
    snapshots = tuple(check_obs_index(i, n, f"snapshots[{k}]") for k, i in enumerate(snapshots))
    ok = ~torch.isnan(z)
    idx = torch.nonzero(ok).flatten()
    if idx.numel() < 3:
        raise ValueError("the learner trend needs at least 3 usable values since onset")
    zz = z[idx]
    t_on = float(t[0])
    scale = max(float(t[-1]) - t_on, 1e-12)
    gen = torch.Generator().manual_seed(seed)
    module = TimeELM(n_hidden, gen).to(z.device)  # features drawn on the CPU, then moved
    with torch.no_grad():  # prior mean of c_0: the first value, so a change of units (a shift
        module.c[0, 0] = zz[0]  # of z = log(y - phi)) shifts g and leaves the RUL unchanged
    rise = max(float(zz.max() - zz.min()), 1e-6)
    sd = max(float(zz.std(correction=1)) if zz.numel() > 1 else 0.0, 1e-6)
    f64 = dict(dtype=torch.float64, device=z.device)
    P0 = {"c": torch.tensor([(10 * sd) ** 2, (3 * rise) ** 2], **f64)[:, None],
          "elm.beta": torch.full((n_hidden, 1), rise**2 / (n_hidden / 4.0), **f64)}  # fmt: skip
    P0_flat = torch.cat([P0["c"].flatten(), P0["elm.beta"].flatten()])
    nz = level_fit.noise
    R = float(nz.meas) + float(level_fit.a[ok].median()) + float(nz.wander)
    # the random walk lets g drift by about two noise std over the observed span
    q_c, q_b = drift * R / idx.numel(), drift * R / (idx.numel() * n_hidden / 4.0)
    Q = [q_c, q_c] + [q_b] * n_hidden
    opt = KalmanOptimizer(module, filter="ekf", P0=P0_flat, Q=torch.tensor(Q, **f64), R=R)
    tau = (t[idx] - t_on) / scale
    X, Y = tau[:, None], zz[:, None]
    wanted = sorted(set(snapshots) | {n - 1})
    cuts = {w: int(torch.searchsorted(idx, idx.new_tensor(w), right=True)) for w in wanted}
    snaps: dict[int, GaussianBelief] = {w: opt.belief for w, c in cuts.items() if c == 0}
    stops = sorted({c for c in cuts.values() if c > 0})
    size = max(1, math.ceil(idx.numel() / max_steps))
    traces, seen, pos = [], [], 0
    while pos < idx.numel():
        end = min(pos + size, idx.numel())
        later = [c for c in stops if c > pos]
        if later:
            end = min(end, later[0])
        opt.step(X[pos:end], Y[pos:end])
        pos = end
        traces.append(float(torch.diagonal(opt.parameter_covariance()).sum()))
        seen.append(pos)
        for w, c in cuts.items():
            if c == pos:
                snaps[w] = opt.belief
    dts = torch.diff(t[idx])
    return LearnerTrendFit(
        module=module,
        optimizer=opt,
        level_fit=level_fit,
        t_onset=t_on,
        scale=scale,
        snapshots=snaps,
        trace=torch.tensor(traces, dtype=torch.float64),
        seen=torch.tensor(seen, dtype=torch.int64),
        Q=torch.tensor(Q, **f64),
        dt_data=float(dts[dts > 0].median()) if bool((dts > 0).any()) else 1.0,
    )


def fit_learner_trends(
    level_fit: TrendFit,
    *,
    members: int = 4,
    n_hidden: int = 10,
    seed: int = 0,
    snapshots: tuple[int, ...] = (),
    **kwargs,
) -> TrendPool:
    """An equal-weight ensemble of ``members`` learner trends with independent random features.

    An ELM's hidden features are drawn at random and stay fixed, so one learner trend's RUL
    depends on that draw beyond the Monte Carlo noise of its paths. Pooling ``members`` ELMs,
    each trained online by its own Kalman optimiser on the same data (:func:`fit_learner_trend`)
    with the features of seed ``(seed * members + j) mod 2**64``, averages over the draw (a
    sample of the random-feature prior) instead of betting on one.

    Args:
        level_fit: an exponential-shape :class:`~prognos_torch.prognosis.trends.TrendFit`.
        members: ELMs in the ensemble (``1``: ``fit_learner_trend(seed=seed)`` alone).
        n_hidden, seed, snapshots, kwargs: as :func:`fit_learner_trend`.

    Returns:
        a :class:`~prognos_torch.prognosis.trends.TrendPool` of :class:`LearnerTrendFit`.
    """
    if not is_int(members) or members < 1:
        raise ValueError(f"members must be an int >= 1, got {members!r}")
    # (a NumPy members overflowed in (seed * members + j) % 2**64; 1.5 was read as 1 for seed)
    members, seed = int(members), check_seed(seed)
    if isinstance(snapshots, Iterable) and not isinstance(snapshots, str):
        snapshots = tuple(snapshots)  # (an iterator gave its indices to the first member only)
    fits = tuple(
        fit_learner_trend(
            level_fit,
            n_hidden=n_hidden,
            seed=(seed * members + j) % 2**64,
            snapshots=snapshots,
            **kwargs,
        )
        for j in range(members)
    )
    return TrendPool(fits)
