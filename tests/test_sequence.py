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


def _assert_particle_run_is_the_loop(pf, model, b0, ys, seed: int, **run_options):
    """``pf.run`` gives what ``pf.step`` gives step by step with the same generator seed."""
    tr = pf.run(model, b0, ys, generator=torch.Generator().manual_seed(seed), **run_options)
    g = torch.Generator().manual_seed(seed)
    state = pf.init(model, b0, generator=g, k=0)
    for t in range(ys.shape[0]):
        state, info = pf.step(model, state, ys[t], None, t + 1, generator=g)
        assert torch.equal(tr.means[t], info.mean) and torch.equal(tr.ess[t], info.ess)
        if tr.particles is not None:
            assert torch.equal(tr.particles[t], info.particles)
    assert torch.equal(tr.final.particles, state.particles)
    return tr


def test_particle_run_is_the_step_by_step_loop():
    model, ys, b0 = _problem()
    tr = _assert_particle_run_is_the_loop(sir(64), model, b0, ys, 3, keep_particles=True)
    assert bool(tr.missing[4, 1]) and not bool(tr.missing[4, 0])


def test_scan_runs_later_steps_in_inference_mode_when_nothing_needs_a_gradient():
    """``inference=True``: once the first step shows that nothing needs a gradient, the other
    steps run under inference mode; what is handed out is ordinary all the same (writable,
    usable with autograd). A state that needs a gradient keeps autograd at every step."""
    modes = []

    def step(s, y, u, k):
        modes.append(torch.is_inference_mode_enabled())
        return s + y, None

    ys = torch.arange(4.0, dtype=F64).reshape(4, 1)
    final, out = scan(step, torch.zeros(1, dtype=F64), ys, record=lambda s, i: {"s": s},
                      inference=True)  # fmt: skip
    assert modes == [False, True, True, True]
    assert not final.is_inference() and not out["s"].is_inference()
    final.add_(1.0)  # writable outside inference mode
    modes.clear()
    x0 = torch.zeros(1, dtype=F64, requires_grad=True)
    final, out = scan(step, x0, ys, record=lambda s, i: {"s": s}, inference=True)
    assert modes == [False] * 4
    out["s"].sum().backward()
    assert float(x0.grad) == 4.0


def test_filter_runs_hand_out_ordinary_tensors_and_stay_differentiable():
    model, ys, b0 = _problem()
    tr = run(sckf(), model, b0, ys, inference=True)
    assert torch.equal(tr.means, run(sckf(), model, b0, ys).means)
    assert not tr.final.belief.mean.is_inference() and not tr.final.belief.chol.is_inference()
    assert not tr.means.is_inference()
    ptr = sir(64).run(model, b0, ys, generator=torch.Generator().manual_seed(3), inference=True)
    assert not ptr.final.particles.is_inference() and not ptr.final.log_weights.is_inference()
    ptr.final.particles.mul_(1.0)
    m0 = b0.mean.clone().requires_grad_(True)
    tr = run(sckf(), model, GaussianBelief(m0, b0.chol), ys, inference=True)
    tr.log_likelihoods.sum().backward()
    assert m0.grad is not None and bool(torch.isfinite(m0.grad).all())


def test_caches_filled_in_inference_mode_hold_ordinary_tensors():
    """A step run in inference mode may fill the library's caches; what they keep must serve
    a later step that autograd records (an inference tensor cannot be saved for backward)."""
    from prognos_torch.filters._blocks import _sigma_points
    from prognos_torch.filters.resampling import _arange
    from prognos_torch.learners import ANFIS

    like = torch.zeros(3, dtype=F64)
    with torch.inference_mode():
        sig = _sigma_points(sckf().rule, 13, like)
        j, jl = _arange(12347, F64, like.device), _arange(12347, torch.int64, like.device)
        consts = ANFIS(2, 2)._constants(like)
    tensors = [sig.xi, sig.wm, j, jl, *consts]
    assert not any(t.is_inference() for t in tensors)
    w = torch.ones(sig.wm.shape, dtype=F64, requires_grad=True)
    (sig.wm * w).sum().backward()  # saved for backward: fails with an inference tensor


def test_a_model_that_differentiates_inside_falls_back_to_autograd_with_the_same_draws():
    """A transition Jacobian by reverse-mode autograd cannot run in inference mode: that step
    is undone (the generator's draws too) and the run goes on with autograd, with the numbers
    of the step-by-step loop."""
    from prognos_torch.core.model import StateSpaceModel
    from prognos_torch.filters import stpf

    def f(x, u, k):
        return x + 0.1 * torch.sin(x)

    def jac_f(x, u, k):
        with torch.enable_grad():
            xr = x.detach().clone().requires_grad_(True)
            (g,) = torch.autograd.grad(f(xr, u, k).sum(), xr)
        return g.unsqueeze(-1)

    model = StateSpaceModel(
        f=f, h=lambda x, u, k: x, state_dim=1, obs_dim=1, batched=True, jac_f=jac_f,
        jac_h=lambda x, u, k: torch.ones_like(x).unsqueeze(-1),
        chol_Q=torch.tensor([[0.1]], dtype=F64), chol_R=torch.tensor([[0.3]], dtype=F64),
    )  # fmt: skip
    ys = torch.cumsum(0.1 * torch.ones(12, 1, dtype=F64), 0)
    b0 = GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    a = _assert_particle_run_is_the_loop(stpf(50), model, b0, ys, 4, inference=True)
    assert not a.final.particles.is_inference()


def test_by_default_a_run_keeps_autograd_for_parameters_used_only_later():
    """Inference mode is opt-in: by default a parameter that enters the model only from the
    second step (a fault onset, say) keeps its gradient, and the noise Gram of a factor that
    needs a gradient is not cached (a second backward pass used to find its graph spent)."""
    model, ys, b0 = _problem()
    rate = torch.tensor(0.1, dtype=F64, requires_grad=True)
    f0 = model.f if model.f is not None else (lambda x, u, k: x)

    def f(x, u, k):
        return f0(x, u, k) + rate if k >= 2 else f0(x, u, k)

    from dataclasses import replace

    m2 = replace(model, f=f, F=None) if hasattr(model, "F") else replace(model, f=f)
    tr = run(sckf(), m2, b0, ys)
    tr.log_likelihoods[torch.isfinite(tr.log_likelihoods)].sum().backward()
    assert rate.grad is not None and float(rate.grad) != 0.0
    SQ = model.chol_Q.clone().requires_grad_(True)
    m3 = replace(model, chol_Q=SQ)
    for _ in range(2):  # the second pass rebuilds S S^T: nothing cached with a spent graph
        run(sckf(prior="cholesky"), m3, b0, ys).log_likelihoods.nansum().backward()
    assert SQ.grad is not None and bool(torch.isfinite(SQ.grad).all())


def test_compiled_scans_of_many_steps_do_not_share_the_recompile_limit(monkeypatch):
    """Each compiled step has its own entry: more distinct steps than dynamo's recompile limit
    per code object still compile (fullgraph=True fails hard past it), and each equals its
    eager loop. Also: a scan without controls compiles. (The limit is lowered to 2 so that 3
    steps exceed it; the default, 8, would take 9 compilations.)"""
    import torch._dynamo

    monkeypatch.setattr(torch._dynamo.config, "recompile_limit", 2)
    ys = torch.linspace(0.0, 1.0, 6, dtype=F64).reshape(6, 1)

    def make(op):
        def step(s, y, u, k):
            new = (op(s[0]) + y.sum(),)
            return new, new[0].clone()  # (the scan forbids outputs that alias the carry)

        return step

    ops = [torch.sin, torch.cos, torch.tanh]

    record = lambda s, info: {"x": info}  # noqa: E731
    assert len(ops) > torch._dynamo.config.recompile_limit
    for op in ops:
        step = make(op)
        state = (torch.ones((), dtype=F64),)
        got = scan(step, state, ys, record=record, compile=True)[1]["x"]
        ref = scan(step, state, ys, record=record)[1]["x"]
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=0.0)


def test_scan_hands_out_ordinary_named_tuple_states():
    from collections import namedtuple

    State = namedtuple("State", "x c")
    ys = torch.arange(3.0, dtype=F64).reshape(3, 1)
    s0 = State(torch.zeros(1, dtype=F64), torch.ones(1, dtype=F64))
    final, _ = scan(lambda s, y, u, k: (State(s.x + y, s.c), None), s0, ys,
                    record=lambda s, i: {"x": s.x}, inference=True)  # fmt: skip
    assert type(final) is State and not final.x.is_inference()
    final.x.add_(1.0)  # writable outside inference mode
    assert final.x.tolist() == [4.0]


def test_scan_names_a_record_whose_shape_changes():
    ys = torch.zeros(3, 1, dtype=F64)
    with pytest.raises(
        ValueError, match=r"record 'a' gave shape \(2,\) first and shape \(3,\) later"
    ):
        scan(lambda s, y, u, k: (s + 1, None), 1, ys, record=lambda s, i: {"a": torch.zeros(s)})
    with pytest.raises(ValueError, match="record 'b' gave shape .* int"):
        scan(lambda s, y, u, k: (s + 1, None), 1, ys,
             record=lambda s, i: {"b": torch.zeros(1) if s == 2 else s})  # fmt: skip


def test_compiled_scan_of_no_steps_returns_the_state_without_compiling(monkeypatch):
    def no_compile(*args, **kwargs):
        raise AssertionError("nothing to compile")

    monkeypatch.setattr(torch, "compile", no_compile)
    s0 = (torch.ones(2, dtype=F64),)
    final, out = scan(lambda s, y, u, k: (s, None), s0, torch.zeros(0, 1, dtype=F64),
                      record=lambda s, i: {"x": s[0]}, compile=True)  # fmt: skip
    assert out == {} and len(final) == 1 and torch.equal(final[0], s0[0])
    with pytest.raises(TypeError, match="state must be a tuple of tensors"):
        scan(lambda s, y, u, k: (s, None), [s0[0]], torch.zeros(0, 1), record=dict,
             compile=True)  # fmt: skip
