"""Prognosis: fault probability and remaining-useful-life distributions from predictions."""

from .rul import RULDistribution, fault_probability, fault_probability_gaussian, rul_distribution

__all__ = [
    "RULDistribution",
    "fault_probability",
    "fault_probability_gaussian",
    "rul_distribution",
]
from .forecast import (
    FaultPrediction,
    GaussianPaths,
    MeasurementForecaster,
    RecursivePaths,
    RollingFaultPrediction,
    ROSELMState,
    SamplePaths,
    gaussian_paths,
    learner_transition_model,
    particle_paths,
    predict_fault_parameter,
    predict_paths,
    recursive_predict,
    rolling_fault_prediction,
    ros_elm_forecast,
    ros_elm_init,
    ros_elm_update,
)

__all__ += [
    "FaultPrediction",
    "GaussianPaths",
    "MeasurementForecaster",
    "RecursivePaths",
    "RollingFaultPrediction",
    "ROSELMState",
    "SamplePaths",
    "gaussian_paths",
    "learner_transition_model",
    "particle_paths",
    "predict_fault_parameter",
    "predict_paths",
    "recursive_predict",
    "rolling_fault_prediction",
    "ros_elm_forecast",
    "ros_elm_init",
    "ros_elm_update",
]

from .assess import (  # noqa: E402  (after the names it uses)
    ThresholdCrossings,
    aligned_forecasts,
    first_alarm,
    origin_fading_factors,
    persistence_forecasts,
    predict_threshold_crossings,
    rolling_forecasts,
)

__all__ += [
    "aligned_forecasts",
    "ThresholdCrossings",
    "first_alarm",
    "origin_fading_factors",
    "persistence_forecasts",
    "predict_threshold_crossings",
    "rolling_forecasts",
]
