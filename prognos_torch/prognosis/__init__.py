"""Prognosis: learners as transition models, multi-step prediction, forecasted measurements,
fault prediction, and fault probability and remaining-useful-life distributions.

* :mod:`.learner_model`: a trained one-step predictor as an m-order state-space model
  (paper 002 Eq. 15-26).
* :mod:`.paths`: recursive multi-step prediction, deterministic, Gaussian or as weighted sample
  paths (paper 002 Eq. 11-14), and where the noise-free recursion settles (:func:`settle`).
* :mod:`.forecaster`: forecasted measurements, one learner (ROS-ELM) per channel (paper 000
  Sec. 5); the ROS-ELM core is :mod:`prognos_torch.learners.ros_elm`.
* :mod:`.fault`: n-step-ahead and rolling fault-parameter prediction (paper 000 Sec. 5).
* :mod:`.particle_prediction`: rolling prediction with a particle filter, ahead of each
  measurement (paper 002 Fig. 8-10).
* :mod:`.assess`: scoring forecast-fed fault prediction (rolling forecasts, alarms, predicted
  threshold crossings).
* :mod:`.rul`: fault probability and RUL distributions from predicted paths.
* :mod:`.events`: batched Monte-Carlo simulation of samples to an event (EOD, EOL).
* :mod:`.onset`: degradation onset (first prediction time) against a healthy baseline.
* :mod:`.trends`: exponential, power-law and linear degradation trends as state-space models
  estimated by the filter engine; :mod:`.learner_trend`: an ELM trend trained online by the
  Kalman optimiser; :mod:`.protocol`: the known-threshold RUL protocol of bearing studies
  (:func:`last_sample_indices`: prediction times to sample indices); :mod:`.backtest`: trend
  models judged by the crossing times they predict on a series' own past; :mod:`.conformal`:
  RUL intervals calibrated on assets that ran to failure (split-conformal, CQR).
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
from .backtest import (
    backtest_scores,
    crossing_pairs,
    crps_log_time,
    one_standard_error_choice,
)
from .conformal import (
    RULCalibration,
    calibrate_intervals,
    conformal_margin,
    interval_scores,
    leave_one_group_out,
    points_needed,
    record_settings,
)
from .events import EventPrediction, sample_belief, simulate_to_event
from .fault import (
    FaultPrediction,
    RollingFaultPrediction,
    predict_fault_parameter,
    rolling_fault_prediction,
)
from .forecaster import MeasurementForecaster
from .learner_model import learner_transition_model, window_belief
from .learner_trend import LearnerTrendFit, TimeELM, fit_learner_trend, fit_learner_trends
from .onset import (
    GLITCH_SCREEN,
    GLITCH_WIDENING,
    ONSET_METHODS,
    Baseline,
    Onset,
    cusum_arl0,
    cusum_onset,
    detect_onset,
    healthy_baseline,
    isolated_outliers,
    ksigma_false_alarm_rate,
    ksigma_onset,
    moving_median,
)
from .particle_prediction import RollingParticlePrediction, rolling_particle_prediction
from .paths import (
    GaussianPaths,
    RecursivePaths,
    SamplePaths,
    gaussian_paths,
    particle_paths,
    predict_paths,
    recursive_predict,
    settle,
)
from .protocol import last_sample_indices
from .rul import RULDistribution, fault_probability, fault_probability_gaussian, rul_distribution
from .trends import (
    STRONG_TRACKING_BETA,
    TREND_SHAPES,
    Passage,
    TrendFit,
    TrendNoise,
    TrendPool,
    fit_trends,
    integrated_rw_chol,
    local_trend_model,
    noise_grid,
    path_grid,
    simulate_first_passage,
    strong_tracking_filter,
    trend_measurement,
    trend_transition,
)

__all__ = [
    "RollingParticlePrediction",
    "rolling_particle_prediction",
    "RULDistribution",
    "fault_probability",
    "fault_probability_gaussian",
    "rul_distribution",
    "EventPrediction",
    "sample_belief",
    "simulate_to_event",
    "FaultPrediction",
    "GaussianPaths",
    "MeasurementForecaster",
    "RecursivePaths",
    "RollingFaultPrediction",
    "ROSELMState",
    "SamplePaths",
    "gaussian_paths",
    "learner_transition_model",
    "window_belief",
    "particle_paths",
    "predict_fault_parameter",
    "predict_paths",
    "recursive_predict",
    "settle",
    "last_sample_indices",
    "rolling_fault_prediction",
    "ros_elm_forecast",
    "ros_elm_init",
    "ros_elm_update",
    "LearnerTrendFit",
    "TimeELM",
    "fit_learner_trend",
    "fit_learner_trends",
    "GLITCH_SCREEN",
    "GLITCH_WIDENING",
    "ONSET_METHODS",
    "Baseline",
    "Onset",
    "cusum_arl0",
    "cusum_onset",
    "detect_onset",
    "healthy_baseline",
    "isolated_outliers",
    "ksigma_false_alarm_rate",
    "ksigma_onset",
    "moving_median",
    "STRONG_TRACKING_BETA",
    "TREND_SHAPES",
    "Passage",
    "TrendFit",
    "TrendPool",
    "TrendNoise",
    "fit_trends",
    "integrated_rw_chol",
    "local_trend_model",
    "noise_grid",
    "path_grid",
    "simulate_first_passage",
    "strong_tracking_filter",
    "trend_measurement",
    "trend_transition",
    "backtest_scores",
    "crossing_pairs",
    "crps_log_time",
    "one_standard_error_choice",
    "ThresholdCrossings",
    "aligned_forecasts",
    "first_alarm",
    "origin_fading_factors",
    "persistence_forecasts",
    "predict_threshold_crossings",
    "rolling_forecasts",
    "RULCalibration",
    "calibrate_intervals",
    "conformal_margin",
    "record_settings",
    "interval_scores",
    "leave_one_group_out",
    "points_needed",
]
