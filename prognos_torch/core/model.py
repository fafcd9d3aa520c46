"""State-space models: per-sample transition and measurement functions with additive Gaussian noise.

Convention (used by every filter, simulator and particle filter in the library): for
``k = 1, 2, ...``

    x_k = f(x_{k-1}, u_k, k) + w_k,   w_k ~ N(q_k, Q_k)      (paper 000 Eq. 1)
    y_k = h(x_k, u_k, k) + v_k,       v_k ~ N(r_k, R_k)      (paper 000 Eq. 2)

``f`` and ``h`` are written for ONE sample: ``x`` has shape ``(n,)``, ``u`` shape ``(p,)`` or
``None``, ``k`` is a Python ``int``; they return ``(n,)`` and ``(m,)``. The library batches them
with ``torch.func.vmap`` over runs, sigma points and particles, so a model is written once.
Models that already handle arbitrary leading dimensions can say so with ``batched=True``.

Noise is given by its mean and a lower square-root factor of its covariance, each either a
tensor (constant) or a callable ``k -> tensor`` (per step). Square-root factors may carry
leading batch dimensions (e.g. one ``Q`` per Monte Carlo run).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor
from torch.func import jvp, vmap

from .validation import is_int

__all__ = [
    "StateSpaceModel",
    "Noise",
    "diagonal_noise",
    "joint_state_parameter_model",
    "linear_gaussian_model",
]

Fn = Callable[[Tensor, "Tensor | None", int], Tensor]
TensorOrFn = "Tensor | Callable[[int], Tensor]"


@dataclass(frozen=True)
class Noise:
    """Additive noise statistics for one step.

    Attributes:
        q: process-noise mean ``(..., n)`` or ``None`` (zero).
        chol_Q: process-noise square root ``(..., n, n)``.
        r: measurement-noise mean ``(..., m)`` or ``None`` (zero).
        chol_R: measurement-noise square root ``(..., m, m)``.
        diag_Q: ``(..., n)``, the diagonal of ``Q = S_Q S_Q^T`` when ``S_Q`` is diagonal (then
            ``Q`` is that diagonal: the Cholesky prior adds it to the diagonal of ``A A^T``
            instead of forming ``S_Q S_Q^T``), or ``None`` (not known to be diagonal).
    """

    q: Tensor | None
    chol_Q: Tensor
    r: Tensor | None
    chol_R: Tensor
    diag_Q: Tensor | None = None


def diagonal_noise(chol_Q: Tensor) -> Tensor | None:
    """``(..., n)`` the diagonal of ``S_Q S_Q^T`` when the factor ``chol_Q`` ``(..., n, n)`` is
    diagonal, else ``None``. Tests the factor's entries: one host synchronisation, for
    constant noise made once (:meth:`StateSpaceModel.checked_noise` caches it)."""
    d = torch.diagonal(chol_Q, dim1=-2, dim2=-1)
    if torch.count_nonzero(chol_Q) != torch.count_nonzero(d):
        return None
    return d.square()


def _version(t: Tensor) -> int:
    """``t``'s version counter (in-place changes), -1 for inference tensors (which have none
    and cannot be changed in place outside inference mode)."""
    return -1 if t.is_inference() else t._version


def _at(v, k: int):
    return v(k) if callable(v) else v


def _apply(fn: Fn, x: Tensor, u: Tensor | None, k: int, batched: bool, name: str = "f") -> Tensor:
    """Evaluate a per-sample function on ``x`` of shape ``(..., n)`` (and ``u`` ``(..., p)``)."""
    if batched:
        return fn(x, u, k)
    lead = x.shape[:-1]
    xf = x.reshape(-1, x.shape[-1])
    if u is None:
        out = vmap(lambda xi: fn(xi, None, k))(xf)
    else:
        uf = torch.broadcast_to(u, lead + u.shape[-1:]).reshape(-1, u.shape[-1])
        out = vmap(lambda xi, ui: fn(xi, ui, k))(xf, uf)
    if out.dim() != 2:  # a per-sample result that is not a vector (e.g. a scalar for m = 1)
        raise ValueError(
            f"model.{name} returned shape {tuple(out.shape[1:])} for one sample; a per-sample "
            f"model.{name} must return a vector ((n,) for f, (m,) for h; one output as x[0:1])"
        )
    return out.reshape(*lead, out.shape[-1])


def _jacobian(fn: Fn, x: Tensor, u: Tensor | None, k: int, batched: bool = False) -> Tensor:
    """Jacobian ``d fn / d x`` at each of the leading-batch points: ``(..., out, n)``.

    Forward mode, one Jacobian-vector product per (point, basis vector) pair: ``B n`` pairs as
    rows of one batch, pushed through ``fn`` by ONE ``vmap`` (per-sample ``fn``; the numbers of
    ``vmap(jacfwd(fn))``, which nests a second ``vmap`` over the basis, at about 0.6 of its
    dispatch cost for small ``n``) or directly (``batched``: ``fn`` takes the rows as they are).
    """
    lead, n = x.shape[:-1], x.shape[-1]
    xf = x.reshape(-1, n)
    B = xf.shape[0]
    xr = xf.repeat_interleave(n, dim=0)  # point b, n times (a copy: jvp writes its duals)
    vr = torch.eye(n, dtype=x.dtype, device=x.device).repeat(B, 1)
    ur = None
    if u is not None:
        uf = torch.broadcast_to(u, lead + u.shape[-1:]).reshape(-1, u.shape[-1])
        ur = uf.repeat_interleave(n, dim=0)
    if batched:
        _, t = jvp(lambda z: fn(z, ur, k), (xr,), (vr,))
    else:  # u = None is passed through unbatched
        row = lambda xi, ui, vi: jvp(lambda z: fn(z, ui, k), (xi,), (vi,))  # noqa: E731
        _, t = vmap(row, in_dims=(0, None if ur is None else 0, 0))(xr, ur, vr)
    J = t.reshape(B, n, -1).mT  # row b*n + j holds column j of point b's Jacobian
    return J.reshape(*lead, J.shape[-2], n)


@dataclass(frozen=True)
class StateSpaceModel:
    """A nonlinear state-space model with additive Gaussian noise (see module docstring).

    Attributes:
        f: per-sample transition ``f(x (n,), u (p,) | None, k) -> (n,)``; ``None`` means the
            random walk ``x_k = x_{k-1} + w_k`` (the optimiser face, paper 003 Eq. 45), which the
            filters propagate exactly without sigma points or Jacobians.
        h: per-sample measurement ``h(x (n,), u, k) -> (m,)``.
        state_dim: ``n``.
        obs_dim: ``m``.
        chol_Q: ``(..., n, n)`` lower square root of ``Q``, or ``k -> tensor``.
        chol_R: ``(..., m, m)`` lower square root of ``R``, or ``k -> tensor``.
        q: process-noise mean ``(..., n)``, ``k -> tensor`` or ``None``.
        r: measurement-noise mean ``(..., m)``, ``k -> tensor`` or ``None``.
        control_dim: ``p`` (0 when the model takes no control).
        batched: ``f``/``h`` already accept arbitrary leading dimensions (skip ``vmap``).
        jac_f, jac_h: optional analytic Jacobians with the same signature, returning
            ``(n, n)`` / ``(m, n)`` per sample; by default forward-mode autodiff (``jvp``,
            under ``vmap`` unless ``batched``), exact but 5-8x slower than analytic Jacobians
            of a batched model in ``benchmarks/bench_jacobian.py``.
        f_into: optional ``f_into(x (..., n), u, k, out (..., n)) -> out``: the batched ``f``
            written into the given tensor ``out`` (any strides, not overlapping ``x``), with
            the same numbers as ``f``. Loops that keep their states in a buffer of their own
            (:func:`~prognos_torch.prognosis.simulate_to_event`) use it through
            :meth:`transition_into` to skip a copy per step; plain tensors only (no
            ``torch.func`` transforms). Needs ``batched=True``.
    """

    f: Fn | None
    h: Fn
    state_dim: int
    obs_dim: int
    chol_Q: Tensor | Callable[[int], Tensor]
    chol_R: Tensor | Callable[[int], Tensor]
    q: Tensor | Callable[[int], Tensor] | None = None
    r: Tensor | Callable[[int], Tensor] | None = None
    control_dim: int = 0
    batched: bool = False
    jac_f: Fn | None = field(default=None, repr=False)
    jac_h: Fn | None = field(default=None, repr=False)
    f_into: Callable[..., Tensor] | None = field(default=None, repr=False)

    def __post_init__(self):
        if not callable(self.h):
            raise TypeError("h must be a callable h(x, u, k) -> (m,)")
        if self.f is not None and not callable(self.f):
            raise TypeError("f must be a callable f(x, u, k) -> (n,) or None (random walk)")
        for name in ("state_dim", "obs_dim"):
            v = getattr(self, name)
            if not is_int(v) or v < 1:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
            object.__setattr__(self, name, int(v))
        if not is_int(self.control_dim) or self.control_dim < 0:
            raise ValueError(f"control_dim must be a non-negative int, got {self.control_dim!r}")
        object.__setattr__(self, "control_dim", int(self.control_dim))
        if self.f_into is not None and not (
            callable(self.f_into) and self.f is not None and self.batched
        ):
            raise ValueError(
                "f_into must be a callable f_into(x, u, k, out) -> out, given with f and "
                "batched=True"
            )

    # -- noise --------------------------------------------------------------------------
    def noise(self, k: int) -> Noise:
        """Noise statistics at step ``k`` (callables are evaluated here)."""
        return Noise(_at(self.q, k), _at(self.chol_Q, k), _at(self.r, k), _at(self.chol_R, k))

    def checked_noise(self, k: int, batch_shape, like: Tensor, owner: str = "belief") -> Noise:
        """Noise at step ``k`` converted to ``like``'s dtype and checked against ``batch_shape``.

        Each tensor must have its plain shape (``(n,)``, ``(n, n)``, ``(m,)``, ``(m, m)``) or
        ``batch_shape`` followed by it; anything else is a ``ValueError`` naming the field.
        """
        n, m, bs = self.state_dim, self.obs_dim, tuple(batch_shape)
        raw = (self.q, self.chol_Q, self.r, self.chol_R)
        key = (bs, like.dtype, like.device)
        hit = None if torch.compiler.is_compiling() else self.__dict__.get("_checked_noise")
        if hit is not None and hit[0] == key and all(a is b for a, b in zip(hit[1], raw)):
            if hit[3] == _version(hit[2].chol_Q):
                return hit[2]  # constant noise, already checked for this batch shape and dtype
            # S_Q changed in place: its diagonal test is redone below
        noise = self.noise(k)

        def conv(x, name, tail, what):
            if x is None:
                return None
            if not isinstance(x, Tensor):
                x = torch.as_tensor(x, dtype=like.dtype, device=like.device)
            if x.device != like.device:
                raise ValueError(f"{name} is on {x.device}, the {owner} on {like.device}")
            if x.dtype != like.dtype:
                x = x.to(like.dtype)
            if tuple(x.shape) not in (tail, bs + tail):
                raise ValueError(
                    f"{name} must have shape {what} with {tail} or batch shape {bs} + {tail}, "
                    f"got {tuple(x.shape)}"
                )
            # values (a host sync on an accelerator: there once per constant tensor, below)
            if x.device.type == "cpu" and not torch.compiler.is_compiling():
                _check_finite_noise(x, name)
            return x

        out = Noise(
            conv(noise.q, "model.q", (n,), "(n,)"),
            conv(noise.chol_Q, "model.chol_Q", (n, n), "(n, n)"),
            conv(noise.r, "model.r", (m,), "(m,)"),
            conv(noise.chol_R, "model.chol_R", (m, m), "(m, m)"),
        )
        if not torch.compiler.is_compiling() and all(
            a is b for a, b in zip(raw, (out.q, out.chol_Q, out.r, out.chol_R))
        ):
            # constant tensors used as they are (no conversion that an in-place change of the
            # original would make stale): remember the check for the next step, with the
            # diagonal of a diagonal Q
            if out.chol_Q.device.type != "cpu":  # (on the CPU conv checked them)
                for name, v in zip(("model.q", "model.chol_Q", "model.r", "model.chol_R"), out):
                    if v is not None:
                        _check_finite_noise(v, name)
            if not out.chol_Q.requires_grad:  # (a diagonal under autograd would cut its graph)
                with torch.inference_mode(False), torch.no_grad():
                    out = replace(out, diag_Q=diagonal_noise(out.chol_Q))
            object.__setattr__(self, "_checked_noise", (key, raw, out, _version(out.chol_Q)))
        return out

    # -- batched evaluation -------------------------------------------------------------
    def transition(self, x: Tensor, u: Tensor | None, k: int) -> Tensor:
        """Noise-free ``f`` on ``x`` of shape ``(..., n)``; returns ``(..., n)``."""
        if self.f is None:
            return x
        return _checked_out(_evaluate(self.f, "f", x, u, k, self.batched), self.state_dim, "f",
                            "state_dim")  # fmt: skip

    def transition_into(self, x: Tensor, u: Tensor | None, k: int, out: Tensor) -> Tensor:
        """:meth:`transition` of ``x`` ``(..., n)`` written into ``out`` ``(..., n)``; returns ``out``.

        Uses ``f_into`` when the model has one, else copies ``transition(x, u, k)`` into ``out``.
        """
        if self.f_into is not None:
            return self.f_into(x, u, k, out)
        return out.copy_(self.transition(x, u, k))

    def observe(self, x: Tensor, u: Tensor | None, k: int) -> Tensor:
        """Noise-free ``h`` on ``x`` of shape ``(..., n)``; returns ``(..., m)``."""
        return _checked_out(_evaluate(self.h, "h", x, u, k, self.batched), self.obs_dim, "h",
                            "obs_dim")  # fmt: skip

    def transition_jacobian(self, x: Tensor, u: Tensor | None, k: int) -> Tensor:
        """``df/dx`` at ``x`` ``(..., n)``: ``(..., n, n)`` (identity for the random walk)."""
        if self.f is None:
            eye = torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
            return eye.expand(*x.shape[:-1], self.state_dim, self.state_dim)
        if self.jac_f is not None:
            J = _apply_matrix(self.jac_f, x, u, k, self.batched)
            return _checked_jac(J, self.state_dim, self.state_dim, "jac_f", "(n, n)")
        return _jacobian(self.f, x, u, k, self.batched)

    def observation_jacobian(self, x: Tensor, u: Tensor | None, k: int) -> Tensor:
        """``dh/dx`` at ``x`` ``(..., n)``: ``(..., m, n)``."""
        if self.jac_h is not None:
            J = _apply_matrix(self.jac_h, x, u, k, self.batched)
            return _checked_jac(J, self.obs_dim, self.state_dim, "jac_h", "(m, n)")
        return _jacobian(self.h, x, u, k, self.batched)


class NonFiniteNoiseError(ValueError):
    """A model's noise mean or square root holds NaN or inf (every estimate would be NaN)."""


def _check_finite_noise(x: Tensor, name: str) -> None:
    """A noise mean or square root holds finite numbers (a NaN would make every mean NaN)."""
    if not bool(torch.isfinite(x).all()):
        raise NonFiniteNoiseError(f"{name} contains non-finite values (NaN or inf)")


def _evaluate(fn: Fn, name: str, x: Tensor, u, k: int, batched: bool):
    """``fn`` (the model's ``f`` or ``h``, called ``name``) on ``x``; a dtype clash inside it
    (float64 constants on float32 states, a float32 model on a float64 belief) is raised as
    such, not as torch's "expected m1 and m2 to have the same dtype"."""
    try:
        return _apply(fn, x, u, k, batched, name)
    except RuntimeError as exc:
        text = str(exc)
        if "dtype" not in text and "scalar type" not in text:
            raise
        raise TypeError(
            f"model.{name} failed on states of dtype {x.dtype} ({text.splitlines()[0]}): the "
            f"model computes in another dtype; pass the belief or particles in the model's "
            f"dtype, or build the model's constants in {x.dtype}"
        ) from exc


def _checked_out(out, dim: int, fn: str, field: str) -> Tensor:
    """``out`` of the model's ``f`` or ``h``, refused unless its last dimension is ``dim`` (a
    wrong length would broadcast through the filter's arithmetic into finite, wrong numbers)."""
    if not isinstance(out, Tensor) or out.dim() == 0 or out.shape[-1] != dim:
        got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
        raise ValueError(
            f"model.{fn} returned {got}; it must return (..., {field}) = (..., {dim}) for each "
            f"input (..., state_dim)"
        )
    return out


def _checked_jac(J, rows: int, cols: int, name: str, what: str) -> Tensor:
    """An analytic Jacobian, refused unless it ends in ``(rows, cols)`` (a wrong shape would
    broadcast through the filter's products into wrong numbers or a cryptic error)."""
    if not isinstance(J, Tensor) or J.dim() < 2 or J.shape[-2:] != (rows, cols):
        got = tuple(J.shape) if isinstance(J, Tensor) else type(J).__name__
        raise ValueError(
            f"model.{name} returned {got}; it must return {what} = ({rows}, {cols}) per sample"
        )
    return J


def _apply_matrix(fn: Fn, x: Tensor, u: Tensor | None, k: int, batched: bool) -> Tensor:
    if batched:
        return fn(x, u, k)
    lead = x.shape[:-1]
    flat = lambda xi, ui: fn(xi, ui, k).reshape(-1)  # noqa: E731
    xf = x.reshape(-1, x.shape[-1])
    if u is None:
        out = vmap(lambda xi: flat(xi, None))(xf)
    else:
        uf = torch.broadcast_to(u, lead + u.shape[-1:]).reshape(-1, u.shape[-1])
        out = vmap(flat)(xf, uf)
    J0 = fn(xf[0], None if u is None else uf[0], k)
    return out.reshape(*lead, *J0.shape)


def linear_gaussian_model(
    F: Tensor,
    H: Tensor,
    chol_Q: Tensor,
    chol_R: Tensor,
    *,
    B: Tensor | None = None,
    q: Tensor | None = None,
    r: Tensor | None = None,
) -> StateSpaceModel:
    """``x_k = F x_{k-1} + B u_k + w_k``, ``y_k = H x_k + v_k`` as a :class:`StateSpaceModel`.

    ``F``: ``(n, n)``, ``H``: ``(m, n)``, ``B``: ``(n, p)`` or ``None``. The filters treat it as any
    nonlinear model (sigma points / Jacobians), which is what the exactness tests rely on.
    """
    for name, M in (("F", F), ("H", H), ("B", B)):
        if M is not None and (not isinstance(M, Tensor) or M.dim() != 2):
            got = tuple(M.shape) if isinstance(M, Tensor) else type(M).__name__
            raise ValueError(f"linear_gaussian_model: {name} must be a 2-D tensor, got {got}")
    n, m = F.shape[-1], H.shape[-2]
    if F.shape != (n, n) or H.shape != (m, n) or (B is not None and B.shape[0] != n):
        raise ValueError(
            f"linear_gaussian_model: F must be (n, n), H (m, n) and B (n, p), got F "
            f"{tuple(F.shape)}, H {tuple(H.shape)}" + ("" if B is None else f", B {tuple(B.shape)}")
        )
    if B is None:
        f = lambda x, u, k: F @ x  # noqa: E731
        p = 0
    else:

        def f(x, u, k):
            if u is None:
                raise ValueError(f"this linear_gaussian_model has B {tuple(B.shape)}: pass u (p,)")
            return F @ x + B @ u

        p = B.shape[-1]
    h = lambda x, u, k: H @ x  # noqa: E731
    return StateSpaceModel(
        f=f, h=h, state_dim=n, obs_dim=m, chol_Q=chol_Q, chol_R=chol_R, q=q, r=r, control_dim=p
    )


def joint_state_parameter_model(
    f: Callable[[Tensor, Tensor, Tensor | None, int], Tensor],
    h: Callable[[Tensor, Tensor, Tensor | None, int], Tensor],
    *,
    state_dim: int,
    param_dim: int,
    obs_dim: int,
    chol_Q: Tensor | Callable[[int], Tensor],
    chol_D: Tensor | Callable[[int], Tensor],
    chol_R: Tensor | Callable[[int], Tensor],
    q: Tensor | None = None,
    r: Tensor | None = None,
    control_dim: int = 0,
    batched: bool = False,
) -> StateSpaceModel:
    """Augment unknown parameters ``theta`` as random-walk states (paper 000 Eq. 3-4; paper 004 Eq. 12-13).

    ``x^e_k = [f(x_{k-1}, theta_{k-1}, u_k, k); theta_{k-1}] + [w; d]``,
    ``y_k = h(x_k, theta_k, u_k, k) + v``. The assistant model ``theta_k = theta_{k-1}`` is the
    paper's choice when the fault's law of change is unknown.

    Args:
        f: per-sample ``f(x (n,), theta (d,), u, k) -> (n,)``, or with ``batched=True``
            ``f(x (..., n), theta (..., d), u, k) -> (..., n)``.
        h: per-sample ``h(x, theta, u, k) -> (m,)`` (batched: ``(..., m)``).
        chol_Q: ``(n, n)`` square root of the state-noise covariance.
        chol_D: ``(d, d)`` square root of the parameter random-walk covariance.
        chol_R: ``(m, m)``.
        batched: ``f`` and ``h`` accept any leading dimensions; the augmented model is then
            ``batched=True`` (no ``vmap`` per call).
    Returns:
        A :class:`StateSpaceModel` on the ``n + d`` dimensional augmented state.
    """
    n, d = state_dim, param_dim

    def fa(z, u, k):
        x, th = z[..., :n], z[..., n:]
        return torch.cat([f(x, th, u, k), th], -1)

    def ha(z, u, k):
        return h(z[..., :n], z[..., n:], u, k)

    def block(k: int) -> Tensor:
        SQ, SD = _at(chol_Q, k), _at(chol_D, k)
        out = SQ.new_zeros(*SQ.shape[:-2], n + d, n + d)
        out[..., :n, :n] = SQ
        out[..., n:, n:] = SD
        return out

    const = not callable(chol_Q) and not callable(chol_D)
    qa = None if q is None else torch.cat([q, q.new_zeros(d)])
    return StateSpaceModel(
        f=fa,
        h=ha,
        state_dim=n + d,
        obs_dim=obs_dim,
        chol_Q=block(0) if const else block,
        chol_R=chol_R,
        q=qa,
        r=r,
        control_dim=control_dim,
        batched=batched,
    )
