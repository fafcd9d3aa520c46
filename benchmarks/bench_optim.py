"""Benchmark of the Kalman optimisers on the paper 003 Lorenz set-up (ANFIS, 44 parameters).

Rows: one pass over the 497 training pairs of the Lorenz(x) series (1000 points, RK4 with
dt = 0.01, scaled to [0, 1], embedding dimension 3) with EKF, SRUKF and ImSRUKF, one run each,
and ImSRUKF with 50 Monte Carlo runs (50 ANFIS initialisations) vectorised in one optimiser.
Times are the optimiser steps only (``History.time`` of :func:`prognos_torch.optim.fit`), the
best of ``--repeats`` passes from a fresh optimiser. ``--profile`` adds where the time of one
pass goes, per step, by function (cProfile; its own overhead inflates small functions).

    python benchmarks/bench_optim.py [--threads 1] [--repeats 3] [--runs 50] [--profile]
"""

from __future__ import annotations

import argparse
import copy
import cProfile
import pstats
import time
from pathlib import Path

import torch

from prognos_torch.datasets.windows import MinMaxScaler, chronological_split, embed
from prognos_torch.learners import ANFIS
from prognos_torch.optim import KalmanOptimizer, ParameterBridge, fit
from prognos_torch.systems.lorenz import lorenz_series

ROOT = str(Path(__file__).resolve().parents[1]) + "/"  # trimmed from profile paths
P0 = {"alpha": 1.0, "b": 1e-2, "beta": 1e-4}
Q, R = 1e-6, 1e-3
TARGET_ONE, TARGET_MANY = 0.2, 3.0


def lorenz_data(device=None):
    z = MinMaxScaler().fit_transform(lorenz_series(1000, device=device))
    U, T = embed(z, 3)
    Xtr, Xte = chronological_split(U, n_train=497)
    Ytr, Yte = chronological_split(T.unsqueeze(-1), n_train=497)
    return Xtr, Ytr, Xte, Yte


def make(filter_name: str, runs: int | None, Xtr, device=None):
    """A fresh ANFIS and its Kalman optimiser; run ``s`` starts from the ANFIS of seed ``s``
    (premises initialised on the CPU copy of ``Xtr``; built once per run count and cached)."""
    model = copy.deepcopy(_initial(runs or 1, Xtr)[0]).to(device)
    theta0 = _initial(runs, Xtr)[1].to(device) if runs else None
    opt = KalmanOptimizer(model, filter=filter_name, P0=P0, Q=Q, R=R, runs=runs, theta0=theta0)
    return model, opt


_INITS: dict = {}


def _initial(runs: int, Xtr):
    """(ANFIS of seed 0, stacked initial parameters ``(runs, 44)``), on the CPU, cached per
    run count and training inputs."""
    X = Xtr.cpu()
    key = (runs, tuple(X.shape), hash(X.numpy().tobytes()))
    if key not in _INITS:
        inits = [
            ANFIS(3, 2, generator=torch.Generator().manual_seed(s)).init_premises(X)
            for s in range(runs)
        ]
        _INITS[key] = (inits[0], ParameterBridge(inits[0]).stack(inits))
    return _INITS[key]


def one_pass(filter_name, runs, data, repeats, device=None):
    Xtr, Ytr, Xte, Yte = data
    best, hist = float("inf"), None
    for _ in range(repeats):
        model, opt = make(filter_name, runs, Xtr, device)
        hist = fit(model, opt, (Xtr, Ytr), epochs=1, val=(Xte, Yte), progress=False)
        best = min(best, hist.time[0])
    return best, hist


# Function groups reported by --profile (cumulative time of these functions, per step).
GROUPS = [
    ("KalmanOptimizer.step (all)", "kalman.py", "step"),
    ("GaussianFilter.step (engine, incl. h)", "gaussian.py", "step"),
    ("  model evaluation h: ParameterBridge.measurement", "params.py", "measurement"),
    ("  EKF Jacobian: ParameterBridge.jacobian", "params.py", "jacobian"),
    ("  _moments (sigma points + h)", "gaussian.py", "_moments"),
    ("  _prior (tria of [S, S_Q])", "gaussian.py", "_prior"),
    ("  _innovation_chol", "gaussian.py", "_innovation_chol"),
    ("  _posterior_chol", "gaussian.py", "_posterior_chol"),
    ("  SageHusa.update", "noise.py", "update"),
    ("    _project_pd", "noise.py", "_project_pd"),
    ("  tria (QR), all calls", "linalg.py", "tria"),
    ("  cho_solve_right (gain)", "linalg.py", "cho_solve_right"),
    ("  chol_downdate", "linalg.py", "chol_downdate"),
    ("optimiser input checks: _check_batch", "kalman.py", "_check_batch"),
    ("write-back: ParameterBridge.assign", "params.py", "assign"),
]


def profile(filter_name, runs, data, device=None, top=15):
    Xtr, Ytr, _, _ = data
    model, opt = make(filter_name, runs, Xtr, device)
    opt.step(Xtr[:1], Ytr[:1])  # warm-up: caches, first-step initialisation
    n = Xtr.shape[0] - 1
    pr = cProfile.Profile()
    pr.enable()
    for i in range(1, n + 1):
        opt.step(Xtr[i : i + 1], Ytr[i : i + 1])
    pr.disable()
    st = pstats.Stats(pr).stats
    label = f"{filter_name}, runs={runs or 1}"
    print(f"\nWhere the time goes ({label}; cProfile, microseconds per step, {n} steps)")
    print(f"{'group (cumulative)':58s} {'us/step':>9s}")
    for name, file, func in GROUPS:
        cum = sum(v[3] for k, v in st.items() if k[0].endswith(file) and k[2] == func)
        if cum > 0:
            print(f"{name:58s} {cum / n * 1e6:9.0f}")
    print(f"\ntop {top} functions by own time (tottime), {label}")
    print(f"{'function':70s} {'calls/step':>10s} {'us/step':>9s}")
    rows = sorted(st.items(), key=lambda kv: -kv[1][2])[:top]
    for (file, line, func), (_, nc, tt, _, _) in rows:
        where = f"{file.split('site-packages/')[-1].split(ROOT)[-1]}:{line}({func})"
        print(f"{where[-70:]:70s} {nc / n:10.1f} {tt / n * 1e6:9.0f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1)")
    ap.add_argument("--repeats", type=int, default=3, help="passes per row, best reported")
    ap.add_argument("--runs", type=int, default=50, help="Monte Carlo runs of the batched row")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--profile", action="store_true", help="profile ImSRUKF (1 and --runs runs)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    data = lorenz_data(device)
    print(
        f"ANFIS (3 inputs, 2 sigmoid MFs, 44 parameters), Lorenz(x) one-step, one pass over "
        f"{data[0].shape[0]} training pairs; P0={P0}, Q={Q}, R={R}; torch {torch.__version__}, "
        f"{args.threads} thread(s), device {device}"
    )
    rows = [
        ("EKF", "ekf", None, TARGET_ONE),
        ("SRUKF", "srukf", None, TARGET_ONE),
        ("ImSRUKF", "imsrukf", None, TARGET_ONE),
        (f"ImSRUKF x {args.runs} runs", "imsrukf", args.runs, TARGET_MANY),
    ]
    print(
        f"\n{'optimiser':22s} {'pass [s]':>9s} {'us/step':>9s} {'target [s]':>10s} "
        f"{'test MAE':>17s} {'test RMSE':>9s}"
    )
    for label, name, runs, target in rows:
        t, hist = one_pass(name, runs, data, args.repeats, device)
        mae, rmse = hist.val["mae"][-1], hist.val["rmse"][-1]
        steps = hist.steps
        mae_s = f"{float(mae.mean()):.4f}" + (f" +- {float(mae.std()):.4f}" if mae.dim() else "")
        print(
            f"{label:22s} {t:9.3f} {t / steps * 1e6:9.0f} {target:10.1f} "
            f"{mae_s:>17s} {float(rmse.mean()):9.4f}" + ("" if t <= target else "  (over target)")
        )
    if args.profile:
        profile("imsrukf", None, data, device)
        profile("imsrukf", args.runs, data, device)
        profile("ekf", None, data, device, top=10)


if __name__ == "__main__":
    t0 = time.perf_counter()
    main()
    print(f"\ntotal {time.perf_counter() - t0:.1f} s")
