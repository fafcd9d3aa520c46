"""The compiled bootstrap particle filter (``ParticleFilter.run(..., compile=True)``) against the
eager filter fed the same draws, its conditions, and its eager fallback."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import prognos_torch.filters.particle as particle_mod
import prognos_torch.filters.resampling as resampling_mod
import prognos_torch.filters.sequence
from prognos_torch.core import GaussianBelief, StateSpaceModel, linear_gaussian_model
from prognos_torch.core.random import _randn_cpu_f64, box_muller
from prognos_torch.filters import ParticleState, ekf, ekpf, sir, stpf, upf

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

F64 = torch.float64


def _model_1d(batched: bool) -> StateSpaceModel:
    f = lambda x, u, k: x + 0.05 * torch.sin(x)  # noqa: E731
    h = lambda x, u, k: x + 0.1 * x**2  # noqa: E731
    if batched:  # closed-form Jacobians (the proposal filters' compiled pass needs them)
        jac_f = lambda x, u, k: (1.0 + 0.05 * torch.cos(x)).unsqueeze(-1)  # noqa: E731
        jac_h = lambda x, u, k: (1.0 + 0.2 * x).unsqueeze(-1)  # noqa: E731
    else:  # per sample
        jac_f = lambda x, u, k: (1.0 + 0.05 * torch.cos(x)).reshape(1, 1)  # noqa: E731
        jac_h = lambda x, u, k: (1.0 + 0.2 * x).reshape(1, 1)  # noqa: E731
    return StateSpaceModel(
        f=f,
        h=h,
        state_dim=1,
        obs_dim=1,
        chol_Q=torch.tensor([[0.1]], dtype=F64),
        chol_R=torch.tensor([[0.3]], dtype=F64),
        batched=batched,
        jac_f=jac_f,
        jac_h=jac_h,
    )


def _model_2d_control() -> StateSpaceModel:
    A = torch.tensor([[0.95, 0.1], [0.0, 0.9]], dtype=F64)
    B = torch.tensor([[0.0], [0.5]], dtype=F64)
    f = lambda x, u, k: x @ A.mT + u @ B.mT  # noqa: E731
    h = lambda x, u, k: torch.stack([x[..., 0] + x[..., 1] ** 2 / 4, x[..., 1]], -1)  # noqa: E731
    LQ = torch.tensor([[0.2, 0.0], [0.05, 0.1]], dtype=F64)  # not diagonal: the matrix draw
    LR = torch.tensor([[0.3, 0.0], [0.1, 0.25]], dtype=F64)  # the triangular solve
    q, r = torch.tensor([0.05, -0.02], dtype=F64), torch.tensor([0.1, 0.0], dtype=F64)

    def jac_h(x, u, k):
        one, zero = torch.ones_like(x[..., 0]), torch.zeros_like(x[..., 0])
        rows = [torch.stack([one, x[..., 1] / 2], -1), torch.stack([zero, one], -1)]
        return torch.stack(rows, -2)

    return StateSpaceModel(
        f=f,
        h=h,
        jac_f=lambda x, u, k: A.expand(*x.shape[:-1], 2, 2),
        jac_h=jac_h,
        state_dim=2,
        obs_dim=2,
        chol_Q=LQ,
        chol_R=LR,
        q=q,
        r=r,
        control_dim=1,
        batched=True,
    )


def _data(model: StateSpaceModel, bs: tuple, T: int, us: torch.Tensor | None, seed: int):
    g = torch.Generator().manual_seed(seed)
    n = model.state_dim
    x = torch.zeros(*bs, n, dtype=F64)
    ys = []
    for t in range(T):
        u = None if us is None else us[t]
        x = model.transition(x, u, t + 1) + torch.randn(*bs, n, generator=g, dtype=F64) @ (
            model.chol_Q.mT
        )
        y = model.observe(x, u, t + 1)
        ys.append(y + torch.randn(y.shape, generator=g, dtype=F64) @ model.chol_R.mT)
    return torch.stack(ys)


def _eager_with_the_compiled_draws(pf, model, state, ys, us, seed, monkeypatch):
    """The eager run fed the draws the compiled pass makes from ``seed``: per step, normals
    from ``16 ceil(B N n / 16)`` uniforms by the Box-Muller blocks, then one resampling point
    per run."""
    bs, N, n = state.batch_shape, state.num_particles, state.particles.shape[-1]
    T, count = ys.shape[0], state.particles.numel()
    M, R = 16 * -(-count // 16), math.prod(bs)
    draws = torch.rand((T, M + R), generator=torch.Generator().manual_seed(seed), dtype=F64)
    eps = box_muller(draws[:, :M].reshape(T, -1, 16)).reshape(T, M)[:, :count]
    eps = eps.reshape(T, *bs, N, n)
    points = draws[:, M:].reshape(T, *bs, 1)
    t = [-1]

    def normals(shape, generator, dtype, device):
        t[0] += 1
        assert tuple(shape) == tuple(eps.shape[1:])
        return eps[t[0]].clone()

    def uniform(shape, generator, like):
        assert tuple(shape) == tuple(points.shape[1:])
        return points[t[0]].clone()

    with monkeypatch.context() as m:
        m.setattr(particle_mod, "standard_normal", normals)
        m.setattr(resampling_mod, "_uniform", uniform)
        out = pf.run(model, state, ys, us, generator=torch.Generator(), keep_particles=True)
    assert t[0] == T - 1
    return out


def _compare(a, b, rtol=1e-12, atol=1e-12):
    assert torch.equal(a.resampled, b.resampled)
    for name in ("means", "covs", "ess", "log_likelihoods", "particles", "log_weights"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=rtol, atol=atol)
    torch.testing.assert_close(a.final.particles, b.final.particles, rtol=rtol, atol=atol)
    torch.testing.assert_close(a.final.log_weights, b.final.log_weights, rtol=rtol, atol=atol)
    for name in ("collapsed", "missing"):
        assert torch.equal(getattr(a, name), getattr(b, name))
    assert torch.equal(a.prior_fallback, b.prior_fallback)
    torch.testing.assert_close(a.fading_factors, b.fading_factors, rtol=rtol, atol=atol)
    fa, fb = a.final.proposal, b.final.proposal
    assert (fa is None) == (fb is None)
    if fa is not None:  # each particle's Gaussian and strong-tracking state
        torch.testing.assert_close(fa.belief.mean, fb.belief.mean, rtol=rtol, atol=atol)
        torch.testing.assert_close(fa.belief.chol, fb.belief.chol, rtol=rtol, atol=atol)
        assert (fa.fading is None) == (fb.fading is None)
        if fa.fading is not None:
            torch.testing.assert_close(fa.fading.V, fb.fading.V, rtol=rtol, atol=atol)
            assert torch.equal(fa.fading.started, fb.fading.started)


FACTORIES = {"sir": sir, "ekpf": ekpf, "stpf": stpf}


@pytest.mark.parametrize("batched", [True, False])
@pytest.mark.parametrize("name", ["sir", "ekpf", "stpf"])
def test_compiled_pf_equals_the_eager_pf_fed_the_same_draws_one_run(name, batched, monkeypatch):
    model = _model_1d(batched)
    ys = _data(model, (), 60, None, seed=3)
    ys[30] += 2.0  # a jump: some steps resample, some do not
    pf = FACTORIES[name](500)  # 500 normals: a partial block of 16
    b0 = GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    state = pf.init(model, b0, generator=torch.Generator().manual_seed(0))
    ref = _eager_with_the_compiled_draws(pf, model, state, ys, None, 7, monkeypatch)
    out = pf.run(
        model,
        state,
        ys,
        generator=torch.Generator().manual_seed(7),
        keep_particles=True,
        compile=True,
    )
    assert 0 < int(ref.resampled.sum()) < 60
    _compare(out, ref)


def _linear_gaussian_2d() -> StateSpaceModel:
    # its transition x @ F^T leaves the particles in a transposed layout
    t = lambda v: torch.tensor(v, dtype=F64)  # noqa: E731
    return linear_gaussian_model(
        t([[0.95, 0.1], [-0.1, 0.9]]), t([[1.0, 0.5], [0.0, 1.0]]),
        t([[0.4, 0.0], [0.1, 0.3]]), t([[0.6, 0.0], [0.0, 0.5]]), q=t([0.05, -0.02]),
    )  # fmt: skip


@pytest.mark.parametrize(
    "name, which",
    [("sir", "nonlinear, controls"), ("sir", "linear-Gaussian"), ("stpf", "nonlinear, controls")],
)
def test_compiled_pf_equals_the_eager_pf_batched_runs_full_noise(name, which, monkeypatch):
    control = which == "nonlinear, controls"
    model = _model_2d_control() if control else _linear_gaussian_2d()
    bs, T = (3,), 40
    us = torch.linspace(-1.0, 1.0, T, dtype=F64).reshape(T, 1) if control else None
    ys = _data(model, bs, T, us, seed=4)
    ys[20, 1] += 3.0  # one run jumps: runs resample at different steps
    pf = FACTORIES[name](300, resample_threshold=0.6)
    eye = torch.eye(2, dtype=F64)
    b0 = GaussianBelief(torch.zeros(*bs, 2, dtype=F64), 0.5 * eye.expand(*bs, 2, 2))
    state = pf.init(model, b0, generator=torch.Generator().manual_seed(1))
    ref = _eager_with_the_compiled_draws(pf, model, state, ys, us, 11, monkeypatch)
    gen = torch.Generator().manual_seed(11)
    out = pf.run(model, state, ys, us, generator=gen, keep_particles=True, compile=True)
    per_step = ref.resampled.sum(-1)
    assert bool(((per_step > 0) & (per_step < 3)).any())  # some steps resample some runs only
    _compare(out, ref)


def test_box_muller_is_the_vectorised_normals_transform():
    g = torch.Generator().manual_seed(5)
    u = torch.rand(4096, generator=g, dtype=F64)
    z = _randn_cpu_f64(4096, torch.Generator().manual_seed(5))
    assert torch.equal(box_muller(u.view(-1, 16)).reshape(-1), z)
    with pytest.raises(ValueError, match=r"\(\.\.\., 16\)"):
        box_muller(u.view(-1, 8))


def test_compiled_run_reuses_its_code_and_draws_from_the_generator():
    model = _model_1d(True)
    ys = _data(model, (), 30, None, seed=2)
    b0 = GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    pf = sir(200)
    a = pf.run(model, b0, ys, generator=torch.Generator().manual_seed(3), compile=True)
    # an equal configuration (a new filter object) reuses the compiled code
    b = sir(200).run(model, b0, ys, generator=torch.Generator().manual_seed(3), compile=True)
    assert prognos_torch.filters.sequence.last_compile_seconds == 0.0
    c = pf.run(model, b0, ys, generator=torch.Generator().manual_seed(4), compile=True)
    assert torch.equal(a.means, b.means) and torch.equal(a.log_likelihoods, b.log_likelihoods)
    assert not torch.equal(a.means, c.means)
    assert a.particles is None and a.log_weights is None
    # the generator advanced past the initial draw and every step's uniforms
    g = torch.Generator().manual_seed(3)
    pf.run(model, b0, ys, generator=g, compile=True)
    h = torch.Generator().manual_seed(3)
    pf.init(model, b0, generator=h)
    torch.rand((30, 208 + 1), generator=h, dtype=F64)
    assert torch.equal(g.get_state(), h.get_state())


def test_compiled_sir_estimates_the_linear_gaussian_likelihood():
    """On a linear-Gaussian model the particle log-likelihood is unbiased for the likelihood
    (its exponential); with 20,000 particles it lies within a few of its standard errors of the
    Kalman filter's exact value, compiled as eagerly."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from _kalman_reference import kalman_filter

    F, H, LQ, LR = 0.9, 1.0, 0.5, 0.4
    t = lambda v: torch.tensor([[v]], dtype=F64)  # noqa: E731
    model = linear_gaussian_model(t(F), t(H), t(LQ), t(LR))
    ys = _data(model, (), 50, None, seed=9)
    b0 = GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    one = np.ones((1, 1))
    _, _, exact = kalman_filter(
        F * one, H * one, LQ**2 * one, LR**2 * one, np.zeros(1), one, ys.numpy()
    )
    lls = [
        float(
            sir(20000)
            .run(model, b0, ys, generator=torch.Generator().manual_seed(s), compile=True)
            .log_likelihood
        )
        for s in range(4)
    ]
    assert abs(sum(lls) / 4 - exact) < 0.05, (lls, exact)


def test_compiled_run_falls_back_to_eager_when_the_pass_is_not_finite():
    """A measurement that rules out every particle: the eager step's exact path (weight
    collapse, its warning) decides, from the same generator state as the eager run."""
    from prognos_torch.filters.particle import WeightCollapseWarning

    model = _model_1d(True)
    ys = _data(model, (), 20, None, seed=1)
    ys[10] = 1e200  # every squared residual overflows: every weight is 0
    b0 = GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    pf = sir(100)
    with pytest.warns(WeightCollapseWarning):
        out = pf.run(model, b0, ys, generator=torch.Generator().manual_seed(2), compile=True)
    with pytest.warns(WeightCollapseWarning):
        ref = pf.run(model, b0, ys, generator=torch.Generator().manual_seed(2))
    assert torch.equal(out.means, ref.means) and bool(out.collapsed[10])


def test_compiled_run_names_what_it_needs():
    model = _model_1d(True)
    ys = _data(model, (), 10, None, seed=1)
    b0 = GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    g = torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match="EKF proposal"):
        upf(50).run(model, b0, ys, generator=g, compile=True)
    with pytest.raises(ValueError, match="square-root EKF"):
        ekpf(50, proposal=ekf(sqrt=False)).run(model, b0, ys, generator=g, compile=True)
    uses_k = StateSpaceModel(
        f=lambda x, u, k: x * (k + 1), h=model.h, state_dim=1, obs_dim=1, batched=True,
        chol_Q=model.chol_Q, chol_R=model.chol_R,
    )  # fmt: skip
    with pytest.raises(RuntimeError, match="could not compile"):
        sir(50).run(uses_k, b0, ys, generator=g, compile=True)
    with pytest.raises(ValueError, match="systematic"):
        sir(50, resampler="multinomial").run(model, b0, ys, generator=g, compile=True)
    noisy = StateSpaceModel(
        f=model.f,
        h=model.h,
        state_dim=1,
        obs_dim=1,
        batched=True,
        chol_Q=lambda k: torch.tensor([[0.1]], dtype=F64),
        chol_R=model.chol_R,
    )
    with pytest.raises(ValueError, match="constant"):
        sir(50).run(noisy, b0, ys, generator=g, compile=True)
    gappy = ys.clone()
    gappy[3] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        sir(50).run(model, b0, gappy, generator=g, compile=True)
    grad = GaussianBelief(torch.zeros(1, dtype=F64, requires_grad=True), torch.eye(1, dtype=F64))
    with pytest.raises(ValueError, match="gradient"):
        sir(50).run(model, grad, ys, generator=g, compile=True)
    with pytest.raises(TypeError, match="compile must be a bool"):
        sir(50).run(model, b0, ys, generator=g, compile=1)
    state = g.get_state()
    with pytest.raises(ValueError):
        sir(50).run(model, b0, gappy, generator=g, compile=True)
    assert torch.equal(g.get_state(), state)  # nothing drawn before the error
    assert isinstance(sir(50).init(model, b0, generator=g), ParticleState)


@pytest.mark.parametrize("refused", [False, True])
def test_a_step_the_scan_operator_refuses_runs_compiled_step_by_step(monkeypatch, refused):
    """A model whose closures alias (``A.mT`` in ``f``, ``A`` in ``h``): torch 2.13's scan
    operator refuses the traced step (2.14 takes it), and the pass runs as one compiled call per
    step, with the same numbers as the eager filter fed the same draws. ``refused``: the
    refusal is forced, so that the step-by-step pass is checked whatever torch's version."""
    import prognos_torch.filters._particle_compiled as pc

    if refused:

        def refuse(*args, **kwargs):
            raise torch._dynamo.exc.UncapturedHigherOrderOpError("inputs alias (forced)")

        monkeypatch.setattr(pc, "_compiled_scan", refuse)
    A = torch.tensor([[0.9, 0.2], [0.0, 0.8]], dtype=F64)
    model = StateSpaceModel(
        f=lambda x, u, k: x @ A.mT,
        h=lambda x, u, k: torch.tanh(x @ A),
        state_dim=2,
        obs_dim=2,
        chol_Q=0.2 * torch.eye(2, dtype=F64),
        chol_R=0.3 * torch.eye(2, dtype=F64),
        batched=True,
    )
    ys = _data(model, (), 30, None, seed=6)
    pf = sir(200)
    b0 = GaussianBelief(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    state = pf.init(model, b0, generator=torch.Generator().manual_seed(0))
    before = dict(pc._PER_STEP)
    gen = torch.Generator().manual_seed(5)
    out = pf.run(model, state, ys, generator=gen, keep_particles=True, compile=True)
    if refused:
        assert len(set(pc._PER_STEP) - set(before)) == 1  # the step compiled alone, kept
    ref = _eager_with_the_compiled_draws(pf, model, state, ys, None, 5, monkeypatch)
    _compare(out, ref)


def test_compiled_code_is_not_reused_across_dtypes(monkeypatch):
    """A float32 run between two float64 runs of the same filter and model: each gets its own
    compiled step (the noise constants in the dtype of its particles), and the float64 pass
    equals the eager filter fed the same draws."""
    model = _model_1d(True)
    ys = _data(model, (), 25, None, seed=8)
    pf = sir(160)
    b64 = GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    b32 = GaussianBelief(torch.zeros(1), torch.eye(1))
    s32 = pf.init(model, b32, generator=torch.Generator().manual_seed(0))
    g32 = torch.Generator().manual_seed(2)
    out32 = pf.run(model, s32, ys.float(), generator=g32, keep_particles=True, compile=True)
    assert out32.means.dtype == torch.float32 and out32.final.particles.dtype == torch.float32
    s64 = pf.init(model, b64, generator=torch.Generator().manual_seed(0))
    gen = torch.Generator().manual_seed(2)
    out = pf.run(model, s64, ys, generator=gen, keep_particles=True, compile=True)
    ref = _eager_with_the_compiled_draws(pf, model, s64, ys, None, 2, monkeypatch)
    _compare(out, ref)


def test_compiled_sir_runs_a_one_state_linear_model():
    """``x @ F.mT`` with a 1 x 1 ``F``: the loop code of inductor's C++ wrapper (torch 2.13)
    corrupts the heap on it, so the whole-pass scan runs with the Python wrapper. Checked
    against the exact Kalman likelihood within Monte Carlo error."""
    F, H = torch.tensor([[0.9]], dtype=F64), torch.tensor([[1.0]], dtype=F64)
    model = StateSpaceModel(
        f=lambda x, u, k: x @ F.mT,
        h=lambda x, u, k: x @ H.mT,
        state_dim=1,
        obs_dim=1,
        chol_Q=torch.tensor([[0.5]], dtype=F64),
        chol_R=torch.tensor([[0.4]], dtype=F64),
        batched=True,
    )
    ys = _data(model, (), 30, None, seed=4)
    b0 = GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    out = sir(5000).run(model, b0, ys, generator=torch.Generator().manual_seed(1), compile=True)
    ref = sir(5000).run(model, b0, ys, generator=torch.Generator().manual_seed(1))
    assert abs(float(out.log_likelihood) - float(ref.log_likelihood)) < 0.5
