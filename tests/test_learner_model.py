"""Tests of prognos_torch.prognosis.learner_model: learners as m-order transition models
(paper 002 Eq. 15-26).

References are independent: central finite differences, paper 002 Eq. 25 written out, and the
learner's own online update.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.func import vmap

from prognos_torch.core.model import StateSpaceModel
from prognos_torch.datasets.windows import embed
from prognos_torch.learners import ELM
from prognos_torch.prognosis import learner_transition_model

sys.path.insert(0, str(Path(__file__).parent))
from _prognosis_helpers import F64, _gen, _learner, _series  # noqa: E402


def _fd_jacobian(model: StateSpaceModel, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Central differences of the (noise-free) transition at each row of ``x`` ``(B, n)``."""
    cols = []
    for j in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[:, j] = eps
        cols.append(
            (model.transition(x + e, None, 1) - model.transition(x - e, None, 1)) / (2 * eps)
        )
    return torch.stack(cols, dim=-1)


# =============================================================================== learner as model
@pytest.mark.parametrize(
    "kind,jacobian",
    [
        ("elm", "autograd"),
        ("elm", "engine"),
        ("lssvr", "autograd"),
        ("lssvr", "engine"),
        ("lssvr", "input_gradient"),
        ("anfis", "autograd"),
        ("anfis", "engine"),
    ],
)
def test_transition_jacobian_matches_finite_differences(kind, jacobian):
    learner, X = _learner(kind)
    model = learner_transition_model(learner, 4, 0.01, 0.02, jacobian=jacobian)
    x = X[::17][:6] + 0.05 * torch.randn(6, 4, generator=_gen(2), dtype=F64)
    J = model.transition_jacobian(x, None, 1)
    assert J.shape == (6, 4, 4)
    torch.testing.assert_close(J, _fd_jacobian(model, x), rtol=1e-6, atol=1e-8)
    # batch dims are carried through
    J2 = model.transition_jacobian(x.reshape(2, 3, 4), None, 1)
    torch.testing.assert_close(J2.reshape(6, 4, 4), J)
    # the state transition shifts the window and appends the learner's prediction (Eq. 18-19)
    fx = model.transition(x, None, 1)
    torch.testing.assert_close(fx[:, :3], x[:, 1:])
    torch.testing.assert_close(fx[:, 3], learner(x)[:, 0].detach())
    torch.testing.assert_close(model.observe(x, None, 1), x[:, 3:])


def test_lssvr_rbf_jacobian_is_paper_002_eq_20_to_26():
    lssvr, X = _learner("lssvr")
    model = learner_transition_model(lssvr, 4, 0.01, 0.02)  # autograd route, default
    P = X[5:40:7]
    J = model.transition_jacobian(P, None, 1)
    # Eq. 25 written out: sum_i alpha_i exp(-|P_s - P_i|^2 / (2 sigma^2)) (-1/sigma^2) (P_s - P_i)
    sv = lssvr.support_vectors.numpy()
    alpha = lssvr.alpha.detach().numpy()[:, 0]
    sig2 = float(lssvr.sigma) ** 2
    eq25 = []
    for p in P.numpy():
        d = p[None, :] - sv
        k = np.exp(-(d * d).sum(1) / (2 * sig2))
        eq25.append(((alpha * k)[:, None] * (-1.0 / sig2) * d).sum(0))
    eq25 = torch.tensor(np.array(eq25))
    torch.testing.assert_close(J[:, -1, :], eq25, rtol=1e-9, atol=1e-12)  # Eq. 21/25
    torch.testing.assert_close(J[:, -1, :], lssvr.input_gradient(P)[:, 0, :].detach())
    torch.testing.assert_close(J[:, -1, -1], eq25[:, -1])  # Eq. 23/26: df / dx_s
    shift = torch.eye(4, dtype=F64)[1:].expand(P.shape[0], 3, 4)
    torch.testing.assert_close(J[:, :-1, :], shift)  # companion structure


def test_transition_model_is_vmap_friendly_and_noise_structure():
    for kind in ("elm", "lssvr", "anfis"):
        learner, X = _learner(kind)
        model = learner_transition_model(learner, 4, 0.03, 0.02)
        x = X[:7]
        per_sample = vmap(lambda xi, mdl=model: mdl.f(xi, None, 1))(x)
        torch.testing.assert_close(per_sample, model.transition(x, None, 1))
        assert not model.transition(x, None, 1).requires_grad  # detached learner parameters
    noise = model.noise(1)
    want = torch.zeros(4, 4, dtype=F64)
    want[-1, -1] = 0.03  # Eq. 19: noise on the new element only
    torch.testing.assert_close(noise.chol_Q, want)
    torch.testing.assert_close(noise.chol_R, torch.full((1, 1), 0.02, dtype=F64))
    full = torch.diag(torch.tensor([1e-3, 1e-3, 1e-3, 0.03], dtype=F64))
    torch.testing.assert_close(
        learner_transition_model(learner, 4, full, 0.02).noise(1).chol_Q, full
    )


def test_transition_model_sees_online_updates():
    X, y = embed(_series(), 3)
    elm = ELM(3, 20, generator=_gen(4)).init_online(X[:40], y[:40], 1e-4)
    model = learner_transition_model(elm, 3, 0.01, 0.01)
    before = model.transition(X[50:52], None, 1)[:, -1]
    elm.partial_fit(X[40:80], y[40:80])
    after = model.transition(X[50:52], None, 1)[:, -1]
    torch.testing.assert_close(after, elm(X[50:52])[:, 0].detach())
    assert not torch.allclose(before, after)


def test_bad_transition_model_arguments_raise_clear_errors():
    elm, X = _learner("elm")
    with pytest.raises(ValueError, match="does not match the learner's input dimension"):
        learner_transition_model(elm, 3, 0.01, 0.01)
    with pytest.raises(ValueError, match="chol_Q"):
        learner_transition_model(elm, 4, -0.1, 0.01)
    with pytest.raises(ValueError, match=r"chol_Q must be a number \(std\) or have shape"):
        learner_transition_model(elm, 4, torch.eye(3, dtype=F64), 0.01)
    with pytest.raises(ValueError, match="jacobian"):
        learner_transition_model(elm, 4, 0.01, 0.01, jacobian="numeric")
    with pytest.raises(TypeError, match="input_gradient"):
        learner_transition_model(elm, 4, 0.01, 0.01, jacobian="input_gradient")
    with pytest.raises(ValueError, match="n_out_index"):
        learner_transition_model(elm, 4, 0.01, 0.01, n_out_index=1)


def test_transition_model_shift_std_gives_a_nonsingular_Q():
    elm = ELM(3, 5, generator=torch.Generator().manual_seed(0))
    plain = learner_transition_model(elm, 3, 0.2, 0.1).noise(1).chol_Q
    shifted = learner_transition_model(elm, 3, 0.2, 0.1, shift_std=0.01).noise(1).chol_Q
    assert torch.equal(plain, torch.diag(torch.tensor([0.0, 0.0, 0.2], dtype=plain.dtype)))
    assert torch.equal(shifted, torch.diag(torch.tensor([0.01, 0.01, 0.2], dtype=plain.dtype)))
    with pytest.raises(ValueError, match="shift_std"):
        learner_transition_model(elm, 3, torch.eye(3, dtype=plain.dtype), 0.1, shift_std=0.01)
    with pytest.raises(ValueError, match="shift_std"):
        learner_transition_model(elm, 3, 0.2, 0.1, shift_std=-1.0)


def test_window_belief_is_the_measured_window_before_end():
    from prognos_torch.prognosis import window_belief

    z = torch.arange(10, dtype=torch.float64) / 10
    b = window_belief(z, 6, 4, 0.5)
    assert torch.equal(b.mean, torch.tensor([0.2, 0.3, 0.4, 0.5], dtype=torch.float64))
    assert torch.equal(b.chol, 0.5 * torch.eye(4, dtype=torch.float64))
    br = window_belief(z, 4, 4, torch.tensor(0.25, dtype=torch.float64), runs=3)
    assert br.mean.shape == (3, 4) and br.chol.shape == (3, 4, 4)
    assert torch.equal(br.mean, z[:4].expand(3, 4))
    assert torch.equal(br.chol, 0.25 * torch.eye(4, dtype=torch.float64).expand(3, 4, 4))
    br.mean[0, 0] = 7.0  # a copy: the series is untouched
    assert float(z[0]) == 0.0
    for bad, match in (((z, 3, 4, 0.1), "end"), ((z, 11, 4, 0.1), "end"), ((z, 6, 4, -1.0), "std")):
        with pytest.raises(ValueError, match=match):
            window_belief(*bad)
    with pytest.raises(ValueError, match="series"):
        window_belief(z[None], 6, 4, 0.1)
