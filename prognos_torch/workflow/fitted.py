"""The fitted model as a plain record: a trained learner, its scaler and its configuration.

Functions act on it from elsewhere, so imports run one way (``fitted`` imports nothing of the
workflow): :func:`~prognos_torch.workflow.fit_series` makes one,
:func:`~prognos_torch.workflow.forecast` and :func:`~prognos_torch.workflow.rul` use one,
:func:`~prognos_torch.workflow.save_model` and :func:`~prognos_torch.workflow.load_model`
write and read one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import nn

from ..datasets.windows import MinMaxScaler

__all__ = ["FittedModel"]


@dataclass
class FittedModel:
    """A trained one-step learner with its scaler and configuration.

    Attributes:
        learner: the trained learner ``(..., m) -> (..., 1)`` on scaled values (its
            ``state_dict`` is what a model file stores).
        scaler: the :class:`MinMaxScaler` of the training part.
        config: JSON-able configuration and fit record: ``learner``, ``learner_options``,
            ``optimizer``, ``optimizer_options``, ``m``, ``m_selection``, ``scaler``
            (``data_min``, ``data_max``, ``feature_range``), ``dtype``, ``seed``,
            ``residual_rmse`` (scaled), ``series`` (name, time column, unit, ``dt``, rows
            used), ``data`` (how to read the CSV again), ``holdout`` (size and metrics),
            ``train`` (epochs, seconds, training RMSE).
    """

    learner: nn.Module
    scaler: MinMaxScaler
    config: dict = field(default_factory=dict)

    @property
    def m(self) -> int:
        """The embedding dimension."""
        return int(self.config["m"])

    @property
    def metrics(self) -> dict:
        """Held-out metrics recorded by :func:`~prognos_torch.workflow.fit_series` (empty
        without a holdout)."""
        holdout = self.config.get("holdout") or {}  # (None: no holdout, as {} is)
        return dict(holdout.get("metrics") or {})
