"""Paper 002 study: LS-SVR + strong-tracking particle filter on the IMS bearing health indicator.

Protocol (paper 002, Sec. "Experiments and results", Table 1, Table 2, Fig. 8-13), as far as the
data allow (every reading is listed in ``table.md``; its captions and readings are the
template ``lssvr_stpf.md``):

* health indicator (:func:`~prognos_torch.datasets.health_indicator`): bearing 3 of IMS test 1,
  six time-domain features (the shipped table has no median), LLE with 12 neighbours, last 12
  days; channel 5 trains the predictor, channel 6 tests it. The LLE coordinate is brought to the
  paper's scale (the unit-norm eigenvector, ``y / sqrt(N)``), on which the failure threshold 0.1
  is first reached on the test channel at about day 11, as the paper states;
* LS-SVR of fourth order (embedding ``m = 4``, Gaussian kernel, Eq. 1-14), width and
  regularisation chosen on the training channel in two ways, each run through the whole
  protocol: by blocked 5-fold cross-validation of the one-step error (the paper's rows), and,
  beyond the paper, by the time-to-cross error of the recursive prediction on the same folds
  (:func:`~prognos_torch.learners.blocked_multistep_cv`; rows marked ``(ms)``);
* four one-step predictors on the test channel: the LS-SVR alone (Eq. 12 on the measured
  window), and LS-SVR PF (SIR), LS-SVR EKPF and LS-SVR STPF (Eq. 27, steps 1-7) with the LS-SVR
  as the m-order transition model (:func:`~prognos_torch.prognosis.learner_transition_model`,
  Eq. 15-26); one-step RMSE over days 1-12 and 10-12 (Table 1, Fig. 8-9; days are counted from 1 as
  in the paper, so days 10-12 are ``t in [9, 12)`` and the 11th day is ``t in [10, 11)``);
* fault probability per step, ``fault(1, k) = sum_i w_k^i I(x_{k+1|k}^i >= 0.1)``
  (Fig. 10), and per-day box plots;
* RUL every 0.1 d from the ninth day (``t = 8``): particle paths with frozen weights run
  until every particle reaches the threshold or a 15-day cap
  (:func:`~prognos_torch.prognosis.simulate_to_event`), first passage, RUL pmf and its
  expectation (Eq. 28), Fig. 11-13; accuracy, RMSE, alpha-lambda (alpha = 0.3, lambda = 0.5) and CRA (lambda = 0,
  0.25, 0.5, 0.75) of the RUL predictions (Table 2).

Monte Carlo runs differ in the particle-filter seed only (the indicator and the LS-SVR are
deterministic); the runs are one batched pass through the filters' batch dimension, each
predicting one step ahead before it assimilates a sample
(:func:`~prognos_torch.prognosis.rolling_particle_prediction`).
"""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from prognos_torch.datasets import MinMaxScaler, embed, health_indicator
from prognos_torch.filters import ekpf, sir, stpf
from prognos_torch.learners import LSSVR, LSSVRGram, blocked_multistep_cv
from prognos_torch.metrics import first_crossing_time, point_rul_scores, rmse
from prognos_torch.plots import (
    LinePanel,
    plot_alpha_lambda,
    plot_fault_probability,
    plot_fault_probability_box,
    plot_line_panels,
    plot_rul_pdf,
)
from prognos_torch.prognosis import (
    last_sample_indices,
    learner_transition_model,
    rolling_particle_prediction,
    settle,
    simulate_to_event,
    window_belief,
)
from prognos_torch.studies import (
    Study,
    StudyConfig,
    StudyResult,
    ascending,
    fill_template,
    method_mean,
    run_rows,
    threshold_census,
)
from prognos_torch.studies import markdown_table as md

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


# --------------------------------------------------------------------------- data and learner
def _indicator(dev):
    """The health indicator on the paper's scale (unit-norm LLE eigenvector) and its time axis."""
    hi = health_indicator()  # bearing 3, channels 5 -> 6, six features, K = 12, last 12 days
    n = hi.train.shape[0]
    # health_indicator scales the LLE coordinate to (1/N) sum y^2 = 1 (Roweis & Saul);
    # the unit-norm eigenvector (eigs, scikit-learn) is y / sqrt(N).
    scale = math.sqrt(n)
    return hi, scale, (hi.train / scale).to(dev), (hi.test / scale).to(dev), hi.elapsed.to(dev)


def _fit(X, y, sigma: float, C: float, dev) -> LSSVR:
    return LSSVR(kernel="rbf", sigma=sigma, C=C).to(dev).fit(X, y)


def _fitter(sigma: float, C: float, dev):
    """``fit(X, y) -> predict`` for the blocked cross-validation (evaluated by LSSVRGram)."""

    def fit(X, y):
        g = LSSVRGram(_fit(X, y, sigma, C, dev))
        return lambda Xh: g(Xh)[:, 0]

    return fit


RUL_KEYS = ("Accuracy", "RUL_RMSE", "alpha_lambda", "CRA")  # metrics.PointRULScores, Table 2


# --------------------------------------------------------------------------- filtering
def _filter_pass(pf, model, z_test, k0, runs, gen, keep):
    """One particle filter over ``z_test[k0:]`` in ``runs`` batched runs, predicting each
    sample one step ahead before it is assimilated (the library's rolling prediction)."""
    m, ys = M_ORDER, z_test[k0:]
    r = float(model.noise(1).chol_R[0, 0])
    b0 = window_belief(z_test, k0, m, r, runs)  # the measured window before z_test[k0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rp = rolling_particle_prediction(
            pf,
            model,
            b0,
            ys[:, None, None].expand(-1, runs, 1),
            generator=gen,
            threshold=THRESHOLD,
            k0=k0 - 1,
            keep=keep,
        )
    out = {
        "pred": rp.mean[..., 0],
        "fault": rp.fault_probability[..., 0],
        "filt": rp.filtered[..., -1],
        "ess": rp.ess,
        "lam": rp.fading_factors,
        "fallback": int(rp.prior_fallback.sum()),
        "collapsed": int(rp.collapsed.sum()),
    }
    parts = torch.stack([rp.states[i].particles for i in keep])  # (P, R, N, m)
    weights = torch.stack([rp.states[i].weights for i in keep])  # (P, R, N)
    return out, parts, weights


# --------------------------------------------------------------------------- figures
def _figures(out_dir: Path, c: SimpleNamespace) -> list[str]:
    """Fig. 1 and 8-13 in the paper's style (run 0) from the run's results ``c``; returns the
    file names."""
    plot_line_panels(
        out_dir / "fig1_indicator.png",
        c.t,
        [
            LinePanel(
                {
                    f"training, channel {c.hi.train_channel}": c.z_train,
                    f"test, channel {c.hi.test_channel}": c.z_test,
                },
                title="Health indicator of bearing 3 (LLE of six features, unit-norm scale)",
                ylabel="LLE health indicator",
                hline=THRESHOLD,
                vline=c.t_eol,
                gap=GAP_DAYS,
                vline_label=f"test crosses at {c.t_eol:.2f} d",
                legend="upper left",
            )
        ],
        xlabel="time (days, last 12 days of test 1)",
        lw=0.7,
    )
    one_step = [
        LinePanel(
            {"one-step prediction": p},
            title=f"({'abcd'[i]}) {name}",
            truth=c.truth,
            truth_label="test indicator",
            hline=THRESHOLD,
            gap=GAP_DAYS,
            legend="upper left" if i == 0 else None,
        )
        for i, (name, p) in enumerate(c.preds0.items())
    ]
    plot_line_panels(
        out_dir / "fig8_one_step.png",
        c.t_tgt,
        one_step,
        ncols=2,
        lw=0.7,
        xlabel="time (days)",
        figsize=(8.0, 7.0),
    )
    err = {n: (p - c.truth).abs() for n, p in c.preds0.items()}
    tail = c.t_tgt >= TAIL_START
    plot_line_panels(
        out_dir / "fig9_abs_error.png",
        c.t_tgt,
        [
            LinePanel(
                err,
                title="(a) absolute one-step error, days 1-12 (run 0)",
                ylabel="|error|",
                gap=GAP_DAYS,
                legend="upper left",
            ),
            LinePanel(
                {n: e[tail] for n, e in err.items()},
                x=c.t_tgt[tail],
                style=".-",
                gap=GAP_DAYS,
                title=f"(b) absolute one-step error, days {TAIL_START:g}-12 (run 0)",
                ylabel="|error|",
                legend="upper left",
            ),
        ],
        xlabel="time (days)",
        lw=0.7,
        figsize=(8.0, 5.5),
    )
    figs = ["fig1_indicator.png", "fig8_one_step.png", "fig9_abs_error.png"]
    for name, out in c.res.items():
        fn, fb, fr = (
            f"fig{k}_{SHORT[name]}.png"
            for k in ("10_fault_probability", "10_fault_probability_box", "12_rul_pdf")
        )
        plot_fault_probability(
            out_dir / fn,
            c.t_tgt,
            {name: out["fault"][:, 0]},
            decision=FAULT_DECISION,
            title=f"{name}: fault probability per step (threshold {THRESHOLD:g}, run 0)",
        )
        plot_fault_probability_box(
            out_dir / fb,
            c.t_tgt,
            out["fault"][:, 0],
            period=1.0,
            decision=FAULT_DECISION,
            title=f"{name}: fault probability per day (run 0)",
        )
        # display only: mean pmf over the runs in bins of PMF_BIN steps (2 h), at the paper's
        # prediction times (Fig. 12)
        d, sel = c.dists[name], c.paper_idx
        support, pmf = d.binned(PMF_BIN)
        plot_rul_pdf(
            out_dir / fr,
            [round(v, 2) for v in c.times[sel].tolist()],
            support,
            pmf[sel].mean(1),
            true_rul=c.true_rul[sel],
            censored_mass=d.censored_mass[sel].mean(1),
            title=f"{name}: RUL pmf (mean of {c.runs} runs, 2 h bins, cap {CAP_DAYS:g} d)",
        )
        figs += [fn, fb, fr]
    for name, pred in c.rul_pred.items():
        fa = f"fig13_alpha_lambda_{SHORT[name]}.png"
        kind = "deterministic" if "PF" not in name else f"bars: range over {c.runs} runs"
        plot_alpha_lambda(
            out_dir / fa,
            c.times,
            c.true_rul,
            pred[:, 0],
            alpha=ALPHA,
            lower=pred.min(-1).values,
            upper=pred.max(-1).values,
            lam=LAMBDA,
            t_eol=c.t_eol,
            title=f"{name}: RUL (Eq. 28); {kind}",
        )
        figs.append(fa)
    return figs


# --------------------------------------------------------------------------- one protocol
def _event(x):  # the indicator (newest window element) has reached the threshold
    return x[..., -1] >= THRESHOLD


def _protocol(ctx, key, score, suffix, offset, cfg, dev):
    """LS-SVR (sigma = key[0] x std, C = key[1]) and the three particle filters through the
    whole protocol; rows are labelled ``name + suffix``."""
    m, runs, n_part = M_ORDER, ctx.runs, ctx.n_part
    sigma, C = key[0] * ctx.sd, key[1]
    learner = LSSVRGram(_fit(ctx.X, ctx.y, sigma, C, dev))  # Eq. 8 / Eq. 25 by matrix products
    # Process and measurement noise (the paper gives neither): the out-of-fold one-step
    # residual variance s^2 of the selected LS-SVR, split equally, q^2 = r^2 = s^2 / 2, on
    # every window element (see notes).
    q = r = score.one_step / math.sqrt(2.0)
    chol_Q = q * torch.eye(m, dtype=ctx.X.dtype, device=dev)
    model = learner_transition_model(learner, m, chol_Q, r, jacobian="input_gradient")
    # LS-SVR alone: one step from the measured window, RUL by the noise-free recursion
    t0 = time.perf_counter()
    with torch.no_grad():
        ls_pred = learner(ctx.win_test[ctx.k0 - m :])[:, 0]  # predictions of y_{k0..T-1}
    ev = simulate_to_event(
        model, ctx.windows[:, None], _event, max_steps=ctx.cap, dt=ctx.dt, active_only=True
    )
    dists, rul_pred = {"LS-SVR": ev.rul}, {"LS-SVR": ev.rul.restricted_mean.unsqueeze(-1)}
    secs = {"LS-SVR": time.perf_counter() - t0}
    filters = {
        "LS-SVR PF": sir(n_part, resample_threshold=RESAMPLE),
        "LS-SVR EKPF": ekpf(n_part, resample_threshold=RESAMPLE),
        "LS-SVR STPF": stpf(n_part, resample_threshold=RESAMPLE),
    }
    res = {}
    for i, (name, pf) in enumerate(filters.items()):
        gen = torch.Generator(device=dev).manual_seed(cfg.seed + 1000 * (i + offset))
        t0 = time.perf_counter()
        res[name], parts, weights = _filter_pass(
            pf, model, ctx.z_test, ctx.k0, runs, gen, ctx.rul_idx
        )
        ev = simulate_to_event(
            model,
            parts,
            _event,
            max_steps=ctx.cap,
            weights=weights,
            dt=ctx.dt,
            process_noise=True,
            generator=gen,
            active_only=True,
        )  # until every particle crosses, or the cap
        dists[name], rul_pred[name] = ev.rul, ev.rul.restricted_mean  # (P, R)
        secs[name] = (time.perf_counter() - t0) / runs

    def rul_rows(pred):  # Table 2 metrics of each run's point RULs (P, R)
        scores = [
            point_rul_scores(ctx.times, ctx.true_rul, pred[:, i], **ctx.rul_kw)
            for i in range(pred.shape[1])
        ]
        return {k: [sc[j] for sc in scores] for j, k in enumerate(RUL_KEYS)}

    tail, truth = ctx.tail, ctx.truth
    rows = run_rows(
        "LS-SVR" + suffix,
        {
            "RMSE_1_12": float(rmse(ls_pred, truth)),
            "RMSE_10_12": float(rmse(ls_pred[tail], truth[tail])),
        }
        | rul_rows(rul_pred["LS-SVR"])
        | {"censored": float(dists["LS-SVR"].censored_mass.mean()), "time_s": secs["LS-SVR"]},
    )
    for name, out in res.items():
        tt = truth.unsqueeze(-1).expand_as(out["pred"])
        rows += run_rows(
            name + suffix,
            {
                "RMSE_1_12": rmse(out["pred"], tt, dim=0),
                "RMSE_10_12": rmse(out["pred"][tail], tt[tail], dim=0),
                "filt_RMSE_1_12": rmse(out["filt"], tt, dim=0),
                "filt_RMSE_10_12": rmse(out["filt"][tail], tt[tail], dim=0),
                "Pf_day11": out["fault"][ctx.day11].mean(0),
                "Pf_day12": out["fault"][ctx.t_tgt >= DAY11[1]].mean(0),
            }
            | rul_rows(rul_pred[name])
            | {
                "censored": dists[name].censored_mass.mean(0),
                "ess": out["ess"].mean(0),
                "time_s": secs[name],
            },
        )
    tag = lambda d: {n + suffix: v for n, v in d.items()}  # noqa: E731
    return SimpleNamespace(
        rows=rows,
        learner=learner,
        model=model,
        q=q,
        sigma=sigma,
        C=C,
        score=score,
        preds0={"LS-SVR": ls_pred} | {n: o["pred"][:, 0] for n, o in res.items()},
        res=tag(res),
        dists=tag(dists),
        rul_pred=tag(rul_pred),
    )


# --------------------------------------------------------------------------- the study
def run(cfg: StudyConfig, out_dir: Path) -> StudyResult:
    quick = cfg.quick
    dev = torch.device(cfg.device)
    m = M_ORDER
    t_start = time.perf_counter()
    ctx = SimpleNamespace(runs=cfg.runs or (2 if quick else DEFAULT_RUNS))
    ctx.n_part = 20 if quick else N_PARTICLES

    # ------------------------------------------------------------ indicator and threshold
    hi, scale, z_train, z_test, t = _indicator(dev)
    t_eol = first_crossing_time(t, z_test, THRESHOLD)  # end of life: test indicator reaches 0.1
    dt_step = float(torch.diff(t).median())  # nominal sampling interval (10 min), days
    mm = MinMaxScaler().fit(z_train)
    thr_minmax = float(mm.inverse_transform(torch.tensor(THRESHOLD, dtype=z_train.dtype)))
    t_minmax = first_crossing_time(t, z_test, thr_minmax)

    # ------------------------------------------------------------ LS-SVR selection (training channel)
    X, y = embed(z_train, m)
    sd = float(z_train.std())
    sig_grid = (3.0, 30.0) if quick else SIGMA_GRID
    c_grid = (1e3, 1e4) if quick else C_GRID
    h_sel = int(round(SELECT_DAYS / dt_step))
    scores = {
        (s, C): blocked_multistep_cv(
            _fitter(s * sd, C, dev),
            z_train,
            m,
            h_sel,
            CV_FOLDS,
            threshold=THRESHOLD,
            stride=SELECT_STRIDE,
        )
        for s in sig_grid
        for C in c_grid
    }
    key_1 = min(scores, key=lambda k: scores[k].one_step)  # the paper's rows
    key_ms = min(scores, key=lambda k: scores[k].crossing)  # beyond the paper: (ms) rows

    # ------------------------------------------------------------ time indices
    k0 = m
    if quick:  # reduced protocol: filter from day QUICK_START on
        k0 = max(m, int(torch.nonzero(t >= QUICK_START).flatten()[0]))
    t_tgt = t[k0:]  # times of the predicted samples y_{k0+1..T} (0-based index k0..T-1)
    # the last sample at or before each nominal prediction time, each sample once
    rul_idx = last_sample_indices(t, np.arange(RUL_START, t_eol, RUL_EVERY), first=k0)
    times = t[rul_idx].to(torch.float64)
    true_rul = t_eol - times
    win_test, _ = embed(z_test, m)  # windows ending at samples m-1 .. T-2
    ctx.__dict__.update(X=X, y=y, sd=sd, z_test=z_test, win_test=win_test, k0=k0, t_tgt=t_tgt)
    ctx.__dict__.update(truth=z_test[k0:], tail=t_tgt >= TAIL_START, rul_idx=rul_idx, dt=dt_step)
    ctx.__dict__.update(day11=(t_tgt >= DAY11[0]) & (t_tgt < DAY11[1]), times=times)
    ctx.__dict__.update(true_rul=true_rul, cap=int(round(CAP_DAYS / dt_step)))
    ctx.windows = torch.stack([z_test[i - m + 1 : i + 1] for i in rul_idx])  # (P, m)
    d0 = float(true_rul[0])  # accuracy normaliser: the true RUL at the first prediction
    ctx.rul_kw = dict(t_eol=t_eol, d0=d0, alpha=ALPHA, lam=LAMBDA, cra_lambdas=CRA_LAMBDAS)

    # ------------------------------------------------------------ both protocols
    one = _protocol(ctx, key_1, scores[key_1], "", 0, cfg, dev)
    ms = _protocol(ctx, key_ms, scores[key_ms], MS, 3, cfg, dev)
    rows = one.rows + ms.rows
    res, dists, rul_pred = one.res | ms.res, one.dists | ms.dists, one.rul_pred | ms.rul_pred

    # ------------------------------------------------------------ proposal-structure diagnostic
    q, r, n_part, runs = one.q, one.q, ctx.n_part, ctx.runs
    diag_txt = "(diagnostic skipped in quick mode)"
    if not quick:
        model_j = learner_transition_model(
            one.learner, m, q, r, jacobian="input_gradient", shift_std=JITTER_DIAG * q
        )
        steps = 200
        gen = torch.Generator(device=dev).manual_seed(cfg.seed)
        pf_j = ekpf(n_part, resample_threshold=RESAMPLE)
        out_j, _, _ = _filter_pass(pf_j, model_j, z_test[: m + steps], m, 1, gen, [m + steps - 1])
        ess_uni = float(res["LS-SVR EKPF"]["ess"][:steps].mean())
        j = f"{JITTER_DIAG:g} q"
        diag_txt = (
            f"EKPF over the first {steps} steps (1 run, {n_part} particles): mean ESS "
            f"{float(out_j['ess'].mean()):.1f} with Q = diag({j}, {j}, {j}, q) against "
            f"{ess_uni:.1f} with Q = q^2 I."
        )

    # ------------------------------------------------------------ figures (run 0)
    paper_idx = [int((times - v).abs().argmin()) for v in PAPER_RUL_TIMES if times[0] <= v]
    c = SimpleNamespace(hi=hi, t=t, z_train=z_train, z_test=z_test, t_eol=t_eol, t_tgt=t_tgt)
    c.__dict__.update(truth=ctx.truth, preds0=one.preds0, res=res, dists=dists)
    c.__dict__.update(rul_pred=rul_pred, times=times, true_rul=true_rul, runs=runs)
    c.paper_idx = paper_idx
    figs = _figures(out_dir, c)

    # ------------------------------------------------------------ tables
    every = max(1, int(round(0.5 / RUL_EVERY)))
    table_rul = [
        [f"{float(times[p]):.3f}", f"{float(true_rul[p]):.3f}"]
        + [f"{float(rul_pred[n][p].mean()):.3f}" for n in ALL_METHODS]
        for p in range(0, len(rul_idx), every)
    ]
    table_cv = []
    with torch.no_grad():
        for (s, C), sc in scores.items():
            lr = LSSVRGram(_fit(X, y, s * sd, C, dev))
            te_rmse = float(rmse(lr(win_test[k0 - m :])[:, 0], ctx.truth))
            mark = " **(one-step)**" if (s, C) == key_1 else ""
            mark += " **(ms)**" if (s, C) == key_ms else ""
            table_cv.append(
                [
                    f"{s:g}{mark}",
                    f"{C:g}",
                    f"{sc.one_step:.5f}",
                    f"{sc.multi_step:.5f}",
                    f"{sc.crossing * dt_step:.3f}",
                    f"{te_rmse:.5f}",
                ]
            )
    head_cv = [
        "sigma / std",
        "C",
        "one-step CV RMSE",
        "multi-step CV RMSE",
        "time-to-cross CV RMSE (d)",
        "test one-step RMSE (reported only)",
    ]
    census_windows = win_test[int(torch.nonzero(t[m - 1 : -1] >= RUL_START).flatten()[0]) :]

    def census(model):  # where the noise-free recursion from each window settles
        end = settle(model, census_windows, ATTRACTOR_STEPS)[:, -1]
        return threshold_census(end, THRESHOLD, verb="settle")

    # ------------------------------------------------------------ readings
    def listing(key, names, spec):
        return ", ".join(f"{n} {method_mean(rows, n, key):{spec}}" for n in names)

    def order(key, names=METHODS):
        return ascending({n: method_mean(rows, n, key) for n in names}, ".5f")

    pf_names = [n for n in ALL_METHODS if "PF" in n]
    lam_all = res["LS-SVR STPF"]["lam"]
    n_tail = int(ctx.tail.sum())
    frac = n_tail / ctx.truth.shape[0]
    stpf_ms = res["LS-SVR STPF" + MS]["fault"][ctx.day11]  # (steps, R)
    zero = point_rul_scores(times, true_rul, torch.zeros_like(true_rul), **ctx.rul_kw)
    report = {
        "rul_zero": ", ".join(f"{k} {v:.3f}" for k, v in zip(RUL_KEYS, zero)),
        "table_rul": md(["prediction time (d)", "true RUL (d)", *ALL_METHODS], table_rul),
        "table_cv": md(head_cv, table_cv),
        "paper_rul_times": ", ".join(f"{v:g}" for v in PAPER_RUL_TIMES),
        "paper_rul": "; ".join(
            f"{n}: " + ", ".join(f"{v:g}" for v in vals) for n, vals in PAPER_RUL.items()
        ),
        "our_rul_paper_times": "; ".join(
            f"{n}: " + ", ".join(f"{float(rul_pred[n][p].mean()):.2f}" for p in paper_idx)
            for n in pf_names
        ),
        "true_rul_paper_times": ", ".join(f"{float(true_rul[p]):.2f}" for p in paper_idx),
        "order_rmse": order("RMSE_1_12"),
        "order_rmse_tail": order("RMSE_10_12"),
        "order_rmse_ms": order("RMSE_1_12", [n + MS for n in METHODS]),
        "order_rmse_tail_ms": order("RMSE_10_12", [n + MS for n in METHODS]),
        "filt_rmse": listing("filt_RMSE_1_12", pf_names, ".5f"),
        "pf_day11": listing("Pf_day11", pf_names, ".2f"),
        "pf_day12": listing("Pf_day12", pf_names, ".2f"),
        "stpf_ms_day11_frac": float((stpf_ms > FAULT_DECISION).double().mean()),
        "stpf_ms_day11_q": ", ".join(
            f"{float(v):.2f}"
            for v in stpf_ms.flatten().quantile(
                torch.tensor([0.25, 0.5, 0.75], dtype=stpf_ms.dtype)
            )
        ),
        "censored": listing("censored", ALL_METHODS, ".2f"),
        "alpha_lambda_met": listing("alpha_lambda", ALL_METHODS, ".0%"),
        "cra": listing("CRA", ALL_METHODS, ".2f"),
        "t_first": float(times[0]),
        "t_last": float(times[-1]),
        "n_rul": len(rul_idx),
        "features": ", ".join(hi.feature_names),
        "n_snap": z_train.shape[0],
        "t_span": float(t[-1]),
        "train_channel": hi.train_channel,
        "test_channel": hi.test_channel,
        "n_windows": X.shape[0],
        "step_noise": one.score.one_step / math.sqrt(2.0),
        "n_predicted": ctx.truth.shape[0],
        "n_tail": n_tail,
        "frac": frac,
        "rmse_bound": math.sqrt(frac) * 0.4302,
        "dt_minutes": dt_step * 1440,
        "census_one": census(one.model),
        "census_ms": census(ms.model),
        "n_census": census_windows.shape[0],
        "fb_total": {n: o["fallback"] for n, o in res.items()},
        "col_total": {n: o["collapsed"] for n, o in res.items()},
        "cra_lambdas": ", ".join(f"{v:g}" for v in CRA_LAMBDAS),
        "lam_median": float(lam_all.median()),
        "lam_q95": float(lam_all.quantile(0.95)),
        "lam_max": float(lam_all.max()),
        "seed": cfg.seed,
        "quick_note": (
            f"- QUICK MODE: the filters start at day {QUICK_START:g} (RMSE_1_12 covers days "
            f"{QUICK_START:g}-12 only), {n_part} particles, {len(scores)} LS-SVR candidates.\n"
        )
        if quick
        else "",
    }
    constants = ("THRESHOLD", "CAP_DAYS", "CV_FOLDS", "TAIL_START", "ALPHA", "LAMBDA", "RUL_EVERY")
    constants += ("SELECT_DAYS", "SELECT_STRIDE", "ATTRACTOR_STEPS", "DEFAULT_RUNS", "N_PARTICLES")
    constants += ("RUL_START",)
    report |= {k: globals()[k] for k in constants}
    report |= dict(sd=sd, diag_txt=diag_txt, scale=scale, t_eol=t_eol, thr_minmax=thr_minmax)
    report |= dict(t_minmax=t_minmax, m=m, q=q, n_part=n_part, d0=d0, runs=runs)
    report |= dict(s_one=key_1[0], c_one=key_1[1], sigma_one=one.sigma, q_ms=ms.q)
    report |= dict(s_ms=key_ms[0], c_ms=key_ms[1], sigma_ms=ms.sigma, s_cv=one.score.one_step)
    report |= dict(cross_one=scores[key_1].crossing * dt_step, h_sel=h_sel, cap=ctx.cap)
    report |= dict(cross_ms=scores[key_ms].crossing * dt_step, n_origins=scores[key_1].origins)
    report["wall"] = time.perf_counter() - t_start
    sel = lambda o: {
        "sigma": o.sigma,
        "C": o.C,
        "cv_rmse": o.score.one_step,  # noqa: E731
        "crossing_rmse_steps": o.score.crossing,
        "q": o.q,
        "r": o.q,
    }
    return StudyResult(
        rows=rows,
        metrics=METRICS,
        paper=PAPER,
        figures=figs,
        config={
            "m": m,
            "threshold": THRESHOLD,
            "indicator_scale": scale,
            "t_eol_days": t_eol,
            "lssvr": {"kernel": "rbf", **sel(one)},
            "lssvr_ms": {
                "kernel": "rbf",
                **sel(ms),
                "selection_horizon_steps": h_sel,
                "selection_stride": SELECT_STRIDE,
            },
            "chol_Q": "q * I",
            "particles": n_part,
            "resample_threshold": RESAMPLE,
            "stpf": {"rho": 0.95, "beta": 1.0},
            "rul_times_days": times.tolist(),
            "cap_steps": ctx.cap,
            "dt_days": dt_step,
            "accuracy_d0": d0,
            "quick_start_day": QUICK_START if quick else None,
        },
        notes=fill_template(REPORT, report),
    )


STUDY = Study(
    name="lssvr-stpf",
    paper="002",
    title="LS-SVR + strong-tracking PF: one-step prediction, fault probability and RUL "
    "(IMS bearing 3)",
    run=run,
    default_runs=DEFAULT_RUNS,
)
