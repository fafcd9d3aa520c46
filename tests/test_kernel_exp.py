"""core.kernel_exp.floored_exp: exp with its argument floored per dtype, in place where it may be."""

import warnings

import pytest
import torch
from torch.func import jacfwd, jacrev, vmap

from prognos_torch.core.kernel_exp import EXP_FLOORS, floored_exp
from prognos_torch.learners import ELM, LSSVR, LSSVRGram


def _z():
    # from the ordinary range through the subnormal range to values that underflow to 0
    return torch.linspace(-2000.0, 5.0, 4001, dtype=torch.float64)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.bfloat16])
def test_equals_exp_above_the_floor_and_exp_of_the_floor_below(dtype):
    z = _z().to(dtype)
    got = floored_exp(z.clone())
    above = z >= EXP_FLOORS[dtype]
    assert torch.equal(got[above], torch.exp(z[above]))  # bit for bit
    floor = torch.exp(torch.tensor(EXP_FLOORS[dtype], dtype=dtype))
    assert bool((got[~above] == floor).all()) and bool((~above).any())
    assert float((got - torch.exp(z)).abs().max()) <= float(floor)
    assert bool((got >= torch.finfo(dtype).tiny).all())  # never 0, never subnormal


def test_a_dtype_without_a_floor_gets_plain_exp():
    z = torch.linspace(-30.0, 5.0, 71, dtype=torch.float16)
    assert torch.float16 not in EXP_FLOORS
    assert torch.equal(floored_exp(z.clone()), torch.exp(z))
    assert torch.equal(floored_exp(z, out_of_place=True), torch.exp(z))


def test_in_place_only_where_allowed():
    z = _z()
    w = z.clone()
    assert floored_exp(w) is w  # autograd off for w: written in place
    w = z.clone()
    out = floored_exp(w, out_of_place=True)
    assert out is not w and torch.equal(w, z)
    zg = z.clone().requires_grad_()
    out = floored_exp(zg)
    assert out is not zg and torch.equal(zg.detach(), z)


def test_gradients_equal_exp_above_the_floor_and_zero_below():
    z = torch.tensor([-800.0, -3.0, 0.5], dtype=torch.float64, requires_grad=True)
    floored_exp(z).sum().backward()
    assert float(z.grad[0]) == 0.0  # below the floor: the floored value is a constant
    assert torch.equal(z.grad[1:], torch.exp(z.detach()[1:]))

    P = torch.randn(7, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def k(x, fn):
        return fn(-3.0 * ((x - P) ** 2).sum(-1))  # a fresh temporary, as in the kernels

    x = torch.randn(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # no slow vmap fallback for in-place ops
        for tr in (jacrev, jacfwd):
            a = vmap(tr(lambda xi: k(xi, floored_exp)))(x)
            b = vmap(tr(lambda xi: k(xi, torch.exp)))(x)
            assert torch.allclose(a, b, rtol=1e-15, atol=0)


@pytest.mark.parametrize("far", [0.0, 1e3])
def test_lssvr_kernels_equal_plain_exp_near_and_far_from_the_data(far):
    g = torch.Generator().manual_seed(2)
    X = torch.randn(80, 4, dtype=torch.float64, generator=g)
    y = torch.sin(X.sum(-1))
    m = LSSVR(kernel="rbf", sigma=0.3, C=100.0).fit(X, y)
    Xq = torch.randn(30, 4, dtype=torch.float64, generator=g) + far
    c = 1.0 / (2 * 0.3**2)
    K = torch.exp(-c * ((Xq[:, None, :] - X) ** 2).sum(-1))  # plain exp, underflowing far away
    ref = K @ m.alpha.reshape(80, -1) + m.b
    assert torch.allclose(m(Xq).reshape(ref.shape), ref, rtol=1e-12, atol=1e-300)
    assert torch.allclose(LSSVRGram(m)(Xq).reshape(ref.shape), ref, rtol=1e-12, atol=1e-300)


def test_elm_gaussian_activation_far_from_its_centres():
    elm = ELM(2, 20, 1, activation="gaussian", generator=torch.Generator().manual_seed(3))
    x = torch.tensor([[1e3, -1e3], [0.1, 0.2]], dtype=torch.float64)
    pre = x @ elm.a.mT + elm.b
    H = elm.hidden(x)
    assert torch.equal(H[1], torch.exp(-(pre[1] ** 2)))  # near: exp bit for bit
    assert float((H[0] - torch.exp(-(pre[0] ** 2))).abs().max()) < 1e-304  # far: floored
    assert bool((H >= torch.finfo(torch.float64).tiny).all())
