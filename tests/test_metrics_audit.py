"""Audit of the prognostic metrics against hand-computed values on small edge cases."""

import math

import pytest
import torch

from prognos_torch.metrics import (
    alpha_lambda,
    convergence,
    cumulative_relative_accuracy,
    lambda_index,
    probability_in_bounds,
    prognostic_horizon,
    relative_accuracy,
    rmse,
)

F64 = torch.float64

# Unequally spaced predictions, end of life at t = 10.
#   t_i     = 0, 1, 5, 6, 9
#   r*(t_i) = 10, 9, 5, 4, 1
#   r(t_i)  = 12, 8, 6, 4.5, 0.5
#   |Delta| = 2, 1, 1, 0.5, 0.5;  RA_i = 0.8, 8/9, 0.8, 0.875, 0.5
T = torch.tensor([0.0, 1.0, 5.0, 6.0, 9.0], dtype=F64)
R_TRUE = 10.0 - T
R_PRED = torch.tensor([12.0, 8.0, 6.0, 4.5, 0.5], dtype=F64)
RA = [0.8, 8 / 9, 0.8, 0.875, 0.5]


# --------------------------------------------------------------------------- defects fixed
def test_alpha_bounds_are_inclusive_despite_round_off():
    # (1 - 0.2) * 3 = 2.4000000000000004 and (1 + 0.2) * 3 = 3.5999999999999996 in float64:
    # predictions of 2.4 and 3.6, on the cone [2.4, 3.6], were counted outside
    t, r = torch.tensor([0.0], dtype=F64), torch.tensor([3.0], dtype=F64)
    for p in (2.4, 3.6):
        assert alpha_lambda(t, r, torch.tensor([p], dtype=F64), alpha=0.2, lam=0.0) is True
    lo, hi = (
        torch.tensor([2.4000000000000004], dtype=F64),
        torch.tensor([3.5999999999999996], dtype=F64),
    )
    samples = torch.tensor([[2.4, 3.6, 5.0, math.inf]], dtype=F64)
    assert probability_in_bounds(lo, hi, rul_samples=samples).item() == 0.5
    pmf = torch.tensor([[0.25, 0.25, 0.25]], dtype=F64)  # 0.25 censored
    support = torch.tensor([2.4, 3.6, 5.0], dtype=F64)
    got = probability_in_bounds(lo, hi, rul_pmf=pmf, rul_support=support).item()
    assert got == 0.5
    # PH's point criterion reads the same bounds: r* = 3 - t, alpha 0.2 of t_EoL = 3 (+-0.6)
    t3 = torch.tensor([0.0, 1.0], dtype=F64)
    assert prognostic_horizon(t3, 3.0 - t3, torch.tensor([3.0, 1.0 + 1.2 * 0.5]), alpha=0.2) == 3.0


def test_lambda_index_refuses_unsorted_times_and_a_missing_t_eol():
    # t_lambda = 15: the first prediction made at or after it is t = 20; unsorted, index 1
    # (t = 30) came back
    with pytest.raises(ValueError, match="times must be strictly increasing"):
        lambda_index(torch.tensor([0.0, 30.0, 10.0, 20.0], dtype=F64), 0.3, t_eol=50.0)
    with pytest.raises(TypeError, match="t_eol"):
        lambda_index(T, 0.5, t_eol=None)


def test_predictions_after_end_of_life_are_refused():
    t = torch.tensor([0.0, 4.0, 8.0, 12.0], dtype=F64)
    # lam = 0.9 -> t_lambda = 9; the next prediction (t = 12) is after t_EoL = 10, its cone
    # [(1 - a) r*, (1 + a) r*] = [-1.6, -2.4] is empty: alpha-lambda said False for a perfect
    # prediction
    with pytest.raises(ValueError, match=r"no prediction in \[t_lambda, t_EoL\] = \[9, 10\]"):
        alpha_lambda(t, 10.0 - t, 10.0 - t, alpha=0.2, lam=0.9)
    with pytest.raises(ValueError, match=r"no prediction in \[t_lambda, t_EoL\]"):
        relative_accuracy(t, 10.0 - t, 10.0 - t, lam=0.9)
    # first entry into r* +- 1 at t = 12: PH came out as 10 - 12 = -2
    pred = torch.tensor([15.0, 11.0, 7.0, -2.0], dtype=F64)
    with pytest.raises(ValueError, match=r"times must not be later than t_eol \(10\)"):
        prognostic_horizon(t, 10.0 - t, pred, alpha=0.1)
    # a prediction at t_EoL itself (r* = 0) is still accepted
    t5 = torch.tensor([0.0, 5.0, 10.0], dtype=F64)
    assert alpha_lambda(t5, 10.0 - t5, 10.0 - t5, alpha=0.2, lam=1.0) is True
    assert prognostic_horizon(t5, 10.0 - t5, torch.tensor([20.0, 8.0, 0.0]), alpha=0.1) == 0.0


# --------------------------------------------------------------------------- checked correct
def test_lambda_index_on_unequal_spacing():
    # t_lambda = lam * 10: exactly on t = 5, 6; between 1 and 5, 6 and 9; after 9
    for lam, i in [(0.0, 0), (0.1, 1), (0.15, 2), (0.5, 2), (0.6, 3), (0.61, 4), (0.9, 4)]:
        assert lambda_index(T, lam, t_eol=10.0) == i
    with pytest.raises(ValueError, match="no prediction at or after t_lambda = 9.5"):
        lambda_index(T, 0.95, t_eol=10.0)
    # t_P = 2: t_lambda = 2 + lam * 8
    assert lambda_index(T, 0.0, t_eol=10.0, t_p=2.0) == 2
    assert lambda_index(T, 0.5, t_eol=10.0, t_p=2.0) == 3  # t_lambda = 6


def test_ra_cra_on_unequal_spacing_and_weights():
    assert relative_accuracy(T, R_TRUE, R_PRED, lam=0.5) == pytest.approx(0.8)  # t = 5
    assert relative_accuracy(T, R_TRUE, R_PRED, lam=0.61) == pytest.approx(0.5)  # t = 9
    # Saxena's CRA: p_lambda = {t_P <= t_i <= t_lambda}
    assert cumulative_relative_accuracy(T, R_TRUE, R_PRED) == pytest.approx(sum(RA) / 5)
    assert cumulative_relative_accuracy(T, R_TRUE, R_PRED, lam=0.55) == pytest.approx(
        sum(RA[:3]) / 3
    )
    assert cumulative_relative_accuracy(T, R_TRUE, R_PRED, lam=0.6) == pytest.approx(
        sum(RA[:4]) / 4
    )  # t_lambda = 6 falls on a prediction: included
    w = torch.tensor([0.0, 1.0, 2.0, 3.0, 100.0], dtype=F64)  # t = 9 lies beyond t_lambda
    want = (RA[1] + 2 * RA[2] + 3 * RA[3]) / 6
    assert cumulative_relative_accuracy(T, R_TRUE, R_PRED, lam=0.6, weights=w) == pytest.approx(
        want
    )
    with pytest.raises(ValueError, match="weights"):
        cumulative_relative_accuracy(T, R_TRUE, R_PRED, lam=0.05, weights=w)  # only t = 0
    # t_P = 2 -> i = 2, 3 up to t_lambda = 2 + 0.5 * 8 = 6
    got = cumulative_relative_accuracy(T, R_TRUE, R_PRED, lam=0.5, t_p=2.0)
    assert got == pytest.approx((RA[2] + RA[3]) / 2)
    # paper 002's form on this spacing: lambda 0, .25, .5, .75 -> t = 0, 5 (2.5), 5, 9 (7.5)
    got = cumulative_relative_accuracy(T, R_TRUE, R_PRED, lambdas=(0.0, 0.25, 0.5, 0.75))
    assert got == pytest.approx((RA[0] + RA[2] + RA[2] + RA[4]) / 4)


def test_single_prediction_and_true_rul_zero():
    t, r, p = T[:1], R_TRUE[:1], R_PRED[:1]
    assert prognostic_horizon(t, r, p, alpha=0.2) == 10.0  # |2| <= 0.2 * 10
    assert math.isnan(prognostic_horizon(t, r, p, alpha=0.1))  # |2| > 1: never inside
    assert alpha_lambda(t, r, p, alpha=0.2, lam=0.0) is True  # [8, 12]
    assert alpha_lambda(t, r, p, alpha=0.19, lam=0.0) is False
    assert cumulative_relative_accuracy(t, r, p) == pytest.approx(0.8)  # t_lambda = 10, i = 0
    with pytest.raises(ValueError, match="at least two prediction times"):
        convergence(t, r, p)
    # one step of M = 2 on [0, 10]: centroid (5, 1)
    assert convergence(t, r, p, t_end=10.0) == pytest.approx(math.hypot(5.0, 1.0))
    t0 = torch.tensor([0.0, 10.0], dtype=F64)
    with pytest.raises(ValueError, match="true_rul > 0"):
        relative_accuracy(t0, 10.0 - t0, torch.tensor([10.0, 1.0], dtype=F64), lam=1.0)


def test_prognostic_horizon_first_entry_and_persistent():
    # alpha 0.05 of t_EoL = 10: r* +- 0.5; inside at i = 3, 4 only; PH = 10 - 6
    assert prognostic_horizon(T, R_TRUE, R_PRED, alpha=0.05) == pytest.approx(4.0)
    # in, out, in: first entry at t = 1 (|1| <= 1), but t = 5 has |Delta| = 1.5
    pred = torch.tensor([12.0, 8.0, 6.5, 4.5, 0.5], dtype=F64)
    assert prognostic_horizon(T, R_TRUE, pred, alpha=0.1) == pytest.approx(9.0)
    assert prognostic_horizon(T, R_TRUE, pred, alpha=0.1, persistent=True) == pytest.approx(4.0)
    # asymmetric: under-prediction of 1 at t = 1 needs alpha^- >= 0.1
    assert prognostic_horizon(T, R_TRUE, pred, alpha=(0.05, 0.2)) == pytest.approx(10.0)
    assert prognostic_horizon(T, R_TRUE, pred, alpha=(0.05, 0.1)) == pytest.approx(4.0)


def test_convergence_unequal_spacing():
    # M = 2, 1, 1, 0.5 on [0, 1), [1, 5), [5, 6), [6, 9)
    area = 2 * 1 + 1 * 4 + 1 * 1 + 0.5 * 3
    sx = 1 * 2 + 24 * 1 + 11 * 1 + 45 * 0.5
    sy = 1 * 4 + 4 * 1 + 1 * 1 + 3 * 0.25
    want = math.hypot(sx / (2 * area), sy / (2 * area))
    assert convergence(T, R_TRUE, R_PRED) == pytest.approx(want, rel=1e-12)


def test_batched_rmse_equals_per_series_loop():
    g = torch.Generator().manual_seed(0)
    p = torch.randn(3, 4, 5, generator=g, dtype=F64)
    y = torch.randn(3, 4, 5, generator=g, dtype=F64)
    loop = torch.stack([torch.stack([rmse(p[i, j], y[i, j]) for j in range(4)]) for i in range(3)])
    assert bool((rmse(p, y, dim=-1) == loop).all())
    with pytest.raises(ValueError, match=r"times must be 1-D with shape \(n,\), got \(2, 5\)"):
        alpha_lambda(T.expand(2, 5), R_TRUE.expand(2, 5), R_PRED.expand(2, 5), alpha=0.2, lam=0.5)


def test_the_protocol_cone_is_the_metrics_cone():
    """rul_scores (the RUL studies' alpha-lambda) compared (1 - a) r <= p <= (1 + a) r in
    floating point, so 0.8 x 3 = 2.4000000000000004 left out a prediction of 2.4, where the
    metrics' inclusive cone takes it (in_alpha_cone)."""
    from prognos_torch.metrics import in_alpha_cone
    from prognos_torch.prognosis.protocol import rul_scores

    times = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    r = 5.0 - times  # 4, 3, 2
    p = torch.tensor([4.0 * 1.3, 2.4, 2.0 * 0.69], dtype=F64)
    want = [True, True, False]
    assert in_alpha_cone(p, r, 0.3).tolist() == want
    assert in_alpha_cone(p, r, 0.2).tolist() == [False, True, False]
    s = rul_scores(times, r, p, t_onset=0.0, t_eol=5.0)
    assert s["in_cone_0.3"].tolist() == want and s["alpha_lambda_0.2"] == 1 / 3
    assert not bool(in_alpha_cone(torch.tensor([math.inf, math.nan], dtype=F64), 3.0, 0.3).any())
