"""Time per step of the Gaussian filter engine on the optimiser-face problem (random-walk state,
learner output as the measurement), against filterpy's UKF on the same n = 44 problem.

    python benchmarks/bench_filters.py [--steps 200] [--threads 1]

Problems: n = 4 (linear regression on 3 inputs + bias), n = 44 (paper 003's ANFIS, 3 inputs,
2 sigmoid MFs), n = 200 (ELM output weights, 200 hidden nodes). Batch 1 and 256 independent runs.
The measurement function and its Jacobian (EKF) come from ``ParameterBridge``, as in the
optimiser face (the learners' closed-form Jacobians; ``torch.func`` for ``nn.Linear``).

Each row is the best of three timed passes after a warm-up (one pass for n = 200, batch 256). Each configuration is timed twice: in PyTorch's default grad mode, and under
``torch.inference_mode()``, the way to run a filter when no gradient through it is needed
(no version counters or view tracking; the Kalman optimisers do this themselves).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import ekf, sckf, srukf
from prognos_torch.learners import ANFIS, ELM
from prognos_torch.optim import ParameterBridge


def learner_problem(n: int):
    if n == 4:
        module = torch.nn.Linear(3, 1, dtype=torch.float64)
    elif n == 44:
        module = ANFIS(3, 2)
    elif n == 200:
        module = ELM(3, 200)
    else:
        raise ValueError(n)
    bridge = ParameterBridge(module)  # the optimiser face's path: forward_with or vmap
    assert bridge.numel == n

    def h(theta, u, k):  # theta (..., n), u (3,) -> (..., 1)
        return bridge.measurement(theta, u.unsqueeze(0))

    def jac_h(theta, u, k):  # (..., 1, n)
        return bridge.jacobian(theta, u.unsqueeze(0))

    return module, h, jac_h, bridge.flatten().to(torch.float64)


def time_engine(filt, n, batch, steps, seed=0, inference=False, repeats=3):
    with torch.inference_mode() if inference else torch.enable_grad():
        return _time_engine(filt, n, batch, steps, seed, repeats)


def _time_engine(filt, n, batch, steps, seed, repeats):
    module, h, jac_h, theta0 = learner_problem(n)
    g = torch.Generator().manual_seed(seed)
    us = torch.rand(steps, 3, generator=g, dtype=torch.float64)
    ys = torch.rand(steps, *((batch,) if batch > 1 else ()), 1, generator=g, dtype=torch.float64)
    chol_Q = 1e-3 * torch.eye(n, dtype=torch.float64)
    chol_R = 0.1 * torch.eye(1, dtype=torch.float64)
    model_for = lambda u: StateSpaceModel(  # noqa: E731  (the input u_k changes every step)
        None,
        lambda th, _u, k: h(th, u, k),
        n,
        1,
        chol_Q=chol_Q,
        chol_R=chol_R,
        batched=True,
        jac_h=lambda th, _u, k: jac_h(th, u, k),
    )
    bs = (batch,) if batch > 1 else ()
    b0 = GaussianBelief(
        theta0.expand(*bs, n).clone(),
        0.1 * torch.eye(n, dtype=torch.float64).expand(*bs, n, n).clone(),
    )
    best = float("inf")
    for _ in range(repeats):  # best of `repeats` passes from the same start, after a warm-up
        state = filt.init(model_for(us[0]), b0)
        for k in range(3):
            state, _ = filt.step(model_for(us[k]), state, ys[k], k=k + 1)
        state = filt.init(model_for(us[0]), b0)
        t0 = time.perf_counter()
        for k in range(steps):
            state, _ = filt.step(model_for(us[k]), state, ys[k], k=k + 1)
        best = min(best, (time.perf_counter() - t0) / steps)
    return best


def numpy_anfis(theta, u):
    """Paper 003 Eq. 1-5 in NumPy, theta in the order of Eq. 44 (3 inputs, 2 MFs)."""
    alpha = theta[:32].reshape(4, 8)  # (n_in + 1, R), rule index fastest
    b = theta[32:38].reshape(3, 2)
    beta = theta[38:44].reshape(3, 2)
    mu = 1.0 / (1.0 + np.exp(-b * (u[:, None] - beta)))
    w = np.ones(8)
    for i, (l1, l2, l3) in enumerate(np.ndindex(2, 2, 2)):
        w[i] = mu[0, l1] * mu[1, l2] * mu[2, l3]
    w = w / w.sum()
    return np.array([w @ (alpha[:3].T @ u + alpha[3])])


def time_filterpy(steps, torch_module: bool):
    from filterpy.kalman import JulierSigmaPoints, UnscentedKalmanFilter

    module, h, _, theta0 = learner_problem(44)
    n = 44
    rng = np.random.default_rng(0)
    us = rng.random((steps, 3))
    if torch_module:

        def hx(theta, u):
            with torch.no_grad():
                return h(torch.as_tensor(theta), torch.as_tensor(u), 0).numpy()
    else:
        hx = numpy_anfis
    ys = rng.random(steps)
    best = float("inf")
    for _ in range(3):  # best of three passes, as for our filters
        f = UnscentedKalmanFilter(
            dim_x=n,
            dim_z=1,
            dt=1.0,
            fx=lambda x, dt: x,
            hx=hx,
            points=JulierSigmaPoints(n, kappa=1.0),
        )
        f.x = theta0.numpy().copy()
        f.P = 0.01 * np.eye(n)
        f.Q = 1e-6 * np.eye(n)
        f.R = np.array([[0.01]])
        t0 = time.perf_counter()
        for k in range(steps):
            f.predict()
            f.update(np.array([ys[k]]), u=us[k])
        best = min(best, (time.perf_counter() - t0) / steps)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 44, 200])
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(
        f"# torch {torch.__version__}, {platform.processor() or platform.machine()}, "
        f"threads={args.threads}, {time.strftime('%Y-%m-%d')}"
    )
    print(
        "| filter | n | batch | ms / step (grad mode) | ms / step (inference_mode) | "
        "ms / step / run (inference_mode) |"
    )
    print("|---|---|---|---|---|---|")
    ours = {}
    for n in args.sizes:
        for name, filt in (("SRUKF", srukf()), ("SCKF", sckf()), ("EKF", ekf())):
            for batch in (1, 256):
                steps = args.steps if batch == 1 else max(5, args.steps // (10 if n < 200 else 40))
                rep = 1 if n >= 200 and batch > 1 else 3
                s = time_engine(filt, n, batch, steps, repeats=rep)
                si = time_engine(filt, n, batch, steps, inference=True, repeats=rep)
                ours[name, n, batch] = (s, si)
                print(
                    f"| {name} | {n} | {batch} | {1e3 * s:.3f} | {1e3 * si:.3f} | "
                    f"{1e3 * si / batch:.4f} |",
                    flush=True,
                )
    if 44 in args.sizes:
        ref = {}
        for tm in (False, True):
            s = time_filterpy(max(20, args.steps // 4), tm)
            ref[tm] = s
            label = "filterpy UKF, torch ANFIS" if tm else "filterpy UKF, NumPy ANFIS"
            print(f"| {label} | 44 | 1 | {1e3 * s:.3f} | | |", flush=True)
        s, si = ours["SRUKF", 44, 1]
        print(
            f"\nSRUKF n = 44, batch 1 vs filterpy UKF with the NumPy ANFIS: {ref[False] / s:.1f}x "
            f"faster (grad mode), {ref[False] / si:.1f}x (inference_mode); vs filterpy driving "
            f"the torch module: {ref[True] / s:.1f}x / {ref[True] / si:.1f}x"
        )


if __name__ == "__main__":
    main()
