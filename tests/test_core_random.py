"""core.random.standard_normal: draws on the generator's own device, moved to the data's."""

from __future__ import annotations

import torch

from prognos_torch.core.random import standard_normal


def test_cpu_generator_gives_the_plain_draws_in_any_dtype():
    for dtype in (torch.float64, torch.float32):
        got = standard_normal((3, 4), torch.Generator().manual_seed(7), dtype, "cpu")
        want = torch.randn(3, 4, generator=torch.Generator().manual_seed(7), dtype=dtype)
        assert got.dtype == dtype and torch.equal(got, want)
    # successive calls continue the generator's stream
    g, h = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    a = torch.cat([standard_normal((5,), g, torch.float64, "cpu") for _ in range(2)])
    assert torch.equal(a, torch.randn(10, generator=h, dtype=torch.float64))


def test_draws_land_on_the_requested_device_without_a_generator():
    torch.manual_seed(3)
    got = standard_normal((4,), None, torch.float64, "cpu")
    torch.manual_seed(3)
    assert torch.equal(got, torch.randn(4, dtype=torch.float64))
    meta = standard_normal((2, 2), torch.Generator().manual_seed(0), torch.float64, "meta")
    assert meta.device.type == "meta" and meta.shape == (2, 2)


def _ulp_close(got: torch.Tensor, want: torch.Tensor) -> None:
    # a few ulps of rounding in the vectorised log / cos / sin (at most 3 measured: 1e-15
    # relative), and an absolute 1e-15 where cos or sin is near zero
    torch.testing.assert_close(got, want, rtol=1e-15, atol=1e-15)


def test_large_float64_cpu_draws_are_torch_randn_to_an_ulp():
    for shape in ((4096,), (4097,), (3, 2000, 2), (100_007,)):
        g, h = torch.Generator().manual_seed(11), torch.Generator().manual_seed(11)
        got = standard_normal(shape, g, torch.float64, "cpu")
        want = torch.randn(shape, generator=h, dtype=torch.float64)
        assert got.shape == want.shape and got.dtype == torch.float64
        _ulp_close(got, want)
        # the same layout, not just the same distribution: almost every draw is identical
        assert (got == want).double().mean() > 0.95
        # the generator is left where torch.randn leaves it (the tail's 16 extra uniforms)
        assert torch.equal(
            torch.rand(5, generator=g, dtype=torch.float64),
            torch.rand(5, generator=h, dtype=torch.float64),
        )


def test_large_draws_from_the_global_stream_and_successive_calls():
    torch.manual_seed(4)
    got = standard_normal((5000,), None, torch.float64, "cpu")
    torch.manual_seed(4)
    _ulp_close(got, torch.randn(5000, dtype=torch.float64))
    g, h = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)
    a = torch.cat([standard_normal((4100,), g, torch.float64, "cpu") for _ in range(3)])
    b = torch.cat([torch.randn(4100, generator=h, dtype=torch.float64) for _ in range(3)])
    _ulp_close(a, b)


def test_large_cpu_draws_ignore_a_default_device():
    want = standard_normal((5000,), torch.Generator().manual_seed(8), torch.float64, "cpu")
    torch.set_default_device("meta")
    try:
        got = standard_normal((5000,), torch.Generator().manual_seed(8), torch.float64, "cpu")
    finally:
        torch.set_default_device(None)
    assert got.device.type == "cpu" and torch.equal(got, want)
