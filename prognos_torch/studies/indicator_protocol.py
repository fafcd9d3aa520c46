"""Paper 002's protocol on a measured health indicator: a one-step learner alone and as the
m-order transition model of particle filters (Sec. "Experiments and results", Table 1-2,
Fig. 8-13; the figures: :mod:`~prognos_torch.studies.indicator_report`).

* :func:`indicator_case` (:class:`IndicatorCase`): the test indicator, the first predicted
  sample, the end of life (first sample at the threshold), the RUL prediction times (the last
  sample at or before each nominal time, each sample once) and the step cap of the RUL paths;
* :func:`particle_pass`: one particle filter over the test samples in ``R`` batched runs, each
  sample predicted one step ahead before it is assimilated
  (:func:`~prognos_torch.prognosis.rolling_particle_prediction`), with the fault probability
  ``fault(1, k) = sum_i w_k^i I(x_{k+1|k}^i >= threshold)`` (Fig. 10) and the weighted particle
  sets at the RUL prediction times; :func:`proposal_ess`: the EKPF's mean ESS with jitter on
  the shifted window elements (a diagnostic of the proposal's structure);
* :func:`evaluate_learner_filters`: the learner alone (Eq. 12 on the measured window; its RUL
  by the noise-free recursion, Eq. 12-14) and each filter (its RUL from the weighted particles,
  frozen weights and process noise); the paths run until every one reaches the threshold or
  the cap (:func:`~prognos_torch.prognosis.simulate_to_event`), the point RUL is the
  expectation of Eq. 28 with the paths at the cap counted at the cap;
* :func:`protocol_rows`: the per-run result rows: one-step and filtered RMSE over spans of the
  predicted samples (Table 1), the mean fault probability over spans, the point-RUL scores of
  Table 2 (:func:`~prognos_torch.metrics.point_rul_scores`), the censored mass, ESS and time;
* :func:`rul_table`: the point RULs per prediction time; :func:`selection_table`: the
  blocked cross-validation scores of an LS-SVR grid
  (:func:`~prognos_torch.learners.lssvr_grid_cv`) as a markdown table, with each candidate's
  test one-step RMSE (:func:`candidate_test_rmse`).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from ..core.model import StateSpaceModel
from ..core.validation import check_pos_int, check_positive_real
from ..datasets import embed
from ..filters import ParticleFilter, ekpf
from ..learners import MultiStepCV, fit_lssvr_gram
from ..metrics import first_crossing_time, point_rul_scores, rmse
from ..prognosis import (
    RULDistribution,
    last_sample_indices,
    learner_transition_model,
    rolling_particle_prediction,
    simulate_to_event,
    window_belief,
)
from .rows import run_rows
from .tables import markdown_table

__all__ = [
    "POINT_RUL_KEYS",
    "IndicatorCase",
    "indicator_case",
    "ParticlePass",
    "particle_pass",
    "proposal_ess",
    "MethodResult",
    "evaluate_learner_filters",
    "protocol_rows",
    "rul_table",
    "candidate_test_rmse",
    "selection_table",
]

#: Row keys of the point-RUL scores (:class:`~prognos_torch.metrics.PointRULScores`, Table 2).
POINT_RUL_KEYS = ("Accuracy", "RUL_RMSE", "alpha_lambda", "CRA")


@dataclass(frozen=True)
class IndicatorCase:
    """The test side of the protocol (:func:`indicator_case`).

    Attributes:
        z, t: ``(T,)`` the test indicator and its sample times.
        m: embedding dimension (model order).
        k0: index of the first predicted sample (``k0 >= m``).
        threshold: failure threshold (failure when ``z >= threshold``).
        t_eol: end of life, the time of the first sample at the threshold.
        dt: nominal sampling interval (the median time step).
        horizon: cap of the RUL paths in time units; cap: the same in steps.
        rul_idx: sample indices of the ``P`` RUL prediction times.
        times, true_rul: ``(P,)`` float64 prediction times and ``t_eol - times``.
        windows: ``(P, m)`` the measured windows ending at the prediction times.
    """

    z: Tensor
    t: Tensor
    m: int
    k0: int
    threshold: float
    t_eol: float
    dt: float
    horizon: float
    cap: int
    rul_idx: list[int]
    times: Tensor
    true_rul: Tensor
    windows: Tensor

    @property
    def truth(self) -> Tensor:
        """``(T - k0,)`` the predicted samples ``z[k0:]``."""
        return self.z[self.k0 :]

    @property
    def t_target(self) -> Tensor:
        """``(T - k0,)`` their times."""
        return self.t[self.k0 :]

    @property
    def one_step_windows(self) -> Tensor:
        """``(T - k0, m)`` the measured window before each predicted sample."""
        return embed(self.z, self.m)[0][self.k0 - self.m :]


def indicator_case(
    z: Tensor,
    t: Tensor,
    m: int,
    *,
    threshold: float,
    rul_start: float,
    rul_every: float,
    horizon: float,
    start: float | None = None,
) -> IndicatorCase:
    """The test indicator ``z`` ``(T,)`` at times ``t`` ``(T,)`` set up for the protocol.

    The RUL is predicted at the last sample at or before each of ``rul_start, rul_start +
    rul_every, ...`` below the end of life (each sample once, none before ``k0``); its paths run
    for at most ``round(horizon / dt)`` steps. ``start``: filter from the first sample at or
    after this time (``None``: from the first full window, ``k0 = m``).
    """
    m = check_pos_int(m, "m")
    check_positive_real(rul_every, "rul_every")
    t_eol = first_crossing_time(t, z, threshold)  # end of life: the indicator reaches it
    if math.isnan(t_eol):
        raise ValueError(f"z never reaches the threshold {threshold!r}: no end of life")
    dt = float(torch.diff(t).median())
    after = torch.nonzero(t >= start).flatten() if start is not None else None
    if after is not None and after.numel() == 0:
        raise ValueError(f"start {start!r} lies after the last sample time {float(t[-1])!r}")
    k0 = m if start is None else max(m, int(after[0]))
    rul_idx = last_sample_indices(t, np.arange(rul_start, t_eol, rul_every), first=k0)
    if not rul_idx:
        raise ValueError(
            f"no RUL prediction time: none of rul_start={rul_start!r} + k rul_every before the "
            f"end of life {t_eol!r} falls on a sample at or after k0={k0}"
        )
    times = t[rul_idx].to(torch.float64)
    return IndicatorCase(
        z=z,
        t=t,
        m=m,
        k0=k0,
        threshold=threshold,
        t_eol=t_eol,
        dt=dt,
        horizon=horizon,
        cap=int(round(horizon / dt)),
        rul_idx=rul_idx,
        times=times,
        true_rul=t_eol - times,
        windows=torch.stack([z[i - m + 1 : i + 1] for i in rul_idx]),
    )


@dataclass(frozen=True)
class ParticlePass:
    """One particle filter over ``z[k0:]`` (:func:`particle_pass`), ``T' = T - k0`` steps.

    Attributes:
        pred: ``(T', R)`` the predictive mean of each sample, made before it is seen.
        fault: ``(T', R)`` ``fault(1, k)``, the one-step fault probability.
        filtered: ``(T', R)`` the newest element of the posterior mean (step 5).
        ess: ``(T', R)`` effective sample size; fading_factors: ``(T', R)`` the weighted mean
            fading factor (1 without strong tracking).
        prior_fallback, collapsed: counts over steps and runs of particles drawn from the prior
            and of weight collapses.
        particles: ``(P, R, N, m)`` and weights ``(P, R, N)``: the sets at the ``keep`` indices
            (``None`` without ``keep``).
    """

    pred: Tensor
    fault: Tensor
    filtered: Tensor
    ess: Tensor
    fading_factors: Tensor
    prior_fallback: int
    collapsed: int
    particles: Tensor | None
    weights: Tensor | None


def particle_pass(
    pf: ParticleFilter,
    model: StateSpaceModel,
    z: Tensor,
    k0: int,
    runs: int,
    generator: torch.Generator,
    *,
    threshold: float,
    keep: Sequence[int] = (),
) -> ParticlePass:
    """Filter ``z[k0:]`` (``z``: ``(T,)``) with ``pf`` in ``runs`` batched runs, predicting each
    sample one step ahead before it is assimilated
    (:func:`~prognos_torch.prognosis.rolling_particle_prediction`).

    The initial belief is the measured window before ``z[k0]`` with the model's measurement std
    (:func:`~prognos_torch.prognosis.window_belief`). The filter's weight-collapse and
    proposal-fallback warnings are silenced: their counts are in the result. ``keep``: sample
    indices whose filtered particle sets are returned (after assimilating that sample).
    """
    m, ys = model.state_dim, z[k0:]
    r = float(model.noise(1).chol_R[0, 0])
    b0 = window_belief(z, k0, m, r, runs)  # the measured window before z[k0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rp = rolling_particle_prediction(
            pf,
            model,
            b0,
            ys[:, None, None].expand(-1, runs, 1),
            generator=generator,
            threshold=threshold,
            k0=k0 - 1,
            keep=keep,
        )
    return ParticlePass(
        pred=rp.mean[..., 0],
        fault=rp.fault_probability[..., 0],
        filtered=rp.filtered[..., -1],
        ess=rp.ess,
        fading_factors=rp.fading_factors,
        prior_fallback=int(rp.prior_fallback.sum()),
        collapsed=int(rp.collapsed.sum()),
        particles=torch.stack([rp.states[i].particles for i in keep]) if keep else None,
        weights=torch.stack([rp.states[i].weights for i in keep]) if keep else None,
    )


def proposal_ess(
    learner: nn.Module,
    m: int,
    q: float,
    z: Tensor,
    *,
    n_particles: int,
    steps: int,
    jitter: float,
    resample_threshold: float,
    threshold: float,
    seed: int,
) -> float:
    """Mean ESS of an EKPF (1 run) over the first ``steps`` samples after the first window of
    ``z`` ``(T,)``, with the learner's m-order transition model whose process noise is ``q`` on
    the newest window element and ``jitter q`` on the shifted ones (a diagnostic of the
    proposal's structure: with ``q^2 I`` the shifted elements are nearly deterministic)."""
    model = learner_transition_model(
        learner, m, q, q, jacobian="input_gradient", shift_std=jitter * q
    )
    gen = torch.Generator(device=z.device).manual_seed(seed)
    pf = ekpf(n_particles, resample_threshold=resample_threshold)
    return float(
        particle_pass(pf, model, z[: m + steps], m, 1, gen, threshold=threshold).ess.mean()
    )


@dataclass(frozen=True)
class MethodResult:
    """One method through the protocol (:func:`evaluate_learner_filters`).

    Attributes:
        pred: one-step predictions of :attr:`IndicatorCase.truth`: ``(T',)`` for the learner
            alone, ``(T', R)`` for a filter.
        rul: the RUL distribution at the prediction times, batch ``(P, 1)`` or ``(P, R)``.
        rul_pred: ``(P, 1)`` or ``(P, R)`` the point RUL (Eq. 28, paths at the cap counted at
            the cap: :attr:`~prognos_torch.prognosis.RULDistribution.restricted_mean`).
        seconds: wall time per run.
        filter: the filter's :class:`ParticlePass` (``None`` for the learner alone).
    """

    pred: Tensor
    rul: RULDistribution
    rul_pred: Tensor
    seconds: float
    filter: ParticlePass | None = None


def evaluate_learner_filters(
    learner: Callable[[Tensor], Tensor],
    model: StateSpaceModel,
    filters: Mapping[str, ParticleFilter],
    case: IndicatorCase,
    *,
    runs: int,
    seeds: Sequence[int],
    name: str,
) -> dict[str, MethodResult]:
    """The learner alone and each particle filter through the protocol (module docstring).

    Args:
        learner: the one-step predictor ``(B, m) -> (B, 1)``.
        model: its m-order transition model
            (:func:`~prognos_torch.prognosis.learner_transition_model`).
        filters: ``{name: particle filter}``, each run with ``model``.
        case: the test indicator (:func:`indicator_case`).
        runs: batched Monte Carlo runs of each filter (they differ in the seed only).
        seeds: one seed per filter (a generator on the indicator's device for the filter pass
            and its RUL paths).
        name: the learner's row label.
    Returns:
        ``{name: MethodResult}``: the learner first, then the filters in order.
    """

    def event(x: Tensor) -> Tensor:  # the indicator (newest window element) reaches it
        return x[..., -1] >= case.threshold

    if len(seeds) != len(filters):
        raise ValueError(f"seeds must hold one seed per filter ({len(filters)}), got {seeds!r}")
    t0 = time.perf_counter()
    with torch.no_grad():
        pred = learner(case.one_step_windows)[:, 0]  # Eq. 12: predictions of z[k0:]
    ev = simulate_to_event(
        model, case.windows[:, None], event, max_steps=case.cap, dt=case.dt, active_only=True
    )  # the noise-free recursion (Eq. 12-14) from each window
    rul_pred = ev.rul.restricted_mean.unsqueeze(-1)
    out = {name: MethodResult(pred, ev.rul, rul_pred, time.perf_counter() - t0)}
    for (fname, pf), seed in zip(filters.items(), seeds):
        gen = torch.Generator(device=case.z.device).manual_seed(seed)
        t0 = time.perf_counter()
        p = particle_pass(
            pf, model, case.z, case.k0, runs, gen, threshold=case.threshold, keep=case.rul_idx
        )
        ev = simulate_to_event(
            model,
            p.particles,
            event,
            max_steps=case.cap,
            weights=p.weights,
            dt=case.dt,
            process_noise=True,
            generator=gen,
            active_only=True,
        )  # until every particle crosses, or the cap
        secs = (time.perf_counter() - t0) / runs
        out[fname] = MethodResult(p.pred, ev.rul, ev.rul.restricted_mean, secs, p)  # (P, R)
    return out


def _point_rul(case: IndicatorCase, pred: Tensor, rul_kw: Mapping) -> dict[str, list[float]]:
    """Table 2 scores of each run's point RULs ``pred`` ``(P, R)``."""
    scores = [
        point_rul_scores(case.times, case.true_rul, pred[:, i], **rul_kw)
        for i in range(pred.shape[1])
    ]
    return {k: [sc[j] for sc in scores] for j, k in enumerate(POINT_RUL_KEYS)}


def protocol_rows(
    results: Mapping[str, MethodResult],
    case: IndicatorCase,
    *,
    spans: Mapping[str, Tensor | None],
    fault_spans: Mapping[str, Tensor],
    rul_kw: Mapping,
) -> list[dict]:
    """The result rows of every method (one row per run; the learner alone: one row).

    Args:
        results: :func:`evaluate_learner_filters` output (several may be merged).
        case: the test indicator.
        spans: ``{label: (T',) bool mask or None (all)}`` over the predicted samples: keys
            ``RMSE_<label>`` (and ``filt_RMSE_<label>`` for the filters).
        fault_spans: ``{key: (T',) bool mask}``: the mean fault probability over the span.
        rul_kw: keyword arguments of :func:`~prognos_torch.metrics.point_rul_scores`
            (``t_eol``, ``d0``, ``alpha``, ``lam``, ``cra_lambdas``).
    Returns:
        Rows with the keys above, then :data:`POINT_RUL_KEYS`, ``censored`` (the mean censored
        mass), ``ess`` (filters) and ``time_s``.
    """
    truth, rows = case.truth, []
    for name, r in results.items():
        if r.filter is None:
            v = {
                f"RMSE_{s}": float(rmse(r.pred, truth) if w is None else rmse(r.pred[w], truth[w]))
                for s, w in spans.items()
            }
            v |= _point_rul(case, r.rul_pred, rul_kw)
            rows += run_rows(
                name, v | {"censored": float(r.rul.censored_mass.mean()), "time_s": r.seconds}
            )
            continue
        p, tt = r.filter, truth.unsqueeze(-1).expand_as(r.pred)
        v = {}
        for key, x in (("RMSE", p.pred), ("filt_RMSE", p.filtered)):
            v |= {
                f"{key}_{s}": rmse(x, tt, dim=0) if w is None else rmse(x[w], tt[w], dim=0)
                for s, w in spans.items()
            }
        v |= {k: p.fault[w].mean(0) for k, w in fault_spans.items()}
        v |= _point_rul(case, r.rul_pred, rul_kw)
        v |= {"censored": r.rul.censored_mass.mean(0), "ess": p.ess.mean(0), "time_s": r.seconds}
        rows += run_rows(name, v)
    return rows


def rul_table(
    results: Mapping[str, MethodResult], case: IndicatorCase, names: Sequence[str], every: int = 1
) -> str:
    """Markdown: at every ``every``-th prediction time (days) the true RUL and each method's
    point RUL (Eq. 28), the mean over its runs."""
    rows = [
        [f"{float(case.times[p]):.3f}", f"{float(case.true_rul[p]):.3f}"]
        + [f"{float(results[n].rul_pred[p].mean()):.3f}" for n in names]
        for p in range(0, len(case.rul_idx), every)
    ]
    return markdown_table(["prediction time (d)", "true RUL (d)", *names], rows)


def candidate_test_rmse(
    X: Tensor, y: Tensor, keys: Sequence[tuple[float, float]], *, scale: float, case: IndicatorCase
) -> dict[tuple[float, float], float]:
    """The test one-step RMSE of each LS-SVR grid candidate ``(sigma / scale, C)`` fitted on the
    training pairs ``X`` ``(N, m)``, ``y`` ``(N, 1)``, on the case's one-step windows (reported
    beside the cross-validation scores of :func:`selection_table`, never used to choose)."""
    w = case.one_step_windows
    with torch.no_grad():
        fits = {k: fit_lssvr_gram(X, y, sigma=k[0] * scale, C=k[1]) for k in keys}
        return {k: float(rmse(f(w)[:, 0], case.truth)) for k, f in fits.items()}


def selection_table(
    scores: Mapping[tuple[float, float], MultiStepCV],
    *,
    dt: float,
    test_rmse: Mapping[tuple[float, float], float],
    chosen: Mapping[str, tuple[float, float]],
) -> str:
    """The blocked cross-validation scores of an LS-SVR grid as a markdown table.

    Args:
        scores: ``{(sigma / std, C): MultiStepCV}`` in row order.
        dt: days per step (the time-to-cross RMSE is in steps, the table's in days).
        test_rmse: ``{key: test one-step RMSE}`` (reported, not used to choose).
        chosen: ``{label: key}``: a key's rows are marked ``**(label)**``.
    """
    rows = [
        [
            f"{key[0]:g}" + "".join(f" **({lab})**" for lab, k in chosen.items() if k == key),
            f"{key[1]:g}",
            f"{sc.one_step:.5f}",
            f"{sc.multi_step:.5f}",
            f"{sc.crossing * dt:.3f}",
            f"{test_rmse[key]:.5f}",
        ]
        for key, sc in scores.items()
    ]
    head = ["sigma / std", "C", "one-step CV RMSE", "multi-step CV RMSE"]
    head += ["time-to-cross CV RMSE (d)", "test one-step RMSE (reported only)"]
    return markdown_table(head, rows)
