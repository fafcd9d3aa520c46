"""Small learners as plain ``torch.nn.Module``s (no knowledge of filters).

* :class:`ELM`: extreme learning machine, ridge and ROS-ELM online learning (paper 000).
* :mod:`.ros_elm`: ROS-ELM as a functional core batched over runs (:class:`ROSELMState`,
  :func:`ros_elm_init`, :func:`ros_elm_update`, :func:`ros_elm_forecast`; paper 000 Eq. 54-56).
* :class:`LSSVR`: least-squares support vector regression with input Jacobian (paper 002);
  :class:`FixedSizeLSSVR`: the same model on ``M`` support points (Nystrom, for long series);
  :class:`LSSVRGram`: a fitted RBF LS-SVR evaluated through matrix products
  (:func:`fit_lssvr_gram`; :func:`lssvr_gram_fitter` and :func:`lssvr_grid_cv` for the blocked
  cross-validation).
* :class:`ANFIS`: first-order Sugeno ANFIS with grid rules, Eq. 44 parameter order (paper 003).
* :func:`blocked_cv_rmse`: blocked (time-ordered) cross-validation of any fit/predict pair;
  :func:`blocked_multistep_cv`: the same folds scoring the recursive (iterated) prediction
  over a horizon and its time to cross a threshold; :func:`best_setting` picks a grid's
  setting by one of those scores (NaN never wins).

Every ``forward`` maps ``(..., n_in) -> (..., n_out)`` with pure tensor code, so it can be used
with ``torch.func.functional_call``, ``vmap``, ``jacrev`` and ``jacfwd``.
"""

from .anfis import ANFIS
from .elm import ELM
from .introspect import learner_dims, learner_dtype_device
from .lssvr import LSSVR
from .lssvr_fixed import FixedSizeLSSVR
from .lssvr_gram import LSSVRGram, fit_lssvr_gram, lssvr_gram_fitter, lssvr_grid_cv
from .ros_elm import ROSELMState, ros_elm_forecast, ros_elm_init, ros_elm_update
from .selection import (
    MultiStepCV,
    best_setting,
    blocked_cv_rmse,
    blocked_folds,
    blocked_multistep_cv,
)

__all__ = [
    "ELM",
    "LSSVR",
    "LSSVRGram",
    "fit_lssvr_gram",
    "lssvr_gram_fitter",
    "lssvr_grid_cv",
    "FixedSizeLSSVR",
    "ANFIS",
    "ROSELMState",
    "ros_elm_init",
    "ros_elm_update",
    "ros_elm_forecast",
    "learner_dims",
    "learner_dtype_device",
    "blocked_cv_rmse",
    "blocked_folds",
    "blocked_multistep_cv",
    "MultiStepCV",
    "best_setting",
]
