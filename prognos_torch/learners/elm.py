"""Extreme learning machine with ridge and regularised online sequential learning (paper 000).

ELM with ``L`` additive hidden nodes (paper 000, Eq. 47-48)::

    f_L(mu) = sum_i beta^i g(a_i . mu + b_i)

with random, fixed input weights ``a_i`` uniform in [-1, 1] and biases ``b_i`` uniform in [0, 1]
(paper 000, Sec. 6). The output weights ``beta`` are found by ridge regression (Eq. 52-54) or
recursively by ROS-ELM (Eq. 55-56).

The module is a plain ``torch.nn.Module``: ``forward`` is pure tensor code (no in-place ops on
parameters, no data-dependent control flow), so it can be evaluated with
``torch.func.functional_call`` under ``vmap``/``jacrev``/``jacfwd``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from prognos_torch.core.kernel_exp import floored_exp
from prognos_torch.core.validation import (
    as_data,
    as_targets,
    check_dtype_arg,
    check_forward_input,
    check_learner_params,
    check_nonneg,
    check_pos_int,
    to_float64,
)

__all__ = ["ELM", "ACTIVATIONS"]


def _gaussian(z: Tensor) -> Tensor:
    return floored_exp(-z * z)  # floored far out, no subnormal results (core.kernel_exp)


def _linear(z: Tensor) -> Tensor:
    return z


#: Hidden-node activation functions ``g`` of Eq. 48, by name.
ACTIVATIONS: dict[str, Callable[[Tensor], Tensor]] = {
    "sigmoid": torch.sigmoid,  # paper 000, Sec. 6: g(z) = 1 / (1 + exp(-z))
    "tanh": torch.tanh,
    "relu": torch.relu,
    "sin": torch.sin,
    "cos": torch.cos,
    "softplus": F.softplus,
    "gaussian": _gaussian,
    "linear": _linear,
}


# --------------------------------------------------------------------------- shared pieces
# (used by all learners in this package; their argument checks live in core.validation)


def broadcast_jacobian(module: nn.Module, jac: dict[str, Tensor], lead) -> dict[str, Tensor]:
    """Expand ``jac[name]`` ``(..., B, n_out, *shape)`` to the batch dims ``lead`` of the output.

    A parameter that was not batched in ``forward_and_jacobian`` gives an unbatched factor; the
    trailing dims are ``(B, n_out)`` and the parameter's own shape.
    """
    out = {}
    for name, J in jac.items():
        tail = 2 + getattr(module, name).dim()
        out[name] = J.expand(*lead, *J.shape[J.dim() - tail :])
    return out


def _chol_spd(A: Tensor, what: str) -> Tensor:
    """Cholesky factor of a symmetric positive definite matrix, ``ValueError`` if it is not."""
    L, info = torch.linalg.cholesky_ex(A)
    if bool((info > 0).any()):
        raise ValueError(f"{what} is not positive definite (singular or ill-conditioned)")
    return L


# --------------------------------------------------------------------------- functional core


def ridge_output_weights(H: Tensor, T: Tensor, lam: float) -> tuple[Tensor, Tensor]:
    """Regularised least squares ``beta = (H^T H + lam I)^{-1} H^T T`` (paper 000, Eq. 52-54).

    The extracted Eq. 53/54 reads ``(H^T H + lam I)^- H T``; the transpose on the second ``H`` was
    lost in extraction: the normal equations of Eq. 52 give ``H^T T``. Solved with a Cholesky
    factorisation of ``H^T H + lam I`` (no explicit inverse).

    Args:
        H: hidden-layer output matrix ``(N, L)`` (Eq. 51).
        T: targets ``(N, m)``.
        lam: ridge parameter ``lambda >= 0``.
    Returns:
        ``(beta, chol)``: output weights ``(L, m)`` and the lower Cholesky factor ``(L, L)`` of
        ``H^T H + lam I``.
    """
    L_nodes = H.shape[-1]
    G = H.mT @ H + lam * torch.eye(L_nodes, dtype=H.dtype, device=H.device)
    chol = _chol_spd(G, "H^T H + lam I (ELM ridge system, Eq. 53)")
    beta = torch.cholesky_solve(H.mT @ T, chol)
    return beta, chol


def block_rls_update(K: Tensor, beta: Tensor, h: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
    """One ROS-ELM step on a chunk of ``B`` samples (paper 000, Eq. 55-56 in block form).

    With ``S = I_B + h K h^T``::

        K_k    = K_{k-1} - K_{k-1} h^T S^{-1} h K_{k-1}                  (Eq. 55, chunk form)
        beta_k = beta_{k-1} + K_k h^T (t - h beta_{k-1})                 (Eq. 56)

    For ``B = 1`` this is exactly Eq. 55-56. ``K_k h^T = K_{k-1} h^T S^{-1}``, so the gain is
    computed once from a Cholesky solve with ``S``. ``K`` is re-symmetrised after the update.

    Args:
        K: ``(L, L)``, the inverse of ``H^T H + lam I`` accumulated so far.
        beta: ``(L, m)``.
        h: hidden outputs of the chunk ``(B, L)``.
        t: targets of the chunk ``(B, m)``.
    Returns:
        ``(K_k, beta_k)``.
    """
    B = h.shape[0]
    Kh = K @ h.mT  # (L, B)
    S = torch.eye(B, dtype=K.dtype, device=K.device) + h @ Kh
    chol = _chol_spd(S, "I + h K h^T (ROS-ELM update, Eq. 55)")
    gain = torch.cholesky_solve(Kh.mT, chol).mT  # K h^T S^{-1} = K_k h^T, (L, B)
    K_new = K - gain @ Kh.mT
    K_new = 0.5 * (K_new + K_new.mT)
    beta_new = beta + gain @ (t - h @ beta)
    return K_new, beta_new


# --------------------------------------------------------------------------- module


class ELM(nn.Module):
    """Single-hidden-layer extreme learning machine (paper 000, Eq. 47-56).

    Parameters (registration order): ``a`` ``(L, n_in)`` input weights, ``b`` ``(L,)`` biases,
    ``beta`` ``(L, n_out)`` output weights. ``a`` and ``b`` are random features drawn from
    ``generator`` (uniform in [-1, 1] and [0, 1], paper 000 Sec. 6) with ``requires_grad=False``;
    ``beta`` is trainable and starts at zero.

    Buffers: ``K`` ``(L, L)`` float64, the ROS-ELM matrix ``(H^T H + lam I)^{-1}`` (Eq. 55);
    ``n_seen`` number of samples absorbed by :meth:`init_online`/:meth:`partial_fit`
    (0: online learning not initialised). ``K`` stays float64 under ``module.to(dtype)``.

    Args:
        n_in: input dimension ``n_mu``.
        n_hidden: number of hidden nodes ``L``.
        n_out: output dimension ``m``.
        activation: name in :data:`ACTIVATIONS` or a callable ``g`` (element-wise, Eq. 48).
        generator: ``torch.Generator`` for ``a`` and ``b``; ``None`` uses a CPU generator seeded
            with 0 (reproducible).
        dtype: floating dtype of the parameters.
    """

    def __init__(
        self,
        n_in: int,
        n_hidden: int,
        n_out: int = 1,
        activation: str | Callable[[Tensor], Tensor] = "sigmoid",
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.n_in = check_pos_int(n_in, "n_in")
        self.n_hidden = check_pos_int(n_hidden, "n_hidden")
        self.n_out = check_pos_int(n_out, "n_out")
        check_dtype_arg(dtype)
        if isinstance(activation, str):
            if activation not in ACTIVATIONS:
                raise ValueError(
                    f"activation must be one of {sorted(ACTIVATIONS)} or a callable, "
                    f"got {activation!r}"
                )
            self.activation_name = activation
            self._g = ACTIVATIONS[activation]
        elif callable(activation):
            self.activation_name = getattr(activation, "__name__", "custom")
            self._g = activation
        else:
            raise TypeError(f"activation must be a str or a callable, got {type(activation)}")
        if generator is None:
            generator = torch.Generator().manual_seed(0)
        elif not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be a torch.Generator or None, got {type(generator)}")
        gdev = generator.device
        a = 2.0 * torch.rand(n_hidden, n_in, generator=generator, dtype=torch.float64, device=gdev)
        a = a - 1.0
        b = torch.rand(n_hidden, generator=generator, dtype=torch.float64, device=gdev)
        self.a = nn.Parameter(a.to(dtype), requires_grad=False)
        self.b = nn.Parameter(b.to(dtype), requires_grad=False)
        self.beta = nn.Parameter(torch.zeros(n_hidden, n_out, dtype=dtype, device=gdev))
        self.register_buffer("K", torch.zeros(n_hidden, n_hidden, dtype=torch.float64, device=gdev))
        self.register_buffer("n_seen", torch.zeros((), dtype=torch.int64, device=gdev))

    def _apply(self, fn, recurse=True):
        # Keep the ROS-ELM matrix K in float64 whatever dtype the module is cast to; follow the
        # device only (the cast is applied to the float64 original, so no precision is lost).
        K = self._buffers.get("K")
        out = super()._apply(fn, recurse)
        moved = self._buffers.get("K")
        if K is not None and moved is not None and moved.dtype != torch.float64:
            # a cast: recast the float64 original (no data on the meta device: nothing to keep)
            keep = K.is_meta or moved.is_meta
            self._buffers["K"] = moved.to(torch.float64) if keep else K.to(moved.device,
                                                                           torch.float64)  # fmt: skip
        return out

    def extra_repr(self) -> str:
        return (
            f"n_in={self.n_in}, n_hidden={self.n_hidden}, n_out={self.n_out}, "
            f"activation={self.activation_name!r}, dtype={self.beta.dtype}"
        )

    # ---------------------------------------------------------------- forward (functional)
    def hidden(self, x: Tensor) -> Tensor:
        """Hidden-layer outputs ``g(a_i . x + b_i)`` (Eq. 48, rows of ``H`` in Eq. 51).

        Args:
            x: ``(..., n_in)`` with the module's dtype and device.
        Returns:
            ``(..., L)``.
        """
        check_forward_input(x, self.n_in, self.a)
        return self._g(x @ self.a.mT + self.b)

    def forward(self, x: Tensor) -> Tensor:
        """ELM output ``f_L(x) = h(x) beta`` (Eq. 47).

        Args:
            x: ``(..., n_in)`` (typically ``(B, n_in)``), module dtype and device.
        Returns:
            ``(..., n_out)``.
        """
        check_forward_input(x, self.n_in, self.beta)
        return self.hidden(x) @ self.beta

    def forward_with(self, params: dict[str, Tensor], x: Tensor) -> Tensor:
        """``forward`` with parameters batched over leading dims, without ``vmap``.

        Args:
            params: any of ``a`` ``(..., L, n_in)``, ``b`` ``(..., L)``, ``beta`` ``(..., L, n_out)``
                (missing ones are the module's own); all share the same leading dims ``...``.
            x: ``(B, n_in)`` shared by every parameter set.
        Returns:
            ``(..., B, n_out)``, equal to ``torch.func.vmap`` of ``functional_call`` over ``...``.
        """
        check_forward_input(x, self.n_in, self.beta)
        check_learner_params(params, self, "ELM")  # (a misspelt name was ignored, b (1,) broadcast)
        a = params.get("a", self.a)
        b = params.get("b", self.b)
        beta = params.get("beta", self.beta)
        H = self._g(x @ a.mT + b.unsqueeze(-2))  # (..., B, L), Eq. 48
        return H @ beta  # Eq. 47

    def forward_and_jacobian(
        self, params: dict[str, Tensor], x: Tensor, names: tuple[str, ...] | None = None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """:meth:`forward_with` and the exact derivatives of the output by the parameters.

        With ``z = x a^T + b`` and ``H = g(z)`` (Eq. 48), ``t = H beta`` (Eq. 47)::

            d t_o / d beta_{h o'} = H_h delta(o, o')
            d t_o / d b_h         = beta_{h o} g'(z_h)
            d t_o / d a_{h j}     = beta_{h o} g'(z_h) x_j

        ``g'`` comes from one forward-mode product of the (elementwise) activation, so custom
        activations work too.

        Args:
            params, x: as :meth:`forward_with`.
            names: parameters to differentiate (default: all).
        Returns:
            ``(out, jac)``: ``out`` ``(..., B, n_out)`` and ``jac[name]``
            ``(..., B, n_out, *shape)``.
        """
        names = ("a", "b", "beta") if names is None else tuple(names)
        unknown = set(names) - {"a", "b", "beta"}
        if unknown:
            raise ValueError(f"ELM has no parameters {sorted(unknown)}")
        check_forward_input(x, self.n_in, self.beta)
        check_learner_params(params, self, "ELM")
        a = params.get("a", self.a)
        b = params.get("b", self.b)
        beta = params.get("beta", self.beta)
        z = x @ a.mT + b.unsqueeze(-2)  # (..., B, L)
        if "a" in names or "b" in names:
            H, dH = torch.func.jvp(self._g, (z,), (torch.ones_like(z),))
        else:
            H, dH = self._g(z), None
        out = H @ beta  # (..., B, n_out)
        o = out.shape[-1]
        jac: dict[str, Tensor] = {}
        if "beta" in names:  # (..., B, o, L, o')
            eye_o = torch.eye(o, dtype=out.dtype, device=out.device)
            jac["beta"] = H[..., :, None, :, None] * eye_o[:, None, :]
        if dH is not None:
            gb = dH.unsqueeze(-2) * beta.mT.unsqueeze(-3)  # (..., B, o, L): beta_ho g'(z_h)
            if "b" in names:
                jac["b"] = gb
            if "a" in names:
                jac["a"] = gb.unsqueeze(-1) * x[:, None, None, :]  # (..., B, o, L, n_in)
        return out, broadcast_jacobian(self, jac, out.shape[:-2])

    # ---------------------------------------------------------------- training (stateful)
    def _hidden64(self, x: Tensor) -> Tensor:
        """Hidden outputs in float64 for the least-squares solvers."""
        return self._g(x @ self.a.detach().to(torch.float64).mT + self.b.detach().to(torch.float64))

    @torch.no_grad()
    def fit_ridge(self, x, y, lam: float) -> ELM:
        """Batch ridge solution ``beta = (H^T H + lam I)^{-1} H^T T`` (Eq. 52-54).

        Computed in float64 (Cholesky, no inverse) and stored in ``beta`` in the module dtype.
        Does not touch the online state ``K``.

        Args:
            x: inputs ``(N, n_in)``.
            y: targets ``(N, n_out)`` (or ``(N,)`` if ``n_out == 1``).
            lam: ridge parameter ``>= 0``; with ``lam == 0`` ``H`` must have full column rank.
        Returns:
            ``self``.
        """
        dev = self.beta.device
        X = as_data(x, "x", device=dev, n_cols=self.n_in)
        T = as_targets(y, "y", device=dev, n_rows=X.shape[0], n_out=self.n_out)
        lam = check_nonneg(lam, "lam")
        beta, _ = ridge_output_weights(self._hidden64(X), T, lam)
        self.beta.copy_(beta.to(self.beta.dtype))
        return self

    @torch.no_grad()
    def init_online(self, x0, y0, lam: float) -> ELM:
        """ROS-ELM Step I (paper 000, Eq. 54): ``K_0 = (H_0^T H_0 + lam I)^{-1}``,
        ``beta_0 = K_0 H_0^T T_0``.

        The paper requires ``N_0 >= L``. That is necessary only without regularisation: with
        ``lam > 0`` any ``N_0 >= 1`` gives a well-posed problem and is accepted; with ``lam == 0``
        and ``N_0 < L`` a ``ValueError`` is raised (``H_0^T H_0`` is singular).

        Args:
            x0: initial inputs ``(N0, n_in)``.
            y0: initial targets ``(N0, n_out)`` (or ``(N0,)`` if ``n_out == 1``).
            lam: ridge parameter ``lambda >= 0`` (Eq. 52).
        Returns:
            ``self``.
        """
        dev = self.beta.device
        X = as_data(x0, "x0", device=dev, n_cols=self.n_in)
        T = as_targets(y0, "y0", device=dev, n_rows=X.shape[0], n_out=self.n_out)
        lam = check_nonneg(lam, "lam")
        if lam == 0.0 and X.shape[0] < self.n_hidden:
            raise ValueError(
                f"x0 has N0={X.shape[0]} rows but ROS-ELM initialisation without "
                f"regularisation needs N0 >= L={self.n_hidden} (paper 000, Step I); "
                "pass more samples or lam > 0"
            )
        beta, chol = ridge_output_weights(self._hidden64(X), T, lam)
        self.K.copy_(torch.cholesky_inverse(chol))  # K_0, float64
        self.K.copy_(0.5 * (self.K + self.K.mT))
        self.beta.copy_(beta.to(self.beta.dtype))
        self.n_seen.fill_(X.shape[0])
        return self

    @torch.no_grad()
    def partial_fit(self, x, y) -> ELM:
        """ROS-ELM Step II (Eq. 55-56) for one sample or a chunk (block recursive least squares).

        After :meth:`init_online` on ``N0`` samples with ``lam``, any sequence of
        ``partial_fit`` calls yields (up to rounding) the batch ridge solution on all data seen.

        Args:
            x: one sample ``(n_in,)`` or a chunk ``(B, n_in)``.
            y: ``(n_out,)`` for one sample, ``(B, n_out)`` (or ``(B,)`` if ``n_out == 1``) for a
                chunk.
        Returns:
            ``self``.
        """
        if int(self.n_seen) == 0:
            raise RuntimeError("call init_online(x0, y0, lam) before partial_fit (ROS-ELM Step I)")
        dev = self.beta.device
        xt = to_float64(x, "x", device=dev)
        if xt.dim() == 1:  # one sample: x (n_in,), y (n_out,)
            yt = to_float64(y, "y", device=dev)
            if yt.dim() != 1 or yt.shape[0] != self.n_out:
                raise ValueError(
                    f"y must have shape (n_out,) = ({self.n_out},) for a single sample x, "
                    f"got {tuple(yt.shape)}"
                )
            xt, yt = xt.unsqueeze(0), yt.unsqueeze(0)
        else:
            yt = y
        X = as_data(xt, "x", device=dev, n_cols=self.n_in)
        T = as_targets(yt, "y", device=dev, n_rows=X.shape[0], n_out=self.n_out)
        beta64 = self.beta.detach().to(torch.float64)
        K, beta = block_rls_update(self.K, beta64, self._hidden64(X), T)
        self.K.copy_(K)
        self.beta.copy_(beta.to(self.beta.dtype))
        self.n_seen.add_(X.shape[0])
        return self
