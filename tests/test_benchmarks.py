"""Every benchmark script runs to the end at a tiny size (speed is not measured here).

The benchmarks call the public API the way a user would; without this test they fall behind
when the API moves. Each runs as ``__main__`` in this interpreter (an interpreter of its own
cost about 3 s of start-up each), with ``sys.argv``, ``sys.path``, the working folder, the
warning filters and the torch thread count (which they set) restored afterwards, and with
arguments that shrink the work to seconds; a script that starts worker processes of the
library runs in its own interpreter, where its workers can import it.
"""

import os
import subprocess
import sys

import pytest
from _scripts import ROOT, run_script

#: scripts run in their own interpreter: the fleet's --workers processes (spawned) import the
#: script that started them
OWN_INTERPRETER = {"bench_fleet.py"}

TINY = {
    "bench_anfis_rules.py": ["--repeat", "1", "--max-rules", "8"],
    "bench_calibrate.py": ["--histories", "1", "--method", "exponential"],
    "bench_datasets.py": ["--repeat", "1", "--n-files", "2", "--rows", "512", "--channels", "4"],
    "bench_filters.py": ["--steps", "5", "--sizes", "4"],
    "bench_fleet.py": [
        "--assets",
        "20",
        "--steps",
        "40",
        "--samples",
        "50",
        "--shard-size",
        "8",
        "--workers",
        "2",
    ],  # fmt: skip
    "bench_float32.py": ["--steps", "50", "--runs", "2"],
    "bench_optim.py": ["--repeats", "1", "--runs", "2"],
    "bench_particle.py": [
        "--steps",
        "10",
        "--small",
        "50",
        "--large",
        "200",
        "--large-steps",
        "3",
        "--mid-steps",
        "2",
        "--repeat",
        "1",
        "--no-memory",
        "--no-compile",
    ],  # fmt: skip  (compiled passes: test_particle_compiled.py; a cold compile costs ~20 s)
    "bench_peers.py": [
        "--repeats",
        "1",
        "--runs",
        "2",
        "--no-dynamax",
        "--filters",
        "ekf",
        "--no-single",
        "--no-compile",
    ],  # fmt: skip  (fit(compile=True) itself: test_compiled_steps.py; two cold compiles ~25 s)
    "bench_prognose.py": ["--rows", "400", "--repeat", "1"],
    "bench_progpy.py": [
        "--samples",
        "5",
        "--large",
        "20",
        "--estimate-steps",
        "5",
        "--repeat",
        "1",
    ],  # fmt: skip
    "bench_jacobian.py": ["--steps", "5", "--batch", "2", "--repeat", "1"],
    "bench_kernel_exp.py": ["--windows", "50", "--batch", "8", "--repeat", "1", "--calls", "1"],
    "bench_long.py": ["--rows", "300", "--learners", "elm"],
    "bench_study_batching.py": ["--runs", "1", "2", "--threads", "1"],
}


def test_every_benchmark_is_listed():
    scripts = {p.name for p in (ROOT / "benchmarks").glob("bench_*.py")}
    assert scripts == set(TINY)


@pytest.mark.parametrize("script", sorted(TINY))
def test_benchmark_runs(script, tmp_path):
    if script not in OWN_INTERPRETER:
        run_script(ROOT / "benchmarks" / script, TINY[script], tmp_path)
        return
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), *TINY[script]],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, f"{script} failed:\n{proc.stderr[-3000:]}"
