"""Fast evaluation of a trained Gaussian-kernel LS-SVR (paper 002, Eq. 8 and Eq. 25).

:class:`~prognos_torch.learners.LSSVR` evaluates its RBF kernel from explicit differences
``(B, M, n)`` (exact at ``x = P_i``) and its input Jacobian with ``vmap(jacrev(...))``. Inside a
particle filter, where ``B`` is runs x particles (10^3-10^5 windows) and ``M`` the number of
training windows (~10^3), both are memory-bound and slow. :class:`LSSVRGram` is a frozen copy
of a fitted RBF LS-SVR that evaluates the same formulas through matrix products:

* prediction (Eq. 8 with the kernel of Eq. 24)::

      d_i(x) = |x|^2 - 2 <x, P_i> + |P_i|^2,   f(x) = sum_i alpha_i exp(-d_i / (2 sigma^2)) + b

  (the products with the support vectors are one ``addmm``);
* input gradient (Eq. 25, closed form)::

      df/dx = -(1 / sigma^2) sum_i alpha_i phi_i (x - P_i)
            = -(1 / sigma^2) [ (sum_i alpha_i phi_i) x - sum_i alpha_i phi_i P_i ]

  whose last component is Eq. 23/26 (the derivative with respect to the newest value).

The squared-distance expansion loses absolute accuracy ``~ eps (|x|^2 + |P_i|^2)``, so ``x`` and
the ``P_i`` are taken from the support vectors' centre ``mu`` first (the kernel and Eq. 25 are
shift-invariant): the loss is then ``~ eps (|x - mu|^2 + |P_i - mu|^2)``, negligible relative to
``2 sigma^2`` wherever the data lie (the tests compare with :class:`LSSVR` to 1e-12, and in
float32 far from the origin).

It exposes ``n_in``, ``n_out``, ``forward`` and ``input_gradient`` like :class:`LSSVR`, so it
plugs into :func:`~prognos_torch.prognosis.learner_model.learner_transition_model` (e.g. with
``jacobian="input_gradient"``) unchanged. It has buffers only (no parameters): it is an
evaluator, not a trainable model; re-create it after re-fitting the LS-SVR.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence

import torch
from torch import Tensor, nn

from ..core.kernel_exp import floored_exp
from ..core.validation import check_forward_input, is_real
from .lssvr import LSSVR, _blocked
from .selection import MultiStepCV, blocked_multistep_cv

#: Row-block budget of the ``(B, M)`` kernel values (bytes; no ``(B, M, n)`` difference tensor
#: is formed here, so the budget is larger than the LS-SVR's ``KERNEL_BLOCK_BYTES``).
GRAM_BLOCK_BYTES = 64 * 2**20

__all__ = ["LSSVRGram", "fit_lssvr_gram", "lssvr_gram_fitter", "lssvr_grid_cv"]


class LSSVRGram(nn.Module):
    """Frozen Gram-expansion evaluator of a fitted RBF :class:`LSSVR` (paper 002, Eq. 8, 25).

    With ``c = 1 / (2 sigma^2)`` and ``x``, ``P_i`` taken from the centre ``mu`` of the support
    vectors, the log-kernel is affine in ``x`` apart from ``-c |x|^2``::

        log phi(P_i, x) = (2 c P_i)^T x - c |P_i|^2 - c |x|^2

    so one ``addmm`` with the precomputed ``2 c P^T`` and ``-c |P_i|^2`` gives all kernel values.
    Round-off may leave ``log phi`` a few ulps above 0 at ``x = P_i``; that changes ``phi`` by
    ~1e-16 relative, so nothing is clamped.

    Buffers (dtype and device of the source model; ``.to(...)`` moves them): ``support_vectors``
    ``(M, n_in)``, ``alpha`` ``(M, n_out)``, ``b`` ``(n_out,)``, ``inv_two_sigma2`` (0-d ``c``),
    ``centre`` ``(n_in,)`` = ``mu``, and of the centred ``P``: ``sv_scaled_t`` ``(n_in, M)`` =
    ``2 c P^T``, ``sv_log_norm`` ``(M,)`` = ``-c |P_i|^2``, ``alpha_sv`` ``(M, n_out * n_in)`` =
    ``alpha_i P_i`` (for Eq. 25).

    Args:
        lssvr: a fitted :class:`LSSVR` with ``kernel="rbf"``.
    Raises:
        TypeError: ``lssvr`` is not an :class:`LSSVR`.
        ValueError: the kernel is not ``"rbf"`` or the model is not fitted.
    """

    def __init__(self, lssvr: LSSVR) -> None:
        super().__init__()
        if not isinstance(lssvr, LSSVR):
            raise TypeError(f"lssvr must be a fitted LSSVR, got {type(lssvr).__name__}")
        if lssvr.kernel != "rbf":
            raise ValueError(f"LSSVRGram needs kernel='rbf', got kernel={lssvr.kernel!r}")
        sv = lssvr.support_vectors.detach()
        if sv.shape[0] == 0:
            raise ValueError("lssvr is not fitted: call lssvr.fit(X, y) first")
        sigma = lssvr.sigma.detach()
        alpha = lssvr.alpha.detach()
        c = 1.0 / (2.0 * sigma * sigma)
        self.n_in = int(sv.shape[1])
        self.n_out = int(lssvr.n_out)
        self.register_buffer("support_vectors", sv.clone())
        self.register_buffer("alpha", alpha.clone())
        self.register_buffer("b", lssvr.b.detach().clone())
        self.register_buffer("inv_two_sigma2", c.clone())
        mu = sv.mean(0)
        self.register_buffer("centre", mu)
        sv = sv - mu  # (the kernel and Eq. 25 are shift-invariant; the expansion is not exact)
        self.register_buffer("sv_scaled_t", (2.0 * c * sv).mT.contiguous())
        self.register_buffer("sv_log_norm", -c * (sv * sv).sum(-1))
        alpha_sv = alpha.unsqueeze(-1) * sv.unsqueeze(-2)  # (M, n_out, n_in)
        self.register_buffer("alpha_sv", alpha_sv.reshape(sv.shape[0], -1).contiguous())

    def extra_repr(self) -> str:
        return f"n_in={self.n_in}, n_sv={self.support_vectors.shape[0]}, n_out={self.n_out}"

    def _phi(self, x: Tensor) -> Tensor:
        """Kernel values ``phi(P_i, x)`` (Eq. 24), ``(..., n_in) -> (..., M)``."""
        x2 = x.reshape(-1, self.n_in) - self.centre
        logk = torch.addmm(self.sv_log_norm, x2, self.sv_scaled_t)  # 2c P.x - c|P|^2
        # - c|x|^2 in place (the block is fresh); round-off can leave log phi ~ +1e-16 at
        # x = P_i: harmless. Far from every P_i, exp is floored (core.kernel_exp)
        phi = floored_exp(logk.sub_(self.inv_two_sigma2 * (x2 * x2).sum(-1, keepdim=True)))
        return phi.reshape(*x.shape[:-1], phi.shape[-1])

    def forward(self, x: Tensor) -> Tensor:
        """Prediction ``f(x)`` (Eq. 8): ``x (..., n_in) -> (..., n_out)``; the ``(B, M)`` kernel
        values in row blocks above :data:`GRAM_BLOCK_BYTES`."""
        check_forward_input(x, self.n_in, self.alpha)

        def block(xb: Tensor) -> Tensor:
            return self._phi(xb) @ self.alpha + self.b

        per_row = x.element_size() * self.support_vectors.shape[0]
        return _blocked(block, x, per_row, GRAM_BLOCK_BYTES)

    def input_gradient(self, x: Tensor) -> Tensor:
        """Closed-form Jacobian ``df/dx`` (Eq. 25): ``x (B, n_in) -> (B, n_out, n_in)``."""
        check_forward_input(x, self.n_in, self.alpha)
        if x.dim() != 2:
            raise ValueError(
                f"x must have shape (B, n_in) with n_in={self.n_in}, got {tuple(x.shape)}"
            )

        def block(xb: Tensor) -> Tensor:
            phi = self._phi(xb)  # (B, M)
            s = phi @ self.alpha  # (B, n_out): sum_i alpha_i phi_i
            wp = (phi @ self.alpha_sv).reshape(-1, self.n_out, self.n_in)  # sum alpha phi P_i
            xc = (xb - self.centre).unsqueeze(-2)
            return -2.0 * self.inv_two_sigma2 * (s.unsqueeze(-1) * xc - wp)

        per_row = x.element_size() * self.support_vectors.shape[0]
        return _blocked(block, x, per_row, GRAM_BLOCK_BYTES)


def fit_lssvr_gram(X: Tensor, y: Tensor, *, sigma: float, C: float) -> LSSVRGram:
    """A Gaussian-kernel :class:`LSSVR` fitted on ``(X, y)`` (Eq. 1-8, the KKT system of Eq. 4,
    on the device of ``X``) and returned as its Gram evaluator.

    Args:
        X: ``(M, n_in)`` training windows; y: ``(M,)`` or ``(M, 1)`` targets.
        sigma: kernel width; C: regularisation (both finite, ``> 0``).
    Returns:
        :class:`LSSVRGram`, ``(..., n_in) -> (..., 1)``.
    """
    return LSSVRGram(LSSVR(kernel="rbf", sigma=sigma, C=C).to(X.device).fit(X, y))


def lssvr_gram_fitter(
    sigma: float, C: float
) -> Callable[[Tensor, Tensor], Callable[[Tensor], Tensor]]:
    """``fit(X, y) -> predict`` for the blocked cross-validation
    (:func:`~prognos_torch.learners.blocked_multistep_cv`): each fold's model is
    :func:`fit_lssvr_gram` with these ``sigma`` and ``C``, its predictor ``(B, n_in) -> (B,)``
    in the dtype of its input (the model is fitted and evaluated in float64, so a float32
    series cross-validates as well)."""

    def fit(X: Tensor, y: Tensor) -> Callable[[Tensor], Tensor]:
        g = fit_lssvr_gram(X, y, sigma=sigma, C=C)
        # (the evaluator is float64: a float32 window was refused with a dtype TypeError)
        return lambda Xh: g(Xh.to(g.alpha.dtype))[:, 0].to(Xh.dtype)

    return fit


def _check_positive(v, name: str) -> float:
    """A finite real number ``> 0`` (``bool`` refused), as given."""
    if not is_real(v):
        raise TypeError(f"{name} must be a finite number > 0, got {type(v).__name__} {v!r}")
    if not 0.0 < float(v) < math.inf:
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return v


def _grid_values(values, name: str) -> tuple:
    """A non-empty tuple of finite numbers ``> 0`` (one axis of the grid)."""
    if isinstance(values, (str, bytes)) or not isinstance(values, Iterable):
        raise TypeError(f"{name} must be a non-empty sequence of numbers > 0, got {values!r}")
    values = tuple(values)
    if not values:
        raise ValueError(f"{name} must be a non-empty sequence of numbers > 0, got ()")
    for i, v in enumerate(values):
        _check_positive(v, f"{name}[{i}]")
    return values


def lssvr_grid_cv(
    series: Tensor,
    m: int,
    horizon: int,
    *,
    sigmas: Sequence[float],
    Cs: Sequence[float],
    scale: float = 1.0,
    folds: int = 5,
    threshold: float | None = None,
    stride: int = 1,
) -> dict[tuple[float, float], MultiStepCV]:
    """Blocked cross-validation of the Gaussian-kernel LS-SVR over a grid of kernel widths and
    regularisations (:func:`~prognos_torch.learners.blocked_multistep_cv` of
    :func:`lssvr_gram_fitter` per grid point).

    Args:
        series: ``(n,)`` the training series in time order; m: embedding dimension.
        horizon, folds, threshold, stride: as in
            :func:`~prognos_torch.learners.blocked_multistep_cv`.
        sigmas: kernel widths in units of ``scale`` (e.g. multiples of the series' std);
            Cs: regularisations; both non-empty, of finite numbers ``> 0`` (any iterable; a
            generator is read once).
        scale: finite number ``> 0``.
    Returns:
        ``{(s, C): MultiStepCV}`` for the width ``s * scale``, ``s`` outer and ``C`` inner.
    Raises:
        ValueError / TypeError: an empty grid, or a width, regularisation or scale that is not
            a finite number ``> 0``.
    """
    # (a generator of Cs was exhausted by the first width: the other widths got no cells;
    # an empty grid returned {} and a later min() over it failed without a name)
    sigmas, Cs = _grid_values(sigmas, "sigmas"), _grid_values(Cs, "Cs")
    _check_positive(scale, "scale")
    return {
        (s, C): blocked_multistep_cv(
            lssvr_gram_fitter(s * scale, C),
            series,
            m,
            horizon,
            folds,
            threshold=threshold,
            stride=stride,
        )
        for s in sigmas
        for C in Cs
    }
