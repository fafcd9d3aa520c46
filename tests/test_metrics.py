"""Metrics against hand-computed values (worked example) and NumPy references."""

import math

import numpy as np
import pytest
import torch

from prognos_torch.metrics import (
    alpha_bounds,
    alpha_lambda,
    convergence,
    cumulative_relative_accuracy,
    exponential_accuracy,
    lambda_index,
    lambda_time,
    mae,
    mape,
    probability_in_bounds,
    prognostic_horizon,
    relative_accuracy,
    rmse,
)

F64 = torch.float64

# Worked example: five predictions, end of life at t = 50.
#   t_i      = 0, 10, 20, 30, 40
#   r*(t_i)  = 50, 40, 30, 20, 10
#   r(t_i)   = 60, 44, 36, 21, 10.5
#   |Delta|  = 10,  4,  6,  1, 0.5
#   RA_i     = 1 - |Delta| / r* = 0.8, 0.9, 0.8, 0.95, 0.95
T = torch.tensor([0.0, 10.0, 20.0, 30.0, 40.0], dtype=F64)
R_TRUE = 50.0 - T
R_PRED = torch.tensor([60.0, 44.0, 36.0, 21.0, 10.5], dtype=F64)


# --------------------------------------------------------------------------- point errors
def test_mae_rmse_mape_match_numpy():
    rng = np.random.default_rng(0)
    pred = rng.normal(size=(4, 7))
    target = rng.normal(size=(4, 7)) + 3.0
    p, y = torch.from_numpy(pred), torch.from_numpy(target)
    assert mae(p, y).item() == pytest.approx(np.mean(np.abs(pred - target)), rel=1e-14)
    assert rmse(p, y).item() == pytest.approx(np.sqrt(np.mean((pred - target) ** 2)), rel=1e-14)
    assert mape(p, y).item() == pytest.approx(
        100 * np.mean(np.abs((pred - target) / target)), rel=1e-14
    )
    np.testing.assert_allclose(
        rmse(p, y, dim=1).numpy(), np.sqrt(np.mean((pred - target) ** 2, axis=1)), rtol=1e-14
    )
    np.testing.assert_allclose(
        mae(p, y, dim=0).numpy(), np.mean(np.abs(pred - target), axis=0), rtol=1e-14
    )
    assert mae(p.float(), y.float()).dtype == F64


def test_mape_rejects_zero_target_and_shapes_must_match():
    with pytest.raises(ValueError, match="target"):
        mape(torch.tensor([1.0, 2.0]), torch.tensor([1.0, 0.0]))
    with pytest.raises(ValueError, match="same shape"):
        mae(torch.zeros(3), torch.zeros(3, 1))
    with pytest.raises(ValueError, match="non-finite"):
        rmse(torch.tensor([1.0, math.nan]), torch.zeros(2))


# --------------------------------------------------------------------------- worked example
def test_lambda_time_and_index():
    assert lambda_time(0.0, 50.0, 0.5) == 25.0
    # t_lambda = 25 -> first prediction at or after it is t = 30 (index 3).
    assert lambda_index(T, 0.5, t_eol=50.0) == 3
    assert lambda_index(T, 0.0, t_eol=50.0) == 0
    assert lambda_index(T, 0.4, t_eol=50.0) == 2  # t_lambda = 20 exactly
    with pytest.raises(ValueError, match="t_lambda"):
        lambda_index(T, 1.0, t_eol=50.0)  # t_lambda = 50, no prediction there


def test_prognostic_horizon_point():
    # alpha = 0.1 of t_EoL = 50: bounds r* +- 5. |Delta| <= 5 first at i = 1 (t = 10).
    assert prognostic_horizon(T, R_TRUE, R_PRED, alpha=0.1) == pytest.approx(50.0 - 10.0)
    # Persistent reading: i = 2 fails (6 > 5), inside from i = 3 (t = 30) on.
    assert prognostic_horizon(T, R_TRUE, R_PRED, alpha=0.1, persistent=True) == pytest.approx(20.0)
    # alpha = 0.2 (+-10): the first prediction is on the bound (inclusive).
    assert prognostic_horizon(T, R_TRUE, R_PRED, alpha=0.2) == pytest.approx(50.0)
    # Asymmetric: over-predictions need alpha^+ t_EoL >= 10 at t = 0 -> fails with 0.1; the
    # next over-prediction (+4) passes.
    assert prognostic_horizon(T, R_TRUE, R_PRED, alpha=(0.0, 0.1)) == pytest.approx(40.0)
    assert math.isnan(prognostic_horizon(T, R_TRUE, R_PRED, alpha=0.001))


def test_alpha_lambda_point():
    # lambda = 0.5 -> t = 30: r* = 20, alpha = 0.2 -> [16, 24], r = 21 inside.
    assert alpha_lambda(T, R_TRUE, R_PRED, alpha=0.2, lam=0.5) is True
    # alpha = 0.04 -> [19.2, 20.8], r = 21 outside.
    assert alpha_lambda(T, R_TRUE, R_PRED, alpha=0.04, lam=0.5) is False
    # lambda = 0 -> t = 0: r* = 50, alpha = 0.1 -> [45, 55], r = 60 outside; 0.2 -> [40, 60].
    assert alpha_lambda(T, R_TRUE, R_PRED, alpha=0.1, lam=0.0) is False
    assert alpha_lambda(T, R_TRUE, R_PRED, alpha=0.2, lam=0.0) is True
    # Paper 002's setting alpha = 0.3, lambda = 0.5.
    assert alpha_lambda(T, R_TRUE, R_PRED, alpha=0.3, lam=0.5) is True
    lo, hi = alpha_bounds(R_TRUE, (0.1, 0.3))
    torch.testing.assert_close(lo, 0.9 * R_TRUE)
    torch.testing.assert_close(hi, 1.3 * R_TRUE)


def test_relative_and_cumulative_relative_accuracy():
    assert relative_accuracy(T, R_TRUE, R_PRED, lam=0.5) == pytest.approx(1 - 1 / 20)
    assert relative_accuracy(T, R_TRUE, R_PRED, lam=0.0) == pytest.approx(1 - 10 / 50)
    # Plain CRA over all predictions up to t_lambda = t_EoL: mean of RA.
    ra = [0.8, 0.9, 0.8, 0.95, 0.95]
    assert cumulative_relative_accuracy(T, R_TRUE, R_PRED) == pytest.approx(sum(ra) / 5)
    # lambda = 0.5 -> t_lambda = 25 -> i = 0, 1, 2.
    assert cumulative_relative_accuracy(T, R_TRUE, R_PRED, lam=0.5) == pytest.approx(2.5 / 3)
    # Weighted mean with w = 1..5: (0.8 + 1.8 + 2.4 + 3.8 + 4.75) / 15.
    w = torch.arange(1.0, 6.0, dtype=F64)
    assert cumulative_relative_accuracy(T, R_TRUE, R_PRED, weights=w) == pytest.approx(13.55 / 15)
    # Paper 002: lambda in {0, .25, .5, .75} -> t_lambda = 0, 12.5, 25, 37.5 -> i = 0, 2, 3, 4.
    cra = cumulative_relative_accuracy(T, R_TRUE, R_PRED, lambdas=[0.0, 0.25, 0.5, 0.75])
    assert cra == pytest.approx((0.8 + 0.8 + 0.95 + 0.95) / 4)
    cra_w = cumulative_relative_accuracy(
        T, R_TRUE, R_PRED, lambdas=[0.0, 0.5], weights=torch.tensor([1.0, 3.0])
    )
    assert cra_w == pytest.approx((0.8 + 3 * 0.95) / 4)


def test_convergence_worked_example():
    # M = |Delta| held on [t_i, t_{i+1}): M = 10, 4, 6, 1 on four intervals of width 10.
    area = 10 * (10 + 4 + 6 + 1)  # 210
    sx = (100 - 0) * 10 + (400 - 100) * 4 + (900 - 400) * 6 + (1600 - 900) * 1  # 5900
    sy = 10 * (100 + 16 + 36 + 1)  # 1530
    expected = math.hypot(sx / (2 * area), sy / (2 * area))
    assert convergence(T, R_TRUE, R_PRED) == pytest.approx(expected, rel=1e-12)
    # Closing the last interval at t_EoL = 50 adds M = 0.5 on [40, 50).
    area2, sx2, sy2 = area + 5, sx + (2500 - 1600) * 0.5, sy + 10 * 0.25
    expected2 = math.hypot(sx2 / (2 * area2), sy2 / (2 * area2))
    assert convergence(T, R_TRUE, R_PRED, t_end=50.0) == pytest.approx(expected2, rel=1e-12)


def test_convergence_constant_metric_is_rectangle_centroid():
    t = torch.tensor([2.0, 3.0, 7.0, 12.0], dtype=F64)
    m = torch.full((4,), 3.0, dtype=F64)
    # Rectangle [2, 12] x [0, 3]: centroid (7, 1.5), distance to (t_P, 0) = (2, 0).
    got = convergence(t, None, None, metric=m)
    assert got == pytest.approx(math.hypot(7 - 2, 1.5), rel=1e-12)
    assert math.isnan(convergence(t, None, None, metric=torch.zeros(4, dtype=F64)))


def test_exponential_accuracy():
    errs = [10, 4, 6, 1, 0.5]
    expected = sum(math.exp(-e / 10.0) for e in errs) / 5
    assert exponential_accuracy(R_TRUE, R_PRED, d0=10.0) == pytest.approx(expected, rel=1e-14)
    assert exponential_accuracy(R_TRUE, R_TRUE, d0=1.0) == 1.0
    with pytest.raises(ValueError, match="d0"):
        exponential_accuracy(R_TRUE, R_PRED, d0=0.0)


# --------------------------------------------------------------------------- distributions
def _ph_samples():
    # Mass within r* +- 5 per row: 0.2, 0.6 (45 and 35 on the bounds), 0.4, 0.8, 1.0.
    return torch.tensor(
        [
            [50.0, 30.0, 30.0, 70.0, 70.0],
            [35.0, 45.0, 40.0, 20.0, 60.0],
            [30.0, 31.0, 10.0, 10.0, 50.0],
            [20.0, 21.0, 22.0, 23.0, 0.0],
            [10.0, 10.0, 10.0, 10.0, 10.0],
        ],
        dtype=F64,
    )


def test_prognostic_horizon_probability_mass():
    s = _ph_samples()
    lo, hi = R_TRUE - 5.0, R_TRUE + 5.0
    torch.testing.assert_close(
        probability_in_bounds(lo, hi, rul_samples=s),
        torch.tensor([0.2, 0.6, 0.4, 0.8, 1.0], dtype=F64),
    )
    ph = prognostic_horizon(T, R_TRUE, alpha=0.1, beta=0.5, rul_samples=s)
    assert ph == pytest.approx(40.0)
    ph_p = prognostic_horizon(T, R_TRUE, alpha=0.1, beta=0.5, rul_samples=s, persistent=True)
    assert ph_p == pytest.approx(20.0)
    assert prognostic_horizon(T, R_TRUE, alpha=0.1, beta=0.9, rul_samples=s) == pytest.approx(10.0)


def test_alpha_lambda_probability_mass_samples_and_pmf():
    s = _ph_samples().clone()
    s[3] = torch.tensor([15.0, 17.0, 20.0, 23.0, 25.0])
    w = torch.full((5, 5), 0.2, dtype=F64)
    w[3] = torch.tensor([0.1, 0.2, 0.2, 0.1, 0.4])
    # At t = 30: bounds [16, 24] hold 17, 20, 23 -> 0.2 + 0.2 + 0.1 = 0.5.
    kw = dict(alpha=0.2, lam=0.5, rul_samples=s, sample_weights=w)
    assert alpha_lambda(T, R_TRUE, beta=0.5, **kw) is True
    assert alpha_lambda(T, R_TRUE, beta=0.55, **kw) is False
    # pmf on support 5, 10, ..., 60; row 3 puts 0.3 on 20 (inside), 0.3 on 15 and 0.2 on 25
    # (outside), 0.2 censored (missing) -> 0.3.
    support = torch.arange(5.0, 65.0, 5.0, dtype=F64)
    pmf = torch.zeros(5, 12, dtype=F64)
    pmf[:, 0] = 1.0
    pmf[3] = 0.0
    pmf[3, 3], pmf[3, 2], pmf[3, 4] = 0.3, 0.3, 0.2
    kw = dict(alpha=0.2, lam=0.5, rul_pmf=pmf, rul_support=support)
    assert alpha_lambda(T, R_TRUE, beta=0.3, **kw) is True
    assert alpha_lambda(T, R_TRUE, beta=0.5, **kw) is False


def test_distribution_argument_checks():
    s = _ph_samples()
    with pytest.raises(ValueError, match="exactly one"):
        probability_in_bounds(R_TRUE, R_TRUE, rul_samples=s, rul_pmf=s, rul_support=R_TRUE)
    with pytest.raises(ValueError, match="sample_weights"):
        probability_in_bounds(
            R_TRUE, R_TRUE, rul_samples=s, sample_weights=torch.full((5, 5), 0.3, dtype=F64)
        )
    with pytest.raises(ValueError, match="rul_pmf"):
        probability_in_bounds(
            R_TRUE, R_TRUE, rul_pmf=torch.ones(5, 3, dtype=F64), rul_support=torch.ones(3)
        )
    with pytest.raises(ValueError, match="pred_rul"):
        alpha_lambda(T, R_TRUE, alpha=0.2, lam=0.5)


def test_trajectory_checks():
    with pytest.raises(ValueError, match="t_eol"):
        relative_accuracy(T, R_TRUE + torch.arange(5.0, dtype=F64), R_PRED, lam=0.5)
    # With an explicit t_eol, inconsistent true RUL (e.g. other units) is accepted.
    assert relative_accuracy(T, R_TRUE, R_PRED, lam=0.5, t_eol=50.0) == pytest.approx(0.95)
    with pytest.raises(ValueError, match="strictly increasing"):
        alpha_lambda(T.flip(0), R_TRUE, R_PRED, alpha=0.2, lam=0.5, t_eol=50.0)
    with pytest.raises(ValueError, match="pred_rul"):
        relative_accuracy(T, R_TRUE, R_PRED[:4], lam=0.5)
    with pytest.raises(ValueError, match="lam"):
        relative_accuracy(T, R_TRUE, R_PRED, lam=1.5)
    with pytest.raises(ValueError, match="alpha"):
        prognostic_horizon(T, R_TRUE, R_PRED, alpha=-0.1)
    with pytest.raises(ValueError, match="beta"):
        prognostic_horizon(T, R_TRUE, R_PRED, alpha=0.1, beta=0.0)


def test_convergence_from_t_p_sums_from_the_first_prediction_at_or_after_it():
    # [S10]: the sums run from i = P; with t_P = 15 the intervals from t = 20 on count
    # (M = 6, 1 on [20, 30), [30, 40)), and the distance is from (15, 0)
    area = 10 * (6 + 1)
    sx = (900 - 400) * 6 + (1600 - 900) * 1
    sy = 10 * (36 + 1)
    expected = math.hypot(sx / (2 * area) - 15.0, sy / (2 * area))
    assert convergence(T, R_TRUE, R_PRED, t_p=15.0) == pytest.approx(expected, rel=1e-12)
    with pytest.raises(ValueError, match=r"t_p \(100\) is later than the last prediction"):
        convergence(T, R_TRUE, R_PRED, t_p=100.0)


def test_end_of_life_before_the_predictions_is_refused():
    # t_lambda ran backwards (t_eol 5 < t_P 10) and PH came out negative
    with pytest.raises(ValueError, match=r"t_eol \(5\) must be later than the first prediction"):
        prognostic_horizon(T + 10, R_TRUE, R_PRED, alpha=0.2, t_eol=5.0)
    with pytest.raises(ValueError, match=r"t_eol \(30\) must be later than t_P \(35\)"):
        alpha_lambda(T, R_TRUE, R_PRED, alpha=0.3, lam=0.5, t_eol=30.0, t_p=35.0)


def test_arguments_that_would_be_ignored_are_refused():
    samples = R_TRUE[:, None] + torch.zeros(5, 3, dtype=F64)
    with pytest.raises(ValueError, match="give pred_rul .* or a distribution .*, not both"):
        alpha_lambda(T, R_TRUE, 100 * R_TRUE, alpha=0.3, lam=0.5, rul_samples=samples)
    with pytest.raises(ValueError, match="beta applies to a distribution"):
        prognostic_horizon(T, R_TRUE, R_PRED, alpha=0.2, beta=0.8)
    with pytest.raises(ValueError, match="give lam .* or lambdas .*, not both"):
        cumulative_relative_accuracy(T, R_TRUE, R_PRED, lam=0.5, lambdas=[0.0, 0.5])
    assert alpha_lambda(T, R_TRUE, alpha=0.3, lam=0.5, rul_samples=samples, beta=0.9)


def test_metric_messages_name_the_point_and_what_to_do():
    t = torch.tensor([0.0, 10.0, 20.0, 30.0, 40.0, 50.0], dtype=F64)
    with pytest.raises(ValueError, match=r"true_rul > 0 .* it is 0 at t = 50 .* lam < 1"):
        cumulative_relative_accuracy(t, 50.0 - t, 50.0 - t)  # (default lam = 1: the EoL point)
    assert cumulative_relative_accuracy(t, 50.0 - t, 50.0 - t, lam=0.9) == 1.0
    with pytest.raises(ValueError, match=r"pred_rul contains non-finite values \(first at index 2"):
        alpha_lambda(T, R_TRUE, torch.tensor([60.0, 44.0, math.nan, 21.0, 10.5], dtype=F64),
                     alpha=0.3, lam=0.5)  # fmt: skip
    bad = (R_TRUE[:, None] + torch.zeros(5, 3, dtype=F64)).index_put_((torch.tensor([3]),),
                                                                     torch.tensor(math.nan, dtype=F64))  # fmt: skip
    with pytest.raises(ValueError, match=r"rul_samples contains NaN \(first in row 3\).*inf"):
        probability_in_bounds(R_TRUE * 0.7, R_TRUE * 1.3, rul_samples=bad)


def test_a_float32_pmf_is_held_to_float32_rounding():
    # softmax rows in float32 sum to 1 within ~1e-7: accepted as sample weights are
    g = torch.Generator().manual_seed(0)
    pmf = torch.softmax(torch.randn(5, 400, generator=g), -1)
    support = torch.linspace(1.0, 80.0, 400, dtype=F64)
    got = probability_in_bounds(R_TRUE * 0.7, R_TRUE * 1.3, rul_pmf=pmf, rul_support=support)
    inside = (support >= (R_TRUE * 0.7)[:, None]) & (support <= (R_TRUE * 1.3)[:, None])
    ref = (pmf.double() * inside).sum(-1)
    torch.testing.assert_close(got, ref, rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"within 0.00019\); row \d sums to 1 \+ 0.01"):
        probability_in_bounds(R_TRUE * 0.7, R_TRUE * 1.3, rul_pmf=pmf * 1.01,
                              rul_support=support)  # fmt: skip
