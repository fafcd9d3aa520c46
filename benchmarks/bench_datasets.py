"""Benchmark of prognos_torch.datasets: shipped IMS table, LLE health indicator, raw reader.

Usage::

    python benchmarks/bench_datasets.py [--repeat 5] [--n-files 20] [--rows 20480] [--channels 8]

Prints a table of wall-clock times (median and best of ``--repeat`` runs):

* reading ``datasets/ims/test1_features.csv`` (2,156 snapshots x 8 channels);
* paper 002's health indicator (bearing 3, six features, LLE K = 12, last 12 days, 1,263 points);
* the raw reader on synthetic snapshots of real size (20,480 x 8, IMS-like ASCII, tab
  separated), without cache and from a warm cache, in snapshots per second.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import torch

from prognos_torch.datasets import health_indicator, load_ims_features, read_raw_features


def _timed(fn, repeat: int) -> tuple[float, float, object]:
    times, result = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), min(times), result


def _write_snapshots(folder: Path, n_files: int, n_rows: int, n_channels: int) -> None:
    rng = np.random.default_rng(0)
    start = datetime(2003, 10, 22, 12, 6, 24)
    for i in range(n_files):
        x = np.round(-0.09 + 0.08 * rng.standard_normal((n_rows, n_channels)), 3)
        name = (start + timedelta(minutes=10 * i)).strftime("%Y.%m.%d.%H.%M.%S")
        np.savetxt(folder / name, x, fmt="%.3f", delimiter="\t")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5, help="timed runs per row")
    parser.add_argument("--n-files", type=int, default=20, help="synthetic raw snapshots")
    parser.add_argument("--rows", type=int, default=20480, help="samples per snapshot")
    parser.add_argument("--channels", type=int, default=8, choices=(4, 8), help="8: test 1")
    args = parser.parse_args(argv)

    rows = []
    med, best, feats = _timed(load_ims_features, args.repeat)
    rows.append(("load_ims_features(1)", f"{feats.values.shape[0]} snapshots", med, best, ""))
    med_hi, best_hi, hi = _timed(lambda: health_indicator(feats), args.repeat)
    rows.append(("health_indicator (transform)", f"{len(hi.days)} points", med_hi, best_hi, ""))
    med_s, best_s, _ = _timed(lambda: health_indicator(feats, mode="separate"), args.repeat)
    rows.append(("health_indicator (separate)", f"{len(hi.days)} points x 2", med_s, best_s, ""))
    med_t, best_t, _ = _timed(lambda: health_indicator(load_ims_features()), args.repeat)
    rows.append(("load + health_indicator", "target < 2 s", med_t, best_t, ""))

    test = 1 if args.channels == 8 else 2
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        _write_snapshots(folder, args.n_files, args.rows, args.channels)
        size_mb = sum(p.stat().st_size for p in folder.iterdir()) / 1e6
        what = f"{args.n_files} x ({args.rows} x {args.channels}), {size_mb:.0f} MB"
        med_r, best_r, _ = _timed(
            lambda: read_raw_features(folder, test=test, cache=False), args.repeat
        )
        rows.append(("read_raw_features, no cache", what, med_r, best_r, args.n_files / med_r))
        read_raw_features(folder, test=test)  # fill the cache
        med_c, best_c, _ = _timed(lambda: read_raw_features(folder, test=test), args.repeat)
        rows.append(("read_raw_features, cached", what, med_c, best_c, args.n_files / med_c))

    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"torch {torch.__version__} ({torch.get_num_threads()} threads), "
        f"numpy {np.__version__}, repeat={args.repeat}"
    )
    print(f"| {'step':<30} | {'size':<26} | {'median s':>9} | {'best s':>9} | {'snap/s':>8} |")
    print(f"|{'-' * 32}|{'-' * 28}|{'-' * 11}|{'-' * 11}|{'-' * 10}|")
    for step, size, m, b, rate in rows:
        rate_text = f"{rate:8.1f}" if rate else " " * 8
        print(f"| {step:<30} | {size:<26} | {m:9.3f} | {b:9.3f} | {rate_text} |")


if __name__ == "__main__":
    main()
