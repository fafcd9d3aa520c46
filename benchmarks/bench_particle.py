"""Benchmark of prognos_torch.filters.particle: SIR and the strong-tracking particle filter (STPF).

Usage::

    python benchmarks/bench_particle.py [--steps 500] [--large 100000] [--large-steps 20]
                                        [--repeat 3] [--threads 1] [--profile] [--no-memory]
                                        [--no-peers] [--peers-only] [--cpu-time]
    python benchmarks/bench_particle.py --device cuda [--device-counts 1000:500 ...]

Prints tables of

* STPF with 1,000 particles on a 1-D state over 500 steps (targets: <= 1 s with the
  per-sample model, <= 0.2 s with the batched one), for three ways of writing the same model:
  per-sample ``f``/``h`` (batched by ``vmap``, Jacobians by ``jacfwd``), ``batched=True`` with
  analytic Jacobians, and the random walk ``f=None``, each by default and with
  ``run(..., inference=True)`` (rows marked ``inf``), and the batched one with
  ``run(..., compile=True)`` (``comp``, its compile time apart);
* the library's SIR, eager and compiled (``run(..., compile=True)``, its compile time apart),
  beside a vectorised NumPy SIR written here (same model, same initial
  belief, same systematic resampling at ``N_eff < N / 2``, the same per-step outputs: weighted
  mean and variance, ``N_eff``, log-likelihood increment) at 10^3, 10^4 and 10^5 particles,
  timed interleaved in this process (eager, compiled, NumPy, eager, ...), with the speed ratio
  ``NumPy time / library time`` (>= 1: the library is at least as fast; target >= 1). Both get
  their measurements and model built beforehand and create their generator inside the timed
  call (the library's ``ParticleFilter.run`` includes its input checks and the initial draw);
* the four resamplers (:mod:`prognos_torch.filters.resampling`, public functions with their
  input checks, from log-weights) beside NumPy equivalents (``cumsum`` + ``searchsorted``),
  interleaved, with ratios;
* particle-steps per second of SIR and STPF at 10^3 and 10^5 particles;
* peak resident memory of a run at 10^5 particles (``resource.getrusage`` in a fresh child
  process, minus the child's footprint before the run);
* with ``--profile``: where the STPF time goes (engine step, Jacobians, QR, particle side).

``--device cuda`` prints only the throughput of SIR and STPF (batched model) on that device at
the ``--device-counts`` (particles:steps), the device synchronised before the clock is read,
beside the same runs on the CPU where they take under a few seconds (``--device-cpu-max``),
timed by the wall clock (``--cpu-time`` does not apply).
``--peers-only`` runs the NumPy comparisons alone; ``--cpu-time`` times with the process's CPU
time (``time.process_time``) instead of the wall clock, which on a shared machine leaves out
the time the process waits for a core (not the slowdown other jobs cause while it runs).

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

import numpy as np
import torch

import prognos_torch
from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import resampling, sir, stpf

SQ, SR = 0.05, 0.3


def make_model(kind: str, device=None) -> StateSpaceModel:
    """The 1-D model written three ways (same dynamics except ``random-walk``)."""
    cq = torch.tensor([[SQ]], dtype=torch.float64, device=device)
    cr = torch.tensor([[SR]], dtype=torch.float64, device=device)
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


_MODELS: dict = {}


def one_run(
    name: str, kind: str, N: int, T: int, seed: int = 1, inference: bool = False,
    compile: bool = False,
):  # fmt: skip
    # (one model per form, so that a compiled run reuses its compiled code)
    model, ys = _MODELS.setdefault(kind, make_model(kind)), make_data(T)
    b0 = GaussianBelief(torch.zeros(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64))
    pf = make_filter(name, N)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gen = torch.Generator().manual_seed(seed)
        return pf.run(model, b0, ys, generator=gen, inference=inference, compile=compile)


# --------------------------------------------------------------------------- NumPy peers
def numpy_sir(ys: np.ndarray, N: int, seed: int = 1, threshold: float = 0.5) -> dict:
    """Vectorised NumPy bootstrap filter on the benchmark model (``ys``: ``(T,)``).

    The same algorithm as the library's SIR: particles from ``N(0, 1)``, propagation
    ``x + 0.01 sin x + SQ w``, Gaussian log-likelihood, normalised log-weights, weighted mean
    and variance, ``N_eff = 1 / sum w^2``, systematic resampling when ``N_eff < threshold N``.
    """
    rng = np.random.default_rng(seed)
    T = ys.shape[0]
    x = rng.standard_normal(N)
    lw = np.full(N, -np.log(N))
    out = {k: np.empty(T) for k in ("means", "vars", "ess", "log_likelihoods")}
    c = -0.5 * np.log(2.0 * np.pi) - np.log(SR)
    j = np.arange(N)
    for t in range(T):
        x = x + 0.01 * np.sin(x) + SQ * rng.standard_normal(N)
        e = (ys[t] - x) / SR
        lw = lw + (c - 0.5 * e * e)
        mx = lw.max()
        w = np.exp(lw - mx)
        s = w.sum()
        ll = mx + np.log(s)
        w /= s
        lw = lw - ll
        mu = w @ x
        d = x - mu
        n_eff = 1.0 / (w @ w)
        out["means"][t], out["vars"][t] = mu, w @ (d * d)
        out["ess"][t], out["log_likelihoods"][t] = n_eff, ll
        if n_eff < threshold * N:
            cdf = np.cumsum(w)
            cdf /= cdf[-1]
            u = (j + rng.random()) / N
            x = x[np.minimum(np.searchsorted(cdf, u, side="right"), N - 1)]
            lw = np.full(N, -np.log(N))
    return out


def numpy_resampler(name: str, log_w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """NumPy equivalents of the library's resamplers (1-D log-weights)."""
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    N = w.shape[0]
    cdf = np.cumsum(w)
    cdf /= cdf[-1]
    if name == "multinomial":
        u = rng.random(N)
    elif name == "stratified":
        u = (np.arange(N) + rng.random(N)) / N
    elif name == "systematic":
        u = (np.arange(N) + rng.random()) / N
    elif name == "residual":
        Nw = N * w
        det = np.floor(Nw).astype(np.int64)
        idx = np.repeat(np.arange(N), det)
        R = N - idx.shape[0]
        if R == 0:
            return idx
        res = Nw - det
        rc = np.cumsum(res)
        rc /= rc[-1]
        extra = np.minimum(np.searchsorted(rc, rng.random(R), side="right"), N - 1)
        return np.concatenate([idx, extra])
    else:
        raise ValueError(name)
    return np.minimum(np.searchsorted(cdf, u, side="right"), N - 1)


#: the clock of every timing (``--cpu-time``: ``time.process_time``)
CLOCK = time.perf_counter


def interleaved(fns: list, repeat: int) -> list[float]:
    """Median seconds of each function, run in turn ``repeat`` times (same machine load)."""
    times: list[list[float]] = [[] for _ in fns]
    for fn in fns:  # warm-up
        fn()
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            start = CLOCK()
            fn()
            times[i].append(CLOCK() - start)
    return [statistics.median(t) for t in times]


def sir_vs_numpy(counts: list[tuple[int, int]], repeat: int, compile: bool = True) -> None:
    print(
        "\nSIR: library (eager, and compiled: run(compile=True)) vs vectorised NumPy (same "
        "model, systematic at N_eff < N/2; median s; ratio = NumPy / library)"
    )
    print(
        f"{'N':>8}{'steps':>7}{'eager s':>9}{'compiled s':>12}{'NumPy s':>10}{'eager':>7}"
        f"{'compiled':>10}{'compile s':>11}{'comp p-steps/s':>16}{'|mean diff|':>13}"
    )
    model = make_model("batched+jac")
    b0 = GaussianBelief(torch.zeros(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64))
    for N, T in counts:
        ys = make_data(T)
        ys_np = ys[:, 0].numpy()
        pf = make_filter("SIR", N)

        def lib(pf=pf, ys=ys):
            return pf.run(model, b0, ys, generator=torch.Generator().manual_seed(1))

        def comp(pf=pf, ys=ys):
            return pf.run(model, b0, ys, generator=torch.Generator().manual_seed(1), compile=True)

        peer = lambda N=N, ys_np=ys_np: numpy_sir(ys_np, N)  # noqa: E731
        if compile:
            comp()  # compiles (time apart)
            t_compile = prognos_torch.filters.sequence.last_compile_seconds
        times = interleaved([lib, comp, peer] if compile else [lib, peer], repeat)
        t_lib, t_np = times[0], times[-1]
        # the filters use different random streams: their means agree to Monte Carlo error
        ours = (comp if compile else lib)().means[:, 0].numpy()
        diff = float(np.abs(ours - peer()["means"]).mean())
        cols = ("-",) * 4  # the compiled columns, empty with --no-compile
        if compile:
            t_comp = times[1]
            cols = (f"{t_comp:.4f}", f"{t_np / t_comp:.2f}", f"{t_compile:.1f}",
                    f"{N * T / t_comp:.3g}")  # fmt: skip
        print(
            f"{N:>8}{T:>7}{t_lib:>9.4f}{cols[0]:>12}{t_np:>10.4f}{t_np / t_lib:>7.2f}"
            f"{cols[1]:>10}{cols[2]:>11}{cols[3]:>16}{diff:>13.2e}"
        )


def resamplers_vs_numpy(sizes: list[int], repeat: int, calls: int = 20) -> None:
    print(f"\nresamplers: library vs NumPy (from log-weights; median ms per call of {calls})")
    print(f"{'scheme':<13}{'N':>8}{'library ms':>12}{'NumPy ms':>10}{'ratio':>8}")
    for N in sizes:
        g = torch.Generator().manual_seed(0)
        x = 3.0 * torch.randn(N, generator=g, dtype=torch.float64)
        lw_t = -0.5 * ((1.0 - x) / 0.3) ** 2  # a peaked likelihood, as after a jump
        lw_np = lw_t.numpy().copy()
        rng = np.random.default_rng(0)
        for name in ("systematic", "stratified", "multinomial", "residual"):
            fn = getattr(resampling, name)

            def lib(fn=fn, lw_t=lw_t, g=g):
                for _ in range(calls):
                    fn(lw_t, g)

            def peer(name=name, lw_np=lw_np, rng=rng):
                for _ in range(calls):
                    numpy_resampler(name, lw_np, rng)

            t_lib, t_np = interleaved([lib, peer], repeat)
            print(
                f"{name:<13}{N:>8}{1e3 * t_lib / calls:>12.4f}{1e3 * t_np / calls:>10.4f}"
                f"{t_np / t_lib:>8.2f}"
            )


def device_rows(device: torch.device, counts: list[tuple[int, int]], repeat: int, cpu_max: float):
    """Particle-steps per second of SIR and STPF (batched model) on ``device`` and the CPU."""
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else str(device)
    print(f"\nSIR and STPF, batched model, on {name} (median of {repeat}; CPU beside it)")
    print(
        f"{'filter':<6}{'N':>10}{'steps':>7}{'device s':>10}{'p-steps/s':>11}"
        f"{'CPU s':>9}{'CPU/device':>11}{'|mean diff|':>13}"
    )
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    skip_cpu: set[str] = set()
    for N, T in counts:
        ys_cpu = make_data(T)
        for name_f in ("SIR", "STPF"):
            out = {}
            for dev in (device, torch.device("cpu")):
                if dev.type == "cpu" and name_f in skip_cpu:
                    continue
                model, ys = make_model("batched+jac", dev), ys_cpu.to(dev)
                b0 = GaussianBelief(
                    torch.zeros(1, dtype=torch.float64, device=dev),
                    torch.eye(1, dtype=torch.float64, device=dev),
                )
                pf = make_filter(name_f, N)

                def go(pf=pf, model=model, b0=b0, ys=ys, dev=dev):
                    g = torch.Generator(device=dev).manual_seed(1)
                    tr = pf.run(model, b0, ys, generator=g, inference=True)
                    sync()
                    return tr

                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    go()  # warm-up (kernels, caches)
                    med, _ = timed(go, repeat)
                    out[dev.type] = (med, go().means[:, 0].cpu())
                if dev.type == "cpu" and med > cpu_max:
                    skip_cpu.add(name_f)  # larger counts only on the device
            t_dev, m_dev = out[device.type]
            row = f"{name_f:<6}{N:>10}{T:>7}{t_dev:>10.4f}{N * T / t_dev:>11.3g}"
            if "cpu" in out:
                t_cpu, m_cpu = out["cpu"]
                diff = float((m_dev - m_cpu).abs().mean())  # different streams: Monte Carlo error
                row += f"{t_cpu:>9.3f}{t_cpu / t_dev:>11.2f}{diff:>13.2e}"
            print(row, flush=True)


def timed(fn, repeat: int) -> tuple[float, float]:
    times = []
    for _ in range(repeat):
        start = CLOCK()
        fn()
        times.append(CLOCK() - start)
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
    engine = cum("gaussian.py", "_update")  # the engine step after its input checks
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
            cum("resampling.py", "_systematic") + cum("particle.py", "gather_particles"),
        ),
    ]
    return rows


def peers(args) -> None:
    """SIR and the resamplers beside NumPy at the three particle counts."""
    counts = [(args.small, args.steps), (10 * args.small, args.mid_steps),
              (args.large, args.large_steps)]  # fmt: skip
    sir_vs_numpy(counts, args.repeat, compile=not args.no_compile)
    resamplers_vs_numpy([args.small, 10 * args.small, args.large], args.repeat)


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
    parser.add_argument("--no-peers", action="store_true", help="skip the NumPy comparisons")
    parser.add_argument(
        "--no-compile", action="store_true", help="eager rows only (no run(compile=True))"
    )
    parser.add_argument("--peers-only", action="store_true", help="only the NumPy comparisons")
    parser.add_argument("--cpu-time", action="store_true", help="time with process CPU time")
    parser.add_argument("--mid-steps", type=int, default=100, help="steps of the 10^4 runs")
    parser.add_argument(
        "--child", nargs=4, metavar=("FILTER", "MODEL", "N", "T"), help=argparse.SUPPRESS
    )
    parser.add_argument("--device", default="cpu", help="cuda: the device throughput rows only")
    parser.add_argument(
        "--device-counts",
        nargs="+",
        default=["1000:500", "100000:100", "1000000:100", "10000000:20"],
        help="particles:steps of the device rows",
    )
    parser.add_argument(
        "--device-cpu-max", type=float, default=3.0, help="seconds above which the CPU stops"
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.device != "cpu":
        counts = [tuple(int(v) for v in c.split(":")) for c in args.device_counts]
        device_rows(torch.device(args.device), counts, args.repeat, args.device_cpu_max)
        return
    global CLOCK
    CLOCK = time.process_time if args.cpu_time else time.perf_counter
    if args.child:
        name, kind, N, T = args.child
        child_memory(name, kind, int(N), int(T))
        return

    print(
        f"torch {torch.__version__}, numpy {np.__version__}, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"torch threads {torch.get_num_threads()}, float64, load average "
        + " ".join(f"{v:.2f}" for v in os.getloadavg())
    )
    print(f"prognos_torch from {os.path.dirname(prognos_torch.__file__)}")
    print(f"clock: {'process CPU time' if args.cpu_time else 'wall'}")
    if args.peers_only:
        peers(args)
        print("\nload average at the end " + " ".join(f"{v:.2f}" for v in os.getloadavg()))
        return
    print(
        f"\nSTPF, {args.small} particles, 1-D state, {args.steps} steps "
        "(targets: per-sample <= 1 s, batched <= 0.2 s)"
    )
    print(f"{'model form':<18}{'median s':>6}{'best s':>9}{'ms/step':>9}{'target':>8}{'met':>5}")
    targets = {"per-sample": 1.0, "batched+jac": 0.2, "random-walk": 1.0}
    # each form by default and with run(..., inference=True) (the steps after the first in
    # torch.inference_mode(); the same numbers)
    for kind in ("per-sample", "batched+jac", "random-walk"):
        for inf in (False, True):
            med, best = timed(
                lambda kind=kind, inf=inf: one_run(
                    "STPF", kind, args.small, args.steps, inference=inf
                ),
                args.repeat,
            )
            ok = "yes" if med <= targets[kind] else "no"
            label = kind + (" inf" if inf else "")
            print(
                f"{label:<18}{med:>6.3f}{best:>9.3f}{1e3 * med / args.steps:>9.2f}"
                f"{targets[kind]:>8.1f}{ok:>5}"
            )
    # run(..., compile=True): the filter as one compiled pass (its compile time apart)
    if not args.no_compile:
        go = lambda: one_run("STPF", "batched+jac", args.small, args.steps, compile=True)  # noqa: E731
        go()
        t_compile = prognos_torch.filters.sequence.last_compile_seconds
        med, best = timed(go, args.repeat)
        ok = "yes" if med <= targets["batched+jac"] else "no"
        print(
            f"{'batched+jac comp':<18}{med:>6.3f}{best:>9.3f}{1e3 * med / args.steps:>9.2f}"
            f"{targets['batched+jac']:>8.1f}{ok:>5}   (compile {t_compile:.1f} s apart)"
        )

    if not args.no_peers:
        peers(args)

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

    print("\nload average at the end " + " ".join(f"{v:.2f}" for v in os.getloadavg()))

    if args.profile:
        for kind in ("per-sample", "batched+jac"):
            rows = profile_stpf(kind, args.small, args.steps)
            total = rows[0][1]
            print(f"\nprofile: STPF, {kind}, {args.small} particles, {args.steps} steps (cProfile)")
            for label, sec in rows:
                print(f"{label:<62}{sec:>8.3f} s{100 * sec / total:>7.1f} %")


if __name__ == "__main__":
    main()
