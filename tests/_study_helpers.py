"""Shared checks of the studies' quick mode (not a test module)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from prognos_torch.cli import main


def run_quick(tmp_path_factory, name: str, runs: int | None = None) -> Path:
    """Run ``prognos study NAME --quick`` into a temporary folder; return the study's folder."""
    out = tmp_path_factory.mktemp(name.replace("-", "_"))
    args = ["study", name, "--quick", "--out", str(out), "--no-progress"]
    if runs is not None:
        args += ["--runs", str(runs)]
    assert main(args) == 0
    return out / name


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
