"""Small learners as plain ``torch.nn.Module``s (no knowledge of filters).

* :class:`ELM`: extreme learning machine, ridge and ROS-ELM online learning (paper 000).
* :mod:`.ros_elm`: ROS-ELM as a functional core batched over runs (:class:`ROSELMState`,
  :func:`ros_elm_init`, :func:`ros_elm_update`, :func:`ros_elm_forecast`; paper 000 Eq. 54-56).
* :class:`LSSVR`: least-squares support vector regression with input Jacobian (paper 002).
* :class:`ANFIS`: first-order Sugeno ANFIS with grid rules, Eq. 44 parameter order (paper 003).

Every ``forward`` maps ``(..., n_in) -> (..., n_out)`` with pure tensor code, so it can be used
with ``torch.func.functional_call``, ``vmap``, ``jacrev`` and ``jacfwd``.
"""

from .anfis import ANFIS
from .elm import ELM
from .introspect import learner_dims, learner_dtype_device
from .lssvr import LSSVR
from .lssvr_gram import LSSVRGram
from .ros_elm import ROSELMState, ros_elm_forecast, ros_elm_init, ros_elm_update

__all__ = [
    "ELM",
    "LSSVR",
    "LSSVRGram",
    "ANFIS",
    "ROSELMState",
    "ros_elm_init",
    "ros_elm_update",
    "ros_elm_forecast",
    "learner_dims",
    "learner_dtype_device",
]
