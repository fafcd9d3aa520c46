"""The one loop over a time-leading sequence: step, record, stack.

:func:`scan` is what :func:`~prognos_torch.filters.run.run` (Gaussian filters),
:meth:`~prognos_torch.filters.particle.ParticleFilter.run` and
:func:`~prognos_torch.prognosis.rolling_fault_prediction` are built on; a study that needs
something else per step (a prediction before each update, a forecaster fed with each
measurement) wraps the filter's step instead of writing the loop again.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

import torch
from torch import Tensor

__all__ = ["scan"]

S = TypeVar("S")
I = TypeVar("I")


def scan(
    step: Callable[[S, Tensor, Tensor | None, int], tuple[S, I]],
    state: S,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    record: Callable[[S, I], Mapping[str, Tensor | None]],
    k0: int = 0,
    progress: Callable[[Iterable[int]], Iterable[int]] | None = None,
) -> tuple[S, dict[str, Tensor | None]]:
    """Run ``step`` over the rows of ``ys`` and stack what ``record`` returns.

    For ``t = 0, ..., T - 1``::

        state, info = step(state, ys[t], us[t], k0 + t + 1)   # us[t] is None without us
        row = record(state, info)                              # {name: tensor or None}

    Time convention of the filters: row ``t`` is the measurement at ``k = k0 + t + 1`` and
    ``state`` enters as the state at ``k0``. NaN rows pass through unchanged (the filter's step
    decides what a missing measurement means). ``step`` may do more than filter, e.g. take a
    prediction from the state before updating it, or feed the measurement to a forecaster;
    whatever it returns as ``info`` reaches ``record``.

    Args:
        step: ``(state, y (..., m), u (..., p) or None, k) -> (state, info)``, e.g.
            ``lambda s, y, u, k: filt.step(model, s, y, u, k)``.
        state: the state at ``k0``.
        ys: ``(T, ..., m)`` measurements, time leading.
        us: ``(T, ..., p)`` per-step controls (any trailing shape the step accepts) or ``None``.
        record: ``(state, info) -> {name: tensor or None}`` after each step; a name whose value
            is ``None`` is skipped at that step.
        k0: time index of ``state``.
        progress: wraps the step indices, e.g. ``functools.partial(tqdm, desc=...)``.
    Returns:
        The state after the last step and ``{name: (T', ...) tensor}``: the stack over the
        steps at which ``record`` gave a tensor for ``name`` (``T' = T`` unless it skipped some),
        ``None`` where it never did. With ``T = 0`` the dict is empty.
    """
    if not isinstance(ys, Tensor) or ys.dim() < 1:
        raise TypeError("ys must be a torch.Tensor of shape (T, ..., m)")
    T = ys.shape[0]
    if us is not None and (not isinstance(us, Tensor) or us.dim() < 1 or us.shape[0] != T):
        got = tuple(us.shape) if isinstance(us, Tensor) else type(us)
        raise ValueError(f"us must have one row per step of ys (T = {T}), got {got}")
    steps: Iterable[int] = range(T) if progress is None else progress(range(T))
    rows: dict[str, list[Any]] = {}
    for t in steps:
        state, info = step(state, ys[t], None if us is None else us[t], k0 + t + 1)
        for key, value in record(state, info).items():
            col = rows.setdefault(key, [])
            if value is not None:
                col.append(value)
    return state, {key: (torch.stack(col) if col else None) for key, col in rows.items()}
