"""Module buffers under the Kalman optimisers: BatchNorm running statistics, clear errors.

A Kalman optimiser evaluates the module at many parameter vectors per step (sigma points, a
Jacobian by ``torch.func``), usually under ``torch.func.vmap``. A module whose ``forward``
changes its own buffers cannot be evaluated that way: which of the ``2n + 1`` evaluations should
move the running statistics? The answer kept here is the one of any ``torch.optim`` training
loop, where one forward pass at the current parameters precedes ``step``: the running
statistics of every BatchNorm layer in training mode are updated ONCE per step, by one forward
pass of the mini-batch at the parameters before the step (the prior mean); during the filter's
own evaluations the layers normalise by the batch statistics (as in training mode) and leave
their buffers alone. In ``eval()`` mode BatchNorm uses its running statistics, which are then
constants, and nothing needs handling.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from torch import nn
from torch.nn.modules.batchnorm import _BatchNorm

__all__ = ["tracking_batch_norms", "batch_statistics_only", "explain_transform_error"]


def tracking_batch_norms(module: nn.Module) -> list[_BatchNorm]:
    """The BatchNorm layers of ``module`` that update running statistics in ``forward``
    (training mode, ``track_running_stats=True``)."""
    return [
        m
        for m in module.modules()
        if isinstance(m, _BatchNorm) and m.training and m.track_running_stats
    ]


@contextmanager
def batch_statistics_only(norms: list[_BatchNorm]) -> Iterator[None]:
    """Inside, the given layers normalise by batch statistics without touching their buffers
    (``track_running_stats`` is switched off and restored on exit, also on error)."""
    for m in norms:
        m.track_running_stats = False
    try:
        yield
    finally:
        for m in norms:
            m.track_running_stats = True


def explain_transform_error(exc: RuntimeError) -> Exception | None:
    """A clear error for a module ``forward`` that ``torch.func`` cannot evaluate at many
    parameter vectors (an in-place change of a buffer, random numbers), else ``None``."""
    text = str(exc)
    low = text.lower()
    if "randomness" in low:
        return ValueError(
            "the module draws random numbers in forward (e.g. Dropout in training mode); a "
            "Kalman optimiser evaluates it at many parameter vectors per step and needs a "
            "deterministic forward: call module.eval() on those layers (or remove them)"
        )
    if ("inplace" in low or "in-place" in low) and ("vmap" in low or "transform" in low):
        return ValueError(
            "the module changes a tensor it does not own in forward (an in-place buffer "
            "update); a Kalman optimiser evaluates the module at many parameter vectors per "
            "step and cannot decide which evaluation should change it. BatchNorm layers are "
            "handled (running statistics updated once per step); for other layers call "
            "eval() or make the update out of place"
        )
    return None
