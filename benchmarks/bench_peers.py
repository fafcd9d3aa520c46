"""The library beside its peers on paper 003's ANFIS (44 parameters), one pass, one thread.

Rows (the same 497 Lorenz(x) training pairs, initial parameters, P0, Q and R on every side):

* SRUKF (Julier, kappa = 1) vs dynamax's UKF (alpha = 1, beta = 0, kappa = 1: the same weights),
  1 run and ``--runs`` runs (the library's ``runs=R`` optimiser; ``jax.vmap`` over the runs);
* EKF vs dynamax's EKF, 1 run and ``--runs`` runs;
* filterpy's UKF (Julier points, kappa = 1) with a NumPy ANFIS, 1 run (same process).

Every library row is timed eager and compiled (``fit(..., compile=True)``: the pass as one
``torch.compile`` call of the engine's step under a traced scan; compile time reported apart,
from the first, compiling pass of the run; ``--no-compile`` leaves it out).

dynamax runs in a virtual environment made on first use under ``--cache``
(``python -m venv`` + ``pip install jax jaxlib dynamax``; never a dependency of the library
or its tests), in a worker process (``_dynamax_worker.py``) that gets the data as an ``.npz``
file and is asked for one pass at a time, so that the passes interleave (library, dynamax,
library, dynamax, ...) and both sides see the same machine load. dynamax's functions are
jitted and compiled before the first timed pass (compile time reported separately); its time
is the compiled call with the result blocked on. The library's time is the optimiser steps of
the pass (``History.time`` of :func:`prognos_torch.optim.fit`). Both sides run one thread
(``torch.set_num_threads(1)``; XLA's CPU client with one intra-op thread). The test MAE of
every run must agree to 5 decimals between the library and each peer.

On a CUDA machine, ``--device cuda`` runs the library's rows on the GPU and dynamax's on JAX's
GPU backend (``JAX_PLATFORMS=cuda``, no memory preallocation); ``--runs`` takes several counts
(e.g. ``50 500 2000 10000``); ``--python`` names a Python that already has jax and dynamax
(no virtual environment is made). The library's pass time then includes its queued kernels
(``fit`` synchronises the device around each epoch) and dynamax's is blocked on.

    python benchmarks/bench_peers.py [--repeats 3] [--runs 50 ...] [--cache DIR] [--no-dynamax]
        [--no-filterpy] [--no-compile] [--filters srukf ekf] [--device cpu|cuda] [--python PY]
        [--no-single]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import venv
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_optim import P0, Q, R, lorenz_data, make  # noqa: E402

from prognos_torch.optim import fit  # noqa: E402

MAE_DECIMALS = 5


# --------------------------------------------------------------------------- dynamax side
def dynamax_python(cache: Path) -> Path:
    """Python of the benchmark's JAX environment, created on first use."""
    env = cache / "jaxenv"
    py = env / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    ok = env / ".installed"
    if not ok.exists():
        print(f"creating {env} (jax, jaxlib, dynamax from the package index) ...", flush=True)
        venv.create(env, with_pip=True, clear=True)  # (a half-made one from a failed try)
        subprocess.run(
            [str(py), "-m", "pip", "install", "-q", "jax", "jaxlib", "dynamax"], check=True
        )
        ok.write_text("ok\n")
    return py


class DynamaxWorker:
    """The worker process: one JSON request per pass, one JSON answer."""

    def __init__(self, py: Path, npz: Path, platform: str = "cpu"):
        env = dict(os.environ)
        env.update(
            OMP_NUM_THREADS="1",
            XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
            JAX_PLATFORMS=platform,
            # on a GPU shared with the library's process: allocate as needed, not 75 % up front
            XLA_PYTHON_CLIENT_PREALLOCATE="false",
        )
        self.proc = subprocess.Popen(
            [str(py), str(HERE / "_dynamax_worker.py"), str(npz)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )

    def run(self, filt: str, runs: int) -> dict:
        self.proc.stdin.write(json.dumps({"filter": filt, "runs": runs}) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the dynamax worker stopped (see its error output above)")
        return json.loads(line)

    def close(self):
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


# --------------------------------------------------------------------------- filterpy side
def numpy_anfis(theta, u):
    """Paper 003 Eq. 1-5 in NumPy, theta in the order of Eq. 44 (3 inputs, 2 MFs)."""
    alpha = theta[:32].reshape(4, 8)  # (n_in + 1, R), rule index fastest
    b = theta[32:38].reshape(3, 2)
    beta = theta[38:44].reshape(3, 2)
    mu = 1.0 / (1.0 + np.exp(-b * (u[:, None] - beta)))  # Eq. 2
    w = (mu[0][:, None, None] * mu[1][None, :, None] * mu[2][None, None, :]).reshape(8)
    w = w / w.sum()  # Eq. 3-4
    return np.array([w @ (alpha[:3].T @ u + alpha[3])])  # Eq. 5


def filterpy_pass(data, theta0, P0m, Qm, Rm):
    from filterpy.kalman import JulierSigmaPoints, UnscentedKalmanFilter

    Xtr, Ytr, Xte, Yte = data
    n = theta0.shape[-1]
    f = UnscentedKalmanFilter(
        dim_x=n,
        dim_z=1,
        dt=1.0,
        fx=lambda x, dt: x,
        hx=numpy_anfis,
        points=JulierSigmaPoints(n, kappa=1.0),
    )
    f.x, f.P, f.Q, f.R = theta0.copy(), P0m.copy(), Qm.copy(), Rm.copy()
    t0 = time.perf_counter()
    for k in range(Xtr.shape[0]):
        f.predict()
        f.update(Ytr[k], u=Xtr[k])
    dt = time.perf_counter() - t0
    pred = np.array([numpy_anfis(f.x, u)[0] for u in Xte])
    return dt, np.abs(pred - Yte.reshape(-1)).mean()


# --------------------------------------------------------------------------- library side
def library_pass(filt, runs, data, compile=False):
    """Time of one pass (compile time apart), test MAE per run, compile time."""
    Xtr, Ytr, Xte, Yte = data
    model, opt = make(filt, runs, Xtr, Xtr.device)
    hist = fit(model, opt, (Xtr, Ytr), epochs=1, val=(Xte, Yte), progress=False, compile=compile)
    return hist.time[0], np.atleast_1d(hist.val["mae"][-1].cpu().numpy()), hist.compile_time[0]


def prior_floor_pass(runs, data):
    """Time of the square-root prior ALONE over one pass, compiled: ``T`` steps of
    ``chol(S S^T + Q)`` (the product, Q's diagonal, the LAPACK Cholesky), the engine's
    Cholesky prior of the EKF optimiser's random walk, under the same one-loop ``scan``;
    nothing else of the step. The floor of the square-root form against a full-covariance
    peer (no learner, no update). Returns (time, compile time)."""
    from prognos_torch.core.model import diagonal_noise
    from prognos_torch.filters import scan
    from prognos_torch.filters.gaussian import _chol_prior, deferred_fallbacks

    Xtr, Ytr, _, _ = data
    _, opt = make("ekf", runs, Xtr, Xtr.device)
    s = opt.state[next(iter(opt.state))]
    chol_Q = opt._cfg[0].chol_Q
    diag_Q = diagonal_noise(chol_Q)
    key = ("floor", runs)
    step = _FLOOR.get(key)
    if step is None:

        def step(carry, y, u, k):
            (S,) = carry
            return (_chol_prior(S, chol_Q, diag_Q),), None

        _FLOOR[key] = step
    ys = Ytr.reshape(Ytr.shape[0], -1).to(torch.float64)
    with torch.inference_mode(), deferred_fallbacks():
        t0 = time.perf_counter()
        scan(step, (s["chol"],), ys, ys, record=_floor_record, compile=True)
        dt = time.perf_counter() - t0
    from prognos_torch.filters import sequence

    c = sequence.last_compile_seconds
    return dt - c, c


_FLOOR: dict = {}


def _floor_record(state, info):
    return {"tr": state[0].diagonal(dim1=-2, dim2=-1).sum(-1)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="interleaved passes per row (best)")
    ap.add_argument(
        "--runs", type=int, nargs="+", default=[50], help="Monte Carlo runs of the batched rows"
    )
    ap.add_argument("--device", default="cpu", help="the library's device (cpu or cuda)")
    ap.add_argument("--python", help="a Python with jax and dynamax (else a venv under --cache)")
    ap.add_argument("--no-single", action="store_true", help="leave out the 1-run rows")
    ap.add_argument("--cache", default=os.path.expanduser("~/.cache/prognos_torch_bench"))
    ap.add_argument("--no-dynamax", action="store_true", help="library and filterpy only")
    ap.add_argument("--no-filterpy", action="store_true")
    ap.add_argument(
        "--no-compile", action="store_true", help="eager library rows only (no fit(compile=True))"
    )
    ap.add_argument(
        "--floor",
        action="store_true",
        help="also time the square-root prior alone (compiled) beside dynamax's EKF passes",
    )
    ap.add_argument(
        "--filters",
        nargs="+",
        choices=("srukf", "ekf"),
        default=["srukf", "ekf"],
        help="the library filters of the dynamax rows (default both)",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    device = torch.device(args.device)
    data = tuple(a.to(device) for a in lorenz_data())
    Xtr, Ytr, Xte, Yte = (a.cpu() for a in data)
    model, opt = make("srukf", max(args.runs), Xtr)
    theta0 = opt.theta.numpy()  # (runs, 44): the runs' initial parameters
    S0, SQ = opt._cfg[0].chol_P0.numpy(), opt._cfg[0].chol_Q.numpy()
    P0m, Qm = S0 @ S0.T, SQ @ SQ.T
    Rm = np.array([[R]])
    print(
        f"ANFIS (44 parameters), one pass over {Xtr.shape[0]} Lorenz pairs; P0={P0}, Q={Q}, "
        f"R={R}; torch {torch.__version__}, 1 thread, device {device}"
        + (f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else "")
        + "; load average "
        + " ".join(f"{x:.2f}" for x in os.getloadavg())
    )

    worker = None
    if not args.no_dynamax:
        cache = Path(args.cache)
        cache.mkdir(parents=True, exist_ok=True)
        py = Path(args.python) if args.python else dynamax_python(cache)
        npz = cache / "problem.npz"
        np.savez(
            npz,
            Xtr=Xtr.numpy(),
            Ytr=Ytr.numpy().reshape(-1),
            Xte=Xte.numpy(),
            Yte=Yte.numpy().reshape(-1),
            theta0=theta0,
            P0=P0m,
            Q=Qm,
            R=Rm,
        )
        worker = DynamaxWorker(py, npz, "cuda" if device.type == "cuda" else "cpu")

    rows = (
        []
        if args.no_single
        else [
            ("SRUKF vs dynamax UKF, 1 run", "srukf", "ukf", None),
            ("EKF vs dynamax EKF, 1 run", "ekf", "ekf", None),
        ]
    )
    for runs in args.runs:
        rows += [
            (f"SRUKF vs dynamax UKF, {runs} runs", "srukf", "ukf", runs),
            (f"EKF vs dynamax EKF, {runs} runs", "ekf", "ekf", runs),
        ]
    rows = [row for row in rows if row[1] in args.filters]
    modes = [False] if args.no_compile else [False, True]
    print(
        f"\n{'row':34s} {'library':>8s} {'lib [s]':>8s} {'compile [s]':>11s} "
        f"{'dynamax [s]':>11s} {'dyn/lib':>8s} {'compile [s]':>11s} {'max |dMAE|':>10s} "
        f"{'test MAE (lib)':>15s}"
    )
    for label, lib_name, dyn_name, runs in rows:
        lib_t = {m: [] for m in modes}
        lib_c = dict.fromkeys(modes, 0.0)
        lib_mae = dict.fromkeys(modes)
        dyn_t, comp, dyn_mae = [], None, None
        floor = args.floor and lib_name == "ekf"
        floor_t, floor_c = [], 0.0
        for _ in range(args.repeats):  # interleaved: eager, compiled, dynamax, eager, ...
            for m in modes:
                t, lib_mae[m], c = library_pass(lib_name, runs, data, compile=m)
                lib_t[m].append(t)
                lib_c[m] = max(lib_c[m], c)
            if floor:
                t, c = prior_floor_pass(runs, data)
                floor_t.append(t)
                floor_c = max(floor_c, c)
            if worker is not None:
                ans = worker.run(dyn_name, runs or 1)
                dyn_t.append(ans["time"])
                comp = ans["compile"] if ans["compile"] is not None else comp
                dyn_mae = np.asarray(ans["mae"])
        for m in modes:
            lt = min(lib_t[m])
            mae_s = f"{lib_mae[m].mean():.6f}"
            kind = "compiled" if m else "eager"
            head = f"{label:34s} {kind:>8s} {lt:8.3f} {lib_c[m]:11.1f}"
            if worker is None:
                print(f"{head}{'':>44s} {mae_s:>15s}")
                continue
            dt = min(dyn_t)
            dmae = float(np.abs(dyn_mae - lib_mae[m]).max())
            agree = bool(
                np.all(np.round(dyn_mae, MAE_DECIMALS) == np.round(lib_mae[m], MAE_DECIMALS))
            )
            flag = "" if agree else "  (MAE differs at 5 decimals)"
            print(f"{head} {dt:11.4f} {dt / lt:8.2f} {comp:11.2f} {dmae:10.1e} {mae_s:>15s}{flag}")
        if floor:
            ft = min(floor_t)
            tail = "" if worker is None else f" {min(dyn_t):11.4f} {min(dyn_t) / ft:8.2f}"
            print(
                f"{'  square-root prior alone':34s} {'compiled':>8s} {ft:8.3f} {floor_c:11.1f}{tail}"
            )
    if worker is not None:
        worker.close()

    if not args.no_filterpy:
        fp_t = []
        lib_t = {m: [] for m in modes}
        lib_mae = dict.fromkeys(modes)
        for _ in range(args.repeats):
            t, mae_fp = filterpy_pass(tuple(a.cpu().numpy() for a in data), theta0[0], P0m, Qm, Rm)
            fp_t.append(t)
            for m in modes:
                t, lib_mae[m], _ = library_pass("srukf", None, data, compile=m)
                lib_t[m].append(t)
        ft = min(fp_t)
        print(
            f"\nfilterpy UKF (Julier, kappa=1) + NumPy ANFIS, 1 run: {ft:.3f} s, test MAE {mae_fp:.6f}"
        )
        for m in modes:
            lt = min(lib_t[m])
            same = round(mae_fp, MAE_DECIMALS) == round(float(lib_mae[m][0]), MAE_DECIMALS)
            print(
                f"  library SRUKF {'compiled' if m else 'eager'}: {lt:.3f} s in the same run: "
                f"library {ft / lt:.1f}x faster; test MAE {float(lib_mae[m][0]):.6f}"
                + ("" if same else " (differs at 5 decimals)")
            )
    print("load average at the end: " + " ".join(f"{x:.2f}" for x in os.getloadavg()))


if __name__ == "__main__":
    main()
