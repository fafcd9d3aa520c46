"""The study records: a study, its options and what it returns (plain data, no I/O)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..core.validation import check_flag, check_pos_int, check_seed

__all__ = ["Study", "StudyConfig", "StudyResult"]


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
        data: folder of an external dataset, for the studies that read one (``Study.needs_data``).
    """

    runs: int | None = None
    quick: bool = False
    out: Path = Path("results")
    device: str = "cpu"
    seed: int = 0
    progress: bool = True
    data: Path | None = None

    def __post_init__(self):
        # NumPy integers as Python ints (run.json recorded numpy.int64(3) as the string "3");
        # a float seed failed only in the first manual_seed; flags as bools (quick="no" ran
        # the quick protocol)
        runs = None if self.runs is None else check_pos_int(self.runs, "runs")
        object.__setattr__(self, "runs", runs)
        object.__setattr__(self, "seed", check_seed(self.seed))
        object.__setattr__(self, "quick", check_flag(self.quick, "quick"))
        object.__setattr__(self, "progress", check_flag(self.progress, "progress"))
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
    """A named study: ``run(cfg, out_dir) -> StudyResult``.

    ``needs_data`` names the external dataset a study reads from ``StudyConfig.data`` (data the
    library does not ship); ``None`` for the studies on shipped or simulated data.
    """

    name: str
    paper: str
    title: str
    run: Callable[[StudyConfig, Path], StudyResult]
    default_runs: int = 50
    needs_data: str | None = None

    def missing_data(self, cfg: StudyConfig) -> str | None:
        """Why ``cfg`` cannot run this study (its external data not given), or ``None``."""
        if self.needs_data is None or cfg.data is not None:
            return None
        return (
            f"study {self.name!r} reads the {self.needs_data}, which is not shipped; give the "
            "folder of a local copy with --data DIR (StudyConfig(data=DIR) in Python)"
        )
