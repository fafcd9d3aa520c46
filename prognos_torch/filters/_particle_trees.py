"""Per-particle trees: gathering and selecting particles together with everything carried per
particle (the engine's :class:`~prognos_torch.filters.gaussian.FilterState` of a
Gaussian-proposal filter), re-exported by :mod:`prognos_torch.filters.particle`."""

from __future__ import annotations

import numbers
from dataclasses import fields, is_dataclass

import torch
from torch import Tensor

# Tensors of the engine's FilterState have the batch dims leading, except the moving-window
# noise buffers, which carry the window dim first (prognos_torch.adapt.noise.MovingWindow).
ENGINE_LEADING_DIMS: dict[str, int] = {"buf_Q": 1, "buf_R": 1, "buf_valid": 1}


def _particle_view(t: Tensor, v: Tensor, lead: int, nb: int) -> Tensor:
    """Reshape ``t`` ``(*batch, N)`` so that it lines up with ``v``'s batch+particle dims."""
    tail = v.dim() - lead - nb - 1
    return t.reshape((1,) * lead + tuple(t.shape) + (1,) * tail)


def _check_leaf(v: Tensor, name: str, lead: int, want: tuple[int, ...]) -> None:
    got = tuple(v.shape[lead : lead + len(want)])
    if got != want:
        raise ValueError(
            f"{name}: dims {lead}..{lead + len(want) - 1} must be the batch and particle dims "
            f"{want}, got shape {tuple(v.shape)}"
        )


_INIT_FIELDS: dict[type, tuple[str, ...]] = {}


def _init_fields(cls: type) -> tuple[str, ...]:
    names = _INIT_FIELDS.get(cls)
    if names is None:
        names = _INIT_FIELDS[cls] = tuple(f.name for f in fields(cls) if f.init)
    return names


def _kind(obj) -> str:
    if obj is None:
        return "None"
    if isinstance(obj, Tensor):
        return "a tensor"
    return f"a {type(obj).__name__}"


def _tree_map(fn, obj, others, name: str, leading: dict[str, int]):
    # the other trees' node must be of the same kind (b's None or missing field reached
    # torch.where unnamed; a's None dropped b's tensor)
    for o in others:
        same = (
            (obj is None) == (o is None)
            and isinstance(obj, Tensor) == isinstance(o, Tensor)
            and (not is_dataclass(obj) or isinstance(obj, Tensor) or type(o) is type(obj))
        )
        if not same:
            raise TypeError(f"{name}: the trees differ here: {_kind(obj)} and {_kind(o)}")
    if obj is None:
        return None
    if isinstance(obj, Tensor):
        return fn(obj, others, leading.get(name, 0), name)
    if is_dataclass(obj) and not isinstance(obj, type):
        cls = type(obj)
        kw = {
            f: _tree_map(fn, getattr(obj, f), [getattr(o, f) for o in others], f, leading)
            for f in _init_fields(cls)
        }
        return cls(**kw)  # (what dataclasses.replace builds, without its field scan)
    # (NumPy scalars too: a numpy.int64 field was refused)
    np_bool = type(obj).__name__ in ("bool_", "bool") and type(obj).__module__ == "numpy"
    if isinstance(obj, (numbers.Number, str)) or np_bool:
        return obj
    raise TypeError(f"{name}: cannot map over particles of a {type(obj).__name__}")


def gather_particles(obj, ancestors: Tensor, *, leading: dict[str, int] | None = None):
    """Select particles ``ancestors`` in every tensor of a (nested) frozen dataclass.

    Args:
        obj: a tensor, ``None`` or a dataclass of those (e.g. the engine's
            :class:`~prognos_torch.filters.gaussian.FilterState` with ``GaussianBelief``,
            ``StrongTrackingState`` and ``NoiseEstimatorState`` inside), whose tensors have the
            batch dims ``...`` and the particle dim ``N`` leading: ``(..., N, *tail)``.
        ancestors: ``(..., N)`` int64 indices into the particle dim.
        leading: field name -> number of extra dims before the batch dims (default
            :data:`ENGINE_LEADING_DIMS`: the moving-window buffers ``(W, ..., N, ...)``).
    Returns:
        The same structure with ``out[..., j, ...] = obj[..., ancestors[..., j], ...]``.
    """
    # (a float index failed in gather, unnamed; int32 worked for one run only; a 0-dim one
    # selected along the last dim of every leaf)
    if not isinstance(ancestors, Tensor):
        raise TypeError(f"ancestors must be an int64 tensor (..., N), got {type(ancestors)}")
    if ancestors.is_floating_point() or ancestors.is_complex() or ancestors.dtype == torch.bool:
        raise TypeError(f"ancestors must be an int64 tensor (..., N), got {ancestors.dtype}")
    if ancestors.dim() == 0:
        raise ValueError("ancestors must have shape (..., N), got a 0-dim tensor")
    # (an index outside 0..N-1 failed inside gather or index_select, unnamed, and on a GPU as a
    # device-side assert: checked at the first leaf, after its shape; one host read)
    return _gather(obj, ancestors.long(), leading, check=True)


def _check_ancestors(ancestors: Tensor, name: str) -> None:
    """Refuse an int64 ``ancestors`` ``(..., N)`` with an index outside ``0 .. N-1``."""
    N = ancestors.shape[-1]
    if ancestors.numel() == 0:
        return
    lo, hi = torch.aminmax(ancestors)
    if int(lo) < 0 or int(hi) >= N:
        raise ValueError(
            f"{name} must be indices in 0..{N - 1} (N = {N} particles, the last dim), got "
            f"values from {int(lo)} to {int(hi)}"
        )


def _gather(obj, ancestors: Tensor, leading: dict[str, int] | None = None, *, check=False):
    """:func:`gather_particles` for int64 ``ancestors`` ``(..., N)``; their range is checked
    only with ``check`` (a host read: the compiled pass traces this without one)."""
    leading = ENGINE_LEADING_DIMS if leading is None else leading
    want = tuple(ancestors.shape)
    nb = len(want) - 1
    pending = [check]

    def fn(v, _others, lead, name):
        _check_leaf(v, name, lead, want)
        if pending[0]:
            _check_ancestors(ancestors, "ancestors")
            pending[0] = False
        if lead + nb == 0:  # one run: a row selection (the same values as the gather)
            return v.index_select(0, ancestors)
        idx = _particle_view(ancestors, v, lead, nb).expand(v.shape)
        return torch.gather(v, lead + nb, idx)

    return _tree_map(fn, obj, [], "obj", leading)


def where_particles(mask: Tensor, a, b, *, leading: dict[str, int] | None = None):
    """Per-particle ``torch.where(mask, a, b)`` over two trees of the same structure.

    ``mask``: ``(..., N)`` bool; ``a``, ``b``: as in :func:`gather_particles`.
    """
    leading = ENGINE_LEADING_DIMS if leading is None else leading
    if not isinstance(mask, Tensor) or mask.dim() == 0 or mask.dtype != torch.bool:
        got = (mask.dtype, tuple(mask.shape)) if isinstance(mask, Tensor) else type(mask).__name__
        raise TypeError(f"mask must be a bool tensor of shape (..., N), got {got}")
    want = tuple(mask.shape)
    nb = len(want) - 1

    def fn(v, others, lead, name):
        w = others[0]
        _check_leaf(v, name, lead, want)
        if w.shape != v.shape or w.dtype != v.dtype:  # (torch.where broadcast and promoted)
            raise ValueError(
                f"{name}: b's tensor must match a's, shape {tuple(v.shape)} and {v.dtype}, got "
                f"{tuple(w.shape)} and {w.dtype}"
            )
        return torch.where(_particle_view(mask, v, lead, nb), v, w)

    return _tree_map(fn, a, [b], "a", leading)
