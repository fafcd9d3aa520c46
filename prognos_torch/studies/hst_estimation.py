"""State and fault estimation on the high-speed train, scored as in paper 004 Sec. 4.

:class:`HSTProtocol` holds the set-up (runs, window, nominal noise, initial belief, the reduced
protocol of the sensitivity runs); :func:`hst_filters` builds the paper's filters (UKF, RUKF of
Theorem 1, ARUKF of Theorem 2, the same with Theorem 1's scale chosen per step, and AUKF: the
moving window without the robust terms); :func:`score_filter` filters all Monte Carlo runs as one
batch (in time segments) and scores the RMSEs of the state, fault and noise estimates (Tables
2-5, :func:`~prognos_torch.systems.hst_estimation_errors`) as result rows;
:func:`score_filters` does so for a list of jobs; :func:`gamma_sweep` and :func:`noise_sweep` are
the sensitivity runs over Theorem 1's ``gamma`` and over the noise level.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor
from tqdm import tqdm

from ..adapt import MovingWindow
from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..core.validation import check_positive_real
from ..filters import GaussianFilter, arukf, rukf, run_in_segments, ukf
from ..filters.segments import SegmentedTrajectory
from ..quadrature import unscented
from ..systems.high_speed_train import (
    HST_FAULT_NAMES,
    HSTParams,
    hst_estimation_errors,
    hst_fault_model,
    hst_nominal_fault_model,
    hst_state_names,
    simulate_hst_runs,
)
from .rows import run_rows

__all__ = [
    "OPT",
    "ORACLE",
    "STATE_NAMES",
    "FAULT_NAMES",
    "SUMMARY",
    "STATE_COLS",
    "FAULT_COLS",
    "Q_COLS",
    "R_COLS",
    "HSTProtocol",
    "HSTTrace",
    "hst_filters",
    "score_filter",
    "score_filters",
    "gamma_sweep",
    "noise_sweep",
]

OPT = " (eps-opt)"  # method-name suffix: Theorem 1's scale chosen per step (bound="optimised")
ORACLE = "UKF (true Q,R)"  # the UKF with the true Q_k, R_k of Eq. 67-68
STATE_NAMES = hst_state_names(5)
FAULT_NAMES = HST_FAULT_NAMES
SUMMARY = ["state RMSE", "fault RMSE", "Q RMSE", "R RMSE", "Q RMSE (k>N)", "R RMSE (k>N)", "time_s"]
STATE_COLS = [f"RMSE {s}" for s in STATE_NAMES]  # Table 2
FAULT_COLS = [f"RMSE {s}" for s in FAULT_NAMES]  # Table 3
Q_COLS = [f"Q{i} RMSE" for i in range(1, 10)]  # Table 4
R_COLS = [f"R{i} RMSE" for i in range(1, 10)]  # Table 5


@dataclass(frozen=True)
class HSTProtocol:
    """The fault-estimation protocol on the train.

    Attributes:
        runs, n_steps: Monte Carlo runs and steps of the main simulation.
        window: ``N`` of the moving-window noise estimator (Theorem 2); the ``(k>N)`` scores use
            the steps ``k > N``.
        segment: steps per filter call (:func:`~prognos_torch.filters.run_in_segments`).
        sens_runs, sens_steps: the reduced protocol of the sensitivity runs.
        gammas: Theorem 1's ``gamma`` values of :func:`gamma_sweep`.
        r_scales: :func:`noise_sweep`: ``R_k`` (Eq. 68) times these in the truth and the filters.
        qr_scales: :func:`noise_sweep`: ``Q_k`` and ``R_k`` both times these (oracle only).
        q_scale: ``Q_k`` of Eq. 67 times this in the truth and every model.
        chol_D: fault random-walk stds (Eq. 12).
        p0_std: ``(2n-1+3,)`` initial belief stds (mean 0: the equilibrium).
        q_level, r_level: the nominal ``Q = q_scale q_level I``, ``R = r_level I``.
        params: the train.
    """

    runs: int
    n_steps: int
    window: int
    segment: int
    sens_runs: int
    sens_steps: int
    gammas: tuple[float, ...]
    r_scales: tuple[float, ...]
    qr_scales: tuple[float, ...]
    q_scale: float
    chol_D: tuple[float, float, float]
    p0_std: tuple[float, ...]
    q_level: float = 1.0
    r_level: float = 1.1
    params: HSTParams = field(default_factory=HSTParams)


class HSTTrace(NamedTuple):
    """What a figure draws of one filter's run (paper 004 Fig. 2-5)."""

    means: Tensor  # (T, 2n-1+3) estimates of run 0
    Q: Tensor  # (T, 2n-1+3) process-noise variances in use, mean over runs
    R: Tensor  # (T, 2n-1) measurement-noise variances in use, mean over runs


def hst_filters(
    params: HSTParams, window: int, gamma: float | None = None
) -> dict[str, GaussianFilter]:
    """Paper 004's filters by name: ``"UKF"``, ``"RUKF"`` (Theorem 1), ``"ARUKF"`` (Theorem 2,
    diagonal moving window of ``window`` steps), both with ``OPT`` (Theorem 1's scale chosen per
    step), and ``"AUKF"`` (the same window without the robust terms).

    Sigma points: scaled unscented ``alpha = 1, beta = 0, kappa = 1`` (Eq. 36, ``a = 1``);
    ``gamma`` defaults to ``params.gamma``; ``M``, ``N`` from ``params``.
    """
    g = params.gamma if gamma is None else gamma
    M = torch.tensor(params.M, dtype=torch.float64)
    window_noise = MovingWindow(window=window, diagonal=True)
    return {
        "UKF": ukf(1.0, 0.0, 1.0, sqrt=True),
        "RUKF": rukf(g, M, params.N),
        "ARUKF": arukf(g, M, params.N, window=window, diagonal=True),
        "RUKF" + OPT: rukf(g, M, params.N, bound="optimised"),
        "ARUKF" + OPT: arukf(g, M, params.N, window=window, bound="optimised"),
        # Eq. 36: +- sqrt((n + 1) P), a = 1
        "AUKF": GaussianFilter(unscented(1.0, 0.0, 1.0), noise=window_noise, name="AUKF"),
    }


def _detail_columns(s: int) -> tuple[list[str], ...]:
    """``STATE_COLS``, ``FAULT_COLS``, ``Q_COLS``, ``R_COLS`` for a train of ``s = 2n - 1``
    states (the module's columns where ``n = 5``)."""
    states = [f"RMSE {c}" for c in hst_state_names((s + 1) // 2)]
    k = range(1, s + 1)
    return states, FAULT_COLS, [f"Q{i} RMSE" for i in k], [f"R{i} RMSE" for i in k]


def _belief0(std: Sequence[float], runs: int, dtype, device) -> GaussianBelief:
    s = torch.tensor(std, dtype=dtype, device=device)
    mean = torch.zeros(runs, len(std), dtype=dtype, device=device)
    return GaussianBelief(mean, torch.diag(s).expand(runs, -1, -1).clone())


def score_filter(
    proto: HSTProtocol,
    method: str,
    filt: GaussianFilter,
    model: StateSpaceModel,
    truth: Tensor,
    ys: Tensor,
    *,
    q_scale: float | None = None,
    r_scale: float = 1.0,
    detail: bool = True,
) -> tuple[list[dict], SegmentedTrajectory]:
    """Filter all runs as one batch from the belief ``N(0, diag(p0_std^2))`` and score them.

    Args:
        truth: ``(T+1, B, 2n-1+3)`` states from step 0 (:func:`simulate_hst_runs`).
        ys: ``(T, B, 2n-1)`` measurements.
        q_scale: the truth's ``q_scale`` (default ``proto.q_scale``): Q is scored in the units
            of Eq. 67.
        r_scale: the truth's ``r_scale``: R is scored in the units of Eq. 68.
        detail: add the per-component columns ``STATE_COLS``, ``FAULT_COLS``, ``Q_COLS``,
            ``R_COLS`` to the ``SUMMARY`` ones.
    Returns:
        ``(rows, trajectory)``: one row per run (``SUMMARY`` means over the components of
        each table; ``time_s`` the batch wall time per run) and the filter's output.
    """
    qs = proto.q_scale if q_scale is None else q_scale
    check_positive_real(r_scale, "r_scale")  # (0 gave inf R scores)
    t0 = time.perf_counter()
    b0 = _belief0(proto.p0_std, ys.shape[1], ys.dtype, ys.device)
    tr = run_in_segments(filt, model, b0, ys, segment=proto.segment)
    secs = (time.perf_counter() - t0) / ys.shape[1]
    e = hst_estimation_errors(
        tr.means, tr.var_Q, tr.var_R / r_scale, truth, q_scale=qs, skip=proto.window
    )
    keys = ("state", "fault", "Q", "R", "Q_late", "R_late")
    vals = {name: e[k].mean(-1) for name, k in zip(SUMMARY, keys)}
    if detail:  # (the five-car columns named a wider state's components wrongly)
        for cols, k in zip(_detail_columns(e["state"].shape[-1]), ("state", "fault", "Q", "R")):
            vals |= {c: e[k][:, j] for j, c in enumerate(cols)}
    return run_rows(method, vals | {"time_s": secs}), tr


def score_filters(
    proto: HSTProtocol,
    jobs: Sequence[tuple[str, GaussianFilter, StateSpaceModel]],
    truth: Tensor,
    ys: Tensor,
    *,
    progress: bool = False,
    desc: str = "arukf-hst",
) -> tuple[list[dict], dict[str, HSTTrace]]:
    """:func:`score_filter` for each ``(method, filter, model)`` job in order.

    Returns:
        ``(rows, traces)``: the rows of every job and ``{method: HSTTrace}``.
    """
    rows: list[dict] = []
    traces: dict[str, HSTTrace] = {}
    for name, filt, model in tqdm(jobs, desc=desc, disable=not progress):
        r, tr = score_filter(proto, name, filt, model, truth, ys)
        rows += r
        traces[name] = HSTTrace(means=tr.means[:, 0], Q=tr.var_Q.mean(1), R=tr.var_R.mean(1))
    return rows, traces


def gamma_sweep(proto: HSTProtocol, truth: Tensor, ys: Tensor) -> list[dict]:
    """RUKF and ARUKF (``"<name> (gamma=g)"``) with the nominal noise for each ``g`` of
    ``proto.gammas``, summary columns only.

    Args:
        truth: ``(T+1, B, 2n-1+3)``; ys: ``(T, B, 2n-1)`` (e.g. the reduced protocol's part of
            the main simulation).
    """
    p = proto.params
    nominal = hst_nominal_fault_model(
        p, q_level=proto.q_level, r_level=proto.r_level, chol_D=proto.chol_D,
        q_scale=proto.q_scale, dtype=truth.dtype, device=truth.device,
    )  # fmt: skip
    rows: list[dict] = []
    for g in proto.gammas:
        for name in ("RUKF", "ARUKF"):
            filt = hst_filters(p, proto.window, gamma=g)[name]
            rows += score_filter(proto, f"{name} (gamma={g:g})", filt, nominal, truth, ys,
                                 detail=False)[0]  # fmt: skip
    return rows


def noise_sweep(
    proto: HSTProtocol, generator: Callable[[int], torch.Generator], *, device=None
) -> list[dict]:
    """The noise-level sweep on ``proto.sens_runs`` fresh runs of ``proto.sens_steps`` steps.

    For each ``s`` of ``proto.r_scales``: ``R_k`` times ``s`` in the simulation and in every
    filter, rows ``"<name>, R x<s>"`` of the oracle UKF and the ``OPT`` RUKF and ARUKF (nominal
    ``R = s r_level I``); then for each ``s`` of ``proto.qr_scales``: ``Q_k`` and ``R_k`` both
    times ``s``, the oracle only (``"<name>, Q,R x<s>"``). Noise variances are scored in the
    units of Eq. 67-68.

    Args:
        generator: run ``i`` of every simulation draws from ``generator(i)``.
        device: where to simulate and filter.
    Returns:
        The rows, with ``STATE_COLS`` ... ``R_COLS``.
    """
    p, Bs, Ts = proto.params, proto.sens_runs, proto.sens_steps
    oracle = ukf(1.0, 0.0, 1.0, sqrt=True)
    sweep = [("R", 1.0, s) for s in proto.r_scales] + [("Q,R", s, s) for s in proto.qr_scales]
    rows: list[dict] = []
    for what, qm, rs in sweep:
        qs = qm * proto.q_scale
        gens = [generator(i) for i in range(Bs)]
        truth, ys, _ = simulate_hst_runs(Ts, gens, params=p, q_scale=qs, r_scale=rs, device=device)
        dt, dev = truth.dtype, truth.device
        true_m = hst_fault_model(
            p, chol_D=proto.chol_D, q_scale=qs, r_scale=rs, dtype=dt, device=dev
        )
        jobs = [(ORACLE, oracle, true_m)]
        if what == "R":
            fs = hst_filters(p, proto.window)
            nom = hst_nominal_fault_model(
                p, q_level=proto.q_level, r_level=rs * proto.r_level, chol_D=proto.chol_D,
                q_scale=proto.q_scale, dtype=dt, device=dev,
            )  # fmt: skip
            jobs += [(k, fs[k], nom) for k in ("RUKF" + OPT, "ARUKF" + OPT)]
        for name, filt, model in jobs:
            label = f"{name}, {what} x{rs:g}"
            rows += score_filter(proto, label, filt, model, truth, ys, q_scale=qs, r_scale=rs)[0]
    return rows
