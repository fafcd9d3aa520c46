"""ANFIS's batched forward and Jacobian (what a Kalman optimiser calls at every step) for many
rules, with the consequents of Eq. 5 multiplied through ``kron(ubar^T, I_R)`` beside the direct
product with the inputs (``learners.anfis.KRON_MAX_ENTRIES`` picks the form; the kron form is
kept for small shapes, where the committed study runs were made with it).

    python benchmarks/bench_anfis_rules.py [--repeat 5] [--max-rules 243]

Rows: inputs x MFs (rules), batch, parameter sets; median wall time of ``--repeat`` calls of
``forward_and_jacobian`` in each form (A B A B), milliseconds, the ratio, the size of the kron
matrix, and the largest difference between the two outputs.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import prognos_torch.learners.anfis as anfis_mod
from prognos_torch.learners import ANFIS

CASES = [(3, 2, 1, 45), (3, 2, 64, 1), (4, 3, 64, 1), (5, 3, 64, 1), (5, 3, 256, 1)]


def timed(net, params, x, kron: bool) -> tuple[float, torch.Tensor]:
    anfis_mod.KRON_MAX_ENTRIES = 2**62 if kron else -1
    out = net.forward_and_jacobian(params, x)[0]
    t0 = time.perf_counter()
    net.forward_and_jacobian(params, x)
    return 1e3 * (time.perf_counter() - t0), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--max-rules", type=int, default=243, help="skip cases with more rules")
    args = ap.parse_args()
    torch.set_num_threads(1)
    default = anfis_mod.KRON_MAX_ENTRIES
    print(
        "| inputs x MFs (rules) | batch | sets | kron ms | direct ms | kron / direct | kron MiB | max diff |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for n, L, B, S in (c for c in CASES if c[1] ** c[0] <= args.max_rules):
        g = torch.Generator().manual_seed(0)
        net = ANFIS(n, L, generator=g)
        params = {k: v.detach().expand(S, *v.shape).clone() for k, v in net.named_parameters()}
        x = torch.randn(B, n, generator=g, dtype=torch.float64)
        R = net.n_rules
        times: dict[bool, list[float]] = {True: [], False: []}
        outs = {}
        for _ in range(args.repeat):
            for kron in (True, False):
                t, outs[kron] = timed(net, params, x, kron)
                times[kron].append(t)
        a, b = statistics.median(times[True]), statistics.median(times[False])
        mib = (n + 1) * R * B * R * 8 / 2**20
        diff = float((outs[True] - outs[False]).abs().max())
        print(
            f"| {n} x {L} ({R}) | {B} | {S} | {a:.2f} | {b:.2f} | {a / b:.2f} | {mib:.3g} | {diff:.1e} |"
        )
    anfis_mod.KRON_MAX_ENTRIES = default


if __name__ == "__main__":
    main()
