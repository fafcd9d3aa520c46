"""Evaluating one-step forecasters alone and as the transition model of a prognostic filter.

A trained one-step forecaster ``x_{k+1} = f(x_{k-m+1..k})`` (one per Monte Carlo run, e.g. a
:class:`~prognos_torch.optim.StackedLearner`, runs leading) is scored on a test series
(:class:`ForecastProblem`) in the same way whether it is used

* alone (:func:`evaluate_alone`): one-step predictions from the measured windows, recursive
  multi-step predictions (paper 002 Eq. 11-14, :func:`~prognos_torch.prognosis.recursive_predict`);
* or as the transition model of a filter run over the test measurements
  (:func:`evaluate_filtered`; :func:`~prognos_torch.prognosis.learner_transition_model`, paper
  002 Eq. 15-26): Gaussian filters (:func:`evaluate_gaussian`: the one-step prediction is the
  predictive mean of the next measurement, multi-step paths from the posterior by
  :func:`~prognos_torch.prognosis.gaussian_paths`) and particle filters
  (:func:`evaluate_particle`: weighted particle sets,
  :func:`~prognos_torch.prognosis.particle_paths`).

Scores per run (:func:`point_errors`): one-step RMSE/MAE over the test targets and RMSE/MAE of
the ``H``-step-ahead prediction from origins every ``stride`` steps; where the problem has a
failure threshold, the RUL at its prediction times (:func:`rul_scores`): sample paths until they
cross (:func:`~prognos_torch.prognosis.rul_distribution`), against the observed first crossing,
with alpha-lambda (Saxena et al. 2010, :func:`~prognos_torch.metrics.alpha_lambda`).
:func:`residual_noise` sets the filters' noise from the training residuals and
:func:`healthy_runs` flags runs that diverged in training.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.belief import GaussianBelief
from ..core.validation import is_int
from ..datasets import embed
from ..filters import GaussianFilter, ParticleFilter, multinomial
from ..filters import run as filter_run
from ..metrics import alpha_bounds, alpha_lambda, lambda_index, mae, probability_in_bounds, rmse
from ..prognosis import (
    gaussian_paths,
    learner_transition_model,
    particle_paths,
    predict_paths,
    recursive_predict,
    rul_distribution,
    window_belief,
)

__all__ = [
    "ForecastProblem",
    "ForecastProtocol",
    "forecast_problem",
    "point_errors",
    "rul_scores",
    "residual_noise",
    "healthy_runs",
    "evaluate_alone",
    "evaluate_gaussian",
    "evaluate_particle",
    "evaluate_filtered",
]

RUL_KEYS = ("RUL_MAE_d", "RUL_bias_d", "RUL_censored", "AL_mass", "alpha_lambda")


@dataclass(frozen=True)
class ForecastProblem:
    """One test problem: scaled training pairs and the series the test targets come from.

    Attributes:
        name: label; m: embedding dimension.
        X, Y: ``(N, m)`` training windows and ``(N, 1)`` targets.
        z: ``(T,)`` the test series; s0: index in ``z`` of the first test target (``s0 >= m``).
        stride: spacing of the multi-step origins.
        days: ``(T,)`` time of each value of ``z`` (needed for RUL).
        threshold: failure threshold (``None``: no RUL scores); t_eol: its observed first
            crossing (time units of ``days``); rul_idx: indices in ``z`` of the RUL prediction
            times; dt: time per step.
    """

    name: str
    m: int
    X: Tensor
    Y: Tensor
    z: Tensor
    s0: int
    stride: int
    days: Tensor | None = None
    threshold: float | None = None
    t_eol: float | None = None
    rul_idx: tuple[int, ...] = ()
    dt: float = 1.0

    def __post_init__(self):
        if self.X.dim() != 2 or self.X.shape[1] != self.m or self.Y.shape != (self.X.shape[0], 1):
            raise ValueError(
                f"X must be (N, {self.m}) and Y (N, 1), got {self.X.shape}, {self.Y.shape}"
            )
        if self.z.dim() != 1 or not self.m <= self.s0 < self.z.shape[0]:
            raise ValueError(f"z must be (T,) with m <= s0 < T, got {self.z.shape}, s0={self.s0}")
        if self.threshold is not None and (self.days is None or self.t_eol is None):
            raise ValueError("a threshold needs days and t_eol (the observed first crossing)")
        # a RUL time needs a belief before a later test target (rul_index in [0, T - s0 - 1]);
        # one before s0 - 1 gave a negative index, read from the end of the test
        lo, hi = self.s0 - 1, self.z.shape[0] - 2
        bad = [i for i in self.rul_idx if not is_int(i) or not lo <= i <= hi]
        if bad:
            raise ValueError(
                f"rul_idx must hold indices of z in [s0 - 1, T - 2] = [{lo}, {hi}], got {bad}"
            )

    @property
    def targets(self) -> Tensor:
        """``(T - s0,)`` the test targets."""
        return self.z[self.s0 :]

    def origins(self, horizon: int) -> Tensor:
        """Multi-step origins (0-based test-target index ``t``: predictions of ``t..t+H-1``)."""
        return torch.arange(0, self.targets.shape[0] - horizon + 1, self.stride)

    def windows(self) -> Tensor:
        """``(T - s0, m)``: the measured window before each test target."""
        T = self.targets.shape[0]
        return self.z.unfold(0, self.m, 1)[self.s0 - self.m : self.s0 - self.m + T]

    def rul_index(self) -> list[int]:
        """Test-target index whose prior belief is the posterior at each RUL prediction time."""
        return [i - self.s0 + 1 for i in self.rul_idx]


@dataclass(frozen=True)
class ForecastProtocol:
    """Sizes and settings of the evaluation.

    Attributes:
        horizon: multi-step horizon ``H``.
        rul_horizon: steps of the RUL sample paths; rul_paths: paths per run and time.
        alpha, lam, beta: alpha-lambda accuracy (cone half-width, time fraction, mass).
        chunk: particle-filter steps per call (memory of the stored particle sets).
    """

    horizon: int = 10
    rul_horizon: int = 240
    rul_paths: int = 50
    alpha: float = 0.3
    lam: float = 0.5
    beta: float = 0.5
    chunk: int = 100


def _first_reaching(x: Tensor, v: float, what: str) -> int:
    idx = torch.nonzero(x >= v).flatten()
    if idx.numel() == 0:
        raise ValueError(f"no {what} reaches {v:g}")
    return int(idx[0])


def forecast_problem(
    name: str,
    train: Tensor,
    z: Tensor,
    m: int,
    *,
    stride: int,
    s0: int | None = None,
    days: Tensor | None = None,
    test_from: float | None = None,
    threshold: float | None = None,
    rul_times: Sequence[float] = (),
    dt: float = 1.0,
    device: str | torch.device | None = None,
) -> ForecastProblem:
    """A :class:`ForecastProblem` from a scaled training series and a scaled test series.

    Args:
        name: label; m: embedding dimension.
        train: ``(N + m,)`` training series: ``N`` windows and targets
            (:func:`~prognos_torch.datasets.embed`).
        z: ``(T,)`` test series; stride: spacing of the multi-step origins.
        s0: index in ``z`` of the first test target; or (``None``) the first index with
            ``days >= test_from``, at least ``m``.
        days: ``(T,)`` time of each value of ``z`` (stays on its device).
        threshold: failure threshold in the units of ``z``: the end of life ``t_eol`` is the
            time of the first value of ``z`` that reaches it.
        rul_times: RUL prediction times: the first index with ``days >=`` each.
        dt: time per step; device: where ``X``, ``Y`` and ``z`` go.
    """
    X, Y = embed(train, m)
    if s0 is None:
        if days is None or test_from is None:
            raise ValueError("give s0, or days and test_from")
        s0 = max(_first_reaching(days, test_from, "time"), m)
    t_eol = None
    if threshold is not None:
        if days is None:
            raise ValueError("a threshold needs days")
        t_eol = float(days[_first_reaching(z, threshold, "test value")])
    rul_idx = tuple(_first_reaching(days, t, "time") for t in rul_times)
    return ForecastProblem(
        name,
        m,
        X.to(device),
        Y[:, None].to(device),
        z.to(device),
        s0,
        stride,
        days=days,
        threshold=threshold,
        t_eol=t_eol,
        rul_idx=rul_idx,
        dt=dt,
    )


def _expand_runs(x: Tensor, runs: int) -> Tensor:
    return x.unsqueeze(0).expand(runs, *x.shape)


def point_errors(
    pred1: Tensor, predH: Tensor, problem: ForecastProblem, protocol: ForecastProtocol
) -> dict[str, Tensor]:
    """``pred1`` ``(R, T)`` one-step, ``predH`` ``(R, K, H)`` multi-step predictions -> per-run
    ``RMSE_1``, ``MAE_1`` (every test target) and ``RMSE_<H>``, ``MAE_<H>`` (the ``H``-th step
    from each origin)."""
    y, H = problem.targets, protocol.horizon
    y1 = y.expand_as(pred1)
    yH = y[problem.origins(H) + H - 1].expand_as(predH[..., -1])
    return {
        "RMSE_1": rmse(pred1, y1, dim=-1),
        "MAE_1": mae(pred1, y1, dim=-1),
        f"RMSE_{H}": rmse(predH[..., -1], yH, dim=-1),
        f"MAE_{H}": mae(predH[..., -1], yH, dim=-1),
    }


def rul_scores(
    samples: Tensor, weights: Tensor | None, problem: ForecastProblem, protocol: ForecastProtocol
) -> dict[str, Tensor]:
    """RUL from sample paths ``(R, P, N, H)`` started at the prediction times ``rul_idx``.

    Per run: over the prediction times where the median RUL lies within the horizon, the mean
    absolute and the mean signed error of the median (``RUL_MAE_d``, ``RUL_bias_d``); the
    fraction of prediction times where it does not (``RUL_censored``); alpha-lambda at
    ``t_lambda``: the probability mass within ``[(1 - alpha) r*, (1 + alpha) r*]``
    (``AL_mass``) and whether it reaches ``beta`` (``alpha_lambda``). A run with non-finite
    paths gets NaN.
    """
    R = samples.shape[0]
    good = torch.isfinite(samples.reshape(R, -1)).all(-1)
    nan = torch.full((R,), math.nan, dtype=torch.float64)
    out = {k: nan.clone() for k in RUL_KEYS}
    if not bool(good.any()):
        return out
    w = None if weights is None else weights[good]
    dist = rul_distribution(samples[good], problem.threshold, w, dt=problem.dt)
    good = good.cpu()  # the scores are assembled on the CPU
    times = problem.days[list(problem.rul_idx)].to(torch.float64)
    true_rul = problem.t_eol - times
    med = dist.median.cpu()  # (R', P), NaN where more than half the mass is censored
    ok = torch.isfinite(med)
    n_ok = ok.sum(-1)
    d = torch.where(ok, med - true_rul, torch.zeros_like(med))
    some = n_ok > 0
    out["RUL_MAE_d"][good] = torch.where(some, d.abs().sum(-1) / n_ok.clamp_min(1), math.nan)
    out["RUL_bias_d"][good] = torch.where(some, d.sum(-1) / n_ok.clamp_min(1), math.nan)
    out["RUL_censored"][good] = (~ok).to(torch.float64).mean(-1)
    i_lam = lambda_index(times, protocol.lam, t_eol=problem.t_eol)
    lo, hi = alpha_bounds(true_rul[i_lam : i_lam + 1], protocol.alpha)
    pmf, support = dist.pmf.cpu(), dist.support.cpu()
    n = pmf.shape[0]
    out["AL_mass"][good] = probability_in_bounds(
        lo.expand(n), hi.expand(n), rul_pmf=pmf[:, i_lam], rul_support=support
    )
    hits = [
        alpha_lambda(
            times,
            true_rul,
            alpha=protocol.alpha,
            lam=protocol.lam,
            beta=protocol.beta,
            t_eol=problem.t_eol,
            rul_pmf=pmf[r],
            rul_support=support,
        )
        for r in range(n)
    ]
    out["alpha_lambda"][good] = torch.tensor(hits, dtype=torch.float64)
    return out


def residual_noise(
    learner, problem: ForecastProblem, runs: int, *, r_share: float, shift_std: float
) -> tuple[Tensor, Tensor, float]:
    """Filter noise from the learner's one-step training residual RMS ``s`` (over runs).

    The residual variance is split into measurement noise ``R = r_share s^2`` and process noise
    ``Q = (1 - r_share) s^2`` on the newest window element; the shifted elements get std
    ``shift_std q`` (a nonsingular ``Q``, which the Gaussian-proposal particle filters need).

    Returns:
        ``chol_Q`` ``(m, m)``, ``chol_R`` ``(1, 1)`` and ``s``.
    """
    if not 0.0 < r_share < 1.0:
        raise ValueError(f"r_share must be in (0, 1), got {r_share}")
    X = problem.X
    with torch.no_grad():
        res = learner(_expand_runs(X, runs)) - problem.Y
    sres = float(res.square().mean().sqrt())
    r, q = sres * math.sqrt(r_share), sres * math.sqrt(1.0 - r_share)
    d = torch.full((problem.m,), shift_std * q, dtype=X.dtype, device=X.device)
    d[-1] = q
    return torch.diag(d), torch.full((1, 1), r, dtype=X.dtype, device=X.device), sres


def healthy_runs(learner, problem: ForecastProblem, runs: int, *, max_rmse: float) -> Tensor:
    """``(R,)`` bool: the run did not diverge in training (its one-step predictions on the
    training windows are finite and their RMSE is at most ``max_rmse``)."""
    with torch.no_grad():
        out = learner(_expand_runs(problem.X, runs))
    err = (out - problem.Y).square().mean((-2, -1)).sqrt()
    return torch.isfinite(out).all(-1).all(-1) & (err <= max_rmse)


def evaluate_alone(
    learner, problem: ForecastProblem, runs: int, protocol: ForecastProtocol
) -> dict[str, Tensor]:
    """The forecaster alone: one-step and recursive predictions from the measured windows
    (and, with a threshold, RUL from its deterministic paths)."""
    w1, o, H = problem.windows(), problem.origins(protocol.horizon), protocol.horizon
    with torch.no_grad():
        pred1 = recursive_predict(learner, _expand_runs(w1, runs), 1)[..., 0]
        predH = recursive_predict(learner, _expand_runs(w1[o], runs), H)
        out = point_errors(pred1, predH, problem, protocol)
        if problem.threshold is not None:
            ends = [i - problem.m + 1 for i in problem.rul_idx]  # windows ending at the times
            wr = problem.z.unfold(0, problem.m, 1)[ends]
            path = recursive_predict(learner, _expand_runs(wr, runs), protocol.rul_horizon)
            out.update(rul_scores(path.unsqueeze(-2), None, problem, protocol))
    return out


def _init_belief(problem: ForecastProblem, runs: int, chol_R: Tensor) -> GaussianBelief:
    """The measured window before the first target, std = the measurement noise."""
    return window_belief(problem.z, problem.s0, problem.m, chol_R[0, 0], runs)


def evaluate_gaussian(
    filt: GaussianFilter,
    model,
    problem: ForecastProblem,
    runs: int,
    chol_R: Tensor,
    generator: torch.Generator,
    protocol: ForecastProtocol,
) -> dict[str, Tensor]:
    """A Gaussian filter over the test measurements (runs leading): the predictive mean of each
    next measurement, ``H``-step paths from the posterior before each origin and RUL sample
    paths (particles drawn from the posterior) at the prediction times."""
    b0 = _init_belief(problem, runs, chol_R)
    ys = problem.targets[:, None, None].expand(-1, runs, 1)
    with torch.no_grad():
        traj = filter_run(filt, model, b0, ys)
        pred1 = (ys - traj.innovations)[..., 0].T  # (R, T): predictive mean of y_k
        means = torch.cat([b0.mean[None], traj.means[:-1]])  # belief before target t
        chols = torch.cat([b0.chol[None], traj.chols[:-1]])
        o = problem.origins(protocol.horizon)
        bo = GaussianBelief(means[o].movedim(0, 1), chols[o].movedim(0, 1))  # (R, K, m)
        predH = gaussian_paths(filt, model, bo, protocol.horizon).mean
        out = point_errors(pred1, predH, problem, protocol)
        if problem.threshold is not None:
            p = problem.rul_index()
            bp = GaussianBelief(means[p].movedim(0, 1), chols[p].movedim(0, 1))  # (R, P, m)
            paths = predict_paths(
                model,
                bp,
                protocol.rul_horizon,
                method="particle",
                n_particles=protocol.rul_paths,
                generator=generator,
            )
            out.update(rul_scores(paths.samples, paths.weights, problem, protocol))
    return out


def evaluate_particle(
    pf: ParticleFilter,
    model,
    problem: ForecastProblem,
    runs: int,
    chol_R: Tensor,
    generator: torch.Generator,
    protocol: ForecastProtocol,
) -> dict[str, Tensor]:
    """A particle filter over the test measurements (runs leading, particles after them), in
    chunks of ``protocol.chunk`` steps: the weighted mean of the noise-free one-step prediction
    of each particle set, ``H``-step paths from the sets before the origins and RUL paths from
    i.i.d. draws of the sets at the prediction times."""
    b0 = _init_belief(problem, runs, chol_R)
    ys = problem.targets[:, None, None].expand(-1, runs, 1)
    T, m, gen = ys.shape[0], problem.m, generator
    origins = problem.origins(protocol.horizon)
    o_set = {int(v) for v in origins}
    p_set = set(problem.rul_index()) if problem.threshold is not None else set()
    pred1, predH, rul_sets = [], {}, {}

    def consume(parts: Tensor, logw: Tensor, t0: int) -> None:
        # parts (R, C, N, m), logw (R, C, N): weighted particle sets before targets t0, t0 + 1, ..
        w = logw.exp()
        nxt = recursive_predict(model, parts, 1)[..., 0]  # (R, C, N): noise-free f
        pred1.append((w * nxt).sum(-1))
        for c in range(parts.shape[1]):
            t = t0 + c
            if t in o_set:
                predH[t] = particle_paths(
                    model, parts[:, c], protocol.horizon, generator=gen, weights=w[:, c]
                ).mean
            if t in p_set:  # RUL paths: i.i.d. draws from the weighted set
                anc = multinomial(logw[:, c], gen)[:, : protocol.rul_paths]
                rul_sets[t] = parts[:, c].gather(1, anc[..., None].expand(-1, -1, m))

    with torch.no_grad():
        state = pf.init(model, b0, generator=gen)
        consume(state.particles[:, None], state.log_weights[:, None], 0)
        for a in range(0, T - 1, protocol.chunk):  # assimilating targets a..b-1 gives the sets
            b = min(a + protocol.chunk, T - 1)  # before targets a+1..b (the last needs none)
            tr = pf.run(model, state, ys[a:b], generator=gen, k0=a, keep_particles=True)
            state = tr.final
            consume(tr.particles.movedim(0, 1), tr.log_weights.movedim(0, 1), a + 1)
        pred1 = torch.cat(pred1, dim=1)
        predH = torch.stack([predH[int(t)] for t in origins], dim=1)
        out = point_errors(pred1, predH, problem, protocol)
        if p_set:
            parts = torch.stack([rul_sets[t] for t in problem.rul_index()], dim=1)  # (R, P, N', m)
            paths = particle_paths(model, parts, protocol.rul_horizon, generator=gen)
            out.update(rul_scores(paths.samples, paths.weights, problem, protocol))
    return out


def evaluate_filtered(
    learner,
    filt: GaussianFilter | ParticleFilter | None,
    problem: ForecastProblem,
    runs: int,
    chol_Q: Tensor,
    chol_R: Tensor,
    generator: torch.Generator,
    protocol: ForecastProtocol,
) -> dict[str, Tensor]:
    """The forecaster alone (``filt=None``) or as the transition model of ``filt``
    (:func:`~prognos_torch.prognosis.learner_transition_model` with the learner's
    ``input_gradient`` as Jacobian)."""
    if filt is None:
        return evaluate_alone(learner, problem, runs, protocol)
    model = learner_transition_model(learner, problem.m, chol_Q, chol_R, jacobian="input_gradient")
    if isinstance(filt, GaussianFilter):
        return evaluate_gaussian(filt, model, problem, runs, chol_R, generator, protocol)
    if isinstance(filt, ParticleFilter):
        return evaluate_particle(filt, model, problem, runs, chol_R, generator, protocol)
    raise TypeError(f"filt must be a GaussianFilter, a ParticleFilter or None, got {type(filt)}")
