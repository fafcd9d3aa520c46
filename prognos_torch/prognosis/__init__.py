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
from .learner_trend import LearnerTrendFit, TimeELM, fit_learner_trend
from .onset import (
    ONSET_METHODS,
    Baseline,
    Onset,
    cusum_arl0,
    cusum_onset,
    detect_onset,
    healthy_baseline,
    ksigma_false_alarm_rate,
    ksigma_onset,
    moving_median,
)
from .trends import (
    STRONG_TRACKING_BETA,
    TREND_SHAPES,
    Passage,
    TrendFit,
    TrendNoise,
    strong_tracking_filter,
    fit_trends,
    integrated_rw_chol,
    local_trend_model,
    noise_grid,
    path_grid,
    simulate_first_passage,
    trend_measurement,
    trend_transition,
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

__all__ += [
    "ONSET_METHODS",
    "Baseline",
    "Onset",
    "cusum_arl0",
    "cusum_onset",
    "detect_onset",
    "healthy_baseline",
    "ksigma_false_alarm_rate",
    "ksigma_onset",
    "moving_median",
]

__all__ += [
    "LearnerTrendFit",
    "TimeELM",
    "fit_learner_trend",
    "STRONG_TRACKING_BETA",
    "TREND_SHAPES",
    "Passage",
    "strong_tracking_filter",
    "simulate_first_passage",
    "trend_transition",
    "TrendFit",
    "TrendNoise",
    "fit_trends",
    "integrated_rw_chol",
    "local_trend_model",
    "noise_grid",
    "path_grid",
    "trend_measurement",
]
