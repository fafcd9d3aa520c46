"""Particle filters and the filter factories: exact one-step references and bad input named.

- One step of a Gaussian-proposal PF from a point mass on a linear-Gaussian model: the EKF
  proposal is the optimal one, so the weights are uniform and the log-likelihood estimate is
  the Kalman filter's, exactly (closed form, partly missing vectors and a 2-D batch).
- The robust filters of paper 004 by name, ancestors outside ``0..N-1`` (``gather_particles``
  and a custom resampler), a resumed state of another particle count with per-run noise, state
  tensors of another dtype or count, and NumPy threshold scalars.
"""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import (
    FILTERS,
    arukf,
    ekpf,
    make_filter,
    rukf,
    run,
    sir,
    stpf,
    upf,
)
from prognos_torch.filters.particle import ParticleState, gather_particles
from prognos_torch.filters.resampling import systematic

F64 = torch.float64
t = lambda a: torch.as_tensor(a, dtype=F64)  # noqa: E731
gen = lambda s: torch.Generator().manual_seed(s)  # noqa: E731

F = np.array([[0.95, 0.1], [-0.1, 0.9]])
H = np.array([[1.0, 0.5], [0.3, -1.0]])
LQ = np.array([[0.4, 0.0], [0.1, 0.3]])
LR = np.array([[0.6, 0.0], [0.2, 0.5]])
Q0, R0 = np.array([0.05, -0.02]), np.array([0.1, -0.2])


def _model(chol_Q=None):
    LQt = t(LQ) if chol_Q is None else chol_Q
    return linear_gaussian_model(t(F), t(H), LQt, t(LR), q=t(Q0), r=t(R0))


def _scalar_model(chol_Q):
    return linear_gaussian_model(t([[0.8]]), t([[2.0]]), chol_Q, t([[1.0]]))


@pytest.mark.parametrize("factory", [ekpf, upf, stpf])
def test_one_step_from_a_point_mass_is_the_kalman_likelihood(factory):
    """Particles at m0 with a zero factor: the proposal is p(x_1 | x_0, y_1), every increment is
    log N(y_o; H_o (F m0 + q) + r_o, H_o Q H_o^T + R_oo), the weights stay uniform."""
    m0 = np.array([[[0.5, -0.3], [1.0, 2.0]], [[0.0, 0.0], [-1.0, 0.4]]])  # (2, 2) runs
    y = t([[[0.3, 0.2], [1.5, -1.0]], [[math.nan, 0.4], [0.7, math.nan]]])
    pf = factory(6, resample_threshold=0.0)
    b0 = GaussianBelief(t(m0), t(np.eye(2)).expand(2, 2, 2, 2).clone())
    state = pf.init(_model(), b0, generator=gen(0))
    fs = state.proposal
    state = replace(state, particles=t(m0)[..., None, :].expand(2, 2, 6, 2).clone())
    state = replace(state, proposal=replace(fs, belief=GaussianBelief(
        state.particles, torch.zeros_like(fs.belief.chol))))  # fmt: skip
    _, info = pf.step(_model(), state, y, k=1, generator=gen(1))
    Q, R = LQ @ LQ.T, LR @ LR.T
    for i in range(2):
        for j in range(2):
            o = ~np.isnan(y[i, j].numpy())
            S = H[o] @ Q @ H[o].T + R[np.ix_(o, o)]
            e = y[i, j].numpy()[o] - H[o] @ (F @ m0[i, j] + Q0) - R0[o]
            ll = -0.5 * (e @ np.linalg.solve(S, e) + o.sum() * math.log(2 * math.pi)
                         + np.linalg.slogdet(S)[1])  # fmt: skip
            assert float(info.log_likelihood[i, j]) == pytest.approx(ll, abs=1e-12)
    assert float((info.log_weights + math.log(6)).abs().max()) <= 1e-12


def test_make_filter_builds_the_robust_filters_by_name():
    """rukf and arukf are in the module's __all__ but make_filter refused them ("unknown
    filter"). By name (any case) they are the factories' filters; without gamma and M a
    TypeError names them; FILTERS (names that build without settings) is unchanged."""
    M = t([0.1, 0.05])
    model = _model()
    b0 = GaussianBelief.from_cov(t([0.5, -0.3]), t(np.diag([1.0, 0.5])))
    ys = t([[0.3, 0.2], [1.5, -1.0], [0.7, 0.1], [0.2, 0.4]])
    for name, ref in (
        ("rukf", rukf(3.0, M, N=0.5)),
        ("ARUKF", arukf(3.0, M, 0.5, window=2)),
    ):
        got = make_filter(name, gamma=3.0, M=M, N=0.5, **({"window": 2} if ref.noise else {}))
        a, b = run(got, model, b0, ys), run(ref, model, b0, ys)
        assert got.name == ref.name
        assert float((a.means - b.means).abs().max()) <= 1e-12
        assert float((a.chols - b.chols).abs().max()) <= 1e-12
        with pytest.raises(TypeError, match=r"needs the robust bound's gamma and M"):
            make_filter(name, gamma=3.0)
    assert "rukf" not in FILTERS and "arukf" not in FILTERS
    with pytest.raises(ValueError, match=r"unknown filter 'rkf'.*'arukf'"):
        make_filter("rkf")


def test_gather_particles_refuses_ancestors_outside_the_particles():
    """An index N or -1 failed inside gather (RuntimeError) or index_select (IndexError "index
    out of range in self"), and on a GPU as a device-side assert; named now."""
    x = torch.arange(12.0, dtype=F64).reshape(2, 3, 2)
    for anc, obj in (
        (torch.tensor([[0, 1, 3], [0, 0, 0]]), x),
        (torch.tensor([[0, 1, 2], [-1, 0, 0]]), x),
        (torch.tensor([0, 3, 1]), x[0]),
    ):
        with pytest.raises(ValueError, match=r"ancestors must be indices in 0\.\.2"):
            gather_particles(obj, anc)
    anc = torch.tensor([[2, 2, 0], [1, 0, 1]])
    out = gather_particles(x, anc)
    for b in range(2):
        assert torch.equal(out[b], x[b, anc[b]])


def _degenerate_state(B: int | None, N: int = 20):
    """``N`` particles on a grid with one heavy weight (resampled at any threshold)."""
    x = torch.linspace(-1.0, 1.0, N, dtype=F64).reshape(N, 1)
    lw = torch.log_softmax(torch.where(torch.arange(N) == 3, 0.0, -3.0).to(F64), -1)
    if B is not None:
        x, lw = x.expand(B, N, 1).clone(), lw.expand(B, N).clone()
    return ParticleState(x, lw)


@pytest.mark.parametrize("B", [None, 2])
def test_a_custom_resamplers_ancestors_are_checked(B):
    """Float ancestors failed in gather / index_select ("Expected dtype int32/int64"); indices
    outside 0..N-1 failed there too (IndexError "index out of range in self"). int32 ones are
    the int64 ones."""
    model = _scalar_model(t([[0.5]]))
    state = _degenerate_state(B)
    y = t([math.nan]) if B is None else t([[math.nan]] * B)
    for res, exc, msg in (
        (lambda lw, g: systematic(lw, g).double(), TypeError, "integer ancestors"),
        (lambda lw, g: systematic(lw, g) + 20, ValueError, r"indices in 0\.\.19"),
        (lambda lw, g: systematic(lw, g) - 20, ValueError, r"indices in 0\.\.19"),
    ):
        with pytest.raises(exc, match=f"the resampler.*{msg}"):
            sir(20, resampler=res, resample_threshold=1.0).step(model, state, y, generator=gen(0))
    a, _ = sir(20, resampler=lambda lw, g: systematic(lw, g).int()).step(
        model, state, y, generator=gen(0)
    )
    b, _ = sir(20, resampler="systematic").step(model, state, y, generator=gen(0))
    assert torch.equal(a.particles, b.particles)


@pytest.mark.parametrize("factory", [ekpf, stpf])
def test_a_resumed_state_of_another_count_with_per_run_noise(factory):
    """The engine's noise was expanded to num_particles (50), not the state's 7 particles: a
    RuntimeError from expand. The state's count is used, as the bootstrap filter does: the
    same numbers as the filter built for 7 particles."""
    model = _scalar_model(t([[[0.5]], [[0.3]]]))  # per-run Q
    b0 = GaussianBelief(t([[1.0], [0.0]]), t([[2.0]]).expand(2, 1, 1))
    ys = t([[[0.4], [1.1]], [[0.2], [-0.3]]])
    state = factory(7).init(model, b0, generator=gen(1))
    a = factory(50).run(model, state, ys, generator=gen(2))
    b = factory(7).run(model, state, ys, generator=gen(2))
    assert torch.equal(a.means, b.means) and torch.equal(a.final.particles, b.final.particles)
    step, _ = factory(50).step(model, state, ys[0], k=1, generator=gen(3))
    ref, _ = factory(7).step(model, state, ys[0], k=1, generator=gen(3))
    assert torch.equal(step.particles, ref.particles)
    pred = factory(50).predict(model, state, k=1, generator=gen(4))
    assert torch.equal(pred.particles, factory(7).predict(model, state, k=1, generator=gen(4))
                       .particles)  # fmt: skip


def test_states_of_another_dtype_or_particle_count_are_named():
    """Integer log-weights failed in torch.finfo ("requires a floating point input type"),
    float32 ones were promoted; a proposal of another particle count failed in the engine
    ("The size of tensor a (20) must match ...")."""
    model = _scalar_model(t([[0.5]]))
    b0 = GaussianBelief(t([[1.0], [0.0]]), t([[2.0]]).expand(2, 1, 1))
    y = t([[0.4], [1.1]])
    st = sir(5).init(model, b0, generator=gen(0))
    for lw in (st.log_weights.float(), torch.zeros(2, 5, dtype=torch.long)):
        with pytest.raises(ValueError, match=r"state.log_weights must have the particles' dtype"):
            sir(5).step(model, ParticleState(st.particles, lw), y, generator=gen(1))
    st = ekpf(5).init(model, b0, generator=gen(0))
    short = ParticleState(st.particles[:, :3], st.log_weights[:, :3] - math.log(3 / 5), st.proposal)
    with pytest.raises(ValueError, match=r"state.proposal.belief.chol must have shape \(2, 3, 1"):
        ekpf(5).step(model, short, y, generator=gen(1))


def test_a_numpy_float32_threshold_is_its_value():
    """threshold * N was computed in float32 for a numpy.float32 threshold: 0.3 * 1000 gave
    300.0, not 300.0000119 (float32(0.3) = 0.30000001192...), so N_eff = 300.000006 did not
    resample. The settings are kept as Python numbers."""
    N, m = 1000, 100
    target = 300.000006

    def n_eff(c):  # m weights 1 and N - m weights c: (sum w)^2 / sum w^2
        return (m + (N - m) * c) ** 2 / (m + (N - m) * c * c)

    lo, hi = 0.0, 1.0
    for _ in range(80):  # n_eff increases with c on [0, 1]
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if n_eff(mid) < target else (lo, mid)
    w = torch.cat([torch.ones(m, dtype=F64), torch.full((N - m,), lo, dtype=F64)])
    lw = torch.log(w) - torch.log(w.sum())
    state = ParticleState(torch.linspace(-1.0, 1.0, N, dtype=F64).reshape(N, 1), lw)
    model = _scalar_model(t([[0.5]]))
    thr = np.float32(0.3)
    pf = sir(np.int64(N), resample_threshold=thr)
    assert type(pf.num_particles) is int and type(pf.resample_threshold) is float
    assert pf.resample_threshold == float(thr)
    _, info = pf.step(model, state, t([math.nan]), generator=gen(0))
    assert 300.0 < float(info.ess) < float(thr) * N  # between the float32 and the exact cut
    assert bool(info.resampled)
