"""First-order Sugeno ANFIS with grid rules (paper 003, Eq. 1-6 and parameter order Eq. 44).

Layers (paper 003, ``u`` the input, ``j`` the input index, ``l`` the membership index, ``i`` the
rule index)::

    Eq. 1   t_j^(1)  = u_j
    Eq. 2   gamma_jl = 1 / (1 + exp(-b_jl (u_j - beta_jl)))          (sigmoid membership)
    Eq. 3   t_i^(3)  = prod_j gamma_{j, l_j(i)}                        (rule firing strength)
    Eq. 4   t_i^(4)  = t_i^(3) / sum_k t_k^(3)                         (normalisation)
    Eq. 5   t        = sum_i t_i^(4) (alpha_1^i u_1 + ... + alpha_n^i u_n + alpha_{n+1}^i)

Rules form the full grid: rule ``i`` takes membership ``l_j(i)`` of input ``j`` in
``itertools.product(range(n_mfs), repeat=n_inputs)`` order (last input fastest), so there are
``n_mfs ** n_inputs`` rules (paper 003: 3 inputs, 2 MFs, 8 rules). Layers 3-4 are evaluated in log
space (sum of log-memberships, then ``softmax``); this equals Eq. 3-4 exactly and cannot underflow
to 0/0 when all firing strengths are tiny.

Parameter order (paper 003, Eq. 44)::

    theta = [alpha_1^1, alpha_1^2, ..., alpha_{n+1}^R,
             b_11, b_12, ..., b_{n,L}, beta_11, ..., beta_{n,L}]

i.e. the consequents with the rule index fastest, then the slopes ``b_jl`` and the centres
``beta_jl`` with the membership index fastest. The module registers ``alpha``
``(n_out, n_inputs + 1, R)``, ``b`` ``(n_inputs, n_mfs)``, ``beta`` ``(n_inputs, n_mfs)`` in that
order, so ``torch.cat([p.reshape(-1) for p in module.parameters()])``
(:meth:`ANFIS.parameters_flat`) is exactly Eq. 44; :meth:`ANFIS.flat_parameter_names` spells
the names.

Besides the paper's sigmoid (``mf="sigmoid"``: parameters ``b``, ``beta``) two common membership
functions are offered, each with its own premise parameters (registered after ``alpha``):

* ``"gaussian"``: ``exp(-(u - c)^2 / (2 sigma^2))``; parameters ``sigma``, ``c``;
* ``"bell"`` (generalised bell): ``1 / (1 + |(u - c) / a|^(2 b))``; parameters ``a``, ``b``, ``c``.
"""

from __future__ import annotations

import itertools
import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..core.validation import (
    as_data,
    as_targets,
    broadcast_shape,
    check_dtype_arg,
    check_forward_input,
    check_learner_params,
    check_nonneg,
    check_pos_int,
)
from .elm import broadcast_jacobian

__all__ = ["ANFIS", "MEMBERSHIPS", "log_membership"]

#: Membership function names and their premise parameters (registration order).
MEMBERSHIPS: dict[str, tuple[str, ...]] = {
    "sigmoid": ("b", "beta"),  # paper 003, Eq. 2
    "gaussian": ("sigma", "c"),
    "bell": ("a", "b", "c"),
}


# --------------------------------------------------------------------------- functional core


def log_membership(u: Tensor, mf: str, premises: tuple[Tensor, ...]) -> Tensor:
    """Log membership values ``log gamma_jl(u_j)`` (paper 003, Eq. 2 and alternatives).

    Args:
        u: inputs ``(..., n)``.
        mf: ``"sigmoid"``, ``"gaussian"`` or ``"bell"``.
        premises: the premise parameters of :data:`MEMBERSHIPS` ``[mf]``, each ``(n, n_mfs)``.
    Returns:
        ``(..., n, n_mfs)``.
    """
    return _log_membership(u.unsqueeze(-1), mf, premises)


def _log_membership(x: Tensor, mf: str, premises: tuple[Tensor, ...]) -> Tensor:
    """The membership formulas, elementwise: ``x`` and the premises broadcast against each other."""
    if mf == "sigmoid":
        b, beta = premises
        return F.logsigmoid(b * (x - beta))  # log of Eq. 2
    if mf == "gaussian":
        sigma, c = premises
        return -((x - c) ** 2) / (2.0 * sigma * sigma)
    if mf == "bell":
        a, b, c = premises
        return -torch.log1p(torch.abs((x - c) / a) ** (2.0 * b))
    raise ValueError(f"mf must be one of {sorted(MEMBERSHIPS)}, got {mf!r}")


def _log_membership_grads(
    x: Tensor, mf: str, premises: tuple[Tensor, ...], which: list[int]
) -> list[Tensor]:
    """Elementwise ``d log gamma / d p`` for the premise parameters ``premises[k]``, ``k`` in
    ``which`` (same broadcasting as :func:`_log_membership`)."""
    if mf == "sigmoid":
        b, beta = premises
        z = b * (x - beta)
        s = torch.sigmoid(-z)  # d log sigma(z) / dz
        grads = {0: s * (x - beta), 1: -s * b}
    elif mf == "gaussian":
        sigma, c = premises
        dx = x - c
        grads = {0: dx * dx / (sigma * sigma * sigma), 1: dx / (sigma * sigma)}
    elif mf == "bell":
        a, b, c = premises
        t = (x - c) / a
        at = torch.abs(t)
        g = at ** (2.0 * b)
        dl = -1.0 / (1.0 + g)  # d log gamma / d g
        # dg/da = -2 b g / a; dg/dc = -2 b |t|^(2b - 1) sign(t) / a; dg/db = 2 g log|t| (0 at t = 0)
        logt = torch.log(torch.where(at > 0, at, torch.ones_like(at)))
        grads = {
            0: dl * (-2.0 * b * g / a),
            1: dl * (2.0 * g * logt),
            2: dl * (-2.0 * b * at ** (2.0 * b - 1.0) * torch.sign(t) / a),
        }
    else:
        raise ValueError(f"mf must be one of {sorted(MEMBERSHIPS)}, got {mf!r}")
    shape = broadcast_shape(x.shape, *(p.shape for p in premises))
    return [grads[k].expand(shape) for k in which]


def normalized_firing(log_mu: Tensor) -> Tensor:
    """Normalised grid-rule firing strengths ``t^(4)`` (paper 003, Eq. 3-4).

    Args:
        log_mu: ``(..., n, n_mfs)`` log memberships.
    Returns:
        ``(..., n_mfs ** n)``, rules in ``itertools.product`` order (last input fastest).
    """
    n = log_mu.shape[-2]
    log_w = log_mu[..., 0, :]
    for j in range(1, n):  # log of Eq. 3: outer sums, last input fastest
        log_w = (log_w.unsqueeze(-1) + log_mu[..., j, :].unsqueeze(-2)).flatten(-2)
    return torch.softmax(log_w, dim=-1)  # Eq. 4


# --------------------------------------------------------------------------- module


#: Entries of ``kron(ubar^T, I_R)`` up to which Eq. 5 of the batched forward multiplies by it
#: (the form the committed study runs were made with); above, by the inputs directly (the same
#: numbers to rounding, memory ``O(B R)``: 243 rules on a batch of 256 needed 700 MB a call)
KRON_MAX_ENTRIES = 2**20


class ANFIS(nn.Module):
    """First-order Sugeno ANFIS with grid rules (paper 003, Eq. 1-6).

    Parameters (registration order = Eq. 44): ``alpha`` ``(n_out, n_inputs + 1, R)`` with
    ``alpha[o, m-1, i-1] = alpha_m^i`` (``m = n_inputs + 1`` is the constant term), then the premise
    parameters of :data:`MEMBERSHIPS` ``[mf]``, each ``(n_inputs, n_mfs)`` with ``[j-1, l-1]`` the
    paper's ``_jl``. All are trainable.

    Initialisation: premises as :meth:`init_premises` for inputs spread over ``[-1, 1]``;
    consequents uniform in ``[-0.1, 0.1]`` from ``generator`` (``None``: a CPU generator seeded
    with 0). Use :meth:`init_premises` and :meth:`init_consequents_lstsq` for data-driven values.

    Args:
        n_inputs: number of inputs ``n``.
        n_mfs: membership functions per input ``L`` (rules: ``L ** n``).
        mf: ``"sigmoid"`` (paper 003, Eq. 2), ``"gaussian"`` or ``"bell"``.
        n_out: number of outputs (each with its own consequents, premises shared).
        generator: ``torch.Generator`` for the consequent initialisation.
        dtype: floating dtype of the parameters.
    """

    def __init__(
        self,
        n_inputs: int,
        n_mfs: int = 2,
        mf: str = "sigmoid",
        n_out: int = 1,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.n_inputs = check_pos_int(n_inputs, "n_inputs")
        self.n_mfs = check_pos_int(n_mfs, "n_mfs")
        self.n_out = check_pos_int(n_out, "n_out")
        if not isinstance(mf, str) or mf not in MEMBERSHIPS:
            raise ValueError(f"mf must be one of {sorted(MEMBERSHIPS)}, got {mf!r}")
        self.mf = mf
        check_dtype_arg(dtype)
        if generator is None:
            generator = torch.Generator().manual_seed(0)
        elif not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be a torch.Generator or None, got {type(generator)}")
        self.n_rules = n_mfs**n_inputs
        alpha = torch.rand(
            n_out,
            n_inputs + 1,
            self.n_rules,
            generator=generator,
            dtype=torch.float64,
            device=generator.device,
        )
        self.alpha = nn.Parameter((0.2 * alpha - 0.1).to(dtype))
        for name in MEMBERSHIPS[mf]:
            p = torch.zeros(n_inputs, n_mfs, dtype=dtype, device=generator.device)
            self.register_parameter(name, nn.Parameter(p))
        lo = torch.full((n_inputs,), -1.0, dtype=torch.float64, device=generator.device)
        self._set_premises(lo, -lo)

    @property
    def premise_names(self) -> tuple[str, ...]:
        """Names of the premise parameters, in registration order."""
        return MEMBERSHIPS[self.mf]

    def premises(self) -> tuple[Tensor, ...]:
        """The premise parameters, each ``(n_inputs, n_mfs)``."""
        return tuple(getattr(self, name) for name in self.premise_names)

    def extra_repr(self) -> str:
        return (
            f"n_inputs={self.n_inputs}, n_mfs={self.n_mfs}, mf={self.mf!r}, "
            f"n_rules={self.n_rules}, n_out={self.n_out}, dtype={self.alpha.dtype}"
        )

    def rules(self) -> list[tuple[int, ...]]:
        """Membership index ``(l_1, ..., l_n)`` (0-based) of each rule, in rule order."""
        return list(itertools.product(range(self.n_mfs), repeat=self.n_inputs))

    # ---------------------------------------------------------------- parameter order (Eq. 44)
    def parameters_flat(self) -> Tensor:
        """All parameters as one vector in the order of paper 003, Eq. 44 ``(P,)``."""
        return torch.cat([p.reshape(-1) for p in self.parameters()])

    def flat_parameter_names(self) -> list[str]:
        """Paper names of the entries of :meth:`parameters_flat` (1-based indices, Eq. 44).

        ``alpha_m^i`` (consequent ``m`` of rule ``i``; with ``n_out > 1`` suffixed ``[o]``),
        then ``<premise>_j,l`` for each premise parameter (e.g. ``b_1,2``, ``beta_3,1``).
        """
        names = []
        for o in range(self.n_out):
            suffix = f"[{o + 1}]" if self.n_out > 1 else ""
            for m in range(1, self.n_inputs + 2):
                names += [f"alpha_{m}^{i}{suffix}" for i in range(1, self.n_rules + 1)]
        for name in self.premise_names:
            for j in range(1, self.n_inputs + 1):
                names += [f"{name}_{j},{l}" for l in range(1, self.n_mfs + 1)]
        return names

    # ---------------------------------------------------------------- forward (functional)
    def firing_strengths(self, x: Tensor) -> Tensor:
        """Normalised firing strengths ``t^(4)`` (Eq. 1-4): ``(..., n_inputs)`` -> ``(..., R)``."""
        check_forward_input(x, self.n_inputs, self.alpha)
        return normalized_firing(log_membership(x, self.mf, self.premises()))

    def forward(self, x: Tensor) -> Tensor:
        """ANFIS output (Eq. 5-6), one column per output.

        Args:
            x: ``(..., n_inputs)`` (typically ``(B, n_inputs)``), module dtype and device.
        Returns:
            ``(..., n_out)``.
        """
        wbar = self.firing_strengths(x)  # (..., R)
        ubar = torch.cat([x, torch.ones_like(x[..., :1])], dim=-1)  # [u_1 .. u_n, 1]
        return torch.einsum("...i,...m,omi->...o", wbar, ubar, self.alpha)  # Eq. 5

    def forward_with(self, params: dict[str, Tensor], x: Tensor) -> Tensor:
        """``forward`` with parameters batched over leading dims (sigma points, runs), no ``vmap``.

        Args:
            params: any of ``alpha`` ``(..., n_out, n_inputs + 1, R)`` and the premise parameters
                ``(..., n_inputs, n_mfs)`` (missing ones are the module's own); one set of
                leading dims ``...`` shared by all.
            x: ``(B, n_inputs)`` shared by every parameter set.
        Returns:
            ``(..., B, n_out)``, equal to ``torch.func.vmap`` of ``functional_call`` over ``...``.

        The same Eq. 1-5 as :meth:`forward`, arranged for many parameter sets: every layer is
        elementwise on contiguous ``(..., B, n_inputs * n_mfs)`` blocks or a matrix product
        with a constant matrix (rule selection for Eq. 3) or one 2-D product with the inputs
        (Eq. 5), so the large leading dimension never meets a reduction over a tiny trailing
        one.
        """
        return self._forward_parts(params, x)[0]

    def _forward_parts(self, params: dict[str, Tensor], x: Tensor):
        """Eq. 1-5 for batched parameters; returns the output and the intermediate layers."""
        check_forward_input(x, self.n_inputs, self.alpha)
        if x.dim() != 2:
            raise ValueError(f"x must have shape (B, {self.n_inputs}), got {tuple(x.shape)}")
        self._check_params(params)
        alpha = params.get("alpha", self.alpha)
        nL = self.n_inputs * self.n_mfs
        premises = []  # (..., 1, n * L), membership index fastest
        for name in self.premise_names:
            p = params.get(name, getattr(self, name))
            premises.append(p.reshape(*p.shape[:-2], 1, nL))
        premises = tuple(premises)
        G, E = self._constants(x)
        xr = x @ E  # (B, n * L): u_j once per MF of input j (E = kron(I_n, 1_L^T), exact)
        log_mu = _log_membership(xr, self.mf, premises)  # (..., B, n * L), log of Eq. 2
        log_w = log_mu @ G  # (..., B, R), log of Eq. 3 (each rule picks one MF per input)
        wbar = torch.softmax(log_w, dim=-1)  # Eq. 4 (exp of the log firing, normalised)
        B, R = x.shape[0], self.n_rules
        m = alpha.shape[-2]
        ubar_t = F.pad(x.mT, (0, 0, 0, 1), value=1.0)  # (n + 1, B): [u_1 .. u_n, 1] per column
        ubar = ubar_t.mT  # (B, n + 1)
        # f_i(u_b) = alpha_i . ubar_b (Eq. 5) for every parameter set as ONE 2-D GEMM (a batched
        # matmul of many tiny products is several times slower)
        if m * R * B * R <= KRON_MAX_ENTRIES:
            # with U = kron(ubar^T, I_R), U[(m, i), (b, i')] = ubar[b, m] delta(i, i')
            U = torch.kron(ubar_t, torch.eye(R, dtype=x.dtype, device=x.device))  # ((n+1) R, B R)
            f = (alpha.reshape(-1, m * R) @ U).reshape(*alpha.shape[:-2], B, R)
        else:  # U would grow as B R^2 (mostly zeros): ubar by alpha laid out (n + 1, sets x R)
            a = alpha.reshape(-1, m, R).transpose(0, 1).reshape(m, -1)
            f = (ubar @ a).reshape(B, -1, R).transpose(0, 1).reshape(*alpha.shape[:-2], B, R)
        out = (f * wbar.unsqueeze(-3)).sum(-1).mT  # Eq. 5: (..., B, n_out)
        return out, (premises, xr, G, wbar, ubar, f)

    def _check_params(self, params: dict[str, Tensor]) -> None:
        """Names and trailing shapes of batched parameters (metadata only): a premise given as
        ``(n_mfs, n_inputs)`` or a misspelt name was used silently (wrong numbers)."""
        check_learner_params(params, self, "ANFIS")

    def forward_and_jacobian(
        self, params: dict[str, Tensor], x: Tensor, names: tuple[str, ...] | None = None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """:meth:`forward_with` and the exact derivatives of the output by the parameters.

        Back-propagation of Eq. 1-5 written out (used by the EKF, which needs the Jacobian of
        the output with respect to all 44 parameters at every step)::

            d t / d alpha_m^i   = t_i^(4) ubar_m                                  (Eq. 5)
            d t / d log w_i     = t_i^(4) (f_i - t)                               (Eq. 4, softmax)
            d t / d log mu_jl   = sum over the rules i using MF l of input j of d t / d log w_i
            d t / d p_jl        = d t / d log mu_jl * d log mu_jl / d p_jl         (Eq. 2)

        with ``d log mu / d p`` of the sigmoid ``log sigma(b (u - beta))``: ``sigma(-z)(u - beta)``
        for ``b`` and ``-sigma(-z) b`` for ``beta``; Gaussian and bell formulas likewise.

        Args:
            params, x: as :meth:`forward_with`.
            names: parameters to differentiate (default: all).
        Returns:
            ``(out, jac)``: ``out`` ``(..., B, n_out)`` and ``jac[name]``
            ``(..., B, n_out, *shape)`` with ``shape`` the parameter's own shape.
        """
        names = tuple(n for n, _ in self.named_parameters()) if names is None else tuple(names)
        out, (premises, xr, G, wbar, ubar, f) = self._forward_parts(params, x)
        lead, B, o = out.shape[:-2], x.shape[0], self.n_out
        jac: dict[str, Tensor] = {}
        if "alpha" in names:  # (..., B, o, o', n + 1, R), zero for o != o'
            base = ubar.unsqueeze(-1) * wbar.unsqueeze(-2)  # (..., B, n + 1, R)
            if o == 1:
                jac["alpha"] = base[..., :, None, None, :, :]
            else:
                eye_o = torch.eye(o, dtype=out.dtype, device=out.device)
                jac["alpha"] = base[..., :, None, None, :, :] * eye_o[:, :, None, None]
        wanted = [k for k, name in enumerate(self.premise_names) if name in names]
        if wanted:
            g = wbar.unsqueeze(-3) * (f - out.mT.unsqueeze(-1))  # (..., o, B, R): d t / d log w
            d_log_mu = (g @ G.transpose(-2, -1)).movedim(-3, -2)  # (..., B, o, n * L)
            for k, d in zip(wanted, _log_membership_grads(xr, self.mf, premises, wanted)):
                J = d_log_mu * d.unsqueeze(-2)  # (..., B, o, n * L)
                jac[self.premise_names[k]] = J.reshape(*lead, B, o, self.n_inputs, self.n_mfs)
        unknown = set(names) - set(jac)
        if unknown:
            raise ValueError(f"ANFIS has no parameters {sorted(unknown)}")
        return out, broadcast_jacobian(self, jac, lead)

    def _constants(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """For ``like``'s dtype and device: the rule-selection matrix ``(n * L, R)`` (Eq. 3 in
        log space) and ``kron(I_n, 1_L^T)`` ``(n, n * L)`` (each input once per MF)."""
        key = (like.dtype, like.device)
        cache = getattr(self, "_forward_constants", None)
        if cache is not None and key in cache:  # read only (a traced step may not write)
            return cache[key]
        if cache is None:
            cache = self._forward_constants = {}
        if key not in cache:
            cache[key] = self._make_constants(like)
        return cache[key]

    def _make_constants(self, like: Tensor) -> tuple[Tensor, Tensor]:
        with torch.inference_mode(False), torch.no_grad():  # ordinary tensors in the cache
            G = torch.zeros(
                self.n_inputs * self.n_mfs, self.n_rules, dtype=like.dtype, device=like.device
            )
            for i, rule in enumerate(self.rules()):
                for j, l in enumerate(rule):
                    G[j * self.n_mfs + l, i] = 1.0
            E = torch.eye(self.n_inputs, dtype=like.dtype, device=like.device)
            E = E.repeat_interleave(self.n_mfs, dim=-1)
            return G, E

    # ---------------------------------------------------------------- initialisation helpers
    @torch.no_grad()
    def _set_premises(self, lo: Tensor, hi: Tensor) -> None:
        n_mfs = self.n_mfs
        span = hi - lo
        const = span <= 0  # constant input: use a unit range around the value
        lo = torch.where(const, lo - 0.5, lo)
        span = torch.where(const, torch.ones_like(span), span)
        k = torch.arange(n_mfs, dtype=torch.float64, device=lo.device)
        if self.mf == "sigmoid":
            # centres at the interior points of an even grid; MFs of the lower half decrease
            # ("low"), of the upper half increase ("high"); 0.12 -> 0.88 over one grid spacing
            spacing = span / (n_mfs + 1)
            centres = lo[:, None] + (k + 1) * spacing[:, None]
            sign = torch.where(k < n_mfs / 2.0, -1.0, 1.0).to(lo)
            values = {"b": sign * (4.0 / spacing)[:, None], "beta": centres}
        else:
            # centres on an even grid over [lo, hi] (mid-range for one MF); neighbours cross at 0.5
            if n_mfs == 1:
                centres = (lo + 0.5 * span)[:, None]
                spacing = span
            else:
                spacing = span / (n_mfs - 1)
                centres = lo[:, None] + k * spacing[:, None]
            width = spacing[:, None].expand(-1, n_mfs)
            if self.mf == "gaussian":
                values = {"sigma": width / (2.0 * math.sqrt(2.0 * math.log(2.0))), "c": centres}
            else:
                values = {"a": width / 2.0, "b": torch.full_like(width, 2.0), "c": centres}
        for name, v in values.items():
            p = getattr(self, name)
            p.copy_(v.to(device=p.device, dtype=p.dtype))

    @torch.no_grad()
    def init_premises(self, X) -> ANFIS:
        """Data-driven premises: spread the membership functions over each input's range.

        For each input ``j`` with range ``[lo_j, hi_j]`` over the rows of ``X``:

        * sigmoid: centres ``beta_jl`` at the ``n_mfs`` interior points of an even grid,
          ``|b_jl| = 4 / spacing`` (0.12 -> 0.88 over one spacing), negative slope for the
          lower half of the MFs and positive for the upper half;
        * gaussian / bell: centres evenly over ``[lo_j, hi_j]`` (the midpoint if ``n_mfs=1``),
          widths such that neighbouring MFs cross at 0.5 (bell exponent ``b = 2``).

        A constant input column uses the unit range ``[lo - 0.5, lo + 0.5]``.

        Args:
            X: inputs ``(N, n_inputs)``.
        Returns:
            ``self``.
        """
        X64 = as_data(X, "X", device=self.alpha.device, n_cols=self.n_inputs)
        self._set_premises(X64.min(0).values, X64.max(0).values)
        return self

    def _regressors(self, X64: Tensor) -> Tensor:
        """Matrix ``V`` of Eq. 6 ``(N, (n+1) R)``: column ``m R + i`` is ``t_i^(4) ubar_m``."""
        premises = tuple(p.detach().to(torch.float64) for p in self.premises())
        wbar = normalized_firing(log_membership(X64, self.mf, premises))  # (N, R)
        ubar = torch.cat([X64, torch.ones_like(X64[:, :1])], dim=-1)  # (N, n+1)
        return (ubar.unsqueeze(-1) * wbar.unsqueeze(-2)).flatten(-2)

    @torch.no_grad()
    def init_consequents_lstsq(self, X, y, lam: float = 0.0) -> ANFIS:
        """Least-squares consequents with the premises fixed (Eq. 6: ``t = U V^T`` is linear in
        ``U``).

        Minimises ``||V theta - y||^2 + lam ||theta||^2`` per output via an SVD of ``V``
        (float64). With ``lam == 0`` the minimum-norm least-squares solution is returned, with
        singular values below ``eps * max(N, P) * s_max`` treated as zero (``numpy.linalg.lstsq``'s
        default), so rank-deficient problems (e.g. ``N < P``) are handled.

        Args:
            X: inputs ``(N, n_inputs)``.
            y: targets ``(N, n_out)`` (or ``(N,)`` if ``n_out == 1``).
            lam: ridge parameter ``>= 0``.
        Returns:
            ``self``.
        """
        dev = self.alpha.device
        X64 = as_data(X, "X", device=dev, n_cols=self.n_inputs)
        Y64 = as_targets(y, "y", device=dev, n_rows=X64.shape[0], n_out=self.n_out)
        lam = check_nonneg(lam, "lam")
        V = self._regressors(X64)
        U, s, Vh = torch.linalg.svd(V, full_matrices=False)
        if lam > 0.0:
            s_inv = s / (s * s + lam)
        else:
            cutoff = torch.finfo(torch.float64).eps * max(V.shape) * s.max()
            s_inv = torch.where(s > cutoff, 1.0 / s, torch.zeros_like(s))
        theta = Vh.mT @ (s_inv.unsqueeze(-1) * (U.mT @ Y64))  # (P, n_out)
        alpha = theta.mT.reshape(self.n_out, self.n_inputs + 1, self.n_rules)
        self.alpha.copy_(alpha.to(self.alpha.dtype))
        return self
