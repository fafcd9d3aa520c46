"""The report of a forecaster matrix: its figures and the numbers its readings quote.

:func:`matrix_figures` draws a :class:`~prognos_torch.studies.matrix.MatrixResult` as three
heatmap figures (:func:`~prognos_torch.plots.plot_heatmaps`): the one-step RMSE of each
forecaster alone (learner x trainer), of every (learner-trainer) x filter, and the RUL of one
problem (error of the median as text, alpha-lambda mass as colour). :func:`best_label`,
:func:`ratio_text`, :func:`most_hits` and :func:`always_censored` are the summaries a study's
notes quote, :func:`problem_summary` all of them for one problem.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from ..plots import HeatmapPanel, plot_heatmaps
from .matrix import MatrixResult

__all__ = [
    "always_censored",
    "best_label",
    "matrix_figures",
    "most_hits",
    "problem_summary",
    "ratio_text",
]

FIGURES = ("fig1_one_step_rmse.png", "fig2_filters_one_step_rmse.png", "fig3_rul.png")


def matrix_figures(
    res: MatrixResult, out_dir: Path, *, rul_problem: str | None = None, alpha: float = 0.3
) -> list[str]:
    """Write the matrix's heatmaps to ``out_dir``; returns their file names.

    1. one-step RMSE (log colour) of each forecaster alone, learner x trainer, one panel per
       problem, the first reference forecaster's RMSE in the title;
    2. one-step RMSE (log colour) of every (learner-trainer) x filter, one panel per problem;
    3. with ``rul_problem``: its RUL per (learner-trainer) x filter, the mean error of the
       median as text ("cens." when every median lies beyond the horizon, the censored share
       when some do), the alpha-lambda mass (cone ``±alpha``) as colour.
    """
    n = len(res.problems)
    panels = []
    for p in res.problems:
        ref_name = res.references[0]
        ref = res.mean(res.combo(p, ref_name, "none"), "none", "RMSE_1")
        title = f"{p}: one-step RMSE, forecaster alone\n({ref_name} {ref:.3f})"
        h = res.heatmap(p, "RMSE_1", alone=True, log=True, fmt=".3f")
        panels.append(HeatmapPanel(*h, title=title, cmap="viridis_r", colorbar="log10 RMSE"))
    plot_heatmaps(out_dir / FIGURES[0], panels, figsize=(5.0 * n, 3.4))
    panels = [
        HeatmapPanel(
            *res.heatmap(p, "RMSE_1", log=True, fmt=".3g"),
            title=f"{p}: one-step RMSE",
            cmap="viridis_r",
            colorbar="log10 RMSE",
        )
        for p in res.problems
    ]
    plot_heatmaps(out_dir / FIGURES[1], panels, figsize=(5.0 * n, 6.0))
    if rul_problem is None:
        return list(FIGURES[:2])

    def rul_text(c: str, f: str, mass: float) -> str:
        err, cens = res.mean(c, f, "RUL_MAE_d"), res.mean(c, f, "RUL_censored")
        text = f"{err:.2f} d" if math.isfinite(err) else "cens."
        return text + (f"\n{cens:.0%} c" if 0 < cens < 1 else "")

    title = (
        f"{rul_problem}: RUL error of the median (text; 'cens.': beyond the horizon)\n"
        f"colour: P(RUL within ±{alpha:.0%} of the truth at t_lambda)"
    )
    panel = HeatmapPanel(
        *res.heatmap(rul_problem, "AL_mass", text=rul_text),
        title=title,
        cmap="viridis",
        clim=(0.0, 1.0),
        colorbar="alpha-lambda mass",
    )
    plot_heatmaps(out_dir / FIGURES[2], [panel], figsize=(6.5, 6.0))
    return list(FIGURES)


def best_label(
    res: MatrixResult,
    problem: str,
    metric: str,
    filters: Sequence[str] | None = None,
    high: bool = False,
) -> tuple[float, str]:
    """:meth:`~MatrixResult.best` as ``(value, "<learner>-<trainer> + <filter>")``;
    ``(nan, "— + —")`` when no cell has a value."""
    b = res.best(problem, metric, filters, high) or (math.nan, " | —", "—")
    return b[0], f"{b[1].split(' | ')[1]} + {b[2]}"


def ratio_text(res: MatrixResult, problem: str, metric: str = "RMSE_1") -> str:
    """``"PF 1.40, EKPF 1.64, ..."``: :meth:`~MatrixResult.median_ratio` of each filter other
    than ``"none"``, two decimals."""
    fs = [f for f in res.filters if f != "none"]
    return ", ".join(f"{f} {res.median_ratio(problem, f, metric):.2f}" for f in fs)


def most_hits(res: MatrixResult, problem: str) -> tuple[int, int]:
    """``(hits, runs)`` of the cell of ``problem`` (references left out) whose runs meet
    alpha-lambda most often (ties: more runs); ``(0, 0)`` without alpha-lambda scores."""
    refs = {res.combo(problem, r, "none") for r in res.references}
    hits = [
        (round(st["alpha_lambda"].mean * st["alpha_lambda"].n), st["alpha_lambda"].n)
        for meth, st in res.summary.items()
        if meth.startswith(f"{problem} | ")
        and meth.rsplit(" | ", 1)[0] not in refs
        and "alpha_lambda" in st
    ]
    return max(hits) if hits else (0, 0)


def always_censored(res: MatrixResult, problem: str, fname: str = "none") -> list[str]:
    """The ``"<learner>-<trainer>"`` of ``problem`` whose RUL is censored at every prediction
    time with filter ``fname`` (mean ``RUL_censored`` of 1)."""
    return [
        c.split(" | ")[1]
        for c, _, _ in res.combos(problem)
        if res.summary.get(f"{c} | {fname}") and res.mean(c, fname, "RUL_censored") == 1.0
    ]


def problem_summary(res: MatrixResult, problem: str, horizon: int = 10) -> dict[str, object]:
    """The numbers a reading quotes about one problem (a note template's ``{HI_sum[best]}``).

    Keys: ``best``, ``best_name``: lowest mean one-step RMSE (:func:`best_label`); ``alone``,
    ``alone_name``: the same with filter ``"none"``; ``best_h``, ``best_h_name``: lowest
    ``RMSE_<horizon>``; ``ratios``: :func:`ratio_text`; ``best_mass``, ``best_mass_name``:
    highest alpha-lambda mass; ``bias_min``, ``bias_max``: range of the mean RUL bias (NaN
    without RUL scores); ``hits``, ``hits_n``: :func:`most_hits`; ``censored_alone``:
    :func:`always_censored` joined by commas, or ``"no combination"``.
    """
    out: dict[str, object] = {}
    for key, metric, fs, high in (
        ("best", "RMSE_1", None, False),
        ("alone", "RMSE_1", ("none",), False),
        ("best_h", f"RMSE_{horizon}", None, False),
        ("best_mass", "AL_mass", None, True),
    ):
        out[key], out[key + "_name"] = best_label(res, problem, metric, fs, high)
    bias = res.means(problem, "RUL_bias_d") or [math.nan]
    out["hits"], out["hits_n"] = most_hits(res, problem)
    return out | {
        "ratios": ratio_text(res, problem),
        "bias_min": min(bias),
        "bias_max": max(bias),
        "censored_alone": ", ".join(always_censored(res, problem)) or "no combination",
    }
