"""RUL on PRONOSTIA (FEMTO) bearings: the ims-rul protocol, unchanged, on bearings never tuned on.

Data: a local copy of the IEEE PHM 2012 challenge records (``--data DIR``; not shipped, see
:mod:`prognos_torch.datasets.pronostia`): the 17 run-to-failure bearings (``Learning_set``,
``Full_Test_Set``), each from the ``rms`` of its horizontal and of its vertical accelerometer
(one record every 10 s; time in hours). The protocol is that of the ``ims-rul`` study
(:mod:`prognos_torch.studies.rul_protocol`): threshold ``0.9 x`` the highest 5-point moving
median, end of life its first crossing, onset the first of 5 moving medians above mean + 4 std
of the first 30 % of life, predictions at 20/40/60/80/90 % of [onset, EoL] from the data up to
each time. Methods: those of ``ims-rul`` without the power shape (the worst there) and the
earlier workflow's ``fit_series + rul(stpf)`` (an ANFIS trained at every point, which is slow
on series of thousands of records). No setting of ``prognose`` was chosen on these bearings.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from prognos_torch.datasets.pronostia import find_pronostia_bearings, read_pronostia_bearing
from prognos_torch.plots import plot_rul_trajectory
from prognos_torch.prognosis.protocol import PROTOCOL_MIN_POINTS
from prognos_torch.studies import Study, StudyConfig, StudyDataError, StudyResult
from prognos_torch.studies.rul_protocol import (
    RUL_BASELINES,
    conformal_rows,
    headline_table,
    protocol_rows,
)

MAIN = "prognose (auto)"
CONFORMAL = f"{MAIN} + conformal"
METHODS = (MAIN, "prognose (exponential)", "prognose (elm)", "prognose (linear)",
           "prognose (auto, strong tracking)", "prognose (auto, ekf+stekf pool)",
           *RUL_BASELINES[1:])  # fmt: skip
METRICS = ["in_cone_0.2", "in_cone_0.3", "covered", "abs_error", "rel_error", "censored",
           "crps_log"]  # fmt: skip
QUICK_BEARINGS = 2


def series_cases(root: Path, quick: bool) -> dict:
    """``{"<bearing> <axis>": (hours, rms, True)}`` for every run-to-failure bearing."""
    folders = find_pronostia_bearings(root)
    if quick:
        folders = dict(list(folders.items())[:QUICK_BEARINGS])
    cases = {}
    for name, folder in folders.items():
        try:
            f = read_pronostia_bearing(folder)
        except ValueError as exc:  # a malformed record: one error line, not a traceback
            raise StudyDataError(str(exc)) from None
        if f.hours.numel() < PROTOCOL_MIN_POINTS:
            raise StudyDataError(
                f"{folder}: {f.hours.numel()} records; the protocol needs at least "
                f"{PROTOCOL_MIN_POINTS} (a run to failure)"
            )
        rms = f.feature("rms")
        cases[f"{name} h"] = (f.hours, rms[:, 0], True)
        cases[f"{name} v"] = (f.hours, rms[:, 1], True)
    return cases


def run(cfg: StudyConfig, out: Path) -> StudyResult:
    t_start = time.perf_counter()
    torch.set_num_threads(1)
    cases = series_cases(Path(cfg.data), cfg.quick)
    methods = (MAIN, "prognose (exponential)", *RUL_BASELINES[1:]) if cfg.quick else METHODS
    rows, panels, per_series, _ = protocol_rows(
        cases, methods, seed=cfg.seed, every=2 if cfg.quick else 1, time_unit="hours",
        cone_methods=(MAIN, *RUL_BASELINES[1:]),
    )  # fmt: skip
    # the 90 % intervals of auto calibrated on the other bearings' points
    rows += conformal_rows(rows, MAIN, lambda name: name.split()[0])
    methods = (MAIN, CONFORMAL, *methods[1:])
    figs = _figure(out, panels)
    tables = [_axis_table(rows, methods, axis) for axis in ("h", "v")]
    tables.append(headline_table(rows, methods, "both axes", held_out=None))
    tables.append("| series | method | CRA | PH (alpha = 0.2 of [onset, EoL], h) |\n"
                  "|---|---|---|---|\n" + "\n".join(per_series))  # fmt: skip
    return StudyResult(rows=rows, metrics=METRICS, figures=figs, notes=_notes(cfg, t_start),
                       extra_tables=tables, config={"methods": list(methods),
                                                    "series": list(cases)})  # fmt: skip


def _axis_table(rows, methods, axis: str) -> str:
    sel = [r for r in rows if r["series"].endswith(f" {axis}")]
    title = {"h": "horizontal accelerometer rms", "v": "vertical accelerometer rms"}[axis]
    return headline_table(sel, methods, title, held_out=None)


def _figure(out: Path, panels) -> list[str]:
    if not panels:
        return []
    plot_rul_trajectory(out / "rul_vs_time.png", panels, alpha=0.3, ncols=4, time_unit="hours")
    return ["rul_vs_time.png"]


def _notes(cfg: StudyConfig, t_start: float) -> str:
    return f"""Notes
- Held out: no setting of prognose was chosen on PRONOSTIA; the methods run as in ims-rul.
  Protocol not usable (no onset before end of life, or fewer than 10 samples from onset to end
  of life) is listed per series below and leaves the series out.
- pred = median of the RUL distribution (inf when more than half is censored); 90 % interval =
  [q05, q95], open to the right when more than 5 % is censored. RUL in hours.
- Wall time {time.perf_counter() - t_start:.0f} s{" (quick mode: 2 bearings, 3 points)" if cfg.quick else ""}.
"""


STUDY = Study(
    name="pronostia-rul",
    paper="issue 12",
    title="RUL on PRONOSTIA (FEMTO) run-to-failure bearings (known-threshold protocol)",
    run=run,
    default_runs=1,
    needs_data="PRONOSTIA (FEMTO, IEEE PHM 2012) bearing records",
)
