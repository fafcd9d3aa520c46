"""Audit of the ELM / ROS-ELM (paper 000) and the fixed-size LS-SVR against exact references.

References: the ROS-ELM's Step I condition (paper 000: ``N0 >= L`` without regularisation) as
:meth:`ELM.init_online` states it; a NumPy implementation of the fixed-size LS-SVR's documented
Nystrom approximation (eigendecomposition of ``K_MM``, primal ridge with an unpenalised bias,
solved by ``numpy.linalg.lstsq``) on the support points the model selected.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prognos_torch.learners import ELM, FixedSizeLSSVR, ros_elm_init

F64 = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# --------------------------------------------------------------------------- ROS-ELM core
def test_ros_elm_init_without_regularisation_refuses_fewer_pairs_than_hidden_nodes():
    # N0 - p = 3 pairs, L = 4 nodes, lam = 0: H^T H has rank 3. Its Cholesky factor succeeded
    # on rounding and the state came back with K ~ 8e15 (beta 1.4), no error; ELM.init_online
    # refuses the same problem
    p, L = 2, 4
    elms = [ELM(p, L, activation="tanh", generator=_gen(0))]
    z0 = torch.randn(3 + p, 1, generator=_gen(1000), dtype=F64)
    with pytest.raises(ValueError, match=r"channel 0: .*N0 - p = 3 .*N0 - p >= L = 4"):
        ros_elm_init(elms, z0, p, 0.0)
    X, y = z0[:, 0].unfold(0, p, 1)[:-1], z0[p:, 0]  # the same 3 pairs
    with pytest.raises(ValueError, match=r"N0"):  # the module's own rule, for comparison
        ELM(p, L, activation="tanh", generator=_gen(0)).init_online(X, y, 0.0)
    # with regularisation the same data is a well-posed ridge problem; with enough pairs too
    st = ros_elm_init(elms, z0, p, 1e-3)
    assert float(st.K[0].abs().max()) < 1e4
    st = ros_elm_init(elms, torch.randn(L + p, 1, generator=_gen(3), dtype=F64), p, 0.0)
    assert st.n_seen == L


# --------------------------------------------------------------------------- fixed-size LS-SVR
def _np_fixed_size(X, Y, Z, sigma, C):
    """Module notes of lssvr_fixed, steps 2-4, in NumPy: ``(beta, b)`` on the support points."""

    def k(A, B):
        return np.exp(-((A[:, None, :] - B[None, :, :]) ** 2).sum(-1) / (2 * sigma**2))

    lam, U = np.linalg.eigh(k(Z, Z))
    keep = lam > lam[-1] * Z.shape[0] * np.finfo(float).eps
    W = U[:, keep] / np.sqrt(lam[keep])
    F = k(X, Z) @ W
    r, N = F.shape[1], X.shape[0]
    A = np.block([[F, np.ones((N, 1))], [np.eye(r) / np.sqrt(C), np.zeros((r, 1))]])
    rhs = np.vstack([Y, np.zeros((r, Y.shape[1]))])
    sol = np.linalg.lstsq(A, rhs, rcond=None)[0]
    return W @ sol[:r], sol[r]


@pytest.mark.parametrize("selection", ["renyi", "random"])
def test_fixed_size_below_n_is_the_documented_nystrom_ridge(selection):
    g = _gen(0)
    X = torch.rand(120, 2, generator=g, dtype=F64)
    Y = torch.stack([torch.sin(3 * X.sum(1)), X[:, 0] ** 2], 1)
    Y = Y + 0.05 * torch.randn(120, 2, generator=g, dtype=F64)
    sigma, C = 0.3, 20.0
    fs = FixedSizeLSSVR(
        sigma=sigma, C=C, n_support=15, n_out=2, selection=selection, generator=_gen(3)
    ).fit(X, Y)
    Z = fs.support_vectors.numpy()
    assert Z.shape == (15, 2) and len({tuple(z) for z in Z}) == 15
    beta, b = _np_fixed_size(X.numpy(), Y.numpy(), Z, sigma, C)
    np.testing.assert_allclose(fs.alpha.detach().numpy(), beta, rtol=0, atol=1e-9 * abs(beta).max())
    np.testing.assert_allclose(fs.b.detach().numpy(), b, rtol=0, atol=1e-10)
    # batched predictions equal row-by-row ones
    Xt = torch.rand(3, 4, 2, generator=g, dtype=F64)
    with torch.no_grad():
        batched = fs(Xt)
        rows = torch.stack([fs(x) for x in Xt.reshape(-1, 2)]).reshape(3, 4, 2)
    torch.testing.assert_close(batched, rows, rtol=0, atol=1e-14)


# --------------------------------------------------------------------------- ELM forward_with
def test_elm_forward_with_checks_parameter_names_and_shapes():
    # a misspelt name was ignored (the module's own beta used) and a b of shape (1,) was
    # broadcast over the hidden nodes: wrong outputs, no error (ANFIS refused both)
    elm = ELM(3, 4, n_out=2, generator=_gen(1))
    torch.nn.init.normal_(elm.beta, generator=_gen(2))
    x = torch.randn(5, 3, generator=_gen(3), dtype=F64)
    beta = torch.randn(6, 4, 2, generator=_gen(4), dtype=F64)  # 6 parameter sets
    out = elm.forward_with({"beta": beta}, x)
    ref = torch.sigmoid(x @ elm.a.detach().T + elm.b.detach()) @ beta  # Eq. 47-48
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match=r"params has no ELM parameter 'bta'; expected any of"):
        elm.forward_with({"bta": beta}, x)
    with pytest.raises(ValueError, match=r"params\['b'\] must have shape \(\.\.\., 4\), got \(1,\)"):
        elm.forward_with({"b": torch.zeros(1, dtype=F64)}, x)
    with pytest.raises(ValueError, match=r"params\['beta'\] must have shape \(\.\.\., 4, 2\)"):
        elm.forward_and_jacobian({"beta": beta.mT}, x)
    with pytest.raises(TypeError, match="params must be a dict of tensors"):
        elm.forward_with([beta], x)
