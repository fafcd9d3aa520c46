"""Learners' parameter-batched forward equals vmap over functional_call."""

import pytest
import torch
from torch.func import functional_call, vmap

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
