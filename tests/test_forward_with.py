"""Learners' parameter-batched forward equals vmap over functional_call."""

import pytest
import torch
from torch.func import functional_call, jacrev, vmap

from prognos_torch.learners import ANFIS, ELM
from prognos_torch.optim import ParameterBridge


def _vmap_reference(module, names, params, x):
    fixed = {k: v for k, v in module.named_parameters() if k not in names}

    def one(*ps):
        return functional_call(module, dict(zip(names, ps)) | fixed, (x,))

    flat = [params[k].reshape(-1, *params[k].shape[2:]) for k in names]
    out = vmap(one)(*flat)
    return out.reshape(*params[names[0]].shape[:2], *out.shape[1:])


@pytest.mark.parametrize(
    "module",
    [ANFIS(3, 2), ANFIS(2, 3, mf="gaussian", n_out=2), ANFIS(2, 2, mf="bell"), ELM(3, 7, n_out=2)],
)
def test_forward_with_equals_vmap(module):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(
        5,
        module.alpha.shape[1] - 1 if isinstance(module, ANFIS) else 3,
        generator=g,
        dtype=torch.float64,
    )
    names = [k for k, _ in module.named_parameters()]
    params = {
        k: p.detach() + 0.1 * torch.randn(4, 3, *p.shape, generator=g, dtype=torch.float64)
        for k, p in module.named_parameters()
    }
    if isinstance(module, ANFIS):
        params = {k: (v.abs() + 0.5 if k in ("sigma", "a") else v) for k, v in params.items()}
    ours = module.forward_with(params, x)
    ref = _vmap_reference(module, names, params, x)
    assert ours.shape == ref.shape == (4, 3, 5, module(x).shape[-1])
    assert torch.allclose(ours, ref, atol=1e-12)


def test_bridge_uses_fast_path_with_selected_subset():
    m = ELM(3, 6)
    bridge = ParameterBridge(m)  # beta only (a, b are fixed random features)
    g = torch.Generator().manual_seed(1)
    theta = torch.randn(10, bridge.numel, generator=g, dtype=torch.float64)
    x = torch.rand(4, 3, generator=g, dtype=torch.float64)
    fast = bridge.batched(theta, x)
    slow = bridge.batched(theta, x, chunk_size=3)  # chunked: the vmap path
    assert torch.allclose(fast, slow, atol=1e-12)


@pytest.mark.parametrize(
    "module",
    [
        ANFIS(3, 2),
        ANFIS(2, 3, mf="gaussian", n_out=2),
        ANFIS(2, 2, mf="bell"),
        ELM(3, 7, n_out=2),
        ELM(2, 5, activation="tanh"),
        ELM(2, 4, activation=torch.nn.functional.gelu),  # custom activation: g' by jvp
    ],
)
def test_closed_form_jacobian_equals_autodiff(module):
    """``forward_and_jacobian`` (hand-written back-propagation) against ``torch.func.jacrev``."""
    g = torch.Generator().manual_seed(3)
    n_in = module.alpha.shape[1] - 1 if isinstance(module, ANFIS) else module.n_in
    x = torch.rand(4, n_in, generator=g, dtype=torch.float64)
    names = [k for k, _ in module.named_parameters()]
    params = {
        k: p.detach() + 0.1 * torch.randn(3, *p.shape, generator=g, dtype=torch.float64)
        for k, p in module.named_parameters()
    }
    if isinstance(module, ANFIS):
        params = {k: (v.abs() + 0.5 if k in ("sigma", "a") else v) for k, v in params.items()}
    out, jac = module.forward_and_jacobian(params, x)
    assert torch.allclose(out, module.forward_with(params, x), rtol=0, atol=1e-14)
    for r in range(3):
        one = {k: v[r] for k, v in params.items()}
        ref = jacrev(lambda d: functional_call(module, d, (x,)))(one)
        for k in names:
            assert jac[k][r].shape == ref[k].shape
            assert torch.allclose(jac[k][r], ref[k], rtol=0, atol=1e-12), k
    # only the asked-for parameters
    _, part = module.forward_and_jacobian(params, x, names[-1:])
    assert list(part) == names[-1:]


@pytest.mark.parametrize(
    "module,select",
    [
        (ANFIS(3, 2), None),
        (ANFIS(3, 2), ["b"]),
        (ANFIS(3, 2), ["alpha"]),  # premises fixed: unbatched firing strengths
        (ANFIS(3, 2, n_out=2), ["alpha", "beta"]),
        (ELM(3, 6), None),  # beta only: unbatched hidden layer
        (ELM(3, 6, n_out=2), ["a", "beta"]),
    ],
)
def test_bridge_auto_jacobian_uses_the_closed_form(module, select):
    m = module
    bridge = ParameterBridge(m, select)
    g = torch.Generator().manual_seed(4)
    theta = bridge.flatten() + 0.05 * torch.randn(5, bridge.numel, generator=g, dtype=torch.float64)
    x = torch.rand(3, 3, generator=g, dtype=torch.float64)
    assert bridge.has_closed_form_jacobian(x)
    J = bridge.jacobian(theta, x)  # auto: closed form
    ref = bridge.jacobian(theta, x, mode="rev")
    n_out = m(x).shape[-1]
    assert J.shape == ref.shape == (5, 3 * n_out, bridge.numel)
    assert torch.allclose(J, ref, rtol=0, atol=1e-12)
    out, J2 = bridge.measurement_and_jacobian(theta, x)
    assert torch.equal(J2, J)
    assert torch.allclose(out, bridge.measurement(theta, x), rtol=0, atol=1e-14)


def test_bridge_reverse_mode_jacobian_works_under_inference_mode():
    """A filter run under torch.inference_mode may still ask for autograd Jacobians."""
    m = torch.nn.Linear(3, 2, dtype=torch.float64)  # no closed form: reverse mode
    bridge = ParameterBridge(m)
    g = torch.Generator().manual_seed(5)
    theta = bridge.flatten() + torch.randn(2, bridge.numel, generator=g, dtype=torch.float64)
    x = torch.rand(4, 3, generator=g, dtype=torch.float64)
    ref = bridge.jacobian(theta, x, mode="rev")
    with torch.inference_mode():
        J = bridge.jacobian(theta.clone(), x.clone())
        _, J2 = bridge.measurement_and_jacobian(theta.clone(), x.clone())
    assert torch.allclose(J, ref, rtol=0, atol=1e-14) and torch.allclose(
        J2, ref, rtol=0, atol=1e-14
    )
