"""Synthetic run-to-failure families: closed forms, noise scale, onset and protocol, bad input."""

from __future__ import annotations

import math

import pytest
import torch

from prognos_torch.prognosis.protocol import known_threshold_protocol
from prognos_torch.systems.run_to_failure import (
    RUN_TO_FAILURE_FAMILIES,
    run_to_failure_set,
    simulate_run_to_failure,
)


@pytest.fixture(scope="module")
def records():
    return run_to_failure_set(4, seed=11)


def test_reproducible_from_the_seed_and_different_between_seeds():
    a = run_to_failure_set(1, seed=5)
    b = run_to_failure_set(1, seed=5)
    c = run_to_failure_set(1, seed=6)
    for k in a:
        torch.testing.assert_close(a[k].y, b[k].y, rtol=0, atol=0)
        assert a[k].y.shape != c[k].y.shape or not torch.equal(a[k].y, c[k].y)


def test_healthy_before_onset_and_final_rise(records):
    for r in records.values():
        assert bool((torch.diff(r.t) > 0).all()) and bool(torch.isfinite(r.y).all())
        y0, rise = r.params["y0"], r.params["rise"]
        before = r.t <= r.onset
        torch.testing.assert_close(r.degradation[before], torch.full_like(r.t[before], y0))
        if r.family != "two_phase":  # the two-phase level carries its AR(1) wander at the end
            assert float(r.degradation[-1]) == pytest.approx(y0 * (1 + rise), rel=1e-12)


def test_shocks_and_paris_are_monotone(records):
    for r in records.values():
        if r.family in ("shocks", "paris"):
            assert bool((torch.diff(r.degradation) >= 0).all())


def test_paris_law_growth_rate():
    """da/ds = C a^(m/2) (Paris-Erdogan with dK ~ sqrt(a)): the log-log slope of the central
    finite-difference rate against the crack size is m / 2."""
    g = torch.Generator().manual_seed(2)
    r = simulate_run_to_failure("paris", g, dt=1e-3, life=(3.0, 3.0), gaps=False)
    p = r.params
    a = 1.0 + (r.degradation - p["y0"]) * (p["a_final"] - 1.0) / (p["y0"] * p["rise"])
    s = r.t - r.onset
    k = torch.nonzero(s > 0).flatten()[1:-1]
    rate = (a[k + 1] - a[k - 1]) / (r.t[k + 1] - r.t[k - 1])
    X = torch.stack([torch.ones_like(rate), a[k].log()], -1)
    coef = torch.linalg.lstsq(X, rate.log()[:, None]).solution
    assert float(coef[1]) == pytest.approx(p["m"] / 2.0, rel=1e-3)


def test_noise_scale_and_student_t():
    g = torch.Generator().manual_seed(4)
    for _ in range(6):
        r = simulate_run_to_failure("hump", g, life=(30.0, 30.0), gaps=False)
        e = r.y - r.degradation
        # 4,320 samples: the sample std is within 10 % (heavier tails widen it for 3 dof)
        assert float(e.std()) == pytest.approx(r.params["noise_sd"], rel=0.1 if
                                               r.params["t_dof"] != 3 else 0.35)  # fmt: skip


def test_the_protocol_finds_onset_after_the_true_onset(records):
    for name, r in records.items():
        pc = known_threshold_protocol(r.t, r.y)
        assert pc.valid, name
        assert pc.t_onset >= r.onset - 1e-9, name  # no false alarm in the healthy part
        assert pc.t_eol <= float(r.t[-1])


def test_bad_input():
    g = torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match="family must be one of"):
        simulate_run_to_failure("weibull", g)
    with pytest.raises(TypeError, match="generator must be a torch.Generator"):
        simulate_run_to_failure("paris", 0)
    with pytest.raises(ValueError, match="dt must be a finite positive number"):
        simulate_run_to_failure("paris", g, dt=0.0)
    with pytest.raises(ValueError, match="onset must satisfy"):
        simulate_run_to_failure("paris", g, onset=(0.5, 1.2))
    with pytest.raises(TypeError, match="life must be a tuple"):
        simulate_run_to_failure("paris", g, life=10.0)
    with pytest.raises(ValueError, match="at least 50"):
        simulate_run_to_failure("paris", g, life=(0.1, 0.1))
    with pytest.raises(ValueError, match="per_family must be an int"):
        run_to_failure_set(0)
    assert set(RUN_TO_FAILURE_FAMILIES) == {"shocks", "paris", "two_phase", "hump"}
    assert not math.isnan(run_to_failure_set(1)["hump 0"].onset)
