"""Shared set-up and checks of the study tests (not a test module).

A study test module starts with::

    from _study_helpers import check_outputs, quick_fixture, read_rows, trainer_fixture

    quick_out = quick_fixture("elm-stsckf", runs=3)   # module fixture: the study's folder
    trainer = trainer_fixture("elm_stsckf")           # module fixture: trainers/elm_stsckf.py
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from types import ModuleType

import pytest

from prognos_torch.cli import main
from prognos_torch.studies import load_trainer as _load

TRAINERS = Path(__file__).resolve().parents[1] / "trainers"


def load_trainer(stem: str) -> ModuleType:
    """The study script ``trainers/<stem>.py`` as a module (the runner's own loader)."""
    return _load(TRAINERS / f"{stem}.py")


def run_quick(tmp_path_factory, name: str, runs: int | None = None) -> Path:
    """Run ``prognos study NAME --quick`` into a temporary folder; return the study's folder."""
    out = tmp_path_factory.mktemp(name.replace("-", "_"))
    args = ["study", name, "--quick", "--out", str(out), "--no-progress"]
    if runs is not None:
        args += ["--runs", str(runs)]
    assert main(args) == 0
    return out / name


def quick_fixture(name: str, runs: int | None = None):
    """A module-scoped fixture running study ``name`` once in quick mode (see :func:`run_quick`)."""

    @pytest.fixture(scope="module")
    def quick_out(tmp_path_factory) -> Path:
        return run_quick(tmp_path_factory, name, runs)

    return quick_out


def trainer_fixture(stem: str):
    """A module-scoped fixture with the study script ``trainers/<stem>.py`` loaded."""

    @pytest.fixture(scope="module")
    def trainer() -> ModuleType:
        return load_trainer(stem)

    return trainer


def read_rows(d: Path) -> list[dict]:
    with open(d / "results.csv") as fh:
        return list(csv.DictReader(fh))


def check_outputs(d: Path, name: str, n_figures: int, methods, runs: int) -> tuple[dict, list]:
    """table.md, results.csv, run.json present; every figure a PNG; one row per run and method."""
    for f in ("table.md", "results.csv", "run.json"):
        assert (d / f).stat().st_size > 0
    meta = json.loads((d / "run.json").read_text())
    assert meta["study"] == name and meta["config"]["quick"] is True
    assert len(meta["figures"]) == n_figures
    for fig in meta["figures"]:
        assert (d / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = read_rows(d)
    assert sorted((int(r["run"]), r["method"]) for r in rows) == sorted(
        (i, m) for i in range(runs) for m in methods
    )
    return meta, rows


def means(rows: list[dict], metric: str) -> dict[str, float]:
    """``{method: mean of metric over the runs}`` (empty and NaN cells skipped)."""
    acc: dict[str, list[float]] = {}
    for r in rows:
        v = r.get(metric, "")
        if v not in ("", "None", "nan"):
            acc.setdefault(r["method"], []).append(float(v))
    return {m: sum(v) / len(v) for m, v in acc.items()}
