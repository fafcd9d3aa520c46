"""Argument checks shared by the library: each error names the argument and the expected shape.

Every module validates its arguments with these functions; a module keeps a private check only
where the rule is its own (a registry name, a dataset's test number, a paper's parameter range).
Sections: tensors and factors; integers and numbers; learner data; filter inputs (one
measurement, one control, a time-leading sequence, a generator); prediction choices (window,
band level, channel, controls over a horizon, state components, importance weights); simulator
parameters (dataclass fields, noise standard deviations).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import fields

import torch
from torch import Tensor

__all__ = [
    "as_tensor",
    "is_int",
    "is_real",
    "all_finite",
    "check_finite",
    "check_chol",
    "check_shape",
    "broadcast_shape",
    "chol_from_cov",
    "check_pos_int",
    "check_nonneg_int",
    "check_float_tensor",
    "check_window",
    "check_level",
    "check_channel",
    "check_controls",
    "check_index",
    "check_count",
    "check_seed",
    "check_nonneg",
    "check_scalar",
    "check_real",
    "check_dtype_arg",
    "check_forward_input",
    "check_matches",
    "to_float64",
    "as_data",
    "as_targets",
    "check_generator",
    "check_measurement",
    "check_control",
    "check_sequence",
    "check_weights",
    "check_params_finite",
    "check_positive",
    "check_std",
    "diag_chol",
    "chol_from_std",
]


def as_tensor(x, name: str, *, dtype=None, device=None) -> Tensor:
    """Convert array-likes to a tensor; reject anything else with a ``TypeError`` naming ``name``."""
    if isinstance(x, Tensor):
        return x.to(dtype=dtype or x.dtype, device=device or x.device)
    try:
        return torch.as_tensor(x, dtype=dtype or torch.float64, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise TypeError(f"{name} must be a tensor or array-like of numbers, got {type(x)}") from exc


def all_finite(x: Tensor) -> bool:
    """``bool(torch.isfinite(x).all())``, usually with one reduction instead of five operations.

    A sum is finite only if every entry is (inf and NaN propagate); a non-finite sum of finite
    entries (overflow) falls back to the exact elementwise test.
    """
    if x.numel() == 0:
        return True
    if not x.is_floating_point():
        return True
    if math.isfinite(float(x.detach().sum())):  # no graph node, no warning under autograd
        return True
    return bool(torch.isfinite(x).all())


def has_missing(x: Tensor, name: str, what: str = "value") -> bool:
    """Whether ``x`` has NaN entries, which mark missing ``what``s; inf is refused, naming
    ``name``. One reduction when every entry is finite (the usual case)."""
    if all_finite(x):
        return False
    if bool(torch.isinf(x).any()):
        raise ValueError(f"{name} contains inf (use NaN to mark a missing {what})")
    return True


def check_finite(x: Tensor, name: str, shape: str | None = None) -> Tensor:
    """``ValueError`` if ``x`` holds NaN or inf; ``shape`` (e.g. ``'(T, ..., m)'``) is quoted."""
    if not all_finite(x):
        where = "" if shape is None else f"; shape {shape}"
        raise ValueError(f"{name} contains non-finite values (NaN or inf){where}")
    return x


def broadcast_shape(*shapes: Sequence[int]) -> torch.Size:
    """The shape that ``shapes`` broadcast to (NumPy's rule, as ``torch.broadcast_shapes``,
    which imports SymPy through torch's symbolic shapes on its first call: about 0.3 s of a
    command's start). Raises ``ValueError`` naming the shapes where they do not broadcast."""
    out: list[int] = []
    for shape in shapes:
        shape = tuple(shape)
        if len(shape) > len(out):
            out = [1] * (len(shape) - len(out)) + out
        for i, n in enumerate(shape, start=len(out) - len(shape)):
            if out[i] == 1:
                out[i] = n  # (a 1 takes the other size, 0 included)
            elif n not in (1, out[i]):
                shown = ", ".join(str(tuple(s)) for s in shapes)
                raise ValueError(f"shapes {shown} do not broadcast")
    return torch.Size(out)


def check_shape(x: Tensor, name: str, tail: tuple[int, ...], what: str) -> Tensor:
    """Check that ``x.shape`` ends with ``tail``; ``what`` spells the expected shape, e.g. '(..., n)'."""
    if x.dim() < len(tail) or tuple(x.shape[x.dim() - len(tail) :]) != tuple(tail):
        raise ValueError(f"{name} must have shape {what} with {tail}, got {tuple(x.shape)}")
    return x


def check_chol(S: Tensor, name: str, n: int) -> Tensor:
    """A square-root factor: shape ``(..., n, n)``, finite, lower triangular, positive diagonal."""
    check_shape(S, name, (n, n), "(..., n, n)")
    check_finite(S, name)
    if not bool(torch.equal(S, torch.tril(S))):
        raise ValueError(f"{name} must be lower triangular (a Cholesky factor), shape (..., n, n)")
    if not bool((torch.diagonal(S, dim1=-2, dim2=-1) > 0).all()):
        raise ValueError(
            f"{name} must have a positive diagonal (the covariance must be positive definite)"
        )
    return S


def chol_from_cov(C: Tensor, name: str, n: int) -> Tensor:
    """Cholesky factor of a covariance ``(..., n, n)``; ``ValueError`` if not symmetric PD."""
    check_shape(C, name, (n, n), "(..., n, n)")
    check_finite(C, name)
    if not bool(torch.allclose(C, C.mT, rtol=1e-10, atol=1e-12 * float(C.abs().max()) + 1e-300)):
        raise ValueError(f"{name} must be symmetric, shape (..., n, n)")
    L, info = torch.linalg.cholesky_ex(C)
    if bool((info > 0).any()):
        raise ValueError(f"{name} must be positive definite, shape (..., n, n)")
    return L


# ------------------------------------------------------------------------------ integers
def is_int(v) -> bool:
    """An integral number (``int``, ``numpy.int64``, ...), not a ``bool`` (``numpy.bool_`` is
    not integral either)."""
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def check_flag(v, name: str) -> bool:
    """An on/off option as a Python ``bool`` (``numpy.bool_`` too); anything else, which would be
    read by its truth value (``sqrt="no"`` is true), is a ``TypeError``."""
    if (
        isinstance(v, bool)
        or type(v).__name__ in ("bool_", "bool")
        and type(v).__module__ == "numpy"
    ):
        return bool(v)
    raise TypeError(f"{name} must be a bool, got {v!r}")


def is_bool_or_complex(value) -> bool:
    """A bool or complex value or array (Python, NumPy or torch), which a cast to float would
    read as ``0``/``1`` or strip of its imaginary part."""
    dt = getattr(value, "dtype", None)
    return (
        isinstance(value, (bool, complex))
        or dt == torch.bool
        or (isinstance(dt, torch.dtype) and dt.is_complex)
        or getattr(dt, "kind", "") in ("b", "c")  # NumPy bool or complex
    )


def holds_bool_or_complex(value) -> bool:
    """:func:`is_bool_or_complex` of ``value`` or, for a list or tuple, of any of its entries
    (values a cast to float would read as ``0``/``1`` or strip of an imaginary part)."""
    return is_bool_or_complex(value) or (
        isinstance(value, (list, tuple)) and any(is_bool_or_complex(v) for v in value)
    )


def is_real(v) -> bool:
    """A real number (``int``, ``float``, ``numpy.float32``, ``numpy.int64``, ...), not a
    ``bool``."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def check_levels(q, name: str = "q", *, device=None) -> Tensor:
    """Quantile levels: a probability in ``(0, 1]`` (a Python or NumPy real, a 0-d tensor) or a
    non-empty 1-D sequence of them, as a float64 tensor ``()`` or ``(Q,)`` on ``device``.
    Bools, text, ``None``, NaN and 2-D levels raise ``ValueError`` naming ``name`` (``True``
    was read as ``q = 1``; text failed inside ``torch.as_tensor``)."""
    vals = q.tolist() if isinstance(q, Tensor) or hasattr(q, "dtype") else q
    flat = list(vals) if isinstance(vals, (list, tuple)) else [vals]
    qs = None
    if flat and all(is_real(v) for v in flat):
        qs = torch.as_tensor(vals, dtype=torch.float64, device=device)
    if qs is None or qs.dim() > 1 or bool(torch.isnan(qs).any()):
        raise ValueError(f"{name} must be a probability in (0, 1] or a 1-D sequence of them, "
                         f"got {q!r}")  # fmt: skip
    if not bool(((qs > 0) & (qs <= 1)).all()):
        raise ValueError(f"{name} must lie in (0, 1], got {q!r}")
    return qs


def plain_number(value):
    """A NumPy integer or real as the Python ``int`` or ``float`` it is (the same value);
    anything else unchanged. Settings that are recorded or saved keep Python numbers: JSON and
    ``torch.load(weights_only=True)`` refuse NumPy scalars, and a recorded ``repr`` reads
    ``np.int64(500)``."""
    if type(value) in (int, float) or not is_real(value):
        return value
    return int(value) if is_int(value) else float(value)


def check_pos_int(v, name: str) -> int:
    """An integral number ``>= 1`` as a Python ``int`` (``bool`` rejected)."""
    if not is_int(v) or v < 1:
        raise ValueError(f"{name} must be a positive int, got {v!r}")
    return int(v)


def check_nonneg_int(v, name: str) -> int:
    """An integral number ``>= 0`` as a Python ``int`` (``bool`` rejected)."""
    if not is_int(v) or v < 0:
        raise ValueError(f"{name} must be a non-negative int, got {v!r}")
    return int(v)


def check_count(value, name: str, minimum: int = 1, *, error: type = TypeError) -> int:
    """An integral number ``>= minimum`` as a Python ``int`` (``bool`` rejected). A value that
    is not an int raises ``error`` (``TypeError`` by default), one below ``minimum`` a
    ``ValueError``."""
    if not is_int(value):
        raise error(f"{name} must be an int >= {minimum}, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value}")
    return int(value)


def check_seed(value, name: str = "seed") -> int:
    """A seed: a Python or NumPy integer (``bool`` refused) as an ``int``; anything else (text,
    a float) raises a ``TypeError`` naming ``name``."""
    if not is_int(value):  # (np.bool_ is not integral)
        raise TypeError(f"{name} must be an int, got {value!r}")
    if not -(2**63) <= int(value) < 2**64:  # torch.Generator.manual_seed's range
        raise ValueError(f"{name} must lie in [-2**63, 2**64) (a generator seed), got {value!r}")
    return int(value)


def check_nonneg(value, name: str, *, numbers_only: bool = False) -> float:
    """A finite real ``>= 0`` as a float.

    By default anything ``float()`` accepts (numbers, 0-d tensors and arrays) but a ``bool``
    is taken and a value it rejects raises ``TypeError``; with ``numbers_only`` only a real
    number (``int``, ``float``, NumPy scalars; not ``bool``) is accepted, and anything else
    raises ``ValueError``.
    """
    if numbers_only:
        if not is_real(value) or not 0 <= value < math.inf:
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        return float(value)
    if isinstance(value, bool) or type(value).__name__ == "bool_":
        raise TypeError(f"{name} must be a real number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a real number, got {type(value)}") from exc
    if not (v >= 0.0 and v < float("inf")):
        raise ValueError(f"{name} must be a finite number >= 0, got {value}")
    return v


# ------------------------------------------------------------------------------ tensors
def check_float_tensor(x, name: str, shape: str) -> Tensor:
    """A floating-point tensor; ``shape`` spells the expected shape in the message."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {shape}, got {type(x)}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor of shape {shape}, got {x.dtype}")
    return x


def check_window(window, m: int, name: str = "window") -> Tensor:
    """A finite embedding window ``(..., m)``, oldest value first (paper 002 Eq. 12-14)."""
    hint = f"(..., {m})"
    w = check_float_tensor(window, name, hint)
    if w.dim() < 1 or w.shape[-1] != m:
        raise ValueError(
            f"{name} must have shape (..., m) with m={m} (the embedding dimension, oldest value "
            f"first), got {tuple(w.shape)}"
        )
    return check_finite(w, name, hint)


# ------------------------------------------------------------------------------ choices
def check_level(level: float) -> float:
    """A probability ``level`` in ``(0, 1)`` (of a central band)."""
    if not is_real(level) or not 0.0 < level < 1.0:
        raise ValueError(f"level must be a number in (0, 1), got {level!r}")
    return float(level)


def check_channel(channel, obs_dim: int) -> int:
    """A measurement channel index in ``[0, obs_dim)``."""
    if not is_int(channel) or not 0 <= channel < obs_dim:
        raise ValueError(f"channel must be an int in [0, {obs_dim}), got {channel!r}")
    return int(channel)


def check_controls(model, us, horizon: int, name: str = "us") -> Tensor | None:
    """Controls ``(horizon, ..., p)`` for a model with ``control_dim = p > 0``; ``None`` for a
    model without controls (where passing ``us`` is an error)."""
    if model.control_dim == 0:
        if us is not None:
            raise ValueError(f"{name} was given but the model has control_dim=0")
        return None
    p = model.control_dim
    if not isinstance(us, Tensor) or us.dim() < 2 or us.shape[0] != horizon or us.shape[-1] != p:
        got = tuple(us.shape) if isinstance(us, Tensor) else type(us)
        raise ValueError(
            f"{name} must have shape ({horizon}, ..., {p}) (one row per step), got {got}"
        )
    return us


def check_index(index, n: int, name: str = "param_index") -> Tensor:
    """State components selected by an int, a slice, a sequence of ints or ``None`` (all of
    them) as an int64 index tensor ``(d,)`` in ``[0, n)``."""
    if index is None:
        return torch.arange(n)
    if isinstance(index, bool):
        raise TypeError(f"{name} must be an int, a slice, a sequence of ints or None")
    if is_int(index):
        idx = [int(index)]
    elif isinstance(index, slice):
        idx = list(range(n))[index]
    else:
        try:
            idx = [int(i) for i in index]
        except TypeError as exc:
            raise TypeError(f"{name} must be an int, a slice, a sequence of ints or None") from exc
    if not idx or any(not -n <= i < n for i in idx):
        raise ValueError(f"{name} {index!r} selects nothing or is out of range for n={n}")
    return torch.tensor([i % n for i in idx], dtype=torch.long)


def check_scalar(x, name: str) -> float:
    """A finite real scalar (a number, or a tensor with one element and at most one dim) as a
    float; ``bool`` is rejected."""
    if isinstance(x, bool):
        raise TypeError(f"{name} must be a real number, got bool")
    if isinstance(x, (str, bytes)):  # (float("1") would take text)
        raise TypeError(f"{name} must be a real number, got the text {x!r}")
    if isinstance(x, Tensor):
        if x.numel() != 1 or x.dim() > 1:
            raise ValueError(
                f"{name} must be a scalar (0-dim tensor or number), got shape {tuple(x.shape)}"
            )
        x = x.item()
    try:
        value = float(x)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a real number, got {type(x)}") from exc
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


def check_positive_real(v, name: str) -> None:
    """``ValueError`` naming ``name`` unless ``v`` is a finite real number ``> 0`` (a Python or
    NumPy scalar; not a bool or text): a step size, a scale."""
    if not is_real(v) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a finite positive number, got {v!r}")


def check_real(v, name: str) -> float:
    """A finite real number as a float: a Python or NumPy scalar, or a 0-dim tensor or array.
    Unlike :func:`check_scalar`, text (``"20"``) and one-element vectors are refused, and every
    refusal is a ``ValueError`` naming ``name``."""
    if getattr(v, "ndim", None) == 0 and hasattr(v, "item"):
        v = v.item()  # (a bool or complex tensor gives a bool or complex: refused below)
    if not is_real(v) or not math.isfinite(float(v)):
        raise ValueError(f"{name} must be a finite number, got {v!r}")
    return float(v)


def check_setting(v, name: str, *, optional: bool = False) -> None:
    """A filter setting that is one finite real number, a Python or NumPy scalar (the same for
    every batch element: a tensor is refused), or ``None`` where ``optional``; ``ValueError``."""
    if v is None and optional:
        return
    if not is_real(v) or not math.isfinite(v):
        raise ValueError(
            f"{name} must be a finite real number (one value for every batch element), got {v!r}"
        )


# ------------------------------------------------------------------------------ learner data
def check_dtype_arg(dtype: torch.dtype) -> torch.dtype:
    """A module ``dtype`` argument: a floating-point ``torch.dtype``."""
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating-point torch.dtype, got {dtype!r}")
    return dtype


def check_learner_params(params, module, label: str) -> None:
    """Names and trailing shapes of batched parameters given to a learner's ``forward_with``:
    ``params[name]`` is ``(..., *module.name.shape)`` for a parameter ``name`` of ``module``.

    Only metadata is inspected (compatible with ``torch.func``): a misspelt name was ignored
    (the module's own values used), a transposed or short tensor reshaped or broadcast.
    """
    if not isinstance(params, dict):
        raise TypeError(f"params must be a dict of tensors, got {type(params).__name__}")
    own_params = dict(module.named_parameters(recurse=False))
    for name, v in params.items():
        own = own_params.get(name)
        if own is None:
            raise ValueError(
                f"params has no {label} parameter {name!r}; expected any of {list(own_params)}"
            )
        want = tuple(own.shape)
        if not isinstance(v, Tensor):
            raise TypeError(f"params[{name!r}] must be a torch.Tensor, got {type(v).__name__}")
        if v.dim() < len(want) or tuple(v.shape[v.dim() - len(want) :]) != want:
            raise ValueError(
                f"params[{name!r}] must have shape (..., {', '.join(map(str, want))}), "
                f"got {tuple(v.shape)}"
            )


def check_forward_input(x: Tensor, n_in: int, ref: Tensor) -> None:
    """The input of a ``forward``: a tensor ``(..., n_in)`` with ``ref``'s dtype and device.

    Only metadata (type, shape, dtype, device) is inspected, never values, so the check is
    compatible with ``torch.func`` transforms. Non-finite values propagate to the output.
    """
    if not isinstance(x, Tensor):
        raise TypeError(f"x must be a torch.Tensor of shape (..., {n_in}), got {type(x)}")
    if x.dim() < 1 or x.shape[-1] != n_in:
        raise ValueError(f"x must have shape (..., n_in) with n_in={n_in}, got {tuple(x.shape)}")
    if x.dtype != ref.dtype:
        raise TypeError(
            f"x has dtype {x.dtype} but the module has dtype {ref.dtype}; "
            f"convert x (x.to({ref.dtype})) or the module (module.to(dtype))"
        )
    if x.device != ref.device:
        raise ValueError(
            f"x is on device {x.device} but the module is on {ref.device}; move one of them"
        )


def check_matches(x: Tensor, name: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``x`` has the module parameters' ``dtype`` and ``device`` and is finite."""
    if x.dtype != dtype:
        raise TypeError(f"{name} has dtype {x.dtype} but the module parameters have dtype {dtype}")
    if x.device != device:
        raise ValueError(f"{name} is on {x.device} but the module is on {device}")
    return check_finite(x, name)


def to_float64(v, name: str, *, device: torch.device) -> Tensor:
    """A tensor or array-like of real numbers as a float64 tensor on ``device``.

    A tensor must already be on ``device`` (nothing is moved silently between devices).
    """
    if isinstance(v, Tensor):
        if v.dtype.is_complex or v.dtype == torch.bool:
            raise TypeError(f"{name} must be a real-valued tensor, got dtype {v.dtype}")
        if v.device != device:
            raise ValueError(f"{name} is on device {v.device} but the module is on {device}")
        return v.detach().to(torch.float64)
    try:
        return torch.as_tensor(v, dtype=torch.float64, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise TypeError(f"{name} must be a tensor or array-like of numbers, got {type(v)}") from exc


def as_data(x, name: str, *, device: torch.device, n_cols: int | None = None) -> Tensor:
    """Training inputs as a finite float64 tensor of shape ``(N, n_cols)`` on ``device``.

    ``n_cols=None`` accepts any number of columns.
    """
    t = to_float64(x, name, device=device)
    want = f"(N, {n_cols})" if n_cols is not None else "(N, n)"
    if t.dim() != 2 or (n_cols is not None and t.shape[1] != n_cols):
        raise ValueError(f"{name} must have shape {want}, got {tuple(t.shape)}")
    if t.shape[0] == 0:
        raise ValueError(f"{name} must have at least one row, shape {want}")
    return check_finite(t, name)


def as_targets(y, name: str, *, device: torch.device, n_rows: int, n_out: int) -> Tensor:
    """Targets as a finite float64 ``(n_rows, n_out)`` tensor; ``(n_rows,)`` is accepted if
    ``n_out == 1`` (it is the single output column; nothing is broadcast)."""
    t = to_float64(y, name, device=device)
    if t.dim() == 1 and n_out == 1 and t.shape[0] == n_rows:
        t = t.unsqueeze(-1)
    if t.dim() != 2 or tuple(t.shape) != (n_rows, n_out):
        raise ValueError(
            f"{name} must have shape (N, n_out) = ({n_rows}, {n_out}) matching the inputs"
            + (f" (or ({n_rows},) since n_out=1)" if n_out == 1 else "")
            + f", got {tuple(t.shape)}"
        )
    return check_finite(t, name)


# ------------------------------------------------------------------------------ filter inputs
def check_generator(generator, like: Tensor, what: str = "particles") -> torch.Generator:
    """A ``torch.Generator`` on the device type of ``like`` (the ``what`` it draws for)."""
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    if generator.device.type != like.device.type:
        raise ValueError(
            f"generator is on {generator.device}, the {what} on {like.device}: "
            f"create the generator on the {what}' device"
        )
    return generator


def check_measurement(
    y, obs_dim: int, batch_shape, like: Tensor, owner: str = "belief"
) -> tuple[Tensor, bool]:
    """One measurement ``y`` ``(*batch_shape, m)`` on ``like``'s device, NaN marking missing
    components (inf is rejected). Returns ``y`` in ``like``'s dtype and whether any entry is
    missing; ``owner`` names what ``like`` is in the device message."""
    if not isinstance(y, Tensor):
        raise TypeError(f"y must be a torch.Tensor of shape (..., {obs_dim})")
    want = tuple(batch_shape) + (obs_dim,)
    if tuple(y.shape) != want:
        raise ValueError(f"y must have shape {want} (batch shape + (m,)), got {tuple(y.shape)}")
    if y.device != like.device:
        raise ValueError(f"y is on {y.device}, the {owner} on {like.device}")
    check_real_tensor(y, "y")
    return y.to(like.dtype), has_missing(y, "y", "measurement")


def check_real_tensor(x: Tensor, name: str) -> None:
    """Real numbers (integers are converted); a complex or bool tensor is refused (a cast would
    drop the imaginary part with a warning only, or read True as 1)."""
    if x.is_complex() or x.dtype == torch.bool:
        raise TypeError(f"{name} must hold real numbers, got dtype {x.dtype}")


def check_control(u, control_dim: int, batch_shape, like: Tensor) -> Tensor | None:
    """One control ``u``: ``(p,)`` shared by the batch or ``(*batch_shape, p)``, finite; ``None``
    for a model without controls (where passing one is an error)."""
    p = control_dim
    if p == 0:
        if u is not None:
            raise ValueError("u was given but the model has control_dim=0")
        return None
    if u is None:
        raise ValueError(f"u is required: shape (..., {p}) or ({p},)")
    if not isinstance(u, Tensor):
        raise TypeError("u must be a torch.Tensor")
    if tuple(u.shape) not in ((p,), tuple(batch_shape) + (p,)):
        raise ValueError(
            f"u must have shape ({p},) or {tuple(batch_shape) + (p,)}, got {tuple(u.shape)}"
        )
    if not bool(torch.isfinite(u).all()):
        raise ValueError("u contains non-finite values")
    return u.to(like.dtype)


def check_sequence(
    x,
    name: str,
    tail: int,
    batch,
    *,
    steps: int | None = None,
    shared: bool = False,
    nonempty: bool = False,
) -> Tensor:
    """A time-leading sequence ``(T, *batch, tail)``; with ``shared`` also ``(T, tail)`` (one row
    for the whole batch, e.g. controls), with ``steps`` exactly ``T = steps`` rows, with
    ``nonempty`` at least one row. ``None`` is an error (the sequence is required)."""
    b = ", ".join(map(str, batch)) + ", " if len(batch) else ""
    want = f"(T, {b}{tail})"
    if shared and len(batch):
        want = f"(T, {tail}) or {want}"
    if steps is not None:
        want += f" with T = {steps}"
    elif nonempty:
        want += " with T >= 1"
    if x is None:
        raise ValueError(f"{name} must have shape {want}; it is required, got None")
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (T, ..., {tail})")
    check_real_tensor(x, name)
    mid = tuple(x.shape[1:-1])
    ok = (
        x.dim() >= 2
        and x.shape[-1] == tail
        and (steps is None or x.shape[0] == steps)
        and (mid == tuple(batch) or (shared and mid == ()))
        and (not nonempty or x.shape[0] >= 1)
    )
    if not ok:
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
    return x


# ------------------------------------------------------------------------------ weights
def check_weights(weights, batch_shape: Sequence[int], n: int, device, name: str = "weights"):
    """Normalised importance weights ``(*batch_shape, n)`` as float64; ``None`` gives ``1/n``.

    Raises ``ValueError`` (naming ``name``) for a wrong shape, NaN/inf, negative entries, rows that
    are all zero, or rows that do not sum to one within ``1e-6 + 4 n eps(dtype)``. Weights are
    never renormalised silently.
    """
    shape = (*tuple(batch_shape), n)
    if weights is None:
        return torch.full(shape, 1.0 / n, dtype=torch.float64, device=device)
    w = as_tensor(weights, name, device=device)
    if not w.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor of shape {shape}, got {w.dtype}")
    if tuple(w.shape) != shape:
        raise ValueError(f"{name} must have shape {shape} (..., N), got {tuple(w.shape)}")
    if bool(torch.isnan(w).all(-1).any()):
        raise ValueError(f"{name} are all NaN for some batch element; shape {shape}")
    if not bool(torch.isfinite(w).all()):
        raise ValueError(f"{name} contain NaN or inf; shape {shape}")
    if bool((w < 0).any()):
        raise ValueError(f"{name} must be non-negative")
    if bool((w == 0).all(-1).any()):
        raise ValueError(f"{name} are all zero for some batch element; shape {shape}")
    tol = 1e-6 + 4.0 * n * torch.finfo(w.dtype).eps
    w64 = w.to(torch.float64)
    dev = (w64.sum(-1) - 1.0).abs()
    if bool((dev > tol).any()):
        raise ValueError(
            f"{name} must sum to one along the last axis (max |sum - 1| = {dev.max().item():.3g})"
        )
    return w64


# ------------------------------------------------------------------------------ simulators
def check_params_finite(obj) -> None:
    """``ValueError`` naming the first field of a parameter dataclass that is not finite.

    Fields are real numbers (Python or NumPy, not ``bool``) or (nested) tuples / lists of them;
    anything else is a ``TypeError`` naming the field."""
    for f in fields(obj):
        v = getattr(obj, f.name)
        vals = v if isinstance(v, (tuple, list)) else (v,)
        flat = []
        for e in vals:
            flat.extend(e if isinstance(e, (tuple, list)) else (e,))
        for e in flat:
            if not is_real(e):  # (np.float32, np.int64 too; np.bool_ is not real)
                raise TypeError(f"{type(obj).__name__}.{f.name} must be a real number, got {e!r}")
            if not math.isfinite(e):
                raise ValueError(f"{type(obj).__name__}.{f.name} must be finite, got {v!r}")


def check_positive(obj, *names: str) -> None:
    """``ValueError`` naming the first of the fields ``names`` of ``obj`` that is not ``> 0``."""
    for name in names:
        v = getattr(obj, name)
        vals = v if isinstance(v, (tuple, list)) else (v,)
        if any(e <= 0 for e in vals):
            raise ValueError(f"{type(obj).__name__}.{name} must be > 0, got {v!r}")


def check_std(value, n: int, name: str) -> tuple[float, ...]:
    """A standard deviation given as one number or ``n`` numbers, finite and ``>= 0``."""
    if isinstance(value, Tensor):
        value = value.detach().cpu().reshape(-1).tolist()
    vals = tuple(value) if hasattr(value, "__iter__") else (value,) * n
    if len(vals) != n:
        raise ValueError(f"{name} must be a number or a sequence of {n} numbers, got {value!r}")
    for v in vals:
        if not is_real(v):
            raise TypeError(f"{name} must contain real numbers, got {value!r}")
        if not math.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
    return tuple(float(v) for v in vals)


def diag_chol(std: Sequence[float], dtype, device) -> Tensor:
    """The diagonal square-root factor ``diag(std)``."""
    return torch.diag(torch.tensor(list(std), dtype=dtype, device=device))


def chol_from_std(value, d: int, name: str, dtype, device) -> Tensor:
    """A ``(d, d)`` square-root factor from a number (``std * I``), ``d`` stds or a lower
    triangular matrix."""
    if isinstance(value, Tensor) and value.dim() == 2:
        S = value.to(dtype=dtype, device=device)
        if tuple(S.shape) != (d, d):
            raise ValueError(f"{name} must have shape ({d}, {d}), got {tuple(S.shape)}")
        if not bool(torch.isfinite(S).all()):
            raise ValueError(f"{name} contains non-finite values")
        if not bool(torch.equal(S, torch.tril(S))):
            raise ValueError(f"{name} must be lower triangular, shape ({d}, {d})")
        return S
    return diag_chol(check_std(value, d, name), dtype, device)
