"""Paper 002 study: LS-SVR + strong-tracking particle filter on the IMS bearing health indicator.

Protocol (paper 002, Sec. "Experiments and results", Table 1, Table 2, Fig. 8-13), as far as the
data allow, run by :mod:`prognos_torch.studies.indicator_protocol` (every reading is listed in
``table.md``; its captions and readings are the template ``lssvr_stpf.md``):

* health indicator (:func:`~prognos_torch.datasets.health_indicator`): bearing 3 of IMS test 1,
  six time-domain features (the shipped table has no median), LLE with 12 neighbours, last 12
  days; channel 5 trains the predictor, channel 6 tests it. The LLE coordinate is brought to the
  paper's scale (the unit-norm eigenvector, ``y / sqrt(N)``), on which the failure threshold 0.1
  is first reached on the test channel at about day 11, as the paper states;
* LS-SVR of fourth order (embedding ``m = 4``, Gaussian kernel, Eq. 1-14), width and
  regularisation chosen on the training channel in two ways, each run through the whole
  protocol: by blocked 5-fold cross-validation of the one-step error (the paper's rows), and,
  beyond the paper, by the time-to-cross error of the recursive prediction on the same folds
  (:func:`~prognos_torch.learners.lssvr_grid_cv`; rows marked ``(ms)``);
* four one-step predictors on the test channel: the LS-SVR alone (Eq. 12 on the measured
  window), and LS-SVR PF (SIR), LS-SVR EKPF and LS-SVR STPF (Eq. 27, steps 1-7) with the LS-SVR
  as the m-order transition model (Eq. 15-26); one-step RMSE over days 1-12 and 10-12 (Table 1,
  Fig. 8-9; days are counted from 1 as in the paper, so days 10-12 are ``t in [9, 12)`` and the
  11th day is ``t in [10, 11)``);
* fault probability per step, ``fault(1, k)`` with the threshold 0.1 (Fig. 10), and per-day box
  plots;
* RUL every 0.1 d from the ninth day (``t = 8``): paths until every particle reaches the
  threshold or a 15-day cap, RUL pmf and its expectation (Eq. 28), Fig. 11-13; accuracy, RMSE,
  alpha-lambda (alpha = 0.3, lambda = 0.5) and CRA (lambda = 0, 0.25, 0.5, 0.75) of the RUL
  predictions (Table 2).

Monte Carlo runs differ in the particle-filter seed only (the indicator and the LS-SVR are
deterministic); the runs are one batched pass through the filters' batch dimension.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from types import SimpleNamespace

import torch

from prognos_torch.datasets import MinMaxScaler, embed, health_indicator
from prognos_torch.filters import ekpf, sir, stpf
from prognos_torch.learners import best_setting, fit_lssvr_gram, lssvr_grid_cv
from prognos_torch.metrics import first_crossing_time, point_rul_scores
from prognos_torch.prognosis import learner_transition_model, settle
from prognos_torch.studies import Study, StudyConfig, StudyResult, method_mean, tables
from prognos_torch.studies import indicator_protocol as ip
from prognos_torch.studies.indicator_report import indicator_figure, protocol_figures

# Paper 002, Table 1 (one-step RMSE) and Table 2 (RUL metrics; alpha-lambda False = 0, True = 1).
# The paper's "Proposed method"/"Proposed algorithm" is LS-SVR STPF; Table 2's "LS-SVR EKFPF" is
# the LS-SVR EKPF of Table 1.
PAPER_COLUMNS = ("RMSE_1_12", "RMSE_10_12", "Accuracy", "RUL_RMSE", "alpha_lambda", "CRA")
PAPER = {
    name: dict(zip(PAPER_COLUMNS, values))
    for name, values in {
        "LS-SVR": (0.0083, 0.4302, 0.3542, 2.445, 0.0, 0.152),
        "LS-SVR PF": (0.0127, 0.6071, 0.2983, 3.036, 0.0, 0.104),
        "LS-SVR EKPF": (0.0075, 0.2546, 0.321, 1.980, 0.0, 0.213),
        "LS-SVR STPF": (0.0010, 0.0010, 0.603, 1.002, 1.0, 0.390),
    }.items()
}
# RUL expectations (days) the paper reports at 9.5, 10 and 10.5 days (text under Fig. 12).
PAPER_RUL = {
    "LS-SVR PF": (3.716, 3.750, 4.135),
    "LS-SVR EKPF": (3.211, 2.764, 2.988),
    "LS-SVR STPF": (1.143, 2.156, 0.962),
}
PAPER_RUL_TIMES = (9.5, 10.0, 10.5)
METRICS = [
    *("RMSE_1_12", "RMSE_10_12", "filt_RMSE_1_12", "filt_RMSE_10_12", "Pf_day11", "Pf_day12"),
    *("Accuracy", "RUL_RMSE", "alpha_lambda", "CRA", "censored", "ess", "time_s"),
]
METHODS = ("LS-SVR", "LS-SVR PF", "LS-SVR EKPF", "LS-SVR STPF")
MS = " (ms)"  # rows whose LS-SVR is selected by the multi-step (time-to-cross) error

M_ORDER = 4  # "fourth-order" LS-SVR (Fig. 8-9, Table 1)
THRESHOLD = 0.1  # failure threshold on the paper's indicator scale
FAULT_DECISION = 0.5  # "fault probability exceeds 0.5 -> failure" (Fig. 10)
ALPHA, LAMBDA = 0.3, 0.5  # alpha-lambda (Table 2)
CRA_LAMBDAS = (0.0, 0.25, 0.5, 0.75)  # CRA (Table 2)
RUL_START = 8.0  # "from the ninth day", days counted from 1: the ninth day is t in [8, 9)
RUL_EVERY = 0.1  # dense prediction times 8.0, 8.1, ... (the paper's 9.5, 10, 10.5 among them)
CAP_DAYS = 15.0  # paths run until every particle crosses, or to this cap
SELECT_DAYS = 3.0  # horizon of the multi-step selection (> the largest true RUL, 3.1 d)
SELECT_STRIDE = 3  # every 3rd held window is an origin of the multi-step selection
TAIL_START = 9.0  # "10-12 days" (Table 1, Fig. 9b), days counted from 1: t in [9, 12)
DAY11 = (10.0, 11.0)  # "the 11th day": t in [10, 11)
DIAG_STEPS = 200  # steps of the proposal-structure diagnostic (full runs only)
ATTRACTOR_STEPS = 1500  # deterministic recursion length for the attractor census
N_PARTICLES = 100  # the paper does not give its particle count
RESAMPLE = 1.0 / 3.0  # STPF step 6 and prognosis step 2: resample when N_eff < N/3
DEFAULT_RUNS = 3  # the 15-day paths of 100 particles from 31 times dominate the run time
CV_FOLDS = 5
SIGMA_GRID = (3.0, 10.0, 30.0, 100.0)  # kernel width as multiples of the training-channel std
C_GRID = (1e1, 1e2, 1e3, 1e4)
QUICK_START = 8.9  # quick mode filters from this day on
JITTER_DIAG = 0.1  # shifted-element noise of the proposal-structure diagnostic (x q)
PMF_BIN = 12  # RUL pmf figure: bins of 12 steps (2 h)
GAP_DAYS = 30.0 / 1440.0  # figures break their lines at recording gaps longer than 30 min
REPORT = Path(__file__).with_name("lssvr_stpf.md")  # table.md captions, readings
SHORT = {"LS-SVR": "lssvr", "LS-SVR PF": "pf", "LS-SVR EKPF": "ekpf", "LS-SVR STPF": "stpf"}
SHORT |= {n + MS: v + "_ms" for n, v in SHORT.items()}
ALL_METHODS = METHODS + tuple(n + MS for n in METHODS)
FILTERS = {"LS-SVR PF": sir, "LS-SVR EKPF": ekpf, "LS-SVR STPF": stpf}  # each with the LS-SVR


def _indicator(dev):
    """The health indicator on the paper's scale (unit-norm LLE eigenvector) and its time axis."""
    hi = health_indicator()  # bearing 3, channels 5 -> 6, six features, K = 12, last 12 days
    # health_indicator scales the LLE coordinate to (1/N) sum y^2 = 1 (Roweis & Saul);
    # the unit-norm eigenvector (eigs, scikit-learn) is y / sqrt(N).
    scale = math.sqrt(hi.train.shape[0])
    return hi, scale, (hi.train / scale).to(dev), (hi.test / scale).to(dev), hi.elapsed.to(dev)


def _protocol(case, X, y, sd, scores, runs, n_part, key, suffix, seed):
    """LS-SVR (sigma = key[0] x std, C = key[1]) and the three particle filters (seeds ``seed +
    1000 x filter index``) through the whole protocol; rows are labelled ``name + suffix``."""
    m, sigma, C, score = M_ORDER, key[0] * sd, key[1], scores[key]
    learner = fit_lssvr_gram(X, y, sigma=sigma, C=C)  # Eq. 8 / Eq. 25 by matrix products
    # Process and measurement noise (the paper gives neither): the out-of-fold one-step
    # residual variance s^2 of the selected LS-SVR, split equally, q^2 = r^2 = s^2 / 2, on
    # every window element (see notes).
    q = score.one_step / math.sqrt(2.0)
    chol_Q = q * torch.eye(m, dtype=X.dtype, device=X.device)
    model = learner_transition_model(learner, m, chol_Q, q, jacobian="input_gradient")
    pfs = {n + suffix: make(n_part, resample_threshold=RESAMPLE) for n, make in FILTERS.items()}
    seeds = [seed + 1000 * i for i in range(len(pfs))]
    res = ip.evaluate_learner_filters(
        learner, model, pfs, case, runs=runs, seeds=seeds, name="LS-SVR" + suffix
    )
    config = {"kernel": "rbf", "sigma": sigma, "C": C, "cv_rmse": score.one_step}
    config |= {"crossing_rmse_steps": score.crossing, "q": q, "r": q}
    return SimpleNamespace(learner=learner, model=model, q=q, sigma=sigma, score=score, res=res,
                           config=config)  # fmt: skip


def run(cfg: StudyConfig, out_dir: Path) -> StudyResult:
    quick, dev, m = cfg.quick, torch.device(cfg.device), M_ORDER
    t_start = time.perf_counter()
    runs, n_part = cfg.runs or (2 if quick else DEFAULT_RUNS), 20 if quick else N_PARTICLES

    # data: the indicator, its end of life and the RUL prediction times (quick: from QUICK_START)
    hi, scale, z_train, z_test, t = _indicator(dev)
    case = ip.indicator_case(z_test, t, m, threshold=THRESHOLD, rul_start=RUL_START,
                             rul_every=RUL_EVERY, horizon=CAP_DAYS,
                             start=QUICK_START if quick else None)  # fmt: skip
    t_eol, dt_step, times, true_rul = case.t_eol, case.dt, case.times, case.true_rul
    mm = MinMaxScaler().fit(z_train)
    thr_minmax = float(mm.inverse_transform(torch.tensor(THRESHOLD, dtype=z_train.dtype)))
    t_minmax = first_crossing_time(t, z_test, thr_minmax)

    # models: LS-SVR selection on the training channel, by the one-step and time-to-cross errors
    X, y = embed(z_train, m)
    sd, h_sel = float(z_train.std()), int(round(SELECT_DAYS / dt_step))
    grid = dict(sigmas=(3.0, 30.0), Cs=(1e3, 1e4)) if quick else dict(sigmas=SIGMA_GRID, Cs=C_GRID)
    scores = lssvr_grid_cv(z_train, m, h_sel, **grid, scale=sd, folds=CV_FOLDS,
                           threshold=THRESHOLD, stride=SELECT_STRIDE)  # fmt: skip
    key_1 = best_setting(scores, "one_step")  # the paper's rows
    key_ms = best_setting(scores, "crossing")  # beyond the paper: (ms) rows

    # results: both protocols ((ms) filters: seed + 1000 x (filter index + 3))
    args = (case, X, y, sd, scores, runs, n_part)
    one = _protocol(*args, key_1, "", cfg.seed)
    ms = _protocol(*args, key_ms, MS, cfg.seed + 3000)
    res = one.res | ms.res
    t_tgt, truth = case.t_target, case.truth
    tail, day12 = t_tgt >= TAIL_START, t_tgt >= DAY11[1]
    day11 = (t_tgt >= DAY11[0]) & (t_tgt < DAY11[1])
    d0 = float(true_rul[0])  # accuracy normaliser: the true RUL at the first prediction
    rul_kw = dict(t_eol=t_eol, d0=d0, alpha=ALPHA, lam=LAMBDA, cra_lambdas=CRA_LAMBDAS)
    spans, fault_spans = {"1_12": None, "10_12": tail}, {"Pf_day11": day11, "Pf_day12": day12}
    rows = ip.protocol_rows(res, case, spans=spans, fault_spans=fault_spans, rul_kw=rul_kw)
    diag_txt = "(diagnostic skipped in quick mode)"
    if not quick:  # proposal-structure diagnostic
        ess_uni = float(res["LS-SVR EKPF"].filter.ess[:DIAG_STEPS].mean())
        ess_j = ip.proposal_ess(one.learner, m, one.q, case.z, n_particles=n_part,
                                steps=DIAG_STEPS, jitter=JITTER_DIAG, seed=cfg.seed,
                                resample_threshold=RESAMPLE, threshold=THRESHOLD)  # fmt: skip
        j = f"{JITTER_DIAG:g} q"
        diag_txt = (f"EKPF over the first {DIAG_STEPS} steps (1 run, {n_part} particles): mean "
                    f"ESS {ess_j:.1f} with Q = diag({j}, {j}, {j}, q) against {ess_uni:.1f} with "
                    "Q = q^2 I.")  # fmt: skip

    # figures (run 0)
    paper_idx = [int((times - v).abs().argmin()) for v in PAPER_RUL_TIMES if times[0] <= v]
    lines = {f"training, channel {hi.train_channel}": z_train}
    lines[f"test, channel {hi.test_channel}"] = z_test
    indicator_figure(out_dir / "fig1_indicator.png", t, lines, threshold=THRESHOLD, t_eol=t_eol,
                     title="Health indicator of bearing 3 (LLE of six features, unit-norm scale)",
                     ylabel="LLE health indicator", gap=GAP_DAYS,
                     xlabel="time (days, last 12 days of test 1)")  # fmt: skip
    figs = ["fig1_indicator.png"]
    figs += protocol_figures(out_dir, one.res, res, case, short=SHORT, tail=tail,
                                span_labels=("days 1-12", f"days {TAIL_START:g}-12"),
                                paper_idx=paper_idx, alpha=ALPHA, lam=LAMBDA,
                                decision=FAULT_DECISION, pmf_bin=(PMF_BIN, "2 h"),
                                gap=GAP_DAYS)  # fmt: skip

    # tables and readings
    test_rmse = ip.candidate_test_rmse(X, y, scores, scale=sd, case=case)  # reported, not used
    win_test, _ = embed(z_test, m)  # windows ending at samples m-1 .. T-2
    census_windows = win_test[int(torch.nonzero(t[m - 1 : -1] >= RUL_START).flatten()[0]) :]

    def census(model):  # where the noise-free recursion from each window settles
        end = settle(model, census_windows, ATTRACTOR_STEPS)[:, -1]
        return tables.threshold_census(end, THRESHOLD, verb="settle")

    def listing(key, names, spec):
        return ", ".join(f"{n} {method_mean(rows, n, key):{spec}}" for n in names)

    def order(key, names=METHODS):
        return tables.ascending({n: method_mean(rows, n, key) for n in names}, ".5f")

    def at_paper_times(n):
        return ", ".join(f"{float(res[n].rul_pred[p].mean()):.2f}" for p in paper_idx)

    pf_names, ms_names = [n for n in ALL_METHODS if "PF" in n], [n + MS for n in METHODS]
    lam_all = res["LS-SVR STPF"].filter.fading_factors
    n_tail = int(tail.sum())
    frac = n_tail / truth.shape[0]
    stpf_ms = res["LS-SVR STPF" + MS].filter.fault[day11]  # (steps, R)
    stpf_ms_q = stpf_ms.flatten().quantile(torch.tensor([0.25, 0.5, 0.75], dtype=stpf_ms.dtype))
    zero = point_rul_scores(times, true_rul, torch.zeros_like(true_rul), **rul_kw)
    paper_rul = (f"{n}: " + ", ".join(f"{v:g}" for v in vals) for n, vals in PAPER_RUL.items())
    report = dict(
        rul_zero=", ".join(f"{k} {v:.3f}" for k, v in zip(ip.POINT_RUL_KEYS, zero)),
        table_rul=ip.rul_table(res, case, ALL_METHODS, every=max(1, round(0.5 / RUL_EVERY))),
        table_cv=ip.selection_table(
            scores, dt=dt_step, test_rmse=test_rmse, chosen={"one-step": key_1, "ms": key_ms}
        ),
        paper_rul_times=", ".join(f"{v:g}" for v in PAPER_RUL_TIMES),
        paper_rul="; ".join(paper_rul),
        our_rul_paper_times="; ".join(f"{n}: {at_paper_times(n)}" for n in pf_names),
        true_rul_paper_times=", ".join(f"{float(true_rul[p]):.2f}" for p in paper_idx),
        order_rmse=order("RMSE_1_12"),
        order_rmse_tail=order("RMSE_10_12"),
        order_rmse_ms=order("RMSE_1_12", ms_names),
        order_rmse_tail_ms=order("RMSE_10_12", ms_names),
        filt_rmse=listing("filt_RMSE_1_12", pf_names, ".5f"),
        pf_day11=listing("Pf_day11", pf_names, ".2f"),
        pf_day12=listing("Pf_day12", pf_names, ".2f"),
        stpf_ms_day11_frac=float((stpf_ms > FAULT_DECISION).double().mean()),
        stpf_ms_day11_q=", ".join(f"{float(v):.2f}" for v in stpf_ms_q),
        censored=listing("censored", ALL_METHODS, ".2f"),
        alpha_lambda_met=listing("alpha_lambda", ALL_METHODS, ".0%"),
        cra=listing("CRA", ALL_METHODS, ".2f"),
        fb_total={n: r.filter.prior_fallback for n, r in res.items() if r.filter},
        col_total={n: r.filter.collapsed for n, r in res.items() if r.filter},
        cra_lambdas=", ".join(f"{v:g}" for v in CRA_LAMBDAS),
        features=", ".join(hi.feature_names),
        census_one=census(one.model),
        census_ms=census(ms.model),
    )
    report["quick_note"] = (
        f"- QUICK MODE: the filters start at day {QUICK_START:g} (RMSE_1_12 covers days "
        f"{QUICK_START:g}-12 only), {n_part} particles, {len(scores)} LS-SVR candidates.\n"
        if quick
        else ""
    )
    constants = ("THRESHOLD", "CAP_DAYS", "CV_FOLDS", "TAIL_START", "ALPHA", "LAMBDA", "RUL_EVERY")
    constants += ("SELECT_DAYS", "SELECT_STRIDE", "ATTRACTOR_STEPS", "DEFAULT_RUNS", "N_PARTICLES")
    constants += ("RUL_START",)
    report |= {k: globals()[k] for k in constants}
    report |= dict(t_first=float(times[0]), t_last=float(times[-1]), n_rul=len(case.rul_idx))
    report |= dict(n_snap=z_train.shape[0], t_span=float(t[-1]), n_windows=X.shape[0])
    report |= dict(train_channel=hi.train_channel, test_channel=hi.test_channel, seed=cfg.seed)
    report |= dict(step_noise=one.score.one_step / math.sqrt(2.0), n_predicted=truth.shape[0])
    report |= dict(n_tail=n_tail, frac=frac, rmse_bound=math.sqrt(frac) * 0.4302)
    report |= dict(dt_minutes=dt_step * 1440, n_census=census_windows.shape[0])
    report |= dict(lam_median=float(lam_all.median()), lam_q95=float(lam_all.quantile(0.95)))
    report |= dict(lam_max=float(lam_all.max()))
    report |= dict(sd=sd, diag_txt=diag_txt, scale=scale, t_eol=t_eol, thr_minmax=thr_minmax)
    report |= dict(t_minmax=t_minmax, m=m, q=one.q, n_part=n_part, d0=d0, runs=runs)
    report |= dict(s_one=key_1[0], c_one=key_1[1], sigma_one=one.sigma, q_ms=ms.q)
    report |= dict(s_ms=key_ms[0], c_ms=key_ms[1], sigma_ms=ms.sigma, s_cv=one.score.one_step)
    report |= dict(cross_one=scores[key_1].crossing * dt_step, h_sel=h_sel, cap=case.cap)
    report |= dict(cross_ms=scores[key_ms].crossing * dt_step, n_origins=scores[key_1].origins)
    report["wall"] = time.perf_counter() - t_start
    config = dict(m=m, threshold=THRESHOLD, indicator_scale=scale, t_eol_days=t_eol)
    selection = dict(selection_horizon_steps=h_sel, selection_stride=SELECT_STRIDE)
    config |= dict(lssvr=one.config, lssvr_ms=ms.config | selection)
    config |= dict(chol_Q="q * I", particles=n_part, resample_threshold=RESAMPLE)
    config |= dict(stpf={"rho": 0.95, "beta": 1.0}, rul_times_days=times.tolist())
    config |= dict(cap_steps=case.cap, dt_days=dt_step, accuracy_d0=d0)
    config["quick_start_day"] = QUICK_START if quick else None
    return StudyResult(rows=rows, metrics=METRICS, paper=PAPER, figures=figs, config=config,
                       notes=tables.fill_template(REPORT, report))  # fmt: skip


STUDY = Study(
    name="lssvr-stpf",
    paper="002",
    title="LS-SVR + strong-tracking PF: one-step prediction, fault probability and RUL "
    "(IMS bearing 3)",
    run=run,
    default_runs=DEFAULT_RUNS,
)
