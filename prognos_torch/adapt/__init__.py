"""Adaptation pieces that plug into the Gaussian filter engine.

- :class:`StrongTracking` - suboptimal fading factor (paper 000 Eq. 7-20, 27-36).
- :class:`SageHusa` - recursive noise-statistics estimator for SRUKF (paper 003 Eq. 31-43).
- :class:`MovingWindow` - moving-window unbiased Q/R estimator (paper 004 Eq. 47-49).
- :class:`RobustBound` - robust update with bound gamma and uncertainty M, N (paper 004 Thm 1).
"""

from .noise import MovingWindow, NoiseEstimatorState, SageHusa
from .robust import RobustBound
from .strong_tracking import StrongTracking, StrongTrackingState

__all__ = [
    "StrongTracking",
    "StrongTrackingState",
    "SageHusa",
    "MovingWindow",
    "NoiseEstimatorState",
    "RobustBound",
]
