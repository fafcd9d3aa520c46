"""Fleet RUL benchmark: 10,000 synthetic assets x 500 steps, accuracy against known failures.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_fleet.py [--assets 10000] [--steps 500]
        [--samples 1000] [--shard-size 1024] [--method exponential|prognose] [--ray]
        [--workers 2] [--io] [--json out.json]

The fleet is :func:`prognos_torch.fleet.synthetic_fleet` (exponential degradation after a
random onset, random rate, observation ending at 30-90 % of the degradation interval, 5 %
healthy assets; 500 steps each, or lengths uniform in ``[ragged * 500, 500]`` with
``--ragged``; threshold 20). The timed call is
``fleet_rul(table, 20.0)`` on the in-memory long table (validation, grouping, padding, onset,
the engine's filter over each shard, posterior sampling), run in a child process so that its
peak resident memory (``ru_maxrss``) can be stated. Reported against the truth:

* onset detection rate among degraded assets;
* alpha-lambda hit rate (alpha = 0.2, 0.3): the median RUL within ``[1 - alpha, 1 + alpha]``
  times the true RUL (assets without a RUL count as misses); the prediction time of asset ``j``
  is at the fraction ``lambda_j`` of its degradation interval, so the rate is also given per
  lambda bin;
* coverage of the 90 % interval ``[q05, q95]`` and the median relative error.

``--ray`` also runs the Ray backend on 2 local workers and checks that the table is the same;
``--method prognose`` runs the full ``prognose`` per asset (``--samples`` paths each) instead
of the batched trend; ``--workers N`` also times ``fleet_rul(..., workers=N)`` (the local backend's spawned processes,
process start-up included) and checks that the table is the same; ``--io`` times reading the same
table from CSV and Parquet.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np


def child(args) -> dict:
    import torch

    from prognos_torch.fleet import fleet_rul, synthetic_fleet

    torch.set_num_threads(1)
    sf = synthetic_fleet(args.assets, args.steps, seed=args.seed, ragged=args.ragged)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    draws = {"samples": args.samples} if args.method == "exponential" else {"n_paths": args.samples}
    res = fleet_rul(sf.table, sf.threshold, method=args.method, shard_size=args.shard_size,
                    seed=0, **draws)  # fmt: skip
    wall = time.perf_counter() - t
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    c = res.columns
    med = np.array(c["rul_median"])
    lo, hi = np.array(c["rul_q05"]), np.array(c["rul_q95"])
    truth = sf.true_rul
    deg = np.isfinite(truth)
    got = deg & np.isfinite(med)
    lam = (sf.t_end - sf.onset) / (sf.failure - sf.onset)
    out = {
        "assets": args.assets,
        "rows": int(len(sf.table["t"])),
        "wall_s": wall,
        "peak_rss_mib": rss1 / 1024.0,
        "rss_before_call_mib": rss0 / 1024.0,
        "degraded": int(deg.sum()),
        "onset_detected": float(got.sum() / deg.sum()),
        "false_onsets_on_healthy": int((~deg & np.isfinite(np.array(c["onset_time"]))).sum()),
    }
    for alpha in (0.2, 0.3):
        hit = np.zeros(len(med), dtype=bool)
        hit[got] = np.abs(med[got] - truth[got]) <= alpha * truth[got]
        out[f"alpha_lambda_{alpha}"] = float(hit[deg].mean())
        out[f"alpha_lambda_{alpha}_by_lambda"] = {
            f"{a:.1f}-{b:.1f}": float(hit[deg & (lam >= a) & (lam < b)].mean())
            for a, b in ((0.3, 0.5), (0.5, 0.7), (0.7, 0.9))
        }
    hi_f = np.where(np.isnan(hi), np.inf, hi)
    out["coverage_90"] = float(((lo[got] <= truth[got]) & (truth[got] <= hi_f[got])).mean())
    out["median_rel_error"] = float(np.median(np.abs(med[got] - truth[got]) / truth[got]))
    flags: dict[str, int] = {}
    for f in c["flags"]:
        for x in filter(None, f.split(";")):
            flags[x] = flags.get(x, 0) + 1
    out["flags"] = flags
    if args.ray:
        import ray

        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        try:
            t = time.perf_counter()
            rr = fleet_rul(
                sf.table,
                sf.threshold,
                samples=args.samples,
                shard_size=args.shard_size,
                backend="ray",
            )
            out["ray_wall_s"] = time.perf_counter() - t
        finally:
            ray.shutdown()
        diff = 0.0
        for k in ("rul_median", "rul_q05", "rul_q95", "p_fail_within_horizon"):
            a, b = np.array(c[k]), np.array(rr.columns[k])
            same_nan = np.array_equal(np.isnan(a), np.isnan(b))
            m = np.isfinite(a)
            diff = max(diff, 0.0 if not m.any() else float(np.max(np.abs(a[m] - b[m]) / a[m])))
            out["ray_same_nan_pattern"] = out.get("ray_same_nan_pattern", True) and same_nan
        out["ray_max_rel_diff"] = diff
        out["ray_same_flags"] = rr.columns["flags"] == c["flags"]
    if args.workers > 1:  # the local backend's process pool, timed right after the same call
        t = time.perf_counter()
        rw = fleet_rul(sf.table, sf.threshold, method=args.method, shard_size=args.shard_size,
                       seed=0, workers=args.workers, **draws)  # fmt: skip
        out["workers"] = args.workers
        out["workers_wall_s"] = time.perf_counter() - t
        out["workers_speedup"] = wall / out["workers_wall_s"]
        diff = 0.0
        for k in ("rul_median", "rul_q05", "rul_q95", "p_fail_within_horizon"):
            a, b = np.array(c[k]), np.array(rw.columns[k])
            m = np.isfinite(a) & (a != 0)
            diff = max(diff, 0.0 if not m.any() else float(np.max(np.abs(a[m] - b[m]) / a[m])))
        out["workers_max_rel_diff"] = diff
        out["workers_same_flags"] = rw.columns["flags"] == c["flags"]
    if args.io:
        from prognos_torch.fleet import read_fleet_table, write_table

        with tempfile.TemporaryDirectory() as d:
            cols = {k: list(v) for k, v in sf.table.items()}
            for name in ("f.csv", "f.parquet"):
                path = os.path.join(d, name)
                write_table(path, cols)
                t = time.perf_counter()
                read_fleet_table(path)
                out[f"read_{name.split('.')[1]}_s"] = time.perf_counter() - t
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--assets", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--shard-size", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--ragged", type=float, default=1.0, help="lengths uniform in [ragged*steps, steps]"
    )
    ap.add_argument("--ray", action="store_true")
    ap.add_argument("--workers", type=int, default=1, help="also time the local process pool")
    ap.add_argument("--method", default="exponential", help="exponential or prognose (per asset)")
    ap.add_argument("--io", action="store_true")
    ap.add_argument("--json", default=None)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args)))
        return
    cmd = [sys.executable, __file__, "--child"] + [a for a in sys.argv[1:] if a != "--child"]
    load0 = os.getloadavg()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["machine"] = (
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    )
    out["load_average_before"] = load0
    out["load_average_after"] = os.getloadavg()
    print(json.dumps(out, indent=1))
    print(
        f"\n{out['assets']} assets ({out['rows']} rows): {out['wall_s']:.1f} s (target <= 60 s), "
        f"peak RSS {out['peak_rss_mib']:.0f} MiB; alpha-lambda(0.2) {out['alpha_lambda_0.2']:.3f}, "
        f"(0.3) {out['alpha_lambda_0.3']:.3f}; 90 % coverage {out['coverage_90']:.3f}"
    )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
