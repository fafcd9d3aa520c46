"""Fault probability and RUL distribution against direct counts, SciPy and known failure times."""

import math

import numpy as np
import pytest
import torch
from scipy import stats

from prognos_torch.metrics import probability_in_bounds
from prognos_torch.prognosis import (
    RULDistribution,
    fault_probability,
    fault_probability_gaussian,
    rul_distribution,
)

F64 = torch.float64


# --------------------------------------------------------------------------- fault probability
def test_fault_probability_matches_direct_count():
    g = torch.Generator().manual_seed(1)
    samples = torch.randn(2, 5, 4, generator=g, dtype=F64)
    w = torch.rand(2, 5, generator=g, dtype=F64)
    w = w / w.sum(-1, keepdim=True)
    thr = 0.3
    got = fault_probability(samples, thr, w)
    got_below = fault_probability(samples, thr, w, direction="below")
    s, wn = samples.numpy(), w.numpy()
    for b in range(2):
        for j in range(4):
            above = sum(wn[b, i] for i in range(5) if s[b, i, j] >= thr)
            below = sum(wn[b, i] for i in range(5) if s[b, i, j] <= thr)
            assert got[b, j].item() == pytest.approx(above, abs=1e-15)
            assert got_below[b, j].item() == pytest.approx(below, abs=1e-15)
    # Uniform weights: the fraction of paths at or above the threshold.
    x = torch.tensor([[1.0, 0.0], [2.0, 3.0], [0.5, 0.5], [0.0, 1.0]])  # (N=4, H=2)
    torch.testing.assert_close(fault_probability(x, 1.0), torch.tensor([0.5, 0.5], dtype=F64))


def test_fault_probability_gaussian_matches_scipy():
    g = torch.Generator().manual_seed(2)
    mean = torch.randn(3, 6, generator=g, dtype=F64)
    std = 0.1 + torch.rand(3, 6, generator=g, dtype=F64)
    thr = 0.2
    ref_above = stats.norm.sf(thr, loc=mean.numpy(), scale=std.numpy())
    ref_below = stats.norm.cdf(thr, loc=mean.numpy(), scale=std.numpy())
    np.testing.assert_allclose(
        fault_probability_gaussian(mean, std, thr).numpy(), ref_above, rtol=1e-12, atol=1e-15
    )
    np.testing.assert_allclose(
        fault_probability_gaussian(mean, std, thr, direction="below").numpy(),
        ref_below,
        rtol=1e-12,
        atol=1e-15,
    )
    # Zero std: the point prediction's indicator (threshold reached counts as failure).
    p0 = fault_probability_gaussian(torch.tensor([0.0, 0.2, 0.5]), torch.zeros(3), 0.2)
    torch.testing.assert_close(p0, torch.tensor([0.0, 1.0, 1.0], dtype=F64))


def test_gaussian_and_sample_fault_probability_agree():
    # Many Gaussian samples: Monte Carlo estimate within 4 binomial standard errors.
    g = torch.Generator().manual_seed(3)
    n = 20000
    mean = torch.tensor([0.0, 0.5, 1.0], dtype=F64)
    std = torch.tensor([1.0, 0.5, 0.2], dtype=F64)
    samples = mean + std * torch.randn(n, 3, generator=g, dtype=F64)
    p_mc = fault_probability(samples, 0.8)
    p = fault_probability_gaussian(mean, std, 0.8)
    assert bool(((p_mc - p).abs() <= 4 * torch.sqrt(p * (1 - p) / n) + 1e-12).all())


# --------------------------------------------------------------------------- RUL: worked example
def test_rul_distribution_worked_example():
    # Threshold 2.5, dt = 0.5. First passages (1-based): p0 -> 4, p1 -> 1, p2 never, p3 -> 3.
    x = torch.tensor(
        [
            [0.0, 1.0, 2.0, 3.0, 4.0],
            [3.0, 0.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 2.5, 0.0, 0.0],
        ],
        dtype=F64,
    )
    w = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=F64)
    d = rul_distribution(x, 2.5, w, dt=0.5)
    assert isinstance(d, RULDistribution)
    assert d.first_passage.tolist() == [4, 1, -1, 3]
    assert d.path_censored.tolist() == [False, False, True, False]
    torch.testing.assert_close(d.pmf, torch.tensor([0.2, 0.0, 0.4, 0.1, 0.0], dtype=F64))
    assert d.censored_mass.item() == pytest.approx(0.3)
    torch.testing.assert_close(d.support, torch.tensor([0.5, 1.0, 1.5, 2.0, 2.5], dtype=F64))
    # Censored mass 0.3 > tol = 0: no expectation, explicit lower bound RUL > H dt.
    assert bool(d.censored) and math.isnan(d.expectation.item()) and math.isnan(d.mean.item())
    assert d.rul_lower_bound == 2.5
    path_rul = d.path_rul
    assert math.isnan(path_rul[2].item())
    torch.testing.assert_close(path_rul[[0, 1, 3]], torch.tensor([2.0, 0.5, 1.5], dtype=F64))
    # cdf = 0.2, 0.2, 0.6, 0.7, 0.7: median 1.5; 0.75 lies beyond the horizon.
    assert d.median.item() == pytest.approx(1.5)
    q = d.quantile([0.1, 0.7, 0.75])
    assert q[0].item() == pytest.approx(0.5) and q[1].item() == pytest.approx(2.0)
    assert math.isnan(q[2].item())
    # With tol = 0.3 the conditional expectation over the crossing paths (Eq. 28) is given.
    d2 = rul_distribution(x, 2.5, w, dt=0.5, tol=0.3)
    expected = (0.2 * 0.5 + 0.4 * 1.5 + 0.1 * 2.0) / 0.7
    assert not bool(d2.censored)
    assert d2.expectation.item() == pytest.approx(expected, rel=1e-14)


def test_expectation_is_eq28_when_every_path_crosses():
    g = torch.Generator().manual_seed(4)
    n, h = 50, 30
    slopes = 0.2 + torch.rand(n, generator=g, dtype=F64)
    x = slopes[:, None] * torch.arange(1, h + 1, dtype=F64)
    w = torch.rand(n, generator=g, dtype=F64)
    w = w / w.sum()
    d = rul_distribution(x, 5.0, w, dt=2.0)
    assert d.censored_mass.item() == 0.0 and not bool(d.censored)
    # Eq. 28: RUL = sum_i l^i w^i with l^i = dt * first passage.
    eq28 = sum(2.0 * int(fp) * wi for fp, wi in zip(d.first_passage.tolist(), w.tolist()))
    assert d.expectation.item() == pytest.approx(eq28, rel=1e-13)


# --------------------------------------------------------------------------- RUL: synthetic
def test_linear_degradation_known_failure_time():
    # x(t) = v t + noise, failure when x >= 1 -> T_f = 1 / v = 10 (step 20 with dt = 0.5).
    g = torch.Generator().manual_seed(5)
    n, h, dt, v = 2000, 40, 0.5, 0.1
    t = dt * torch.arange(1, h + 1, dtype=F64)
    x = v * t + 0.01 * torch.randn(n, h, generator=g, dtype=F64)
    d = rul_distribution(x, 1.0, dt=dt)
    assert d.censored_mass.item() == 0.0
    assert d.pmf.sum().item() == pytest.approx(1.0, abs=1e-12)
    assert abs(d.expectation.item() - 10.0) < dt
    assert abs(d.median.item() - 10.0) <= dt


def test_random_slopes_pmf_equals_analytic_first_passage():
    # Noise-free paths x_i(j dt) = v_i j dt: first passage step = ceil(c / (v_i dt)).
    rng = np.random.default_rng(6)
    n, h, dt, c = 500, 60, 0.25, 3.0
    v = rng.uniform(0.15, 1.0, size=n)
    x = v[:, None] * dt * np.arange(1, h + 1)
    steps = np.ceil(c / (v * dt)).astype(int)
    d = rul_distribution(torch.from_numpy(x), c, dt=dt)
    ref_pmf = np.bincount(steps, minlength=h + 2)[1 : h + 1] / n
    np.testing.assert_allclose(d.pmf.numpy(), ref_pmf, atol=1e-15)
    assert d.censored_mass.item() == pytest.approx(np.mean(steps > h), abs=1e-15)
    censored = np.mean(steps > h)
    assert 0.0 < censored < 0.5  # slow paths run past the horizon: no expectation at tol = 0
    assert math.isnan(d.expectation.item())
    d_tol = rul_distribution(torch.from_numpy(x), c, dt=dt, tol=0.5)
    cond_mean = dt * steps[steps <= h].mean()
    assert d_tol.expectation.item() == pytest.approx(cond_mean, rel=1e-13)
    assert d_tol.median.item() == pytest.approx(dt * np.sort(steps)[(n - 1) // 2], rel=1e-13)


def test_exponential_degradation_below_threshold_with_batch():
    # Health index decays, h(t) = exp(-b t); failure when h <= 0.2 -> T_f = ln 5 / b.
    g = torch.Generator().manual_seed(7)
    n, h, dt = 1000, 80, 0.1
    b = torch.tensor([0.5, 1.0], dtype=F64)
    t = dt * torch.arange(1, h + 1, dtype=F64)
    noise = 0.003 * torch.randn(2, n, h, generator=g, dtype=F64)
    x = torch.exp(-b[:, None, None] * t) + noise
    d = rul_distribution(x, 0.2, dt=dt, direction="below")
    assert d.pmf.shape == (2, h) and d.first_passage.shape == (2, n)
    torch.testing.assert_close(d.pmf.sum(-1) + d.censored_mass, torch.ones(2, dtype=F64))
    # T_f = 3.22 and 1.61, both within the horizon H dt = 8.
    t_f = math.log(5.0) / b
    assert bool((d.expectation - t_f).abs().lt(2 * dt).all())


def test_censored_when_threshold_never_reached():
    x = torch.linspace(0.0, 1.0, 10, dtype=F64).expand(3, 10)
    d = rul_distribution(x, 5.0, dt=1.0)
    assert d.censored_mass.item() == pytest.approx(1.0)
    assert bool(d.censored) and math.isnan(d.expectation.item())
    assert math.isnan(d.median.item())
    assert d.first_passage.tolist() == [-1, -1, -1]
    assert d.pmf.abs().sum().item() == 0.0
    assert d.rul_lower_bound == 10.0
    # Even a positive tolerance never turns an all-censored set into a number.
    assert math.isnan(rul_distribution(x, 5.0, tol=0.5).expectation.item())


def test_rul_pmf_feeds_probability_in_bounds():
    g = torch.Generator().manual_seed(8)
    x = torch.randn(4, 200, 15, generator=g, dtype=F64).cumsum(-1)
    d = rul_distribution(x, 2.0, dt=0.5)
    lo = torch.tensor([0.5, 1.0, 2.0, 0.0], dtype=F64)
    hi = torch.tensor([3.0, 4.0, 7.5, 20.0], dtype=F64)
    got = probability_in_bounds(lo, hi, rul_pmf=d.pmf, rul_support=d.support)
    r = d.path_rul.numpy()  # NaN (censored) compares False: outside any finite bounds
    ref = [np.mean((r[i] >= lo[i].item()) & (r[i] <= hi[i].item())) for i in range(4)]
    np.testing.assert_allclose(got.numpy(), ref, atol=1e-15)


def test_float32_inputs_give_float64_results():
    x = torch.tensor([[0.0, 1.0, 2.0], [0.0, 0.0, 3.0]], dtype=torch.float32)
    w = torch.tensor([0.25, 0.75], dtype=torch.float32)
    d = rul_distribution(x, 1.5, w)
    assert d.pmf.dtype == F64 and d.expectation.dtype == F64
    assert d.expectation.item() == pytest.approx(0.25 * 3 + 0.75 * 3)
    assert fault_probability(x, 1.5, w).dtype == F64


# --------------------------------------------------------------------------- validation
@pytest.mark.parametrize("thr", [math.nan, math.inf, -math.inf, torch.tensor(math.nan)])
def test_invalid_threshold(thr):
    with pytest.raises(ValueError, match="threshold"):
        fault_probability(torch.zeros(3, 4), thr)
    with pytest.raises(ValueError, match="threshold"):
        rul_distribution(torch.zeros(3, 4), thr)
    with pytest.raises(ValueError, match="threshold"):
        fault_probability_gaussian(torch.zeros(4), torch.ones(4), thr)


def test_invalid_shapes_and_horizon():
    with pytest.raises(ValueError, match="horizon"):
        rul_distribution(torch.zeros(3, 0), 1.0)
    with pytest.raises(ValueError, match="samples"):
        fault_probability(torch.zeros(5), 1.0)
    with pytest.raises(ValueError, match="weights"):
        fault_probability(torch.zeros(2, 3, 4), 1.0, torch.full((3,), 1 / 3))
    with pytest.raises(ValueError, match="std"):
        fault_probability_gaussian(torch.zeros(4), torch.ones(3), 1.0)
    with pytest.raises(ValueError, match="std"):
        fault_probability_gaussian(torch.zeros(4), -torch.ones(4), 1.0)
    with pytest.raises(ValueError, match="direction"):
        fault_probability(torch.zeros(3, 4), 1.0, direction="up")
    with pytest.raises(ValueError, match="dt"):
        rul_distribution(torch.zeros(3, 4), 1.0, dt=0.0)
    with pytest.raises(ValueError, match="tol"):
        rul_distribution(torch.zeros(3, 4), 1.0, tol=1.0)
    with pytest.raises(ValueError, match="samples"):
        rul_distribution(torch.tensor([[0.0, math.nan]]), 1.0)


@pytest.mark.parametrize(
    ("weights", "message"),
    [
        (torch.tensor([0.5, 0.4, 0.0], dtype=F64), "sum to one"),
        (torch.tensor([0.6, 0.6, -0.2], dtype=F64), "non-negative"),
        (torch.full((3,), math.nan, dtype=F64), "all NaN"),
        (torch.zeros(3, dtype=F64), "all zero"),
        (torch.tensor([0.5, math.nan, 0.5], dtype=F64), "NaN or inf"),
        (torch.tensor([1, 0, 0]), "floating"),
    ],
)
def test_invalid_weights(weights, message):
    with pytest.raises((ValueError, TypeError), match=message):
        rul_distribution(torch.zeros(3, 4), 1.0, weights)
    with pytest.raises((ValueError, TypeError), match=message):
        fault_probability(torch.zeros(3, 4), 1.0, weights)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    g = torch.Generator().manual_seed(9)
    x = torch.randn(3, 100, 20, generator=g, dtype=F64).cumsum(-1)
    w = torch.rand(3, 100, generator=g, dtype=F64)
    w = w / w.sum(-1, keepdim=True)
    d_cpu = rul_distribution(x, 2.0, w, dt=0.5, tol=0.5)
    d_gpu = rul_distribution(x.cuda(), 2.0, w.cuda(), dt=0.5, tol=0.5)
    assert d_gpu.pmf.is_cuda
    torch.testing.assert_close(d_gpu.pmf.cpu(), d_cpu.pmf)
    torch.testing.assert_close(d_gpu.expectation.cpu(), d_cpu.expectation, equal_nan=True)
    torch.testing.assert_close(d_gpu.quantile([0.25, 0.5]).cpu(), d_cpu.quantile([0.25, 0.5]))
    torch.testing.assert_close(
        fault_probability(x.cuda(), 2.0, w.cuda()).cpu(), fault_probability(x, 2.0, w)
    )


def test_scalars_text_and_complex_samples():
    S = torch.zeros(4, 5, dtype=torch.float64)
    with pytest.raises(TypeError, match="threshold must be a real number, got the text '1'"):
        rul_distribution(S, "1")  # (float("1") took the text)
    with pytest.raises(TypeError, match="samples must be real, got dtype torch.complex64"):
        rul_distribution(torch.ones(2, 3, dtype=torch.complex64), 1.0)
    a = rul_distribution(S + torch.arange(5.0, dtype=torch.float64), 2.5, dt=np.float32(2.0))
    b = rul_distribution(S + torch.arange(5.0, dtype=torch.float64), 2.5, dt=2.0)
    assert a.dt == 2.0 and torch.equal(a.pmf, b.pmf)
    for x, y in zip(a.binned(np.int64(2)), b.binned(2)):
        assert torch.equal(x, y)


def test_particle_and_gaussian_bands_agree_once_the_particles_carry_the_measurement_noise():
    from prognos_torch.core import GaussianBelief, linear_gaussian_model
    from prognos_torch.prognosis import fault_probability_gaussian, particle_paths, predict_paths

    f = torch.float64
    model = linear_gaussian_model(torch.eye(1, dtype=f), torch.eye(1, dtype=f),
                                  torch.eye(1, dtype=f) * 0.3, torch.eye(1, dtype=f) * 0.5,
                                  q=torch.tensor([0.1], dtype=f))  # fmt: skip
    b = GaussianBelief(torch.zeros(1, dtype=f), torch.eye(1, dtype=f) * 0.4)
    gp = predict_paths(model, b, 10, method="gaussian")
    sp = predict_paths(model, b, 10, method="particle", n_particles=40_000,
                       generator=torch.Generator().manual_seed(0), measurement_noise=True)  # fmt: skip
    pg = float(fault_probability_gaussian(gp.mean, gp.std, 2.0)[-1])  # exact: 0.1911
    ps = float(fault_probability(sp.samples, 2.0, sp.weights)[-1])
    assert abs(ps - pg) < 4 * (pg * (1 - pg) / 40_000) ** 0.5
    with pytest.raises(TypeError, match="model.f failed on states of dtype torch.float32"):
        particle_paths(model, torch.zeros(10, 1), 3, generator=torch.Generator())
