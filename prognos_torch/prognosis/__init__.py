"""Prognosis: fault probability and remaining-useful-life distributions from predictions."""

from .particle_prediction import RollingParticlePrediction, rolling_particle_prediction
from .rul import RULDistribution, fault_probability, fault_probability_gaussian, rul_distribution

__all__ = [
    "RollingParticlePrediction",
    "rolling_particle_prediction",
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
