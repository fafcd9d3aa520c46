"""Audit of core.linalg, core.kernel_exp and core.random against exact references.

References: ``torch.linalg.cholesky`` of the formed matrix, ``numpy.linalg.solve``, finite
differences (``gradcheck``), ``torch.randn`` with the same seed, closed forms on diagonal
factors whose entries are powers of two (exact in floating point).
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import test_linalg
import torch

import prognos_torch.core.linalg as linalg
from prognos_torch.core.kernel_exp import EXP_FLOORS, floored_exp
from prognos_torch.core.linalg import (
    cho_solve_right,
    chol_downdate,
    chol_downdate_ex,
    chol_update,
    safe_cholesky,
    symmetrize,
    tria,
)
from prognos_torch.core.random import box_muller, standard_normal

#: either implementation of the up/downdates (normally chosen by size): test_linalg's fixture
path = test_linalg.path

F64 = torch.float64


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _factor(g, *batch, n, dtype=F64):
    A = torch.randn(*batch, n, n + 2, generator=g, dtype=F64)
    return torch.linalg.cholesky(A @ A.mT).to(dtype)


# ------------------------------------------------------------------------------ references
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(
    "shape", [(4, 9), (5, 2), (3, 3), (2, 3, 7), (4, 1, 6), (1, 5), (3, 0)], ids=str
)
def test_tria_reproduces_a_a_transpose(shape, dtype):
    g = _gen(sum(shape))
    A = torch.randn(*shape, generator=g, dtype=F64)
    S = tria(A.to(dtype))
    n = shape[-2]
    assert S.shape == (*shape[:-1], n) and S.dtype == dtype
    assert torch.equal(S, S.tril())
    assert bool((torch.diagonal(S, dim1=-2, dim2=-1) >= 0).all())
    ref = A @ A.mT
    tol = (1e-12 if dtype == F64 else 1e-5) * max(float(ref.abs().max()), 1.0)
    torch.testing.assert_close(S.double() @ S.double().mT, ref, rtol=0, atol=tol)
    if shape[-1] >= n:  # full row rank: the unique Cholesky factor (the sign convention)
        torch.testing.assert_close(S.double(), torch.linalg.cholesky(ref), rtol=0, atol=tol)


def test_tria_of_rank_deficient_and_zero_matrices():
    g = _gen(1)
    B = torch.randn(3, 2, 4, generator=g, dtype=F64)
    A = torch.cat([B[:, :1], B], dim=1)  # (3, 3, 4): rows 0 and 1 equal, rank 2
    for X in (A, torch.zeros(2, 3, 5, dtype=F64)):
        S = tria(X)
        torch.testing.assert_close(S @ S.mT, X @ X.mT, rtol=0, atol=1e-12 * 10)
        assert torch.equal(S, S.tril())
        assert bool((torch.diagonal(S, dim1=-2, dim2=-1) >= 0).all())
    assert torch.equal(tria(torch.zeros(2, 3, 5, dtype=F64)), torch.zeros(2, 3, 3, dtype=F64))


@pytest.mark.parametrize("n,k", [(1, 1), (3, 1), (5, 3), (12, 2)])
def test_up_and_downdates_equal_the_cholesky_of_the_formed_matrix(n, k, path):
    g = _gen(10 * n + k)
    S = _factor(g, 3, n=n)
    V = 0.4 * torch.randn(3, n, k, generator=g, dtype=F64)
    up = chol_update(S, V)
    ref = torch.linalg.cholesky(S @ S.mT + V @ V.mT)
    scale = float(ref.abs().max())
    torch.testing.assert_close(up, ref, rtol=0, atol=1e-12 * scale)
    down = chol_downdate(up, V)
    torch.testing.assert_close(down, S, rtol=0, atol=1e-11 * scale)
    # a batch of vectors (one dimension fewer than the factor) is one column each
    v = V[..., 0]
    ref1 = torch.linalg.cholesky(S @ S.mT + v[..., :, None] * v[..., None, :])
    torch.testing.assert_close(chol_update(S, v), ref1, rtol=0, atol=1e-12 * scale)
    torch.testing.assert_close(chol_downdate(ref1, v), S, rtol=0, atol=1e-11 * scale)


@pytest.mark.parametrize("k", [1, 3])
def test_downdate_to_an_indefinite_matrix_raises_or_flags(k, path):
    S = torch.eye(4, dtype=F64).expand(2, 4, 4).clone()
    V = torch.zeros(2, 4, k, dtype=F64)
    V[0, :, -1] = 0.6  # |v|^2 = 1.44 > 1: I - v v^T indefinite
    V[1, 0, 0] = 0.5
    S2, ratio = chol_downdate_ex(S, V)
    assert not bool(ratio[0] > 0) and bool(ratio[1] > 0)
    torch.testing.assert_close(
        S2[1], torch.linalg.cholesky(S[1] - V[1] @ V[1].mT), rtol=0, atol=1e-15
    )
    with pytest.raises(torch.linalg.LinAlgError, match="not positive definite"):
        chol_downdate(S, V)


@pytest.mark.parametrize("m", [1, 4])
def test_cho_solve_right_equals_numpy_solve(m):
    g = _gen(m)
    S = _factor(g, 2, n=m)
    B = torch.randn(2, 3, m, generator=g, dtype=F64)
    ref = np.linalg.solve((S @ S.mT).numpy(), B.mT.numpy()).transpose(0, 2, 1)
    np.testing.assert_allclose(cho_solve_right(B, S).numpy(), ref, rtol=1e-12, atol=1e-12)


def test_gradients_equal_finite_differences(path):
    g = _gen(3)
    S = _factor(g, 2, n=3).requires_grad_()
    V = (0.3 * torch.randn(2, 3, 2, generator=g, dtype=F64)).requires_grad_()
    B = torch.randn(2, 2, 3, generator=g, dtype=F64, requires_grad=True)
    A = torch.randn(2, 3, 5, generator=g, dtype=F64, requires_grad=True)
    P = (S @ S.mT).detach().requires_grad_()
    assert torch.autograd.gradcheck(tria, (A,))
    assert torch.autograd.gradcheck(chol_update, (S, V))
    assert torch.autograd.gradcheck(lambda s, v: chol_downdate_ex(s, v), (S, V))
    assert torch.autograd.gradcheck(cho_solve_right, (B, S))
    assert torch.autograd.gradcheck(safe_cholesky, (P,))


def test_no_explicit_inverse_in_the_square_root_algebra():
    src = inspect.getsource(linalg)
    for bad in ("linalg.inv", ".inverse(", "torch.inverse", "pinv"):
        assert bad not in src


# ------------------------------------------------------------------------------ fixes
@pytest.mark.parametrize(
    "dtype,v,k", [(torch.float64, 1 - 2.0**-20, 60), (torch.float32, 1 - 2.0**-10, 18)]
)
def test_a_valid_downdate_by_many_strong_columns_is_not_reported_failed(dtype, v, k, path):
    # S = diag(2^(i mod 3)), V = v S: S S^T - V V^T = diag(4^(i mod 3) (1 - v^2)), exact in
    # the dtype; the determinant ratio (1 - v^2)^k (1e-344, 1e-49) underflows to 0
    s = 2.0 ** (torch.arange(k) % 3).to(dtype)
    S, V = torch.diag(s), torch.diag(v * s)
    ref = torch.diag(s * (1.0 - v * v) ** 0.5)
    S2, ratio = chol_downdate_ex(S, V)
    assert bool(ratio > 0)  # former: 0, "not positive definite"
    rtol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(S2, ref, rtol=rtol, atol=0)
    torch.testing.assert_close(chol_downdate(S, V), ref, rtol=rtol, atol=0)
    # a last column that makes the matrix indefinite is still reported after the underflow
    Vbad = torch.cat([V, 2.0 * s[:, None] * torch.ones(k, 1, dtype=dtype)], dim=-1)
    assert not bool(chol_downdate_ex(S, Vbad)[1] > 0)
    with pytest.raises(torch.linalg.LinAlgError):
        chol_downdate(S, Vbad)


def _bad(name, fn, err, match):
    return pytest.param(fn, err, match, id=name)


_E, _I = torch.eye(3, dtype=F64), torch.ones(3, dtype=F64)
_BAD = [
    # silently accepted before
    _bad("update non-square S", lambda: chol_update(torch.ones(3, 4, dtype=F64), _I), ValueError, r"S must have shape \(\.\.\., n, n\)"),
    _bad("update mixed dtypes", lambda: chol_update(_E, _I.float()), TypeError, "one dtype"),
    _bad("downdate mixed dtypes", lambda: chol_downdate_ex(_E.float(), 0.1 * _I), TypeError, "one dtype"),
    _bad("solve 1x1 S, B of 3 columns", lambda: cho_solve_right(torch.ones(5, 3, dtype=F64), 2 * torch.ones(1, 1, dtype=F64)), ValueError, r"B must have shape \(\.\.\., n, 1\)"),
    _bad("symmetrize a row", lambda: symmetrize(torch.ones(1, 3, dtype=F64)), ValueError, r"P must have shape"),
    _bad("safe_cholesky of a row, jitter", lambda: safe_cholesky(torch.ones(1, 2, dtype=F64), jitter=1e-9), ValueError, r"P must have shape"),
    # obscure errors before
    _bad("update V of wrong n", lambda: chol_update(_E, torch.ones(4, dtype=F64)), ValueError, r"V must have shape \(\.\.\., 3\)"),
    _bad("update batch mismatch", lambda: chol_update(_E.expand(2, 3, 3), torch.ones(5, 3, 1, dtype=F64)), ValueError, "batch dimensions of S"),
    _bad("update vector of a batch factor", lambda: chol_update(_E.expand(2, 3, 3), torch.ones(3, dtype=F64)), ValueError, "V must have shape"),
    _bad("downdate non-square S", lambda: chol_downdate(torch.ones(3, 4, dtype=F64), 0.1 * _I), ValueError, "S must have shape"),
    _bad("downdate W of other columns", lambda: chol_downdate_ex(_E, 0.1 * _I, torch.ones(3, 2, dtype=F64)), ValueError, "W"),
    _bad("solve n mismatch", lambda: cho_solve_right(torch.ones(5, 3, dtype=F64), torch.eye(2, dtype=F64)), ValueError, r"B must have shape \(\.\.\., n, 2\)"),
    _bad("solve non-square S", lambda: cho_solve_right(torch.ones(5, 3, dtype=F64), torch.ones(3, 2, dtype=F64)), ValueError, "S must have shape"),
    _bad("tria of a vector", lambda: tria(torch.ones(3, dtype=F64)), ValueError, r"A must have shape \(\.\.\., n, L\)"),
    _bad("tria of integers", lambda: tria(torch.ones(3, 3, dtype=torch.int64)), TypeError, "A must be a floating"),
    _bad("tria of a list", lambda: tria([[1.0, 2.0]]), TypeError, "A must be a torch.Tensor"),
    _bad("safe_cholesky non-square", lambda: safe_cholesky(torch.ones(3, 2, dtype=F64)), ValueError, "P must have shape"),
    _bad("safe_cholesky jitter nan", lambda: safe_cholesky(torch.ones(2, 2, dtype=F64), jitter=float("nan")), ValueError, "jitter"),
    _bad("safe_cholesky jitter inf", lambda: safe_cholesky(-torch.eye(2, dtype=F64), jitter=float("inf")), ValueError, "jitter"),
    _bad("safe_cholesky jitter text", lambda: safe_cholesky(torch.eye(2, dtype=F64), jitter="1"), ValueError, "jitter"),
    _bad("safe_cholesky max_tries float", lambda: safe_cholesky(torch.ones(2, 2, dtype=F64), jitter=1e-9, max_tries=2.5), TypeError, "max_tries"),
]  # fmt: skip


@pytest.mark.parametrize("fn,err,match", _BAD)
def test_bad_input_is_named(fn, err, match):
    with pytest.raises(err, match=match):
        fn()


def test_numpy_scalars_are_accepted_by_safe_cholesky():
    P = torch.ones(2, 2, dtype=F64)
    a = safe_cholesky(P, jitter=np.float64(1e-9), max_tries=np.int64(6))
    torch.testing.assert_close(a, safe_cholesky(P, jitter=1e-9, max_tries=6), rtol=0, atol=0)


def test_nan_input_is_named_in_the_failure():
    nan = torch.full((2, 2), float("nan"), dtype=F64)
    with pytest.raises(torch.linalg.LinAlgError, match="P contains non-finite"):
        safe_cholesky(nan, jitter=1e-9)  # former: "not positive definite, even with jitter"
    S = torch.eye(2, dtype=F64)
    with pytest.raises(torch.linalg.LinAlgError, match="S or V contains NaN"):
        chol_downdate(S, torch.tensor([0.1, float("nan")], dtype=F64))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_safe_cholesky_jitters_a_zero_matrix_in_either_dtype(dtype):
    # former: float32 raised (its floor 1e-300 of the mean diagonal is 0 in float32)
    L = safe_cholesky(torch.zeros(2, 3, 3, dtype=dtype), jitter=1e-6)
    d = torch.diagonal(L, dim1=-2, dim2=-1)
    assert L.dtype == dtype and torch.equal(L, torch.diag_embed(d))
    assert bool((d > 0).all()) and bool(torch.isfinite(d).all())
    assert bool((d == d[0, 0]).all())  # the same jitter on every diagonal entry


# ------------------------------------------------------------------------------ random
def test_standard_normal_same_seed_same_draws_in_torch_randn_order():
    for shape in ((2, 3, 4), (np.int64(3), 5)):
        a = standard_normal(shape, _gen(5), F64, "cpu")
        b = standard_normal(shape, _gen(5), F64, "cpu")
        want = torch.randn(tuple(int(d) for d in shape), generator=_gen(5), dtype=F64)
        assert torch.equal(a, b) and torch.equal(a, want)  # row-major, as torch.randn
    # a batch drawn at once is the rows of successive draws' concatenation
    g, h = _gen(6), _gen(6)
    whole = standard_normal((3, 4), g, torch.float32, "cpu")
    rows = torch.stack([standard_normal((4,), h, torch.float32, "cpu") for _ in range(3)])
    assert torch.equal(whole, rows)


@pytest.mark.parametrize(
    "args,err,match",
    [
        (((3,), 0, F64, "cpu"), TypeError, "generator must be a torch.Generator"),
        (((5000,), np.random.default_rng(0), F64, "cpu"), TypeError, "generator"),
        ((5, None, F64, "cpu"), TypeError, "shape must be a tuple"),
        (((2.0, 3), None, F64, "cpu"), TypeError, "shape"),
        (((2, -3), None, F64, "cpu"), ValueError, "shape"),
        (((2, 3), None, torch.int64, "cpu"), TypeError, "dtype must be a floating"),
    ],
    ids=[
        "int generator",
        "numpy generator",
        "int shape",
        "float size",
        "negative size",
        "int dtype",
    ],
)
def test_standard_normal_bad_arguments_named(args, err, match):
    with pytest.raises(err, match=match):
        standard_normal(*args)


def test_box_muller_out_of_the_wrong_shape_is_refused():
    u = torch.rand(2, 16, generator=_gen(0), dtype=F64)
    out = torch.zeros(3, 16, dtype=F64)
    with pytest.raises(ValueError, match="out must have u's shape"):
        box_muller(u, out)  # former: out returned unwritten (a resized view was written)
    assert torch.equal(out, torch.zeros(3, 16, dtype=F64))
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., 16\)"):
        box_muller(torch.tensor(0.5))
    # the closed form, in place and not
    r = torch.sqrt(-2.0 * torch.log(1.0 - u[:, :8]))
    ref = torch.cat(
        [r * torch.cos(2 * torch.pi * u[:, 8:]), r * torch.sin(2 * torch.pi * u[:, 8:])], -1
    )
    torch.testing.assert_close(box_muller(u), ref, rtol=1e-15, atol=1e-15)
    torch.testing.assert_close(box_muller(u, torch.empty_like(u)), ref, rtol=1e-15, atol=1e-15)


# ------------------------------------------------------------------------------ kernel_exp
def test_floored_exp_bad_arguments_and_integer_exponents():
    with pytest.raises(TypeError, match="z must be a torch.Tensor"):
        floored_exp(-3.0)
    z = torch.tensor([1.0, -800.0], dtype=F64)
    with pytest.raises(TypeError, match="out_of_place must be a bool"):
        floored_exp(z.clone(), out_of_place="no")  # former: read as True
    zi = torch.tensor([1, -2])
    torch.testing.assert_close(floored_exp(zi), torch.exp(zi.double()).float(), rtol=1e-6, atol=0)
    assert torch.equal(zi, torch.tensor([1, -2]))  # former: RuntimeError from the in-place exp
    with pytest.raises(TypeError, match="out_of_place=False needs a floating z"):
        floored_exp(zi, out_of_place=False)
    w = z.clone()
    assert floored_exp(w, out_of_place=np.bool_(False)) is w
    assert float(w[1]) == float(torch.exp(torch.tensor(EXP_FLOORS[F64], dtype=F64)))
