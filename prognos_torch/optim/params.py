"""The bridge between a module's parameters and the filter state ``theta`` (paper 003 Eq. 44-46).

Training as state estimation needs three things from a learner: its parameters as one float64
vector ``theta`` (Eq. 44), the model output as a function of ``theta`` (the measurement function
``g(theta, u)`` of Eq. 46), and that function evaluated at many ``theta`` at once (sigma points,
Monte Carlo runs) or differentiated with respect to ``theta`` (EKF). :class:`ParameterBridge`
provides exactly these, with ``torch.func.functional_call`` so that the module stays a plain
``nn.Module`` that knows nothing about filters.

Layout of ``theta``: the selected parameters in the module's registration order
(``module.named_parameters()``), each flattened row-major. For :class:`~prognos_torch.learners.ANFIS`
this is the order of paper 003 Eq. 44 (see ``ANFIS.flat_parameter_names``).

Layout of the measurement vector: the model output of a mini-batch, ``(B, n_out)`` (or any shape),
flattened row-major, i.e. sample after sample.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import torch
from torch import Tensor, nn
from torch.func import functional_call, jacfwd, jacrev, jvp, vmap

from ..core.validation import is_bool_or_complex

__all__ = ["ParameterBridge", "Selector"]

#: How to choose the parameters that form ``theta``: ``None`` (those with ``requires_grad``),
#: a sequence of parameter names, or a predicate ``(name, parameter) -> bool``.
Selector = None | Sequence[str] | Callable[[str, nn.Parameter], bool]


class ParameterBridge:
    """Flatten selected module parameters to ``theta`` and evaluate the module as ``g(theta, x)``.

    Non-selected parameters and all buffers are held fixed at their current values in the module
    (they are read from the module at every call, so later changes to them are seen).

    Args:
        module: the learner.
        params: selection of the parameters that form ``theta``: ``None`` selects every parameter
            with ``requires_grad=True``; a sequence of names (as in ``module.named_parameters()``)
            selects those, trainable or not (a Kalman optimiser needs no gradients; a tied
            parameter, one ``Parameter`` in several layers, is one entry of ``theta`` under its
            first name, and any of its names selects it); a callable
            ``(name, parameter) -> bool`` selects where it returns true. ``theta`` always follows
            the module's registration order.

    Raises:
        TypeError: ``module`` is not an ``nn.Module`` or ``params`` has the wrong type.
        ValueError: ``params`` selects nothing, names an unknown parameter, or selects parameters
            of mixed dtype/device or of a non-floating dtype.
    """

    def __init__(self, module: nn.Module, params: Selector = None) -> None:
        if not isinstance(module, nn.Module):
            raise TypeError(f"module must be a torch.nn.Module, got {type(module)}")
        named = list(module.named_parameters())
        if params is None:
            chosen = [(n, p) for n, p in named if p.requires_grad]
        elif isinstance(params, str):
            raise TypeError(
                f"params must be None, a sequence of parameter names or a predicate; "
                f"got the string {params!r} (wrap a single name in a list)"
            )
        elif callable(params):
            chosen = [(n, p) for n, p in named if params(n, p)]
        elif isinstance(params, Iterable):
            wanted = list(params)
            if not all(isinstance(w, str) for w in wanted):
                raise TypeError("params must be a sequence of parameter names (str)")
            known = {n for n, _ in named}
            # a tied parameter (one Parameter in two layers) is listed once by
            # named_parameters(), under its first name; its other names select it too
            first = {id(p): n for n, p in named}
            alias = {n: first[id(p)] for n, p in module.named_parameters(remove_duplicate=False)}
            unknown = [w for w in wanted if w not in alias]
            if unknown:
                raise ValueError(
                    f"params names unknown parameters {unknown}; the module has {sorted(known)}"
                )
            resolved = [alias[w] for w in wanted]
            if len(set(resolved)) != len(resolved):
                tied = [f"{w!r} is {alias[w]!r}" for w in wanted if alias[w] != w]
                raise ValueError(
                    f"params names a parameter more than once: {wanted}"
                    + (f" (tied: {', '.join(tied)})" if tied else "")
                )
            chosen = [(n, p) for n, p in named if n in set(resolved)]
        else:
            raise TypeError(
                f"params must be None, a sequence of parameter names or a predicate (name, "
                f"parameter) -> bool, got {type(params)}"
            )
        if not chosen:
            raise ValueError(
                "params selects no trainable parameters of the module (default: parameters "
                "with requires_grad=True); pass params=[names] to choose them explicitly"
            )
        if sum(p.numel() for _, p in chosen) == 0:
            raise ValueError(
                f"params selects only parameters with no elements ({', '.join(n for n, _ in chosen)}"
                "): theta would be empty"
            )
        dtypes = {p.dtype for _, p in chosen}
        devices = {p.device for _, p in chosen}
        if len(dtypes) != 1 or not next(iter(dtypes)).is_floating_point:
            raise ValueError(
                f"params must select floating-point parameters of one dtype, got {sorted(map(str, dtypes))}"
            )
        if len(devices) != 1:
            raise ValueError(f"params must select parameters on one device, got {devices}")
        self.module = module
        self.names: tuple[str, ...] = tuple(n for n, _ in chosen)
        self.shapes: tuple[torch.Size, ...] = tuple(p.shape for _, p in chosen)
        self.numels: tuple[int, ...] = tuple(p.numel() for _, p in chosen)
        self.numel: int = sum(self.numels)
        self.dtype: torch.dtype = next(iter(dtypes))
        self.device: torch.device = next(iter(devices))
        offsets = [0]
        for k in self.numels:
            offsets.append(offsets[-1] + k)
        self.slices: tuple[slice, ...] = tuple(
            slice(a, b) for a, b in zip(offsets[:-1], offsets[1:])
        )
        self._params = [p for _, p in chosen]

    # ------------------------------------------------------------------ parameters <-> theta
    def parameters(self) -> list[nn.Parameter]:
        """The selected parameter objects of the module, in ``theta`` order."""
        params = dict(self.module.named_parameters())
        return [params[n] for n in self.names]

    def expand(self, values: dict[str, float], name: str = "values") -> Tensor:
        """A per-parameter-tensor value spread over ``theta``: ``{name: v}`` -> ``(n,)`` float64.

        Every selected parameter must be named (e.g. ``{"alpha": 1.0, "b": 1e-2, "beta": 1e-4}``
        for an ANFIS prior variance); ``v`` is a number or a tensor of the parameter's shape.
        """
        if not isinstance(values, dict):
            raise TypeError(f"{name} must be a dict parameter name -> value")
        missing = [n for n in self.names if n not in values]
        extra = [n for n in values if n not in self.names]
        if missing or extra:
            raise ValueError(
                f"{name} must give a value for exactly the selected parameters {list(self.names)}"
                f"; missing {missing}, unknown {extra}"
            )
        parts = []
        for pname, shape, k in zip(self.names, self.shapes, self.numels):
            raw = values[pname]
            kind = getattr(getattr(raw, "dtype", None), "kind", "")  # NumPy text or objects
            # (a bool was read as 1, a complex value lost its imaginary part, text failed in torch)
            if isinstance(raw, str) or kind in ("U", "S", "O") or is_bool_or_complex(raw):
                raise TypeError(
                    f"{name}[{pname!r}] must be a real number or a tensor of reals, got {raw!r}"
                )
            v = torch.as_tensor(raw, dtype=torch.float64, device=self.device)
            if v.dim() == 0:
                v = v.expand(k)
            elif tuple(v.shape) == tuple(shape):
                v = v.reshape(-1)
            else:
                raise ValueError(
                    f"{name}[{pname!r}] must be a number or have shape {tuple(shape)}, got "
                    f"{tuple(v.shape)}"
                )
            parts.append(v)
        return torch.cat(parts)

    def flat_names(self) -> list[str]:
        """One label per entry of ``theta``: ``name[i, j, ...]`` (the module's index)."""
        out = []
        for name, shape in zip(self.names, self.shapes):
            if len(shape) == 0:
                out.append(name)
                continue
            for idx in torch.cartesian_prod(*[torch.arange(s) for s in shape]).reshape(
                -1, len(shape)
            ):
                out.append(f"{name}[{', '.join(str(int(i)) for i in idx)}]")
        return out

    def flatten(self, module: nn.Module | None = None) -> Tensor:
        """``theta`` ``(n,)`` float64 (detached copy) from ``module`` (default: the bridged one).

        ``module`` may be any module with the same selected parameter names and shapes (e.g.
        another initialisation of the same learner).
        """
        src = self.module if module is None else module
        params = dict(src.named_parameters())
        parts = []
        for name, shape, own in zip(self.names, self.shapes, self._params):
            p = params.get(name)
            if module is None and p is not None and p.shape != shape:
                raise ValueError(
                    f"the module's parameter {name!r} now has shape {tuple(p.shape)}; this was "
                    f"built for {tuple(shape)} (an LS-SVR refitted on another number of samples "
                    "changes alpha's shape, for one): build a new optimiser for the module"
                )
            if module is None and p is not None and p is not own:
                # assign writes into the objects the bridge was built on: the module's new
                # parameter would be read here but never written (its training silently lost)
                raise ValueError(
                    f"the module's parameter {name!r} was replaced by a new Parameter object "
                    "after this was built (module.<name> = nn.Parameter(...)): build a new "
                    "optimiser for the module, or write new values in place "
                    "(with torch.no_grad(): parameter.copy_(values))"
                )
            if p is None or p.shape != shape:
                raise ValueError(
                    f"module has no parameter {name!r} of shape {tuple(shape)} "
                    "(it must have the bridged module's structure)"
                )
            parts.append(p.detach().reshape(-1).to(device=self.device, dtype=torch.float64))
        return torch.cat(parts)

    def stack(self, modules: Sequence[nn.Module]) -> Tensor:
        """``theta`` of several structurally identical modules: ``(R, n)`` float64.

        Used to start a batch of Monte Carlo runs from ``R`` independent initialisations.
        """
        modules = list(modules)
        if not modules:
            raise ValueError("modules must contain at least one module")
        return torch.stack([self.flatten(m) for m in modules])

    def _check_theta(self, theta: Tensor, name: str = "theta") -> Tensor:
        if not isinstance(theta, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor of shape (..., {self.numel})")
        if theta.dim() < 1 or theta.shape[-1] != self.numel:
            raise ValueError(
                f"{name} must have shape (..., n) with n={self.numel} (the number of selected "
                f"parameter entries), got {tuple(theta.shape)}"
            )
        return theta

    def unflatten(self, theta: Tensor) -> dict[str, Tensor]:
        """Split ``theta`` ``(..., n)`` into ``{name: (..., *shape)}`` in the module dtype.

        The result is differentiable with respect to ``theta`` and works under ``vmap``.
        """
        theta = self._check_theta(theta)
        lead = theta.shape[:-1]
        if theta.dtype != self.dtype:
            theta = theta.to(self.dtype)
        # (shapes as one tuple: a scalar parameter of shape () needs reshape(()))
        if len(self.names) == 1:
            return {self.names[0]: theta.reshape(tuple(lead) + tuple(self.shapes[0]))}
        parts = theta.split(self.numels, dim=-1)  # one operation for all the views
        return {
            name: part.reshape(tuple(lead) + tuple(shape))
            for name, part, shape in zip(self.names, parts, self.shapes)
        }

    def assign(self, theta: Tensor) -> None:
        """Write ``theta`` ``(n,)`` into the module's parameters (cast to the module dtype)."""
        if torch.is_grad_enabled():
            with torch.no_grad():
                return self.assign(theta)
        theta = self._check_theta(theta)
        if theta.dim() != 1:
            raise ValueError(f"theta must have shape ({self.numel},), got {tuple(theta.shape)}")
        if theta.device != self.device:
            theta = theta.to(self.device)
        parts = theta.split(self.numels)
        # copy_ casts to the parameter dtype; one fused call for all parameters
        torch._foreach_copy_(self._params, [t.view_as(p) for t, p in zip(parts, self._params)])

    # ------------------------------------------------------------------ the model as g(theta, x)
    def functional(self, theta: Tensor, x: Tensor) -> Tensor:
        """``module(x)`` with the selected parameters replaced by ``theta`` ``(n,)``
        (paper 003 Eq. 46: ``g(theta, u)``); output in the module dtype."""
        return functional_call(self.module, self.unflatten(theta), (x,))

    def batched(self, theta: Tensor, x: Tensor, *, chunk_size: int | None = None) -> Tensor:
        """``g(theta, x)`` for many ``theta`` ``(..., n)`` at once (vmap): ``(..., *out)``.

        Args:
            theta: ``(..., n)``, e.g. sigma points ``(L, n)`` or runs x sigma points ``(R, L, n)``.
            x: the module input (shared by all ``theta``).
            chunk_size: evaluate at most this many ``theta`` per vectorised call.
        """
        theta = self._check_theta(theta)
        if theta.dim() == 1:
            return self.functional(theta, x)
        lead = theta.shape[:-1]
        fast = getattr(self.module, "forward_with", None)
        if fast is not None and chunk_size is None and x.dim() == 2:
            # the learner broadcasts over batched parameters itself: one pass, no vmap
            return fast(self.unflatten(theta), x)
        out = vmap(lambda t: self.functional(t, x), chunk_size=chunk_size)(
            theta.reshape(-1, self.numel)
        )
        return out.reshape(*lead, *out.shape[1:])

    def measurement(self, theta: Tensor, x: Tensor, *, chunk_size: int | None = None) -> Tensor:
        """The measurement vector ``g(theta, x)`` flattened and in float64: ``(..., M)``.

        ``M`` is the number of output entries of the mini-batch (``B * n_out`` for ``(B, n_out)``
        outputs), flattened sample after sample.
        """
        out = self.batched(theta, x, chunk_size=chunk_size)
        lead = theta.shape[:-1]
        out = out.reshape(*lead, -1)
        return out if out.dtype == torch.float64 else out.to(torch.float64)

    def has_closed_form_jacobian(self, x: Tensor, chunk_size: int | None = None) -> bool:
        """Whether the module offers ``forward_and_jacobian`` (the library's learners do) and
        it applies here (2-D input ``(B, n_in)``, no chunking)."""
        return (
            getattr(self.module, "forward_and_jacobian", None) is not None
            and chunk_size is None
            and isinstance(x, Tensor)
            and x.dim() == 2
        )

    def _closed_form(self, theta: Tensor, x: Tensor) -> tuple[Tensor, Tensor]:
        """Measurement ``(..., M)`` and Jacobian ``(..., M, n)`` from the module's own
        ``forward_and_jacobian(params, x, names)`` (exact derivatives, no autograd)."""
        lead = theta.shape[:-1]
        out, jac = self.module.forward_and_jacobian(self.unflatten(theta), x, self.names)
        M = out.shape[-2] * out.shape[-1]
        J = torch.cat([jac[n].reshape(*lead, M, k) for n, k in zip(self.names, self.numels)], -1)
        out = out.reshape(*lead, M)
        if out.dtype != torch.float64:
            out, J = out.to(torch.float64), J.to(torch.float64)
        return out, J

    def jacobian(
        self,
        theta: Tensor,
        x: Tensor,
        *,
        mode: str = "auto",
        chunk_size: int | None = None,
    ) -> Tensor:
        """Jacobian of the measurement vector with respect to ``theta``: ``(..., M, n)`` float64.

        Args:
            theta: ``(..., n)``; every leading index gets its own Jacobian.
            x: the module input.
            mode: ``"rev"`` (``torch.func.jacrev``: one vector-Jacobian product per output
                entry), ``"fwd"`` (``torch.func.jacfwd``: one Jacobian-vector product per
                parameter), ``"autograd"`` (reverse mode with ``torch.autograd.grad`` on the
                vectorised forward pass: the outputs of different leading indices depend only on
                their own ``theta``, so the gradient of their sum gives every row at once; the
                same numbers as ``"rev"`` with less overhead), or ``"auto"``: the module's
                closed-form ``forward_and_jacobian`` when it has one (ELM, ANFIS; see
                :meth:`has_closed_form_jacobian`), else ``"fwd"`` when ``n <= M``, else
                ``"autograd"``.
            chunk_size: at most this many products at once (limits memory for large models).
        """
        theta = self._check_theta(theta)
        if mode not in ("auto", "rev", "fwd", "autograd"):
            raise ValueError(f"mode must be 'auto', 'rev', 'fwd' or 'autograd', got {mode!r}")
        theta = theta.to(torch.float64)
        if mode == "auto" and self.has_closed_form_jacobian(x, chunk_size):
            return self._closed_form(theta, x)[1]
        if mode == "auto":
            with torch.no_grad():
                M = self.functional(theta.reshape(-1, self.numel)[0], x).numel()
            mode = "fwd" if self.numel <= M else "autograd"
        if mode == "autograd":
            return self._jacobian_autograd(theta, x, chunk_size)
        g = lambda t: self.functional(t, x).reshape(-1).to(torch.float64)  # noqa: E731
        if mode == "rev":
            jac = jacrev(g, chunk_size=chunk_size)
        elif chunk_size is None:
            jac = jacfwd(g)
        else:  # jacfwd has no chunk_size: push the basis through jvp in chunks
            eye = torch.eye(self.numel, dtype=torch.float64, device=theta.device)

            def jac(t):
                cols = vmap(lambda v: jvp(g, (t,), (v,))[1], chunk_size=chunk_size)(eye)
                return cols.mT

        if theta.dim() == 1:
            return jac(theta)
        lead = theta.shape[:-1]
        J = vmap(jac)(theta.reshape(-1, self.numel))
        return J.reshape(*lead, *J.shape[1:])

    def measurement_and_jacobian(
        self, theta: Tensor, x: Tensor, *, chunk_size: int | None = None, mode: str = "auto"
    ) -> tuple[Tensor, Tensor]:
        """:meth:`measurement` ``(..., M)`` and :meth:`jacobian` ``(..., M, n)`` from one pass:
        the module's closed form (``mode="auto"``, when it has one) or one forward and one
        reverse pass (``"autograd"``, and ``"auto"`` otherwise)."""
        if mode not in ("auto", "autograd"):
            raise ValueError(f"mode must be 'auto' or 'autograd', got {mode!r}")
        theta = self._check_theta(theta)
        if theta.dtype != torch.float64:
            theta = theta.to(torch.float64)
        if mode == "auto" and self.has_closed_form_jacobian(x, chunk_size):
            return self._closed_form(theta, x)
        return self._jacobian_autograd(theta, x, chunk_size, with_output=True)

    def _jacobian_autograd(
        self, theta: Tensor, x: Tensor, chunk_size: int | None, with_output: bool = False
    ):
        J, out = self._autograd_rows(theta, x, chunk_size)
        return (out, J) if with_output else J

    def _autograd_rows(self, theta: Tensor, x: Tensor, chunk_size: int | None):
        if torch.is_inference_mode_enabled() or theta.is_inference() or x.is_inference():
            # reverse mode needs ordinary tensors: leave inference mode for this computation
            with torch.inference_mode(False):
                return self._autograd_rows(theta.clone(), x.clone(), chunk_size)
        with torch.enable_grad():
            t = theta.detach().requires_grad_(True)
            out = self.measurement(t, x)  # (..., M)
            M = out.shape[-1]
            total = out.reshape(-1, M).sum(0)  # row j: sum over leading indices of output j
            if M == 1:
                (g,) = torch.autograd.grad(total, t)
                return g.unsqueeze(-2), out.detach()
            eye = torch.eye(M, dtype=total.dtype, device=total.device)
            step = M if chunk_size is None else chunk_size
            rows = []
            for a in range(0, M, step):
                (g,) = torch.autograd.grad(
                    total, t, eye[a : a + step], retain_graph=a + step < M, is_grads_batched=True
                )
                rows.append(g)
            return torch.cat(rows).movedim(0, -2), out.detach()
