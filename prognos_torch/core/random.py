"""Draws from an explicit ``torch.Generator``, onto the device that uses them."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .validation import is_int

#: from this many float64 draws on the CPU the vectorised transform of :func:`_randn_cpu_f64`
#: is faster than ``torch.randn``'s per-element loop (the two cross near 2,000-4,000 draws on
#: the 2-core benchmark machine; ``benchmarks/bench_particle.py``)
_VECTOR_MIN = 4096

_TWO_PI = 2.0 * math.pi


def standard_normal(
    shape: tuple[int, ...],
    generator: torch.Generator | None,
    dtype: torch.dtype,
    device: torch.device | str,
) -> Tensor:
    """Standard normal draws of ``shape`` on ``device``: ``torch.randn``'s draws.

    They are drawn on the generator's own device and then moved, so a CPU generator gives the
    same draws whatever device the computation runs on, and a CUDA generator draws on its GPU
    (``torch.randn`` refuses a generator of another device). ``generator=None`` draws from the
    global stream of ``device``. Float64 draws on the CPU from :data:`_VECTOR_MIN` values on
    come from :func:`_randn_cpu_f64`: ``torch.randn``'s uniforms and transform, vectorised (the
    same numbers to a few ulps, at most 3 measured, the generator left in the same state).
    """
    if not torch.compiler.is_compiling():  # (traced: symbolic sizes, checked by the caller)
        _check_draw_args(shape, generator, dtype)
        shape = tuple(int(d) for d in shape)
    where = torch.device(device if generator is None else generator.device)
    n = math.prod(shape)
    if dtype == torch.float64 and where.type == "cpu" and n >= _VECTOR_MIN:
        z = _randn_cpu_f64(n, generator).view(shape)
    else:
        z = torch.randn(shape, generator=generator, dtype=dtype, device=where)
    return z if generator is None or z.device == torch.device(device) else z.to(device)


def _check_draw_args(shape, generator, dtype) -> None:
    """:func:`standard_normal`'s arguments, each named (``NumPy`` integers are sizes too)."""
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(
            f"generator must be a torch.Generator or None, got {type(generator).__name__}"
        )
    if not isinstance(shape, (tuple, list)) or not all(is_int(d) for d in shape):
        raise TypeError(f"shape must be a tuple of non-negative ints, got {shape!r}")
    if any(d < 0 for d in shape):
        raise ValueError(f"shape must be a tuple of non-negative ints, got {shape!r}")
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype!r}")


def box_muller(u: Tensor, out: Tensor | None = None) -> Tensor:
    """Normals from uniforms ``u`` ``(..., 16)`` in ``[0, 1)``, 16 per block (Box & Muller 1958,
    in torch's block layout): ``r = sqrt(-2 log(1 - u_j))``, ``z_j = r cos(2 pi u_{j+8})``,
    ``z_{j+8} = r sin(2 pi u_{j+8})`` for ``j < 8``.

    Returns ``(..., 16)``; written into ``out`` (the same shape) when given, else a new tensor
    (the pure form, for traced code).
    """
    if u.dim() == 0 or u.shape[-1] != 16:
        raise ValueError(f"u must have shape (..., 16), got {tuple(u.shape)}")
    if out is not None and out.shape != u.shape:  # (a resized view of out would stay unwritten)
        raise ValueError(f"out must have u's shape {tuple(u.shape)}, got {tuple(out.shape)}")
    theta = u[..., 8:] * _TWO_PI
    if out is None:  # (out of place: a traced step fuses it without copies)
        r = torch.sqrt(torch.log(torch.rsub(u[..., :8], 1.0)) * -2.0)
        return torch.cat([r * torch.cos(theta), r * torch.sin(theta)], dim=-1)
    r = torch.rsub(u[..., :8], 1.0).log_().mul_(-2.0).sqrt_()  # (the same, in place)
    torch.mul(r, torch.cos(theta), out=out[..., :8])
    torch.mul(r, theta.sin_(), out=out[..., 8:])
    return out


def _randn_cpu_f64(n: int, generator: torch.Generator | None) -> Tensor:
    """``torch.randn(n, dtype=torch.float64, generator=generator)`` on the CPU, ``n >= 16``.

    ``torch.randn`` there draws ``n`` uniforms in order and turns each block of 16 into 16
    normals by :func:`box_muller`'s transform, one element at a time; when 16 does not divide ``n`` it
    redoes the last 16 outputs from 16 further uniforms. Here the same uniforms, drawn by
    ``torch.rand`` in the same order, go through the same transform on whole blocks. The
    vectorised ``log``, ``cos`` and ``sin`` round differently from the C library's in about one
    draw in a hundred (by at most 3 ulps measured; ``tests/test_core_random.py`` compares the
    two), and the generator ends where ``torch.randn`` leaves it.
    """
    tail = n % 16
    cpu = torch.device("cpu")
    u = torch.rand(n + (16 if tail else 0), generator=generator, dtype=torch.float64, device=cpu)
    z = torch.empty(n, dtype=torch.float64, device=cpu)
    m = n - tail
    box_muller(u[:m].view(-1, 16), z[:m].view(-1, 16))
    if tail:
        box_muller(u[n:].view(1, 16), z[n - 16 :].view(1, 16))
    return z
