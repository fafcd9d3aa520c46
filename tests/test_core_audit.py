"""Audit of GaussianBelief and StateSpaceModel against exact references and for clear errors."""

import numpy as np
import pytest
import torch

from prognos_torch.core.belief import GaussianBelief
from prognos_torch.core.model import StateSpaceModel, linear_gaussian_model

F64 = torch.float64


def _t(x):
    return torch.as_tensor(x, dtype=F64)


def test_from_cov_two_batch_dims_matches_numpy():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((2, 3, 4, 4))
    C = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
    b = GaussianBelief.from_cov(_t(rng.standard_normal((2, 3, 4))), _t(C))
    np.testing.assert_allclose(b.cov.numpy(), C, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(b.chol.numpy(), np.linalg.cholesky(C), rtol=1e-12, atol=1e-13)
    assert b[..., 1].chol.shape == (2, 4, 4)
    np.testing.assert_allclose(b[..., 1].cov.numpy(), C[:, 1], rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("cov", [torch.ones(2), torch.tensor(2.0), torch.ones(2, 3)])
def test_from_cov_bad_shape_is_value_error(cov):
    # was a RuntimeError from torch (tensor.mT / cholesky / broadcasting)
    with pytest.raises(ValueError, match=r"cov \(\.\.\., n, n\)"):
        GaussianBelief.from_cov(torch.zeros(2, dtype=F64), cov.to(F64))


def test_from_cov_asymmetry_judged_per_matrix_of_the_batch():
    # a large matrix in the batch used to widen the symmetry tolerance of all of them, so
    # an asymmetric [[1, 0.500001], [0.5, 1]] was silently symmetrised
    cov = torch.stack([1e8 * torch.eye(2, dtype=F64), _t([[1.0, 0.5 + 1e-6], [0.5, 1.0]])])
    with pytest.raises(ValueError, match="symmetric"):
        GaussianBelief.from_cov(torch.zeros(2, 2, dtype=F64), cov)
    ok = torch.stack([1e8 * torch.eye(2, dtype=F64), _t([[1.0, 0.5], [0.5, 1.0]])])
    b = GaussianBelief.from_cov(torch.zeros(2, 2, dtype=F64), ok)
    torch.testing.assert_close(b.cov, ok, rtol=1e-15, atol=0)


def test_from_cov_nan_names_non_finite():
    with pytest.raises(ValueError, match="non-finite"):
        GaussianBelief.from_cov(torch.zeros(2, dtype=F64), _t([[float("nan"), 0], [0, 1]]))


def test_expand_batched_belief_bad_shape_is_value_error():
    b = GaussianBelief(torch.zeros(2, 3, dtype=F64), torch.eye(3, dtype=F64).expand(2, 3, 3))
    assert b.expand(5, 2).mean.shape == (5, 2, 3)
    with pytest.raises(ValueError, match="batch_shape"):
        b.expand(5)


def _nonlinear(batched):
    def f(x, u, k):
        return torch.stack(
            [
                torch.sin(x[..., 0]) * x[..., 1] + k * u[..., 0],
                x[..., 1] ** 2 + torch.exp(0.1 * x[..., 2]) * u[..., 1],
                x[..., 0] * x[..., 2],
            ],
            -1,
        )

    def h(x, u, k):
        return torch.stack([x[..., 0] * x[..., 1], torch.cos(x[..., 2]) + u[..., 0]], -1)

    eye = torch.eye(3, dtype=F64)
    return StateSpaceModel(f, h, 3, 2, eye, eye[:2, :2], control_dim=2, batched=batched)


def test_jacobians_match_finite_differences_and_loops():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(4, 5, 3, dtype=F64, generator=g)
    u = torch.randn(4, 5, 2, dtype=F64, generator=g)
    per, bat = _nonlinear(False), _nonlinear(True)
    k, eps = 3, 1e-6
    for fn, jac in ((bat.transition, "transition_jacobian"), (bat.observe, "observation_jacobian")):
        cols = []
        for j in range(3):
            e = torch.zeros(3, dtype=F64)
            e[j] = eps
            cols.append((fn(x + e, u, k) - fn(x - e, u, k)) / (2 * eps))
        fd = torch.stack(cols, -1)
        for mod in (per, bat):
            J = getattr(mod, jac)(x, u, k)
            assert J.shape == fd.shape
            torch.testing.assert_close(J, fd, rtol=0, atol=1e-8)
    loop = torch.stack([per.f(xi, ui, k) for xi, ui in zip(x.reshape(-1, 3), u.reshape(-1, 2))])
    torch.testing.assert_close(per.transition(x, u, k), loop.reshape(4, 5, 3), rtol=0, atol=0)


def test_scalar_per_sample_output_is_value_error():
    eye = torch.eye(2, dtype=F64)
    mod = StateSpaceModel(None, lambda x, u, k: x[0] * x[1], 2, 1, eye, eye[:1, :1])
    with pytest.raises(ValueError, match="model.h returned shape"):
        mod.observe(torch.ones(4, 2, dtype=F64), None, 1)  # was a RuntimeError of reshape


def test_analytic_jacobian_of_wrong_shape_is_value_error():
    eye = torch.eye(3, dtype=F64)
    mod = StateSpaceModel(
        lambda x, u, k: x, lambda x, u, k: x[:2], 3, 2, eye, eye[:2, :2],
        jac_h=lambda x, u, k: torch.eye(3, dtype=F64),
    )  # fmt: skip
    with pytest.raises(ValueError, match="jac_h"):  # was returned as (4, 3, 3)
        mod.observation_jacobian(torch.ones(4, 3, dtype=F64), None, 1)


@pytest.mark.parametrize(
    "F, H, B",
    [
        (torch.eye(3), torch.ones(2, 4), None),
        (torch.ones(3, 4), torch.ones(2, 3), None),
        (torch.eye(3), torch.ones(2, 3), torch.ones(4, 2)),
        (torch.eye(3).expand(2, 3, 3), torch.ones(2, 3), None),
    ],
)
def test_linear_gaussian_model_bad_shapes_are_value_errors(F, H, B):
    with pytest.raises(ValueError, match="linear_gaussian_model"):
        linear_gaussian_model(F.to(F64), H.to(F64), torch.eye(3), torch.eye(2), B=B)


def test_linear_gaussian_model_with_controls_and_callable_noise():
    g = torch.Generator().manual_seed(2)
    F, H, B = (torch.randn(s, dtype=F64, generator=g) for s in ((3, 3), (2, 3), (3, 2)))
    q = torch.randn(3, dtype=F64, generator=g)
    mod = linear_gaussian_model(F, H, lambda k: k * torch.eye(3, dtype=F64), torch.eye(2), B=B,
                                q=lambda k: k * q)  # fmt: skip
    x = torch.randn(4, 5, 3, dtype=F64, generator=g)
    u = torch.randn(2, dtype=F64, generator=g)
    torch.testing.assert_close(mod.transition(x, u, 1), x @ F.T + u @ B.T, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(mod.observation_jacobian(x, u, 1), H.expand(4, 5, 2, 3))
    nz = mod.checked_noise(3, (4, 5), x)
    assert torch.equal(nz.q, 3 * q) and torch.equal(nz.chol_Q, 3 * torch.eye(3, dtype=F64))
    with pytest.raises(ValueError, match="pass u"):
        mod.transition(x, None, 1)
