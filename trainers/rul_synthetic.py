"""RUL on synthetic run-to-failure data from processes outside prognose's trend models.

The selection set of ``prognose(method="auto")``: records of four degradation families
(:mod:`prognos_torch.systems.run_to_failure`: compound-Poisson shocks, Paris-law crack growth,
two-phase exponential with a jump and AR(1) wander, exponential with a transient hump; Gaussian
or Student-t noise, recording gaps), scored under the same known-threshold protocol as the IMS
bearings (:func:`~prognos_torch.prognosis.protocol.known_threshold_protocol`; predictions at
20/40/60/80/90 % of [onset, EoL] from the data up to each time). Rules chosen here are chosen
on data that no trend model contains, so the IMS bearings (``ims-rul``) stay a held-out check.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from prognos_torch.plots import plot_rul_trajectory
from prognos_torch.studies import Study, StudyConfig, StudyResult
from prognos_torch.studies.rul_protocol import conformal_rows, headline_table, protocol_rows
from prognos_torch.systems import RUN_TO_FAILURE_FAMILIES, run_to_failure_set

MAIN = "prognose (auto)"
CONFORMAL = f"{MAIN} + conformal"
METHODS = (MAIN, "prognose (exponential)", "prognose (elm)", "prognose (power)",
           "prognose (linear)", "linear slope", "exponential LSQ")  # fmt: skip
METRICS = ["in_cone_0.2", "in_cone_0.3", "covered", "abs_error", "rel_error", "crps_log"]
PER_FAMILY = 5  # records per family in the full run (100 prediction points)


def run(cfg: StudyConfig, out: Path) -> StudyResult:
    t_start = time.perf_counter()
    torch.set_num_threads(1)
    records = run_to_failure_set(1 if cfg.quick else PER_FAMILY, seed=cfg.seed)
    cases = {name: (r.t, r.y, True) for name, r in records.items()}
    methods = (MAIN, "prognose (exponential)", "exponential LSQ") if cfg.quick else METHODS
    rows, panels, per_series, _ = protocol_rows(
        cases, methods, seed=cfg.seed, every=2 if cfg.quick else 1, time_unit="days",
        cone_methods=(MAIN, "prognose (exponential)", "exponential LSQ"),
    )  # fmt: skip
    # the 90 % intervals of auto calibrated on the other seriess' points
    rows += conformal_rows(rows, MAIN, lambda name: name)
    methods = (MAIN, CONFORMAL, *methods[1:])
    plot_rul_trajectory(
        out / "rul_vs_time.png", panels[:: max(1, len(panels) // 8)], alpha=0.3, time_unit="days"
    )
    tables = [headline_table(rows, methods, "all families")]
    for fam in RUN_TO_FAILURE_FAMILIES:
        fam_rows = [r for r in rows if r["series"].split()[0] == fam]
        tables.append(headline_table(fam_rows, methods, f"family: {fam}"))
    tables.append("| series | method | CRA | PH (alpha = 0.2 of [onset, EoL]) |\n|---|---|---|---|\n"
                  + "\n".join(per_series))  # fmt: skip
    n = len(records)
    notes = f"""Notes
- {n} records ({n // len(RUN_TO_FAILURE_FAMILIES)} per family, seed {cfg.seed}); times in days,
  sampled every 10 minutes with up to 3 recording gaps. Nothing of prognose was fitted to these
  records; they are where its `auto` rule was chosen (docs/RESULTS.md).
- pred = median of the RUL distribution (inf when more than half is censored); 90 % interval
  [q05, q95]; crps_log: CRPS of the log RUL (censored at 10 x the truth), lower is better.
- Wall time {time.perf_counter() - t_start:.0f} s{" (quick mode: 1 record per family, 3 points)" if cfg.quick else ""}.
"""
    return StudyResult(rows=rows, metrics=METRICS, figures=["rul_vs_time.png"], notes=notes,
                       extra_tables=tables, config={"methods": list(methods),
                                                    "records": list(records)})  # fmt: skip


STUDY = Study(
    name="rul-synthetic",
    paper="issue 12",
    title="RUL on synthetic run-to-failure families outside the trend models (selection set)",
    run=run,
    default_runs=1,
)
