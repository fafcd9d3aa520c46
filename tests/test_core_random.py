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
