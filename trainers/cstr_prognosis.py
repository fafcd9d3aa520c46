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
  frozen: a static learner in :class:`~prognos_torch.prognosis.MeasurementForecaster`
  (``online=False``) that forecasts ``z_{k+1..k+n}`` by successive one-step predictions;
* joint state/parameter filters on ``[C_A, T, C_AF]`` with ``C_AF`` a random walk
  (:func:`~prognos_torch.systems.cstr.cstr_joint_model`): SCKF (reference) and STSCKF;
  at each ``k = N0..T`` the filter runs over the forecasts and ``C_AF^_{k+n|k+n}`` is the n-step
  prediction (paper 000 Sec. 5 steps 1-9,
  :func:`~prognos_torch.prognosis.rolling_fault_prediction`), ``n = 10``;
* threshold ``C_AF = 1.15`` mol/L (15 % above nominal), first reached at ``k = 223``: the alarm
  of paper 000 step 8 (first ``k`` with ``C_AF^_{k+n|k+n} >= 1.15``, crossing predicted at
  ``k + n``), and the RUL at prediction times ``k_p`` from the same procedure with the horizon
  stretched to ``H`` steps: first passage of the predicted ``C_AF`` path
  (:func:`~prognos_torch.prognosis.predict_threshold_crossings`).

Monte Carlo runs are batched through the filters' batch dimension. The ANFIS of run ``i`` is
trained on run ``i``'s own measurements; :class:`~prognos_torch.optim.KalmanOptimizer`'s
``runs=`` trains several parameter vectors on *shared* data, so the ``2 R`` trainings are a loop
(documented in the notes); the trained parameter vectors are then evaluated for all runs at once
(:class:`~prognos_torch.optim.StackedLearner` with per-run scaling). The readings in ``table.md``
are the template ``cstr_prognosis.md`` filled with the run's numbers.
"""

from __future__ import annotations

import time
from functools import partial
from pathlib import Path

import torch
from tqdm import tqdm

from prognos_torch import filters, plots, prognosis, studies
from prognos_torch.adapt import SageHusa
from prognos_torch.core import GaussianBelief
from prognos_torch.datasets import embed, minmax_normalize
from prognos_torch.learners import ANFIS
from prognos_torch.optim import ImSRUKF, ParameterBridge, StackedLearner, fit
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
# ImSRUKF with Q (diagonal) and R by Eq. 41 and 43 as printed (k0 = 1): the estimator the
# committed results were produced with (the optimiser's default is now the post-fit R, k0 = 300).
PRINTED_NOISE = SageHusa(estimate=("Q", "R"), diagonal=True)
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
FILTERS = {"SCKF": filters.sckf, "STSCKF": filters.stsckf}  # reference, strong tracking
NOTES = Path(__file__).with_name("cstr_prognosis.md")  # the readings of table.md


def _crossing_step(threshold: float, params: CSTRParams) -> int:
    """First k with C_AF,k >= threshold (Eq. 51 in closed form)."""
    k = 0
    while cstr_feed_drift(k, params) < threshold:
        k += 1
    return k


def _train_anfis(ys: torch.Tensor, device, progress: bool):
    """ImSRUKF-trained ANFIS per run and channel on ``ys[:N0]`` ``(T, R, 2)``: the two channel
    learners (one :class:`StackedLearner` each) and the training seconds per run."""
    R, template = ys.shape[1], ANFIS(EMBED, N_MFS).to(device)
    theta = torch.empty(2, R, ParameterBridge(template).numel, dtype=torch.float64, device=device)
    lo, hi = torch.empty(2, 2, R, dtype=torch.float64, device=device)
    t0 = time.perf_counter()
    jobs = [(r, c) for r in range(R) for c in range(2)]
    for r, c in tqdm(jobs, desc="ANFIS-ImSRUKF", disable=not progress, leave=False):
        ns = minmax_normalize(ys[:N0, r, c])  # the training part's extremes (no look-ahead)
        U, Tg = embed(ns.values, EMBED)
        m = ANFIS(EMBED, N_MFS).to(device).init_premises(U)
        with torch.no_grad():  # theta0: the persistence predictor (see P0 above)
            m.alpha.zero_()
            m.alpha[:, EMBED - 1, :] = 1.0
        opt = ImSRUKF(m, P0=P0, Q=Q_TRAIN, R=R_TRAIN, noise=PRINTED_NOISE)
        fit(m, opt, (U, Tg.unsqueeze(-1)), epochs=PASSES, progress=False)
        theta[c, r], lo[c, r], hi[c, r] = opt.theta, ns.lo, ns.hi
    secs = (time.perf_counter() - t0) / R
    stack = partial(StackedLearner.from_theta, template, evaluate="broadcast")  # one pass
    return [stack(theta[c], lo=lo[c], hi=hi[c]) for c in (0, 1)], secs


def _init_belief(runs: int, device) -> GaussianBelief:
    x0, S = cstr_steady_state(device=device), torch.tensor(S0, dtype=torch.float64, device=device)
    return GaussianBelief(torch.cat([x0, x0.new_ones(1)]), torch.diag(S)).expand(runs)


def run(cfg: StudyConfig, out_dir: Path) -> StudyResult:
    runs = cfg.runs or (3 if cfg.quick else STUDY.default_runs)
    T, sens_runs, dev = T_END, min(runs, 10), cfg.device
    sens_d = (1e-4, 1e-3) if cfg.quick else SENS_D
    k_true = _crossing_step(THRESHOLD, CSTRParams())
    # RUL prediction times: every RUL_STEP steps before the crossing (quick: RUL_TIMES only)
    rul_times = list(RUL_TIMES) if cfg.quick else list(range(N0, k_true, RUL_STEP))
    sims = [simulate_cstr(T + H_LONG, generator=cfg.generator(i), device=dev) for i in range(runs)]
    x, y, theta = (torch.cat([getattr(s, k) for s in sims], 1) for k in ("x", "y", "theta"))
    ys = y[:T]  # the filters and forecasters see z_1..z_T; the rest is truth only
    learners, train_s = _train_anfis(ys, dev, cfg.progress)
    fc = prognosis.MeasurementForecaster(learners, EMBED, online=False)

    def rolling(name, n, d):  # rolling n-step C_AF prediction of the first n runs, seconds
        f = fc if n == runs else type(fc)([lr.select(slice(0, n)) for lr in learners], EMBED)
        args = (FILTERS[name](), cstr_joint_model(chol_D=d, device=dev), ys[:, :n], f, N_AHEAD, N0)
        return studies.timed(
            prognosis.rolling_fault_prediction, *args, init=_init_belief(n, dev), param_index=2
        )

    def crossings(name):  # RUL from the prediction times (horizon H), seconds
        model, b0 = cstr_joint_model(chol_D=CHOL_D, device=dev), _init_belief(runs, dev)
        args = (FILTERS[name](), model, b0, ys, fc, rul_times, H_LONG, THRESHOLD)
        return studies.timed(prognosis.predict_threshold_crossings, *args, param_index=2)

    jobs = {("main", n, CHOL_D): partial(rolling, n, runs, CHOL_D) for n in FILTERS}
    if not cfg.quick:  # run 0 alone: unbatched time per run
        jobs |= {("single", n, CHOL_D): partial(rolling, n, 1, CHOL_D) for n in FILTERS}
    jobs |= {("rul", n, CHOL_D): partial(crossings, n) for n in FILTERS}
    sens_d1 = [d for d in sens_d if d != CHOL_D]  # the main runs serve chol_D = CHOL_D
    jobs |= {("sens", n, d): partial(rolling, n, sens_runs, d) for d in sens_d1 for n in FILTERS}
    out = studies.run_jobs(jobs, desc="cstr-prognosis", progress=cfg.progress)
    main, rul = ({n: out[(k, n, CHOL_D)] for n in FILTERS} for k in ("main", "rul"))
    single = {n: out[("single", n, CHOL_D)][1] for n in FILTERS if not cfg.quick}
    sens = {}
    for n, d in ((n, d) for d in sens_d for n in FILTERS):
        res = (main[n] if d == CHOL_D else out[("sens", n, d)])[0]
        e = studies.fault_prediction_errors(res, theta[:, : res.predicted.shape[1]])
        sens[(n, d)] = {k: v[:sens_runs].mean().item() for k, v in e.items()}

    rows = []
    for name, (res, secs) in main.items():
        scores = studies.fault_prediction_errors(res, theta)
        scores["alarm_err"] = prognosis.first_alarm(res, THRESHOLD) - k_true
        scores |= studies.crossing_scores(rul[name][0], k_true, at=RUL_TIMES)
        time_s = round((secs + rul[name][1]) / runs, 6)
        for i in range(runs):
            row = {"run": i, "method": name, **{k: v[i].item() for k, v in scores.items()}}
            rows.append(row | {"time_s": time_s, "train_s": round(train_s, 6)})
    metrics = ["MAE", "RMSE", "filt_RMSE", "alarm_err"] + [f"RUL_err@{kp}" for kp in RUL_TIMES]
    metrics += ["cross_MAE", "censored", "time_s", "train_s"]

    # ---------------------------------------------------------------- figures (run 0)
    figs = ["fig1_caf_prediction.png", "fig2_anfis_forecasts.png", "fig3_fading_factor.png"]
    figs.append("fig4_rul.png")
    plots.plot_prediction_errors(
        out_dir / figs[0],
        torch.arange(N0 + N_AHEAD, T + N_AHEAD + 1),
        theta[N0 + N_AHEAD : T + N_AHEAD + 1, 0, 0],
        {f"{n} {N_AHEAD}-step": r.predicted[:, 0, 0] for n, (r, _) in main.items()},
        title=f"{N_AHEAD}-step-ahead prediction of $C_{{AF}}$ (run 0, chol_D = {CHOL_D:g})",
        ylabel="$C_{AF}$ (mol/L)",
        xlabel="target time k + n (steps of 0.02 min)",
        truth_label="true $C_{AF}$ (Eq. 51)",
        threshold=THRESHOLD,
        error_ylabel="absolute error (mol/L)",
    )
    zf = prognosis.rolling_forecasts(fc, ys, N_AHEAD, N0)  # (K, n, R, 2)
    one, nst = (prognosis.aligned_forecasts(zf, j)[:, 0].cpu() for j in (1, N_AHEAD))
    plots.plot_panels(
        out_dir / figs[1],
        torch.arange(N0 + 1, T + 1),
        {"measurements": ys[N0:T, 0].cpu(), "ANFIS 1-step": one, f"ANFIS {N_AHEAD}-step": nst},
        truth=x[N0 + 1 : T + 1, 0].cpu(),
        names=["$C_A$ (mol/L)", "$T$ (K)"],
        ncols=2,
        title="ANFIS-ImSRUKF forecasts vs the true state (run 0, trained on k <= 150)",
        xlabel="time k (steps)",
    )
    model = cstr_joint_model(chol_D=CHOL_D, device=dev)
    traj = filters.run(filters.stsckf(), model, _init_belief(runs, dev), ys)
    lam = prognosis.origin_fading_factors(main["STSCKF"][0])[:, 0].cpu()
    plots.plot_fading_factor(
        out_dir / figs[2],
        torch.arange(1, T + 1),
        {
            "real-time filter on z_k (run 0)": traj.fading_factors[:, 0].cpu(),
            f"step n = {N_AHEAD} of the prediction made at k (run 0)": lam,
        },
        title="STSCKF fading factor $\\lambda_k$",
    )
    times = rul["SCKF"][0].times
    plots.plot_rul_band(
        out_dir / figs[3],
        times,
        k_true - times,
        {n: r.rul() for n, (r, _) in rul.items()},
        title=f"Predicted RUL of $C_{{AF}} \\geq {THRESHOLD:g}$ ({runs} runs, H = {H_LONG})",
        xlabel="prediction time $k_p$ (steps)",
        ylabel="RUL (steps)",
    )

    # ---------------------------------------------------------------- extra tables and notes
    f_rmse = studies.rolling_forecast_rmse(zf, x, N0)  # (n, 2)
    p_rmse = studies.rolling_forecast_rmse(prognosis.persistence_forecasts(ys, N_AHEAD, N0), x, N0)
    tab_z = studies.markdown_table(
        ["horizon j", "RMSE C_A ANFIS", "RMSE C_A persistence", "RMSE T ANFIS (K)"]
        + ["RMSE T persistence (K)"],
        (
            [j + 1, f"{f_rmse[j, 0]:.2e}", f"{p_rmse[j, 0]:.2e}", f"{f_rmse[j, 1]:.3f}"]
            + [f"{p_rmse[j, 1]:.3f}"]
            for j in range(N_AHEAD)
        ),
    )
    tab_s = studies.sweep_table(
        "chol_D", sens_d, sens, tuple(FILTERS), ("MAE", "RMSE"), ratio=("RMSE", *FILTERS, 2)
    )
    tab_r = studies.crossing_table({n: r for n, (r, _) in rul.items()}, k_true)
    tab_t = studies.markdown_table(
        ["method", "batched, per run (s)", "one run alone (s)", "ANFIS training per run (s)"],
        (
            [n, f"{secs / runs:.4f}", f"{single[n]:.3f}" if n in single else "— (quick mode)"]
            + [f"{train_s:.3f}"]
            for n, (_, secs) in main.items()
        ),
    )
    lam_rt = traj.fading_factors[N0:]
    values = {k: v for k, v in globals().items() if k.isupper()}  # the settings, and:
    values |= dict(T=T, k_true=k_true, N0_STEP=N0 + RUL_STEP, S0=list(S0), seed=cfg.seed, runs=runs)
    values |= dict(
        ratio_t=(f_rmse[-1, 1] / p_rmse[-1, 1]).item(),
        ratio_ca=(f_rmse[-1, 0] / p_rmse[-1, 0]).item(),
        diverged=", ".join(f"{n} {r.diverged}" for n, (r, _) in rul.items()),
        n_paths=len(rul_times) * runs,
        lam_median=lam_rt.median().item(),
        lam_q95=lam_rt.quantile(0.95).item(),
        lam_max=lam_rt.max().item(),
    )
    return StudyResult(
        rows=rows,
        metrics=metrics,
        paper={},
        figures=figs,
        config=dict(T=T, N0=N0, horizon=N_AHEAD, threshold=THRESHOLD, true_crossing=k_true)
        | dict(rul_horizon=H_LONG, rul_times=times.tolist())
        | {"anfis": {"embedding": EMBED, "n_mfs": N_MFS, "mf": "sigmoid", "passes": PASSES}}
        | {"imsrukf": {"P0": P0, "Q": Q_TRAIN, "R": R_TRAIN, "theta0": "persistence"}}
        | dict(chol_D=CHOL_D, init_std=list(S0), sensitivity_chol_D=list(sens_d))
        | {"sensitivity_runs": sens_runs}
        | {"time_s": "batched wall time (rolling prediction + RUL predictions) / runs"},
        notes=studies.fill_template(NOTES, values),
        extra_tables=[
            f"Time of the rolling {N_AHEAD}-step prediction: {runs} runs in one batched pass "
            "(divided by the runs) and run 0 alone; ANFIS training (2 channels, loop) separately. "
            "time_s in the main table adds the RUL predictions:\n\n" + tab_t,
            f"RUL (steps of 0.02 min) predicted at k_p for C_AF >= {THRESHOLD:g} (true crossing "
            f"k = {k_true}), median over the runs that predict a crossing within H = {H_LONG}:\n\n"
            + tab_r,
            f"Sensitivity to the C_AF random-walk std chol_D ({N_AHEAD}-step prediction, first "
            f"{sens_runs} runs, mean over runs):\n\n" + tab_s,
            f"ANFIS forecasts made at k = {N0}..{T} against the true state, and the persistence "
            f"forecast z_(k+j) = z_k (all {runs} runs):\n\n" + tab_z,
        ],
    )


STUDY = Study(
    name="cstr-prognosis",
    paper="003+000",
    title="ANFIS-ImSRUKF forecasts + strong-tracking SCKF: C_AF drift prediction and "
    "threshold-crossing time on the CSTR",
    run=run,
    default_runs=50,
)
