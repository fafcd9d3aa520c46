"""Benchmark of the own-data workflow on long series: ``prognos fit | forecast | rul``.

Usage::

    python benchmarks/bench_long.py [--rows 1000 10000 100000] [--learners elm lssvr anfis]
                                    [--exact-lssvr 1000 5000] [--tree PATH] [--timeout 900]
                                    [--json out.json]

Every command runs in a fresh subprocess under ``/usr/bin/time -v`` (GNU time): wall time and
peak resident memory of the whole process, interpreter and imports included, as a user sees
them. Per row count and learner:

* ``fit``: ``prognos fit DATA --column rms --time-column t --learner L --out model.pt`` with the
  defaults (m chosen by validation over its candidates, 20 % held out, holdout metrics);
* ``forecast``: ``prognos forecast model.pt DATA --horizon 50`` (SCKF, 100 filtered steps);
* ``rul``: ``prognos rul model.pt DATA --threshold X`` (STPF, 500 particles, horizon 200), with
  ``X`` 5 % of the series' range above its last value (exit status 3, a censored RUL, is a
  normal outcome and still timed).

``--exact-lssvr N ...`` adds fits of the exact LS-SVR (``--max-support`` above the row count)
at those sizes. ``--tree PATH`` runs the commands with another checkout first on
``PYTHONPATH`` (to measure a previous version interleaved with this one). ELM is the peer:
on a shared machine compare ratios against it, not absolute times.

The series (deterministic): a year-like condition-monitoring indicator, slow drift plus an
exponential growth at the end, a daily cycle of 144 samples and AR(1) noise::

    x_t = 0.1 + 0.05 s + 0.3 exp(5 (s - 1)) + 0.02 sin(2 pi t / 144) + a_t,  s = t / T,
    a_t = 0.95 a_{t-1} + 0.01 e_t
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def make_series(T: int, path: Path, seed: int = 0) -> tuple[float, float]:
    """Write the benchmark series (module notes) to ``path``; return (last value, range)."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    s = t / T
    e = 0.01 * rng.standard_normal(T)
    a = np.zeros(T)
    for i in range(1, T):
        a[i] = 0.95 * a[i - 1] + e[i]
    x = 0.1 + 0.05 * s + 0.3 * np.exp(5 * (s - 1)) + 0.02 * np.sin(2 * math.pi * t / 144) + a
    with open(path, "w") as fh:
        fh.write("t,rms\n")
        fh.writelines(f"{i},{v:.6f}\n" for i, v in enumerate(x))
    return float(x[-1]), float(x.max() - x.min())


def timed(cmd: list[str], env: dict, timeout: float, cwd: str) -> dict:
    """Run ``cmd`` under ``/usr/bin/time -v`` in ``cwd``; wall seconds, peak RSS (MiB), exit
    status. (``python -m`` puts the working directory first on ``sys.path``: run it outside any
    checkout so that ``PYTHONPATH`` decides which tree is measured.)"""
    t0 = time.perf_counter()
    try:
        p = subprocess.run(
            ["/usr/bin/time", "-v", *cmd],
            env=env,
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return {"seconds": time.perf_counter() - t0, "peak_mib": None, "rc": "timeout"}
    wall = time.perf_counter() - t0
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr)
    errs = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")]
    return {
        "seconds": wall,
        "peak_mib": int(rss.group(1)) / 1024 if rss else None,
        "rc": p.returncode,  # GNU time exits with the command's status
        "error": errs[0] if errs else None,
        "stdout": p.stdout,
    }


def _fmt(r: dict | None) -> str:
    if r is None:
        return "—"
    if r["rc"] == "timeout":
        return f"> {r['seconds']:.0f} s (timeout)"
    mem = f"{r['peak_mib']:.0f} MiB" if r["peak_mib"] is not None else "?"
    rc = "" if r["rc"] in (0, 3) else f" (exit {r['rc']})"
    return f"{r['seconds']:.1f} s, {mem}{rc}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, nargs="+", default=[1000, 10000, 100000])
    ap.add_argument("--learners", nargs="+", default=["elm", "lssvr", "anfis"])
    ap.add_argument("--exact-lssvr", type=int, nargs="*", default=[], metavar="N")
    ap.add_argument("--tree", type=Path, default=ROOT, help="checkout to run (default: this)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per command")
    ap.add_argument("--json", type=Path, help="write the raw results here")
    args = ap.parse_args()

    env = dict(os.environ, PYTHONPATH=str(args.tree.resolve()), OMP_NUM_THREADS="1")
    py = [sys.executable, "-m", "prognos_torch.cli"]
    results: list[dict] = []
    print(
        f"# {platform.node()} {platform.machine()} {os.cpu_count()} cores, Python "
        f"{platform.python_version()}, tree {args.tree}, {time.strftime('%Y-%m-%d %H:%M')}"
    )
    meta: dict[int, tuple[float, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        runs = [(n, lr, None) for n in args.rows for lr in args.learners]
        runs += [(n, "lssvr", 10 * n) for n in args.exact_lssvr]
        for n, learner, support in runs:
            data = Path(tmp) / f"s{n}.csv"
            if n not in meta:
                meta[n] = make_series(n, data)
            last, span = meta[n]
            model = Path(tmp) / f"{learner}{n}{support or ''}.pt"
            fit = [*py, "fit", str(data), "--column", "rms", "--time-column", "t"]
            fit += ["--learner", learner, "--out", str(model)]
            if support is not None:
                fit += ["--max-support", str(support)]
            row = {"rows": n, "learner": learner + (" (exact)" if support else ""), "fit": None}
            row["fit"] = timed(fit, env, args.timeout, tmp)
            out = row["fit"].pop("stdout", "")
            sup = re.search(r"support points\s+(\d+)", out)
            row["support"] = int(sup.group(1)) if sup else None
            if model.exists():
                fc = [*py, "forecast", str(model), str(data), "--horizon", "50"]
                row["forecast"] = timed(fc, env, args.timeout, tmp)
                row["forecast"].pop("stdout", None)
                thr = f"{last + 0.05 * span:.6f}"
                ru = [*py, "rul", str(model), str(data), "--threshold", thr]
                row["rul"] = timed(ru, env, args.timeout, tmp)
                row["rul"].pop("stdout", None)
            results.append(row)
            print(
                f"| {n:,} | {row['learner']} | {_fmt(row['fit'])} | {_fmt(row.get('forecast'))} "
                f"| {_fmt(row.get('rul'))} |",
                flush=True,
            )
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
