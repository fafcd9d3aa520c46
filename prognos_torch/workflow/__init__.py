"""Use the library on your own data: a series from a CSV, a fitted learner, forecasts, RUL.

::

    from prognos_torch.workflow import fit_series, forecast, load_model, load_series, rul, save_model

    s = load_series("data.csv", column="hi", time_column="t")       # float64 Series
    model = fit_series(s, learner="anfis", optimizer="ekf")           # m chosen by validation
    print(model.metrics)                                              # held-out tail scores
    save_model(model, "model.pt")                                     # safe file, no pickle
    model = load_model("model.pt")
    fc = forecast(model, s, horizon=50)                               # mean and 95 % band
    r = rul(model, s, threshold=0.8, filter="stpf")                   # RUL distribution

Modules, each importing only those before it: :mod:`.data` (:func:`load_series`),
:mod:`.fitted` (:class:`FittedModel`, a plain record), :mod:`.predict` (:func:`forecast`,
:func:`rul`), :mod:`.model` (:func:`fit_series`, learners and optimisers by name), :mod:`.store`
(:func:`save_model`, :func:`load_model` on :mod:`prognos_torch.io`), :mod:`.prognosing`
(:func:`prognose`, from a series to a RUL), :mod:`.calibrate` (:func:`calibrate_rul`, its
intervals calibrated on assets that ran to failure); the figures
(:func:`plot_forecast`, :func:`plot_rul`) live in :mod:`prognos_torch.plots`. The
``prognos fit | forecast | rul`` commands are thin wrappers around these functions.
"""

from .calibrate import calibrate_rul
from .data import FILL_METHODS, Series, load_series, parse_where
from .extrapolation import ExtrapolationWarning
from .fitted import FittedModel
from .model import (
    DEFAULT_OPTIMIZER,
    LEARNER_DEFAULTS,
    LEARNERS,
    OPTIMIZER_DEFAULTS,
    OPTIMIZERS,
    fit_series,
    select_embedding,
)
from .predict import (
    FILTER_NAMES,
    ForecastResult,
    RULResult,
    ThresholdWarning,
    forecast,
    holdout_metrics,
    rul,
)
from .prognosing import PROGNOSE_METHODS, prognose
from .store import load_model, save_model

__all__ = [
    "Series",
    "load_series",
    "parse_where",
    "FILL_METHODS",
    "LEARNERS",
    "OPTIMIZERS",
    "DEFAULT_OPTIMIZER",
    "LEARNER_DEFAULTS",
    "OPTIMIZER_DEFAULTS",
    "FittedModel",
    "fit_series",
    "select_embedding",
    "ForecastResult",
    "RULResult",
    "FILTER_NAMES",
    "forecast",
    "rul",
    "holdout_metrics",
    "ThresholdWarning",
    "save_model",
    "load_model",
    "plot_forecast",
    "plot_rul",
    "prognose",
    "PROGNOSE_METHODS",
    "calibrate_rul",
    "ExtrapolationWarning",
]


def __getattr__(name: str):
    # the figures load matplotlib (about a second): only when asked for
    if name in ("plot_forecast", "plot_rul"):
        from .. import plots

        return getattr(plots, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
