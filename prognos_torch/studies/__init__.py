"""Study infrastructure: configuration, Monte Carlo bookkeeping and result files.

A study (one per paper, in the repository's ``trainers/`` folder) is a thin script that composes
library pieces and returns a :class:`StudyResult`; this module turns it into ``table.md``
(mean ± std over runs, with the paper's numbers beside ours), ``results.csv`` (one row per run
and method), ``run.json`` (configuration, versions, machine) and the figures the study saved.
:mod:`.tables` holds the table helpers every study uses (summaries over runs, markdown tables,
notes filled from a template); :mod:`.evaluate` and :mod:`.forecasters` the evaluation
protocols the studies share (fault prediction, one-step forecasters alone and inside prognostic
filters); :mod:`.training` timed training of a learner by an optimiser over input/target
pairs, Monte Carlo runs batched or in turn, its frozen and online test readings
(:mod:`.training_report` draws them); :mod:`.matrix`
a learner x trainer x filter matrix over test problems (:mod:`.matrix_training` trains its
learners by name, :mod:`.matrix_report` draws its figures); :mod:`.rows` builds the per-run
result rows and writes them as CSV; :mod:`.indicator_protocol` runs paper 002's protocol on a
measured health indicator (a learner alone and inside particle filters: one-step prediction,
fault probability, RUL, their rows and tables; :mod:`.indicator_report` draws its figures).
"""

from .evaluate import (
    crossing_scores,
    crossing_table,
    fault_prediction_errors,
    lowest_counts,
    rolling_forecast_rmse,
    run_errors,
)
from .forecasters import (
    ForecastProblem,
    ForecastProtocol,
    evaluate_alone,
    evaluate_filtered,
    evaluate_gaussian,
    evaluate_particle,
    forecast_problem,
    healthy_runs,
    point_errors,
    residual_noise,
    rul_scores,
)
from .matrix import (
    Cell,
    Footnotes,
    MatrixResult,
    capture,
    filter_factories,
    matrix_metrics,
    run_forecaster_matrix,
)
from .matrix_report import (
    always_censored,
    best_label,
    matrix_figures,
    most_hits,
    problem_summary,
    ratio_text,
)
from .matrix_training import MatrixTraining, not_applicable, persistence, train_forecasters
from .rows import method_mean, run_rows, write_rows_csv
from .runner import (
    Study,
    StudyConfig,
    StudyDataError,
    StudyResult,
    discover_studies,
    load_trainer,
    run_jobs,
    run_study,
    timed,
    trainers_dir,
    write_outputs,
)
from .tables import (
    Stat,
    ascending,
    fill_template,
    fmt_value,
    format_table,
    markdown_table,
    summarize,
    sweep_crossing,
    sweep_table,
    threshold_census,
)
from .training import (
    TrainTest,
    kalman_runs,
    outcome_rows,
    runs_in_turn,
    train_and_test,
    untrained_runs,
)

__all__ = [
    "Study",
    "StudyConfig",
    "StudyDataError",
    "StudyResult",
    "discover_studies",
    "format_table",
    "load_trainer",
    "run_jobs",
    "run_study",
    "timed",
    "trainers_dir",
    "write_outputs",
    "Stat",
    "summarize",
    "markdown_table",
    "sweep_crossing",
    "sweep_table",
    "threshold_census",
    "ascending",
    "method_mean",
    "fmt_value",
    "fill_template",
    "run_rows",
    "write_rows_csv",
    "fault_prediction_errors",
    "rolling_forecast_rmse",
    "crossing_scores",
    "crossing_table",
    "run_errors",
    "lowest_counts",
    "TrainTest",
    "train_and_test",
    "kalman_runs",
    "runs_in_turn",
    "untrained_runs",
    "outcome_rows",
    "ForecastProblem",
    "ForecastProtocol",
    "point_errors",
    "rul_scores",
    "residual_noise",
    "healthy_runs",
    "evaluate_alone",
    "evaluate_gaussian",
    "evaluate_particle",
    "evaluate_filtered",
    "forecast_problem",
    "Cell",
    "Footnotes",
    "MatrixResult",
    "capture",
    "filter_factories",
    "matrix_metrics",
    "run_forecaster_matrix",
    "matrix_figures",
    "best_label",
    "ratio_text",
    "most_hits",
    "always_censored",
    "problem_summary",
    "MatrixTraining",
    "not_applicable",
    "persistence",
    "train_forecasters",
]
