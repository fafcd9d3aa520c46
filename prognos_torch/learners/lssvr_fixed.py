"""Fixed-size LS-SVR for long series: a Nystrom approximation on ``M`` support points.

The LS-SVR of paper 002 (Eq. 4) solves an ``N x N`` KKT system: ``O(N^2)`` memory and ``O(N^3)``
time, and every prediction sums ``N`` kernel terms (Eq. 8). The fixed-size LS-SVM of Suykens,
Van Gestel, De Brabanter, De Moor and Vandewalle (*Least Squares Support Vector Machines*, World
Scientific 2002, Sec. 6.5; De Brabanter et al., *Comput. Stat. Data Anal.* 54, 2010) keeps ``M``
support points ``z_1..z_M`` and solves the primal problem in a Nystrom feature space:

1. **support points** maximise the quadratic Renyi entropy of the working set,
   ``H_R = -log( (1 / M^2) sum_kl phi(z_k, z_l) )`` with the RBF window of width ``sigma``, by
   random swaps (replace a random ``z_k`` by a random training input, keep the swap if
   ``H_R`` grows); or a uniform random subset (``selection="random"``);
2. **Nystrom features** from the eigendecomposition ``K_MM = U diag(lambda) U^T``::

       phihat_j(x) = lambda_j^{-1/2} sum_k U_kj phi(z_k, x),      j with lambda_j > tol

   (``tol = lambda_max M eps``: directions the float64 eigensolver cannot resolve are dropped);
3. **primal ridge regression**: ``min_{w, b} (1 / C) |w|^2 + sum_i (y_i - w^T phihat(x_i) - b)^2``
   (paper 002 Eq. 1-2 with ``phihat`` for ``phi``), solved in square-root form: the triangular
   factor of the stacked system ``[[phihat(X), e, Y]; [C^{-1/2} I, 0, 0]]`` is accumulated over
   row blocks by QR (:func:`~prognos_torch.core.tria`), then one triangular solve. ``O(N M^2)``
   time; the inputs plus ``O(block M + M^2)`` memory;
4. the model is stored in the dual form of Eq. 8 on the support points,
   ``f(x) = sum_k beta_k phi(z_k, x) + b`` with ``beta = U diag(lambda^{-1/2}) w``, so
   prediction and the input Jacobian (Eq. 25) cost ``O(M)`` per input, and everything that uses
   an :class:`~prognos_torch.learners.LSSVR` (forward, ``input_gradient``,
   :class:`~prognos_torch.learners.LSSVRGram`, the learner transition model of the particle
   filters, Kalman optimisers over ``(alpha, b)``) uses it unchanged.

With ``M = N`` and ``z = X`` (``n_support >= N``), ``phihat(X) phihat(X)^T = K`` and the ridge
problem is the LS-SVR primal, whose solution is the KKT solution of Eq. 4 (tested to 1e-9).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

from ..core.kernel_exp import floored_exp
from ..core.linalg import tria
from ..core.validation import (
    as_data,
    as_targets,
    check_count,
    check_forward_input,
    check_pos_int,
)
from . import lssvr as _lssvr
from .lssvr import LSSVR, _blocked, kernel_matrix

__all__ = ["FixedSizeLSSVR", "SELECTIONS", "renyi_support", "nystrom_ridge"]

SELECTIONS = ("renyi", "random")


def _rbf_cross(X: Tensor, Z: Tensor, sigma: Tensor) -> Tensor:
    """``exp(-|x - z|^2 / (2 sigma^2))`` for ``X (..., n)``, ``Z (M, n)`` -> ``(..., M)`` by one
    matrix product (the expansion ``|x|^2 - 2 x.z + |z|^2``, as
    :class:`~prognos_torch.learners.LSSVRGram`). The kernel is shift-invariant, so both are
    taken from the centre ``mu`` of ``Z`` first: the expansion is then exact to
    ``~eps (|x - mu|^2 + |z - mu|^2) / sigma^2``, however far the data lie from the origin
    (uncentred, float32 inputs near 100 with ``sigma = 0.5`` lost every digit)."""
    mu = Z.mean(0)
    X, Z = X - mu, Z - mu
    c = 1.0 / (2.0 * sigma * sigma)
    logk = X @ ((2.0 * c) * Z.mT) - c * (Z * Z).sum(-1)
    # logk is fresh: - c|x|^2 in place; floored_exp writes in place unless autograd needs z
    return floored_exp(logk.sub_(c * (X * X).sum(-1, keepdim=True)))


def renyi_support(
    X: Tensor, M: int, sigma: float | Tensor, *, trials: int, generator: torch.Generator
) -> Tensor:
    """Indices of ``M`` rows of ``X`` with large quadratic Renyi entropy (Suykens et al. 2002).

    Starts from a uniform random subset and tries ``trials`` random swaps (a random member
    against a random training row); a swap is kept when it lowers
    ``sum_{k != l} phi(z_k, z_l)``, i.e. raises ``H_R``. Each trial costs ``O(M n)``. The swaps
    are a sequential loop of small steps: it runs on the CPU in NumPy (the candidates' kernel
    rows are formed 256 at a time), whatever the device of ``X``.

    Args:
        X: ``(N, n)`` candidate points.
        M: working-set size, ``1 <= M <= N``.
        sigma: width of the RBF window ``phi``.
        trials: swaps tried (``>= 0``).
        generator: CPU ``torch.Generator`` for the subset and the swaps.
    Returns:
        ``(M,)`` int64 indices on ``X``'s device.
    """
    N = X.shape[0]
    if not 1 <= M <= N:
        raise ValueError(f"M must be in [1, N={N}], got {M}")
    idx = torch.randperm(N, generator=generator)[:M]
    if M == N or trials == 0:
        return idx.to(X.device)
    out_k = torch.randint(M, (trials,), generator=generator).numpy()
    cand = torch.randint(N, (trials,), generator=generator).numpy()
    P = X.detach().to("cpu", torch.float64).numpy()
    c = 1.0 / (2.0 * float(sigma) ** 2)

    def phi(A: np.ndarray, B: np.ndarray) -> np.ndarray:
        return np.exp(-c * ((A[:, None, :] - B[None, :, :]) ** 2).sum(-1))

    sel = idx.numpy().copy()
    member = np.zeros(N, dtype=bool)
    member[sel] = True
    Z = P[sel].copy()
    K = phi(Z, Z)
    np.fill_diagonal(K, 1.0)
    rows = K.sum(-1)
    for s in range(0, trials, 256):
        ks, cs = out_k[s : s + 256], cand[s : s + 256]
        Kc = phi(P[cs], Z)  # candidates against the current working set
        for j in range(cs.shape[0]):
            k, ci = int(ks[j]), int(cs[j])
            if member[ci]:
                continue
            kc = Kc[j].copy()
            kc[k] = 1.0
            total = kc.sum()
            if total < rows[k]:  # the off-diagonal sum falls by 2 (rows[k] - total)
                rows += kc - K[k]
                rows[k] = total
                K[k] = kc
                K[:, k] = kc
                Z[k] = P[ci]
                member[sel[k]] = False
                member[ci] = True
                sel[k] = ci
                if j + 1 < cs.shape[0]:  # the later candidates now meet x_ci in slot k
                    Kc[j + 1 :, k] = phi(P[cs[j + 1 :]], P[ci : ci + 1])[:, 0]
    return torch.from_numpy(sel).to(X.device)


def nystrom_ridge(
    X: Tensor,
    Y: Tensor,
    Z: Tensor,
    C: float | Tensor,
    kernel_fn,
    *,
    block_bytes: int | None = None,
) -> tuple[Tensor, Tensor, int]:
    """Fixed-size LS-SVR solve (module notes, steps 2-4).

    Args:
        X: ``(N, n)`` training inputs; Y: ``(N, n_out)`` targets (float64).
        Z: ``(M, n)`` support points.
        C: regularisation ``C > 0`` (paper 002, Eq. 1).
        kernel_fn: ``(A (B, n), Z (M, n)) -> (B, M)`` kernel values.
        block_bytes: bytes per block of kernel rows (default
            :data:`~prognos_torch.learners.lssvr.KERNEL_BLOCK_BYTES`).
    Returns:
        ``(beta, b, rank)``: ``(M, n_out)`` dual weights on ``Z``, ``(n_out,)`` bias, and the
        number of Nystrom features kept.
    """
    n_out = Y.shape[1]
    K_MM = kernel_fn(Z, Z)
    lam, U = torch.linalg.eigh(0.5 * (K_MM + K_MM.mT))
    tol = lam[-1].clamp_min(0.0) * Z.shape[0] * torch.finfo(lam.dtype).eps
    keep = lam > tol
    r = int(keep.sum())
    if r == 0:
        raise ValueError("the kernel matrix of the support points is zero: no Nystrom features")
    W = U[:, keep] / lam[keep].sqrt()  # (M, r): phihat(x) = k(x, Z) W
    width = r + 1 + n_out  # [features, ones (bias), targets]
    # square root of the normal equations, started with the ridge rows [C^{-1/2} I_r, 0, 0]
    S = torch.zeros(width, width, dtype=X.dtype, device=X.device)
    S[:r, :r] = torch.eye(r, dtype=X.dtype, device=X.device) / torch.as_tensor(C).sqrt()
    budget = _lssvr.KERNEL_BLOCK_BYTES if block_bytes is None else int(block_bytes)
    rows = max(256, budget // (8 * (Z.shape[0] + 2 * width)))
    for s in range(0, X.shape[0], rows):
        F = kernel_fn(X[s : s + rows], Z) @ W
        ones = torch.ones(F.shape[0], 1, dtype=X.dtype, device=X.device)
        A = torch.cat([S, torch.cat([F, ones, Y[s : s + rows]], dim=-1)], dim=0)
        S = tria(A.mT).mT  # upper (width, width): S^T S = A^T A
    R, q = S[: r + 1, : r + 1], S[: r + 1, r + 1 :]
    theta = torch.linalg.solve_triangular(R, q, upper=True)  # (r + 1, n_out)
    return W @ theta[:r], theta[r], r


class FixedSizeLSSVR(LSSVR):
    """Fixed-size LS-SVR ``f(x) = sum_k beta_k phi(z_k, x) + b`` on ``M`` support points.

    An :class:`~prognos_torch.learners.LSSVR` (same parameters, buffers and state dict;
    ``alpha`` holds ``beta`` and ``support_vectors`` the ``z_k``) whose :meth:`fit` solves the
    Nystrom-approximated problem of the module notes in ``O(N M^2)`` time instead of the
    ``N x N`` KKT system. With the RBF kernel, ``forward`` forms the squared distances by the
    expansion ``|x|^2 - 2 x.z + |z|^2`` (one matrix product, as
    :class:`~prognos_torch.learners.LSSVRGram`) and ``input_gradient`` is the closed form of
    Eq. 25; both cost ``O(M n)`` per input and evaluate in blocks of
    :data:`~prognos_torch.learners.lssvr.KERNEL_BLOCK_BYTES`.

    Args:
        kernel, sigma, C, degree, coef0, n_out, trainable_hyper, dtype: as
            :class:`~prognos_torch.learners.LSSVR`.
        n_support: ``M``, the number of support points (all rows when ``N <= M``).
        selection: ``"renyi"`` (quadratic Renyi entropy, the default) or ``"random"``.
        trials: swaps tried by the Renyi selection (default ``20 M``).
        generator: CPU ``torch.Generator`` for the selection (default: seeded with 0). Each
            :meth:`fit` draws from it, so a second fit on the same data continues its stream
            and may select other support points (pass a freshly seeded generator to repeat a
            fit); its state is not part of ``state_dict`` (a loaded model holds the fitted
            support points, not the stream).
    """

    def __init__(
        self,
        kernel: str = "rbf",
        sigma: float = 1.0,
        C: float = 10.0,
        n_support: int = 200,
        selection: str = "renyi",
        trials: int | None = None,
        degree: int = 2,
        coef0: float = 1.0,
        n_out: int = 1,
        trainable_hyper: bool = False,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__(kernel, sigma, C, degree, coef0, n_out, trainable_hyper, dtype)
        self.n_support = check_pos_int(n_support, "n_support")
        if selection not in SELECTIONS:
            raise ValueError(f"selection must be one of {SELECTIONS}, got {selection!r}")
        self.selection = selection
        if trials is not None:
            trials = check_count(trials, "trials", 0, error=ValueError)
        self.trials = 20 * self.n_support if trials is None else trials
        if generator is not None and not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be a torch.Generator, got {type(generator)}")
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        #: Nystrom features kept by the last :meth:`fit` (``None`` before).
        self.rank: int | None = None

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, n_support={self.n_support}, selection={self.selection!r}"

    def _fitted_sv(self, x: Tensor) -> Tensor:
        sv = self.support_vectors
        if sv.shape[0] == 0:
            raise RuntimeError("FixedSizeLSSVR is not fitted: call fit(X, y) first")
        check_forward_input(x, sv.shape[1], self.alpha)
        return sv

    def forward(self, x: Tensor) -> Tensor:
        """Prediction ``f(x) = sum_k beta_k phi(z_k, x) + b`` (Eq. 8 on the support points).

        Args:
            x: ``(..., n_in)``, module dtype and device.
        Returns:
            ``(..., n_out)``.
        """
        if self.kernel != "rbf":
            return super().forward(x)
        sv = self._fitted_sv(x)
        sigma = torch.exp(self.log_sigma)

        def block(xb: Tensor) -> Tensor:
            return _rbf_cross(xb, sv, sigma) @ self.alpha + self.b

        return _blocked(block, x, x.element_size() * sv.shape[0])

    def input_gradient(self, x: Tensor) -> Tensor:
        """Jacobian ``df/dx`` (Eq. 25 in closed form for the RBF kernel, autograd otherwise).

        Args:
            x: ``(B, n_in)``.
        Returns:
            ``(B, n_out, n_in)``.
        """
        if self.kernel != "rbf":
            return super().input_gradient(x)
        sv = self._fitted_sv(x)
        if x.dim() != 2:
            raise ValueError(
                f"x must have shape (B, n_in) with n_in={sv.shape[1]}, got {tuple(x.shape)}"
            )
        sigma = torch.exp(self.log_sigma)
        alpha = self.alpha

        mu = sv.mean(
            0
        )  # (x - z_k is shift-invariant; centred, s x - sum beta phi z does not cancel)
        svc = sv - mu

        def block(xb: Tensor) -> Tensor:
            phi = _rbf_cross(xb, sv, sigma)  # (B, M)
            s = phi @ alpha  # (B, n_out): sum_k beta_k phi_k
            wz = torch.einsum("bk,ko,kn->bon", phi, alpha, svc)  # sum_k beta_k phi_k z_k
            return -(s.unsqueeze(-1) * (xb - mu).unsqueeze(-2) - wz) / (sigma * sigma)

        per_row = x.element_size() * sv.shape[0] * (1 + self.n_out)
        return _blocked(block, x, per_row)

    @torch.no_grad()
    def fit(self, X, y) -> FixedSizeLSSVR:
        """Select the support points and solve the fixed-size problem (module notes), float64.

        Args:
            X: inputs ``(N, n_in)``.
            y: targets ``(N, n_out)`` (or ``(N,)`` if ``n_out == 1``).
        Returns:
            ``self``.
        """
        dev = self.alpha.device
        X64 = as_data(X, "X", device=dev)
        Y64 = as_targets(y, "y", device=dev, n_rows=X64.shape[0], n_out=self.n_out)
        N = X64.shape[0]
        sigma = torch.exp(self.log_sigma.detach().to(torch.float64))
        M = min(self.n_support, N)
        if M == N:
            Z = X64
        elif self.selection == "renyi":
            Z = X64[renyi_support(X64, M, sigma, trials=self.trials, generator=self.generator)]
        else:
            Z = X64[torch.randperm(N, generator=self.generator)[:M].to(dev)]
        if self.kernel == "rbf":

            def kfn(A: Tensor, B: Tensor) -> Tensor:
                return _rbf_cross(A, B, sigma)
        else:

            def kfn(A: Tensor, B: Tensor) -> Tensor:
                return kernel_matrix(A, B, self.kernel, degree=self.degree, coef0=self.coef0)

        C = torch.exp(self.log_C.detach().to(torch.float64))
        beta, b, self.rank = nystrom_ridge(X64, Y64, Z, C, kfn)
        if not (math.isfinite(float(beta.abs().max())) and math.isfinite(float(b.abs().max()))):
            raise ValueError("the fixed-size LS-SVR solve gave non-finite weights")
        dtype = self.alpha.dtype
        if self.alpha.shape != beta.shape:
            self.alpha = nn.Parameter(beta.to(dtype), requires_grad=self.alpha.requires_grad)
        else:
            self.alpha.copy_(beta.to(dtype))
        self.b.copy_(b.to(dtype))
        self.support_vectors = Z.to(dtype).clone()
        return self
