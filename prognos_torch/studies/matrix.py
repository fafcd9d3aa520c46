"""A forecaster matrix: every learner x trainer x prognostic filter on every test problem.

:func:`run_forecaster_matrix` trains each (learner, trainer) combination on each
:class:`~prognos_torch.studies.forecasters.ForecastProblem` (``R`` Monte Carlo runs), flags the
runs that diverged in training, sets the filters' noise from the training residuals and scores
the forecaster alone and inside each filter
(:func:`~prognos_torch.studies.forecasters.evaluate_filtered`). Every cell of the matrix gets a
status (:class:`Cell`: evaluated, not applicable, skipped, failed) and a note (warnings raised,
runs diverged, the error of a failed filter); reference forecasters (e.g. persistence) add a
row each. :class:`MatrixResult` answers the questions a reader asks of the matrix: the mean of
a metric in a cell, the cost, the best combination with ties broken by cost, and writes the
full table (:meth:`MatrixResult.table`), one learner x trainer pivot per problem
(:meth:`MatrixResult.pivots`) and heatmap panels (:meth:`MatrixResult.heatmap`).
:func:`filter_factories` builds the filters of a matrix by name, :func:`matrix_metrics` names
its metric columns. The learners are trained by :mod:`.matrix_training`, the figures drawn by
:mod:`.matrix_report`.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from ..filters import PARTICLE_FILTERS, make_filter, make_particle_filter
from ..optim import StackedLearner
from .forecasters import (
    RUL_KEYS,
    ForecastProblem,
    ForecastProtocol,
    evaluate_alone,
    evaluate_filtered,
    healthy_runs,
    residual_noise,
)
from .tables import Stat, markdown_table, summarize

__all__ = [
    "Cell",
    "Footnotes",
    "MatrixResult",
    "capture",
    "filter_factories",
    "matrix_metrics",
    "run_forecaster_matrix",
]

EVAL_ERRORS = (FloatingPointError, torch.linalg.LinAlgError, ValueError)


def matrix_metrics(horizon: int = 10) -> list[str]:
    """The per-run metrics of a matrix's summary table, in order (the RUL ones are empty on
    problems without a threshold)."""
    return ["RMSE_1", "MAE_1", f"RMSE_{horizon}", f"MAE_{horizon}", *RUL_KEYS, "time_s"]


def filter_factories(
    names: Sequence[str], n_particles: int
) -> dict[str, Callable[[], object] | None]:
    """``name -> factory`` of each filter of a matrix (:func:`run_forecaster_matrix`):
    ``"none"`` -> ``None`` (the forecaster alone), particle filters by
    :func:`~prognos_torch.filters.make_particle_filter` name (``"PF"``, ``"EKPF"``, ``"STPF"``,
    ...) with ``n_particles``, Gaussian filters by :func:`~prognos_torch.filters.make_filter`
    name (``"SCKF"``, ``"STSCKF"``, ...)."""
    out: dict[str, Callable[[], object] | None] = {}
    for f in names:
        if f == "none":
            out[f] = None
        elif f.lower() in PARTICLE_FILTERS:
            out[f] = lambda f=f: make_particle_filter(f, num_particles=n_particles)
        else:
            make_filter(f)  # an unknown name fails here, not inside the matrix
            out[f] = lambda f=f: make_filter(f)
    return out


@dataclass(frozen=True)
class Cell:
    """What happened to one (problem, learner, trainer, filter): ``status`` is ``"ok"``,
    ``"n/a"``, ``"skipped"`` or ``"failed"``; ``note`` says why or what was seen."""

    status: str
    note: str = ""


def capture(
    fn: Callable[..., dict], *args, errors=EVAL_ERRORS, what: str = "filter"
) -> tuple[dict, str]:
    """``fn(*args)`` with its warnings recorded and the ``errors`` caught.

    Returns:
        ``(result, note)``: ``{}`` and ``"<what> failed: <error>"`` when ``fn`` raised one of
        ``errors``; the note ends with ``"<n> warnings (<kinds>)"`` when warnings were raised.
    """
    res, note = {}, ""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            res = fn(*args)
        except errors as exc:
            note = f"{what} failed: {type(exc).__name__}: {str(exc)[:80]}"
    kinds = sorted({type(w.message).__name__ for w in caught})
    if kinds:
        note = (note + "; " if note else "") + f"{len(caught)} warnings ({', '.join(kinds)})"
    return res, note


class Footnotes:
    """Numbered notes for a table: :meth:`mark` gives each distinct text its ``[k]``."""

    def __init__(self) -> None:
        self.notes: dict[str, str] = {}

    def mark(self, text: str) -> str:
        if text not in self.notes:
            self.notes[text] = f"[{len(self.notes) + 1}]"
        return self.notes[text]

    def lines(self) -> list[str]:
        return [f"{k} {text}" for text, k in self.notes.items()]


def _fmt(v: float, std: float | None = None, digits: int = 4) -> str:
    if v is None or not math.isfinite(v):
        return "—"
    if abs(v) >= 1e3:  # a run that blew up: the scale is what matters
        return f"{v:.2e}" if std is None else f"{v:.2e} ± {std:.2e}"
    s = f"{v:.{digits}f}"
    return s if std is None else f"{s} ± {std:.{digits}f}"


@dataclass
class MatrixResult:
    """Rows, cell statuses and summaries of a forecaster matrix.

    Attributes:
        rows: one dict per (run, method); method ``"<problem> | <learner>-<trainer> | <filter>"``.
        cells: ``{(combo, filter): Cell}`` with ``combo = "<problem> | <learner>-<trainer>"``.
        info: per combo ``train_s`` (seconds per run), ``diverged_runs``, ``train_rms``.
        problems, learners, trainers, filters: the names, in order.
        references: names of the reference forecasters (one ``<name>-none`` combo each).
        summary: :func:`~prognos_torch.studies.summarize` of the rows per method.
    """

    rows: list[dict]
    cells: dict[tuple[str, str], Cell]
    info: dict[str, dict]
    problems: list[str]
    learners: list[str]
    trainers: list[str]
    filters: list[str]
    references: list[str] = field(default_factory=list)
    summary: dict[str, dict[str, Stat]] = field(default_factory=dict)

    @staticmethod
    def combo(problem: str, learner: str, trainer: str) -> str:
        return f"{problem} | {learner}-{trainer}"

    def combos(self, problem: str, with_ref: bool = False) -> list[tuple[str, str, str]]:
        """``(combo, learner, trainer)`` of a problem (with the references last)."""
        out = [
            (self.combo(problem, ln, tn), ln, tn) for ln in self.learners for tn in self.trainers
        ]
        if with_ref:
            out += [(self.combo(problem, r, "none"), r, "none") for r in self.references]
        return out

    def stat(self, combo: str, fname: str, metric: str) -> Stat | None:
        return self.summary.get(f"{combo} | {fname}", {}).get(metric)

    def mean(self, combo: str, fname: str, metric: str) -> float:
        st = self.stat(combo, fname, metric)
        return st.mean if st else math.nan

    def std(self, combo: str, fname: str, metric: str = "RMSE_1") -> float:
        st = self.stat(combo, fname, metric)
        return st.std if st else math.nan

    def cost(self, combo: str, fname: str) -> float:
        """Mean seconds per run: evaluation plus training (``inf`` when not evaluated)."""
        t, tr = self.stat(combo, fname, "time_s"), self.stat(combo, fname, "train_s")
        return (t.mean if t else math.inf) + (tr.mean if tr else 0.0)

    def best(
        self,
        problem: str,
        metric: str,
        filters: Sequence[str] | None = None,
        high: bool = False,
        tie: float = 5e-3,
    ) -> tuple[float, str, str] | None:
        """The evaluated ``(value, combo, filter)`` with the best mean ``metric`` on a problem.

        Values within ``tie`` (relative) of the best count as ties; among them the cheapest
        (:meth:`cost`) wins, so that an exact equivalent does not hide the cheap route.
        """
        filters = self.filters if filters is None else filters
        cand = [
            (self.mean(c, f, metric), c, f)
            for c, _, _ in self.combos(problem)
            for f in filters
            if math.isfinite(self.mean(c, f, metric))
        ]
        if not cand:
            return None
        top = (max if high else min)(v for v, _, _ in cand)
        tied = [x for x in cand if abs(x[0] - top) <= tie * abs(top)]
        return min(tied, key=lambda x: self.cost(x[1], x[2]))

    def means(self, problem: str, metric: str, filters: Sequence[str] | None = None) -> list[float]:
        """The finite means of ``metric`` over a problem's combinations and ``filters``."""
        filters = self.filters if filters is None else filters
        out = [self.mean(c, f, metric) for c, _, _ in self.combos(problem) for f in filters]
        return [v for v in out if math.isfinite(v)]

    def median_ratio(self, problem: str, fname: str, metric: str = "RMSE_1") -> float:
        """Median over a problem's combinations of ``metric`` with filter ``fname`` divided by
        the forecaster alone (``"none"``); NaN when no combination has both."""
        r = [
            self.mean(c, fname, metric) / self.mean(c, "none", metric)
            for c, _, _ in self.combos(problem)
        ]
        r = [x for x in r if math.isfinite(x)]
        return float(np.median(r)) if r else math.nan

    def value_label(self, combo: str, fname: str, text: str) -> str:
        """``text``, with the count of runs behind it when some runs diverged."""
        n_ok = (self.stat(combo, fname, "RMSE_1") or Stat(0, 0, 0)).n
        total = (self.stat(combo, fname, "diverged") or Stat(0, 0, 0)).n
        return text if n_ok >= total else f"{text}\n({n_ok}/{total} runs)"

    def label(self, combo: str, fname: str) -> str:
        """Text of a cell without a value: n/a, skipped, diverged runs or a failed filter."""
        cell = self.cells[(combo, fname)]
        if cell.status in ("n/a", "skipped"):
            return cell.status
        return "div." if "diverged" in cell.note else "failed"

    def view(self, problem: str, kind: str = "mean") -> _View:
        """A mapping for note templates: ``view["ELM-closed none"]`` is the mean one-step RMSE
        of that cell, ``view["ANFIS-SRUKF STPF RMSE_10"]`` another metric; ``kind`` ``"std"``
        gives the standard deviation, ``"cost"`` :meth:`cost`, ``"diverged"`` the diverged
        runs of a ``"learner-trainer"`` combination."""
        return _View(self, problem, kind)

    # ---------------------------------------------------------------- tables
    def table(self, horizon: int = 10) -> str:
        """The full matrix: one row per (problem, learner, trainer, filter), ``mean ± std``."""
        notes = Footnotes()
        head = [
            "series", "learner", "trainer", "filter", "RMSE_1", "MAE_1", f"RMSE_{horizon}",
            "RUL err (d)", "RUL censored", "AL mass", "alpha-lambda hits", "runs ok", "s/run",
        ]  # fmt: skip
        lines = markdown_table(head, []).splitlines()
        for p in self.problems:
            for combo, ln, tn in self.combos(p, with_ref=True):
                for fname in self.filters if ln not in self.references else ("none",):
                    cell = self.cells[(combo, fname)]
                    lead = f"| {p} | {ln} | {tn} | {fname} |"
                    if cell.status in ("n/a", "skipped"):
                        word = cell.status
                        lines.append(lead + f" {word} {notes.mark(cell.note)} |" + f" {word} |" * 8)
                        continue

                    def g(m, std=False, d=4, c=combo, f=fname):
                        v = self.stat(c, f, m)
                        return _fmt(v.mean, v.std if std else None, d) if v else "—"

                    hits = self.stat(combo, fname, "alpha_lambda")
                    n_ok = (self.stat(combo, fname, "RMSE_1") or Stat(0, 0, 0)).n
                    hits_s = f"{round(hits.mean * hits.n)}/{hits.n}" if hits else "—"
                    t, tr = self.stat(combo, fname, "time_s"), self.stat(combo, fname, "train_s")
                    secs = (t.mean if t else 0.0) + (tr.mean if tr else 0.0)
                    flag = f" {notes.mark(cell.note)}" if cell.note else ""
                    rmse_h = g(f"RMSE_{horizon}", True)
                    lines.append(
                        lead
                        + f" {g('RMSE_1', True)}{flag} | {g('MAE_1')} | {rmse_h} |"
                        + f" {g('RUL_MAE_d', d=2)} | {g('RUL_censored', d=2)} |"
                        + f" {g('AL_mass', d=2)} | {hits_s} | {n_ok} | {secs:.3f} |"
                    )
        return "\n".join(lines + [""] + notes.lines())

    def pivots(self, metric: str = "RMSE_1", alone: str = "none") -> list[str]:
        """Per problem, learner x trainer: the forecaster alone and, in brackets, the filter with
        the lowest mean ``metric``."""
        out = []
        for p in self.problems:
            ref = self.mean(self.combo(p, self.references[0], "none"), alone, metric)
            rows = []
            for ln in self.learners:
                cs = []
                for tn in self.trainers:
                    combo = self.combo(p, ln, tn)
                    v = self.mean(combo, alone, metric)
                    if self.cells[(combo, alone)].status == "n/a":
                        cs.append("n/a")
                    elif not math.isfinite(v):
                        cs.append(self.label(combo, alone))
                    else:
                        fb = min(
                            ((self.mean(combo, f, metric), f) for f in self.filters),
                            key=lambda x: x[0] if math.isfinite(x[0]) else math.inf,
                        )
                        cs.append(f"{_fmt(v)} ({fb[1]} {_fmt(fb[0])})")
                rows.append([ln, *cs])
            intro = (
                f"{p}: one-step test RMSE of the forecaster alone (filter '{alone}'); "
                f"{self.references[0]} {ref:.4f}. In brackets: the filter with the lowest "
                "one-step RMSE.\n\n"
            )
            out.append(intro + markdown_table(["learner", *self.trainers], rows))
        return out

    def heatmap(
        self,
        problem: str,
        metric: str,
        *,
        alone: bool = False,
        log: bool = False,
        fmt: str = ".3g",
        text: Callable[[str, str, float], str] | None = None,
    ) -> tuple[np.ndarray, list[str], list[str], list[list[str]]]:
        """Values and labels of one heatmap: learner x trainer for the forecaster alone
        (``alone=True``) or (learner-trainer) x filter. Cells without a value are NaN with
        their :meth:`label`; ``log`` takes ``log10`` of the colour values; ``text(combo,
        filter, value)`` overrides the cell text."""
        if alone:
            rows, cols = list(self.learners), list(self.trainers)
            keys = [[(self.combo(problem, ln, tn), "none") for tn in cols] for ln in rows]
        else:
            combos = self.combos(problem)
            rows, cols = [f"{ln}-{tn}" for _, ln, tn in combos], list(self.filters)
            keys = [[(c, f) for f in cols] for c, _, _ in combos]
        vals = np.full((len(rows), len(cols)), np.nan)
        labels = [[""] * len(cols) for _ in rows]
        for i, row in enumerate(keys):
            for j, (c, f) in enumerate(row):
                v = self.mean(c, f, metric)
                if not math.isfinite(v):
                    labels[i][j] = self.label(c, f)
                    continue
                vals[i, j] = math.log10(v) if log else v
                labels[i][j] = text(c, f, v) if text else self.value_label(c, f, format(v, fmt))
        return vals, rows, cols, labels


class _View(Mapping):
    def __init__(self, result: MatrixResult, problem: str, kind: str) -> None:
        if kind not in ("mean", "std", "cost", "diverged"):
            raise ValueError(f"kind must be mean, std, cost or diverged, got {kind!r}")
        self.result, self.problem, self.kind = result, problem, kind

    def __getitem__(self, key: str):
        parts = key.split()
        combo = f"{self.problem} | {parts[0]}"
        if self.kind == "diverged":
            return self.result.info.get(combo, {}).get("diverged_runs", 0)
        if self.kind == "cost":
            return self.result.cost(combo, parts[1])
        metric = parts[2] if len(parts) > 2 else "RMSE_1"
        fn = self.result.mean if self.kind == "mean" else self.result.std
        return fn(combo, parts[1], metric)

    def __iter__(self):
        return iter(())

    def __len__(self) -> int:
        return 0


def run_forecaster_matrix(
    problems: Sequence[ForecastProblem],
    learners: Sequence[str],
    trainers: Sequence[str],
    filters: Mapping[str, Callable[[], object] | None],
    train: Callable[[str, str, ForecastProblem], object],
    *,
    runs: int,
    protocol: ForecastProtocol,
    r_share: float,
    shift_std: float,
    max_rmse: float,
    shared_runs: int,
    seed: int,
    device: str = "cpu",
    not_applicable: Callable[[str, str, ForecastProblem], str | None] = lambda ln, tn, p: None,
    skip: Callable[[str, str, str], str | None] = lambda ln, tn, f: None,
    references: Mapping[str, Callable] | None = None,
    progress: bool = True,
    desc: str = "forecaster-matrix",
) -> MatrixResult:
    """Train and evaluate every (problem, learner, trainer, filter).

    Args:
        problems: the test problems.
        learners, trainers: the names of the matrix rows.
        filters: ``name -> factory`` of each prognostic filter; ``None`` for the forecaster
            alone (named ``"none"`` by convention).
        train: ``(learner, trainer, problem) -> forecaster``: a
            :class:`~prognos_torch.optim.StackedLearner` of ``runs`` runs, or one shared
            deterministic forecaster (any leading dims), evaluated on ``shared_runs`` runs
            that differ in the filters' random draws only.
        protocol: the evaluation settings; r_share, shift_std: :func:`residual_noise`.
        max_rmse: training one-step RMSE above which a run counts as diverged (no metrics).
        seed: generator seed of the first (problem, filter); problem ``p`` and filter ``f``
            use ``seed + 10 p + f`` for every combination (common random numbers).
        not_applicable: reason a (learner, trainer) does not apply to a problem, or ``None``.
        skip: reason a (learner, trainer, filter) is not run (e.g. a reduced matrix), or
            ``None``.
        references: ``name -> forecaster`` evaluated alone on ``runs`` runs (e.g. persistence).
    """
    references = dict(references or {})
    names = [p.name for p in problems]
    res = MatrixResult([], {}, {}, names, list(learners), list(trainers), list(filters))
    res.references = list(references)
    rows, cells, info = res.rows, res.cells, res.info
    jobs = [(k, p, ln, tn) for k, p in enumerate(problems) for ln in learners for tn in trainers]
    bar = tqdm(jobs, desc=desc, disable=not progress)
    for k, s, ln, tn in bar:
        bar.set_postfix_str(f"{s.name} {ln}-{tn}")
        combo = res.combo(s.name, ln, tn)
        reason = not_applicable(ln, tn, s)
        if reason is not None:
            for fname in filters:
                cells[(combo, fname)] = Cell("n/a", reason)
            continue
        t0 = time.perf_counter()
        learner = train(ln, tn, s)
        stacked = isinstance(learner, StackedLearner)
        train_s = (time.perf_counter() - t0) / (runs if stacked else 1)
        n_runs = runs if stacked else min(runs, shared_runs)
        ok = healthy_runs(learner, s, n_runs, max_rmse=max_rmse)
        n_ok = int(ok.sum())
        info[combo] = {"train_s": train_s, "diverged_runs": n_runs - n_ok}
        if n_ok < n_runs and stacked:
            learner = learner.select(ok)
        kw = dict(r_share=r_share, shift_std=shift_std)
        SQ, SR, sres = residual_noise(learner, s, n_ok, **kw) if n_ok else (None, None, math.nan)
        info[combo]["train_rms"] = sres
        for fi, (fname, make) in enumerate(filters.items()):
            why = skip(ln, tn, fname)
            if why is not None:
                cells[(combo, fname)] = Cell("skipped", why)
                continue
            out, note, secs = {}, "", 0.0
            if n_ok:
                gen = torch.Generator(device=device).manual_seed(seed + 10 * k + fi)
                filt = None if make is None else make()
                t1 = time.perf_counter()
                args = (learner, filt, s, n_ok, SQ, SR, gen, protocol)
                out, note = capture(evaluate_filtered, *args)
                secs = (time.perf_counter() - t1) / n_ok
            else:
                note = (
                    "every run diverged in training (training one-step RMSE non-finite or "
                    f"above {max_rmse:g})"
                )
            if n_ok < n_runs and n_ok:
                note = (note + "; " if note else "") + f"{n_runs - n_ok} of {n_runs} runs diverged"
            cells[(combo, fname)] = Cell("failed" if not out else "ok", note)
            j = 0
            for i in range(n_runs):
                row = {"run": i, "method": f"{combo} | {fname}"}
                if out and bool(ok[i]):
                    row.update({k: float(v[j]) for k, v in out.items()})
                    j += 1
                row["diverged"] = float(not bool(ok[i]))
                row["train_s"], row["time_s"] = train_s, secs
                rows.append(row)
    for s in problems:  # references: evaluated alone on every run
        for name, ref in references.items():
            out = evaluate_alone(ref, s, runs, protocol)
            combo = res.combo(s.name, name, "none")
            cells[(combo, "none")] = Cell("ok")
            for i in range(runs):
                row = {"run": i, "method": f"{combo} | none"}
                row.update({k: float(v[i]) for k, v in out.items()})
                rows.append(row | {"diverged": 0.0, "train_s": 0.0, "time_s": 0.0})
    metrics = sorted({k for r in rows for k in r} - {"run", "method"})
    res.summary = summarize(rows, metrics)
    return res
