"""Per-run cost of a batched study pass against the batch size and the torch thread count.

Usage::

    python benchmarks/bench_study_batching.py [--runs 1 10 50] [--threads 1 2] [--filter SCKF]

Times the rolling 5-step-ahead az2 prediction of the elm-stsckf study (paper 000: ROS-ELM
forecasts, joint filter on ``[h1, h2, h3, az2]``, ``k = 50..200``), exactly the study's
``_predict`` job, for ``R`` runs in one batched pass, after one warm-up pass; wall and process
CPU time, in total and per run. Each thread count is set with ``torch.set_num_threads`` before
its passes (the study command itself runs single-threaded unless ``--threads`` is given).
"""

from __future__ import annotations

import argparse
import platform
import time

import torch

from prognos_torch.studies import StudyConfig, load_trainer, trainers_dir


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, nargs="+", default=[1, 10, 50])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--filter", default="SCKF")
    args = ap.parse_args(argv)
    E = load_trainer(trainers_dir() / "elm_stsckf.py")
    R = max(args.runs)
    _, y, _, fc = E._simulate(StudyConfig(runs=R), R, 200)
    ys = y[:200]
    print(f"# {platform.processor() or platform.machine()}, {torch.__version__}, {args.filter}")
    print("| threads | runs | wall (s) | wall per run (s) | CPU (s) | CPU per run (s) |")
    print("|---|---|---|---|---|---|")
    for th in args.threads:
        torch.set_num_threads(th)
        E._predict(args.filter, ys[:, :1], fc.select(slice(0, 1)), E.CHOL_D, "cpu")  # warm-up
        for r in args.runs:
            c0, w0 = time.process_time(), time.perf_counter()
            E._predict(args.filter, ys[:, :r], fc.select(slice(0, r)), E.CHOL_D, "cpu")
            c, w = time.process_time() - c0, time.perf_counter() - w0
            print(f"| {th} | {r} | {w:.3f} | {w / r:.4f} | {c:.3f} | {c / r:.4f} |", flush=True)


if __name__ == "__main__":
    main()
