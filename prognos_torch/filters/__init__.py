"""Filters: the Gaussian engine, the particle filters, their configurations by name
(:mod:`.variants`), the sequence loop (:func:`scan`) and the runners built on it, the RTS
smoothers (:func:`smooth`)."""

from .gaussian import FilterState, GaussianFilter, Spread, StepInfo, Taylor
from .particle import ParticleFilter, ParticleState, ParticleTrajectory
from .resampling import ess, multinomial, residual, stratified, systematic
from .run import Forecast, Trajectory, forecast, run
from .sequence import scan
from .smooth import Smoothed, smooth, smooth_trajectory
from .variants import (
    FILTERS,
    PARTICLE_FILTERS,
    arukf,
    ckf,
    ekf,
    ekpf,
    imsrukf,
    make_filter,
    make_particle_filter,
    rukf,
    sckf,
    sir,
    srukf,
    stekf,
    stpf,
    stsckf,
    stukf,
    ukf,
    upf,
)

__all__ = [
    "FILTERS",
    "FilterState",
    "GaussianFilter",
    "Spread",
    "StepInfo",
    "Taylor",
    "arukf",
    "ckf",
    "ekf",
    "imsrukf",
    "make_filter",
    "rukf",
    "sckf",
    "srukf",
    "stekf",
    "stsckf",
    "stukf",
    "ukf",
    "Forecast",
    "Trajectory",
    "forecast",
    "run",
    "scan",
    "Smoothed",
    "smooth",
    "smooth_trajectory",
    "PARTICLE_FILTERS",
    "ParticleFilter",
    "ParticleState",
    "ParticleTrajectory",
    "ekpf",
    "make_particle_filter",
    "sir",
    "stpf",
    "upf",
    "ess",
    "multinomial",
    "residual",
    "stratified",
    "systematic",
]
