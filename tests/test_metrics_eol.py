"""End of life from an indicator, the restricted-mean RUL and the paper-002 score bundle."""

from __future__ import annotations

import math

import pytest
import torch

from prognos_torch.metrics import (
    PointRULScores,
    alpha_lambda,
    cumulative_relative_accuracy,
    exponential_accuracy,
    first_crossing_time,
    point_rul_scores,
    rmse,
)
from prognos_torch.prognosis import rul_distribution

t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731


def test_first_crossing_time():
    times = t([0.0, 0.5, 1.25, 2.0, 3.0])
    z = t([0.0, 0.05, 0.1, 0.08, 0.2])
    assert first_crossing_time(times, z, 0.1) == 1.25  # reaching the threshold counts
    assert first_crossing_time(times, z, 0.15) == 3.0
    assert math.isnan(first_crossing_time(times, z, 0.3))
    assert first_crossing_time(times, -z, -0.07, direction="below") == 1.25
    assert first_crossing_time(times, t([math.nan, 0.2, 0, 0, 0]), 0.1) == 0.5  # NaN: missing
    with pytest.raises(ValueError, match="values must have shape"):
        first_crossing_time(times, z[:3], 0.1)
    with pytest.raises(ValueError, match="direction"):
        first_crossing_time(times, z, 0.1, direction="up")
    with pytest.raises(ValueError, match="threshold"):
        first_crossing_time(times, z, math.inf)


def test_restricted_mean_is_the_mean_of_min_rul_and_horizon_over_weighted_paths():
    g = torch.Generator().manual_seed(0)
    paths = torch.randn(2, 40, 6, generator=g, dtype=torch.float64).cumsum(-1)  # (B, N, H)
    w = torch.rand(2, 40, generator=g, dtype=torch.float64)
    w = w / w.sum(-1, keepdim=True)
    d = rul_distribution(paths, 1.5, w, dt=0.25)
    want = torch.zeros(2, dtype=torch.float64)
    for b in range(2):
        for i in range(40):
            hit = torch.nonzero(paths[b, i] >= 1.5).flatten()
            life = 0.25 * (int(hit[0]) + 1) if hit.numel() else 0.25 * 6  # min(RUL, H dt)
            want[b] += w[b, i] * life
    assert float(d.censored_mass.min()) > 0  # some paths are censored: a strict lower bound
    torch.testing.assert_close(d.restricted_mean, want, rtol=1e-13, atol=0)
    full = rul_distribution(paths, -100.0, w, dt=0.25)  # every path crosses at step 1
    torch.testing.assert_close(full.restricted_mean, full.expectation)


def test_rul_scores_bundle_the_table_2_metrics():
    times = t([9.0, 9.5, 10.0, 10.5])
    true = 11.0 - times
    pred = t([1.7, 1.6, 1.2, 0.4])
    s = point_rul_scores(times, true, pred, t_eol=11.0, d0=2.0)
    assert isinstance(s, PointRULScores)
    assert s.accuracy == exponential_accuracy(true, pred, d0=2.0)
    assert s.rmse == float(rmse(pred, true))
    assert s.alpha_lambda == float(alpha_lambda(times, true, pred, alpha=0.3, lam=0.5, t_eol=11.0))
    assert s.cra == cumulative_relative_accuracy(
        times, true, pred, lambdas=(0.0, 0.25, 0.5, 0.75), t_eol=11.0
    )
    # by hand: lambda = 0.5 -> t = 10 (true 1.0, pred 1.2, inside +-30 %)
    assert s.alpha_lambda == 1.0
    assert s.rmse == pytest.approx(math.sqrt((0.3**2 + 0.1**2 + 0.2**2 + 0.1**2) / 4), rel=1e-12)
    ra = [1 - 0.3 / 2.0, 1 - 0.1 / 1.5, 1 - 0.2 / 1.0, 1 - 0.1 / 0.5]
    assert s.cra == pytest.approx(sum(ra) / 4, rel=1e-12)
    s2 = point_rul_scores(times, true, pred, t_eol=11.0, d0=2.0, alpha=0.1, cra_lambdas=(0.0,))
    assert s2.alpha_lambda == 0.0 and s2.cra == pytest.approx(ra[0], rel=1e-12)


def test_binned_rul_pmf_sums_consecutive_steps():
    g = torch.Generator().manual_seed(1)
    paths = torch.randn(3, 50, 7, generator=g, dtype=torch.float64).cumsum(-1)  # (B, N, H=7)
    d = rul_distribution(paths, 1.0, dt=0.5)
    support, pmf = d.binned(3)  # bins of steps 1-3 and 4-6; step 7 is dropped
    assert support.shape == (2,) and pmf.shape == (3, 2)
    torch.testing.assert_close(support, torch.tensor([1.0, 2.5], dtype=torch.float64))
    torch.testing.assert_close(pmf[:, 0], d.pmf[:, :3].sum(-1), rtol=0, atol=0)
    torch.testing.assert_close(pmf[:, 1], d.pmf[:, 3:6].sum(-1), rtol=0, atol=0)
    one_support, one = d.binned(10)  # fewer steps than a bin: one bin of all of them
    torch.testing.assert_close(one[:, 0], d.pmf.sum(-1), rtol=1e-15, atol=0)
    assert float(one_support[0]) == 2.0  # mean of 0.5 * (1..7)
    with pytest.raises(ValueError, match="width"):
        d.binned(0)
