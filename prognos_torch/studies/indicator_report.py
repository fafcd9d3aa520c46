"""Fig. 8-13 of paper 002's protocol on a measured indicator
(:mod:`prognos_torch.studies.indicator_protocol`), drawn from a run's results in the paper's
style: one-step predictions and their errors, the fault probability, the RUL pmf and the
alpha-lambda plot (run 0; the files carry the paper's figure numbers). The drawing is the
library's :mod:`prognos_torch.plots`; this module only lays the protocol's results out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from torch import Tensor

from ..plots import (
    LinePanel,
    plot_alpha_lambda,
    plot_fault_probability,
    plot_fault_probability_box,
    plot_line_panels,
    plot_rul_pdf,
)
from .indicator_protocol import IndicatorCase, MethodResult

__all__ = ["indicator_figure", "protocol_figures"]


def protocol_figures(
    out_dir: Path,
    one_step: Mapping[str, MethodResult],
    results: Mapping[str, MethodResult],
    case: IndicatorCase,
    *,
    short: Mapping[str, str],
    tail: Tensor,
    span_labels: tuple[str, str],
    paper_idx: Sequence[int],
    alpha: float,
    lam: float,
    decision: float = 0.5,
    pmf_bin: tuple[int, str] = (1, "1-step"),
    gap: float | None = None,
) -> list[str]:
    """Fig. 8-13 in the paper's style (run 0, times in days); returns the file names written to
    ``out_dir``.

    Args:
        one_step: the methods of Fig. 8-9 (one-step predictions and their absolute errors).
        results: every method: Fig. 10 (fault probability per step and per ``1`` time unit)
            and 12 (RUL pmf at the prediction times ``paper_idx``, mean over the runs) for the
            filters, Fig. 13 (alpha-lambda, ``alpha``, ``lam``) for all.
        short: ``{name: file-name part}``.
        tail: ``(T',)`` mask of the zoom of Fig. 9(b); span_labels: the titles' names of the
            whole span and of the zoom.
        decision: fault probability that declares a fault (the paper: 0.5).
        pmf_bin: steps per bin of the RUL pmf and the bin's label (display only).
        gap: break the lines of Fig. 8-9 at recording gaps longer than this.
    """
    t_tgt, truth, thr = case.t_target, case.truth, case.threshold
    preds0 = {n: r.pred if r.filter is None else r.pred[:, 0] for n, r in one_step.items()}
    panels = [
        LinePanel(
            {"one-step prediction": p},
            title=f"({'abcd'[i]}) {name}",
            truth=truth,
            truth_label="test indicator",
            hline=thr,
            gap=gap,
            legend="upper left" if i == 0 else None,
        )
        for i, (name, p) in enumerate(preds0.items())
    ]
    plot_line_panels(
        out_dir / "fig8_one_step.png",
        t_tgt,
        panels,
        ncols=2,
        lw=0.7,
        xlabel="time (days)",
        figsize=(8.0, 7.0),
    )
    err = {n: (p - truth).abs() for n, p in preds0.items()}
    plot_line_panels(
        out_dir / "fig9_abs_error.png",
        t_tgt,
        [
            LinePanel(
                err,
                title=f"(a) absolute one-step error, {span_labels[0]} (run 0)",
                ylabel="|error|",
                gap=gap,
                legend="upper left",
            ),
            LinePanel(
                {n: e[tail] for n, e in err.items()},
                x=t_tgt[tail],
                style=".-",
                gap=gap,
                title=f"(b) absolute one-step error, {span_labels[1]} (run 0)",
                ylabel="|error|",
                legend="upper left",
            ),
        ],
        xlabel="time (days)",
        lw=0.7,
        figsize=(8.0, 5.5),
    )
    figs = ["fig8_one_step.png", "fig9_abs_error.png"]
    for name, r in results.items():
        if r.filter is None:
            continue
        fn, fb, fr = (
            f"fig{k}_{short[name]}.png"
            for k in ("10_fault_probability", "10_fault_probability_box", "12_rul_pdf")
        )
        fault0 = r.filter.fault[:, 0]
        plot_fault_probability(
            out_dir / fn,
            t_tgt,
            {name: fault0},
            decision=decision,
            title=f"{name}: fault probability per step (threshold {thr:g}, run 0)",
        )
        plot_fault_probability_box(
            out_dir / fb,
            t_tgt,
            fault0,
            period=1.0,
            decision=decision,
            title=f"{name}: fault probability per day (run 0)",
        )
        support, pmf = r.rul.binned(pmf_bin[0])  # display only: mean pmf over the runs
        plot_rul_pdf(
            out_dir / fr,
            [round(v, 2) for v in case.times[paper_idx].tolist()],
            support,
            pmf[paper_idx].mean(1),
            true_rul=case.true_rul[paper_idx],
            censored_mass=r.rul.censored_mass[paper_idx].mean(1),
            title=f"{name}: RUL pmf (mean of {r.rul_pred.shape[1]} runs, {pmf_bin[1]} bins, "
            f"cap {case.horizon:g} d)",
        )
        figs += [fn, fb, fr]
    for name, r in results.items():
        fa = f"fig13_alpha_lambda_{short[name]}.png"
        runs = r.rul_pred.shape[1]
        kind = "deterministic" if r.filter is None else f"bars: range over {runs} runs"
        plot_alpha_lambda(
            out_dir / fa,
            case.times,
            case.true_rul,
            r.rul_pred[:, 0],
            alpha=alpha,
            lower=r.rul_pred.min(-1).values,
            upper=r.rul_pred.max(-1).values,
            lam=lam,
            t_eol=case.t_eol,
            title=f"{name}: RUL (Eq. 28); {kind}",
        )
        figs.append(fa)
    return figs


def indicator_figure(
    path: Path,
    t: Tensor,
    lines: Mapping[str, Tensor],
    *,
    threshold: float,
    t_eol: float,
    title: str,
    ylabel: str,
    xlabel: str,
    gap: float | None = None,
) -> None:
    """Fig. 1: indicator series ``{label: (T,)}`` over ``t`` ``(T,)`` with the failure threshold
    and the end of life (first crossing) of the test series."""
    panel = LinePanel(dict(lines), title=title, ylabel=ylabel, hline=threshold, vline=t_eol,
                      gap=gap, vline_label=f"test crosses at {t_eol:.2f} d",
                      legend="upper left")  # fmt: skip
    plot_line_panels(path, t, [panel], xlabel=xlabel, lw=0.7)
