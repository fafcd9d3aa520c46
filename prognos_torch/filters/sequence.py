"""The one loop over a time-leading sequence: step, record, stack.

:func:`scan` is what :func:`~prognos_torch.filters.run.run` (Gaussian filters),
:meth:`~prognos_torch.filters.particle.ParticleFilter.run` and
:func:`~prognos_torch.prognosis.rolling_fault_prediction` are built on; a study that needs
something else per step (a prediction before each update, a forecaster fed with each
measurement) wraps the filter's step instead of writing the loop again.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
import types
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

import torch
from torch import Tensor

from ..core.validation import check_flag, check_nonneg_int

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
    compile: bool = False,
    inference: bool = False,
    rewind: Callable[[], Callable[[], None]] | None = None,
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
        compile: run the whole sequence as ONE compiled call: the loop becomes
            ``torch._higher_order_ops.scan`` inside ``torch.compile(fullgraph=True)`` (the step
            is traced once, not unrolled, so the compile time does not grow with ``T``).
            Then ``state`` must be a tuple of tensors whose shapes, dtypes and strides the step
            keeps, ``record`` must give a tensor for every name at every step, the step gets
            ``k = None`` (it must not depend on the step index) and ``progress`` is not used.
            The first call for a step compiles (tens of seconds on CPU); later calls with the
            same ``step``, ``record`` and shapes reuse the compiled code.
        inference: when the first step's state and record need no gradient (and neither
            ``ys`` nor ``us`` does), run the other steps under ``torch.inference_mode()``:
            the same numbers without autograd's bookkeeping (about 15 % of a particle
            filter's step). The stacked records and the returned state are ordinary tensors
            all the same. Only for steps that keep no tensors elsewhere (the filters' own)
            and whose models do not differentiate inside: ``torch.autograd.functional``
            returns zeros in inference mode without an error, forward-mode AD tangents are
            dropped, and a parameter the first step does not use loses its gradient (the
            filters' runs therefore take it only when asked, ``inference=True``).
            A step that fails there with a ``RuntimeError`` (a model that differentiates
            inside, e.g. an autograd Jacobian) is undone and run again with autograd, and so
            is every later step.
        rewind: with ``inference``, called before each inference-mode step; returns a
            function that undoes that step's side effects (e.g. restores a generator's state)
            should it fail.
    Returns:
        The state after the last step and ``{name: (T', ...) tensor}``: the stack over the
        steps at which ``record`` gave a tensor for ``name`` (``T' = T`` unless it skipped some),
        ``None`` where it never did. With ``T = 0`` the dict is empty.
    """
    if not isinstance(ys, Tensor):
        raise TypeError(f"ys must be a torch.Tensor of shape (T, ..., m), got {type(ys).__name__}")
    if ys.dim() < 1:
        raise ValueError(f"ys must have shape (T, ..., m) (time leading), got {tuple(ys.shape)}")
    # (a float k0 reached the step as k = 2.5, None failed in k0 + t + 1)
    k0 = check_nonneg_int(k0, "k0")
    # (read by their truth value otherwise: compile="no" compiled the loop)
    compile = check_flag(compile, "compile")
    inference = check_flag(inference, "inference")
    T = ys.shape[0]
    if us is not None and (not isinstance(us, Tensor) or us.dim() < 1 or us.shape[0] != T):
        got = tuple(us.shape) if isinstance(us, Tensor) else type(us)
        raise ValueError(f"us must have one row per step of ys (T = {T}), got {got}")
    if compile:
        if T == 0:  # no step to trace (torch's scan operator refuses an empty sequence)
            _check_compiled_state(state)
            return tuple(state), {}
        return _compiled_scan(step, state, ys, us, record)
    steps: Iterable[int] = range(T) if progress is None else progress(range(T))
    rows: dict[str, list[Any]] = {}
    fast = False  # the steps after the first run under inference mode
    inferred = False  # some step ran there: the state may hold inference tensors
    with contextlib.ExitStack() as mode:
        for t in steps:
            args = (ys[t], None if us is None else us[t], k0 + t + 1)
            row = None
            if fast:
                undo = None if rewind is None else rewind()
                try:
                    new, info = step(state, *args)
                    row = record(new, info)
                    inferred = True
                except RuntimeError:
                    # the step needs autograd (a model differentiating inside it): undo its
                    # side effects, leave inference mode and run it again below, the rest too
                    if undo is not None:
                        undo()
                    mode.close()
                    fast = False
                    state = _ordinary(state)
            if row is None:
                new, info = step(state, *args)
                row = record(new, info)
            state = new
            if not isinstance(row, Mapping):  # (was an AttributeError on .items())
                raise TypeError(
                    f"record must return a mapping {{name: tensor or None}}, got "
                    f"{type(row).__name__} at step {t}"
                )
            for key, value in row.items():
                col = rows.setdefault(key, [])
                if value is not None:
                    col.append(value)
            if inference and t == 0 and not torch.is_inference_mode_enabled():
                fast = not (_needs_grad((ys, us)) or _needs_grad((state, row)))
                if fast:  # (one mode for the other steps: entering it per step costs more)
                    mode.enter_context(torch.inference_mode())
    stacked = {key: _stack(key, col) for key, col in rows.items()}
    return (_ordinary(state) if inferred else state), stacked


def _stack(key: str, col: list[Any]) -> Tensor | None:
    """The rows of ``record``'s ``key`` stacked; an error names the key and the first step
    whose value differs in shape from the first one (or is not a tensor)."""
    if not col:
        return None
    try:
        return torch.stack(col)
    except (RuntimeError, TypeError) as err:
        first = col[0]
        odd = [j for j, v in enumerate(col) if not isinstance(v, Tensor) or v.shape != first.shape]
        if not odd:
            raise
        j, v = odd[0], col[odd[0]]
        what = f"shape {tuple(v.shape)}" if isinstance(v, Tensor) else type(v).__name__
        head = f"shape {tuple(first.shape)}" if isinstance(first, Tensor) else type(first).__name__
        raise ValueError(
            f"record {key!r} gave {head} first and {what} later (row {j} of its stack): a name "
            "must give a tensor of the same shape at every step (or None)"
        ) from err


def _leaves(obj):
    """The tensors of a nest of dataclasses, tuples, lists and dicts."""
    if isinstance(obj, Tensor):
        yield obj
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            yield from _leaves(getattr(obj, f.name))
    elif isinstance(obj, (tuple, list)):
        for v in obj:
            yield from _leaves(v)
    elif isinstance(obj, Mapping):
        for v in obj.values():
            yield from _leaves(v)


def _needs_grad(obj) -> bool:
    return torch.is_grad_enabled() and any(t.requires_grad for t in _leaves(obj))


def _ordinary(obj):
    """``obj`` with every inference tensor replaced by an ordinary copy (dataclasses rebuilt
    from their init fields, tuples, lists and dicts mapped; everything else kept)."""
    if isinstance(obj, Tensor):
        return obj.clone() if obj.is_inference() else obj
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        changes = {}
        for f in dataclasses.fields(obj):
            if f.init:
                v = getattr(obj, f.name)
                w = _ordinary(v)
                if w is not v:
                    changes[f.name] = w
        return dataclasses.replace(obj, **changes) if changes else obj
    if isinstance(obj, tuple):
        out = tuple(_ordinary(v) for v in obj)
        if all(a is b for a, b in zip(out, obj)):
            return obj
        return type(obj)(*out) if hasattr(obj, "_fields") else out  # (a named tuple's type)
    if isinstance(obj, list):
        return [_ordinary(v) for v in obj]
    if isinstance(obj, dict):
        return {k: _ordinary(v) for k, v in obj.items()}
    return obj


_COMPILED: dict = {}


def _check_compiled_state(state) -> None:
    if not isinstance(state, tuple) or not all(isinstance(t, Tensor) for t in state):
        raise TypeError("with compile=True, state must be a tuple of tensors")


def _compile_options(device: torch.device, cpp_wrapper: bool = True) -> dict:
    """Inductor's options for the compiled loop on ``device``.

    Its C++ wrapper calls the loop's kernels from C++ rather than Python, which is most of the
    gain for steps of many small operations (EKF on paper 003's ANFIS, 497 steps: 0.118 s with
    the Python wrapper, 0.072 s with the C++ one, eager 0.43-0.52 s; compile 26 s and 39 s on
    the busy 2-core machine). On CUDA the C++ wrapper cannot generate the scan's loop (torch
    2.11: an assertion in its while-loop code generation), so the GPU gets the Python wrapper.
    ``decompose_mm_pass``: a matrix product with one row (a vector times a matrix: the learner
    on one sample, ``H S``) becomes a reduction that fuses with its neighbours instead of a
    BLAS call; the EKF step on paper 003's ANFIS goes from 7 BLAS calls and 7 fused kernels to
    2 and 4.

    The Python wrapper (on CUDA, or ``cpp_wrapper=False``) is generated without inductor's
    size, stride and alignment assertions: in a scan's loop it re-checks, every step, the
    buffers that the loop itself allocated, 18 Python calls per step of the bootstrap filter
    (about 10 us of its 37 us at 1,000 particles). The compiled passes' tests compare their
    numbers with the eager passes' instead.
    """
    options: dict = {"post_grad_fusion_options": {"decompose_mm_pass": {}}}
    if device.type == "cpu" and cpp_wrapper:
        options["cpp_wrapper"] = True
    else:
        options.update(size_asserts=False, alignment_asserts=False)
    return {"options": options}


def _compiled_scan(
    step, state, ys: Tensor, us: Tensor | None, record, dynamic: bool | None = None,
    cpp_wrapper: bool = True,
):  # fmt: skip
    """:func:`scan` with ``compile=True`` (see there). ``dynamic``: ``torch.compile``'s;
    ``False`` compiles each new set of shapes on its own (torch 2.13's dynamic-shape recompile
    can round a float constant of the step, e.g. ``-log N``, to float32). ``cpp_wrapper``:
    inductor's C++ wrapper on the CPU (see :func:`_compile_options`)."""
    _check_compiled_state(state)
    device = state[0].device if state else ys.device
    key = (step, record, device.type, dynamic, cpp_wrapper)
    fn = _COMPILED.get(key)
    if fn is None:
        try:
            from torch._higher_order_ops.scan import scan as _hop_scan
        except ImportError as err:  # the operator is torch's own and recent
            raise RuntimeError(
                f"compile=True needs torch's scan operator (torch._higher_order_ops.scan), "
                f"which torch {torch.__version__} does not have; use compile=False"
            ) from err

        def body(carry, xs):
            y, u = xs if len(xs) == 2 else (xs[0], None)
            new, info = step(tuple(carry), y, u, None)
            row = dict(record(new, info))
            # the carried tensors keep the layout they came with (the scan requires it)
            new = tuple(t.contiguous() for t in new)
            return new, row

        def run(carry, ys, us):
            # (the scan's inputs are tensors only: without controls it scans ys alone)
            return _hop_scan(body, carry, (ys,) if us is None else (ys, us))

        # a code object of its own: dynamo keeps at most torch._dynamo.config.recompile_limit
        # compiled entries per code object, and every cached step would otherwise share one
        run = types.FunctionType(
            run.__code__.replace(), run.__globals__, run.__name__, None, run.__closure__
        )
        options = _compile_options(device, cpp_wrapper)
        fn = torch.compile(run, fullgraph=True, dynamic=dynamic, **options)
        if len(_COMPILED) > 16:
            _COMPILED.clear()
        _COMPILED[key] = fn
    carry = tuple(t.contiguous() for t in state)
    global last_compile_seconds
    frames = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    t0 = time.perf_counter()
    final, rows = fn(carry, ys, us)
    if torch._dynamo.utils.counters["stats"]["unique_graphs"] != frames:
        # this call compiled: time it apart, and run again for the result and its time
        if device.type == "cuda":  # its queued kernels belong to the compiling call
            torch.cuda.synchronize(device)
        last_compile_seconds = time.perf_counter() - t0
        final, rows = fn(carry, ys, us)
    else:
        last_compile_seconds = 0.0
    return tuple(final), rows


#: Seconds the last ``scan(..., compile=True)`` call spent compiling (the first, compiling
#: call of the compiled function, whose result is discarded and recomputed); 0 when the
#: compiled code was reused.
last_compile_seconds = 0.0
