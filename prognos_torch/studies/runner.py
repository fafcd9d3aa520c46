"""Running studies and writing their outputs (see the package docstring)."""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

__all__ = [
    "Study",
    "StudyConfig",
    "StudyResult",
    "discover_studies",
    "format_table",
    "load_trainer",
    "run_study",
    "trainers_dir",
    "write_outputs",
]


@dataclass(frozen=True)
class StudyConfig:
    """Options every study accepts.

    Attributes:
        runs: Monte Carlo runs (``None``: the study's default, usually the paper's).
        quick: a reduced protocol for tests and smoke runs (well under a minute).
        out: output folder.
        device: ``"cpu"`` or ``"cuda"``.
        seed: base seed; run ``i`` uses ``torch.Generator().manual_seed(seed + i)``.
        progress: show progress bars.
    """

    runs: int | None = None
    quick: bool = False
    out: Path = Path("results")
    device: str = "cpu"
    seed: int = 0
    progress: bool = True

    def __post_init__(self):
        if self.runs is not None and (not isinstance(self.runs, int) or self.runs < 1):
            raise ValueError(f"runs must be a positive int, got {self.runs!r}")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"device must be 'cpu' or 'cuda', got {self.device!r}")
        if self.device == "cuda" and not torch.cuda.is_available():
            raise ValueError("device 'cuda' was asked for but CUDA is not available here")

    def generator(self, offset: int = 0) -> torch.Generator:
        """A CPU generator seeded with ``seed + offset`` (simulators draw on the CPU)."""
        return torch.Generator().manual_seed(self.seed + offset)


@dataclass
class StudyResult:
    """What a study returns.

    Attributes:
        rows: one dict per (run, method): ``{"run": i, "method": name, metric: value, ...}``.
        metrics: metric names to tabulate, in order (e.g. ``["MAE", "RMSE", "time_s"]``).
        paper: the paper's published numbers ``{method: {metric: value}}`` (may be partial).
        figures: paths of the figures the study saved (relative to the output folder).
        config: study-specific settings to record in ``run.json``.
        notes: free text appended to ``table.md`` (readings, caveats).
        extra_tables: additional markdown blocks appended to ``table.md``.
    """

    rows: list[dict]
    metrics: list[str]
    paper: dict[str, dict[str, float]] = field(default_factory=dict)
    figures: list[str] = field(default_factory=list)
    config: dict = field(default_factory=dict)
    notes: str = ""
    extra_tables: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Study:
    """A named study: ``run(cfg, out_dir) -> StudyResult``."""

    name: str
    paper: str
    title: str
    run: Callable[[StudyConfig, Path], StudyResult]
    default_runs: int = 50


def _fmt(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    a = abs(v)
    if a != 0 and (a < 1e-3 or a >= 1e4):
        return f"{v:.3e}"
    return f"{v:.4f}"


def format_table(result: StudyResult) -> str:
    """Markdown table: one row per method, ``mean ± std`` over runs, paper value beside."""
    methods: list[str] = []
    for r in result.rows:
        if r["method"] not in methods:
            methods.append(r["method"])
    head = ["method", "runs"]
    for m in result.metrics:
        head.append(f"{m} (ours)")
        if any(m in result.paper.get(meth, {}) for meth in methods):
            head.append(f"{m} (paper)")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for meth in methods:
        rows = [r for r in result.rows if r["method"] == meth]
        cells = [meth, str(len(rows))]
        for m in result.metrics:
            vals = np.array([float(r[m]) for r in rows if m in r and r[m] is not None], dtype=float)
            vals = vals[np.isfinite(vals)]
            if vals.size:
                cells.append(
                    f"{_fmt(vals.mean())} ± {_fmt(vals.std(ddof=1) if vals.size > 1 else 0.0)}"
                )
            else:
                cells.append("—")
            if any(m in result.paper.get(x, {}) for x in methods):
                cells.append(_fmt(result.paper.get(meth, {}).get(m)))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


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


def _machine() -> dict:
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def write_outputs(
    study: Study, cfg: StudyConfig, result: StudyResult, out_dir: Path, wall_s: float
) -> str:
    """Write ``table.md``, ``results.csv`` and ``run.json``; return the table text."""
    out_dir.mkdir(parents=True, exist_ok=True)
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
    (out_dir / "table.md").write_text(text_s)
    keys: list[str] = []
    for r in result.rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    with open(out_dir / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in result.rows:
            w.writerow({k: r.get(k, "") for k in keys})
    cfg_d = asdict(cfg)
    cfg_d["out"] = str(cfg.out)
    meta = {
        "study": study.name,
        "paper": study.paper,
        "title": study.title,
        "command": " ".join(sys.argv),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "wall_s": wall_s,
        "config": cfg_d,
        "study_config": result.config,
        "paper_numbers": result.paper,
        "figures": result.figures,
        "versions": _versions(),
        "machine": _machine(),
    }
    (out_dir / "run.json").write_text(json.dumps(meta, indent=2, default=str) + "\n")
    return text_s


def run_study(study: Study, cfg: StudyConfig) -> tuple[StudyResult, str]:
    """Run ``study`` with ``cfg`` and write its outputs to ``cfg.out / study.name``."""
    out_dir = Path(cfg.out) / study.name
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    result = study.run(cfg, out_dir)
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
