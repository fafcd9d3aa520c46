"""What a command pays before it computes: shapes broadcast without torch's symbolic-shape
machinery, and a prognosis does not import torch's compiler (``torch._dynamo``), SymPy or
matplotlib (without a figure)."""

from __future__ import annotations

import itertools
import subprocess
import sys

import pytest
import torch

from prognos_torch.core.validation import broadcast_shape


def test_broadcast_shape_equals_torch_broadcast_shapes():
    # every pair and triple of shapes over sizes {0, 1, 2, 3} up to 3 dims: the same shape, or
    # both refuse (torch: RuntimeError; ours: ValueError naming the shapes)
    shapes = [()] + [s for n in (1, 2, 3) for s in itertools.product((0, 1, 2, 3), repeat=n)]
    cases = list(itertools.product(shapes[:41], repeat=2))
    cases += list(itertools.product(shapes[:13], repeat=3))
    refused = 0
    for case in cases:
        try:
            want = torch.broadcast_shapes(*case)
        except RuntimeError:
            refused += 1
            with pytest.raises(ValueError, match=r"^shapes .* do not broadcast$"):
                broadcast_shape(*case)
            continue
        assert broadcast_shape(*case) == want, case
    assert 100 < refused < len(cases) - 1000  # both kinds of case are exercised
    assert broadcast_shape() == torch.Size([]) and isinstance(broadcast_shape((2,)), torch.Size)


def test_a_prognosis_imports_neither_the_compiler_nor_sympy_nor_matplotlib():
    code = """
import sys
import torch
before = {m for m in ("torch._dynamo", "sympy", "matplotlib") if m in sys.modules}
from prognos_torch.workflow import prognose
g = torch.Generator().manual_seed(0)
y = 1.0 + 0.02 * torch.randn(300, generator=g, dtype=torch.float64)
y[200:] += 0.01 * torch.exp(torch.arange(100, dtype=torch.float64) / 20)
r = prognose(y, 3.0, n_paths=200)
assert r.status == "ok" and r.model == "exponential+elm", r.model
print(sorted(m for m in ("torch._dynamo", "sympy", "matplotlib") if m in sys.modules and m not in before))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
