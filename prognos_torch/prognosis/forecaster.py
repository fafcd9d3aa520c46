"""Forecasted measurements for fault prediction (paper 000, Sec. 5, steps 1, 3 and 9).

:class:`MeasurementForecaster` is a thin stateful shell over the functional ROS-ELM core of
:mod:`prognos_torch.learners.ros_elm` (one ROS-ELM per measurement channel, batched over Monte
Carlo runs), or over any static learners. Its forecasts are the pseudo-measurements that
:func:`~prognos_torch.prognosis.fault.predict_fault_parameter` filters.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterable, Sequence

import torch
from torch import Tensor, nn

from ..core.validation import (
    check_finite,
    check_flag,
    check_float_tensor,
    check_nonneg,
    check_pos_int,
)
from ..learners.elm import ELM
from ..learners.introspect import learner_dims
from ..learners.ros_elm import ROSELMState, ros_elm_forecast, ros_elm_init, ros_elm_update

__all__ = ["MeasurementForecaster"]


class MeasurementForecaster:
    """Forecast future measurements with one learner per channel (paper 000 Sec. 5).

    A thin stateful shell over :func:`ros_elm_init` (step 1), :func:`ros_elm_forecast` (step 3)
    and :func:`ros_elm_update` (step 9). The online state (window, ``beta``, ``K``) lives in an
    immutable :class:`ROSELMState` with leading batch dims (Monte Carlo runs, assets): one set
    of output weights per run, while the random hidden layers of the ELMs are shared by the
    runs. The learner modules themselves are never modified.

    Learners: :class:`~prognos_torch.learners.ELM` with ``online=True`` (ROS-ELM, default for
    ELMs), or any trained learner ``(..., p) -> (..., 1)`` with ``online=False`` (static model:
    :meth:`update` only shifts the window).

    Args:
        learners: one learner per measurement channel (input dimension ``p``).
        p: embedding dimension.
        lam: ridge parameter ``lambda`` of the ROS-ELM initialisation (Eq. 52-54).
        online: learn online (ELMs only); ``None``: true if every learner is an ELM.
    """

    def __init__(
        self,
        learners: Sequence[nn.Module | Callable[[Tensor], Tensor]],
        p: int,
        *,
        lam: float = 1e-8,
        online: bool | None = None,
    ) -> None:
        self.p = check_pos_int(p, "p")
        if not isinstance(learners, Iterable):  # (one learner, not a list: 'ELM' is not iterable)
            raise TypeError(
                f"learners must be a sequence of one learner per channel (e.g. [elm]), got "
                f"{type(learners).__name__}"
            )
        learners = tuple(learners)
        if not learners:
            raise ValueError("learners must hold one learner per measurement channel (C >= 1)")
        all_elm = all(isinstance(lr, ELM) for lr in learners)
        # (read by truth value: online="no" was True)
        self.online = all_elm if online is None else check_flag(online, "online")
        if self.online and not all_elm:
            raise TypeError("online=True (ROS-ELM) needs ELM learners for every channel")
        for c, lr in enumerate(learners):
            if not callable(lr):
                raise TypeError(f"learners[{c}] must be callable, got {type(lr)}")
            n_in, n_out = learner_dims(lr)
            if n_in is not None and n_in != p:
                raise ValueError(f"learners[{c}] has input dimension {n_in}, expected p={p}")
            if self.online and n_out != 1:
                raise ValueError(f"learners[{c}] must have n_out=1 for ROS-ELM, got {n_out}")
            if n_out is not None and n_out != 1:  # (a static learner's first output was used)
                raise ValueError(
                    f"learners[{c}] must map (..., p) to (..., 1) (one channel), got n_out={n_out}"
                )
        self.learners = learners
        self.lam = check_nonneg(lam, "lam", numbers_only=True)
        self.state: ROSELMState | None = None

    @classmethod
    def ros_elm(
        cls,
        n_channels: int,
        p: int = 3,
        n_hidden: int = 50,
        lam: float = 1e-8,
        *,
        activation: str = "sigmoid",
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> MeasurementForecaster:
        """``n_channels`` ROS-ELMs with the paper's set-up (paper 000 Sec. 6: ``p = 3``,
        ``L = 50``, ``lambda = 1e-8``, sigmoid, ``a ~ U[-1, 1]``, ``b ~ U[0, 1]``); the hidden
        layers are drawn from ``generator`` (``None``: seeded with 0) and the ELMs moved to
        ``device`` (that of the measurements they will see; ``None``: where they were drawn)."""
        n_channels = check_pos_int(n_channels, "n_channels")
        if generator is None:
            generator = torch.Generator().manual_seed(0)
        elms = [
            ELM(p, n_hidden, 1, activation=activation, generator=generator, dtype=dtype).to(device)
            for _ in range(n_channels)
        ]
        return cls(elms, p, lam=lam, online=True)

    @property
    def n_channels(self) -> int:
        return len(self.learners)

    @property
    def initialized(self) -> bool:
        return self.state is not None

    def copy(self) -> MeasurementForecaster:
        """A copy sharing the (unmodified) learners; the immutable state is shared until updated."""
        return copy.copy(self)

    def initialize(self, z0: Tensor) -> MeasurementForecaster:
        """Step 1: train on the first ``N0`` measurements ``z0`` ``(N0, ..., C)``."""
        if self.online:
            self.state = ros_elm_init(self.learners, z0, self.p, self.lam)
            return self
        z0 = check_float_tensor(z0, "z0", "(N0, ..., C)")
        C = self.n_channels
        if z0.dim() < 2 or z0.shape[-1] != C or z0.shape[0] < self.p:
            raise ValueError(
                f"z0 must have shape (N0, ..., C) with C={C} and N0 >= p={self.p}, "
                f"got {tuple(z0.shape)}"
            )
        check_finite(z0, "z0", "(N0, ..., C)")
        win = z0[-self.p :].to(torch.float64).movedim(0, -1)
        empty = win.new_zeros(0)
        self.state = ROSELMState(win, (empty,) * C, (empty,) * C, 0)
        return self

    def _require(self) -> ROSELMState:
        if self.state is None:
            raise RuntimeError("call initialize(z0) first (paper 000 Sec. 5 step 1)")
        return self.state

    def forecast(self, n: int) -> Tensor:
        """Step 3: ``z_{k+1..k+n}`` ``(n, ..., C)`` by successive one-step predictions."""
        return ros_elm_forecast(self.learners, self._require(), n)

    def update(self, z: Tensor) -> MeasurementForecaster:
        """Step 9: absorb the new real measurement ``z`` ``(..., C)`` (ROS-ELM Eq. 55-56); a
        NaN entry is missing: its window shifts in the prediction instead
        (:func:`~prognos_torch.learners.ros_elm_update`)."""
        self.state = ros_elm_update(self.learners, self._require(), z)
        return self
