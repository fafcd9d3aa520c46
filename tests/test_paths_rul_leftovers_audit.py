"""prognosis/paths.py (weighted quantiles of paths with missing values, bad weights),
prognosis/rul.py (bad quantile levels and samples), prognosis/trends.py and
prognosis/learner_trend.py (the grid times of the paths, bad input to fit_trends).

References are brute force written here: weighted quantiles by scanning sorted values, crossing
times from a float64 copy of a float32 grid.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _prognosis_helpers import F64, _gen, brute_weighted_quantile

from prognos_torch.prognosis import (
    fault_probability_gaussian,
    fit_learner_trend,
    fit_trends,
    particle_paths,
    rul_distribution,
)
from prognos_torch.prognosis.paths import weighted_quantile

# ------------------------------------------------------------------------------ paths.py


def test_weighted_quantile_of_paths_with_nan_is_nan_where_a_weighted_path_is_missing():
    """A NaN sample was sorted as the largest: with one of four equal-weight paths NaN, the
    0.75 quantile was the largest finite value (3.0) and the 0.9 quantile NaN. A column with a
    NaN of positive weight now has no quantile (NaN) at every q; a NaN of weight zero is left
    out."""
    g = _gen(4)
    s = torch.randn(2, 6, 4, generator=g, dtype=F64).round(decimals=1)
    w = torch.rand(2, 6, generator=g, dtype=F64)
    w[0, 3] = 0.0
    w = w / w.sum(-1, keepdim=True)
    s[0, 3, :] = math.nan  # zero weight: ignored
    s[1, 2, 1:] = math.nan  # positive weight, diverged from step 1 on
    s[0, 0, 2] = math.inf  # an overflow is ordered as a value
    for dt in (F64, torch.float32):
        for q in (0.05, 0.5, 0.75, 0.975, 1.0):
            got = weighted_quantile(s.to(dt), w, q)
            assert got.dtype == dt and got.shape == (2, 4)
            for b in range(2):
                for h in range(4):
                    want = brute_weighted_quantile(
                        s[b, :, h].to(dt).double().numpy(), w[b].numpy(), q
                    )
                    v = float(got[b, h])
                    assert (math.isnan(v) and math.isnan(want)) or v == want
    s4 = torch.tensor([[1.0], [2.0], [math.nan], [3.0]], dtype=F64)
    assert math.isnan(float(weighted_quantile(s4, torch.full((4,), 0.25, dtype=F64), 0.75)))


def test_weighted_quantile_never_returns_a_sample_of_weight_zero_at_q_one():
    """Weights summing to 1 - 1e-7 (within the weights' tolerance) never reached q = 1 to
    1e-12, and the quantile was the last sorted sample, one of weight zero (9.0)."""
    s = torch.tensor([[1.0], [2.0], [9.0]], dtype=F64)
    w = torch.tensor([0.5, 0.5 - 1e-7, 0.0], dtype=F64)
    assert float(weighted_quantile(s, w, 1.0)) == 2.0
    assert float(weighted_quantile(s, w, 0.5)) == 1.0


def test_weighted_quantile_refuses_bad_weights_and_samples_by_name():
    """Unnormalised weights gave the minimum, a weight of shape (1,) was broadcast over the
    samples, a negative weight was taken; samples without the N axis failed with IndexError, N
    = 0 with a RuntimeError, a list with a TypeError on sort's 'dim'."""
    s = torch.tensor([[1.0], [2.0], [3.0], [4.0]], dtype=F64)
    with pytest.raises(ValueError, match="weights must sum to one"):
        weighted_quantile(s, torch.ones(4, dtype=F64), 0.5)
    with pytest.raises(ValueError, match=r"weights must have shape \(4,\)"):
        weighted_quantile(s, torch.ones(1, dtype=F64), 0.5)
    with pytest.raises(ValueError, match="weights must be non-negative"):
        weighted_quantile(s, torch.tensor([0.5, -0.5, 0.5, 0.5], dtype=F64), 0.5)
    with pytest.raises(ValueError, match=r"samples must have shape \(\.\.\., N, H\)"):
        weighted_quantile(torch.zeros(3, dtype=F64), torch.full((3,), 1 / 3, dtype=F64), 0.5)
    with pytest.raises(ValueError, match=r"samples must have shape \(\.\.\., N, H\) with N >= 1"):
        weighted_quantile(torch.zeros(0, 2, dtype=F64), torch.zeros(0, dtype=F64), 0.5)
    with pytest.raises(TypeError, match="samples must be a torch.Tensor"):
        weighted_quantile([[1.0], [2.0]], torch.full((2,), 0.5, dtype=F64), 0.5)
    with pytest.raises(TypeError, match="samples must hold real numbers"):
        weighted_quantile(torch.tensor([[True], [False]]), torch.full((2,), 0.5, dtype=F64), 0.5)
    got = weighted_quantile(torch.tensor([[3], [1]]), torch.full((2,), 0.5, dtype=F64), 0.5)
    assert got.dtype == F64 and got.tolist() == [1.0]


def test_particle_band_is_nan_from_the_step_a_weighted_path_becomes_nan():
    """particle_paths' band through weighted_quantile: a path driven to inf - inf = NaN left
    both bands finite (the NaN taken as the largest sample); they are now NaN like the weighted
    mean, and a diverged path of weight zero leaves them as the other paths give them."""
    from prognos_torch.core.model import StateSpaceModel

    def f(x, u, k):  # x -> 1e308 * x: the first particle overflows to inf, then NaN
        return torch.where(x > 1.0, x * 1e308 - x * 1e308, x + 0.0)

    model = StateSpaceModel(f, lambda x, u, k: x, 1, 1, torch.zeros(1, 1, dtype=F64),
                            torch.eye(1, dtype=F64))  # fmt: skip
    parts = torch.tensor([[2.0], [0.1], [0.2], [0.3]], dtype=F64)
    sp = particle_paths(model, parts, 2, generator=_gen(0))
    assert bool(torch.isnan(sp.samples[0]).all())
    assert (
        torch.isnan(sp.lower).all() and torch.isnan(sp.upper).all() and torch.isnan(sp.mean).all()
    )
    w = torch.tensor([0.0, 0.2, 0.3, 0.5], dtype=F64)  # the diverged path carries no weight
    sp = particle_paths(model, parts, 2, generator=_gen(0), weights=w, level=0.5)
    assert sp.lower.tolist() == [0.2, 0.2] and sp.upper.tolist() == [0.3, 0.3]
    # ... and the mean and std are those of the weighted paths (0 x NaN made them NaN)
    live = sp.samples[1:]
    mean = (w[1:, None] * live).sum(0)
    std = (w[1:, None] * (live - mean) ** 2).sum(0).sqrt()
    assert torch.allclose(sp.mean, mean, rtol=1e-14, atol=0.0)
    assert torch.allclose(sp.std, std, rtol=1e-14, atol=0.0)


# ------------------------------------------------------------------------------ rul.py
def test_rul_quantile_refuses_bool_text_and_none_levels():
    """RULDistribution.quantile(True) was read as q = 1 (the largest RUL); text and None failed
    inside torch.as_tensor ('new(): invalid data type str')."""
    s = torch.tensor([[0.0, 1.0, 2.0], [0.0, 2.0, 3.0]], dtype=F64)
    d = rul_distribution(s, 1.5)  # first passages 3 and 2: pmf [0, 0.5, 0.5]
    assert d.quantile(np.float32(0.5)).item() == 2.0 and d.quantile([0.5, 1.0]).tolist() == [
        2.0, 3.0]  # fmt: skip
    for bad in (True, np.bool_(True), torch.tensor(True), "0.5", None, [0.5, True]):
        with pytest.raises(ValueError, match=r"q must be a probability in \(0, 1\]"):
            d.quantile(bad)


def test_bool_samples_and_gaussian_moments_are_refused():
    """Bool samples were read as 0/1 paths, a bool mean as 1 (a fault probability of a
    prediction of 'True')."""
    with pytest.raises(TypeError, match="samples must be real, got dtype torch.bool"):
        rul_distribution(torch.tensor([[True, False]]), 0.5)
    with pytest.raises(TypeError, match="mean must hold real numbers"):
        fault_probability_gaussian(torch.tensor([True]), torch.tensor([0.0], dtype=F64), 0.5)
    with pytest.raises(TypeError, match="std must hold real numbers"):
        fault_probability_gaussian(torch.tensor([1.0], dtype=F64), torch.tensor([True]), 0.5)
    p = fault_probability_gaussian(torch.tensor([1.0], dtype=F64), torch.tensor([2]), 1.0)
    assert p.item() == 0.5  # (integer std still converted)


# ------------------------------------------------------------------------------ trends
@pytest.fixture(scope="module")
def series():
    g = _gen(0)
    t = torch.linspace(0.0, 10.0, 30, dtype=F64)
    y = 1.0 + 0.5 * torch.exp(0.3 * t + 0.05 * torch.randn(30, generator=g, dtype=F64))
    return t, y


def test_trend_paths_take_a_float32_grid_as_its_float64_times_and_name_a_foreign_device(series):
    """TrendFit.first_passage took the first step of a float32 grid from the origin rounded to
    float32 (origin 1e6 + 0.3 read as 1e6 + 0.3125: a first step of 0.5 instead of 0.5125),
    failed with 'expected scalar type Double' for a float64 grid on a float32 fit, and with
    'Tensor.item() cannot be called on meta tensors' for a grid on another device. Reference:
    the same draws on the float64 copy of the float32 grid."""
    t, y = series
    t = t + 1e6 + 0.3
    fit = fit_trends(t, y, phi=1.0, sigma0=0.05, shapes=("exponential",))["exponential"]
    grid = (t[-1] + torch.linspace(0.5, 20.0, 40, dtype=F64)).float()
    lv = 3.0 * float(y[-1])
    ref = fit.first_passage(-1, lv, grid.double(), 64, _gen(2))
    got = fit.first_passage(-1, lv, grid, 64, _gen(2))
    assert got.times.dtype == torch.float32 and bool(torch.isfinite(ref.times).any())
    assert torch.equal(got.times.double(), ref.times)
    with pytest.raises(ValueError, match="grid is on meta, the fit on cpu"):
        fit.first_passage(-1, lv, grid.to("meta"), 8, _gen(2))
    t32, y32 = series[0].float(), series[1].float()
    f32 = fit_trends(t32, y32, phi=1.0, sigma0=0.05, shapes=("exponential",))["exponential"]
    g = torch.linspace(10.5, 30.0, 20, dtype=F64).float().double()  # (exact in float32)
    a = f32.first_passage(-1, 3.0 * float(y[-1]), g, 16, _gen(3))
    b = f32.first_passage(-1, 3.0 * float(y[-1]), g.float(), 16, _gen(3))
    assert torch.equal(a.times, b.times.double())


def test_learner_trend_shares_the_grid_check_and_refuses_a_non_trend_fit(series):
    """The learner trend's grid check is the trend fits' (same messages); fit_learner_trend of
    a text failed with AttributeError on 'shape'."""
    t, y = series
    lf = fit_trends(t, y, phi=1.0, sigma0=0.05, shapes=("exponential",))["exponential"]
    fit = fit_learner_trend(lf, max_steps=2, n_hidden=3)
    grid = torch.linspace(10.5, 20.0, 8, dtype=F64)
    with pytest.raises(ValueError, match="grid is on meta, the fit on cpu"):
        fit.first_passage(-1, 30.0, grid.to("meta"), 4, _gen(1))
    with pytest.raises(TypeError, match=r"grid must be a torch.Tensor of shape \(J,\)"):
        fit.first_passage(-1, 30.0, grid.tolist(), 4, _gen(1))
    with pytest.raises(TypeError, match="level_fit must be a TrendFit, got str"):
        fit_learner_trend("exponential")


def test_fit_trends_refuses_bad_times_values_and_settings_by_name(series):
    """A time stepping back was taken as a negative clock step with its process noise clipped
    to zero; a NaN time failed as 'us contains non-finite values', an inf value as 'init.chol
    contains non-finite values', a list t with AttributeError, an integer t in a median, a
    float32 y beside a float64 t with 'expected scalar type Double'; sigma0=True was read as 1,
    a NaN phi gave 'no trend shape has 3 usable values', shapes='exponential' was read letter
    by letter."""
    t, y = series
    kw = dict(phi=1.0, sigma0=0.05, shapes=("exponential",))
    back = t.clone()
    back[10] = back[8]
    nan_t = t.clone()
    nan_t[4] = math.nan
    inf_y = y.clone()
    inf_y[4] = math.inf
    for bt, by, err, msg in (
        (back, y, ValueError, "t must be finite, strictly increasing times"),
        (nan_t, y, ValueError, "t must be finite, strictly increasing times"),
        (t, inf_y, ValueError, r"y contains inf \(use NaN to mark a missing value\)"),
        (t.tolist(), y, TypeError, r"t must be a torch.Tensor of shape \(n,\)"),
        (torch.arange(30), y, TypeError, r"t must be a floating tensor of shape \(n,\)"),
        (t, y.to("meta"), ValueError, "y is on meta, t on cpu"),
    ):
        with pytest.raises(err, match=msg):
            fit_trends(bt, by, **kw)
    for name, bad in (("sigma0", True), ("phi", math.nan), ("phi", "1.0")):
        with pytest.raises(ValueError, match=f"{name} must be a finite number"):
            fit_trends(t, y, **{**kw, name: bad})
    with pytest.raises(TypeError, match="shapes must be a tuple of shape names"):
        fit_trends(t, y, phi=1.0, sigma0=0.05, shapes="exponential")
    # a float32 y beside float64 t: the float64 fit of the float64 copy of y
    ref = fit_trends(t, y.float().double(), **kw)["exponential"]
    got = fit_trends(t, y.float(), **kw)["exponential"]
    assert got.means.dtype == F64
    assert float((got.means - ref.means).abs().max()) <= 1e-12


def test_protocol_fractions_take_a_tensor_or_array_of_values():
    """A 1-D tensor of fractions was refused (its entries are 0-d tensors, not numbers), an
    array of them taken; a bool tensor, a 0-d or 2-D tensor stay refused."""
    from prognos_torch.prognosis.protocol import check_fractions

    want = (0.25, 0.5)
    assert check_fractions(torch.tensor(want, dtype=torch.float64)) == want
    assert check_fractions(np.array(want)) == want
    for bad in (torch.tensor([True, False]), torch.tensor(0.5), torch.tensor([[0.5]])):
        with pytest.raises(ValueError, match=r"fractions must be distinct numbers in \(0, 1\)"):
            check_fractions(bad)
