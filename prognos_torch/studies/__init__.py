"""Study infrastructure: configuration, Monte Carlo bookkeeping and result files.

A study (one per paper, in the repository's ``trainers/`` folder) is a thin script that composes
library pieces and returns a :class:`StudyResult`; this module turns it into ``table.md``
(mean ± std over runs, with the paper's numbers beside ours), ``results.csv`` (one row per run
and method), ``run.json`` (configuration, versions, machine) and the figures the study saved.
"""

from .runner import (
    Study,
    StudyConfig,
    StudyResult,
    discover_studies,
    format_table,
    load_trainer,
    run_study,
    trainers_dir,
    write_outputs,
)

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
]
