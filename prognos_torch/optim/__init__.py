"""The optimiser face of the filter engine: learners trained by Kalman filtering.

* :class:`ParameterBridge`: module parameters <-> the filter state ``theta`` (paper 003 Eq. 44),
  the module as ``g(theta, x)`` (Eq. 46), vectorised over many ``theta`` and differentiated.
* :class:`KalmanOptimizer` (and :class:`EKF`, :class:`SRUKF`, :class:`ImSRUKF`): a
  ``torch.optim.Optimizer`` whose ``step`` is one step of the library's Gaussian filter on the
  random-walk model of Eq. 45-46.
* :func:`fit`: one training loop for Kalman and gradient optimisers;
  :func:`train_in_blocks` (training curves) and :func:`predict_then_update` (online one-step
  prediction) around it.
* :class:`StackedLearner`, :class:`StackedForecaster`: ``R`` Monte Carlo runs of one learner
  (or forecaster) as one predictor, batched through a run axis.
* :func:`fit_likelihood`: model parameters (noise, ``f``, ``h``) by maximising the filter's
  log-likelihood with any ``torch.optim`` optimiser; :func:`em_linear_gaussian`: EM for
  linear-Gaussian models on the square-root RTS smoother.
"""

from .em import EMFit, em_linear_gaussian, linear_model
from .fit import History, fit
from .kalman import (
    EKF,
    OPTIMIZER_NOISE,
    SRUKF,
    ImSRUKF,
    KalmanOptimizer,
    KalmanStep,
    noise_factor,
)
from .likelihood import LikelihoodFit, fit_likelihood, from_log_cholesky, log_cholesky
from .online import BlockCurve, predict_then_update, train_in_blocks
from .params import ParameterBridge, Selector
from .stacked import (
    StackedForecaster,
    StackedLearner,
    fit_kalman_runs,
    fit_together,
    kalman_runs_optimizer,
    run_sum_mse,
)

__all__ = [
    "ParameterBridge",
    "Selector",
    "KalmanOptimizer",
    "KalmanStep",
    "EKF",
    "SRUKF",
    "ImSRUKF",
    "noise_factor",
    "OPTIMIZER_NOISE",
    "fit",
    "History",
    "BlockCurve",
    "train_in_blocks",
    "predict_then_update",
    "StackedLearner",
    "StackedForecaster",
    "run_sum_mse",
    "fit_together",
    "fit_kalman_runs",
    "kalman_runs_optimizer",
    "fit_likelihood",
    "LikelihoodFit",
    "from_log_cholesky",
    "log_cholesky",
    "em_linear_gaussian",
    "EMFit",
    "linear_model",
]
