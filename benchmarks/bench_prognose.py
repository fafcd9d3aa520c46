"""Benchmark of ``prognos_torch.workflow.prognose`` on a long series, model selection included.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_prognose.py [--rows 6000] [--repeat 3]

The series: ``--rows`` values, a healthy phase (noise around 1) for the first two thirds, then
an exponential rise (to about 3.7) with multiplicative noise; threshold 5. Timed: the first call in the
process (its first use of the library's code paths; it imported ``torch._dynamo`` through
``torch.optim``'s ``add_param_group`` and SymPy through ``torch.broadcast_shapes`` before the
library avoided both), then ``--repeat`` calls of ``prognose(method="auto")`` (onset, three trend
shapes x 27 noise settings in one filter run, the online ELM, the backtest, 2,000 RUL paths)
interleaved with the same number of calls of the workflow's previous route on the same data,
``fit_series(learner="elm") + rul(filter="stpf")``, as the peer measured in the same run, and of
``prognose(filter="ekf+stekf")`` (the models fitted under both filters and pooled).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import torch

from prognos_torch.workflow import Series, fit_series, prognose, rul


def series(rows: int) -> Series:
    g = torch.Generator().manual_seed(0)
    t = torch.arange(rows, dtype=torch.float64)
    on = 2 * rows // 3
    s = (t - on).clamp(min=0) / (rows - on)
    noise = torch.randn(rows, generator=g, dtype=torch.float64)
    y = 1.0 + 0.05 * noise + (0.05 * torch.exp(4.0 * s) - 0.05) * torch.exp(0.05 * noise)
    return Series(y, t, "y")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, default=6000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    s = series(args.rows)
    thr = 5.0
    t0 = time.perf_counter()
    res = prognose(s, thr)
    first = time.perf_counter() - t0
    ours, peer, pool = [], [], []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        res = prognose(s, thr)
        ours.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        prognose(s, thr, filter="ekf+stekf")
        pool.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        rul(fit_series(s, learner="elm"), s, thr, filter="stpf")
        peer.append(time.perf_counter() - t0)
    print(f"machine: {platform.platform()}, torch {torch.__version__}, threads 1")
    print(f"series: {args.rows} rows; onset at {res.onset.time:g}; model {res.model}; "
          f"median RUL {res.summary()['median']}")  # fmt: skip
    print("| call | median s | best s |\n|---|---|---|")
    print(f"| prognose, first call in the process | {first:.2f} | |")
    print(f"| prognose(method='auto') | {statistics.median(ours):.2f} | {min(ours):.2f} |")
    print(f"| prognose(filter='ekf+stekf') | {statistics.median(pool):.2f} | {min(pool):.2f} |")
    print(f"| fit_series(elm) + rul(stpf) (peer) | {statistics.median(peer):.2f} | "
          f"{min(peer):.2f} |")  # fmt: skip
    print(
        f"ratio prognose / peer (medians): {statistics.median(ours) / statistics.median(peer):.2f}"
    )


if __name__ == "__main__":
    main()
