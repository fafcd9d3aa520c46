"""``prognos rul DATA.csv --column C --threshold X``: RUL straight from a CSV (no model file).

The command line face of :func:`~prognos_torch.workflow.prognose`; ``prognos rul MODEL DATA``
(a fitted learner) stays in :mod:`prognos_torch.cli`.
"""

from __future__ import annotations

import math

__all__ = ["run_prognose", "observed_rul", "fmt_time", "within_probability"]


def fmt_time(v: float) -> str:
    """A time on the series' clock with 10 significant digits: Unix seconds (1.7e9) and day
    counts keep the digits that tell two times apart (``%g`` prints 1700021180 and
    1700017580 both as 1.70002e+09)."""
    return f"{v:.10g}"


def _fmt(v, digits: int = 4) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return "inf" if math.isinf(v) else f"{v:.{digits}g}"
    return str(v)


def within_probability(res, within: float, hint: str = "") -> float | None:
    """``res.failure_probability(within)`` for ``--within``, read before anything is printed;
    a refusal names the option and, for a span beyond the horizon, ends with ``hint``."""
    try:
        return res.failure_probability(within)
    except ValueError as exc:
        beyond = hint if within > res.bound else ""
        raise ValueError(f"--within: {exc}{beyond}") from None


def observed_rul(truth, t_eval: float, threshold: float, direction: str) -> float | None:
    """Time from ``t_eval`` to the first later time the trailing 5-point median of the
    observed ``truth`` series reaches ``threshold`` (``None``: not in the data)."""
    from .prognosis import moving_median

    m = moving_median(truth.values, 5)
    hit = (m >= threshold) if direction == "above" else (m <= threshold)
    idx = (hit & (truth.t > t_eval)).nonzero()
    if idx.numel() == 0:
        return None
    return float(truth.t[idx[0, 0]]) - t_eval


def run_prognose(args, series, data_cfg: dict, truth=None) -> str | None:
    """Run ``prognose`` on the loaded series and print the result (and write ``--plot``).

    Returns:
        ``None``, or the sentence for the ``censored RUL:`` line when more than 5 % of the
        distribution lies beyond the horizon, so that its 95 % quantile is unknown (the command
        then exits 3, as ``prognos rul MODEL DATA`` does for any censored mass: its horizon is
        the user's, while ``prognose`` runs until every path crosses or a horizon long enough
        for the model, and a few paths beyond it leave every reported quantile intact).
    """
    from .plots import plot_prognosis
    from .workflow import prognose
    from .workflow.prognose import CENSORED_FLAG, _filters

    filt = "ekf" if args.filter is None else args.filter
    try:
        _filters(filt)
    except ValueError as exc:
        raise ValueError(f"--filter: {exc}") from None
    res = prognose(
        series,
        args.threshold,
        method=args.method,
        filter=filt,
        seed=0 if args.seed is None else args.seed,
        direction=args.direction,
        n_paths=args.paths,
    )
    unit, s = res.time_unit, res.summary()
    p_within = None if args.within is None else within_probability(res, args.within)
    where = data_cfg.get("where") or {}
    sel = f" ({', '.join(f'{k}={v}' for k, v in where.items())})" if where else ""
    print(
        f"RUL of {series.name!r}{sel} from {series.source} at t = {fmt_time(res.t_last)} {unit}: "
        f"threshold {res.threshold:g} ({res.direction})"
    )
    on = res.onset
    onset = f"{fmt_time(on.time)} {unit} ({on.method}, baseline mean {on.baseline.mean:.4g}, std " \
        f"{on.baseline.std:.4g})" if on is not None and on.detected else "not detected"  # fmt: skip
    rows = [("status", res.status), ("degradation onset", onset)]
    if res.status == "ok":
        scores = (res.selection or {}).get("scores") or {}
        chosen = res.model + (
            " (backtest: " + ", ".join(f"{k} {v:.3g}" for k, v in scores.items()) + ")"
            if scores
            else ""
        )
        rows += [
            ("trend model", chosen),
            (f"median RUL ({unit})", _fmt(s["median"])),
            (f"90 % interval ({unit})", f"[{_fmt(s['q05'])}, {_fmt(s['q95'])}]"),
            ("censored mass", f"{s['censored_mass']:.3f} (RUL > {_fmt(s['bound'])} {unit})"),
        ]
    else:
        rows += [(f"lower bound if it stays healthy ({unit})", _fmt(s["bound"]))]
    if args.within is not None:
        rows.append(
            (
                f"P(failure within {args.within:g} {unit})",
                f"{p_within:.3f}" if p_within is not None else f"n/a ({res.status})",
            )
        )
    if truth is not None:
        obs = observed_rul(truth, res.t_last, res.threshold, res.direction)
        rows.append(
            (f"observed RUL ({unit})", "not reached in the data" if obs is None else _fmt(obs))
        )
    width = max(len(r[0]) for r in rows)
    for k, v in rows:
        print(f"  {k.ljust(width)}  {v}")
    for f in res.flags:
        print(f"warning: {f}")
    if args.plot is not None:
        tr = None if truth is None else (truth.t, truth.values)
        plot_prognosis(args.plot, res, truth=tr)
        print(f"figure written to {args.plot}")
    if res.status == "ok" and res.censored_mass > CENSORED_FLAG:
        return (
            f"{100 * res.censored_mass:.3g} % of the predicted paths do not reach the threshold "
            f"{res.threshold:g} within the horizon of {res.bound:g} {unit}; their RUL exceeds it "
            "and the mean is withheld"
        )
    return None
