"""Forecasts and RULs of a fitted model against exact references computed by hand: the
closed-form Kalman filter of a linear learner, the noise-free recursion of a learner, and the
first passages of the returned paths on an uneven time axis."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from _ar2_reference import ar2_kalman_forecast, ar2_model

from prognos_torch.prognosis.paths import recursive_predict
from prognos_torch.workflow import Series, fit_series, forecast, rul
from prognos_torch.workflow.fitted import FittedModel


def test_forecast_of_a_linear_learner_is_the_closed_form_kalman_filter():
    """Every Gaussian filter is exact for a linear learner: the forecast is the Kalman filter
    over the last filter_steps values (NaN: predict only) started from the window with std r,
    then H predict steps, with q = r = sigma / sqrt(2) on the newest element."""
    sigma, H, fs = 0.04, 5, 5
    model, x = ar2_model(sigma)
    x[7] = x[9] = math.nan  # missing values inside the filtered steps, the last one too
    lo, span = 1.0, 2.3
    means, stds = ar2_kalman_forecast(((x - lo) / span).numpy(), 3, H, sigma)
    means, stds = lo + span * means, span * stds
    zq = 1.6448536269514722  # level 0.9
    for name in ("ekf", "sckf", "ukf"):
        fc = forecast(model, Series(x), H, filter=name, filter_steps=fs, level=0.9)
        assert fc.extrapolation.abs().max() == 0
        np.testing.assert_allclose(fc.mean.detach().numpy(), means, rtol=0, atol=1e-13)
        np.testing.assert_allclose(fc.std.detach().numpy(), stds, rtol=0, atol=1e-13)
        np.testing.assert_allclose(fc.upper.detach().numpy(), means + zq * stds, atol=1e-12)
        np.testing.assert_allclose(fc.lower.detach().numpy(), means - zq * stds, atol=1e-12)
        np.testing.assert_allclose(fc.time.numpy(), 9.0 + np.arange(1, H + 1))


def test_a_noise_free_learner_forecasts_and_fails_along_its_own_recursion():
    """A series that the learner reproduces exactly and no residual noise: every filter's
    forecast is the learner's recursive prediction, and every RUL quantile is the step at
    which that recursion first reaches the threshold, times the series' step."""
    rng = np.random.default_rng(0)
    x = 1 + 0.3 * np.sin(np.arange(60) / 4) + 0.02 * rng.standard_normal(60)
    fitted = fit_series(Series(x), "elm", None, 3, holdout=0)
    model = FittedModel(fitted.learner, fitted.scaler, dict(fitted.config, residual_rmse=0.0))
    z0 = model.scaler.transform(torch.as_tensor(x[:3]))
    with torch.no_grad():
        traj = model.scaler.inverse_transform(
            torch.cat([z0, recursive_predict(model.learner, z0, 37)])
        )
    s = Series(traj[:30], time=0.5 * torch.arange(30, dtype=torch.float64))
    ahead = traj[30:40]
    peak = int(ahead.argmax())
    assert ahead[peak] > traj[29]
    thr = float(ahead[peak]) - 1e-3
    first = int((ahead >= thr).nonzero()[0, 0]) + 1
    for name, tol in (("sckf", 1e-9), ("ekf", 1e-9), ("pf", 1e-5), ("stpf", 1e-5)):
        fc = forecast(model, s, 10, filter=name, n_particles=20)
        torch.testing.assert_close(fc.mean, ahead, rtol=0, atol=tol)
        r = rul(model, s, thr, horizon=10, filter=name, n_particles=20)
        sm = r.summary()
        assert sm["q05"] == sm["median"] == sm["q95"] == sm["mean"] == pytest.approx(0.5 * first)
        assert sm["censored_mass"] == 0 and r.t_last == 14.5


def test_rul_summary_on_an_uneven_time_axis_is_the_weighted_first_passage_by_hand():
    """Median, q05, q95, mean (withheld when censored), censored mass, bound and
    P(RUL <= h) from the returned paths and weights, each path's RUL its first step at or
    past the threshold times the median step of an uneven time axis."""
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.5, 1.5, 60))
    x = 1 + 0.02 * np.arange(60) + 0.05 * rng.standard_normal(60)
    s = Series(x, time=t)
    model = fit_series(s, "elm", None, 3, holdout=0)
    dt = float(np.median(np.diff(t)))
    for name, extra, H in (("pf", 0.15, 30), ("sckf", 0.3, 10)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = rul(model, s, float(x.max()) + extra, horizon=H, filter=name, n_particles=50,
                    filter_steps=20, seed=3)  # fmt: skip
        paths, w = r.paths.numpy(), r.weights.numpy()
        fp = np.array([np.flatnonzero(p >= r.threshold)[:1].sum() + 1 if (p >= r.threshold).any()
                       else 0 for p in paths])  # fmt: skip
        ruls = np.where(fp > 0, fp * dt, np.inf)
        order = np.argsort(ruls, kind="stable")
        cum, sorted_ruls = np.cumsum(w[order]), ruls[order]
        want = {k: sorted_ruls[np.searchsorted(cum, q - 1e-12)]
                for k, q in (("q05", 0.05), ("median", 0.5), ("q95", 0.95))}  # fmt: skip
        cens = w[fp == 0].sum()
        sm = r.summary()
        assert r.dt == dt and sm["bound"] == pytest.approx(H * dt)
        assert sm["censored_mass"] == pytest.approx(cens, abs=1e-12)
        for key, v in want.items():  # a quantile beyond the horizon is None
            assert sm[key] == (pytest.approx(v) if np.isfinite(v) else None), key
        if cens > 0:
            assert sm["mean"] is None
        else:
            assert sm["mean"] == pytest.approx((w * ruls).sum())
        assert r.failure_probability(5 * dt) == pytest.approx(w[(fp > 0) & (fp <= 5)].sum())
    assert cens > 0 and sm["q95"] is None  # the second case is partly censored
