"""Square-root linear algebra against dense references (Cholesky of the formed matrix, solves)."""

import pytest
import torch

from prognos_torch.core.linalg import (
    cho_solve_right,
    chol_downdate,
    chol_downdate_ex,
    chol_update,
    tria,
)

torch.set_num_threads(1)


def _spd_factor(g, *shape, n):
    A = torch.randn(*shape, n, n + 2, generator=g, dtype=torch.float64)
    return torch.linalg.cholesky(A @ A.mT)


@pytest.mark.parametrize("n,L", [(1, 5), (4, 2), (6, 13), (30, 61)])
def test_tria_is_the_cholesky_factor(n, L):
    g = torch.Generator().manual_seed(n)
    A = torch.randn(3, n, L, generator=g, dtype=torch.float64)
    S = tria(A)
    if L >= n:
        ref = torch.linalg.cholesky(A @ A.mT)
        torch.testing.assert_close(S, ref, rtol=0, atol=1e-12 * float(ref.abs().max()))
    else:  # rank-deficient: still a lower factor with a non-negative diagonal
        torch.testing.assert_close(S @ S.mT, A @ A.mT, rtol=0, atol=1e-12)
    assert torch.equal(S, S.tril())
    assert bool((torch.diagonal(S, dim1=-2, dim2=-1) >= 0).all())


@pytest.fixture(params=["rank_one", "dense"])
def path(request, monkeypatch):
    """Force either implementation of the up/downdates (normally chosen by size)."""
    import prognos_torch.core.linalg as linalg

    if request.param == "rank_one":
        monkeypatch.setattr(linalg, "_RANK_ONE_MIN_NUMEL", 0)
        monkeypatch.setattr(linalg, "_RANK_ONE_MIN_N_PER_RANK", 0)
    else:
        monkeypatch.setattr(linalg, "_RANK_ONE_MIN_NUMEL", 10**12)
    return request.param


@pytest.mark.parametrize("n", [1, 3, 20])
@pytest.mark.parametrize("k", [1, 2, 4, 9])
def test_update_and_downdate_equal_dense_cholesky(n, k, path):
    g = torch.Generator().manual_seed(10 * n + k)
    S = _spd_factor(g, 2, n=n)
    V = torch.randn(2, n, k, generator=g, dtype=torch.float64)
    up = chol_update(S, V)
    ref = torch.linalg.cholesky(S @ S.mT + V @ V.mT)
    torch.testing.assert_close(up, ref, rtol=0, atol=1e-12 * float(ref.abs().max()))
    down, ratio = chol_downdate_ex(up, V)
    torch.testing.assert_close(down, S, rtol=0, atol=1e-10 * float(S.abs().max()))
    assert torch.equal(down, down.tril())
    # the returned ratio is det(S' S'^T) / det(S S^T)
    det = lambda L: torch.diagonal(L, dim1=-2, dim2=-1).square().prod(-1)  # noqa: E731
    torch.testing.assert_close(ratio, det(S) / det(up), rtol=1e-9, atol=0)
    if k == 1:  # vector form
        torch.testing.assert_close(chol_downdate(up, V[..., 0]), down, rtol=0, atol=1e-13)


@pytest.mark.parametrize("k", [1, 6])
def test_downdate_to_an_indefinite_matrix_is_reported(k, path):
    S = torch.eye(3, dtype=torch.float64).expand(2, 3, 3).clone()
    V = torch.zeros(2, 3, k, dtype=torch.float64)
    V[0, :, 0] = torch.tensor([1.0, 1.0, 1.0])  # I - v v^T has eigenvalue -2
    V[1, :, 0] = torch.tensor([0.5, 0.0, 0.0])  # fine
    _, ratio = chol_downdate_ex(S, V)
    assert not bool(ratio[0] > 0) and bool(ratio[1] > 0)
    with pytest.raises(torch.linalg.LinAlgError, match="positive definite"):
        chol_downdate(S, V)


@pytest.mark.parametrize("m", [1, 3])
def test_cho_solve_right_equals_dense_solve(m):
    g = torch.Generator().manual_seed(m)
    S = _spd_factor(g, 4, n=m)
    B = torch.randn(4, 5, m, generator=g, dtype=torch.float64)
    ref = torch.linalg.solve(S @ S.mT, B.mT).mT
    torch.testing.assert_close(cho_solve_right(B, S), ref, rtol=1e-12, atol=1e-12)


def test_one_by_one_downdate_in_closed_form_and_its_failure():
    S = torch.tensor([[[2.0]], [[1.0]], [[3.0]]], dtype=torch.float64)
    V = torch.tensor([[[1.2, 1.0]], [[1.0, 0.5]], [[0.0, 0.0]]], dtype=torch.float64)
    S2, ratio = chol_downdate_ex(S, V)  # s'^2 = s^2 - sum v^2
    assert S2[0, 0, 0].item() == pytest.approx((4.0 - 1.44 - 1.0) ** 0.5, rel=1e-15)
    assert ratio[0].item() == pytest.approx(1.56 / 4.0, rel=1e-15)
    assert not bool(ratio[1] > 0)  # 1 - 1.25 < 0: reported, not raised
    assert S2[2, 0, 0].item() == 3.0 and ratio[2].item() == 1.0
    with pytest.raises(torch.linalg.LinAlgError, match="positive definite"):
        chol_downdate(S, V)


@pytest.mark.parametrize("shapes", [((5, 1, 1), (5, 1, 1)), ((3, 1), (4, 1, 2)), ((2, 3), (3, 4))])
def test_mm_equals_matmul(shapes):
    from prognos_torch.core.linalg import mm

    g = torch.Generator().manual_seed(0)
    A = torch.randn(*shapes[0], generator=g, dtype=torch.float64)
    B = torch.randn(*shapes[1], generator=g, dtype=torch.float64)
    assert torch.equal(mm(A, B), A @ B)


@pytest.mark.parametrize("n,k", [(1, 1), (5, 1), (20, 1), (20, 3)])
def test_downdate_with_the_callers_solve_equals_the_solved_one(n, k, path):
    # W = S^{-1} V handed over (the Kalman update knows it without a solve): the same factor
    # and ratio as with the solve, both against the Cholesky of the formed matrix
    g = torch.Generator().manual_seed(7 * n + k)
    S = _spd_factor(g, 3, n=n)
    W = 0.5 * torch.randn(3, n, k, generator=g, dtype=torch.float64) / (n * k) ** 0.5
    V = S @ W
    down, ratio = chol_downdate_ex(S, V)
    given, ratio_given = chol_downdate_ex(S, V, W)
    ref = torch.linalg.cholesky(S @ S.mT - V @ V.mT)
    for got in (down, given):
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-12 * float(ref.abs().max()))
    torch.testing.assert_close(ratio_given, ratio, rtol=1e-12, atol=0)


def test_update_of_a_singular_factor_is_the_cholesky_of_the_sum(path):
    # a factor with a zero on its diagonal (a tria of fewer columns than rows, a 1 x 1 zero):
    # the closed form's S^{-1} v does not exist there; the result is the QR's, not NaN
    from prognos_torch.core.linalg import safe_cholesky

    g = torch.Generator().manual_seed(11)
    S = torch.stack(
        [tria(torch.randn(4, 3, generator=g, dtype=torch.float64)), _spd_factor(g, n=4)]
    )
    S.requires_grad_(True)
    V = torch.randn(2, 4, 2, generator=g, dtype=torch.float64, requires_grad=True)
    up = chol_update(S, V)
    ref = safe_cholesky(S @ S.mT + V @ V.mT).detach()
    torch.testing.assert_close(up, ref, rtol=0, atol=1e-12 * float(ref.abs().max()))
    up.sum().backward()
    assert bool(torch.isfinite(S.grad).all()) and bool(torch.isfinite(V.grad).all())
    zero = torch.zeros(3, 1, 1, dtype=torch.float64)
    v = torch.tensor([[0.5], [-2.0], [0.0]], dtype=torch.float64)
    assert chol_update(zero, v).flatten().tolist() == [0.5, 2.0, 0.0]


def test_up_and_downdates_broadcast_a_shared_factor(path):
    g = torch.Generator().manual_seed(12)
    S = _spd_factor(g, n=4)  # one factor for a batch of 3 column blocks
    V = 0.3 * torch.randn(3, 4, 2, generator=g, dtype=torch.float64)
    ref = torch.linalg.cholesky(S @ S.mT + V @ V.mT)
    up = chol_update(S, V)
    torch.testing.assert_close(up, ref, rtol=0, atol=1e-12 * float(ref.abs().max()))
    down, ratio = chol_downdate_ex(up, V[:1])  # and a batch of factors, one block
    torch.testing.assert_close(down[0], S, rtol=0, atol=1e-10)
    assert ratio.shape == (3,)


def test_downdate_by_no_columns_is_the_identity(path):
    g = torch.Generator().manual_seed(13)
    S = _spd_factor(g, 2, n=5)
    down, ratio = chol_downdate_ex(S, S.new_zeros(2, 5, 0))
    assert torch.equal(down, S) and ratio.tolist() == [1.0, 1.0]
    assert torch.equal(chol_update(S, S.new_zeros(2, 5, 0)), S)


def test_tria_of_fewer_columns_than_rows_has_a_gradient():
    g = torch.Generator().manual_seed(14)
    A = torch.randn(2, 4, 2, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.equal(tria(A), tria(A.detach()))  # the values of the QR without autograd
    assert torch.autograd.gradcheck(tria, (A,))


def test_safe_cholesky_jitters_only_the_elements_that_need_it():
    from prognos_torch.core.linalg import safe_cholesky

    P = torch.stack([4.0 * torch.eye(2), torch.ones(2, 2)]).double()  # PD, singular
    L = safe_cholesky(P, jitter=1e-9)
    assert torch.equal(L[0], 2.0 * torch.eye(2, dtype=torch.float64))  # its exact factor
    torch.testing.assert_close(L[1] @ L[1].mT, P[1], rtol=0, atol=1e-7)


def test_mm_of_mismatched_shapes_fails_like_matmul():
    from prognos_torch.core.linalg import mm

    with pytest.raises(RuntimeError):
        mm(torch.ones(2, 1), torch.ones(2, 3))  # A @ B fails; A * B broadcast to (2, 3)
