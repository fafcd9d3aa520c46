"""filters.run_in_segments: the same filter as one run, in bounded memory, and the noise in use."""

from __future__ import annotations

import pytest
import torch

from prognos_torch.adapt import MovingWindow
from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import GaussianFilter, run, run_in_segments, ukf
from prognos_torch.quadrature import unscented

t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731


def _setup(T=23, B=3, seed=0):
    model = linear_gaussian_model(
        t([[0.95, 0.1], [-0.1, 0.9]]),
        t([[1.0, 0.5], [0.0, 1.0]]),
        chol_Q=t([[0.3, 0.0], [0.1, 0.2]]),
        chol_R=lambda k: (0.5 + 0.01 * k) * torch.eye(2, dtype=torch.float64),
    )
    g = torch.Generator().manual_seed(seed)
    ys = torch.randn(T, B, 2, generator=g, dtype=torch.float64).cumsum(0) * 0.2
    eye = torch.eye(2, dtype=torch.float64)
    b0 = GaussianBelief(torch.zeros(B, 2, dtype=torch.float64), eye.expand(B, 2, 2).clone())
    return model, ys, b0


@pytest.mark.parametrize("segment", [1, 5, 23, 100])
def test_fixed_noise_equals_one_run_and_the_model_noise(segment):
    model, ys, b0 = _setup()
    filt = ukf(1.0, 0.0, 1.0, sqrt=True)
    ref = run(filt, model, b0, ys, k0=4)
    seg = run_in_segments(filt, model, b0, ys, segment=segment, k0=4)
    torch.testing.assert_close(seg.means, ref.means, rtol=0, atol=0)
    torch.testing.assert_close(seg.final.belief.chol, ref.final.belief.chol, rtol=0, atol=0)
    assert seg.var_Q.shape == (23, 3, 2) and seg.var_R.shape == (23, 3, 2)
    LQ = t([[0.3, 0.0], [0.1, 0.2]])
    torch.testing.assert_close(seg.var_Q, torch.diagonal(LQ @ LQ.mT).expand(23, 3, 2))
    r = torch.tensor([(0.5 + 0.01 * k) ** 2 for k in range(5, 28)], dtype=torch.float64)
    torch.testing.assert_close(seg.var_R, r[:, None, None].expand(23, 3, 2))


@pytest.mark.parametrize("segment", [1, 7, 50])
def test_noise_estimator_in_use_is_the_estimate_of_the_previous_step(segment):
    model, ys, b0 = _setup(T=30)
    filt = GaussianFilter(unscented(1.0, 0.0, 1.0), noise=MovingWindow(window=5, diagonal=True))
    ref = run(filt, model, b0, ys)
    seg = run_in_segments(filt, model, b0, ys, segment=segment)
    torch.testing.assert_close(seg.means, ref.means, rtol=0, atol=0)
    diag = lambda L: torch.diagonal(L @ L.mT, dim1=-2, dim2=-1)  # noqa: E731
    # step 1 uses the model's noise at k = 1, step k > 1 the estimate after step k - 1
    want_Q = torch.cat([diag(model.noise(1).chol_Q).expand(1, 3, 2), diag(ref.chol_Q[:-1])])
    want_R = torch.cat([diag(model.noise(1).chol_R).expand(1, 3, 2), diag(ref.chol_R[:-1])])
    torch.testing.assert_close(seg.var_Q, want_Q, rtol=1e-14, atol=0)
    torch.testing.assert_close(seg.var_R, want_R, rtol=1e-14, atol=0)
    assert not torch.equal(seg.var_R[-1], seg.var_R[0])  # the estimator moved


def test_run_in_segments_rejects_bad_input():
    model, ys, b0 = _setup(T=4)
    filt = ukf(1.0, 0.0, 1.0, sqrt=True)
    with pytest.raises(ValueError, match="segment"):
        run_in_segments(filt, model, b0, ys, segment=0)
    with pytest.raises(ValueError, match="ys"):
        run_in_segments(filt, model, b0, ys[:0], segment=2)
