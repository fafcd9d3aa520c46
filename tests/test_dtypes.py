"""Dtypes across the public API: float32 where a user asks for it, clear refusals for what the
filters cannot compute in (half precision, complex or bool data), and a named error where a
model and a belief disagree on the dtype."""

from __future__ import annotations

import pytest
import torch

from prognos_torch.adapt.noise import _project_pd
from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import ekf, run, run_in_segments, sckf, sir
from prognos_torch.prognosis import particle_paths, simulate_to_event

F64 = torch.float64


def _linear(dtype=F64):
    A = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=dtype)
    return linear_gaussian_model(A, torch.tensor([[1.0, 0.0]], dtype=dtype),
                                 0.1 * torch.eye(2, dtype=dtype), 0.5 * torch.eye(1, dtype=dtype))  # fmt: skip


def _belief(dtype=F64):
    return GaussianBelief(torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype))


def test_the_noise_projection_holds_in_float32():
    # an indefinite estimate projected to positive definite: the floor 1e-10 max|eig| lay below
    # float32 rounding and the Cholesky after the projection failed (105 of 200 such matrices)
    for seed in range(50):
        g = torch.Generator().manual_seed(seed)
        V, _ = torch.linalg.qr(torch.randn(4, 4, dtype=F64, generator=g))
        C = V @ torch.diag(torch.tensor([1.0, 1e-3, 1e-6, -1e-4], dtype=F64)) @ V.T
        for dt in (F64, torch.float32):
            Cp, L, fb = _project_pd(C.to(dt), torch.tensor(1e-12, dtype=dt), False)
            assert bool(fb) and bool(torch.isfinite(L).all())
            torch.testing.assert_close(L @ L.mT, Cp, rtol=1e-5, atol=1e-6)
        assert float(torch.linalg.eigvalsh(Cp).min()) > 0


def test_a_model_and_a_belief_of_other_dtypes_are_named():
    ys = torch.randn(5, 1, dtype=F64, generator=torch.Generator().manual_seed(0))
    for model, b0, got in ((_linear(F64), _belief(torch.float32), "torch.float32"),
                           (_linear(torch.float32), _belief(F64), "torch.float64")):  # fmt: skip
        with pytest.raises(TypeError, match=f"model.f failed on states of dtype {got}"):
            run(ekf(), model, b0, ys.to(b0.mean.dtype))
    with pytest.raises(TypeError, match="model.f failed on states of dtype torch.float32"):
        particle_paths(_linear(F64), torch.zeros(10, 2), 3, generator=torch.Generator())


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_is_refused_before_it_runs(dtype):
    ys = torch.randn(5, 1, dtype=F64)
    with pytest.raises(TypeError, match=f"init has dtype {dtype}: the filters need float32"):
        run(sckf(), _linear(dtype), _belief(dtype), ys.to(dtype))  # (a raw geqrf error)
    with pytest.raises(TypeError, match=f"belief has dtype {dtype}"):
        sir(50).run(_linear(dtype), _belief(dtype), ys.to(dtype), generator=torch.Generator())
    with pytest.raises(TypeError, match=f"x0 has dtype {dtype}: simulate in float32"):
        simulate_to_event(_linear(dtype), torch.zeros(4, 2, dtype=dtype), lambda x: x[..., 0] > 1,
                          max_steps=5, generator=torch.Generator())  # fmt: skip


def test_complex_and_bool_measurements_are_refused_and_integers_converted():
    model, b0 = _linear(), _belief()
    ys = torch.randint(0, 3, (6, 1))
    for bad in (ys.to(torch.complex128) * (1 + 5j), ys > 0):
        with pytest.raises(TypeError, match=f"ys must hold real numbers, got dtype {bad.dtype}"):
            run(ekf(), model, b0, bad)
        with pytest.raises(TypeError, match="ys must hold real numbers"):
            sir(50).run(model, b0, bad, generator=torch.Generator())
    torch.testing.assert_close(run(ekf(), model, b0, ys).means, run(ekf(), model, b0, ys.double()).means,
                               rtol=0, atol=0)  # fmt: skip


def test_segments_return_the_belief_dtype():
    # float32 dynamics with float64 noise factors (cast to the belief's dtype by the filter)
    model = linear_gaussian_model(torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=torch.float32),
                                  torch.tensor([[1.0, 0.0]], dtype=torch.float32),
                                  0.1 * torch.eye(2, dtype=F64), 0.5 * torch.eye(1, dtype=F64))  # fmt: skip
    out = run_in_segments(sckf(), model, _belief(torch.float32), torch.randn(7, 1), segment=3)
    assert (out.means.dtype, out.var_Q.dtype, out.var_R.dtype) == (torch.float32,) * 3
