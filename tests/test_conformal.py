"""Split-conformal RUL intervals (CQR on the log RUL): the rank rule, the finite-sample coverage
guarantee by Monte Carlo against its exact bounds, leave-one-group-out, the protocol replay of
``calibrate_rul`` and bad input."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from dataclasses import replace

import pytest
import torch

from prognos_torch.prognosis.conformal import (
    RULCalibration,
    calibrate_intervals,
    conformal_margin,
    interval_scores,
    leave_one_group_out,
    points_needed,
)
from prognos_torch.prognosis.protocol import known_threshold_protocol
from prognos_torch.systems import run_to_failure_set
from prognos_torch.workflow import calibrate_rul, prognose

T = lambda *v: torch.tensor(v, dtype=torch.float64)  # noqa: E731


def test_scores_are_the_log_factor_by_which_the_truth_misses():
    e = interval_scores(
        T(1.0, 2.0, 0.5, 1.0), T(4.0, math.inf, 1.0, 2.0), T(0.5, 3.0, 2.0, math.nan)
    )
    assert e[0].item() == pytest.approx(math.log(2.0))  # below: log(1 / 0.5)
    assert e[1].item() == pytest.approx(math.log(2.0 / 3.0))  # inside, open upper end
    assert e[2].item() == pytest.approx(math.log(2.0))  # above: log(2 / 1)
    assert math.isnan(e[3].item())


def test_margin_is_the_ceil_n_plus_one_c_th_smallest_score():
    s = torch.arange(1.0, 10.0, dtype=torch.float64)[torch.randperm(9)]  # 1..9 shuffled
    assert conformal_margin(s, 0.9) == 9.0  # ceil(10 * 0.9) = 9
    assert conformal_margin(s, 0.5) == 5.0  # ceil(5) = 5
    assert conformal_margin(s[:8], 0.9) == math.inf  # ceil(9 * 0.9) = 9 > 8 points
    assert conformal_margin(torch.cat([s, T(math.nan)]), 0.5) == 5.0  # NaN left out
    # points_needed: the fewest points with a finite margin, at the margin's own rank rule
    for c in (0.5, 0.8, 0.9, 0.95, 0.99):
        k = points_needed(c)
        scores = torch.arange(1.0, k + 1.0, dtype=torch.float64)
        assert math.isfinite(conformal_margin(scores, c))
        if k > 1:  # one point fewer: the rank passes the count
            assert conformal_margin(scores[:-1], c) == math.inf
    assert (points_needed(0.9), points_needed(0.95)) == (9, 19)
    with pytest.raises(ValueError, match="coverage must lie in"):
        points_needed(1.0)


@pytest.mark.parametrize("half_width, bias", [(0.3, 0.0), (2.5, 0.0), (0.8, 1.0)])
def test_coverage_lies_within_the_finite_sample_bounds(half_width, bias):
    # exchangeable points: log RUL = mu + z, z ~ N(0, 1); the model's interval exp(mu + bias +-
    # half_width) is too narrow, too wide or off-centre. After calibration on n points the
    # coverage of a new point, averaged over calibration sets, lies in [c, c + 1 / (n + 1)]
    # (Romano et al. 2019, Theorems 1 and 2). Coverage given Q is exact (normal CDF), so the only
    # Monte Carlo error is over R calibration sets: sd <= 0.035 / sqrt(R).
    g = torch.Generator().manual_seed(7)
    n, R, c = 44, 3000, 0.9  # (n + 1) c = 40.5: the rank rule ceil((n + 1) c) = 41, not 40
    normal = torch.distributions.Normal(0.0, 1.0)
    cov = torch.empty(R, dtype=torch.float64)
    for r in range(R):
        mu = 3.0 * torch.rand(n, generator=g, dtype=torch.float64)
        y = mu + torch.randn(n, generator=g, dtype=torch.float64)
        lo, hi = (mu + bias - half_width).exp(), (mu + bias + half_width).exp()
        q = calibrate_intervals(lo, hi, y.exp(), c).margin
        w = half_width + q  # new interval: log r in mu + bias +- w
        cov[r] = (normal.cdf(T(bias + w)) - normal.cdf(T(bias - w))).clamp(min=0.0).item()
    tol = 4 * 0.035 / math.sqrt(R)
    assert c - tol <= cov.mean().item() <= c + 1.0 / (n + 1) + tol


def test_leave_one_group_out_is_calibration_on_the_other_groups():
    g = torch.Generator().manual_seed(1)
    lo = torch.rand(12, generator=g, dtype=torch.float64) + 0.5
    hi = lo * 2.0
    hi[3] = math.inf
    tr = torch.rand(12, generator=g, dtype=torch.float64) * 3 + 0.1
    lo[5] = math.nan  # a point without an interval
    groups = ["a"] * 4 + ["b"] * 4 + ["c"] * 4
    new_lo, new_hi, margin = leave_one_group_out(lo, hi, tr, groups, 0.8)
    for k in range(3):
        mine = slice(4 * k, 4 * k + 4)
        other = torch.ones(12, dtype=torch.bool)
        other[mine] = False
        cal = calibrate_intervals(lo[other], hi[other], tr[other], 0.8)
        a, b = cal.interval(lo[mine], hi[mine])
        torch.testing.assert_close(new_lo[mine], a, equal_nan=True, rtol=0, atol=0)
        torch.testing.assert_close(new_hi[mine], b, equal_nan=True, rtol=0, atol=0)
        ok = ~torch.isnan(lo[mine])
        assert bool((margin[mine][ok] == cal.margin).all())
    assert math.isnan(margin[5].item()) and math.isnan(new_lo[5].item())
    assert new_hi[3].item() == math.inf


def test_interval_keeps_open_ends_and_an_infinite_margin_opens_both():
    cal = RULCalibration(math.log(2.0), 0.9, 10)
    lo, hi = cal.interval(T(1.0, 0.0, math.nan), T(3.0, math.inf, 1.0))
    assert lo.tolist()[:2] == [0.5, 0.0] and math.isnan(lo[2].item())
    assert hi.tolist() == [6.0, math.inf, 2.0]
    a, b = cal.interval(1.0, 3.0)
    assert a.dim() == 0 and (a.item(), b.item()) == (0.5, 6.0)
    lo, hi = RULCalibration(math.inf, 0.9, 3).interval(T(1.0, 0.0), T(2.0, 0.0))
    assert lo.tolist() == [0.0, 0.0] and hi.tolist() == [math.inf, math.inf]


def test_a_margin_of_minus_inf_keeps_open_intervals_and_empties_the_others():
    # most calibration intervals [0, inf): their scores are -inf, and so is Q; the CQR set
    # {r: E(r) <= -inf} is everything for [0, inf) and nothing for any other interval
    lo, hi = torch.cat([torch.zeros(20), T(5.0)]), torch.cat([torch.full((20,), math.inf), T(10.0)])
    cal = calibrate_intervals(lo.double(), hi.double(), torch.full((21,), 7.0, dtype=torch.float64))
    assert cal.margin == -math.inf
    a, b = cal.interval(T(0.0, 2.0, 5.0), T(math.inf, math.inf, 10.0))
    assert a.tolist() == [0.0, math.inf, math.inf] and b.tolist() == [math.inf, math.inf, 0.0]
    # (a margin whose e^Q underflows does the same, not 0 / 0)
    a, b = RULCalibration(-800.0, 0.9, 9).interval(T(0.0, 1.0), T(math.inf, 3.0))
    assert a.tolist() == [0.0, math.inf] and b.tolist() == [math.inf, 0.0]


def test_a_calibrated_summary_says_when_its_interval_is_empty():
    class Result:  # what summary() reads of a RULResult
        threshold, direction, n_particles = 1.0, "above", 100

        def __init__(self, q05, q95):
            self.s = {"status": "ok", "q05": q05, "q95": q95, "median": 2.0, "bound": 50.0}

        def summary(self):
            return dict(self.s)

    narrow, wide = Result(1.8, 2.2), Result(1.0, 4.0)
    cal = RULCalibration(-0.5, 0.9, 20)  # narrows by e^0.5 = 1.65 at each end
    s = cal.summary(narrow)["calibrated"]
    assert s["q05"] > s["q95"] and s["empty"] is True
    s = cal.summary(wide)["calibrated"]
    assert s["q05"] < s["q95"] and s["empty"] is False
    assert RULCalibration(-math.inf, 0.9, 20).summary(wide)["calibrated"]["empty"] is True


@pytest.mark.parametrize(
    "args, match",
    [
        ((T(1.0, 2.0), T(2.0), T(1.0, 1.0)), r"same shape \(n,\).*upper \(1,\)"),
        ((T(2.0), T(1.0), T(1.0)), "upper must be >= lower"),
        ((T(-1.0), T(1.0), T(1.0)), "lower must be finite and >= 0"),
        ((T(math.inf), T(math.inf), T(1.0)), "lower must be finite"),
        ((T(1.0), T(2.0), T(0.0)), "truth must be finite and > 0"),
        ((torch.ones(2, 2), torch.ones(2, 2), torch.ones(2, 2)), r"lower must have shape \(n,\)"),
    ],
)
def test_bad_intervals_are_refused_by_name(args, match):
    with pytest.raises(ValueError, match=match):
        interval_scores(*args)


def test_bad_coverage_and_empty_scores_are_refused():
    with pytest.raises(ValueError, match=r"coverage must lie in \(0, 1\)"):
        conformal_margin(T(1.0), 1.0)
    with pytest.raises(TypeError, match="coverage must be a float"):
        conformal_margin(T(1.0), True)
    with pytest.raises(ValueError, match="no non-NaN entry"):
        conformal_margin(T(math.nan), 0.9)
    with pytest.raises(ValueError, match="groups must have 2 labels"):
        leave_one_group_out(T(1.0, 1.0), T(2.0, 2.0), T(1.0, 1.0), ["a"])
    with pytest.raises(ValueError, match="groups must have 2 labels"):  # not one per character
        leave_one_group_out(T(1.0, 1.0), T(2.0, 2.0), T(1.0, 1.0), "ab")


def test_calibration_record_round_trips_and_refuses_bad_fields():
    import json

    for margin, assets in ((0.25, None), (-0.1, 3), (math.inf, 12), (-math.inf, 2)):
        cal = RULCalibration(margin, 0.9, 12, {"method": "auto", "threshold": "protocol"},
                             assets=assets)  # fmt: skip
        back = RULCalibration.from_dict(json.loads(json.dumps(cal.to_dict())))
        assert back == cal
    ok = {"margin": 0.1, "coverage": 0.9, "n": 5}
    for bad, match in [
        ({"coverage": 0.9, "n": 5}, "has no margin"),
        (dict(ok, margin="0.1"), "margin must be a number, null"),
        (dict(ok, coverage=1.0), r"coverage must lie in \(0, 1\)"),
        (dict(ok, n=-1), "n must be a count"),
        (dict(ok, n=True), "n must be a count"),
        (dict(ok, settings=[1]), "settings must be a mapping"),
        (dict(ok, assets=0), "assets must be a count >= 1 or null"),
        (dict(ok, assets=2.0), "assets must be a count >= 1 or null"),
    ]:
        with pytest.raises(ValueError, match=match):
            RULCalibration.from_dict(bad)
    with pytest.raises(TypeError, match="must be a mapping"):
        RULCalibration.from_dict([0.1, 0.9, 5])


def test_assets_are_counted_among_points_with_an_interval_and_warned_below_the_need():
    lo, hi = T(1.0, 1.0, 1.0, math.nan, 1.0), T(2.0, 2.0, 2.0, math.nan, 2.0)
    tr = T(1.5, 3.0, 0.5, 1.0, 1.2)
    cal = calibrate_intervals(lo, hi, tr, 0.5, groups=["a", "a", "b", "c", "d"])
    assert (cal.n, cal.assets) == (4, 3)  # "c" has no interval
    assert calibrate_intervals(lo, hi, tr, 0.5).assets is None
    with pytest.raises(ValueError, match="groups must be 5 labels"):
        calibrate_intervals(lo, hi, tr, groups=["a", "b"])
    # finite margin from 8 assets at 90 %: the warning; 9 assets, an infinite margin or no
    # record: none
    few = RULCalibration(0.2, 0.9, 40, assets=8).warning("histories")
    assert few.startswith("the points come from 8 histories") and "assured from 9 histories" in few
    assert RULCalibration(0.2, 0.9, 40, assets=9).warning() is None
    assert RULCalibration(math.inf, 0.9, 8, assets=2).warning() is None
    assert RULCalibration(0.2, 0.9, 40).warning() is None


def test_bins_of_the_predicted_median_have_their_own_margin():
    import json

    g = torch.Generator().manual_seed(5)
    n = 300
    med = torch.exp(3 * torch.rand(n, generator=g, dtype=torch.float64))
    med[:10] = math.inf  # censored medians: the top bin
    lo, hi = torch.where(med.isinf(), 50.0, med / 2), med * 2  # censored: open to the right
    # the model misses more at short RULs: truth spread grows as the median shrinks
    spread = 1.5 / (1 + torch.where(med.isinf(), 100.0, med).log())
    tr = torch.where(med.isinf(), 50.0, med) * torch.exp(spread * torch.randn(n, generator=g,
                                                                            dtype=torch.float64))  # fmt: skip
    cal = calibrate_intervals(lo, hi, tr, 0.9, median=med, bins=3)
    z = torch.where(med.isinf(), math.inf, med.log())
    order = torch.sort(z).values
    edges = [0.5 * float(order[c - 1] + order[c]) for c in (100, 200)]
    assert cal.edges == pytest.approx(tuple(edges), rel=1e-15) and len(cal.margins) == 3
    scores = interval_scores(lo, hi, tr)
    for j, sel in enumerate([z < edges[0], (z >= edges[0]) & (z < edges[1]), z >= edges[1]]):
        assert cal.margins[j] == conformal_margin(scores[sel], 0.9)
        assert torch.equal(cal.margin_for(med[sel]), torch.full((int(sel.sum()),), cal.margins[j],
                                                                 dtype=torch.float64))  # fmt: skip
    assert cal.margins[0] > cal.margins[2]  # short RULs need the wider margin
    assert cal.margin == conformal_margin(scores, 0.9)
    a, b = cal.interval(lo[:5], hi[:5], med[:5])
    q = cal.margin_for(med[:5])
    assert torch.equal(a, lo[:5] / q.exp()) and torch.equal(b, hi[:5] * q.exp())
    assert RULCalibration.from_dict(json.loads(json.dumps(cal.to_dict()))) == cal
    with pytest.raises(ValueError, match="pass median="):
        cal.interval(lo, hi)
    with pytest.raises(ValueError, match="bins > 1 needs median="):
        calibrate_intervals(lo, hi, tr, bins=2)
    with pytest.raises(ValueError, match="edges must be increasing"):
        RULCalibration.from_dict(dict(cal.to_dict(), margins=[0.1]))


def test_bins_keep_no_boundary_that_a_tie_of_medians_leaves_empty():
    # medians on a grid tie: the top half are all 10; the boundaries between the top bins lie
    # on the tie and would put every tied point below them and none above (margin inf)
    g = torch.Generator().manual_seed(0)
    med = torch.cat([torch.linspace(2, 8, 20, dtype=torch.float64), torch.full((20,), 10.0,
                                                                              dtype=torch.float64)])  # fmt: skip
    y = med * torch.exp(0.2 * torch.randn(40, generator=g, dtype=torch.float64))
    cal = calibrate_intervals(med * 0.8, med * 1.25, y, 0.8, median=med, bins=4)
    z = med.log()
    idx = torch.searchsorted(torch.tensor(cal.edges, dtype=torch.float64), z)
    assert all(bool((idx == j).any()) for j in range(len(cal.margins)))  # no empty bin
    assert cal.edges[-1] < math.log(10.0) and math.isfinite(cal.margins[-1])
    assert float(cal.margin_for(T(10.5))) == cal.margins[-1]


def test_protocol_with_a_known_threshold():
    t = torch.arange(200, dtype=torch.float64)
    y = torch.ones(200, dtype=torch.float64)
    y[120:] = 1.0 + 0.05 * torch.arange(80, dtype=torch.float64)
    y += 0.01 * torch.randn(200, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    pc = known_threshold_protocol(t, y, threshold=3.0)
    m = torch.tensor([float(y[max(0, i - 4) : i + 1].median()) for i in range(200)])
    assert pc.valid and pc.threshold == 3.0 and pc.i_eol == int(torch.nonzero(m >= 3.0)[0])
    never = known_threshold_protocol(t, y, threshold=100.0)
    assert not never.valid and "never reaches the threshold 100" in never.reason
    with pytest.raises(TypeError, match="threshold must be a real number"):
        known_threshold_protocol(t, y, threshold="3")


def _histories():
    cases = run_to_failure_set(1, seed=3)
    return {n: (r.t, r.y) for n, r in list(cases.items())[:3]}


def test_calibrate_rul_replays_pooled_seeds_as_prognose_pools_them():
    hist = dict(list(_histories().items())[:1])
    cal, points = calibrate_rul(hist, method="exponential", fractions=(0.9,), n_paths=200,
                                seed=(0, 1))  # fmt: skip
    assert cal.settings["seed"] == [0, 1] and len(points) == 1
    (p,) = points
    t, y = hist[p["name"]]
    pc = known_threshold_protocol(t, y, fractions=(0.9,))
    r = prognose(y[t <= p["t"]], pc.threshold, time=t[t <= p["t"]], at=p["t"], seed=(0, 1),
                 method="exponential", n_paths=200)  # fmt: skip
    assert (p["q05"], p["q95"]) == (r.summary()["q05"], r.summary()["q95"])


def test_calibrate_rul_replays_the_protocol_through_prognose():
    hist = _histories()
    cal, points = calibrate_rul(hist, method="exponential", fractions=(0.5, 0.9), n_paths=400)
    usable = [p for p in points if "score" in p]
    assert cal.n == len(usable) >= 4 and cal.coverage == 0.9
    assert cal.assets == len({p["name"] for p in usable}) >= 2
    st = cal.settings  # the procedure the guarantee is for: prognose's settings, defaults too
    assert (st["method"], st["n_paths"], st["filter"], st["threshold"]) == \
        ("exponential", 400, "ekf", "protocol") and st["fractions"] == [0.5, 0.9]  # fmt: skip
    # every point is prognose at that time from the data up to it, with the protocol threshold
    p = usable[0]
    t, y = hist[p["name"]]
    pc = known_threshold_protocol(t, y, fractions=(0.5, 0.9))
    r = prognose(y[t <= p["t"]], pc.threshold, time=t[t <= p["t"]], at=p["t"], seed=0,
                 method="exponential", n_paths=400)  # fmt: skip
    s = r.summary()
    assert (p["q05"], p["true_rul"]) == (s["q05"], pc.t_eol - p["t"])
    q = conformal_margin(interval_scores(*(torch.tensor([u[k] for u in usable]) for k in
                                           ("q05", "q95", "true_rul"))), 0.9)  # fmt: skip
    assert cal.margin == q
    out = cal.summary(r)["calibrated"]
    if math.isfinite(q):
        assert out["q05"] == pytest.approx(s["q05"] * math.exp(-q))
    assert (out["margin"], out["n"], out["assets"]) == (q, cal.n, cal.assets)
    # 3 histories, 9 needed at 90 %: a warning wherever the margin is finite
    assert out["warning"] == cal.warning() and (cal.warning() is None) == math.isinf(q)
    # a result made another way is refused by name (any threshold serves "protocol")
    other = prognose(y[t <= p["t"]], pc.threshold, time=t[t <= p["t"]], at=p["t"], seed=0,
                     method="exponential", n_paths=200)  # fmt: skip
    with pytest.raises(ValueError, match="made with n_paths=400, this result has n_paths=200"):
        cal.summary(other)
    named = replace(cal, settings=dict(cal.settings, threshold=2.5))
    with pytest.raises(ValueError, match=r"made with threshold=2.5, this result has threshold="):
        named.summary(r)
    # bins of the predicted median: the same points, a margin per bin
    binned, _ = calibrate_rul(hist, method="exponential", fractions=(0.5, 0.9), n_paths=400,
                              bins=2)  # fmt: skip
    col = lambda k: torch.tensor([u[k] for u in usable], dtype=torch.float64)  # noqa: E731
    want = calibrate_intervals(col("q05"), col("q95"), col("true_rul"), median=col("median"),
                               bins=2)  # fmt: skip
    assert (binned.edges, binned.margins, binned.margin) == (want.edges, want.margins, q)


def test_calibrate_rul_in_worker_processes_equals_the_sequential_run():
    hist = _histories()
    kw = dict(method="exponential", fractions=(0.5, 0.9), n_paths=400)
    one, p_one = calibrate_rul(hist, **kw)
    two, p_two = calibrate_rul(hist, workers=2, **kw)
    assert p_two == p_one and two == one
    # a history the protocol refuses fails the run before any prediction, named
    flat = (torch.arange(50.0, dtype=torch.float64), torch.ones(50, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"histories\['flat'\]: the series is constant"):
        calibrate_rul({**hist, "flat": flat}, threshold=2.0, workers=2, **kw)
    with pytest.raises(TypeError, match="workers must be an int"):
        calibrate_rul(hist, workers=2.0)
    with pytest.raises(ValueError, match="workers must be >= 1"):
        calibrate_rul(hist, workers=0)


def test_calibrate_rul_in_workers_from_an_unguarded_script_says_why_it_failed(tmp_path):
    # spawned workers import the script again; without the __main__ guard they die at start
    script = tmp_path / "unguarded.py"
    script.write_text(
        "from prognos_torch.systems import run_to_failure_set\n"
        "from prognos_torch.workflow import calibrate_rul\n"
        "cases = run_to_failure_set(1, seed=3)\n"
        "hist = {n: (r.t, r.y) for n, r in list(cases.items())[:2]}\n"
        "calibrate_rul(hist, method='exponential', fractions=(0.9,), n_paths=100, workers=2)\n"
    )
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)  # fmt: skip
    assert out.returncode != 0
    # the script's own last line; multiprocessing's resource tracker, a process of its own,
    # may print its leaked-semaphore warning after it (the broken pool's locks)
    lines = [ln for ln in out.stderr.strip().splitlines() if "resource_tracker" not in ln]
    last = lines[-1]
    assert last.startswith("RuntimeError: workers=2: a worker process ended abruptly"), last
    assert 'if __name__ == "__main__":' in last


def test_calibrate_rul_on_a_falling_indicator_mirrors_the_rising_one():
    # a capacity that fades to a known level: the protocol runs on -y and prognose below
    hist = _histories()
    thr = min(float(known_threshold_protocol(t, y).threshold) for t, y in hist.values())
    kw = dict(method="exponential", fractions=(0.5, 0.9), n_paths=400)
    up, p_up = calibrate_rul(hist, threshold=thr, **kw)
    down, p_down = calibrate_rul({n: (t, -y) for n, (t, y) in hist.items()}, threshold=-thr,
                                 direction="below", **kw)  # fmt: skip
    assert up.n == down.n >= 4
    assert down.margin == pytest.approx(up.margin, rel=1e-8)
    for a, b in zip(p_up, p_down):
        assert (a["t"], a["true_rul"]) == (b["t"], b["true_rul"])
        assert b["q05"] == pytest.approx(a["q05"], rel=1e-8, nan_ok=True)
    with pytest.raises(ValueError, match="direction='below' needs the known threshold"):
        calibrate_rul(hist, direction="below")
    with pytest.raises(ValueError, match="direction must be 'above' or 'below'"):
        calibrate_rul(hist, direction="auto")


def test_calibrate_rul_refuses_bad_histories():
    with pytest.raises(ValueError, match="histories is empty"):
        calibrate_rul({})
    with pytest.raises(TypeError, match="histories must be a mapping or a sequence"):
        calibrate_rul(torch.ones(5))
    with pytest.raises(TypeError, match=r"histories\['a'\] must be a Series or a pair"):
        calibrate_rul({"a": torch.ones(30)})
    with pytest.raises(ValueError, match="sets at= and time= itself"):
        calibrate_rul(_histories(), at=3.0)
    flat = (torch.arange(50.0, dtype=torch.float64), torch.ones(50, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"histories\['0'\]: the series is constant"):
        calibrate_rul([flat], threshold=2.0)
    noise = torch.randn(50, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    with pytest.raises(ValueError, match="no prediction point with an interval"):
        calibrate_rul([(flat[0], 1.0 + 0.01 * noise)], threshold=2.0)


def test_study_rows_are_calibrated_on_the_other_assets():
    from prognos_torch.studies.rul_protocol import conformal_rows

    rows = []
    for k, (s, lo, hi, true) in enumerate(
        [
            ("A h", 1.0, 2.0, 3.0),
            ("A v", 1.0, math.inf, 0.5),
            ("B h", 2.0, 4.0, 3.0),
            ("B v", math.inf, math.inf, 1.0),
            ("C h", 0.5, 1.0, 2.0),
        ]  # fmt: skip
    ):
        rows.append({"run": k, "method": "m", "series": s, "q05": lo, "q95": hi, "true_rul": true,
                     "covered": float(lo <= true <= hi), "crps_log": 0.1})  # fmt: skip
    rows.append(dict(rows[0], run=5, method="other"))
    out = conformal_rows(rows, "m", lambda name: name.split()[0], coverage=0.5)
    assert [r["method"] for r in out] == ["m + conformal"] * 5
    assert [r["run"] for r in out] == [6, 7, 8, 9, 10]
    lo = T(1.0, 1.0, 2.0, math.nan, 0.5)
    new_lo, new_hi, _ = leave_one_group_out(lo, T(2.0, math.inf, 4.0, math.nan, 1.0),
                                            T(3.0, 0.5, 3.0, 1.0, 2.0), list("AABBC"), 0.5)  # fmt: skip
    for i in (0, 1, 2, 4):
        assert (out[i]["q05"], out[i]["q95"]) == (new_lo[i].item(), new_hi[i].item())
        assert out[i]["covered"] == float(out[i]["q05"] <= out[i]["true_rul"] <= out[i]["q95"])
        assert out[i]["crps_log"] is None
    assert (out[3]["q05"], out[3]["covered"]) == (math.inf, 0.0)  # no interval: as it was


def test_calibrate_rul_checks_before_its_replays_and_sets_short_histories_aside():
    """coverage=1.0, bins=0 and fractions outside (0, 1) were refused only after every
    prognose replay; a 10-value history aborted the run (a history that never fails is set
    aside); an input error did not name its history; a below-threshold read in -y's sign."""
    hist = dict(list(_histories().items())[:2])
    for kw, text in ((dict(coverage=1.0), "coverage must lie in (0, 1)"),
                     (dict(bins=0), "bins must be an int >= 1"),
                     (dict(fractions=(0.5, 1.5)), "fractions must be distinct numbers in (0, 1)"),
                     (dict(fractions=(0.5, 0.5)), "fractions must be distinct")):  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(text)):
            calibrate_rul(hist, **kw)
    t0, y0 = next(iter(hist.values()))
    short = {**hist, "short": (t0[:10], y0[:10])}
    cal, points = calibrate_rul(short, method="exponential", fractions=(0.9,), n_paths=100)
    assert [p["status"] for p in points if p["name"] == "short"] == [
        "10 values, the protocol needs 20"
    ]
    bad_t = t0.clone()
    bad_t[3] = math.nan
    with pytest.raises(ValueError, match=r"histories\['bad'\]: time must be finite"):
        calibrate_rul({"bad": (bad_t, y0)})
    t = torch.arange(120, dtype=torch.float64)
    falling = {"f": (t, 2.0 - torch.where(t < 60, 0.0, 0.05 * (t - 60))),
               "flat": (t, 1.0 + 0.01 * torch.sin(t))}  # fmt: skip
    _, pts = calibrate_rul(falling, threshold=0.5, direction="below", method="exponential",
                           fractions=(0.5,), n_paths=100)  # fmt: skip
    assert [p["status"] for p in pts if p["name"] == "flat"] == [
        "protocol not usable: the moving median never reaches the threshold 0.5"
    ]
