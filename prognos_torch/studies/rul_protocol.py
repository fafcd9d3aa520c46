"""RUL methods scored under the known-threshold protocol, point by point (the RUL studies).

For each series, :func:`~prognos_torch.prognosis.protocol.known_threshold_protocol` gives the
threshold, end of life, onset and prediction times; :func:`protocol_rows` predicts at each time
from the data up to it with every method (:func:`predict_rul`) and scores the points with
:func:`~prognos_torch.prognosis.protocol.rul_scores`; :func:`headline_table` summarises a set of
series per method (alpha-lambda at alpha = 0.2 and 0.3, 90 % interval coverage, the median
absolute and relative errors, the mean relative accuracy and, for methods with RUL samples,
the mean CRPS of the log RUL, censored at 10 x the truth).

Methods: ``"prognose (<method>)"`` for every :data:`~prognos_torch.workflow.PROGNOSE_METHODS`
entry (``", strong tracking"`` appended: the strong-tracking EKF; ``", ekf+stekf pool"``: the
models of both filters pooled, ``prognose(filter="ekf+stekf")``), and the baselines
``"fit_series + rul(stpf)"`` (the workflow's learner forecaster and strong-tracking particle
filter), ``"linear slope"`` and ``"exponential LSQ"``
(:mod:`prognos_torch.prognosis.protocol`). :func:`conformal_rows` adds a method's rows with its
90 % intervals calibrated on the other assets' points (split-conformal, leave one asset out).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..core.validation import check_pos_int
from ..prognosis.conformal import leave_one_group_out
from ..prognosis.protocol import (
    ProtocolCase,
    exponential_lsq_rul,
    known_threshold_protocol,
    linear_slope_rul,
    rul_scores,
)

__all__ = ["RUL_BASELINES", "predict_rul", "protocol_rows", "conformal_rows", "headline_table"]

RUL_BASELINES = ("fit_series + rul(stpf)", "linear slope", "exponential LSQ")


def _inf(v) -> float:
    return math.inf if v is None else float(v)


def predict_rul(method: str, t: Tensor, y: Tensor, case: ProtocolCase, tp: float,
                seed: int, time_unit: str = "time") -> dict:  # fmt: skip
    """One prediction at time ``tp`` from the data ``t <= tp`` (``t`` in ``time_unit``).

    Returns:
        ``{"pred", "lo", "hi", "censored", "model"}`` (median, q05, q95: ``inf`` when censored;
        ``lo``/``hi``/``censored`` ``None`` for the point baselines) and, for ``prognose``, the
        :class:`~prognos_torch.workflow.RULResult` as ``"result"``.
    """
    from ..workflow import Series, fit_series, prognose, rul

    sel = t <= tp
    ts, ys = t[sel], y[sel]
    shift = tp - float(ts[-1])
    series = Series(ys, ts, "indicator", "t", time_unit)
    if method.startswith("prognose ("):
        kind = method[len("prognose (") : -1]
        filt = "stekf" if "strong tracking" in kind else "ekf"
        filt = "ekf+stekf" if "ekf+stekf pool" in kind else filt
        res = prognose(series, case.threshold, method=kind.split(",")[0], at=tp, seed=seed,
                       filter=filt)  # fmt: skip
        s = res.summary()
        return {"pred": _inf(s["median"]), "lo": _inf(s["q05"]), "hi": _inf(s["q95"]),
                "censored": s["censored_mass"], "model": res.model or res.status,
                "result": res}  # fmt: skip
    if method == "fit_series + rul(stpf)":
        res = rul(fit_series(series, seed=seed), series, case.threshold, filter="stpf", seed=seed)
        s = res.summary()
        # every quantile from tp, not the last sample, and never below 0 (q95 was not clamped:
        # an interval [0, -0.2])
        return {"pred": max(_inf(s["median"]) - shift, 0.0), "lo": max(_inf(s["q05"]) - shift, 0.0),
                "hi": max(_inf(s["q95"]) - shift, 0.0), "censored": res.censored_mass,
                "model": "anfis"}  # fmt: skip
    if method == "linear slope":
        p = linear_slope_rul(ts, ys, case.threshold, case.t_onset)
    elif method == "exponential LSQ":
        p = exponential_lsq_rul(ts, ys, case.threshold, case.t_onset, case.baseline.mean)
    else:
        raise ValueError(f"unknown RUL method {method!r}")
    return {"pred": max(p - shift, 0.0), "lo": None, "hi": None, "censored": None, "model": ""}


def _crps(p: dict, true: float) -> float | None:
    """Log-time CRPS of a prediction's RUL samples (censored at 10 x the truth), or ``None``."""
    from ..workflow.prognosing import crps_log_time

    res = p.get("result")
    if res is None or res.rul_samples is None or not true > 0:
        return None
    x = res.rul_samples[~torch.isnan(res.rul_samples)]
    return float(crps_log_time(x.clamp(min=1e-12), true, 10.0 * true)) if x.numel() else None


def protocol_rows(
    series: dict[str, tuple[Tensor, Tensor, bool]],
    methods,
    *,
    seed: int = 0,
    every: int = 1,
    cone_methods=(),
    time_unit: str = "time",
) -> tuple[list[dict], list[dict], list[str], dict]:
    """Predict and score every method at the protocol's points of every series.

    Args:
        series: ``{name: (t, y, held_out)}``, each ``(T,)``.
        methods: method names (module docstring).
        seed: seeds every prediction.
        every: use every ``every``-th prediction time (quick runs).
        cone_methods: methods whose predictions go into the returned panels (figures).
        time_unit: the unit of every ``t`` (results and figures say it).

    Returns:
        ``(rows, panels, per_series, results)``: one row per (method, series, point) with the
        truth, prediction, interval, censored mass and scores; per series a panel dict for
        :func:`~prognos_torch.plots.plot_rul_trajectory`; CRA and prognostic-horizon lines
        (markdown rows, or a "protocol not usable" row); and ``{(method, name): [prediction
        dicts]}``.
    """
    every = check_pos_int(every, "every")  # (a slice of the times: "step must be greater ...")
    rows, panels, per_series, results = [], [], [], {}
    for name, (t, y, held) in series.items():
        pc = known_threshold_protocol(t, y)
        if not pc.valid:
            per_series.append(f"| {name} | protocol not usable: {pc.reason} | | |")
            continue
        times = pc.times[::every]
        true = pc.t_eol - times
        panel = {"title": f"{name} (EoL {pc.t_eol:.2f})", "times": times, "true": true,
                 "t_eol": pc.t_eol, "methods": {}}  # fmt: skip
        for m in methods:
            ps = [predict_rul(m, t, y, pc, float(tp), seed, time_unit) for tp in times]
            results[(m, name)] = ps
            pred = torch.tensor([p["pred"] for p in ps], dtype=torch.float64)
            # float64 bounds: in the default float32 a q05 equal to the true RUL (one sampling
            # step) rounded above it and the point counted as not covered
            f64 = torch.float64
            lo = None if ps[0]["lo"] is None else torch.tensor([p["lo"] for p in ps], dtype=f64)
            hi = None if ps[0]["hi"] is None else torch.tensor([p["hi"] for p in ps], dtype=f64)
            sc = rul_scores(times, true, pred, t_onset=pc.t_onset, t_eol=pc.t_eol, lower=lo,
                            upper=hi)  # fmt: skip
            for i, p in enumerate(ps):
                rows.append({"run": len(rows), "method": m, "series": name, "held_out": held,
                             "t": float(times[i]), "true_rul": float(true[i]), "pred_rul": p["pred"],
                             "q05": p["lo"], "q95": p["hi"], "censored": p["censored"],
                             "model": p["model"], "in_cone_0.2": float(sc["in_cone_0.2"][i]),
                             "in_cone_0.3": float(sc["in_cone_0.3"][i]),
                             "covered": None if lo is None else float(sc["covered"][i]),
                             "abs_error": float(sc["abs_error"][i]),
                             "rel_error": float(sc["rel_error"][i]),
                             "crps_log": _crps(p, float(true[i]))})  # fmt: skip
            per_series.append(f"| {name} | {m} | {sc['cra']:.3g} | {sc['ph_0.2']:.3g} |")
            if m in cone_methods:
                panel["methods"][m] = {"pred": pred, "lo": lo, "hi": hi}
        panels.append(panel)
    return rows, panels, per_series, results


def conformal_rows(rows: list[dict], method: str, asset, coverage: float = 0.9) -> list[dict]:
    """``method``'s rows again, as ``"<method> + conformal"``, each 90 % interval calibrated on
    the points of every other asset (:func:`~prognos_torch.prognosis.conformal.leave_one_group_out`,
    CQR on the log RUL): what a user with those assets' run-to-failure histories would get
    from :func:`~prognos_torch.workflow.calibrate_rul`.

    Args:
        rows: from :func:`protocol_rows`.
        method: a method with intervals (a ``prognose`` one).
        asset: series name -> asset label (series of one asset, such as its two accelerometers,
            are left out together).
        coverage: the target coverage.

    Returns:
        New rows (``run`` numbered on from ``rows``): the prediction and its scores unchanged,
        ``q05``/``q95``/``covered`` calibrated, ``crps_log`` ``None`` (an interval, no
        distribution). Points without an interval (before onset) keep their own.
    """
    mine = [r for r in rows if r["method"] == method]
    if not mine:
        return []
    if any(r["q05"] is None or r["q95"] is None for r in mine):
        raise ValueError(
            f"method {method!r} has no intervals (q05/q95 None: a point baseline); calibrate a "
            "prognose method"
        )
    lo = torch.tensor([r["q05"] if math.isfinite(r["q05"]) else math.nan for r in mine],
                      dtype=torch.float64)  # fmt: skip
    hi = torch.tensor([r["q95"] for r in mine], dtype=torch.float64)
    hi = torch.where(torch.isnan(lo), lo, hi)
    true = torch.tensor([r["true_rul"] for r in mine], dtype=torch.float64)
    new_lo, new_hi, _ = leave_one_group_out(lo, hi, true, [asset(r["series"]) for r in mine],
                                            coverage)  # fmt: skip
    out = []
    for i, r in enumerate(mine):
        row = dict(r, run=len(rows) + i, method=f"{method} + conformal", crps_log=None)
        if not math.isnan(float(new_lo[i])):
            a, b = float(new_lo[i]), float(new_hi[i])
            row.update(q05=a, q95=b, covered=float(a <= r["true_rul"] <= b))
        out.append(row)
    return out


def _mean_ra(rel: Tensor) -> str:
    """Mean relative accuracy ``1 - |r - r*| / r*`` (Saxena et al. 2010) over the points with a
    finite prediction; an infinite one (a censored median: "beyond the horizon") has RA
    ``-inf``, so those are counted beside the mean rather than averaged into it."""
    ok = torch.isfinite(rel)
    if not bool(ok.any()):
        return "—"
    out = f"{float((1 - rel[ok]).mean()):.3g}"
    return out if bool(ok.all()) else f"{out} ({int(ok.sum())} of {rel.numel()} finite)"


def headline_table(rows: list[dict], methods, title: str, held_out: bool | None = None) -> str:
    """alpha-lambda, 90 % coverage, the median absolute and relative errors (``torch.median``:
    the lower of the two middle values for an even count) and the mean RA
    (:func:`_mean_ra`) per method over the rows (``held_out``: only those rows; ``None``: all);
    a title with "no points in this run" where none of the rows qualifies."""
    head = ("| method | points | alpha-lambda 0.2 | alpha-lambda 0.3 | 90 % coverage | "
            "median abs error | median rel error | mean RA | mean log-time CRPS |\n"
            "|---|---|---|---|---|---|---|---|---|")  # fmt: skip
    lines = [f"**{title}**", "", head]
    for m in methods:
        rs = [r for r in rows if r["method"] == m and held_out in (None, r["held_out"])]
        if not rs:
            continue
        err = torch.tensor([r["abs_error"] for r in rs], dtype=torch.float64)
        rel = torch.tensor([r["rel_error"] for r in rs], dtype=torch.float64)
        cov = [r["covered"] for r in rs if r["covered"] is not None]
        cov_s = f"{sum(cov) / len(cov):.2f}" if cov else "—"
        a2 = sum(r["in_cone_0.2"] for r in rs) / len(rs)
        a3 = sum(r["in_cone_0.3"] for r in rs) / len(rs)
        crps = [r["crps_log"] for r in rs if r.get("crps_log") is not None]
        crps_s = f"{sum(crps) / len(crps):.3f}" if crps else "—"
        if crps and len(crps) < len(rs):  # points without samples (no degradation detected)
            crps_s += f" ({len(crps)} of {len(rs)})"
        lines.append(f"| {m} | {len(rs)} | {a2:.2f} | {a3:.2f} | {cov_s} | "
                     f"{float(err.median()):.3g} | {float(rel.median()):.3g} | "
                     f"{_mean_ra(rel)} | {crps_s} |")  # fmt: skip
    if len(lines) == 3:  # (a quick run without the held-out series, say)
        return f"**{title}**: no points in this run"
    return "\n".join(lines)
