"""Scoring forecast-fed fault prediction: rolling forecasts, alarms, threshold crossings, errors."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import sckf
from prognos_torch.prognosis import (
    ThresholdCrossings,
    aligned_forecasts,
    first_alarm,
    origin_fading_factors,
    persistence_forecasts,
    predict_threshold_crossings,
    rolling_forecasts,
)
from prognos_torch.studies import (
    crossing_scores,
    crossing_table,
    fault_prediction_errors,
    rolling_forecast_rmse,
)

F64 = torch.float64


class _Trend:
    """Forecasts z_{k+j} = z_k + slope j (per run); a reference with a closed form."""

    def __init__(self, slope):
        self.slope, self.last = torch.as_tensor(slope, dtype=F64), None

    @property
    def initialized(self):
        return self.last is not None

    def copy(self):
        c = _Trend(self.slope)
        c.last = self.last
        return c

    def initialize(self, z0):
        self.last = z0[-1]
        return self

    def update(self, z):
        self.last = z
        return self

    def forecast(self, n):
        j = torch.arange(1, n + 1, dtype=F64).reshape(n, *([1] * self.last.dim()))
        return self.last + self.slope * j  # (n, R, 1)


def _record(T=30, R=2):
    g = torch.Generator().manual_seed(2)
    return torch.rand(T, R, 1, generator=g, dtype=F64).cumsum(0) * 0.1


def test_rolling_aligned_and_persistence_forecasts():
    ys = _record()
    fc = _Trend(torch.tensor([[0.5], [0.0]]))
    zf = rolling_forecasts(fc, ys, 4, 10)
    assert zf.shape == (21, 4, 2, 1) and not fc.initialized  # the input is copied
    for k in range(10, 31):
        for j in range(1, 5):
            ref = ys[k - 1] + fc.slope * j
            torch.testing.assert_close(zf[k - 10, j - 1], ref, rtol=0, atol=0)
    al = aligned_forecasts(zf, 3)  # row t - 11: forecast of z_t made at t - 3
    assert al.shape == (20, 2, 1) and torch.isnan(al[:2]).all()
    for t in range(13, 31):
        torch.testing.assert_close(al[t - 11], zf[t - 3 - 10, 2], rtol=0, atol=0)
    zp = persistence_forecasts(ys, 4, 10)
    assert zp.shape == zf.shape
    torch.testing.assert_close(zp[5, 3], ys[14], rtol=0, atol=0)
    with pytest.raises(ValueError, match="1..4"):
        aligned_forecasts(zf, 5)


def test_first_alarm_and_origin_fading_factors():
    K = 30
    pred = torch.full((K, 3, 1), 1.0, dtype=F64)
    pred[7:, 0] = 1.2  # run 0: origin index 7 -> k = N0 + 7
    pred[0:, 1] = 1.2  # run 1: crosses at the first origin; run 2 never
    N0, n = 150, 10
    res = SimpleNamespace(predicted=pred, origin=torch.arange(N0, N0 + K), n=n)
    got = first_alarm(res, 1.15)
    assert got[0].item() == N0 + 7 + n and got[1].item() == N0 + n and math.isnan(got[2].item())
    lam = torch.rand(K, n, 3, dtype=F64)
    res = SimpleNamespace(
        fading_factors=lam, origin=torch.arange(N0, N0 + K), filtered=torch.zeros(N0 + K - 1, 3)
    )
    out = origin_fading_factors(res)
    assert out.shape == (N0 + K - 1, 3) and torch.isnan(out[: N0 - 1]).all()
    torch.testing.assert_close(out[N0 - 1 :], lam[:, -1], rtol=0, atol=0)


def test_threshold_crossings_follow_the_forecast_trend():
    # a random walk observed almost without noise: the filter's parameter path follows the
    # pseudo-measurements z_kp + slope j, so the crossing is the first j with that >= threshold
    ys = _record()
    one = torch.ones(1, 1, dtype=F64)
    model = linear_gaussian_model(one, one, 0.1 * one, 1e-7 * one)
    b0 = GaussianBelief(torch.zeros(2, 1, dtype=F64), torch.ones(2, 1, 1, dtype=F64))
    slope = torch.tensor([[0.037], [0.0]], dtype=F64)
    thr, H, times = 2.0, 40, [10, 20, 25]
    cr = predict_threshold_crossings(
        sckf(), model, b0, ys, _Trend(slope), times, H, thr, param_index=0
    )
    assert isinstance(cr, ThresholdCrossings) and cr.diverged == 0
    assert cr.crossing.shape == (3, 2)
    for p, kp in enumerate(times):
        z = float(ys[kp - 1, 0, 0])
        j = next((j for j in range(1, H + 1) if z + 0.037 * j >= thr), None)
        want = math.nan if j is None else kp + j
        assert cr.crossing[p, 0].item() == pytest.approx(want, nan_ok=True)
        assert math.isnan(cr.crossing[p, 1].item())  # no trend: censored (ys stays below 2)
        assert cr.rul()[p, 0].item() == pytest.approx(want - kp, nan_ok=True)
    with pytest.raises(ValueError, match="increasing"):
        predict_threshold_crossings(
            sckf(), model, b0, ys, _Trend(slope), [5, 5], H, thr, param_index=0
        )


def test_fault_prediction_errors_and_forecast_rmse_match_numpy():
    g = torch.Generator().manual_seed(4)
    N0, T, n, R = 5, 12, 3, 2
    theta = torch.rand(T + n + 1, R, 1, generator=g, dtype=F64)
    pred = torch.rand(T - N0 + 1, R, 1, generator=g, dtype=F64)
    filt = torch.rand(T, R, 1, generator=g, dtype=F64)
    res = SimpleNamespace(predicted=pred, filtered=filt, origin=torch.arange(N0, T + 1), n=n)
    e = fault_prediction_errors(res, theta)
    th, p, f = theta[..., 0].numpy(), pred[..., 0].numpy(), filt[..., 0].numpy()
    for r in range(R):
        d = p[:, r] - th[N0 + n : T + n + 1, r]
        assert e["MAE"][r].item() == pytest.approx(np.abs(d).mean(), rel=1e-14)
        assert e["RMSE"][r].item() == pytest.approx(np.sqrt((d**2).mean()), rel=1e-14)
        df = f[N0 - 1 :, r] - th[N0 : T + 1, r]
        assert e["filt_RMSE"][r].item() == pytest.approx(np.sqrt((df**2).mean()), rel=1e-14)
    x = torch.rand(T + n + 1, R, 2, generator=g, dtype=F64)
    zf = torch.rand(T - N0 + 1, n, R, 2, generator=g, dtype=F64)
    got = rolling_forecast_rmse(zf, x, N0)
    for j in range(n):
        for c in range(2):
            d = np.array(
                [zf[k - N0, j, :, c].numpy() - x[k + j + 1, :, c].numpy() for k in range(N0, T + 1)]
            )
            assert got[j, c].item() == pytest.approx(np.sqrt((d**2).mean()), rel=1e-14)


def test_crossing_scores_and_table():
    cr = ThresholdCrossings(
        torch.tensor([150, 175, 200]),
        torch.tensor([[230.0, math.nan], [226.0, math.nan], [221.0, 240.0]], dtype=F64),
        0,
    )
    s = crossing_scores(cr, 223, at=(175,))
    assert s["RUL_err@175"].tolist()[0] == 3.0 and math.isnan(s["RUL_err@175"][1].item())
    assert s["cross_MAE"].tolist() == [pytest.approx((7 + 3 + 2) / 3), 17.0]
    assert s["censored"].tolist() == [0.0, pytest.approx(2 / 3)]
    t = crossing_table({"A": cr}, 223).splitlines()
    assert t[0] == "| k_p | true RUL | A pred. RUL (median) | A censored |"
    # torch.median of an even count: the lower middle value
    assert t[2] == "| 150 | 73 | 80 | 0.50 |" and t[4] == "| 200 | 23 | 21 | 0.00 |"
    with pytest.raises(ValueError, match="not one of the prediction times"):
        crossing_scores(cr, 223, at=(160,))
