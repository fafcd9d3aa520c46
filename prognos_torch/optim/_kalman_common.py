"""The parts of the Kalman optimiser (:mod:`prognos_torch.optim.kalman`) that are not the
optimiser class: its step result :class:`KalmanStep`, the parsing of its options (noise factors,
filter, parameter groups and their configuration, learning rate) and the helpers of its
persistent state and of its step arguments.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, fields, replace

import torch
from torch import Tensor, nn

from ..adapt.noise import MovingWindow, SageHusa
from ..adapt.strong_tracking import StrongTracking
from ..core.linalg import tria
from ..core.validation import (
    check_matches,
    has_missing,
    is_bool_or_complex,
    is_int,
    is_real,
    plain_number,
)
from ..filters.gaussian import GaussianFilter, StepInfo
from ..filters.variants import make_filter
from ._buffers import tracking_batch_norms
from .params import ParameterBridge

_STATE_KEY = "kalman"


@dataclass(frozen=True)
class KalmanStep:
    """What :meth:`KalmanOptimizer.step` returns (batch dims ``(R,)`` with ``runs=R``, else ``()``).

    Attributes:
        loss: mean squared innovation ``mean_j (t_j - z_j)^2`` over the measurement vector, under
            the prior (before the update). For the EKF ``z = g(theta_{k-1}, u_k)``, so this is the
            pre-update mean squared error; sigma-point filters use their predicted measurement.
        info: the engine's full :class:`~prognos_torch.filters.gaussian.StepInfo` (of the
            first parameter group).
        infos: the :class:`StepInfo` of every parameter group (``infos[0] is info``).

    With several parameter groups ``loss`` is that of the first group's update, i.e. before
    any group of this step was updated. ``nis`` (normalised innovation squared), ``fading_factor`` (``lambda_k``, 1 without strong
    tracking) and ``log_likelihood`` are read from ``info`` (computed on first access).
    """

    loss: Tensor
    info: StepInfo
    infos: tuple[StepInfo, ...] = ()

    @property
    def nis(self) -> Tensor:
        return self.info.nis

    @property
    def fading_factor(self) -> Tensor:
        return self.info.fading_factor

    @property
    def log_likelihood(self) -> Tensor:
        return self.info.log_likelihood

    def item(self) -> float:
        """The loss as a Python float (mean over runs)."""
        return float(self.loss.mean())


# ---------------------------------------------------------------------- option parsing
def noise_factor(value, dim: int, name: str, *, allow_singular: bool, device=None) -> Tensor:
    """A lower square-root factor ``(dim, dim)`` float64 of a covariance given as a scalar
    variance (``v I``), a vector of variances ``(dim,)`` (``diag(v)``) or a matrix ``(dim, dim)``.

    With ``allow_singular`` a positive semi-definite matrix (e.g. ``Q = 0``) is accepted and
    factorised through its eigen-decomposition; otherwise it must be positive definite.
    """
    v = _as_float64(value, name, device)
    if device is not None:
        v = v.to(device)
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"{name} contains non-finite values")
    strict = "> 0" if not allow_singular else ">= 0"
    if v.dim() == 0 or v.dim() == 1:
        if v.dim() == 1 and v.shape[0] != dim:
            raise ValueError(
                f"{name} as a vector of variances must have shape ({dim},), got {tuple(v.shape)}"
            )
        ok = (v >= 0) if allow_singular else (v > 0)
        if not bool(ok.all()):
            raise ValueError(f"{name} variances must be {strict}, got {value}")
        d = v.sqrt().expand(dim) if v.dim() == 0 else v.sqrt()
        return torch.diag_embed(d)
    if v.dim() != 2 or tuple(v.shape) != (dim, dim):
        raise ValueError(
            f"{name} must be a scalar, a vector ({dim},) or a matrix ({dim}, {dim}), got shape "
            f"{tuple(v.shape)}"
        )
    scale = float(v.abs().max()) if v.numel() else 0.0
    if not bool(torch.allclose(v, v.mT, rtol=1e-10, atol=1e-12 * scale + 1e-300)):
        raise ValueError(f"{name} must be a symmetric matrix ({dim}, {dim})")
    L, info = torch.linalg.cholesky_ex(v)
    if int(info) == 0:
        return L
    w, V = torch.linalg.eigh(0.5 * (v + v.mT))
    if not allow_singular or bool((w < -1e-12 * max(scale, 1e-300)).any()):
        raise ValueError(f"{name} must be positive {'semi-' if allow_singular else ''}definite")
    return tria(V * w.clamp_min(0.0).sqrt().unsqueeze(-2))


def plain_option(value, *, arrays: bool = True):
    """An option as ``param_groups`` keeps it (``state_dict`` saves the groups, and
    ``torch.load(weights_only=True)`` refuses NumPy objects): a NumPy number or 0-d array of
    reals as the Python number it is (:func:`plain_number`), with ``arrays`` a NumPy array of
    reals as a float64 tensor (a copy) and a dict's values (a per-parameter prior) likewise;
    anything else unchanged (bool, complex and text arrays are refused by the option's check)."""
    if isinstance(value, dict) and arrays:
        return {k: plain_option(v) for k, v in value.items()}
    kind = getattr(getattr(value, "dtype", None), "kind", "")  # (NumPy's; torch dtypes have none)
    if kind in ("f", "i", "u"):
        if getattr(value, "ndim", None) == 0:
            return plain_number(value.item())
        if arrays:
            return torch.tensor(value, dtype=torch.float64)
    return plain_number(value)


def _as_float64(value, name: str, device=None) -> Tensor:
    """``value`` (a number, a vector or a matrix) as a float64 tensor. A bool or complex value
    (Python, NumPy or torch) is refused: the cast would read ``True`` as ``1`` and drop an
    imaginary part."""
    if is_bool_or_complex(value):
        raise TypeError(f"{name} must be a real number, a vector or a matrix, got {value!r}")
    try:
        return torch.as_tensor(value, dtype=torch.float64, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise TypeError(
            f"{name} must be a number, a vector or a matrix, got {type(value)}"
        ) from exc


#: The noise estimator of the ``"imsrukf"`` optimiser (paper 003 Eq. 41 and 43, see
#: :class:`KalmanOptimizer`): ``Q`` and ``R`` only, ``Q`` diagonal, ``R`` in the post-fit form,
#: the prior weighted as ``k0 - 1 = 299`` earlier steps.
OPTIMIZER_NOISE = SageHusa(estimate=("Q", "R"), diagonal=True, k0=300.0, r_form="post-fit")


def _resolve_filter(filt, fading, noise) -> GaussianFilter:
    if isinstance(filt, str):
        # the optimiser face's fast path: random walk, prior factor by a Cholesky of S S^T + Q
        base = replace(make_filter(filt), prior="cholesky")
        if filt.lower() == "imsrukf":
            base = replace(base, noise=OPTIMIZER_NOISE)
    elif isinstance(filt, GaussianFilter):
        base = filt
    else:
        raise TypeError(f"filter must be a filter name or a GaussianFilter, got {type(filt)}")
    changes = {}
    if fading is not None:
        if fading is False:
            changes["fading"] = None
        elif fading is True:
            changes["fading"] = StrongTracking()
        elif isinstance(fading, StrongTracking) or is_real(fading):  # (the engine checks >= 1)
            changes["fading"] = fading
        else:
            raise TypeError("fading must be None, True/False, a float >= 1 or StrongTracking")
    if noise is not None:
        if noise is False:
            changes["noise"] = None
        elif noise is True:
            changes["noise"] = SageHusa()
        elif isinstance(noise, (SageHusa, MovingWindow)):
            changes["noise"] = noise
        else:
            raise TypeError("noise must be None, True/False, SageHusa or MovingWindow")
    return replace(base, **changes) if changes else base


def _resolve_groups(params, module) -> tuple[nn.Module, list[dict]]:
    """``(module, parameter groups)`` from the ``params``/``module`` arguments."""
    if isinstance(params, nn.Module):
        if module is not None and module is not params:
            raise ValueError("module must be omitted or be the module passed as params")
        return params, [{"params": ParameterBridge(params).parameters()}]
    if module is None:
        raise ValueError(
            "module is required when params is an iterable of parameters or of parameter "
            "groups (KalmanOptimizer(module.parameters(), module=module))"
        )
    if not isinstance(module, nn.Module):
        raise TypeError(f"module must be a torch.nn.Module, got {type(module)}")
    if isinstance(params, (Tensor, dict)) or not isinstance(params, Iterable):
        raise TypeError(
            "params must be a module, an iterable of its parameters, or an iterable of "
            "parameter groups (dicts with a 'params' entry)"
        )
    items = list(params)
    if not items:
        raise ValueError("params is empty: no parameters to train")
    groups = [isinstance(p, dict) for p in items]
    if all(groups):
        return module, [dict(g) for g in items]
    if any(groups):
        raise TypeError("params mixes parameters and parameter groups (dicts): give one kind")
    return module, [{"params": items}]


def _check_lr(lr, filt: GaussianFilter, where: str) -> float:
    """``lr`` as a float; it scales the measurement noise of its group (``R / lr``)."""
    if isinstance(lr, Tensor) and lr.numel() == 1 and not is_bool_or_complex(lr):
        lr = lr.item()  # (a bool tensor was read as 1, a complex one lost its imaginary part)
    if not is_real(lr) or not math.isfinite(lr) or lr <= 0:
        raise ValueError(
            f"{where} must be a positive finite number (the learning rate divides the "
            f"measurement noise: R / lr), got {lr!r}"
        )
    lr = float(lr)
    noise = filt.noise
    if lr != 1.0 and noise is not None and "R" in getattr(noise, "estimate", ()):
        raise ValueError(
            f"{where} = {lr:g}, but the group's filter estimates R itself "
            f"({type(noise).__name__}, e.g. filter='imsrukf'), so a learning rate R / lr "
            "has no meaning: keep lr = 1.0 (no learning-rate scheduler), or estimate Q only "
            "(noise=SageHusa(estimate=('Q',), diagonal=True)), or use a filter with a fixed R"
        )
    return lr


def _state_key(i: int) -> str:
    """Key of parameter group ``i``'s filter state in ``optimizer.state``."""
    return _STATE_KEY if i == 0 else f"{_STATE_KEY}.{i}"


def norm_statistics(norms: list) -> list[tuple[Tensor, Tensor]]:
    """``(buffer, copy)`` of the running statistics of the BatchNorm layers ``norms``, which a
    step moves once (:mod:`prognos_torch.optim._buffers`) and a failed step puts back."""
    return [(b, b.clone()) for m in norms for b in m.buffers(recurse=False)]


def restore_norm_statistics(norms: list, saved: list[tuple[Tensor, Tensor]]) -> None:
    """Put back the running statistics saved by :func:`norm_statistics`."""
    with torch.no_grad():
        for b, old in saved:
            b.copy_(old)


def all_or_nothing_steps(opt, inputs: Tensor, targets: Tensor) -> Tensor:
    """``opt.step`` on each row of ``inputs`` ``(T, *x)`` and ``targets`` ``(T, *out)``; returns
    the stacked losses. A row that fails undoes the rows before it (each step replaces its
    groups' state entries, so the entries at the start restore them; the running statistics
    of BatchNorm layers are put back too) and raises naming it."""
    before, losses = {i: opt.state[_state_key(i)] for i in range(len(opt._cfg))}, []
    norms = tracking_batch_norms(opt.module)
    stats = norm_statistics(norms) if norms else None
    for row, (x, t) in enumerate(zip(inputs, targets)):
        try:
            losses.append(opt.step(x, t).loss)
        except Exception as exc:
            opt._restore(before)
            if stats is not None:
                restore_norm_statistics(norms, stats)
            if row == 0 or type(exc) not in (ValueError, TypeError):
                raise
            raise type(exc)(
                f"steps, row {row} of {len(inputs)}: {exc} (the {row} steps before it are "
                "undone too: all as before the call)"
            ) from exc
    return torch.stack(losses)


def _clone_state(obj):
    """A copy of a frozen dataclass of tensors (``None`` stays ``None``)."""
    if obj is None:
        return None
    return replace(
        obj,
        **{k: (v.clone() if isinstance(v, Tensor) else v) for k, v in _dataclass_dict(obj).items()},
    )


def _dataclass_dict(obj) -> dict | None:
    if obj is None:
        return None
    return {f.name: getattr(obj, f.name) for f in fields(obj)}


@dataclass
class _Group:
    """What one parameter group's options resolve to (rebuilt after ``load_state_dict``)."""

    bridge: ParameterBridge
    filter: GaussianFilter
    chol_P0: Tensor
    chol_Q: Tensor
    chol_R1: Tensor
    R_scalar: bool
    chol_R: dict = field(default_factory=dict)  # M -> (lr, factor of R / lr, (M, M))
    models: dict = field(default_factory=dict)  # (input shape, output shape) -> model


def _group_bridge(module: nn.Module, params) -> ParameterBridge:
    """The bridge of a group's parameters (which must be parameters of ``module``)."""
    if isinstance(params, Tensor):
        params = [params]
    elif isinstance(params, nn.Module):
        raise TypeError(
            "a parameter group's 'params' must be parameters (e.g. "
            "module.layer.parameters()), got a module"
        )
    elif isinstance(params, (set, dict, str)) or not isinstance(params, Iterable):
        raise TypeError(
            f"a parameter group's 'params' must be an ordered iterable of parameters, got "
            f"{type(params)}"
        )
    by_id = {id(p): n for n, p in module.named_parameters()}
    names = []
    for p in params:
        if isinstance(p, tuple) and len(p) == 2:  # named_parameters()
            p = p[1]
        if isinstance(p, dict):
            raise TypeError("a parameter group's 'params' must not contain dicts")
        if not isinstance(p, Tensor) or id(p) not in by_id:
            raise ValueError("params must contain parameters of module only")
        names.append((by_id[id(p)], p.requires_grad))
    if not names:
        raise ValueError("params is empty: no parameters to train")
    # as with torch.optim, a frozen parameter (requires_grad=False) swept in with trainable ones
    # (module.parameters() of a model with frozen layers) is not trained; a list of frozen
    # parameters only is an explicit request to train them
    if any(trainable for _, trainable in names):
        names = [(n, t) for n, t in names if t]
    return ParameterBridge(module, [n for n, _ in names])


def _configure(module: nn.Module, g: dict, where: str) -> _Group:
    """Resolve one group's options (validated; nothing is changed)."""
    bridge = _group_bridge(module, g["params"])
    n, dev = bridge.numel, bridge.device
    if g["jacobian"] not in ("auto", "rev", "fwd", "autograd"):
        raise ValueError(
            f"jacobian must be 'auto', 'rev', 'fwd' or 'autograd', got {g['jacobian']!r}"
        )
    chunk = g["chunk_size"]
    if chunk is not None and (not is_int(chunk) or chunk < 1):
        raise ValueError(f"chunk_size must be None or a positive int, got {chunk!r}")
    filt = _resolve_filter(g["filter"], g["fading"], g["noise"])
    _check_lr(g["lr"], filt, f"{where}['lr']")
    P0, Q = g["P0"], g["Q"]
    P0 = bridge.expand(P0, "P0") if isinstance(P0, dict) else P0
    Q = bridge.expand(Q, "Q") if isinstance(Q, dict) else Q
    chol_P0 = noise_factor(P0, n, "P0", allow_singular=False, device=dev)
    chol_Q = noise_factor(Q, n, "Q", allow_singular=True, device=dev)
    R = _as_float64(g["R"], "R", dev)
    n_out = 1 if R.dim() == 0 else R.shape[0]
    chol_R1 = noise_factor(R, n_out, "R", allow_singular=False, device=dev)
    return _Group(bridge, filt, chol_P0, chol_Q, chol_R1, R.dim() == 0)


def _checked_state_dict(state_dict, module: nn.Module, param_groups: list[dict], device) -> dict:
    """A copy of a :meth:`KalmanOptimizer.state_dict` ready for ``torch.optim``'s loader: each
    group's belief copied to ``device`` and checked (float64, its parameters' shapes, ``runs``,
    the mean and factor shapes); groups without ``lr`` get ``lr = 1``."""
    if not isinstance(state_dict, dict) or "param_groups" not in state_dict:
        raise TypeError("state_dict must be a dict from KalmanOptimizer.state_dict()")
    sd = dict(state_dict)
    st = dict(sd.get("state", {}))
    saved = [dict(g) for g in sd["param_groups"]]
    if len(saved) != len(param_groups):
        raise ValueError(
            f"state_dict has {len(saved)} parameter groups, this optimiser {len(param_groups)}"
        )
    for g in saved:
        g.setdefault("lr", 1.0)
    sd["param_groups"] = saved

    def conv(v, where):
        if isinstance(v, Tensor):
            if v.is_floating_point() and v.dtype != torch.float64:
                raise ValueError(
                    f"state_dict {where} has dtype {v.dtype}; the Kalman belief must stay "
                    "float64 (it was cast, resuming would not be exact)"
                )
            return v.detach().to(device=device).clone()
        if isinstance(v, dict):
            return {kk: conv(vv, f"{where}[{kk!r}]") for kk, vv in v.items()}
        return v

    for i, (g, cur) in enumerate(zip(saved, param_groups)):
        key = _state_key(i)
        if key not in st:
            raise ValueError(
                f"state_dict['state'] has no {key!r} entry (not a KalmanOptimizer state"
                f"{'' if i == 0 else f' with {i + 1} parameter groups'})"
            )
        entry = st[key]
        lacking = [
            k for k in ("mean", "chol", "step") if not isinstance(entry, dict) or k not in entry
        ]
        if lacking or not is_int(entry["step"]) or entry["step"] < 0:
            raise ValueError(
                f"state_dict['state'][{key!r}] must be a KalmanOptimizer belief entry (a dict "
                f"with 'mean', 'chol' and an int 'step' >= 0), got "
                f"{sorted(entry) if isinstance(entry, dict) else type(entry).__name__}"
            )
        kal = conv(entry, f"['state'][{key!r}]")
        cfg = _configure(module, {**g, "params": cur["params"]}, f"state_dict param_groups[{i}]")
        runs, n = g.get("runs"), cfg.bridge.numel
        if runs != cur.get("runs"):
            raise ValueError(
                f"state_dict was saved with runs={runs!r}, this optimiser has "
                f"runs={cur.get('runs')!r} (runs applies to the whole optimiser)"
            )
        shapes = kal.get("shapes")
        if shapes is not None and [list(v) for v in cfg.bridge.shapes] != shapes:
            raise ValueError(
                f"state_dict param_groups[{i}] holds parameters of shapes {shapes}, this "
                f"optimiser's are {[list(v) for v in cfg.bridge.shapes]}"
            )
        want = (n,) if runs is None else (runs, n)
        if tuple(kal["mean"].shape) != want or tuple(kal["chol"].shape) != want + (n,):
            raise ValueError(
                f"state_dict belief {key!r} has mean {tuple(kal['mean'].shape)}, chol "
                f"{tuple(kal['chol'].shape)}; this optimiser needs {want} and {want + (n,)}"
            )
        if not all(isinstance(kal[k], Tensor) for k in ("mean", "chol")) or not (
            bool(torch.isfinite(kal["mean"]).all()) and bool(torch.isfinite(kal["chol"]).all())
        ):
            raise ValueError(f"state_dict belief {key!r} must hold finite tensors mean and chol")
        kal.pop("shapes", None)
        st[key] = kal
    sd["state"] = st
    return sd


def _check_matches(x: Tensor, name: str, dtype, device, checked: bool) -> None:
    """:func:`check_matches`; the finiteness test is skipped when the values were checked."""
    if checked:
        if x.dtype != dtype:
            check_matches(x, name, dtype, device)  # raises
        if x.device != device:
            check_matches(x, name, dtype, device)  # raises
        return
    check_matches(x, name, dtype, device)


def _check_targets(t: Tensor, dtype, device) -> bool:
    """Targets of a step: the module's dtype and device, finite or NaN where a target is
    missing (the filter then updates with the observed entries only; a step with none
    observed is a prediction). Returns whether any entry is missing."""
    if t.dtype != dtype or t.device != device:
        check_matches(t, "targets", dtype, device)  # raises
    return has_missing(t, "targets", "target")


def _call_closure(closure) -> tuple:
    """``(inputs, targets)`` from a closure; a loss-returning closure gets an explanation."""
    pair = closure()
    if isinstance(pair, tuple) and len(pair) == 2:
        return pair
    if isinstance(pair, (int, float)) or (isinstance(pair, Tensor) and pair.numel() == 1):
        raise TypeError(
            "closure returned a loss; a Kalman optimiser does not minimise a scalar loss: it "
            "updates the parameter belief from the model outputs and the targets (paper 003 "
            "Eq. 46), which one loss value does not carry. Pass the data instead: "
            "step(inputs, targets), or a closure returning (inputs, targets); "
            "prognos_torch.optim.fit(module, optimizer, (X, Y)) runs the loop for either kind "
            "of optimiser"
        )
    raise TypeError(f"closure must return a pair (inputs, targets), got {type(pair).__name__}")
