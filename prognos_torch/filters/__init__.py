"""Filters: the Gaussian engine, the particle filters, their configurations by name
(:mod:`.variants`), the sequence loop (:func:`scan`) and the runners built on it."""

from .gaussian import FilterState, GaussianFilter, StepInfo, Taylor
from .particle import ParticleFilter, ParticleState, ParticleTrajectory
from .resampling import ess, multinomial, residual, stratified, systematic
from .run import Forecast, Trajectory, forecast, run
from .sequence import scan
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
