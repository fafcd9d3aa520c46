"""Paper 000 study: ROS-ELM measurement forecasts + strong-tracking SCKF, three-tank ``az2`` fault.

Protocol (paper 000 Sec. 5-6, Table 1, Fig. 1-3):

* DTS200 three-tank system with the ``az2`` ramp of Eq. 61
  (:func:`~prognos_torch.systems.three_tank.simulate_three_tank`, 200 steps of 1 s);
* one ROS-ELM per measured level (embedding ``p = 3``, ``L = 50`` sigmoid nodes,
  ``lambda = 1e-8``), trained on ``z_1..z_50`` and updated online with every new measurement
  (:class:`~prognos_torch.prognosis.forecast.MeasurementForecaster`);
* joint state/parameter filters on ``[h1, h2, h3, az2]`` with the assistant model
  ``az2_k = az2_{k-1} + d`` (Eq. 62-63, :func:`~prognos_torch.systems.three_tank_joint_model`):
  SCKF, STUKF and STSCKF; at each ``k = 50, ..., 200`` the filter runs over the forecast
  ``z_{k+1..k+5}`` and ``az2^_{k+5|k+5}`` is the 5-step-ahead prediction
  (:func:`~prognos_torch.prognosis.forecast.rolling_fault_prediction`);
* MAE / RMSE (and MSE) of the 5-step-ahead ``az2`` prediction per Monte Carlo run, the 1-step
  filtering RMSE of ``az2`` on the real measurements, time per run; a sensitivity check of the
  SCKF/STSCKF gap to the random-walk noise ``chol_D``.

Monte Carlo runs are batched through the filters' batch dimension. Run ``i`` draws its noise and
the hidden layers of its three ROS-ELMs from ``cfg.generator(i)``; to give every run its own
hidden layers inside one batched pass, the ``R`` runs x 3 channels are packed into one
:class:`MeasurementForecaster` with ``3 R`` channels (:class:`_RunChannels`, a reshaping view).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from tqdm import tqdm

from prognos_torch.core.belief import GaussianBelief
from prognos_torch.filters import run as filter_run
from prognos_torch.filters import sckf, stsckf, stukf
from prognos_torch.metrics import mae, rmse
from prognos_torch.plots import plot_fading_factor, plot_prediction
from prognos_torch.prognosis import MeasurementForecaster, rolling_fault_prediction
from prognos_torch.studies import Study, StudyConfig, StudyResult
from prognos_torch.systems.three_tank import simulate_three_tank, three_tank_joint_model

# Paper 000 Table 1 (50 Monte Carlo runs). The column printed "RMSE" is below the MAE for every
# method, which is impossible for the RMSE of the same errors; it matches an MSE (see notes).
PAPER = {
    "SCKF": {"MAE": 0.4402, "RMSE": 0.3017, "time_s": 1.3011},
    "STUKF": {"MAE": 0.0930, "RMSE": 0.0111, "time_s": 1.2868},
    "STSCKF": {"MAE": 0.0318, "RMSE": 0.0015, "time_s": 1.3540},
}
METRICS = ["MAE", "RMSE", "MSE", "filt_RMSE", "time_s"]

N_AHEAD = 5  # prediction horizon n (Sec. 6.2)
N0 = 50  # initial ROS-ELM training samples z_1..z_50 (Sec. 6.2)
EMBED, HIDDEN, LAM = 3, 50, 1e-8  # ROS-ELM p, L, lambda (Sec. 6.2)
# Random-walk std of az2 (d_k in Eq. 62): the paper gives none. We use the std of the level noise
# w_k (1e-4): the assistant model az2_k = az2_{k-1} is trusted like the level dynamics, as a
# designer who does not know the ramp of Eq. 61 would. The sensitivity table varies it.
CHOL_D = 1e-4
# Initial belief (the paper gives none): the paper's initial levels [1, 0.95, 0.9] m with std
# 1e-3 m (5 measurement-noise stds) and the nominal az2 = 0.6 with std 1e-2.
X0 = (1.0, 0.95, 0.9, 0.6)
S0 = (1e-3, 1e-3, 1e-3, 1e-2)
SENS_D = (1e-5, 1e-4, 1e-3, 3e-3, 1e-2, 3e-2)


def _filters():
    return {"SCKF": sckf(), "STUKF": stukf(), "STSCKF": stsckf()}


class _RunChannels:
    """``R`` runs x ``C`` channels as one forecaster with ``R C`` channels (a reshaping view).

    :class:`MeasurementForecaster` shares its ELMs' hidden layers across batch dims; packing the
    runs into channels gives each run its own hidden layers while the filters stay batched.
    Implements the forecaster protocol of :func:`rolling_fault_prediction`.
    """

    def __init__(self, inner: MeasurementForecaster, runs: int, channels: int):
        self.inner, self.runs, self.channels = inner, runs, channels

    @property
    def initialized(self) -> bool:
        return self.inner.initialized

    def copy(self) -> _RunChannels:
        return _RunChannels(self.inner.copy(), self.runs, self.channels)

    def initialize(self, z0: torch.Tensor) -> _RunChannels:  # (N0, R, C)
        self.inner.initialize(z0.reshape(z0.shape[0], self.runs * self.channels))
        return self

    def forecast(self, n: int) -> torch.Tensor:  # (n, R, C)
        return self.inner.forecast(n).reshape(n, self.runs, self.channels)

    def update(self, z: torch.Tensor) -> _RunChannels:  # (R, C)
        self.inner.update(z.reshape(self.runs * self.channels))
        return self


def _simulate(cfg: StudyConfig, runs: int, T: int):
    """Run ``i``: noise and ROS-ELM hidden layers from ``cfg.generator(i)``."""
    sims, learners = [], []
    for i in range(runs):
        g = cfg.generator(i)
        sims.append(simulate_three_tank(T + N_AHEAD, runs=1, generator=g))
        fc = MeasurementForecaster.ros_elm(3, EMBED, HIDDEN, LAM, generator=g)
        learners += [elm.to(cfg.device) for elm in fc.learners]
    dev = cfg.device
    x = torch.cat([s.x for s in sims], 1).to(dev)  # (T+n+1, R, 3)
    y = torch.cat([s.y for s in sims], 1).to(dev)  # (T+n, R, 3)
    theta = torch.cat([s.theta for s in sims], 1).to(dev)  # (T+n+1, R, 1)
    fc = _RunChannels(MeasurementForecaster(learners, EMBED, lam=LAM, online=True), runs, 3)
    return x, y, theta, fc


def _init_belief(runs: int, device) -> GaussianBelief:
    m = torch.tensor(X0, dtype=torch.float64, device=device).expand(runs, 4)
    S = torch.diag(torch.tensor(S0, dtype=torch.float64, device=device)).expand(runs, 4, 4)
    return GaussianBelief(m.clone(), S.clone())


def _predict(filt, ys, fc, chol_D, device):
    """Rolling 5-step-ahead az2 prediction over ``ys`` ``(T, R, 3)``; returns result, seconds."""
    model = three_tank_joint_model(chol_D=chol_D, device=device)
    b0 = _init_belief(ys.shape[1], device)
    t0 = time.perf_counter()
    res = rolling_fault_prediction(filt, model, ys, fc, N_AHEAD, N0, init=b0, param_index=3)
    return res, time.perf_counter() - t0


def _errors(res, theta, T):
    """Per-run errors: 5-step prediction (targets N0+n..T+n) and 1-step filtering (k=N0..T)."""
    pred = res.predicted[..., 0]  # (K, R), origins k = N0..T
    truth = theta[N0 + N_AHEAD : T + N_AHEAD + 1, :, 0]
    filt = res.filtered[N0 - 1 :, :, 0]  # az2_{k|k}, k = N0..T
    ftruth = theta[N0 : T + 1, :, 0]
    r = rmse(pred, truth, dim=0)
    return {
        "MAE": mae(pred, truth, dim=0),
        "RMSE": r,
        "MSE": r.square(),
        "filt_RMSE": rmse(filt, ftruth, dim=0),
    }


def _measurement_forecasts(fc: _RunChannels, ys, T):
    """ROS-ELM forecasts ``z_{k+1..k+n}`` made at ``k = N0..T``: ``(K, n, R, 3)``."""
    f = fc.copy().initialize(ys[:N0])
    out = []
    for k in range(N0, T + 1):
        out.append(f.forecast(N_AHEAD))
        if k < T:
            f.update(ys[k])
    return torch.stack(out)


def _fig_predictions(path: Path, t, truth, preds: dict, title: str) -> None:
    """Fig. 2 style: predictions of several methods vs truth, and their absolute errors."""
    fig = Figure(figsize=(7.0, 6.0))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    ax1.plot(t, truth, "k-", lw=1.6, label="true $az_2$")
    for i, (name, p) in enumerate(preds.items()):
        # wide pale lines under narrow ones, so that coinciding methods stay visible
        lw, alpha = (3.5, 0.45) if i % 2 else (1.1, 1.0)
        ax1.plot(t, p, f"C{i}--", lw=lw, alpha=alpha, label=name)
        ax2.semilogy(t, np.abs(p - truth), f"C{i}-", lw=lw, alpha=alpha, label=name)
    ax1.set_ylabel("$az_2$")
    ax1.set_title(f"(a) {title}")
    ax1.legend(loc="upper left")
    ax2.set_xlabel("time k (s)")
    ax2.set_ylabel("absolute error")
    ax2.set_title("(b) prediction error")
    ax2.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=100)


def run(cfg: StudyConfig, out_dir: Path) -> StudyResult:
    runs = cfg.runs or (3 if cfg.quick else STUDY.default_runs)
    T = 120 if cfg.quick else 200
    sens_d = (1e-4, 1e-2) if cfg.quick else SENS_D
    sens_runs = min(runs, 10)
    dev = cfg.device
    x, y, theta, fc = _simulate(cfg, runs, T)
    ys = y[:T]  # the filters and ROS-ELMs see z_1..z_T; the extra n steps are truth only

    jobs = [("main", name, CHOL_D) for name in _filters()]
    jobs += [("single", name, CHOL_D) for name in _filters()]
    jobs += [("sens", name, d) for d in sens_d for name in ("SCKF", "STSCKF")]
    bar = tqdm(jobs, desc="elm-stsckf", disable=not cfg.progress)
    main, single, sens = {}, {}, {}
    fc1 = _RunChannels(MeasurementForecaster(fc.inner.learners[:3], EMBED, lam=LAM), 1, 3)
    fcs = _RunChannels(
        MeasurementForecaster(fc.inner.learners[: 3 * sens_runs], EMBED, lam=LAM),
        sens_runs,
        3,
    )
    for kind, name, d in bar:
        bar.set_postfix_str(f"{kind} {name} chol_D={d:g}")
        filt = _filters()[name]
        if kind == "main":
            main[name] = _predict(filt, ys, fc, d, dev)
        elif kind == "single":  # run 0 alone: unbatched time per run, comparable to the paper
            single[name] = _predict(filt, ys[:, :1], fc1, d, dev)[1]
        else:
            res, _ = _predict(filt, ys[:, :sens_runs], fcs, d, dev)
            sens[(name, d)] = {
                k: v.mean().item() for k, v in _errors(res, theta[:, :sens_runs], T).items()
            }

    rows = []
    errs = {name: _errors(res, theta, T) for name, (res, _) in main.items()}
    for i in range(runs):
        for name, (_, secs) in main.items():
            row = {"run": i, "method": name}
            row.update({k: v[i].item() for k, v in errs[name].items()})
            row["time_s"] = round(secs / runs, 6)
            rows.append(row)

    # ---------------------------------------------------------------- figures (run 0)
    figs = []
    zf = _measurement_forecasts(fc, ys, T)  # (K, n, R, 3)
    t_target = torch.arange(N0 + N_AHEAD, T + N_AHEAD + 1)
    for c in range(3):
        name = f"fig1_z{c + 1}_forecast.png"
        plot_prediction(
            out_dir / name,
            t_target,
            x[N0 + N_AHEAD : T + N_AHEAD + 1, 0, c],
            zf[:, -1, 0, c],
            title=f"ROS-ELM 5-step-ahead forecast of $z_{c + 1}$ vs true level (run 0)",
            ylabel=f"$h_{c + 1}$ (m)",
        )
        figs.append(name)
    truth0 = theta[N0 + N_AHEAD : T + N_AHEAD + 1, 0, 0].cpu().numpy()
    preds0 = {n: r.predicted[:, 0, 0].cpu().numpy() for n, (r, _) in main.items()}
    _fig_predictions(
        out_dir / "fig2_az2_prediction.png",
        t_target.numpy(),
        truth0,
        preds0,
        f"5-step-ahead prediction of $az_2$ (run 0, chol_D = {CHOL_D:g})",
    )
    figs.append("fig2_az2_prediction.png")
    model = three_tank_joint_model(chol_D=CHOL_D, device=dev)
    traj = filter_run(stsckf(), model, _init_belief(runs, dev), ys)
    lam_pred = torch.full((T,), math.nan, dtype=torch.float64)
    lam_pred[N0 - 1 :] = main["STSCKF"][0].fading_factors[:, -1, 0].cpu()
    plot_fading_factor(
        out_dir / "fig3_fading_factor.png",
        torch.arange(1, T + 1),
        {
            "real-time filter on z_k (run 0)": traj.fading_factors[:, 0].cpu(),
            "5th forecast step of the prediction made at k (run 0)": lam_pred,
        },
        title="STSCKF fading factor $\\lambda_k$",
    )
    figs.append("fig3_fading_factor.png")

    # ---------------------------------------------------------------- extra tables and notes
    zt = torch.stack([x[N0 + j : T + j + 1] for j in range(1, N_AHEAD + 1)], 1)  # (K, n, R, 3)
    z_rmse = rmse(zf, zt, dim=(0, 2))  # (n, 3)
    tab_z = ["| horizon j | " + " | ".join(f"RMSE z{c + 1} (m)" for c in range(3)) + " |"]
    tab_z.append("|---|---|---|---|")
    for j in range(N_AHEAD):
        tab_z.append(f"| {j + 1} | " + " | ".join(f"{v:.2e}" for v in z_rmse[j].tolist()) + " |")
    tab_z = (
        "ROS-ELM measurement forecasts made at k = 50..T, error against the true levels "
        f"(all {runs} runs):\n\n" + "\n".join(tab_z)
    )

    tab_s = [
        "| chol_D | SCKF MAE | SCKF RMSE | STSCKF MAE | STSCKF RMSE | RMSE ratio SCKF/STSCKF |"
    ]
    tab_s.append("|---|---|---|---|---|---|")
    for d in sens_d:
        a, b = sens[("SCKF", d)], sens[("STSCKF", d)]
        tab_s.append(
            f"| {d:g} | {a['MAE']:.4f} | {a['RMSE']:.4f} | {b['MAE']:.4f} | {b['RMSE']:.4f} | "
            f"{a['RMSE'] / b['RMSE']:.1f} |"
        )
    tab_s = (
        f"Sensitivity to the az2 random-walk std chol_D (first {sens_runs} runs, mean over "
        "runs):\n\n" + "\n".join(tab_s)
    )

    mse = {n: errs[n]["MSE"].mean().item() for n in main}
    tab_m = ["| method | MSE (ours) | paper 'RMSE' | sqrt(paper 'RMSE') | RMSE (ours) |"]
    tab_m.append("|---|---|---|---|---|")
    for n in main:
        p = PAPER[n]["RMSE"]
        tab_m.append(
            f"| {n} | {mse[n]:.4g} | {p:.4g} | {math.sqrt(p):.4f} | "
            f"{errs[n]['RMSE'].mean().item():.4f} |"
        )
    tab_m = "Paper's 'RMSE' column read as an MSE:\n\n" + "\n".join(tab_m)

    tab_t = ["| method | batched, per run (s) | one run alone (s) | paper (s) |"]
    tab_t.append("|---|---|---|---|")
    for n, (_, secs) in main.items():
        tab_t.append(f"| {n} | {secs / runs:.4f} | {single[n]:.3f} | {PAPER[n]['time_s']:.4f} |")
    tab_t = (
        f"Time: {runs} runs in one batched pass (divided by the runs) and run 0 alone, "
        "ROS-ELM training and forecasting included:\n\n" + "\n".join(tab_t)
    )

    lam_rt = traj.fading_factors[N0:]
    d_uc = (main["STUKF"][0].predicted - main["STSCKF"][0].predicted).abs().max().item()
    # mean signed errors (lag behind the ramp), STSCKF, all runs
    res_st = main["STSCKF"][0]
    bias_p = (res_st.predicted[..., 0] - theta[N0 + N_AHEAD : T + N_AHEAD + 1, :, 0]).mean()
    bias_f = (res_st.filtered[N0 - 1 :, :, 0] - theta[N0 : T + 1, :, 0]).mean()
    notes = f"""
Readings and choices (paper 000 gives no filter noise for az2 and no initial covariance):

- Truth and alignment: 5-step-ahead predictions az2^_(k+5|k+5) made at k = {N0}..{T}
  (ROS-ELMs trained on z_1..z_{N0}); the simulation runs {N_AHEAD} steps past T so every target
  k + 5 has its true az2 (Eq. 61). filt_RMSE: az2^_(k|k) of the real-time filter on the real
  z_k, k = {N0}..{T} (no forecast). In Eq. 62 az2_(k-1) drives the step to k, so z_k only informs
  az2_(k-1): every filter carries a lag of one ramp increment (1e-4 (k-10) <= 0.019).
- chol_D = {CHOL_D:g} (std of d_k, = std of the level noise w_k); initial belief mean
  {list(X0)} (paper's levels, nominal az2), std {list(S0)}. STUKF: strong tracking on the
  square-root UKF with Julier's kappa = 1 (the paper's STUKF settings are not given).
  Strong tracking: rho = 0.95, weakening factor 1 (derivative-free fading factor, Eq. 27-35).
- Monte Carlo: run i draws its noise and its ROS-ELM hidden layers from seed {cfg.seed} + i;
  the three filters see the same measurements and the same ROS-ELM forecasts.
- Paper Table 1 prints "RMSE" below "MAE" for every method, which is impossible for the RMSE
  of the same errors (RMSE >= MAE). Read as an MSE the column is consistent
  (sqrt(0.3017) = 0.549 >= 0.4402, sqrt(0.0111) = 0.105 >= 0.093, sqrt(0.0015) = 0.039 >=
  0.0318); compare it with our MSE column.
- STUKF and STSCKF predictions differ by at most {d_uc:.1e} in az2: the level and az2
  spreads are tiny (std ~1e-3 m) against the curvature of sqrt(h), so the cubature and the
  unscented (kappa = 1) rules give the same moments; the sigma-point rule cannot explain the
  paper's STUKF/STSCKF gap here.
- All az2 errors are dominated by a lag behind the accelerating ramp (Fig. 2). STSCKF mean
  signed error: {bias_p.item():+.4f} for the 5-step prediction, {bias_f.item():+.4f} for the
  real-time filter. Our reading of the smaller prediction lag: the ROS-ELM forecasts
  extrapolate the accelerating fall of h2, which the filter attributes to a further rise of
  az2; so the 5-step RMSE can be below filt_RMSE.
- STSCKF fading factor (real-time filter, k > {N0}, all runs): median
  {lam_rt.median().item():.2f}, 95th percentile {lam_rt.quantile(0.95).item():.2f}, max
  {lam_rt.max().item():.2f}.
"""
    return StudyResult(
        rows=rows,
        metrics=METRICS,
        paper=PAPER,
        figures=figs,
        config={
            "T": T,
            "N0": N0,
            "horizon": N_AHEAD,
            "ros_elm": {"p": EMBED, "L": HIDDEN, "lambda": LAM, "activation": "sigmoid"},
            "chol_D": CHOL_D,
            "init_mean": list(X0),
            "init_std": list(S0),
            "strong_tracking": {"rho": 0.95, "beta": 1.0},
            "stukf_kappa": 1.0,
            "sensitivity_chol_D": list(sens_d),
            "sensitivity_runs": sens_runs,
            "time_s": "batched wall time of the method divided by the runs",
        },
        notes=notes,
        extra_tables=[tab_m, tab_t, tab_s, tab_z],
    )


STUDY = Study(
    name="elm-stsckf",
    paper="000",
    title="ROS-ELM forecasts + strong-tracking SCKF: 5-step-ahead az2 prediction (three tanks)",
    run=run,
    default_runs=50,
)
