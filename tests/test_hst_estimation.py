"""Fault estimation on the high-speed train: the nominal model and the per-run simulation."""

from __future__ import annotations

import math

import pytest
import torch

from prognos_torch.systems import (
    HSTParams,
    hst_fault_model,
    hst_nominal_fault_model,
    simulate_hst,
    simulate_hst_runs,
)

P = HSTParams()
QS = P.sigma**2
CHOL_D = (1e-2, 1e-2, 1e-4)


def _gen(i: int) -> torch.Generator:
    return torch.Generator().manual_seed(100 + i)


# ----------------------------------------------------------------------------- systems
def test_nominal_model_has_the_constant_noise_and_the_true_dynamics():
    m = hst_nominal_fault_model(P, q_level=2.0, r_level=11.0, chol_D=CHOL_D, q_scale=QS)
    true = hst_fault_model(P, chol_D=CHOL_D, q_scale=QS)
    for k in (1, 7, 400):
        n = m.noise(k)
        std = [math.sqrt(2.0 * QS)] * 9 + list(CHOL_D)
        torch.testing.assert_close(n.chol_Q, torch.diag(torch.tensor(std, dtype=torch.float64)))
        torch.testing.assert_close(n.chol_R, math.sqrt(11.0) * torch.eye(9, dtype=torch.float64))
    x = 0.1 * torch.randn(4, 12, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    torch.testing.assert_close(m.transition(x, None, 300), true.transition(x, None, 300))
    torch.testing.assert_close(m.observe(x, None, 300), true.observe(x, None, 300))
    with pytest.raises(ValueError, match="r_level"):
        hst_nominal_fault_model(P, r_level=-1.0)


def test_simulate_runs_stacks_one_simulation_per_generator():
    truth, y, t = simulate_hst_runs(15, [_gen(0), _gen(1), _gen(2)], params=P, q_scale=QS)
    assert truth.shape == (16, 3, 12) and y.shape == (15, 3, 9) and t.shape == (16,)
    one = simulate_hst(15, 1, params=P, q_scale=QS, generator=_gen(1))
    torch.testing.assert_close(truth[:, 1], torch.cat([one.x, one.theta], -1)[:, 0])
    torch.testing.assert_close(y[:, 1], one.y[:, 0])
    two, _, _ = simulate_hst_runs(15, [_gen(0), _gen(1)], params=P, q_scale=QS)
    torch.testing.assert_close(two, truth[:, :2])  # a run does not depend on how many are drawn
    assert float(t[-1]) == pytest.approx(15 * P.sigma)
    with pytest.raises(ValueError, match="generators"):
        simulate_hst_runs(15, [])
