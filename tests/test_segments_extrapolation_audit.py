"""Audit of filters.segments, workflow.extrapolation and filters._particle_trees.

Exact references: a plain covariance-form Kalman filter written here (segmented runs with
missing values at the segment boundaries), the extrapolation distance and the widened band
computed by hand from the documented formulas, and particle ancestry traced by a Python loop
over the ancestor indices.
"""

from __future__ import annotations

import math
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import run, run_in_segments, sckf
from prognos_torch.filters.particle import gather_particles, where_particles
from prognos_torch.workflow import extrapolation as ex
from prognos_torch.workflow.extrapolation import ExtrapolationWarning

sys.path.insert(0, str(Path(__file__).parent))
from _kalman_reference import kalman_filter_observed  # noqa: E402

D = torch.float64
F = torch.tensor([[0.9, 0.2], [-0.1, 0.95]], dtype=D)
H = torch.tensor([[1.0, 0.0], [0.5, 1.0]], dtype=D)
LQ = torch.tensor([[0.3, 0.0], [0.1, 0.2]], dtype=D)
LR = torch.tensor([[0.5, 0.0], [0.2, 0.4]], dtype=D)
BU = torch.tensor([[1.0], [0.5]], dtype=D)


def _model(dtype=D, controls=False):
    c = lambda a: a.to(dtype)  # noqa: E731
    return linear_gaussian_model(
        c(F), c(H), chol_Q=c(LQ), chol_R=c(LR), B=c(BU) if controls else None
    )


def _belief(bs, dtype=D):
    mean = torch.arange(math.prod(bs) * 2, dtype=dtype).reshape(*bs, 2) * 0.1
    return GaussianBelief(mean, (0.7 * torch.eye(2, dtype=dtype)).expand(*bs, 2, 2).clone())


def _kalman(ys, m0, P0):
    """Covariance-form Kalman filter of one run in NumPy; a NaN component is not observed."""
    Q, R = (LQ @ LQ.mT).numpy(), (LR @ LR.mT).numpy()
    means, covs, _ = kalman_filter_observed(F.numpy(), H.numpy(), Q, R, m0, P0, ys)
    return means, covs[-1]


# ------------------------------------------------------------------------------ segments
@pytest.mark.parametrize("segment", [1, 4, 5, 12])
def test_segments_equal_a_plain_kalman_filter_with_gaps_at_the_boundaries(segment):
    T, bs = 12, (2, 3)
    g = torch.Generator().manual_seed(1)
    ys = torch.randn(T, *bs, 2, generator=g, dtype=D).cumsum(0) * 0.3
    ys[3:5] = math.nan  # both sides of the boundary at t = 4
    ys[8, 0, :, 1] = math.nan  # a partial row where a segment of 4 starts
    ys[11, 1, 2] = math.nan  # the last step
    b0 = _belief(bs)
    seg = run_in_segments(sckf(), _model(), b0, ys, segment=np.int64(segment), k0=np.int64(3))
    assert seg.means.shape == (T, *bs, 2) and seg.var_R.shape == (T, *bs, 2)
    P0 = (b0.chol @ b0.chol.mT).numpy()
    for i in range(bs[0]):
        for j in range(bs[1]):
            want, P = _kalman(ys[:, i, j].numpy(), b0.mean[i, j].numpy(), P0[i, j])
            np.testing.assert_allclose(seg.means[:, i, j].numpy(), want, rtol=0, atol=1e-12)
            Lf = seg.final.belief.chol[i, j]
            np.testing.assert_allclose((Lf @ Lf.mT).numpy(), P, rtol=0, atol=1e-12)
    want_Q = torch.diagonal(LQ @ LQ.mT).expand(T, *bs, 2)
    torch.testing.assert_close(seg.var_Q, want_Q, rtol=1e-14, atol=0)


def test_segments_float32_match_the_float64_run():
    T, bs = 9, (4,)
    ys = torch.randn(T, *bs, 2, generator=torch.Generator().manual_seed(2), dtype=D)
    ys[4] = math.nan
    ref = run(sckf(), _model(), _belief(bs), ys)
    seg = run_in_segments(sckf(), _model(torch.float32), _belief(bs, torch.float32),
                          ys.float(), segment=4)  # fmt: skip
    assert seg.means.dtype == seg.var_Q.dtype == seg.var_R.dtype == torch.float32
    torch.testing.assert_close(seg.means.double(), ref.means, rtol=0, atol=1e-5)


def test_segments_check_filter_init_and_k0_as_run_does():
    """Before: k0=True was taken as k0 = 1; an uncalled factory (sckf) raised AttributeError
    'function' object has no attribute 'init'; a wrong belief was named 'belief', not init."""
    ys = torch.randn(6, 3, 2, dtype=D)
    b0 = _belief((3,))
    with pytest.raises(ValueError, match=r"k0 must be a non-negative int, got True"):
        run_in_segments(sckf(), _model(), b0, ys, segment=2, k0=True)
    with pytest.raises(TypeError, match=r"filter must be a GaussianFilter.*sckf\(\)"):
        run_in_segments(sckf, _model(), b0, ys, segment=2)
    bad = GaussianBelief(torch.zeros(3, 3, dtype=D), torch.eye(3, dtype=D).expand(3, 3, 3))
    with pytest.raises(ValueError, match=r"init\.mean must have shape \(\.\.\., 2\)"):
        run_in_segments(sckf(), _model(), bad, ys, segment=2)
    with pytest.raises(TypeError, match=r"ys must be a torch\.Tensor"):
        run_in_segments(sckf(), _model(), b0, ys.numpy(), segment=2)


def test_segments_check_the_whole_control_sequence():
    """Before: 12 control rows for 10 steps were cut to 10 segment by segment (one run refuses
    them), and a short or missing us was reported with the segment's T = 3."""
    T, model, b0 = 10, _model(controls=True), _belief((4,))
    ys = torch.randn(T, 4, 2, generator=torch.Generator().manual_seed(3), dtype=D)
    us = torch.randn(12, 1, generator=torch.Generator().manual_seed(4), dtype=D)
    with pytest.raises(ValueError, match=r"us must have shape .* with T = 10, got \(12, 1\)"):
        run_in_segments(sckf(), model, b0, ys, us, segment=3)
    with pytest.raises(ValueError, match=r"us must have shape .* with T = 10, got \(8, 1\)"):
        run_in_segments(sckf(), model, b0, ys, us[:8], segment=3)
    with pytest.raises(ValueError, match=r"us must have shape .* with T = 10; it is required"):
        run_in_segments(sckf(), model, b0, ys, None, segment=3)
    ref = run(sckf(), model, b0, ys, us[:T])
    seg = run_in_segments(sckf(), model, b0, ys, us[:T], segment=3)
    torch.testing.assert_close(seg.means, ref.means, rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------ extrapolation
def _d_by_hand(history, mean, m, lo, hi):
    """d_k = max over the m inputs of step k of their distance outside [lo, hi]; NaN: 0."""

    def out(v):
        return 0.0 if math.isnan(v) else max(lo - v, 0.0) + max(v - hi, 0.0)

    seq = list(history[-m:]) + list(mean)
    return [max(out(v) for v in seq[k : k + m]) for k in range(len(mean))]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_extrapolation_distance_is_the_documented_formula(dtype):
    lo, hi, m = -1.0, 2.0, 3
    history = [0.5, 3.0, math.nan, 1.5, -2.5]
    mean = [2.0, 2.75, math.nan, 1.0, -1.25, math.inf, 0.0, 0.5, 0.25, 1.0]
    got = ex.extrapolation_distance(torch.tensor(history, dtype=D), torch.tensor(mean, dtype=dtype),
                                    np.int64(m), lo, hi)  # fmt: skip
    assert got.shape == (10,) and got.dtype == dtype
    want = torch.tensor(_d_by_hand(history, mean, m, lo, hi), dtype=dtype)
    torch.testing.assert_close(got, want, rtol=0, atol=0)
    assert ex.origin_distance(torch.tensor(history, dtype=D), m, lo, hi) == 1.5
    assert ex.origin_distance(torch.tensor([0.0, 5.0, math.nan]), 1, lo, hi) == 0.0


def test_widen_is_the_documented_formula_and_safe_in_float32():
    """Before: h^2 overflowed in float32 for half-widths above 1.8e19 (an infinite band)."""
    mean = torch.tensor([1.0, -2.0, 0.5, 3.0], dtype=D)
    lower = mean - torch.tensor([0.3, 1.0, 0.0, 2.0], dtype=D)
    upper = mean + torch.tensor([0.4, 0.5, 0.0, 2.5], dtype=D)
    std = torch.tensor([0.2, 0.6, 0.0, 1.0], dtype=D)
    dist = torch.tensor([0.0, 0.7, 1.5, math.inf], dtype=D)
    lw, up, sd = ex.widen(mean, lower, upper, std, dist, np.float64(0.9))
    z = 1.6448536269514722  # the 95 % normal quantile: a central 90 % band
    for k in range(4):
        mk, dk = float(mean[k]), float(dist[k])
        hl, hu = mk - float(lower[k]), float(upper[k]) - mk
        assert float(lw[k]) == pytest.approx(mk - math.sqrt(hl**2 + (z * dk) ** 2), rel=1e-12)
        assert float(up[k]) == pytest.approx(mk + math.sqrt(hu**2 + (z * dk) ** 2), rel=1e-12)
        assert float(sd[k]) == pytest.approx(math.sqrt(float(std[k]) ** 2 + dk**2), rel=1e-12)
    assert torch.equal(lw[:1], lower[:1]) and torch.equal(sd[:1], std[:1])  # d = 0: unchanged
    f = torch.float32
    m32 = torch.zeros(2, dtype=f)
    h = torch.tensor([3e19, 1e-30], dtype=f)
    lw, up, sd = ex.widen(m32, m32 - h, m32 + h, h, torch.tensor([1.0, 0.0], dtype=f), 0.95)
    assert lw.dtype == up.dtype == sd.dtype == f
    torch.testing.assert_close(up, h, rtol=1e-6, atol=0)
    torch.testing.assert_close(lw, -h, rtol=1e-6, atol=0)
    torch.testing.assert_close(sd, h, rtol=1e-6, atol=0)


def test_warn_flag_threshold_inf_and_a_constant_training_range():
    """Before: a constant training range (span 0) raised ZeroDivisionError in the message."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert ex.warn("the forecast", 0.1, 0.0, 1.0) is None  # 10 % is not beyond 10 %
        assert ex.warn("the forecast", 0.0, 2.0, 2.0) is None
    with pytest.warns(ExtrapolationWarning, match=r"by up to 0\.25 \(25 % of its span\)"):
        text = ex.warn("the forecast", np.float32(0.25), np.int64(0), 1.0)
    assert text.endswith("widened by that distance (prognos_torch.workflow.extrapolation)")
    with pytest.warns(ExtrapolationWarning, match=r"by up to inf \(the values overflow\)"):
        ex.warn("the series the RUL starts from", math.inf, 0.0, 1.0)
    with pytest.warns(ExtrapolationWarning, match=r"by up to 1e\+308 \(1e\+308 times its span\)"):
        ex.warn("the forecast", 1e308, 0.0, 1.0)  # (100 x the ratio overflows)
    with pytest.warns(ExtrapolationWarning, match=r"\[2, 2\] by up to 0\.5 \(its span is 0\)"):
        text = ex.warn("the forecast", 0.5, 2.0, 2.0)
    assert "ZeroDivision" not in text


@pytest.mark.parametrize(
    "call, exc, msg",
    [
        # before: None (a NaN bound never warns), a negative span ("-50 % of its span")
        (lambda: ex.warn("x", 0.5, math.nan, 1.0), ValueError, r"lo, hi must be finite"),
        (lambda: ex.warn("x", 0.5, 2.0, 1.0), ValueError, r"lo <= hi .* got 2\.0, 1\.0"),
        (lambda: ex.warn("x", math.nan, 0.0, 1.0), ValueError, r"dist must be a number >= 0"),
        # before: a (1,) d for a (2,) forecast, which widen broadcast
        (lambda: ex.extrapolation_distance(torch.ones(1), torch.ones(2), 3, 0.0, 1.0),
         ValueError, r"history must hold at least m = 3 values, got 1"),
        # before: IndexError from amax
        (lambda: ex.extrapolation_distance(torch.ones(3), torch.ones(2), 0, 0.0, 1.0),
         ValueError, r"m must be a positive int, got 0"),
        # before: RuntimeError from cat
        (lambda: ex.extrapolation_distance(torch.ones(3), torch.ones(1, 2), 2, 0.0, 1.0),
         ValueError, r"mean must be a floating-point tensor of shape \(H,\), got \(1, 2\)"),
        # before: m = 0 took the whole history (history[-0:])
        (lambda: ex.origin_distance(torch.tensor([5.0, 0.5]), 0, 0.0, 1.0),
         ValueError, r"m must be a positive int, got 0"),
        # before: a NaN band
        (lambda: ex.widen(*[torch.ones(2)] * 5, 1.5), ValueError, r"level must be a number"),
        # before: a (1,) dist broadcast over the forecast
        (lambda: ex.widen(*[torch.ones(2)] * 4, torch.ones(1), 0.9),
         ValueError, r"dist must have the shape of mean \(2,\), got \(1,\)"),
    ],
)  # fmt: skip
def test_extrapolation_bad_input_is_named(call, exc, msg):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExtrapolationWarning)
        with pytest.raises(exc, match=msg):
            call()


# ------------------------------------------------------------------------------ particle trees
@dataclass(frozen=True)
class _Buf:
    buf_Q: torch.Tensor  # (W, ..., N, n): window dim first
    count: torch.Tensor  # (..., N)
    k: object = 0


@dataclass(frozen=True)
class _State:
    x: torch.Tensor  # (..., N, n)
    noise: _Buf | None = None


@pytest.mark.parametrize("bs", [(), (3,), (2, 3)])
def test_gather_traces_ancestry_like_a_loop_over_the_indices(bs):
    g = torch.Generator().manual_seed(5)
    N, n, W = 6, 2, 3
    x0 = torch.randn(*bs, N, n, generator=g, dtype=torch.float32)
    buf0 = torch.randn(W, *bs, N, n, generator=g, dtype=torch.float32)
    st = _State(x0, _Buf(buf0, torch.arange(N).expand(*bs, N).clone(), 7))
    ancs = [torch.randint(0, N, (*bs, N), generator=g) for _ in range(4)]
    for a in ancs:  # four resampling steps
        st = gather_particles(st, a)
    assert st.x.dtype == torch.float32 and st.noise.k == 7
    flat = [a.reshape(-1, N) for a in ancs]
    x_ref, q_ref = x0.reshape(-1, N, n), buf0.reshape(W, -1, N, n)
    x_got, q_got = st.x.reshape(-1, N, n), st.noise.buf_Q.reshape(W, -1, N, n)
    for r in range(x_ref.shape[0]):
        for j in range(N):
            i = j
            for a in reversed(flat):  # brute force: the ancestor of j, step by step back
                i = int(a[r, i])
            assert torch.equal(x_got[r, j], x_ref[r, i])
            assert torch.equal(q_got[:, r, j], q_ref[:, r, i])
            assert int(st.noise.count.reshape(-1, N)[r, j]) == i


def test_gather_particles_checks_the_ancestors():
    """Before: float ancestors failed in torch.gather ('Expected dtype int32/int64 for index'),
    a list with AttributeError, and a 0-dim tensor selected along every leaf's last dim."""
    x = torch.randn(2, 4, 3)
    with pytest.raises(TypeError, match=r"ancestors must be an int64 tensor .* torch\.float32"):
        gather_particles(x, torch.zeros(2, 4))
    with pytest.raises(TypeError, match=r"ancestors must be an int64 tensor"):
        gather_particles(x, [[0, 1, 2, 3]] * 2)
    with pytest.raises(ValueError, match=r"ancestors must have shape \(\.\.\., N\), got a 0-dim"):
        gather_particles(x, torch.tensor(1))
    a = torch.tensor([[3, 3, 0, 1], [2, 0, 0, 1]])
    torch.testing.assert_close(gather_particles(x, a.int()), gather_particles(x, a))


def test_gather_keeps_numpy_scalar_fields():
    """Before: TypeError 'k: cannot map over particles of a int64'."""
    st = _Buf(torch.randn(1, 4, 2), torch.arange(4.0), np.int64(3))
    out = gather_particles(st, torch.tensor([1, 1, 0, 2]), leading={"buf_Q": 1})
    assert out.k == 3 and torch.equal(out.count, torch.tensor([1.0, 1.0, 0.0, 2.0]))
    assert gather_particles(_Buf(st.buf_Q, st.count, np.bool_(True)), torch.arange(4)).k


def test_where_particles_refuses_broadcasting_promotion_and_mismatched_trees():
    """Before: b's (1, N, n) or (N, n) leaf was broadcast, a float64 b promoted a float32 a,
    b's None reached torch.where (an unnamed TypeError), a's None dropped b's tensor, a float
    mask failed inside torch.where."""
    g = torch.Generator().manual_seed(6)
    x, y = torch.randn(2, 4, 3, generator=g), torch.randn(2, 4, 3, generator=g)
    mask = torch.tensor([[True, False, True, False], [False, False, True, True]])
    got = where_particles(mask, _State(x), _State(y))
    want = torch.stack([torch.stack([(x if mask[b, j] else y)[b, j] for j in range(4)])
                        for b in range(2)])  # fmt: skip
    assert torch.equal(got.x, want)
    with pytest.raises(ValueError, match=r"x: b's tensor must match a's, shape \(2, 4, 3\)"):
        where_particles(mask, _State(x), _State(y[:1]))
    with pytest.raises(ValueError, match=r"x: b's tensor must match a's"):
        where_particles(mask, _State(x), _State(y[0]))
    with pytest.raises(ValueError, match=r"torch\.float32, got \(2, 4, 3\) and torch\.float64"):
        where_particles(mask, _State(x), _State(y.double()))
    buf = _Buf(torch.zeros(1, 2, 4, 3), torch.zeros(2, 4))
    with pytest.raises(TypeError, match=r"noise: the trees differ here: a _Buf and None"):
        where_particles(mask, _State(x, buf), _State(y))
    with pytest.raises(TypeError, match=r"noise: the trees differ here: None and a _Buf"):
        where_particles(mask, _State(x), _State(y, buf))
    with pytest.raises(TypeError, match=r"mask must be a bool tensor"):
        where_particles(mask.float(), _State(x), _State(y))


def test_a_forecast_that_overflows_warns_that_it_diverges():
    # An ANFIS whose consequents are scaled up grows without bound when iterated: the EKF's
    # mean reached inf with only the extrapolation warning ("inf % of its span"), the UKF
    # failed with torch's "matrix is not positive definite"
    from prognos_torch.workflow import fit_series, forecast, load_series

    t = np.arange(200.0)
    s = load_series(1.0 + 0.2 * np.sin(t / 7.0) + 0.002 * t)
    m = fit_series(s, learner="anfis", m=2, optimizer_options={"epochs": 1}, seed=0)
    with torch.no_grad():
        m.learner.alpha.mul_(1e6)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        f = forecast(m, s, 60, filter="ekf", filter_steps=5)
    first = int((~torch.isfinite(f.mean)).nonzero()[0, 0]) + 1  # the reference: the means
    texts = [str(w.message) for w in caught if issubclass(w.category, ExtrapolationWarning)]
    assert any(f"the forecast diverges: its mean is not finite from step {first} of 60" in x
               for x in texts)  # fmt: skip
    assert not any("inf %" in x for x in texts)
    with pytest.raises(ValueError, match="the ukf forecast diverged within 60 steps"):
        forecast(m, s, 60, filter="ukf", filter_steps=5)
    assert ex.diverged(torch.tensor([1.0, 2.0], dtype=torch.float64)) is None
    with pytest.warns(ExtrapolationWarning, match="not finite from step 2 of 3 on"):
        ex.diverged(torch.tensor([1.0, math.nan, math.inf], dtype=torch.float64))


def test_rul_from_paths_that_overflow_counts_them_as_not_crossing_from_then_on():
    # the model-file RUL refused such paths with "samples contains NaN; shape (..., N, H)"
    from prognos_torch.workflow import fit_series, load_series, rul

    t = np.arange(200.0)
    s = load_series(1.0 + 0.2 * np.sin(t / 7.0) + 0.002 * t)
    m = fit_series(s, learner="anfis", m=2, optimizer_options={"epochs": 1}, seed=0)
    with torch.no_grad():
        m.learner.alpha.mul_(1e6)
    kw = dict(horizon=60, filter_steps=5, n_particles=50)
    with pytest.warns(ExtrapolationWarning, match="diverging paths: 100.0 % of the predicted"):
        up = rul(m, s, 2.0, direction="above", **kw)
    # the reference: each path's first step above the threshold among its finite values
    finite = torch.isfinite(up.paths).to(torch.int8).cummin(-1).values.bool()
    crossed = (up.paths > 2.0) & finite
    first = crossed.to(torch.int8).argmax(-1) + 1
    assert bool(crossed.any(-1).all())
    med = float(first.to(torch.float64).median())  # (lower median, as the sample quantile)
    assert up.summary()["median"] == pytest.approx(med * s.dt)
    assert any(f.startswith("diverging paths") for f in up.flags)
    with pytest.warns(ExtrapolationWarning, match="diverging paths"):
        down = rul(m, s, 0.5, direction="below", **kw)  # they run up to inf: never below
    assert down.summary()["censored_mass"] == 1.0
