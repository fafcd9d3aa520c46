"""Benchmark of ``prognos_torch.workflow.calibrate_rul``: the histories replayed in one process
or in ``--workers`` processes.

Usage (one whole process per call; pair the two settings side by side)::

    python benchmarks/bench_calibrate.py --histories 6 --workers 1
    python benchmarks/bench_calibrate.py --histories 6 --workers 2

The histories: the first ``--histories`` records of
:func:`~prognos_torch.systems.run_to_failure_set` (two per family, seed 3), replayed under the
known-threshold protocol through ``prognose(method="auto")`` (``--method``: another of its
methods) at 20/40/60/80/90 % of [onset, end of life]. Prints the calibration (points, margin:
the same for every ``--workers``) and the seconds of the ``calibrate_rul`` call.
"""

from __future__ import annotations

import argparse
import time

from prognos_torch.systems import run_to_failure_set
from prognos_torch.workflow import calibrate_rul


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--histories", type=int, default=6)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--method", default="auto", help="prognose's method (default auto)")
    args = ap.parse_args(argv)
    cases = list(run_to_failure_set(2, seed=3).items())[: args.histories]
    hist = {name: (r.t, r.y) for name, r in cases}
    t0 = time.perf_counter()
    cal, _ = calibrate_rul(hist, workers=args.workers, method=args.method)
    took = time.perf_counter() - t0
    print(f"{len(hist)} histories, {cal.n} points, margin {cal.margin!r}, "
          f"workers {args.workers}: {took:.2f} s")  # fmt: skip


if __name__ == "__main__":
    main()
