"""Papers 003 + 000 combined: ANFIS-ImSRUKF measurement forecasts feeding strong-tracking joint
filters, n-step prediction and threshold-crossing time (RUL) of the CSTR feed drift.

Protocol:

* CSTR of paper 003 (Eq. 50, Table II; :func:`~prognos_torch.systems.cstr.simulate_cstr`) with
  the feed drift of Eq. 51 from k = 50, measurements ``[C_A, T]`` (noise std 1e-4 mol/L, 0.1 K,
  docs/systems.md), run past paper 003's 200 steps to ``T = 250`` (Eq. 51 continued) so that
  the threshold crossing lies inside the record;
* one ANFIS per measured channel (paper 003: embedding 3, two sigmoid MFs per input, 8 rules),
  trained by ImSRUKF (paper 003 Eq. 40-46, :class:`~prognos_torch.optim.ImSRUKF`, one pass) on
  the first ``N0 = 150`` measurements of the run, min-max scaled with that part's extremes; then
  frozen: a static learner in :class:`~prognos_torch.prognosis.forecast.MeasurementForecaster`
  (``online=False``) that forecasts ``z_{k+1..k+n}`` by successive one-step predictions;
* joint state/parameter filters on ``[C_A, T, C_AF]`` with ``C_AF`` a random walk
  (:func:`~prognos_torch.systems.cstr.cstr_joint_model`): SCKF (reference) and STSCKF;
  at each ``k = N0..T`` the filter runs over the forecasts and ``C_AF^_{k+n|k+n}`` is the n-step
  prediction (paper 000 Sec. 5 steps 1-9,
  :func:`~prognos_torch.prognosis.forecast.rolling_fault_prediction`), ``n = 10``;
* threshold ``C_AF = 1.15`` mol/L (15 % above nominal), first reached at ``k = 223``: the alarm
  of paper 000 step 8 (first ``k`` with ``C_AF^_{k+n|k+n} >= 1.15``, crossing predicted at
  ``k + n``), and the RUL at prediction times ``k_p`` from the same procedure with the horizon
  stretched to ``H`` steps (:func:`~prognos_torch.prognosis.forecast.predict_fault_parameter`
  with ``n = H``): first passage of the predicted ``C_AF`` path
  (:func:`~prognos_torch.prognosis.rul.rul_distribution`).

Monte Carlo runs are batched through the filters' batch dimension. The ANFIS of run ``i`` is
trained on run ``i``'s own measurements; :class:`~prognos_torch.optim.KalmanOptimizer`'s
``runs=`` trains several parameter vectors on *shared* data, so the ``2 R`` trainings are a loop
(documented in the notes); the trained parameter vectors are then evaluated for all runs at once
(:class:`_RunANFIS`, glue: scaling and a ``vmap`` over the runs' parameters).
"""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from tqdm import tqdm

from prognos_torch.core.belief import GaussianBelief
from prognos_torch.datasets.windows import embed, minmax_normalize
from prognos_torch.filters import run as filter_run
from prognos_torch.filters import sckf, stsckf
from prognos_torch.learners import ANFIS
from prognos_torch.metrics import mae, rmse
from prognos_torch.optim import ImSRUKF, ParameterBridge, fit
from prognos_torch.plots import plot_fading_factor, plot_panels
from prognos_torch.prognosis import (
    MeasurementForecaster,
    predict_fault_parameter,
    rolling_fault_prediction,
)
from prognos_torch.prognosis.rul import rul_distribution
from prognos_torch.studies import Study, StudyConfig, StudyResult
from prognos_torch.systems.cstr import (
    CSTRParams,
    cstr_feed_drift,
    cstr_joint_model,
    cstr_steady_state,
    simulate_cstr,
)

T_END = 250  # measurements z_1..z_250 (paper 003: 200; extended so the crossing is inside)
N0 = 150  # ANFIS training part z_1..z_150; predictions start at k = N0 (paper 000 step 2)
N_AHEAD = 10  # prediction horizon n
EMBED, N_MFS = 3, 2  # paper 003: embedding 3, two sigmoid MFs per input (8 rules)
THRESHOLD = 1.15  # C_AF failure threshold (mol/L), 15 % above the nominal feed
H_LONG = 100  # horizon of the RUL predictions (steps)
RUL_STEP = 5  # prediction times k_p = N0, N0 + 5, ... before the true crossing
RUL_TIMES = (150, 175, 200)  # prediction times whose RUL error is tabulated per run
# ImSRUKF training of the ANFIS (paper 003 Eq. 40-46). theta0: the consequents of the
# persistence predictor z_{k+1} = z_k (alpha_3^i = 1, the others 0) and data-spread premises;
# a small P0 on the consequents keeps the learned map near persistence outside the training
# range. P0(alpha) and Q were chosen on seeds 1000-1019 (not the study's runs), see the notes.
P0 = {"alpha": 3e-5, "b": 1e-2, "beta": 1e-4}
Q_TRAIN, R_TRAIN, PASSES = 1e-7, 1e-2, 1
# Random-walk std of C_AF in the filters' assistant model (paper 000 Eq. 3): the paper gives
# none; 1e-4 mol/L per step is 10-20 times below the Eq. 51 increment over k = 150..250
# (1e-3..2e-3), as a designer who does not know the ramp would set it. Sensitivity table below.
CHOL_D = 1e-4
S0 = (1e-4, 0.1, 1e-2)  # initial std of [C_A, T, C_AF] (mean: the nominal steady state)
SENS_D = (1e-5, 1e-4, 1e-3, 3e-3)


def _filters():
    return {"SCKF": sckf(), "STSCKF": stsckf()}


def _crossing_step(threshold: float, params: CSTRParams) -> int:
    """First k with C_AF,k >= threshold (Eq. 51 in closed form)."""
    k = 0
    while cstr_feed_drift(k, params) < threshold:
        k += 1
    return k


class _RunANFIS:
    """One channel's trained ANFIS of every run as one static learner (glue, no algorithm).

    ``(R, p)`` raw windows -> min-max scaled with each run's training extremes -> the run's own
    ANFIS parameters -> unscaled ``(R, 1)``. Implements what :class:`MeasurementForecaster`
    needs of a static learner. :meth:`ANFIS.forward_with` evaluates every run's parameters on
    every run's window in one broadcast pass ``(R, R, 1)``; the diagonal pairs run ``r``'s
    parameters with run ``r``'s window (for the small ``R`` here this is faster than a ``vmap``).
    """

    n_in, n_out = EMBED, 1

    def __init__(self, template: ANFIS, theta, lo, hi):
        self.template, self.theta, self.lo, self.scale = template, theta, lo, hi - lo
        self.params = ParameterBridge(template).unflatten(theta)  # {name: (R, ...)}

    def __call__(self, w: torch.Tensor) -> torch.Tensor:
        u = (w - self.lo[:, None]) / self.scale[:, None]
        with torch.no_grad():
            out = self.template.forward_with(self.params, u).diagonal(0, 0, 1).mT  # (R, 1)
        return out * self.scale[:, None] + self.lo[:, None]

    def runs(self, idx: slice) -> _RunANFIS:
        lo = self.lo[idx]
        return _RunANFIS(self.template, self.theta[idx], lo, lo + self.scale[idx])


def _train_anfis(ys: torch.Tensor, device, progress: bool):
    """ImSRUKF-trained ANFIS per run and channel on ``ys[:N0]`` ``(T, R, 2)``.

    Returns the two channel learners (:class:`_RunANFIS`) and the training seconds per run.
    """
    R = ys.shape[1]
    template = ANFIS(EMBED, N_MFS).to(device)
    bridge = ParameterBridge(template)
    theta = torch.empty(2, R, bridge.numel, dtype=torch.float64, device=device)
    lo = torch.empty(2, R, dtype=torch.float64, device=device)
    hi = torch.empty_like(lo)
    t0 = time.perf_counter()
    jobs = [(r, c) for r in range(R) for c in range(2)]
    for r, c in tqdm(jobs, desc="ANFIS-ImSRUKF", disable=not progress, leave=False):
        ns = minmax_normalize(ys[:N0, r, c])  # the training part's extremes (no look-ahead)
        U, Tg = embed(ns.values, EMBED)
        m = ANFIS(EMBED, N_MFS).to(device).init_premises(U)
        with torch.no_grad():  # theta0: the persistence predictor (see P0 above)
            m.alpha.zero_()
            m.alpha[:, EMBED - 1, :] = 1.0
        opt = ImSRUKF(m, P0=P0, Q=Q_TRAIN, R=R_TRAIN)
        fit(m, opt, (U, Tg.unsqueeze(-1)), epochs=PASSES, progress=False)
        theta[c, r], lo[c, r], hi[c, r] = opt.theta, ns.lo, ns.hi
    secs = (time.perf_counter() - t0) / R
    return [_RunANFIS(template, theta[c], lo[c], hi[c]) for c in range(2)], secs


def _init_belief(runs: int, device) -> GaussianBelief:
    x0 = cstr_steady_state(device=device)
    m = torch.cat([x0, x0.new_ones(1)]).expand(runs, 3)
    S = torch.diag(torch.tensor(S0, dtype=torch.float64, device=device)).expand(runs, 3, 3)
    return GaussianBelief(m.clone(), S.clone())


def _rolling(filt, ys, fc, chol_D, device):
    """Rolling n-step C_AF prediction over ``ys`` ``(T, R, 2)``; returns result, seconds."""
    model = cstr_joint_model(chol_D=chol_D, device=device)
    t0 = time.perf_counter()
    res = rolling_fault_prediction(
        filt, model, ys, fc, N_AHEAD, N0, init=_init_belief(ys.shape[1], device), param_index=2
    )
    return res, time.perf_counter() - t0


def _rul_predictions(filt, ys, learners, times, device):
    """RUL from prediction times ``k_p`` (paper 000 steps 3-8 with the horizon ``H``).

    Returns prediction times ``(P,)``, predicted crossing times ``(P, R)`` (NaN: censored, no
    crossing within ``H``), the number of predicted paths that became non-finite, and seconds.

    Far ahead, the T forecast of some runs runs away (the ANFIS extrapolates its trend) while
    the C_A forecast stays near persistence; the filter explains this with a large C_AF, the
    predicted T exceeds ~450 K and the explicit RK4 step (dt = 0.02 min) turns unstable. A path
    that becomes non-finite counts from then on as not crossing (``-inf``): its first passage
    before the divergence is kept, otherwise it is censored. The count is reported.
    """
    model = cstr_joint_model(chol_D=CHOL_D, device=device)
    R = ys.shape[1]
    t0 = time.perf_counter()
    state = filt.init(model, _init_belief(R, device), 1)
    k_prev, crossing, diverged = 0, [], 0
    for kp in times:
        state = filter_run(filt, model, state, ys[k_prev:kp], k0=k_prev).final
        k_prev = kp
        fc = MeasurementForecaster(learners, EMBED, online=False).initialize(ys[:kp])
        pred = predict_fault_parameter(filt, model, state, fc, H_LONG, kp, param_index=2)
        path = pred.means[..., 2]  # (H, R): C_AF^_{kp+j|kp+j}
        nonfinite = ~torch.isfinite(pred.means).all(-1)  # (H, R)
        bad = nonfinite.to(torch.int8).cummax(0).values.bool()  # from the first one on
        diverged += int(bad.any(0).sum())
        path = torch.where(bad, -math.inf, path)
        fp = rul_distribution(path.T.unsqueeze(-2), THRESHOLD).first_passage[..., 0]  # (R,)
        cross = torch.where(fp > 0, kp + fp, -1).to(torch.float64)
        crossing.append(torch.where(fp > 0, cross, math.nan))
    secs = time.perf_counter() - t0
    return torch.tensor(times, device=ys.device), torch.stack(crossing), diverged, secs


def _alarm(res, threshold: float) -> torch.Tensor:
    """Paper 000 step 8: first origin k with C_AF^_{k+n|k+n} >= threshold; the crossing is then
    predicted at k + n. Returns ``(R,)`` predicted crossing times (NaN: no alarm)."""
    path = res.predicted[..., 0].T.unsqueeze(-2)  # (R, 1, K) over origins k = N0..T
    fp = rul_distribution(path, threshold).first_passage[..., 0]  # 1-based origin index
    k = (N0 - 1 + fp + N_AHEAD).to(torch.float64)
    return torch.where(fp > 0, k, math.nan)


def _errors(res, theta, T):
    """Per-run errors: n-step prediction (targets N0+n..T+n) and real-time filtering (N0..T)."""
    pred = res.predicted[..., 0]  # (K, R), origins k = N0..T
    truth = theta[N0 + N_AHEAD : T + N_AHEAD + 1, :, 0]
    filt = res.filtered[N0 - 1 :, :, 0]  # C_AF^_{k|k}, k = N0..T
    ftruth = theta[N0 : T + 1, :, 0]
    return {
        "MAE": mae(pred, truth, dim=0),
        "RMSE": rmse(pred, truth, dim=0),
        "filt_RMSE": rmse(filt, ftruth, dim=0),
    }


def _measurement_forecasts(learners, ys, T):
    """ANFIS forecasts ``z_{k+1..k+n}`` made at ``k = N0..T``: ``(K, n, R, 2)``."""
    f = MeasurementForecaster(learners, EMBED, online=False).initialize(ys[:N0])
    out = []
    for k in range(N0, T + 1):
        out.append(f.forecast(N_AHEAD))
        if k < T:
            f.update(ys[k])
    return torch.stack(out)


def _fig_caf(path: Path, t, truth, preds: dict, thr: float, title: str) -> None:
    """C_AF truth vs the n-step predictions, and their absolute errors."""
    fig = Figure(figsize=(7.0, 6.0))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    ax1.plot(t, truth, "k-", lw=1.6, label="true $C_{AF}$ (Eq. 51)")
    ax1.axhline(thr, color="C3", lw=0.9, ls=":", label=f"threshold {thr:g}")
    for i, (name, p) in enumerate(preds.items()):
        ax1.plot(t, p, f"C{i}--", lw=1.2, label=name)
        ax2.semilogy(t, np.abs(p - truth), f"C{i}-", lw=1.1, label=name)
    ax1.set_ylabel("$C_{AF}$ (mol/L)")
    ax1.set_title(f"(a) {title}")
    ax1.legend(loc="upper left")
    ax2.set_xlabel("target time k + n (steps of 0.02 min)")
    ax2.set_ylabel("absolute error (mol/L)")
    ax2.set_title("(b) prediction error")
    ax2.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=100)


def _fig_crossing(path: Path, times, crossing: dict, k_true: int, title: str) -> None:
    """Predicted crossing time vs prediction time: median and 10-90 % band over runs."""
    fig = Figure(figsize=(7.0, 4.2))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    t = np.asarray(times, dtype=float)
    ax.axhline(k_true, color="k", lw=1.4, label=f"true crossing k = {k_true}")
    ax.plot(t, t, color="0.6", lw=0.8, ls=":", label="prediction time")
    for i, (name, c) in enumerate(crossing.items()):
        c = np.asarray(c, dtype=float)  # (P, R), NaN = censored
        with warnings.catch_warnings():  # all-NaN columns (every run censored) stay NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(c, axis=1)
            lo = np.nanpercentile(c, 10, axis=1)
            hi = np.nanpercentile(c, 90, axis=1)
        ax.fill_between(t, lo, hi, color=f"C{i}", alpha=0.2)
        ax.plot(
            t,
            med,
            f"C{i}o-",
            ms=3,
            lw=1.2,
            label=f"{name} (median, 10-90 %; runs crossing within H)",
        )
    ax.set_xlabel("prediction time $k_p$ (steps)")
    ax.set_ylabel("predicted crossing time (steps)")
    ax.set_title(title)
    ax.legend(loc="best")
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=100)


def run(cfg: StudyConfig, out_dir: Path) -> StudyResult:
    runs = cfg.runs or (3 if cfg.quick else STUDY.default_runs)
    T = T_END
    sens_d = (1e-4, 1e-3) if cfg.quick else SENS_D
    sens_runs = min(runs, 10)
    dev = cfg.device
    params = CSTRParams()
    k_true = _crossing_step(THRESHOLD, params)
    # RUL prediction times: every RUL_STEP steps before the crossing (quick: RUL_TIMES only)
    rul_times = list(RUL_TIMES) if cfg.quick else list(range(N0, k_true, RUL_STEP))

    # ---------------------------------------------------------------- data and forecasters
    sims = [
        simulate_cstr(T + H_LONG, runs=1, generator=cfg.generator(i), device=dev)
        for i in range(runs)
    ]
    x = torch.cat([s.x for s in sims], 1)  # (T+H+1, R, 2)
    y = torch.cat([s.y for s in sims], 1)  # (T+H, R, 2)
    theta = torch.cat([s.theta for s in sims], 1)  # (T+H+1, R, 1)
    ys = y[:T]  # the filters and forecasters see z_1..z_T; the rest is truth only
    learners, train_s = _train_anfis(ys, dev, cfg.progress)
    fc = MeasurementForecaster(learners, EMBED, online=False)

    # ---------------------------------------------------------------- filters
    jobs = [("main", name, CHOL_D) for name in _filters()]
    if not cfg.quick:  # unbatched timing only
        jobs += [("single", name, CHOL_D) for name in _filters()]
    jobs += [("rul", name, CHOL_D) for name in _filters()]
    # sensitivity (the main runs serve chol_D = CHOL_D)
    jobs += [("sens", name, d) for d in sens_d if d != CHOL_D for name in _filters()]
    bar = tqdm(jobs, desc="cstr-prognosis", disable=not cfg.progress)
    main, single, rul, sens = {}, {}, {}, {}
    fc1 = MeasurementForecaster([lr.runs(slice(0, 1)) for lr in learners], EMBED, online=False)
    fcs = MeasurementForecaster(
        [lr.runs(slice(0, sens_runs)) for lr in learners], EMBED, online=False
    )
    for kind, name, d in bar:
        bar.set_postfix_str(f"{kind} {name} chol_D={d:g}")
        filt = _filters()[name]
        if kind == "main":
            main[name] = _rolling(filt, ys, fc, d, dev)
        elif kind == "single":  # run 0 alone: unbatched time per run
            single[name] = _rolling(filt, ys[:, :1], fc1, d, dev)[1]
        elif kind == "rul":
            rul[name] = _rul_predictions(filt, ys, learners, rul_times, dev)
        else:
            sens[(name, d)] = _rolling(filt, ys[:, :sens_runs], fcs, d, dev)[0]
    for name in _filters():
        sens[(name, CHOL_D)] = main[name][0]
    sens = {
        key: {
            k: v[:sens_runs].mean().item()
            for k, v in _errors(res, theta[:, : res.predicted.shape[1]], T).items()
        }
        for key, res in sens.items()
    }

    # ---------------------------------------------------------------- rows
    errs = {name: _errors(res, theta, T) for name, (res, _) in main.items()}
    alarms = {name: _alarm(res, THRESHOLD) for name, (res, _) in main.items()}
    rows = []
    for name in main:
        times, cross, _, rsecs = rul[name]
        err_cross = cross - k_true  # (P, R) crossing-time error = RUL error at k_p
        for i in range(runs):
            row = {"run": i, "method": name}
            row.update({k: v[i].item() for k, v in errs[name].items()})
            row["alarm_err"] = alarms[name][i].item() - k_true
            for kp in RUL_TIMES:
                j = int((times == kp).nonzero()[0, 0])
                row[f"RUL_err@{kp}"] = err_cross[j, i].item()
            e = err_cross[:, i]
            ok = torch.isfinite(e)
            row["cross_MAE"] = e[ok].abs().mean().item() if bool(ok.any()) else math.nan
            row["censored"] = (~ok).double().mean().item()
            row["time_s"] = round((main[name][1] + rsecs) / runs, 6)
            row["train_s"] = round(train_s, 6)
            rows.append(row)
    metrics = ["MAE", "RMSE", "filt_RMSE", "alarm_err"]
    metrics += [f"RUL_err@{kp}" for kp in RUL_TIMES]
    metrics += ["cross_MAE", "censored", "time_s", "train_s"]

    # ---------------------------------------------------------------- figures (run 0)
    figs = []
    t_target = torch.arange(N0 + N_AHEAD, T + N_AHEAD + 1)
    truth0 = theta[N0 + N_AHEAD : T + N_AHEAD + 1, 0, 0].cpu().numpy()
    preds0 = {
        f"{n} {N_AHEAD}-step": r.predicted[:, 0, 0].cpu().numpy() for n, (r, _) in main.items()
    }
    _fig_caf(
        out_dir / "fig1_caf_prediction.png",
        t_target.numpy(),
        truth0,
        preds0,
        THRESHOLD,
        f"{N_AHEAD}-step-ahead prediction of $C_{{AF}}$ (run 0, chol_D = {CHOL_D:g})",
    )
    figs.append("fig1_caf_prediction.png")

    zf = _measurement_forecasts(learners, ys, T)  # (K, n, R, 2)
    t_all = torch.arange(N0 + 1, T + 1)
    one = torch.full((T - N0, 2), math.nan, dtype=torch.float64)
    nst = torch.full((T - N0, 2), math.nan, dtype=torch.float64)
    one[:] = zf[:-1, 0, 0].cpu()  # made at k - 1 for k = N0+1..T
    nst[N_AHEAD - 1 :] = zf[: T - N0 - N_AHEAD + 1, -1, 0].cpu()  # made at k - n
    plot_panels(
        out_dir / "fig2_anfis_forecasts.png",
        t_all,
        {
            "measurements": ys[N0:T, 0].cpu(),
            "ANFIS 1-step": one,
            f"ANFIS {N_AHEAD}-step": nst,
        },
        truth=x[N0 + 1 : T + 1, 0].cpu(),
        names=["$C_A$ (mol/L)", "$T$ (K)"],
        ncols=2,
        title="ANFIS-ImSRUKF forecasts vs the true state (run 0, trained on k <= 150)",
        xlabel="time k (steps)",
    )
    figs.append("fig2_anfis_forecasts.png")

    model = cstr_joint_model(chol_D=CHOL_D, device=dev)
    traj = filter_run(stsckf(), model, _init_belief(runs, dev), ys)
    lam_pred = torch.full((T,), math.nan, dtype=torch.float64)
    lam_pred[N0 - 1 :] = main["STSCKF"][0].fading_factors[:, -1, 0].cpu()
    plot_fading_factor(
        out_dir / "fig3_fading_factor.png",
        torch.arange(1, T + 1),
        {
            "real-time filter on z_k (run 0)": traj.fading_factors[:, 0].cpu(),
            f"step n = {N_AHEAD} of the prediction made at k (run 0)": lam_pred,
        },
        title="STSCKF fading factor $\\lambda_k$",
    )
    figs.append("fig3_fading_factor.png")

    _fig_crossing(
        out_dir / "fig4_crossing_time.png",
        rul["SCKF"][0].cpu().numpy(),
        {n: r[1].cpu().numpy() for n, r in rul.items()},
        k_true,
        f"Predicted time of $C_{{AF}} \\geq {THRESHOLD:g}$ ({runs} runs, horizon H = {H_LONG})",
    )
    figs.append("fig4_crossing_time.png")

    # ---------------------------------------------------------------- extra tables
    zt = torch.stack([x[N0 + j : T + j + 1] for j in range(1, N_AHEAD + 1)], 1)  # (K, n, R, 2)
    zp = ys[N0 - 1 : T][:, None].expand(-1, N_AHEAD, -1, -1)  # persistence z_k
    f_rmse = rmse(zf, zt, dim=(0, 2))  # (n, 2)
    p_rmse = rmse(zp, zt, dim=(0, 2))
    tab_z = [
        "| horizon j | RMSE C_A ANFIS | RMSE C_A persistence | RMSE T ANFIS (K) | "
        "RMSE T persistence (K) |",
        "|---|---|---|---|---|",
    ]
    for j in range(N_AHEAD):
        a, b = f_rmse[j].tolist(), p_rmse[j].tolist()
        tab_z.append(f"| {j + 1} | {a[0]:.2e} | {b[0]:.2e} | {a[1]:.3f} | {b[1]:.3f} |")
    tab_z = (
        f"ANFIS forecasts made at k = {N0}..{T} against the true state, and the persistence "
        f"forecast z_(k+j) = z_k (all {runs} runs):\n\n" + "\n".join(tab_z)
    )

    tab_s = [
        "| chol_D | SCKF MAE | SCKF RMSE | STSCKF MAE | STSCKF RMSE | RMSE ratio SCKF/STSCKF |",
        "|---|---|---|---|---|---|",
    ]
    for d in sens_d:
        a, b = sens[("SCKF", d)], sens[("STSCKF", d)]
        tab_s.append(
            f"| {d:g} | {a['MAE']:.4f} | {a['RMSE']:.4f} | {b['MAE']:.4f} | {b['RMSE']:.4f} | "
            f"{a['RMSE'] / b['RMSE']:.2f} |"
        )
    tab_s = (
        f"Sensitivity to the C_AF random-walk std chol_D ({N_AHEAD}-step prediction, first "
        f"{sens_runs} runs, mean over runs):\n\n" + "\n".join(tab_s)
    )

    times = rul["SCKF"][0].tolist()
    tab_r = [
        "| k_p | true RUL | "
        + " | ".join(f"{n} pred. RUL (median) | {n} censored" for n in rul)
        + " |"
    ]
    tab_r.append("|---|---|" + "---|---|" * len(rul))
    for j, kp in enumerate(times):
        cells = [str(kp), str(k_true - kp)]
        for r in rul.values():
            c = r[1][j]
            ok = torch.isfinite(c)
            med = (c[ok] - kp).median().item() if bool(ok.any()) else math.nan
            cells += ["—" if math.isnan(med) else f"{med:.0f}", f"{(~ok).double().mean():.2f}"]
        tab_r.append("| " + " | ".join(cells) + " |")
    tab_r = (
        f"RUL (steps of 0.02 min) predicted at k_p for C_AF >= {THRESHOLD:g} (true crossing "
        f"k = {k_true}), median over the runs that predict a crossing within H = {H_LONG}:\n\n"
        + "\n".join(tab_r)
    )

    tab_t = [
        "| method | batched, per run (s) | one run alone (s) | ANFIS training per run (s) |",
        "|---|---|---|---|",
    ]
    for n, (_, secs) in main.items():
        one = f"{single[n]:.3f}" if n in single else "— (quick mode)"
        tab_t.append(f"| {n} | {secs / runs:.4f} | {one} | {train_s:.3f} |")
    tab_t = (
        f"Time of the rolling {N_AHEAD}-step prediction: {runs} runs in one batched pass "
        "(divided by the runs) and run 0 alone; ANFIS training (2 channels, loop) separately. "
        "time_s in the main table adds the RUL predictions:\n\n" + "\n".join(tab_t)
    )

    lam_rt = traj.fading_factors[N0:]
    notes = f"""
There are no paper numbers for this combined study: paper 003 trains ANFIS on the CSTR C_A
series only (Table III, one-step prediction), paper 000 predicts a fault parameter of the
three-tank system with ROS-ELM forecasts. Readings and choices:

- Record: z_1..z_{T} (paper 003 simulates 200 steps; Eq. 51 continued to k = {T} so that the
  crossing of C_AF = {THRESHOLD:g} at k = {k_true} lies inside). The n = {N_AHEAD}-step predictions
  C_AF^_(k+n|k+n) are made at k = {N0}..{T} and scored against Eq. 51 at k + n (MAE, RMSE);
  filt_RMSE: C_AF^_(k|k) of the real-time filter on the real z_k, k = {N0}..{T}.
- ANFIS training part: the first N0 = {N0} measurements (paper 003 trains on 100). Until
  k = 100 the drift moves C_A and T by about 5 noise stds only; an ANFIS trained on z_1..z_100
  reproduces the persistence forecast (seeds 1000-1009, these settings: RMSE ratio to
  persistence 1.01 at every horizon 1..10, both channels), because nothing but noise is there
  to learn. With N0 = {N0} the T forecasts beat persistence (table above: ratio
  {(f_rmse[-1, 1] / p_rmse[-1, 1]).item():.2f} at j = {N_AHEAD}; C_A
  {(f_rmse[-1, 0] / p_rmse[-1, 0]).item():.2f}).
- ANFIS-ImSRUKF: one pass, one sample per step, P0 = {P0}, Q = {Q_TRAIN:g}, R = {R_TRAIN:g}
  (scaled units), the optimiser's ImSRUKF (Sage-Husa Q and R, diagonal Q). theta0 = the
  persistence consequents (alpha_3^i = 1) with data-spread premises. The default random
  consequents with P0(alpha) = 1 gave forecasts 2-25 times worse than persistence out of the
  training range (10 seeds; the min-max-scaled test data leave [0, 1] and the corner rules
  extrapolate), P0(alpha) = 1e-2 still 2-3 times worse. P0(alpha) and Q were then chosen on
  seeds 1000-1019 (20 runs that are not the study's) by the downstream {N_AHEAD}-step C_AF RMSE;
  10-step forecast RMSE / persistence RMSE (median over runs) and C_AF RMSE (mean):

  | P0(alpha) | Q | C_A fc ratio | T fc ratio | SCKF RMSE | STSCKF RMSE | min per-run SCKF/STSCKF |
  |---|---|---|---|---|---|---|
  | 1e-4 | 1e-6 | 1.10 | 0.30 | 0.0353 | 0.0208 | 0.64 |
  | 1e-4 | 0 | 1.06 | 0.22 | 0.0358 | 0.0147 | 0.98 |
  | 3e-5 | 0 | 1.02 | 0.40 | 0.0374 | 0.0106 | 3.01 |
  | 3e-5 | 1e-7 | 1.03 | 0.31 | 0.0369 | 0.0102 | 2.36 |
  | 1e-5 | 0 | 1.01 | 0.71 | 0.0386 | 0.0245 | 1.33 |
  | 1e-5 | 1e-7 | 1.02 | 0.47 | 0.0377 | 0.0118 | 2.43 |
  | 3e-6 | 1e-6 | 1.07 | 0.27 | 0.0356 | 0.0170 | 0.77 |

  The T forecast alone is not what matters: a sharp T forecast with a C_A forecast that lags
  (ratio > 1) is inconsistent, and the STSCKF, whose gain on C_AF is kept open, follows it into
  overshoot; forecasts that err consistently serve the filter better.
- Threshold crossing: the alarm of paper 000 step 8 (first k with C_AF^_(k+n|k+n) >= {THRESHOLD:g};
  crossing predicted at k + n): alarm_err = predicted - true crossing time (steps; negative =
  early). RUL: at k_p = {N0}, {N0 + RUL_STEP}, ... the filter runs over H = {H_LONG} forecast
  measurements from its real-time state (steps 3-8 with n = H); the first passage of the
  predicted C_AF path is the predicted crossing; RUL_err@k_p = predicted - true RUL (= the
  crossing-time error), cross_MAE its mean |.| over all k_p, censored the fraction of k_p
  without a predicted crossing within H (excluded from the error columns). Predicted paths
  that became non-finite within H (the T forecast runs away, the predicted T passes ~450 K
  where the explicit RK4 step of dt = 0.02 min is unstable; they then count as not crossing
  from there on): {", ".join(f"{n} {r[2]}" for n, r in rul.items())} of
  {len(rul_times) * runs} paths per filter.
- Reading: with chol_D well below the ramp increments the SCKF's gain on C_AF closes, its
  estimate lags the ramp and its predicted crossing comes late or beyond H (censored); the
  strong tracking keeps the gain open. With chol_D of the size of the increments (1e-3) the
  SCKF tracks by itself and the fading factor only adds variance (sensitivity table). The
  STSCKF crossing predictions come early (conservative) at the first prediction times. Over
  the long horizon both ANFIS forecasts lag the truth (median over runs, 40 steps after
  k_p = 175: C_A 3.7e-3 mol/L too high, T 1.3 K too low, both pointing to a smaller C_AF), yet
  the STSCKF's predicted C_AF path overtakes the truth after 20-40 steps (median error +0.045
  at j = 40 from k_p = 175, +0.12 from k_p = 200; measured separately on these runs): the two
  forecasts are not consistent with one C_AF under Eq. 50, and with its gain kept open the
  filter turns the mismatch into a rising C_AF. The SCKF path keeps its lag (-0.057).
- chol_D = {CHOL_D:g}; filter process noise std (1e-6, 1e-3) for [C_A, T] and the simulator's
  measurement noise (cstr_joint_model defaults); initial belief: nominal steady state, C_AF = 1,
  std {list(S0)}. Strong tracking: rho = 0.95, weakening factor 1.
- Monte Carlo: run i draws its noise from seed {cfg.seed} + i and trains its own two ANFIS on
  its own measurements. KalmanOptimizer(runs=R) vectorises R parameter vectors over shared
  inputs and targets, so the 2 x {runs} trainings run in a loop (train_s per run); the trained
  parameters of all runs are evaluated in one broadcast pass during forecasting.
- STSCKF fading factor (real-time filter, k > {N0}, all runs): median
  {lam_rt.median().item():.2f}, 95th percentile {lam_rt.quantile(0.95).item():.2f}, max
  {lam_rt.max().item():.2f}.
"""
    return StudyResult(
        rows=rows,
        metrics=metrics,
        paper={},
        figures=figs,
        config={
            "T": T,
            "N0": N0,
            "horizon": N_AHEAD,
            "threshold": THRESHOLD,
            "true_crossing": k_true,
            "rul_horizon": H_LONG,
            "rul_times": times,
            "anfis": {"embedding": EMBED, "n_mfs": N_MFS, "mf": "sigmoid", "passes": PASSES},
            "imsrukf": {"P0": P0, "Q": Q_TRAIN, "R": R_TRAIN, "theta0": "persistence"},
            "chol_D": CHOL_D,
            "init_std": list(S0),
            "sensitivity_chol_D": list(sens_d),
            "sensitivity_runs": sens_runs,
            "time_s": "batched wall time (rolling prediction + RUL predictions) / runs",
        },
        notes=notes,
        extra_tables=[tab_t, tab_r, tab_s, tab_z],
    )


STUDY = Study(
    name="cstr-prognosis",
    paper="003+000",
    title="ANFIS-ImSRUKF forecasts + strong-tracking SCKF: C_AF drift prediction and "
    "threshold-crossing time on the CSTR",
    run=run,
    default_runs=50,
)
