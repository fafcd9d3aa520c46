"""Audit of prognosis/paths.py (weighted quantiles, particle paths and their bands, recursive
prediction), workflow/model.py (fit_series and what it stores) and workflow/calibrate.py
(calibrate_rul's bookkeeping).

References are brute force written here: sorted cumulative weights for the quantiles, the
particle recursion redrawn from the same generator, the CQR score and split-conformal rank for
the calibration (whose ``prognose`` call is replaced by a stub: the bookkeeping, not the
replays, is under test).
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from _prognosis_helpers import brute_weighted_quantile, degradation_history
from torch import nn

import prognos_torch.workflow.calibrate as calibrate_mod
from prognos_torch.core.model import StateSpaceModel
from prognos_torch.prognosis import particle_paths, recursive_predict, settle
from prognos_torch.prognosis.paths import SamplePaths, weighted_quantile
from prognos_torch.workflow import fit_series, load_series
from prognos_torch.workflow.calibrate import calibrate_rul
from prognos_torch.workflow.model import LEARNER_DEFAULTS, build_learner, select_embedding

F64 = torch.float64


def _close(a: torch.Tensor, b: torch.Tensor, tol: float = 1e-12) -> None:
    # (torch.testing.assert_close imports torch.distributed on first use: seconds)
    assert a.shape == b.shape and a.dtype == b.dtype
    assert float((a - b).abs().max()) <= tol


# ------------------------------------------------------------------------------ paths.py


def testweighted_quantile_matches_brute_force_batched_float32_and_zero_weights():
    g = torch.Generator().manual_seed(3)
    s = torch.randn(2, 7, 3, generator=g, dtype=F64).round(decimals=1)  # ties
    w = torch.rand(2, 7, generator=g, dtype=F64)
    w[0, 2] = 0.0  # a zero-weight sample never is a quantile it cannot reach
    w = w / w.sum(-1, keepdim=True)
    for dt in (F64, torch.float32):
        for q in (0.05, 0.3, 0.5, 0.975, 1.0):
            got = weighted_quantile(s.to(dt), w, q)
            assert got.dtype == dt and got.shape == (2, 3)
            for b in range(2):
                for h in range(3):
                    want = brute_weighted_quantile(s[b, :, h].numpy(), w[b].numpy(), q)
                    assert float(got[b, h]) == pytest.approx(want, abs=1e-6)


def test_quantile_refuses_bool_and_text_and_takes_numpy_reals():
    s = torch.tensor([[1.0], [2.0], [3.0], [4.0]], dtype=F64)
    w = torch.full((4,), 0.25, dtype=F64)
    p = SamplePaths(s, w, s.mean(-2), s.std(-2), s[0], s[-1], 0.5)
    assert float(p.quantile(np.float32(0.5))) == float(p.quantile(0.5)) == 2.0
    for bad in (True, np.bool_(True), "0.5", None):  # True was read as q = 1 (the maximum)
        with pytest.raises(ValueError, match="q must be a number in"):
            p.quantile(bad)


def _linear_model(a: float, chol_Q, q=None) -> StateSpaceModel:
    return StateSpaceModel(
        lambda x, u, k: a * x,
        lambda x, u, k: x[..., :1],
        1,
        1,
        chol_Q,
        torch.eye(1, dtype=F64) * 0.1,
        q=q,
        batched=True,
    )


def test_particle_paths_bands_match_a_hand_recursion_with_batched_noise():
    a, B, N, H = 1.05, 2, 6, 3
    SQ = torch.tensor([[[0.1]], [[0.3]]], dtype=F64)  # one square root per batch element
    x0 = torch.linspace(0.5, 1.5, B * N, dtype=F64).reshape(B, N, 1)
    w = torch.rand(B, N, generator=torch.Generator().manual_seed(1), dtype=F64)
    w = w / w.sum(-1, keepdim=True)
    p = particle_paths(
        _linear_model(a, SQ), x0, H, generator=torch.Generator().manual_seed(7), weights=w
    )
    g = torch.Generator().manual_seed(7)  # the same draws, in the same order
    x, ref = x0.clone(), []
    for _ in range(H):
        e = torch.randn(x.shape, generator=g, dtype=F64)
        x = a * x + SQ[:, None, 0, 0, None] * e
        ref.append(x[..., 0])
    ref = torch.stack(ref, -1)  # (B, N, H)
    _close(p.samples, ref)
    mean = (w[..., None] * ref).sum(-2)
    std = (w[..., None] * (ref - mean[:, None]) ** 2).sum(-2).sqrt()
    _close(p.mean, mean)
    _close(p.std, std)
    for b in range(B):
        for h in range(H):
            col, wb = ref[b, :, h].numpy(), w[b].numpy()
            assert float(p.lower[b, h]) == brute_weighted_quantile(col, wb, 0.025)
            assert float(p.upper[b, h]) == brute_weighted_quantile(col, wb, 0.975)


def test_particle_paths_check_the_model_noise_against_the_particles():
    g = torch.Generator().manual_seed(0)
    x0 = torch.zeros(5, 1, dtype=F64)  # unbatched particles
    batched = torch.eye(1, dtype=F64).expand(3, 1, 1) * 0.1
    # were widened silently into a batch of 3 path sets (samples (3, 5, H), weights (5,))
    with pytest.raises(ValueError, match="model.chol_Q must have shape"):
        particle_paths(_linear_model(1.0, batched), x0, 2, generator=g)
    with pytest.raises(ValueError, match="model.q must have shape"):
        particle_paths(
            _linear_model(1.0, torch.eye(1, dtype=F64), q=torch.zeros(3, 1, dtype=F64)),
            x0,
            2,
            generator=g,
        )
    with pytest.raises(ValueError, match="model.chol_Q"):  # (every path was NaN)
        particle_paths(_linear_model(1.0, torch.eye(1, dtype=F64) * math.nan), x0, 2, generator=g)


def test_particle_paths_flags_and_k0_are_checked():
    model = _linear_model(1.0, torch.eye(1, dtype=F64) * 0.1)
    x0 = torch.zeros(4, 1, dtype=F64)
    run = lambda **kw: particle_paths(  # noqa: E731
        model, x0, 2, generator=torch.Generator().manual_seed(0), **kw
    )
    with pytest.raises(TypeError, match="measurement_noise must be a bool, got 'no'"):
        run(measurement_noise="no")  # (was read as True: noise added)
    a, b = run(measurement_noise=np.bool_(True)), run(measurement_noise=True)
    assert torch.equal(a.samples, b.samples)
    for bad in (1.5, True, -1):  # (a float k0 reached f, h and the noise as k)
        with pytest.raises(ValueError, match="k0 must be a non-negative int"):
            run(k0=bad)
    assert torch.equal(run(k0=np.int64(2)).samples, run(k0=2).samples)


def test_recursive_predict_and_settle_check_k0():
    seen = []

    def f(x, u, k):
        seen.append(k)
        return 0.5 * x

    model = StateSpaceModel(f, lambda x, u, k: x, 1, 1, torch.eye(1, dtype=F64),
                            torch.eye(1, dtype=F64), batched=True)  # fmt: skip
    x = torch.ones(1, dtype=F64)
    for bad in (1.5, True):
        with pytest.raises(ValueError, match="k0 must be a non-negative int"):
            recursive_predict(model, x, 2, k0=bad)
        with pytest.raises(ValueError, match="k0 must be a non-negative int"):
            settle(model, x, 2, k0=bad)
    assert not seen  # refused before f ran with k = 2.5
    _close(recursive_predict(model, x, 2, k0=np.int64(3)), torch.tensor([0.5, 0.25], dtype=F64))
    assert seen == [4, 5] and all(type(k) is int for k in seen)


def test_recursive_predict_checks_n_out_index():
    lin = nn.Linear(3, 1, dtype=F64)
    w = torch.zeros(2, 3, dtype=F64)
    # True added an axis (refused deep in shift_append), 0.0 and 1 failed in the indexing
    for bad in (True, 0.0, -1):
        with pytest.raises(ValueError, match="n_out_index must be a non-negative int"):
            recursive_predict(lin, w, 2, n_out_index=bad)
    with pytest.raises(ValueError, match="n_out_index=1 is out of range for n_out=1"):
        recursive_predict(lin, w, 2, n_out_index=1)

    def two(x):  # a callable with no n_out: (..., 2) outputs, the second the next value
        return torch.stack([x.sum(-1), 0.5 * x[..., -1]], -1)

    got = recursive_predict(two, torch.tensor([1.0, 2.0], dtype=F64), 3, n_out_index=np.int64(1))
    _close(got, torch.tensor([1.0, 0.5, 0.25], dtype=F64))
    with pytest.raises(ValueError, match=r"n_out_index=2 is out of range for the learner's"):
        recursive_predict(two, torch.tensor([1.0, 2.0], dtype=F64), 3, n_out_index=2)


# ------------------------------------------------------------------------------ model.py
def _series():
    t = np.arange(40.0)
    return load_series(1.0 + 0.2 * np.sin(t / 5.0) + 0.01 * t)


_FIT = dict(learner="elm", optimizer="closed-form", m=3, holdout=0)


def test_fit_series_stores_numpy_options_as_json_numbers():
    s = _series()
    a = fit_series(s, **_FIT, learner_options={"n_hidden": np.int64(5), "lam": np.float32(0.5)})
    b = fit_series(s, **_FIT, learner_options={"n_hidden": 5, "lam": float(np.float32(0.5))})
    lo = a.config["learner_options"]
    assert type(lo["n_hidden"]) is int and type(lo["lam"]) is float
    json.dumps(a.config)  # (np.int64 was stored: "Object of type int64 is not JSON serializable")
    assert lo == b.config["learner_options"]
    for pa, pb in zip(a.learner.parameters(), b.learner.parameters()):
        assert torch.equal(pa, pb)


def test_fit_series_flags_and_data_checked_up_front(monkeypatch):
    s = _series()
    a = fit_series(s, **_FIT, refit=np.bool_(False), learner_options={"n_hidden": 5})
    assert a.config.get("refit") is None  # np.bool_ was refused: "refit must be a bool"
    import prognos_torch.workflow.model as model_mod

    def boom(*args, **kw):
        raise AssertionError("trained before the arguments were checked")

    monkeypatch.setattr(model_mod, "_train", boom)
    with pytest.raises(TypeError, match="progress must be a bool, got 'no'"):
        fit_series(s, **_FIT, progress="no")  # (read by its truth value: bars drawn)
    with pytest.raises(TypeError, match="data must be a dict or None, got list"):
        fit_series(s, **_FIT, data=[1, 2])  # (was "cannot convert dictionary update ...")


def test_select_embedding_and_build_learner_check_their_arguments():
    z = torch.linspace(0.0, 1.0, 40, dtype=F64) ** 2
    lo = dict(LEARNER_DEFAULTS["elm"], n_hidden=5)
    ref = select_embedding(z, "elm", lo, [2, 3], seed=1)
    # np.int64 seed: torch said "an integer is required"; np.int64 candidates came back as such
    got = select_embedding(z, "elm", lo, [np.int64(2), np.int64(3)], seed=np.int64(1))
    assert got == ref and type(got[0]) is int
    got32 = select_embedding(z.float(), "elm", lo, [2, 3], seed=1)  # (was a dtype TypeError)
    assert got32[0] == ref[0]
    for bad in ([2.0, 3], [True, 2], [], 3):
        with pytest.raises(ValueError, match="candidates must be positive ints"):
            select_embedding(z, "elm", lo, bad)
    with pytest.raises(ValueError, match=r"z must be a floating tensor of shape \(T,\)"):
        select_embedding(z[:, None], "elm", lo, [2, 3])
    with pytest.raises(TypeError, match="seed must be an int, got 1.5"):
        select_embedding(z, "elm", lo, [2, 3], seed=1.5)
    a = build_learner("elm", 3, lo, seed=np.int64(4))
    b = build_learner("elm", 3, lo, seed=4)
    for pa, pb in zip(a.parameters(), b.parameters()):
        assert torch.equal(pa, pb)


# ------------------------------------------------------------------------------ calibrate.py


@pytest.fixture
def stub(monkeypatch):
    """``_predict`` replaced: an interval [true / 2, true * 3] (with a known miss), recorded."""
    calls = []

    def fake(y, t, at, threshold, true, seed, direction, kwargs):
        calls.append(dict(n=len(y), t_max=float(t.max()), at=at, threshold=threshold,
                          true=true, direction=direction, kwargs=kwargs))  # fmt: skip
        if len(calls) == 3:
            return {"status": "error: refused"}
        lo, hi = (true * 1.5, true * 4) if len(calls) == 1 else (true / 2, true * 3)
        return {"q05": lo, "q95": hi, "median": true, "status": "ok"}

    monkeypatch.setattr(calibrate_mod, "_predict", fake)
    return calls


def test_calibrate_rul_bookkeeping_against_brute_force(stub):
    (ta, ya), (tb, yb) = degradation_history(0), degradation_history(1)
    short = (torch.arange(10, dtype=F64), torch.ones(10, dtype=F64))
    cal, points = calibrate_rul({"a": (ta, ya), "b": (tb, yb), "c": short}, threshold=5.0)
    assert len(stub) == 10  # five fractions of each usable history
    for c in stub:  # the data up to the prediction time, the known threshold
        assert c["t_max"] <= c["at"] and c["threshold"] == 5.0 and c["direction"] == "above"
    assert points[-1] == {"name": "c", "status": "10 values, the protocol needs 20"}
    usable = [p for p in points if p.get("status") == "ok"]
    assert len(usable) == 9 and points[2]["status"] == "error: refused"
    assert "score" not in points[2] and math.isnan(points[2]["q05"])
    scores = []
    for p in usable:
        want = max(math.log(p["q05"] / p["true_rul"]), math.log(p["true_rul"] / p["q95"]))
        assert p["score"] == pytest.approx(want, abs=1e-12)
        scores.append(want)
    k = math.ceil((len(scores) + 1) * 0.9)  # split-conformal rank
    assert cal.margin == pytest.approx(sorted(scores)[k - 1], abs=1e-12)
    assert cal.n == 9 and cal.assets == 2


def test_calibrate_rul_records_numpy_settings_as_numbers(stub):
    h = {"a": degradation_history(0), "b": degradation_history(1)}
    cal, _ = calibrate_rul(h, n_paths=np.int64(500), horizon_factor=np.float32(2.0))
    ref, _ = calibrate_rul(h, n_paths=500, horizon_factor=2.0)
    assert cal.settings == ref.settings  # (was "np.int64(500)", the repr)
    summary = {"status": "ok", "q05": 2.0, "q95": 8.0, "median": 4.0, "bound": 100.0}
    result = SimpleNamespace(summary=lambda: dict(summary), threshold=None, direction="above",
                             n_particles=500)  # fmt: skip
    # made every result refused: "made with n_paths='np.int64(500)', this result has 500"
    assert cal.summary(result)["calibrated"]["margin"] == cal.margin


def test_calibrate_rul_refuses_names_that_collide(stub):
    # {1: ..., "1": ...} pooled two assets' points under one name (assets = 1)
    with pytest.raises(ValueError, match="histories names '1' twice"):
        calibrate_rul({1: degradation_history(0), "1": degradation_history(1)})
    assert not stub


def test_calibrate_rul_refuses_a_non_finite_threshold_by_name(stub):
    for bad in (math.nan, math.inf, np.float64(-math.inf)):
        # (was "histories['a']: threshold must be finite", or nothing for short histories)
        with pytest.raises(ValueError, match=r"^threshold must be finite or None"):
            calibrate_rul({"a": degradation_history(0)}, threshold=bad)
    assert not stub
