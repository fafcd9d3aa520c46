"""Running studies and writing their outputs (see the package docstring)."""

from __future__ import annotations

import importlib.util
import json
import os
import platform
import sys
import time
from collections.abc import Callable, Hashable, Mapping
from dataclasses import asdict
from pathlib import Path
from types import ModuleType

import numpy as np
import torch
from tqdm import tqdm

from ..io import atomic_write
from .rows import rows_csv_bytes
from .study import Study, StudyConfig, StudyResult
from .tables import format_table

__all__ = [
    "Study",
    "StudyConfig",
    "StudyDataError",
    "StudyResult",
    "discover_studies",
    "format_table",
    "load_trainer",
    "run_jobs",
    "run_study",
    "timed",
    "trainers_dir",
    "write_outputs",
]


def run_jobs(
    jobs: Mapping[Hashable, Callable[[], object]], *, desc: str, progress: bool = True
) -> dict:
    """Run the study's jobs in order with one progress bar; ``{key: job()}``.

    Each key is shown beside the bar while its job runs (e.g. ``("sens", "SCKF", 1e-3)``).
    """
    bar = tqdm(jobs.items(), desc=desc, disable=not progress)
    out = {}
    for key, job in bar:
        bar.set_postfix_str(" ".join(map(str, key)) if isinstance(key, tuple) else str(key))
        out[key] = job()
    return out


def timed(fn: Callable, *args, **kwargs) -> tuple[object, float]:
    """``(fn(*args, **kwargs), wall seconds)``."""
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def _versions() -> dict:
    import matplotlib
    import scipy

    from .. import __version__

    return {
        "prognos_torch": __version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "matplotlib": matplotlib.__version__,
        "python": sys.version.split()[0],
    }


def _cpu_model() -> str | None:
    """The CPU's model name (from ``/proc/cpuinfo`` on Linux): with the vector instruction set
    it decides how BLAS and the vectorised kernels round, which particle filters amplify."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def _machine() -> dict:
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu": _cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def _command(name: str) -> str:
    """The run as a command a reader can repeat, whichever entry point started it (a trainer
    script, ``prognos study NAME`` or ``python -m prognos_torch study NAME``)."""
    args = sys.argv[1:]
    if args[:2] == ["study", name]:
        args = args[2:]
    threads = os.environ.get("OMP_NUM_THREADS")
    env = f"OMP_NUM_THREADS={threads} " if threads else ""
    return " ".join([f"{env}python -m prognos_torch study {name}", *args])


def write_outputs(
    study: Study, cfg: StudyConfig, result: StudyResult, out_dir: Path, wall_s: float
) -> str:
    """Write ``table.md``, ``results.csv`` and ``run.json``; return the table text.

    The three files are built first and each written atomically: an error while building them
    (a malformed row, say) writes none of them, and no file is ever left half-written.
    """
    table = format_table(result)
    # runs actually made (quick mode may use fewer than asked): the most rows of any method
    counts: dict[str, int] = {}
    for r in result.rows:
        counts[r["method"]] = counts.get(r["method"], 0) + 1
    runs = max(counts.values()) if counts else 0
    text = [
        f"# {study.title}",
        "",
        f"Paper {study.paper}. Runs: {runs}"
        f"{' (quick mode)' if cfg.quick else ''}. Wall time {wall_s:.1f} s.",
        "",
        table,
    ]
    for block in result.extra_tables:
        text += ["", block]
    if result.notes:
        text += ["", result.notes.strip()]
    text_s = "\n".join(text) + "\n"
    csv_b = rows_csv_bytes(result.rows)
    cfg_d = asdict(cfg)
    cfg_d["out"] = str(cfg.out)
    cfg_d["data"] = None if cfg.data is None else str(cfg.data)
    meta = {
        "study": study.name,
        "paper": study.paper,
        "title": study.title,
        "command": _command(study.name),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "wall_s": wall_s,
        "config": cfg_d,
        "study_config": result.config,
        "paper_numbers": result.paper,
        "figures": result.figures,
        "versions": _versions(),
        "machine": _machine(),
    }
    json_s = json.dumps(meta, indent=2, default=str) + "\n"
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write(out_dir / "table.md", text_s.encode())
    atomic_write(out_dir / "results.csv", csv_b)
    atomic_write(out_dir / "run.json", json_s.encode())
    return text_s


class StudyDataError(ValueError):
    """The data a study was given cannot serve it (a malformed file, too few records); the
    message names the file or folder. ``prognos study`` prints it as one ``error:`` line."""


def run_study(study: Study, cfg: StudyConfig) -> tuple[StudyResult, str]:
    """Run ``study`` with ``cfg`` and write its outputs to ``cfg.out / study.name`` (the folders
    made here and left empty by a failed run, ``cfg.out`` included, are removed again)."""
    missing = study.missing_data(cfg)
    if missing is not None:
        raise ValueError(missing)
    out_dir = Path(cfg.out) / study.name
    made = [p for p in (out_dir, *out_dir.parents) if not p.exists()]  # deepest first
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        result = study.run(cfg, out_dir)
    except BaseException:
        for p in made:  # (only out_dir was: a new --out folder stayed behind, empty)
            if any(p.iterdir()):
                break
            p.rmdir()
        raise
    wall = time.perf_counter() - t0
    text = write_outputs(study, cfg, result, out_dir, wall)
    return result, text


def trainers_dir() -> Path:
    """The repository's ``trainers/`` folder (studies live there, next to the package)."""
    env = os.environ.get("PROGNOS_TRAINERS")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "trainers"


def load_trainer(path: str | os.PathLike) -> ModuleType:
    """Import one study script by path, as module ``prognos_trainers.<stem>``.

    The module is registered in ``sys.modules`` under that name (dataclasses and pickling look
    a module up by name), so loading the same file again replaces it. Nothing else is imported:
    a study script composes library calls and exposes ``STUDY``; it never imports the command
    line, which is what drives it (``prognos study NAME``, ``python -m prognos_torch study NAME``).
    """
    path = Path(path)
    if path.suffix != ".py" or not path.is_file():
        raise FileNotFoundError(f"no study script at {path} (expected a .py file)")
    name = f"prognos_trainers.{path.stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    return mod


def discover_studies(directory: Path | None = None) -> dict[str, Study]:
    """Import every ``trainers/*.py`` that defines ``STUDY`` and return them by name."""
    d = Path(directory) if directory is not None else trainers_dir()
    if not d.is_dir():
        raise FileNotFoundError(
            f"no trainers/ folder at {d}: studies run from a checkout of the repository "
            "(pip install -e .), or set PROGNOS_TRAINERS to the folder"
        )
    studies: dict[str, Study] = {}
    for path in sorted(d.glob("*.py")):
        if path.name.startswith("_"):
            continue
        st = getattr(load_trainer(path), "STUDY", None)
        if isinstance(st, Study):
            studies[st.name] = st
    return studies
