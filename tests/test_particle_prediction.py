"""rolling_particle_prediction against the plain step loop.

The reference is the plain loop with the same generator (predict from the state at k - 1, then
step): the rolling prediction must reproduce it draw for draw (exact equality), its predictive
summaries must equal particle_paths / fault_probability on the states the loop produced, and its
filter output must equal ParticleFilter.run where no prediction draws in between.
"""

from __future__ import annotations

import pytest
import torch

from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import ekpf, sir, stpf
from prognos_torch.prognosis import (
    fault_probability,
    learner_transition_model,
    particle_paths,
    rolling_particle_prediction,
)

t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731


def _linear():
    return linear_gaussian_model(
        t([[0.95, 0.1], [-0.1, 0.9]]),
        t([[1.0, 0.5]]),
        chol_Q=t([[0.4, 0.0], [0.1, 0.3]]),
        chol_R=t([[0.6]]),
    )


def _ys(T, runs, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(T, runs, 1, generator=g, dtype=torch.float64).cumsum(0) * 0.3


def _belief(runs, n=2):
    eye = torch.eye(n, dtype=torch.float64)
    return GaussianBelief(torch.zeros(runs, n, dtype=torch.float64), eye.expand(runs, n, n))


def _manual(pf, model, b0, ys, k0, H, threshold, seed):
    """The plain loop: predict H steps from the state at k - 1, then assimilate y_k."""
    g = torch.Generator().manual_seed(seed)
    st = pf.init(model, b0, generator=g, k=k0)
    mean, fault, states, infos = [], [], {k0: st}, []
    for j in range(ys.shape[0]):
        k = k0 + j + 1
        pp = particle_paths(model, st.particles, H, generator=g, weights=st.weights, k0=k - 1)
        mean.append(pp.mean)
        fault.append(fault_probability(pp.samples, threshold, pp.weights))
        st, info = pf.step(model, st, ys[j], k=k, generator=g)
        states[k] = st
        infos.append(info)
    states["infos"] = infos
    return torch.stack(mean), torch.stack(fault), states


@pytest.mark.parametrize("factory", [sir, ekpf])
@pytest.mark.parametrize("H", [1, 3])
def test_rolling_particle_prediction_equals_the_manual_loop(factory, H):
    model, pf = _linear(), factory(40)
    ys, k0, thr = _ys(10, 2, seed=1), 3, 0.2
    rp = rolling_particle_prediction(
        pf, model, _belief(2), ys, H,
        generator=torch.Generator().manual_seed(5), threshold=thr, k0=k0, keep=(3, 6, 13),
    )  # fmt: skip
    mean, fault, states = _manual(pf, model, _belief(2), ys, k0, H, thr, seed=5)
    assert rp.mean.shape == (10, 2, H) and rp.std.shape == (10, 2, H)
    torch.testing.assert_close(rp.mean, mean, rtol=0, atol=0)
    torch.testing.assert_close(rp.fault_probability, fault, rtol=0, atol=0)
    assert sorted(rp.states) == [3, 6, 13]
    for k in (3, 6, 13):
        torch.testing.assert_close(rp.states[k].particles, states[k].particles, rtol=0, atol=0)
        torch.testing.assert_close(rp.states[k].log_weights, states[k].log_weights, rtol=0, atol=0)
    assert rp.filtered.shape == (10, 2, 2) and rp.ess.shape == (10, 2)
    infos = states["infos"]
    torch.testing.assert_close(rp.filtered, torch.stack([i.mean for i in infos]), rtol=0, atol=0)
    torch.testing.assert_close(rp.ess, torch.stack([i.ess for i in infos]), rtol=0, atol=0)
    torch.testing.assert_close(rp.final.particles, states[13].particles, rtol=0, atol=0)


def test_rolling_particle_prediction_on_a_learner_window_model_with_stpf():
    # The paper-002 setting: an m-order window model of a one-step predictor, strong tracking.
    m = 3
    model = learner_transition_model(lambda P: 0.9 * P[..., -1:], m, 0.05, 0.05, shift_std=0.05)
    pf = stpf(30)
    ys = 0.5 + _ys(12, 2, seed=2)
    rp = rolling_particle_prediction(
        pf, model, _belief(2, m), ys, generator=torch.Generator().manual_seed(3), k0=0
    )
    mean, _, _ = _manual(pf, model, _belief(2, m), ys, 0, 1, 0.0, seed=3)
    torch.testing.assert_close(rp.mean, mean, rtol=0, atol=0)
    assert rp.fault_probability is None and rp.states == {}


def test_rolling_particle_prediction_rejects_bad_input():
    model, pf, g = _linear(), sir(10), torch.Generator().manual_seed(0)
    ys = _ys(5, 2)
    with pytest.raises(ValueError, match="horizon"):
        rolling_particle_prediction(pf, model, _belief(2), ys, 0, generator=g)
    with pytest.raises(ValueError, match="keep"):
        rolling_particle_prediction(pf, model, _belief(2), ys, generator=g, keep=(6,))
    with pytest.raises(TypeError, match="keep"):
        rolling_particle_prediction(pf, model, _belief(2), ys, generator=g, keep=(1.0,))
    with pytest.raises(ValueError, match="us was given"):
        rolling_particle_prediction(pf, model, _belief(2), ys, generator=g, us=ys)
    with pytest.raises(ValueError, match="ys"):
        rolling_particle_prediction(pf, model, _belief(2), ys[:, 0, 0], generator=g)


def test_rolling_prediction_over_a_zero_weight_particle_that_left_the_reals():
    """The filter keeps a particle that became infinite with weight zero (``run`` is finite);
    the prediction from that state raised ``particles contains non-finite values``. Its paths
    now carry zero weight as the particle does: the same summaries as from the state with that
    particle replaced by any finite value."""
    import math

    from prognos_torch.core import StateSpaceModel

    model = StateSpaceModel(
        f=lambda x, u, k: torch.where(x > 2.0, math.inf, x),
        h=lambda x, u, k: torch.tanh(x),
        state_dim=1, obs_dim=1, chol_Q=t([[0.3]]), chol_R=t([[0.3]]), batched=True,
    )  # fmt: skip
    pf, ys = sir(200, resample_threshold=0.0), torch.full((3, 1), 0.2, dtype=torch.float64)
    b0 = GaussianBelief(t([0.0]), t([[1.0]]))
    rp = rolling_particle_prediction(
        pf, model, b0, ys, 2, generator=torch.Generator().manual_seed(1), threshold=0.5
    )
    g = torch.Generator().manual_seed(1)
    st = pf.init(model, b0, generator=g)
    for j in range(3):
        x = st.particles
        x = torch.where(torch.isfinite(x), x, torch.full_like(x, -7.0))
        pp = particle_paths(model, x, 2, generator=g, weights=st.weights, k0=j)
        assert torch.equal(rp.mean[j], pp.mean)
        assert torch.equal(rp.std[j], pp.std)
        fault = fault_probability(pp.samples, 0.5, pp.weights)
        assert torch.equal(rp.fault_probability[j], fault)
        st, _ = pf.step(model, st, ys[j], k=j + 1, generator=g)
    assert not bool(torch.isfinite(st.particles).all())  # the case arose


def test_rolling_prediction_refuses_options_it_would_ignore_or_misuse():
    """``k0`` reached f, h and the noise as a float or a negative step (``run`` refuses both);
    a misspelt ``direction`` without a threshold was accepted and ignored."""
    model, pf, g = _linear(), sir(10), torch.Generator().manual_seed(0)
    ys = _ys(3, 2)
    for k0 in (1.5, -2):
        with pytest.raises(ValueError, match="k0 must be a non-negative int"):
            rolling_particle_prediction(pf, model, _belief(2), ys, generator=g, k0=k0)
    with pytest.raises(ValueError, match="direction must be 'above' or 'below'"):
        rolling_particle_prediction(pf, model, _belief(2), ys, generator=g, direction="up")
