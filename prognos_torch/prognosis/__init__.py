"""Prognosis: fault probability and remaining-useful-life distributions from predictions."""

from .rul import RULDistribution, fault_probability, fault_probability_gaussian, rul_distribution

__all__ = [
    "RULDistribution",
    "fault_probability",
    "fault_probability_gaussian",
    "rul_distribution",
]
