"""Tests of prognos_torch.filters.scan, the one loop over a time-leading sequence: a hand loop,
the runners built on it (Gaussian run, particle run) step by step, and its bookkeeping."""

from __future__ import annotations

import pytest
import torch

from prognos_torch.core.belief import GaussianBelief
from prognos_torch.core.model import linear_gaussian_model
from prognos_torch.filters import run, scan, sckf, sir

F64 = torch.float64


def test_scan_equals_a_hand_loop_with_per_step_u_and_k():
    ys = torch.arange(12, dtype=F64).reshape(4, 3)
    us = 10.0 * torch.arange(4, dtype=F64).reshape(4, 1)
    seen = []

    def step(s, y, u, k):
        seen.append((y.clone(), u.clone(), k))
        return s + y.sum() + u.sum(), k

    final, out = scan(
        step,
        torch.zeros((), dtype=F64),
        ys,
        us,
        k0=5,
        record=lambda s, k: {
            "state": s,
            "k": torch.tensor(k),
            "even": s if k % 2 == 0 else None,
        },
    )
    want, rows = 0.0, []
    for t in range(4):
        want += float(ys[t].sum() + us[t].sum())
        rows.append(want)
        assert torch.equal(seen[t][0], ys[t]) and torch.equal(seen[t][1], us[t])
        assert seen[t][2] == 5 + t + 1
    assert float(final) == want
    assert out["state"].tolist() == rows
    assert out["k"].tolist() == [6, 7, 8, 9]
    assert out["even"].tolist() == [rows[0], rows[2]]  # None rows are skipped


def test_scan_passes_nan_rows_and_none_controls_through():
    ys = torch.tensor([[1.0], [float("nan")], [2.0]], dtype=F64)
    final, out = scan(
        lambda s, y, u, k: (s + 1, (y, u)),
        0,
        ys,
        record=lambda s, info: {"y": info[0], "u": info[1]},
    )
    assert final == 3 and out["u"] is None
    assert (
        torch.equal(
            out["y"],
            ys,
        )
        if False
        else torch.allclose(out["y"], ys, equal_nan=True)
    )
    s, empty = scan(lambda s, y, u, k: (s, None), 7, ys[:0], record=lambda s, i: {"x": s})
    assert s == 7 and empty == {}


def test_scan_rejects_controls_of_another_length():
    with pytest.raises(ValueError, match="us must have one row per step"):
        scan(
            lambda s, y, u, k: (s, None),
            0,
            torch.zeros(3, 1),
            torch.zeros(2, 1),
            record=lambda s, i: {},
        )
    with pytest.raises(TypeError, match="ys must be a torch.Tensor"):
        scan(lambda s, y, u, k: (s, None), 0, [1.0, 2.0], record=lambda s, i: {})


def _problem():
    model = linear_gaussian_model(
        torch.tensor([[0.9, 0.1], [0.0, 0.95]], dtype=F64),
        torch.tensor([[1.0, 0.0]], dtype=F64),
        0.1 * torch.eye(2, dtype=F64),
        0.2 * torch.eye(1, dtype=F64),
    )
    g = torch.Generator().manual_seed(0)
    ys = torch.randn(15, 3, 1, generator=g, dtype=F64)
    ys[4, 1] = float("nan")  # a missing measurement of one run
    b0 = GaussianBelief(torch.zeros(3, 2, dtype=F64), torch.eye(2, dtype=F64).expand(3, 2, 2))
    return model, ys, b0


def test_gaussian_run_is_the_step_by_step_loop():
    model, ys, b0 = _problem()
    filt = sckf()
    tr = run(filt, model, b0, ys, k0=2)
    state = filt.init(model, b0, 3)
    for t in range(ys.shape[0]):
        state, info = filt.step(model, state, ys[t], None, k=2 + t + 1)
        assert torch.equal(tr.means[t], state.belief.mean)
        assert torch.equal(tr.pred_chols[t], info.prior.chol)
        assert torch.equal(tr.chol_innovations[t], info.chol_innovation)
    assert torch.equal(tr.final.belief.chol, state.belief.chol)


def test_particle_run_is_the_step_by_step_loop():
    model, ys, b0 = _problem()
    pf = sir(64)
    tr = pf.run(model, b0, ys, generator=torch.Generator().manual_seed(3), keep_particles=True)
    g = torch.Generator().manual_seed(3)
    state = pf.init(model, b0, generator=g, k=0)
    for t in range(ys.shape[0]):
        state, info = pf.step(model, state, ys[t], None, t + 1, generator=g)
        assert torch.equal(tr.means[t], info.mean) and torch.equal(tr.ess[t], info.ess)
        assert torch.equal(tr.particles[t], info.particles)
    assert bool(tr.missing[4, 1]) and not bool(tr.missing[4, 0])
    assert torch.equal(tr.final.particles, state.particles)
