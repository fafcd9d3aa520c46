"""Least-squares support vector regression (paper 002, Eq. 1-8 and Eq. 17-26).

Training solves the KKT system of paper 002, Eq. 4::

    [ Omega + I / C   e ] [alpha]   [Y]
    [ e^T             0 ] [  b  ] = [0]

with ``Omega_ij = phi(P_i, P_j)`` and prediction ``f(P) = sum_i alpha_i phi(P_i, P) + b`` (Eq. 8).

Kernels (paper 002, Eq. 5-7):

* ``"linear"``: ``phi(x, y) = <x, y>`` (Eq. 5);
* ``"poly"``: ``phi(x, y) = (coef0 + <x, y>)^degree``; the paper's Eq. 6 is ``coef0 = 1``,
  ``degree = 2`` (the defaults);
* ``"rbf"``: ``phi(x, y) = exp(-||x - y||^2 / (2 sigma^2))`` (Eq. 7 with ``delta = sigma`` and
  Eq. 24: the width enters as ``2 sigma^2``, not ``sigma^2`` or ``gamma``).

The input derivative used by the EKF/SFEKF (Eq. 17-26) is the Jacobian of Eq. 8 with respect to
the input: :meth:`LSSVR.input_gradient` computes it by automatic differentiation for any kernel.
For the RBF kernel it equals Eq. 25,
``sum_i alpha_i phi(P_i, P_s) (-1 / sigma^2) (P_s - P_i)``, and its last component is Eq. 23
(the derivative with respect to the newest embedded value ``x_s``).
"""

from __future__ import annotations

import math
import os

import torch
from torch import Tensor, nn

from ..core.kernel_exp import floored_exp
from ..core.validation import (
    as_data,
    as_targets,
    check_dtype_arg,
    check_forward_input,
    check_pos_int,
    is_real,
)

__all__ = [
    "LSSVR",
    "KERNELS",
    "linear_kernel",
    "poly_kernel",
    "rbf_kernel",
    "kernel_matrix",
    "solve_kkt",
    "KERNEL_BLOCK_BYTES",
]

KERNELS = ("rbf", "linear", "poly")

#: Memory budget of one block of kernel evaluations (bytes). The RBF kernel's difference tensor
#: ``(rows, M, n)``, a prediction's kernel block ``(rows, M)`` and the intermediates of the
#: autograd Jacobian larger than this are evaluated in row blocks, so neither an ``N x N x n``
#: Gram temporary nor a ``particles x N x n`` one is formed; below it the computation is one
#: call as before (kernel matrices are bit-identical either way, predictions agree to rounding;
#: ``tests/test_lssvr_fixed.py``). Small on purpose: temporaries of tens of MB are page-faulted
#: afresh on every allocation and fragment the heap: 60 steps of 500 particle paths over 4,000
#: support vectors took 31 s and 1.2 GB with 64 MiB blocks, 9 s and 0.5 GB with 4 MiB blocks.
KERNEL_BLOCK_BYTES = 4 * 2**20


def _row_chunks(X: Tensor, bytes_per_row: int, block_bytes: int | None = None) -> int | None:
    """Rows per block when ``X (..., n)`` flattened to rows needs more than the budget, else
    ``None`` (evaluate in one call)."""
    budget = KERNEL_BLOCK_BYTES if block_bytes is None else block_bytes
    n_rows = X.numel() // max(1, X.shape[-1]) if X.dim() > 0 else 1
    if n_rows * bytes_per_row <= budget or X.dim() < 2:
        return None
    return max(1, budget // max(1, bytes_per_row))


def _blocked(fn, X: Tensor, bytes_per_row: int, block_bytes: int | None = None) -> Tensor:
    """``fn(X)`` evaluated on row blocks of ``X (..., n)`` when it would exceed the budget."""
    rows = _row_chunks(X, bytes_per_row, block_bytes)
    if rows is None:
        return fn(X)
    flat = X.reshape(-1, X.shape[-1])
    out = torch.cat([fn(flat[s : s + rows]) for s in range(0, flat.shape[0], rows)], dim=0)
    return out.reshape(*X.shape[:-1], *out.shape[1:])


# --------------------------------------------------------------------------- functional core


def linear_kernel(X: Tensor, Y: Tensor) -> Tensor:
    """``phi(x, y) = <x, y>`` (paper 002, Eq. 5).

    ``X (..., N1, n)``, ``Y (N2, n)`` -> ``(..., N1, N2)``; likewise for the other kernels.
    """
    return X @ Y.mT


def poly_kernel(X: Tensor, Y: Tensor, degree: int = 2, coef0: float = 1.0) -> Tensor:
    """``phi(x, y) = (coef0 + <x, y>)^degree`` (paper 002, Eq. 6: ``coef0=1, degree=2``)."""
    return (X @ Y.mT + coef0) ** degree


def rbf_kernel(X: Tensor, Y: Tensor, sigma: Tensor | float) -> Tensor:
    """``phi(x, y) = exp(-||x - y||^2 / (2 sigma^2))`` (paper 002, Eq. 7 and Eq. 24).

    The squared distances are formed from explicit differences (not ``|x|^2 + |y|^2 - 2 x.y``),
    which is exact at ``x = y`` and has a clean derivative there. The difference tensor is
    formed in row blocks of at most :data:`KERNEL_BLOCK_BYTES`.
    """

    def block(A: Tensor) -> Tensor:
        d2 = ((A.unsqueeze(-2) - Y) ** 2).sum(-1)
        return floored_exp(-d2 / (2.0 * sigma * sigma))  # floored far out (core.kernel_exp)

    return _blocked(block, X, X.element_size() * Y.shape[0] * max(1, Y.shape[-1]))


def kernel_matrix(
    X: Tensor,
    Y: Tensor,
    kernel: str,
    *,
    sigma: Tensor | float = 1.0,
    degree: int = 2,
    coef0: float = 1.0,
) -> Tensor:
    """Kernel matrix ``phi(X_i, Y_j)``: ``X (..., N1, n)``, ``Y (N2, n)`` -> ``(..., N1, N2)``."""
    if kernel == "rbf":
        return rbf_kernel(X, Y, sigma)
    if kernel == "linear":
        return linear_kernel(X, Y)
    if kernel == "poly":
        return poly_kernel(X, Y, degree, coef0)
    raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")


#: float64 ``M x M`` matrices the exact fit holds at once (the kernel matrix, ``Omega + I / C``
#: and its Cholesky factor)
KKT_MATRICES = 3


def _machine_memory(device: torch.device) -> int | None:
    """Bytes of memory on ``device`` (physical memory for the CPU), ``None`` if unknown."""
    try:
        if device.type == "cuda":
            return torch.cuda.get_device_properties(device).total_memory
        if device.type == "cpu":
            return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError, RuntimeError):  # pragma: no cover
        pass
    return None


def _check_kkt_memory(M: int, device: torch.device) -> None:
    """Refuse an exact fit whose ``M x M`` matrices exceed the device's memory (before the
    kernel blocks are built: a 100,000-row fit ran 40 s into an allocator failure)."""
    need = KKT_MATRICES * 8 * M * M
    have = _machine_memory(device)
    if have is not None and need > have:
        raise MemoryError(
            f"the exact LS-SVR on {M:,} samples needs about {need / 2**30:.3g} GiB ({KKT_MATRICES} "
            f"{M:,} x {M:,} float64 matrices: Eq. 4's kernel matrix and its factorisation), more "
            f"than the {have / 2**30:.3g} GiB of this {device.type} device; use "
            "FixedSizeLSSVR(n_support=M) (Nystrom on M support points, memory O(N M))"
        )


def solve_kkt(Omega: Tensor, Y: Tensor, C: Tensor | float) -> tuple[Tensor, Tensor]:
    """Solve the LS-SVR KKT system (paper 002, Eq. 4) by eliminating ``b``.

    With ``A = Omega + I / C`` (symmetric positive definite for ``C > 0``), ``eta = A^{-1} e`` and
    ``nu = A^{-1} Y`` (two solves with one Cholesky factorisation, shared by all outputs)::

        b = e^T nu / e^T eta,    alpha = nu - eta b.

    Differentiable (also with respect to ``C`` and kernel hyper-parameters inside ``Omega``).

    Args:
        Omega: kernel matrix ``(M, M)``.
        Y: targets ``(M, n_out)``.
        C: regularisation parameter ``C > 0``.
    Returns:
        ``(alpha, b)``: ``(M, n_out)`` and ``(n_out,)``.
    Raises:
        ValueError: if ``Omega + I / C`` is not positive definite.
    """
    M = Omega.shape[-1]
    # Omega + I / C without an M x M identity (the same numbers: off-diagonal entries + 0)
    A = Omega.clone()
    A.diagonal(dim1=-2, dim2=-1).add_(torch.ones((), dtype=Omega.dtype, device=Omega.device) / C)
    L, info = torch.linalg.cholesky_ex(A)
    if bool((info > 0).any()):
        raise ValueError(
            "Omega + I/C (LS-SVR KKT system, Eq. 4) is not positive definite: "
            "the kernel matrix is not positive semi-definite or C is too large"
        )
    e = torch.ones(M, 1, dtype=Omega.dtype, device=Omega.device)
    sol = torch.cholesky_solve(torch.cat([e, Y], dim=-1), L)
    eta, nu = sol[:, :1], sol[:, 1:]
    b = nu.sum(0) / eta.sum(0)  # e^T nu / e^T eta, (n_out,)
    alpha = nu - eta * b
    return alpha, b


# --------------------------------------------------------------------------- module


class LSSVR(nn.Module):
    """LS-SVR regressor ``f(P) = sum_i alpha_i phi(P_i, P) + b`` (paper 002, Eq. 4-8).

    Parameters (registration order): ``alpha`` ``(M, n_out)`` Lagrange multipliers, ``b``
    ``(n_out,)`` bias, ``log_sigma`` (RBF width, log form) and ``log_C`` (regularisation, log form),
    both 0-d. ``alpha`` and ``b`` are trainable; ``log_sigma``/``log_C`` have
    ``requires_grad=trainable_hyper``. ``log_C`` enters only :meth:`fit` (Eq. 4), not the
    prediction; ``log_sigma`` is used by the RBF kernel only.

    Buffer: ``support_vectors`` ``(M, n_in)``, the training inputs ``P_i`` (set by :meth:`fit`).
    Before :meth:`fit` the model has ``M = 0`` and ``forward`` raises. :meth:`fit` replaces
    ``alpha`` by a new ``Parameter`` when ``M`` changes (re-create optimisers afterwards);
    ``load_state_dict`` resizes ``alpha`` and ``support_vectors`` to the stored shapes.

    Args:
        kernel: ``"rbf"``, ``"linear"`` or ``"poly"`` (Eq. 5-7).
        sigma: RBF width ``sigma > 0`` in ``exp(-||x - y||^2 / (2 sigma^2))``.
        C: regularisation ``C > 0`` (Eq. 1).
        degree: polynomial degree (``"poly"``), positive int.
        coef0: polynomial offset (``"poly"``).
        n_out: number of outputs (independent regressions sharing the factorisation).
        trainable_hyper: make ``log_sigma`` and ``log_C`` trainable.
        dtype: floating dtype of parameters and support vectors.
    """

    def __init__(
        self,
        kernel: str = "rbf",
        sigma: float = 1.0,
        C: float = 10.0,
        degree: int = 2,
        coef0: float = 1.0,
        n_out: int = 1,
        trainable_hyper: bool = False,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
        for name, v in (("sigma", sigma), ("C", C)):
            if not is_real(v):
                raise TypeError(f"{name} must be a real number, got {type(v).__name__} {v!r}")
            if not (0.0 < float(v) < math.inf):
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        if float(sigma) ** 2 == 0.0:  # (the kernel's 2 sigma^2 would be 0: every entry NaN)
            raise ValueError(f"sigma = {sigma!r} is too small: 2 sigma^2 underflows to 0")
        check_dtype_arg(dtype)
        # the forward evaluates 2 sigma^2 in the module dtype from exp(log_sigma): in float32 a
        # sigma below ~1e-23 gave 0 there, and NaN (0/0) at every support vector
        s = torch.exp(torch.tensor(math.log(sigma), dtype=dtype, device="cpu"))
        if float(2.0 * s * s) == 0.0:
            raise ValueError(
                f"sigma = {sigma!r} is too small: 2 sigma^2 underflows to 0 in {dtype}"
            )
        # Eq. 4's 1 / C (float64, from exp(log_C)) must be finite: C = 1e-310 gave NaN alpha, b
        C_fit = torch.tensor(math.log(C), dtype=dtype, device="cpu").double().exp()  # as in fit
        if not bool(torch.isfinite(1.0 / C_fit)):
            raise ValueError(f"C = {C!r} is too small: 1/C overflows float64")
        self.kernel = kernel
        self.degree = check_pos_int(degree, "degree")
        if not is_real(coef0):
            raise TypeError(f"coef0 must be a real number, got {type(coef0).__name__} {coef0!r}")
        if not math.isfinite(float(coef0)):
            raise ValueError(f"coef0 must be a finite number, got {coef0!r}")
        self.coef0 = float(coef0)
        self.n_out = check_pos_int(n_out, "n_out")
        self.trainable_hyper = bool(trainable_hyper)
        self.alpha = nn.Parameter(torch.zeros(0, n_out, dtype=dtype))
        self.b = nn.Parameter(torch.zeros(n_out, dtype=dtype))
        self.log_sigma = nn.Parameter(
            torch.tensor(math.log(sigma), dtype=dtype), requires_grad=self.trainable_hyper
        )
        self.log_C = nn.Parameter(
            torch.tensor(math.log(C), dtype=dtype), requires_grad=self.trainable_hyper
        )
        self.register_buffer("support_vectors", torch.zeros(0, 0, dtype=dtype))

    def extra_repr(self) -> str:
        return (
            f"kernel={self.kernel!r}, n_in={self.n_in}, n_sv={self.alpha.shape[0]}, "
            f"n_out={self.n_out}, trainable_hyper={self.trainable_hyper}"
        )

    @property
    def n_in(self) -> int | None:
        """Input dimension (``None`` before :meth:`fit`)."""
        sv = self.support_vectors
        return int(sv.shape[1]) if sv.shape[0] > 0 else None

    @property
    def sigma(self) -> Tensor:
        """RBF width ``sigma = exp(log_sigma)``."""
        return torch.exp(self.log_sigma)

    @property
    def C(self) -> Tensor:
        """Regularisation ``C = exp(log_C)``."""
        return torch.exp(self.log_C)

    def _kernel(self, X: Tensor, Y: Tensor, log_sigma: Tensor) -> Tensor:
        return kernel_matrix(
            X, Y, self.kernel, sigma=torch.exp(log_sigma), degree=self.degree, coef0=self.coef0
        )

    # ---------------------------------------------------------------- forward (functional)
    def forward(self, x: Tensor) -> Tensor:
        """Prediction ``f(x) = sum_i alpha_i phi(P_i, x) + b`` (Eq. 8).

        Args:
            x: ``(..., n_in)`` (typically ``(B, n_in)``), module dtype and device.
        Returns:
            ``(..., n_out)``.
        """
        sv = self.support_vectors
        if sv.shape[0] == 0:
            raise RuntimeError("LSSVR is not fitted: call fit(X, y) first")
        check_forward_input(x, sv.shape[1], self.alpha)

        def block(xb: Tensor) -> Tensor:
            return self._kernel(xb, sv, self.log_sigma) @ self.alpha + self.b

        # rows of the kernel block (and, for the RBF kernel, of its difference tensor)
        per_row = x.element_size() * sv.shape[0] * (sv.shape[1] if self.kernel == "rbf" else 1)
        return _blocked(block, x, per_row)

    def input_gradient(self, x: Tensor) -> Tensor:
        """Jacobian of Eq. 8 with respect to the input, ``df/dx`` (generalises Eq. 20-26).

        Computed with ``torch.func.jacrev`` per sample (works for every kernel, inside and
        outside ``torch.no_grad``), vectorised by ``vmap`` in chunks of rows whose
        intermediates (``~6 M n`` numbers per row for the RBF kernel) stay within
        :data:`KERNEL_BLOCK_BYTES`. For an embedding ``P_s = [x_{s-m+1}, ..., x_s]`` the
        derivative with respect to the newest value ``x_s`` (Eq. 23/26) is ``[..., -1]``.

        Args:
            x: ``(B, n_in)``.
        Returns:
            ``(B, n_out, n_in)``.
        """
        sv = self.support_vectors
        if sv.shape[0] == 0:
            raise RuntimeError("LSSVR is not fitted: call fit(X, y) first")
        n_in = sv.shape[1]
        check_forward_input(x, n_in, self.alpha)
        if x.dim() != 2:
            raise ValueError(f"x must have shape (B, n_in) with n_in={n_in}, got {tuple(x.shape)}")
        per_row = 6 * x.element_size() * sv.shape[0] * (n_in if self.kernel == "rbf" else 1)
        chunk = _row_chunks(x, per_row)  # None: one vmap over all rows, as before
        return torch.func.vmap(torch.func.jacrev(self.forward), chunk_size=chunk)(x)

    # ---------------------------------------------------------------- training (stateful)
    @torch.no_grad()
    def fit(self, X, y) -> LSSVR:
        """Train on ``M`` samples: solve the KKT system (Eq. 4) in float64.

        The support vectors, ``alpha`` and ``b`` are stored in the module dtype.

        Args:
            X: inputs ``P_i``, ``(M, n_in)``.
            y: targets ``(M, n_out)`` (or ``(M,)`` if ``n_out == 1``).
        Returns:
            ``self``.
        Raises:
            MemoryError: the ``M x M`` matrices of Eq. 4 (about ``24 M^2`` bytes) exceed the
                device's memory; :class:`~prognos_torch.learners.FixedSizeLSSVR` fits long
                series in ``O(N M)``.
        """
        dev = self.alpha.device
        X64 = as_data(X, "X", device=dev)
        Y64 = as_targets(y, "y", device=dev, n_rows=X64.shape[0], n_out=self.n_out)
        _check_kkt_memory(X64.shape[0], dev)
        log_sigma = self.log_sigma.detach().to(torch.float64)
        Omega = self._kernel(X64, X64, log_sigma)
        alpha, b = solve_kkt(Omega, Y64, torch.exp(self.log_C.detach().to(torch.float64)))
        dtype = self.alpha.dtype
        if self.alpha.shape != alpha.shape:
            self.alpha = nn.Parameter(alpha.to(dtype), requires_grad=self.alpha.requires_grad)
        else:
            self.alpha.copy_(alpha.to(dtype))
        self.b.copy_(b.to(dtype))
        self.support_vectors = X64.to(dtype)
        return self

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # The number of support vectors is data dependent: resize before copying.
        key = prefix + "alpha"
        if key in state_dict and state_dict[key].shape != self.alpha.shape:
            self.alpha = nn.Parameter(
                self.alpha.new_empty(state_dict[key].shape),
                requires_grad=self.alpha.requires_grad,
            )
        key = prefix + "support_vectors"
        if key in state_dict and state_dict[key].shape != self.support_vectors.shape:
            self.support_vectors = self.support_vectors.new_empty(state_dict[key].shape)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
