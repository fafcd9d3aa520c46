"""The arukf-hst study (paper 004) end to end in quick mode, and its panel figure helper."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch

from prognos_torch.cli import main
from prognos_torch.plots import plot_panels

METHODS = ["UKF (true Q,R)"] + [
    m + s for s in ("", " [R x10]") for m in ("UKF", "RUKF", "ARUKF", "AUKF")
]


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("arukf_hst")
    rc = main(["study", "arukf-hst", "--quick", "--runs", "2", "--out", str(out), "--no-progress"])
    assert rc == 0
    return out / "arukf-hst"


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_outputs_complete_and_finite(quick):
    for name in ("table.md", "results.csv", "run.json", "sensitivity.csv"):
        assert (quick / name).is_file(), name
    meta = json.loads((quick / "run.json").read_text())
    assert meta["study"] == "arukf-hst" and meta["paper"] == "004"
    assert len(meta["figures"]) == 4
    for fig in meta["figures"]:
        data = (quick / fig).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, fig
    rows = _rows(quick / "results.csv")
    assert sorted({r["method"] for r in rows}) == sorted(METHODS)
    assert len(rows) == 2 * len(METHODS)
    per_component = (
        [f"RMSE {s}" for s in ("x1", "x2", "x3", "x4", "v1", "v2", "v3", "v4", "v5")]
        + [f"RMSE {s}" for s in ("f_a^c", "f_a^d", "f_s")]
        + [f"Q{i} RMSE" for i in range(1, 10)]
        + [f"R{i} RMSE" for i in range(1, 10)]
    )
    summary = ["state RMSE", "fault RMSE", "Q RMSE", "R RMSE", "Q RMSE (k>N)", "R RMSE (k>N)"]
    for r in rows:
        for key in per_component + summary + ["time_s"]:
            v = float(r[key])
            assert math.isfinite(v) and v >= 0.0, (r["method"], key, v)
        # the summary columns are the means of the per-component tables (Tables 2-5 averages)
        states = [float(r[c]) for c in per_component[:9]]
        assert float(r["state RMSE"]) == pytest.approx(np.mean(states), rel=1e-12)
        faults = [float(r[c]) for c in per_component[9:12]]
        assert float(r["fault RMSE"]) == pytest.approx(np.mean(faults), rel=1e-12)
    sens = _rows(quick / "sensitivity.csv")
    assert {r["method"] for r in sens} >= {"RUKF (gamma=1.05)", "ARUKF (gamma=1.05)"}
    for r in sens:
        for key in summary + ["time_s"]:
            assert math.isfinite(float(r[key]))
    table = (quick / "table.md").read_text()
    assert "Table 5 style" in table and "0.0329" in table  # paper text average beside ours


def test_oracle_and_nominal_noise_errors_are_exact(quick):
    """Fixed-noise filters: the Q/R error is that of their nominal statistics, in closed form."""
    rows = _rows(quick / "results.csv")
    T = json.loads((quick / "run.json").read_text())["study_config"]["n_steps"]
    k = np.arange(1, T + 1)
    q_true = 1.0 + 0.5 * np.sin(0.0003 * (k - 1))  # Eq. 67, step k uses Q_{k-1}
    r_true = 1.1 + 0.08 * np.cos(0.0002 * k)  # Eq. 68
    for r in rows:
        if r["method"] == "UKF (true Q,R)":
            assert float(r["Q RMSE"]) < 1e-12 and float(r["R RMSE"]) < 1e-12
        if r["method"] in ("UKF", "RUKF"):
            assert float(r["Q RMSE"]) == pytest.approx(np.sqrt(np.mean((1.0 - q_true) ** 2)))
            assert float(r["R RMSE"]) == pytest.approx(np.sqrt(np.mean((1.1 - r_true) ** 2)))
        if r["method"] in ("UKF [R x10]", "RUKF [R x10]"):
            assert float(r["R RMSE"]) == pytest.approx(np.sqrt(np.mean((11.0 - r_true) ** 2)))


def test_window_estimate_of_R_beats_a_tenfold_wrong_nominal(quick):
    """With R ten times too large, the moving-window estimate (Eq. 48) after the window has
    filled is far closer to the true R_k than the fixed nominal (error about 9.9)."""
    rows = _rows(quick / "results.csv")

    def late(method):
        return [float(r["R RMSE (k>N)"]) for r in rows if r["method"] == method]

    fixed = late("RUKF [R x10]")
    assert min(fixed) > 9.0
    for method in ("ARUKF [R x10]", "AUKF [R x10]"):
        assert max(late(method)) < 0.25 * min(fixed), method


# ----------------------------------------------------------------------------- plot_panels
def test_plot_panels_writes_png_and_checks_shapes(tmp_path):
    t = torch.linspace(0, 1, 50)
    truth = torch.stack([torch.sin(t), torch.cos(t), t], -1)
    fig = plot_panels(
        tmp_path / "p.png",
        t,
        {"a": truth + 0.1, "b": truth * 100.0},
        truth=truth,
        names=["s", "c", "t"],
        ncols=2,
        clip=1.0,
    )
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert len(axes) == 3
    lo, hi = axes[0].get_ylim()  # truth range sin(0..1) = [0, 0.841], +- its span
    span = math.sin(1.0)
    assert lo == pytest.approx(-span) and hi == pytest.approx(2 * span)
    with pytest.raises(ValueError, match="series"):
        plot_panels(tmp_path / "q.png", t, {})
    with pytest.raises(ValueError, match=r"series\['b'\] must have shape"):
        plot_panels(tmp_path / "q.png", t, {"a": truth, "b": truth[:, :2]})
    with pytest.raises(ValueError, match="truth must have shape"):
        plot_panels(tmp_path / "q.png", t, {"a": truth}, truth=truth[:-1])
    with pytest.raises(ValueError, match="names"):
        plot_panels(tmp_path / "q.png", t, {"a": truth}, names=["x"])
    with pytest.raises(ValueError, match="clip"):
        plot_panels(tmp_path / "q.png", t, {"a": truth}, clip=1.0)
