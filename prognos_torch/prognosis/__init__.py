"""Prognosis: learners as transition models, multi-step prediction, forecasted measurements,
fault prediction, and fault probability and remaining-useful-life distributions.

* :mod:`.learner_model`: a trained one-step predictor as an m-order state-space model
  (paper 002 Eq. 15-26).
* :mod:`.paths`: recursive multi-step prediction, deterministic, Gaussian or as weighted sample
  paths (paper 002 Eq. 11-14).
* :mod:`.forecaster`: forecasted measurements, one learner (ROS-ELM) per channel (paper 000
  Sec. 5); the ROS-ELM core is :mod:`prognos_torch.learners.ros_elm`.
* :mod:`.fault`: n-step-ahead and rolling fault-parameter prediction (paper 000 Sec. 5).
* :mod:`.particle_prediction`: rolling prediction with a particle filter, ahead of each
  measurement (paper 002 Fig. 8-10).
* :mod:`.assess`: scoring forecast-fed fault prediction (rolling forecasts, alarms, predicted
  threshold crossings).
* :mod:`.rul`: fault probability and RUL distributions from predicted paths.
"""

from ..learners.ros_elm import ROSELMState, ros_elm_forecast, ros_elm_init, ros_elm_update
from .assess import (
    ThresholdCrossings,
    aligned_forecasts,
    first_alarm,
    origin_fading_factors,
    persistence_forecasts,
    predict_threshold_crossings,
    rolling_forecasts,
)
from .fault import (
    FaultPrediction,
    RollingFaultPrediction,
    predict_fault_parameter,
    rolling_fault_prediction,
)
from .forecaster import MeasurementForecaster
from .learner_model import learner_transition_model
from .particle_prediction import RollingParticlePrediction, rolling_particle_prediction
from .paths import (
    GaussianPaths,
    RecursivePaths,
    SamplePaths,
    gaussian_paths,
    particle_paths,
    predict_paths,
    recursive_predict,
)
from .rul import RULDistribution, fault_probability, fault_probability_gaussian, rul_distribution

__all__ = [
    "RollingParticlePrediction",
    "rolling_particle_prediction",
    "RULDistribution",
    "fault_probability",
    "fault_probability_gaussian",
    "rul_distribution",
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
    "ThresholdCrossings",
    "aligned_forecasts",
    "first_alarm",
    "origin_fading_factors",
    "persistence_forecasts",
    "predict_threshold_crossings",
    "rolling_forecasts",
]
