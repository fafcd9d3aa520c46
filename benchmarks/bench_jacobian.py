"""The EKF's default Jacobians (per-sample models without ``jac_f``/``jac_h``) beside the former
nested ``vmap(jacfwd)`` and beside analytic Jacobians.

    python benchmarks/bench_jacobian.py [--steps 500] [--batch 1 64] [--repeat 5]

A model written per sample, as a user writes it first: the Lorenz-63 system, one Euler step of
0.01 per filter step (n = 3), measured through ``h(x) = (x_1, x_1 x_2 / 10)`` (m = 2). The
engine takes its Jacobians by forward mode (``StateSpaceModel.transition_jacobian``):

* **engine**: the library's default, one ``jvp`` per (point, basis vector) pair under one
  ``vmap``;
* **nested**: ``vmap(jacfwd(f))``, the default before (one ``vmap`` over the basis inside one
  over the points), timed on the Jacobian call alone and through a whole EKF run (a model
  whose ``jac_f``/``jac_h`` are that formula);
* **batched, autodiff**: the model written for any leading dimensions (``batched=True``)
  without Jacobians: the engine's ``jvp`` runs on all (point, basis vector) rows at once, no
  ``vmap``;
* **analytic**: the same model with its Jacobians written out (``batched=True``), the fastest
  a user can make it.

Rows: median wall time of ``--repeat`` passes (A B C D A B C D), milliseconds; the three EKF runs
agree to the printed difference.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from torch.func import jacfwd, vmap

from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import ekf, run

DT, SIGMA, RHO, BETA = 0.01, 10.0, 28.0, 8.0 / 3.0


def f(x, u, k):
    dx = torch.stack([SIGMA * (x[1] - x[0]), x[0] * (RHO - x[2]) - x[1], x[0] * x[1] - BETA * x[2]])
    return x + DT * dx


def h(x, u, k):
    return torch.stack([x[0], x[0] * x[1] / 10.0])


def f_b(x, u, k):  # batched twins for the analytic model
    a, b, c = x.unbind(-1)
    dx = torch.stack([SIGMA * (b - a), a * (RHO - c) - b, a * b - BETA * c], -1)
    return x + DT * dx


def h_b(x, u, k):
    return torch.stack([x[..., 0], x[..., 0] * x[..., 1] / 10.0], -1)


def jf_b(x, u, k):
    a, b, c = x.unbind(-1)
    z, o = torch.zeros_like(a), torch.ones_like(a)
    J = torch.stack([torch.stack([-SIGMA * o, SIGMA * o, z], -1),
                     torch.stack([RHO - c, -o, -a], -1),
                     torch.stack([b, a, -BETA * o], -1)], -2)  # fmt: skip
    return torch.eye(3, dtype=x.dtype) + DT * J


def jh_b(x, u, k):
    a, b, _ = x.unbind(-1)
    z, o = torch.zeros_like(a), torch.ones_like(a)
    return torch.stack([torch.stack([o, z, z], -1), torch.stack([b / 10, a / 10, z], -1)], -2)


def nested(fn):  # the former default, as an explicit Jacobian of the batch
    def jac(x, u, k):
        xf = x.reshape(-1, x.shape[-1])
        J = vmap(jacfwd(lambda xi: fn(xi, None, k)))(xf)
        return J.reshape(*x.shape[:-1], *J.shape[-2:])

    return jac


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 64])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    noise = dict(chol_Q=0.05 * torch.eye(3, dtype=torch.float64),
                 chol_R=0.5 * torch.eye(2, dtype=torch.float64))  # fmt: skip
    models = {
        "engine (default)": StateSpaceModel(f=f, h=h, state_dim=3, obs_dim=2, **noise),
        "nested vmap(jacfwd)": StateSpaceModel(
            f=f_b,
            h=h_b,
            state_dim=3,
            obs_dim=2,
            batched=True,
            jac_f=nested(f),
            jac_h=nested(h),
            **noise,
        ),  # fmt: skip
        "batched, autodiff": StateSpaceModel(
            f=f_b, h=h_b, state_dim=3, obs_dim=2, batched=True, **noise
        ),  # fmt: skip
        "analytic": StateSpaceModel(
            f=f_b, h=h_b, state_dim=3, obs_dim=2, batched=True, jac_f=jf_b, jac_h=jh_b, **noise
        ),  # fmt: skip
    }
    print(f"Lorenz-63 per sample (n = 3, m = 2), EKF, {args.steps} steps, median of "
          f"{args.repeat}, 1 thread")  # fmt: skip
    print(
        "| batch | Jacobian | one f Jacobian (ms) | EKF run (ms) | run / engine | max diff of means |"
    )
    print("|---|---|---|---|---|---|")
    g = torch.Generator().manual_seed(0)
    for B in args.batch:
        x0 = torch.tensor([1.0, 1.0, 20.0], dtype=torch.float64) + torch.randn(
            B, 3, generator=g, dtype=torch.float64)  # fmt: skip
        ys = 0.5 * torch.randn(args.steps, B, 2, generator=g, dtype=torch.float64)
        ys[..., 0] += 1.0
        b0 = GaussianBelief(x0, torch.eye(3, dtype=torch.float64).expand(B, 3, 3).clone())
        times = {k: ([], []) for k in models}
        means = {}
        for _ in range(args.repeat):
            for name, m in models.items():
                t0 = time.perf_counter()
                for _ in range(20):
                    m.transition_jacobian(x0, None, 0)
                t1 = time.perf_counter()
                means[name] = run(ekf(), m, b0, ys).means
                t2 = time.perf_counter()
                times[name][0].append((t1 - t0) / 20)
                times[name][1].append(t2 - t1)
        base = statistics.median(times["engine (default)"][1])
        for name in models:
            tj, tr = (statistics.median(v) for v in times[name])
            d = float((means[name] - means["engine (default)"]).abs().max())
            print(f"| {B} | {name} | {1e3 * tj:.3f} | {1e3 * tr:.1f} | {tr / base:.2f} | {d:.1e} |",
                  flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
