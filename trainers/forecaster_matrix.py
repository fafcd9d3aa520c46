"""Forecaster matrix: which learner x trainer x prognostic filter to pick (papers 002 and 003).

Protocol, on two series (values min-max scaled to [0, 1], errors in those units):

* **HI**: paper 002's IMS bearing health indicator
  (:func:`~prognos_torch.datasets.health_indicator`, bearing 3, last 12 days, LLE of the time
  features): learners trained on all of channel 5 (1,263 snapshots), tested on days 8-12 of
  channel 6 (the degradation phase, 356 snapshots; the time budget does not allow the particle
  filters on all 12 days); scaled with the training channel's min/max. Embedding ``m = 4``
  (paper 002's fourth-order model).
* **CSTR**: paper 003's C_A series (:func:`~prognos_torch.systems.cstr.simulate_cstr`, the
  reading of docs/systems.md: 200 steps of 0.02 min, feed drift of Eq. 51 from k = 50,
  measurement noise std 1e-4 mol/L; the whole series min-max scaled as in the paper), first 100
  values for training, last 100 for testing. Embedding ``m = 3`` (paper 003).

Every learner (ELM, LS-SVR, ANFIS) is trained as a one-step forecaster
``x_{k+1} = f(x_{k-m+1..k})`` (:func:`~prognos_torch.datasets.embed`) by every trainer that
applies: the closed form (ELM ridge, LS-SVR KKT system), the Kalman optimisers EKF / SRUKF /
ImSRUKF (:class:`~prognos_torch.optim.KalmanOptimizer`, one pass) and Adam
(:func:`~prognos_torch.optim.fit`). ANFIS has no closed form; the LS-SVR Kalman state
``(alpha, b)`` (prior mean: the KKT solution) is too large on the bearing: both are marked n/a.
Each trained forecaster is then used

* alone ("none"): one-step predictions from the measured windows and recursive multi-step
  prediction (:func:`~prognos_torch.prognosis.recursive_predict`);
* as the transition model of a prognostic filter
  (:func:`~prognos_torch.prognosis.learner_transition_model`): particle filters SIR
  ("PF"), EKPF and STPF, Gaussian SCKF and STSCKF, run over the test measurements; the one-step
  prediction is the filter's predictive mean of the next measurement, the multi-step one
  :func:`~prognos_torch.prognosis.gaussian_paths` /
  :func:`~prognos_torch.prognosis.particle_paths` from the posterior.

Metrics per run: one-step RMSE/MAE on the test part, RMSE/MAE of the ``H = 10``-step-ahead
prediction (origins every ``STRIDE`` steps), and on the bearing the RUL at a few prediction
times: sample paths (particles, draws from the Gaussian belief, or the deterministic recursion)
until they cross the failure threshold (:func:`~prognos_torch.prognosis.rul_distribution`),
against the observed first crossing of the test indicator; alpha-lambda (alpha = 0.3,
lambda = 0.5, mass criterion beta = 0.5, :func:`~prognos_torch.metrics.alpha_lambda`).
A persistence forecaster ``x_{k+1} = x_k`` is the reference row.

Monte Carlo: run ``i`` draws its learner initialisation (ELM hidden layer, ANFIS consequents)
from ``cfg.generator(i)``; the runs are trained batched where the optimiser allows (ANFIS Kalman
runs, all Adam runs) and filtered as one batch (runs leading, particles after them), with one
generator per (series, filter) shared by all combinations (common random numbers). LS-SVR and
its trainers are deterministic: it is evaluated on ``SHARED_RUNS`` runs that differ only in the
particle draws. Quick mode runs a reduced matrix: every (learner, trainer) alone, every filter
with one trainer per learner. The matrix is run by
:func:`~prognos_torch.studies.run_forecaster_matrix` (evaluation:
:mod:`prognos_torch.studies.forecasters`); the readings in ``table.md`` are the template
``forecaster_matrix.md`` filled with the run's numbers.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch import Tensor

from prognos_torch import filters, plots, studies
from prognos_torch.datasets import MinMaxScaler, embed, health_indicator, minmax_normalize
from prognos_torch.learners import ANFIS, ELM, LSSVR, LSSVRGram
from prognos_torch.optim import KalmanOptimizer, StackedLearner, fit, fit_kalman_runs, fit_together
from prognos_torch.plots import HeatmapPanel
from prognos_torch.studies import ForecastProblem, Study, StudyConfig, StudyResult
from prognos_torch.systems.cstr import simulate_cstr

# ----------------------------------------------------------------------------------- settings
LEARNERS = ("ELM", "LSSVR", "ANFIS")
TRAINERS = ("closed", "EKF", "SRUKF", "ImSRUKF", "Adam")
FILTERS = ("none", "PF", "EKPF", "STPF", "SCKF", "STSCKF")
EMBED = {"HI": 4, "CSTR": 3}  # paper 002 (fourth-order model), paper 003 (m = 3)

ELM_HIDDEN, ELM_LAM = 20, 1e-4  # sigmoid nodes, ridge parameter (paper 000 Eq. 52-54)
LSSVR_SIGMA, LSSVR_C = 1.0, 100.0  # RBF width (paper 002 Eq. 24) and regularisation (Eq. 1)
ANFIS_MFS = 2  # sigmoid MFs per input: 16 rules for m = 4, 8 for m = 3 (paper 003)
# Kalman optimisers, one pass, R = 1e-3. ANFIS: paper 003's settings (tests/test_optim.py,
# Lorenz): prior variances per parameter group, Q = 1e-6. ELM and LS-SVR enter linearly through
# static weights: Q = 0, so that a pass gives the exact Gaussian posterior; the ELM prior
# variance R / lambda makes the EKF posterior mean the ridge solution, the LS-SVR state
# (alpha, b) starts at the KKT solution. (With Q = 1e-6 the last samples overwrote these
# cancelling weights: HI test RMSE (all 12 days) 0.024 -> 0.12-0.17 for ELM-EKF in our trials.)
KF_R = 1e-3
KF_Q = {"ELM": 0.0, "LSSVR": 0.0, "ANFIS": 1e-6}
P0 = {
    "ELM": {"beta": KF_R / ELM_LAM},
    "ANFIS": {"alpha": 1.0, "b": 1e-2, "beta": 1e-4},
    "LSSVR": {"alpha": 1.0, "b": 1e-2},
}
# Samples per Kalman step: one on the CSTR (97 steps, paper 003); 8 on the bearing (157 steps
# instead of 1,259: in our trials 4x faster and, with Q = 1e-6, more accurate for ANFIS-EKF,
# test RMSE 0.034 against 0.043 with one sample per step, all 12 test days).
KF_BATCH = {"HI": 8, "CSTR": 1}
# Adam: learning rate from {1e-3, 3e-3, 1e-2, 3e-2} on a hold-out (the last 20 % of the
# training windows): 3e-2 was the best or within 20 % of the best for every learner and series
ADAM_LR = 3e-2
ADAM = {"HI": (20, 32), "CSTR": (100, 8)}  # (epochs, batch size)
# The LS-SVR state has one dual weight per training window: 1,260 entries on the bearing; one
# EKF step would factorise a 1260 x 1260 square root, one SRUKF step evaluate 2,521 sigma
# points against 1,259 support vectors.
LSSVR_KALMAN_MAX = 200
# LS-SVR and its trainers are deterministic (no random initialisation): its runs differ only in
# the particle draws, so it is evaluated on this many runs (its inference, 1,259 kernel terms per
# window on the bearing, is the most expensive of the three learners).
SHARED_RUNS = 3
DIVERGED_RMSE = 1.0  # training one-step RMSE above which a run counts as diverged

N_PARTICLES = 200
H_MULTI = 10  # multi-step horizon
STRIDE = {"HI": 10, "CSTR": 5}  # spacing of the multi-step origins
# Filter noise from the learner's one-step training residual RMS s (mean over runs): the
# residual variance is split into measurement and process noise, R = 0.75 s^2 and Q = 0.25 s^2
# on the newest window element; the shifted elements get std q / 2 (not 0) so that the
# Gaussian-proposal particle filters (EKPF, STPF), whose weights contain p(x_k | x_{k-1}),
# do not degenerate.
R_SHARE, SHIFT_STD = 0.75, 0.5

# Bearing: the filters and all errors cover days 8-12 of the test channel (the degradation
# phase, 356 snapshots; the learners still train on all 12 days of channel 5).
HI_TEST_FROM_DAY = 8.0
# RUL: failure threshold 2.5 in indicator units, above every test value before the jump on
# day 11 (observed first crossing 10.99 d); paper 002 uses 0.1 on its own, differently scaled
# index, "about the 11th day".
HI_THRESHOLD = 2.5
RUL_DAYS = (9.5, 10.0, 10.5)  # prediction times, days since the window start
RUL_ALPHA, RUL_LAMBDA, RUL_BETA = 0.3, 0.5, 0.5
RUL_HORIZON = 240  # steps of the nominal 10-minute spacing (1.67 d > the longest true RUL)
RUL_PATHS = 50  # sample paths per run and prediction time
DT_DAYS = 10.0 / (24 * 60)

NA_REASONS = {
    "ANFIS-closed": "no closed form: the premise parameters enter nonlinearly",
    "LSSVR-Kalman": (
        "state (alpha, b) of 1,260 entries on the bearing (one per training window): beyond "
        "the time budget"
    ),
}

METRICS = [
    "RMSE_1",
    "MAE_1",
    "RMSE_10",
    "MAE_10",
    "RUL_MAE_d",
    "RUL_bias_d",
    "RUL_censored",
    "AL_mass",
    "alpha_lambda",
    "time_s",
]


# Quick mode (a reduced matrix): every learner with every trainer alone ("none"), and every
# filter with one trainer per learner.
QUICK_FILTERED = {"ELM": "closed", "LSSVR": "closed", "ANFIS": "EKF"}


class _Protocol:
    """Sizes of one study run (full or quick)."""

    def __init__(self, cfg: StudyConfig):
        q = cfg.quick
        self.runs = cfg.runs or (2 if q else STUDY.default_runs)
        self.n_particles = 30 if q else N_PARTICLES
        self.rul_horizon = 200 if q else RUL_HORIZON
        self.rul_paths = 20 if q else RUL_PATHS
        self.adam = {"HI": (2, 32), "CSTR": (10, 8)} if q else ADAM
        self.hi_from_day = 9.8 if q else HI_TEST_FROM_DAY
        self.hi_train_days = 2.0 if q else None  # quick: train on the last two days only
        self.rul_days = (9.9, 10.5) if q else RUL_DAYS


NOTES = Path(__file__).with_name("forecaster_matrix.md")  # the readings of table.md


# ----------------------------------------------------------------------------------- data
def _first_at(days: Tensor, d: float) -> int:
    return int(torch.nonzero(days >= d).flatten()[0])


def _hi_series(pr: _Protocol, device) -> ForecastProblem:
    hi = health_indicator(train_channel=5, test_channel=6)  # bearing 3, last 12 days
    scaler = MinMaxScaler().fit(hi.train)
    z_tr, z_te, days = scaler.transform(hi.train), scaler.transform(hi.test), hi.elapsed
    thr = float(scaler.transform(torch.tensor(HI_THRESHOLD, dtype=torch.float64)))
    m = EMBED["HI"]
    if pr.hi_train_days is not None:
        z_tr = z_tr[days >= days[-1] - pr.hi_train_days]
    X, Y = embed(z_tr, m)
    return ForecastProblem(
        "HI",
        m,
        X.to(device),
        Y[:, None].to(device),
        z_te.to(device),
        s0=max(_first_at(days, pr.hi_from_day), m),
        stride=STRIDE["HI"],
        days=days,
        threshold=thr,
        t_eol=float(days[torch.nonzero(z_te >= thr).flatten()[0]]),
        rul_idx=tuple(_first_at(days, d) for d in pr.rul_days),
        dt=DT_DAYS,
    )


def _cstr_series(cfg: StudyConfig) -> ForecastProblem:
    sim = simulate_cstr(200, generator=cfg.generator(10**6))  # docs/systems.md reading
    z = minmax_normalize(sim.y[:, 0, 0]).values  # paper 003: the whole series to [0, 1]
    X, Y = embed(z[:100], EMBED["CSTR"])
    dev = cfg.device
    return ForecastProblem(
        "CSTR", EMBED["CSTR"], X.to(dev), Y[:, None].to(dev), z.to(dev), 100, STRIDE["CSTR"]
    )


# ----------------------------------------------------------------------------------- learners
def _not_applicable(learner: str, trainer: str, s: ForecastProblem) -> str | None:
    if learner == "ANFIS" and trainer == "closed":
        return NA_REASONS["ANFIS-closed"]
    kalman = trainer in ("EKF", "SRUKF", "ImSRUKF")
    if learner == "LSSVR" and kalman and s.X.shape[0] > LSSVR_KALMAN_MAX:
        return NA_REASONS["LSSVR-Kalman"]
    return None


def _train(learner: str, trainer: str, s: ForecastProblem, pr: _Protocol, cfg: StudyConfig):
    """``pr.runs`` trained forecasters (a StackedLearner), or the one deterministic LS-SVR."""
    X, Y, dev, gen = s.X, s.Y, cfg.device, cfg.generator
    kalman = dict(filter=trainer.lower(), P0=P0[learner], Q=KF_Q[learner], R=KF_R)
    # the ImSRUKF noise estimator needs equal mini-batches: it drops an incomplete last one
    kfit = dict(epochs=1, batch_size=KF_BATCH[s.name], drop_last=trainer == "ImSRUKF")
    kfit["progress"] = False
    epochs, bs = pr.adam[s.name]
    if learner == "LSSVR":  # deterministic: the KKT solution (paper 002 Eq. 4), shared by runs
        mod = LSSVR(sigma=LSSVR_SIGMA, C=LSSVR_C).to(dev).fit(X, Y)
        if trainer == "Adam":  # from the KKT solution, mini-batches in time order
            opt = torch.optim.Adam([p for p in mod.parameters() if p.requires_grad], lr=ADAM_LR)
            fit(mod, opt, (X, Y), epochs=epochs, batch_size=bs, progress=False)
        elif trainer != "closed":  # state (alpha, b), prior mean = the KKT solution
            fit(mod, KalmanOptimizer(mod, **kalman), (X, Y), **kfit)
        return LSSVRGram(mod)
    if learner == "ELM":
        mods = [ELM(s.m, ELM_HIDDEN, generator=gen(i)).to(dev) for i in range(pr.runs)]
    else:
        mods = [
            ANFIS(s.m, ANFIS_MFS, generator=gen(i)).to(dev).init_premises(X) for i in range(pr.runs)
        ]
    if trainer == "closed":  # ELM ridge, paper 000 Eq. 52-54
        return StackedLearner.from_modules([m.fit_ridge(X, Y, ELM_LAM) for m in mods])
    if trainer == "Adam":  # one optimiser over the runs: shuffled mini-batches shared by all
        adam = lambda ps: torch.optim.Adam(ps, lr=ADAM_LR)  # noqa: E731
        opts = dict(epochs=epochs, batch_size=bs, shuffle=True, generator=gen(2 * 10**6))
        return fit_together(mods, adam, (X, Y), progress=False, **opts)
    # Kalman optimisers (paper 003 Sec. IV), one pass: one optimiser for the ANFIS runs, one per
    # ELM run (each has its own hidden layer)
    return fit_kalman_runs(mods, (X, Y), fit_options=kfit, **kalman)


def _persistence(x: Tensor) -> Tensor:
    """Reference forecaster ``x_{k+1} = x_k`` (the newest window value)."""
    return x[..., -1:]


# ----------------------------------------------------------------------------------- outputs
def _figures(out_dir: Path, res: studies.MatrixResult, problems) -> list[str]:
    figs = ["fig1_one_step_rmse.png", "fig2_filters_one_step_rmse.png", "fig3_rul.png"]
    panels = []
    for s in problems:  # 1. one-step RMSE of the forecaster alone, learner x trainer (log)
        ref = res.mean(res.combo(s.name, "persistence", "none"), "none", "RMSE_1")
        title = f"{s.name}: one-step RMSE, forecaster alone\n(persistence {ref:.3f})"
        h = res.heatmap(s.name, "RMSE_1", alone=True, log=True, fmt=".3f")
        panels.append(HeatmapPanel(*h, title=title, cmap="viridis_r", colorbar="log10 RMSE"))
    plots.plot_heatmaps(out_dir / figs[0], panels, figsize=(10.0, 3.4))
    panels = [  # 2. one-step RMSE of every (learner, trainer) x filter
        HeatmapPanel(
            *res.heatmap(s.name, "RMSE_1", log=True, fmt=".3g"),
            title=f"{s.name}: one-step RMSE",
            cmap="viridis_r",
            colorbar="log10 RMSE",
        )
        for s in problems
    ]
    plots.plot_heatmaps(out_dir / figs[1], panels, figsize=(10.0, 6.0))

    def rul_text(c, f, mass):  # 3. bearing RUL: error of the median (text), AL mass (colour)
        err, cens = res.mean(c, f, "RUL_MAE_d"), res.mean(c, f, "RUL_censored")
        text = f"{err:.2f} d" if math.isfinite(err) else "cens."
        return text + (f"\n{cens:.0%} c" if 0 < cens < 1 else "")

    title = (
        "HI: RUL error of the median (text; 'cens.': beyond the horizon)\n"
        f"colour: P(RUL within ±{RUL_ALPHA:.0%} of the truth at t_lambda)"
    )
    panel = HeatmapPanel(
        *res.heatmap("HI", "AL_mass", text=rul_text),
        title=title,
        cmap="viridis",
        clim=(0.0, 1.0),
        colorbar="alpha-lambda mass",
    )
    plots.plot_heatmaps(out_dir / figs[2], [panel], figsize=(6.5, 6.0))
    return figs


def _notes(res: studies.MatrixResult, problems, pr: _Protocol) -> str:
    hi, cs = problems

    def best(p, metric, filters=None, high=False):
        b = res.best(p, metric, filters, high) or (math.nan, " | —", "—")  # quick: none
        return b[0], f"{b[1].split(' | ')[1]} + {b[2]}"

    def ratios(p):  # median over the combinations of RMSE_1 with the filter / alone
        return ", ".join(f"{f} {res.median_ratio(p, f):.2f}" for f in FILTERS[1:])

    v = {p.name: res.view(p.name) for p in problems}
    alone, alone_name = best("HI", "RMSE_1", ("none",))
    best10, best10_name = best("HI", "RMSE_10")
    elm_vs_best = v["HI"]["ELM-closed none"] / alone - 1
    hits = [
        (round(st["alpha_lambda"].mean * st["alpha_lambda"].n), st["alpha_lambda"].n)
        for meth, st in res.summary.items()
        if meth.startswith("HI") and "alpha_lambda" in st and "persistence" not in meth
    ]
    bias = res.means("HI", "RUL_bias_d") or [math.nan]
    true_rul = [hi.t_eol - float(hi.days[i]) for i in hi.rul_idx]
    gaps = [
        abs(v[s][f"ELM-{tn} {f}"] - v[s][f"ELM-closed {f}"])
        for s in v
        for tn in ("EKF", "SRUKF")
        for f in FILTERS
    ]
    cost = res.view("HI", "cost")
    values = {k: x for k, x in globals().items() if k.isupper()} | dict(hi=hi, cs=cs, pr=pr)
    values |= {**v, "HI_div": res.view("HI", "diverged"), "HI_cost": cost}
    values |= {"CSTR_std": res.view("CSTR", "std")}
    values |= dict(
        rul_days=", ".join(f"{float(hi.days[i]):.2f}" for i in hi.rul_idx),
        true_ruls=", ".join(f"{r:.2f}" for r in true_rul),
        horizon_days=pr.rul_horizon * DT_DAYS,
        alone=alone,
        alone_name=alone_name,
        ratios_hi=ratios("HI"),
        ratios_cs=ratios("CSTR"),
        elm_pick=(
            f"ELM ridge is within {elm_vs_best:.1%} of the best and the cheapest "
            f"({cost['ELM-closed none']:.3f} s/run): pick it for one-step forecasts."
            if elm_vs_best <= 0.05
            else f"ELM ridge is {elm_vs_best:.0%} behind the best: pick {alone_name}."
        ),
        best10=best10,
        best10_name=best10_name,
        reading10=": persistence wins (our reading: the recursive predictions revert towards "
        "the training level while the indicator drifts up). "
        if v["HI"]["persistence-none none RMSE_10"] < best10
        else ". ",
        censored_alone=", ".join(
            c.split(" | ")[1]
            for c, _, _ in res.combos("HI")
            if res.summary.get(f"{c} | none") and res.mean(c, "none", "RUL_censored") == 1.0
        )
        or "no combination",
        bias_min=min(bias),
        bias_max=max(bias),
        rul_min=min(true_rul),
        rul_max=max(true_rul),
        hits=max(hits)[0] if hits else 0,
        hits_n=max(hits)[1] if hits else 0,
        elm_gap=max((g for g in gaps if math.isfinite(g)), default=math.nan),
        elm_kalman_cost=cost["ELM-EKF none"] / max(cost["ELM-closed none"], 1e-9),
        costs=", ".join(f"{f} {cost[f'ELM-closed {f}']:.3f}" for f in FILTERS),
    )
    for key, p in (("best_hi", "HI"), ("best_cs", "CSTR")):
        values[key], values[key + "_name"] = best(p, "RMSE_1")
    values["best_mass"], values["best_mass_name"] = best("HI", "AL_mass", high=True)
    return studies.fill_template(NOTES, values)


def run(cfg: StudyConfig, out_dir: Path) -> StudyResult:
    pr = _Protocol(cfg)
    problems = [_hi_series(pr, cfg.device), _cstr_series(cfg)]
    make = {"PF": filters.sir, "EKPF": filters.ekpf, "STPF": filters.stpf}
    flt = {"none": None} | {f: (lambda f=f: make[f](pr.n_particles)) for f in make}
    flt |= {"SCKF": filters.sckf, "STSCKF": filters.stsckf}
    protocol = studies.ForecastProtocol(
        H_MULTI, pr.rul_horizon, pr.rul_paths, RUL_ALPHA, RUL_LAMBDA, RUL_BETA
    )

    def skip(ln, tn, f):  # quick mode: a reduced matrix
        return (
            "quick mode: not run"
            if cfg.quick and f != "none" and tn != QUICK_FILTERED[ln]
            else None
        )

    res = studies.run_forecaster_matrix(
        problems,
        LEARNERS,
        TRAINERS,
        flt,
        lambda ln, tn, s: _train(ln, tn, s, pr, cfg),
        runs=pr.runs,
        protocol=protocol,
        r_share=R_SHARE,
        shift_std=SHIFT_STD,
        max_rmse=DIVERGED_RMSE,
        shared_runs=SHARED_RUNS,
        seed=cfg.seed + 3 * 10**6,  # common random numbers: one seed per (series, filter)
        device=cfg.device,
        not_applicable=_not_applicable,
        skip=skip,
        references={"persistence": _persistence},
        progress=cfg.progress,
    )
    hi = problems[0]
    intro = (
        "Full matrix (mean ± std over runs; errors in scaled units; RUL metrics on the bearing "
        "only, '—' on the CSTR; n/a = not applicable, reasons below):\n\n"
    )
    return StudyResult(
        rows=res.rows,
        metrics=METRICS,
        figures=_figures(out_dir, res, problems),
        config={
            "runs": pr.runs,
            "embedding": EMBED,
            "elm": {"hidden": ELM_HIDDEN, "lambda": ELM_LAM, "activation": "sigmoid"},
            "lssvr": {"kernel": "rbf", "sigma": LSSVR_SIGMA, "C": LSSVR_C},
            "anfis": {"mfs": ANFIS_MFS, "mf": "sigmoid"},
            "kalman": {"R": KF_R, "Q": KF_Q, "P0": P0, "batch": KF_BATCH, "passes": 1},
            "adam": {"lr": ADAM_LR, "epochs_batch": pr.adam},
            "particles": pr.n_particles,
            "multi_step": {"horizon": H_MULTI, "stride": STRIDE},
            "filter_noise": {"R_share": R_SHARE, "shift_std": SHIFT_STD},
            "hi": {
                "test_from_day": pr.hi_from_day,
                "threshold": HI_THRESHOLD,
                "threshold_scaled": hi.threshold,
                "t_eol_days": hi.t_eol,
                "rul_days": list(pr.rul_days),
                "rul_horizon_steps": pr.rul_horizon,
                "rul_paths": pr.rul_paths,
            },
            "combinations": dict(res.info),
        },
        notes=_notes(res, problems, pr),
        extra_tables=[intro + res.table(H_MULTI), *res.pivots()],
    )


STUDY = Study(
    name="forecaster-matrix",
    paper="002/003",
    title="Forecaster matrix: learner x trainer x prognostic filter (IMS bearing HI, CSTR C_A)",
    run=run,
    default_runs=10,
)
