"""Core abstractions: state-space models, Gaussian beliefs, square-root linear algebra, and the
floored ``exp`` of the learners' Gaussian kernels."""

from .belief import GaussianBelief
from .kernel_exp import EXP_FLOORS, floored_exp
from .linalg import (
    cho_solve_right,
    chol_downdate,
    chol_downdate_ex,
    chol_update,
    safe_cholesky,
    symmetrize,
    tria,
)
from .model import Noise, StateSpaceModel, joint_state_parameter_model, linear_gaussian_model

__all__ = [
    "GaussianBelief",
    "Noise",
    "StateSpaceModel",
    "joint_state_parameter_model",
    "linear_gaussian_model",
    "tria",
    "chol_update",
    "chol_downdate",
    "chol_downdate_ex",
    "cho_solve_right",
    "safe_cholesky",
    "symmetrize",
    "EXP_FLOORS",
    "floored_exp",
]
