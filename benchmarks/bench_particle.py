"""Benchmark of prognos_torch.filters.particle: SIR and the strong-tracking particle filter (STPF).

Usage::

    python benchmarks/bench_particle.py [--steps 500] [--large 100000] [--large-steps 20]
                                        [--repeat 3] [--threads 1] [--profile] [--no-memory]

Prints tables of

* STPF with 1,000 particles on a 1-D state over 500 steps (target: <= 1 s), for three ways of
  writing the same model: per-sample ``f``/``h`` (batched by ``vmap``, Jacobians by ``jacfwd``),
  ``batched=True`` with analytic Jacobians, and the random walk ``f=None``;
* particle-steps per second of SIR and STPF at 10^3 and 10^5 particles;
* peak resident memory of a run at 10^5 particles (``resource.getrusage`` in a fresh child
  process, minus the child's footprint before the run);
* with ``--profile``: where the STPF time goes (engine step, Jacobians, QR, particle side).

The model is paper 002's setting reduced to one health indicator: a slowly drifting state
``x_k = x_{k-1} + 0.01 sin(x_{k-1}) + w_k`` observed directly, ``y_k = x_k + v_k``, with a jump
of the true state half-way (a "saltatory" state).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import platform
import pstats
import resource
import statistics
import subprocess
import sys
import time
import warnings

import torch

from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import sir, stpf

SQ, SR = 0.05, 0.3


def make_model(kind: str) -> StateSpaceModel:
    """The 1-D model written three ways (same dynamics except ``random-walk``)."""
    cq, cr = torch.tensor([[SQ]], dtype=torch.float64), torch.tensor([[SR]], dtype=torch.float64)
    f = lambda x, u, k: x + 0.01 * torch.sin(x)  # noqa: E731
    h = lambda x, u, k: x  # noqa: E731
    if kind == "per-sample":
        return StateSpaceModel(f=f, h=h, state_dim=1, obs_dim=1, chol_Q=cq, chol_R=cr)
    if kind == "batched+jac":
        return StateSpaceModel(
            f=f,
            h=h,
            state_dim=1,
            obs_dim=1,
            chol_Q=cq,
            chol_R=cr,
            batched=True,
            jac_f=lambda x, u, k: (1.0 + 0.01 * torch.cos(x)).unsqueeze(-1),
            jac_h=lambda x, u, k: torch.ones_like(x).unsqueeze(-1),
        )
    if kind == "random-walk":
        return StateSpaceModel(f=None, h=h, state_dim=1, obs_dim=1, chol_Q=cq, chol_R=cr)
    raise ValueError(f"unknown model kind {kind!r}")


def make_data(T: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    w = SQ * torch.randn(T, 1, generator=g, dtype=torch.float64)
    w[T // 2] += 3.0  # saltatory state
    x = torch.cumsum(w, 0)
    return x + SR * torch.randn(T, 1, generator=g, dtype=torch.float64)


def make_filter(name: str, N: int):
    return {"SIR": sir, "STPF": stpf}[name](N)


def one_run(name: str, kind: str, N: int, T: int, seed: int = 1):
    model, ys = make_model(kind), make_data(T)
    b0 = GaussianBelief(torch.zeros(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64))
    pf = make_filter(name, N)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return pf.run(model, b0, ys, generator=torch.Generator().manual_seed(seed))


def timed(fn, repeat: int) -> tuple[float, float]:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), min(times)


def _status_kib(field: str) -> int | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def child_memory(name: str, kind: str, N: int, T: int) -> None:
    """Run once in this (fresh) process and print the peak resident memory of the run as JSON.

    On Linux the peak (``VmHWM``) is reset by writing ``5`` to ``/proc/self/clear_refs`` just
    before the run, so the increase over the resident size at that moment (``VmRSS``) is the
    run's own peak; elsewhere ``ru_maxrss`` is used (an upper bound on the process peak)."""
    one_run(name, kind, 10, 2)  # warm imports, vmap and the allocator
    base = _status_kib("VmRSS")
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        reset = True
    except OSError:
        reset = False
    one_run(name, kind, N, T)
    peak = _status_kib("VmHWM") if reset else None
    if peak is None or base is None:
        base, peak = 0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"base_kib": base, "peak_kib": peak}))


def memory_row(name: str, kind: str, N: int, T: int, threads: int) -> tuple[float, float]:
    cmd = [
        sys.executable,
        __file__,
        "--child",
        name,
        kind,
        str(N),
        str(T),
        "--threads",
        str(threads),
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    d = json.loads(out.strip().splitlines()[-1])
    return (d["peak_kib"] - d["base_kib"]) / 1024.0, d["peak_kib"] / 1024.0


def profile_stpf(kind: str, N: int, T: int) -> list[tuple[str, float]]:
    prof = cProfile.Profile()
    prof.enable()
    one_run("STPF", kind, N, T)
    prof.disable()
    st = pstats.Stats(prof)

    def cum(file_part: str, func: str) -> float:
        return sum(
            v[3] for (f, _, fn), v in st.stats.items() if fn == func and f.endswith(file_part)
        )

    total = cum("particle.py", "run")
    engine = cum("gaussian.py", "step")
    rows = [
        ("ParticleFilter.run (total)", total),
        ("  GaussianFilter.step (engine, per-particle SFEKF)", engine),
        (
            "    model Jacobians (vmap(jacfwd) or jac_f/jac_h)",
            cum("model.py", "transition_jacobian") + cum("model.py", "observation_jacobian"),
        ),
        (
            "    f, h evaluations inside the engine",
            cum("gaussian.py", "_propagate") - cum("model.py", "transition_jacobian"),
        ),
        ("    tria (QR)", cum("linalg.py", "tria")),
        ("    fading factor", cum("strong_tracking.py", "fading_factor")),
        ("  particle side (sampling, weights, estimates, resampling)", total - engine),
        ("    h at the new particles (likelihood)", cum("particle.py", "_log_lik")),
        (
            "    resampling (systematic + gather)",
            cum("resampling.py", "systematic") + cum("particle.py", "gather_particles"),
        ),
    ]
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=500, help="steps of the 10^3-particle runs")
    parser.add_argument("--small", type=int, default=1000, help="small particle count")
    parser.add_argument("--large", type=int, default=100_000, help="large particle count")
    parser.add_argument("--large-steps", type=int, default=20, help="steps of the large runs")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per row (median)")
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--profile", action="store_true", help="profile the STPF run")
    parser.add_argument("--no-memory", action="store_true", help="skip the memory rows")
    parser.add_argument(
        "--child", nargs=4, metavar=("FILTER", "MODEL", "N", "T"), help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.child:
        name, kind, N, T = args.child
        child_memory(name, kind, int(N), int(T))
        return

    print(
        f"torch {torch.__version__}, {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} CPUs, torch threads {torch.get_num_threads()}, float64"
    )
    print(f"\nSTPF, {args.small} particles, 1-D state, {args.steps} steps (target <= 1 s)")
    print(f"{'model form':<14}{'median s':>10}{'best s':>9}{'ms/step':>9}{'<= 1 s':>8}")
    for kind in ("per-sample", "batched+jac", "random-walk"):
        med, best = timed(
            lambda kind=kind: one_run("STPF", kind, args.small, args.steps), args.repeat
        )
        ok = "yes" if best <= 1.0 else "no"
        print(f"{kind:<14}{med:>10.3f}{best:>9.3f}{1e3 * med / args.steps:>9.2f}{ok:>8}")

    print("\nthroughput (particle-steps per second, median)")
    print(f"{'filter':<6}{'model form':<14}{'N':>9}{'steps':>7}{'seconds':>10}{'p-steps/s':>13}")
    for name in ("SIR", "STPF"):
        for kind in ("per-sample", "batched+jac"):
            for N, T in ((args.small, args.steps), (args.large, args.large_steps)):
                med, _ = timed(lambda n=name, k=kind, N=N, T=T: one_run(n, k, N, T), args.repeat)
                print(f"{name:<6}{kind:<14}{N:>9}{T:>7}{med:>10.3f}{N * T / med:>13.3g}")

    if not args.no_memory:
        print(f"\npeak memory at {args.large} particles ({args.large_steps} steps, fresh process)")
        print(f"{'filter':<6}{'model form':<14}{'run MiB':>9}{'process MiB':>13}")
        for name in ("SIR", "STPF"):
            kind = "per-sample"
            run_mib, proc_mib = memory_row(name, kind, args.large, args.large_steps, args.threads)
            print(f"{name:<6}{kind:<14}{run_mib:>9.1f}{proc_mib:>13.1f}")

    if args.profile:
        for kind in ("per-sample", "batched+jac"):
            rows = profile_stpf(kind, args.small, args.steps)
            total = rows[0][1]
            print(f"\nprofile: STPF, {kind}, {args.small} particles, {args.steps} steps (cProfile)")
            for label, sec in rows:
                print(f"{label:<62}{sec:>8.3f} s{100 * sec / total:>7.1f} %")


if __name__ == "__main__":
    main()
