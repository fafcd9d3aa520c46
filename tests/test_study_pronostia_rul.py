"""The PRONOSTIA reader and the pronostia-rul study, on record folders written here.

The records follow the challenge's layout and formats (``,`` and ``;`` separated, a clock that
wraps at midnight, the truncated ``Test_set`` beside ``Full_Test_Set``); the real data are not
shipped, so the features are checked against the IMS feature function on the arrays written.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _study_helpers import read_rows

from prognos_torch.cli import main
from prognos_torch.datasets.ims import snapshot_features
from prognos_torch.datasets.pronostia import find_pronostia_bearings, read_pronostia_bearing
from prognos_torch.prognosis.protocol import known_threshold_protocol


def _write_record(path, clock_s: float, x: np.ndarray, sep: str = ",") -> None:
    s = clock_s % 86400.0
    h, m, sec = s // 3600, s % 3600 // 60, math.floor(s % 60)
    us = round((s - math.floor(s)) * 1e6) + 39.0 * np.arange(len(x))
    cols = np.column_stack([np.full(len(x), h), np.full(len(x), m), np.full(len(x), sec), us, x])
    fmt = ["%d", "%d", "%d", "%.4e" if sep == ";" else "%d", "%.17g", "%.17g"]
    np.savetxt(path, cols, fmt=fmt, delimiter=sep)


def _bearing(folder, n: int, *, start_s: float, sep=",", seed=0, life=False, samples=64):
    """``n`` records every 10 s; with ``life``, amplitude 1 until 60 % of them, then growing."""
    folder.mkdir(parents=True)
    g = np.random.default_rng(seed)
    recs = []
    for k in range(n):
        amp = 1.0 + (max(0.0, k - 0.6 * n) ** 2 / (0.02 * n * n) if life else 0.0)
        x = amp * g.standard_normal((samples, 2))
        _write_record(folder / f"acc_{k + 1:05d}.csv", start_s + 10.0 * k, x, sep)
        recs.append(x)
    return recs


def test_reader_features_times_and_layout(tmp_path):
    root = tmp_path / "phm2012"
    recs = _bearing(root / "Learning_set" / "Bearing1_1", 5, start_s=86400 - 25.0)  # midnight
    full = _bearing(root / "Full_Test_Set" / "Bearing2_3", 4, start_s=3600.0, sep=";", seed=1)
    _bearing(root / "Test_set" / "Bearing2_3", 2, start_s=3600.0, seed=2)  # truncated copy
    found = find_pronostia_bearings(root)
    assert list(found) == ["Bearing1_1", "Bearing2_3"]
    assert found["Bearing2_3"].parent.name == "Full_Test_Set"

    f = read_pronostia_bearing(found["Bearing1_1"], expected_samples=None)
    assert (f.bearing, f.condition, f.clock_mismatch) == ("Bearing1_1", 1, ())
    torch.testing.assert_close(f.hours, torch.arange(5, dtype=torch.float64) * 10 / 3600)
    want = np.stack([snapshot_features(x) for x in recs])
    np.testing.assert_allclose(f.values.numpy(), want, rtol=1e-12, atol=0)
    rms = f.feature("rms")
    assert rms.shape == (5, 2)
    np.testing.assert_allclose(rms[:, 1].numpy(), [np.sqrt((x[:, 1] ** 2).mean()) for x in recs],
                               rtol=1e-12)  # fmt: skip
    # ';' separated, microseconds in scientific notation
    g = read_pronostia_bearing(found["Bearing2_3"], expected_samples=64)
    np.testing.assert_allclose(g.values.numpy(), np.stack([snapshot_features(x) for x in full]),
                               rtol=1e-12)  # fmt: skip
    with pytest.raises(ValueError, match="feature must be one of"):
        f.feature("energy")


def test_reader_flags_a_wrong_clock_and_refuses_bad_records(tmp_path):
    d = tmp_path / "Bearing3_1"
    _bearing(d, 4, start_s=100.0)
    x = np.ones((64, 2))
    _write_record(d / "acc_00003.csv", 5000.0, x)  # stamped far off: flagged, time kept
    f = read_pronostia_bearing(d, expected_samples=64)
    assert f.clock_mismatch == ("acc_00003.csv", "acc_00004.csv")
    torch.testing.assert_close(f.hours, torch.arange(4, dtype=torch.float64) * 10 / 3600)
    with pytest.raises(ValueError, match=r"acc_00001\.csv: expected 2560 rows, got 64"):
        read_pronostia_bearing(d)  # the challenge's records have 2,560 rows
    (d / "acc_00002.csv").write_text("1,2,3,4,5,x\n1,2,3,4,5,6\n")
    with pytest.raises(ValueError, match=r"acc_00002\.csv: not a numeric record"):
        read_pronostia_bearing(d, expected_samples=None)
    (d / "acc_00002.csv").write_text("1,2,3,4,5\n1,2,3,4,5\n")
    with pytest.raises(ValueError, match=r"acc_00002\.csv: expected rows of 6 columns"):
        read_pronostia_bearing(d, expected_samples=None)
    with pytest.raises(FileNotFoundError, match="no PRONOSTIA bearing folder"):
        find_pronostia_bearings(_empty(tmp_path))
    with pytest.raises(FileNotFoundError, match="is no PRONOSTIA bearing folder"):
        read_pronostia_bearing(tmp_path)
    # a non-finite sample (the IMS reader refuses them; here a feature became NaN), a record
    # number written twice, and a Test_set alone (truncated bearings, skipped on purpose)
    _write_record(d / "acc_00002.csv", 110.0, np.ones((64, 2)))
    rows = (d / "acc_00003.csv").read_text().splitlines()
    rows[5] = ",".join(rows[5].split(",")[:5] + ["nan"])
    (d / "acc_00003.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(ValueError, match=r"acc_00003\.csv, row 6, column 6: non-finite value nan"):
        read_pronostia_bearing(d, expected_samples=None)
    _write_record(d / "acc_00003.csv", 120.0, np.ones((64, 2)))
    (d / "acc_3.csv").write_bytes((d / "acc_00003.csv").read_bytes())
    with pytest.raises(ValueError, match=r"acc_0*3\.csv and acc_0*3\.csv are both record 3"):
        read_pronostia_bearing(d, expected_samples=None)
    (d / "acc_3.csv").unlink()
    truncated = tmp_path / "arch" / "Test_set"
    _bearing(truncated / "Bearing1_3", 2, start_s=0.0)
    for where in (truncated, truncated.parent):
        with pytest.raises(FileNotFoundError, match="but those of Test_set, which stop before "
                           "failure: give the archive's root, Learning_set or Full_Test_Set"):  # fmt: skip
            find_pronostia_bearings(where)


def _empty(tmp_path):
    e = tmp_path / "empty"
    e.mkdir()
    return e


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("pronostia_data")
    for i, name in enumerate(("Bearing1_1", "Bearing2_1", "Bearing3_1")):
        _bearing(
            root / "Learning_set" / name,
            120,
            start_s=1000.0 * i,
            seed=10 + i,
            life=True,
            samples=2560,
        )
    out = tmp_path_factory.mktemp("pronostia_out")
    args = ["study", "pronostia-rul", "--quick", "--data", str(root), "--out", str(out),
            "--no-progress"]  # fmt: skip
    assert main(args) == 0
    return root, out / "pronostia-rul"


def test_quick_study_scores_the_protocol_points(quick_run):
    root, out = quick_run
    for name in ("table.md", "results.csv", "run.json", "rul_vs_time.png"):
        assert (out / name).stat().st_size > 0
    rows = read_rows(out)
    # quick mode: the first 2 bearings, both axes, points 20 / 60 / 90 % of [onset, EoL]
    f = read_pronostia_bearing(root / "Learning_set" / "Bearing1_1")
    pc = known_threshold_protocol(f.hours, f.feature("rms")[:, 0])
    mine = [r for r in rows if r["series"] == "Bearing1_1 h" and r["method"] == "linear slope"]
    assert len(mine) == 3
    np.testing.assert_allclose([float(r["true_rul"]) for r in mine],
                               (pc.t_eol - pc.times[::2]).numpy(), rtol=1e-9)  # fmt: skip
    assert {r["series"] for r in rows} <= {"Bearing1_1 h", "Bearing1_1 v", "Bearing2_1 h",
                                           "Bearing2_1 v"}  # fmt: skip
    assert "horizontal accelerometer rms" in (out / "table.md").read_text()


def test_study_needs_its_data(tmp_path, capsys):
    assert main(["study", "pronostia-rul", "--quick", "--out", str(tmp_path)]) == 2
    assert "give the folder of a local copy with --data DIR" in capsys.readouterr().err
    assert main(["study", "pronostia-rul", "--quick", "--data", str(_empty(tmp_path)),
                 "--out", str(tmp_path), "--no-progress"]) == 2  # fmt: skip
    assert "no PRONOSTIA bearing folder" in capsys.readouterr().err
    assert main(["study", "--list"]) == 0
    assert "pronostia-rul" in capsys.readouterr().out


def test_run_study_refuses_a_study_without_its_data(tmp_path):
    from _study_helpers import load_trainer

    from prognos_torch.studies import StudyConfig, run_study

    study = load_trainer("pronostia_rul").STUDY
    with pytest.raises(ValueError, match="PRONOSTIA .* which is not shipped"):
        run_study(study, StudyConfig(quick=True, out=tmp_path))
    assert not (tmp_path / "pronostia-rul").exists()  # nothing half-written


_TINY = """
from pathlib import Path
from prognos_torch.studies import Study, StudyResult

def run(cfg, out):
    return StudyResult(rows=[{{"run": 0, "method": "m", "x": 1.0, "data": str(cfg.data)}}],
                       metrics=["x"])

STUDY = Study(name="{name}", paper="p", title="t", run=run, default_runs=1, needs_data={need})
"""


def test_study_all_skips_the_studies_of_data_not_given(tmp_path, monkeypatch, capsys):
    trainers = tmp_path / "trainers"
    trainers.mkdir()
    (trainers / "plain.py").write_text(_TINY.format(name="plain", need=None))
    (trainers / "ext.py").write_text(_TINY.format(name="ext", need='"X records"'))
    monkeypatch.setenv("PROGNOS_TRAINERS", str(trainers))
    out = tmp_path / "out"
    assert main(["study", "all", "--quick", "--out", str(out), "--no-progress"]) == 0
    assert "[skipped ext: it reads the X records; give --data DIR]" in capsys.readouterr().out
    assert (out / "plain" / "results.csv").is_file() and not (out / "ext").exists()
    assert main(["study", "all", "--quick", "--out", str(out), "--data", str(tmp_path),
                 "--no-progress"]) == 0  # fmt: skip
    assert str(tmp_path) in (out / "ext" / "results.csv").read_text()
    capsys.readouterr()
    assert main(["study", "--list"]) == 0
    lines = {ln.split()[0]: ln for ln in capsys.readouterr().out.splitlines()}
    assert lines["ext"].endswith("(needs --data: X records)")
    assert "needs --data" not in lines["plain"]


def test_study_refuses_short_or_malformed_bearings_in_one_line(tmp_path, capsys):
    """A bearing of 12 records raised a traceback from inside the protocol (naming neither the
    bearing nor the 20 records it needs) and left an empty output folder."""
    root = tmp_path / "arch"
    _bearing(root / "Learning_set" / "Bearing1_1", 12, start_s=0.0, samples=2560)
    out = tmp_path / "out"
    argv = ["study", "pronostia-rul", "--quick", "--data", str(root), "--out", str(out),
            "--no-progress"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ")
    assert "Bearing1_1: 12 records; the protocol needs at least 20" in err
    assert not (out / "pronostia-rul").exists()
    other = tmp_path / "arch2"
    _bearing(other / "Learning_set" / "Bearing1_2", 2, start_s=0.0, samples=64)  # 64 rows
    assert main([str(other) if a == str(root) else a for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "acc_00001.csv: expected 2560 rows, got 64" in err
