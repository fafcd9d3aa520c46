"""Study infrastructure: configuration, Monte Carlo bookkeeping and result files.

A study (one per paper, in the repository's ``trainers/`` folder) is a thin script that composes
library pieces and returns a :class:`StudyResult`; this module turns it into ``table.md``
(mean ± std over runs, with the paper's numbers beside ours), ``results.csv`` (one row per run
and method), ``run.json`` (configuration, versions, machine) and the figures the study saved.
:mod:`.tables` holds the table helpers every study uses (summaries over runs, markdown tables,
notes filled from a template); :mod:`.rows` builds the per-run result rows.
"""

from .rows import run_rows, write_rows_csv
from .runner import (
    Study,
    StudyConfig,
    StudyResult,
    discover_studies,
    load_trainer,
    run_study,
    trainers_dir,
    write_outputs,
)
from .tables import Stat, fill_template, fmt_value, format_table, markdown_table, summarize

__all__ = [
    "Study",
    "StudyConfig",
    "StudyResult",
    "discover_studies",
    "format_table",
    "load_trainer",
    "run_study",
    "trainers_dir",
    "write_outputs",
    "Stat",
    "summarize",
    "markdown_table",
    "fmt_value",
    "fill_template",
    "run_rows",
    "write_rows_csv",
]
