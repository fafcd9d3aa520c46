"""The examples run to the end; the RUL example prints the ``ims-rul`` study's ``prognose (auto)``
rows (it says so)."""

import re

import pytest
from _scripts import ROOT, run_script
from test_study_ims_rul import QUICK_PRED_RUL


def test_ims_rul_example_prints_the_study_rows(tmp_path):
    stdout = run_script(ROOT / "examples" / "ims_rul.py", ["--out", str(tmp_path)], tmp_path)
    rows = [line.split() for line in stdout.splitlines() if line[:1] == " " and "[" in line]
    assert len(rows) == 5  # 20/40/60/80/90 % of [onset, end of life]
    median = [float(r[2]) for r in rows]
    # test_study_ims_rul's quick reference: points 1, 3 and 5 of "T1 B3 rms"
    ref = QUICK_PRED_RUL[("prognose (auto)", "T1 B3 rms")]
    assert median[::2] == pytest.approx(ref, abs=1e-3)
    # the closing line counts what the rows show
    true = [float(r[1]) for r in rows]
    ends = [re.search(r"\[\s*([^,]+),\s*([^\]]+)\]", " ".join(r)).groups() for r in rows]
    lo, hi = ([float(e[k]) for e in ends] for k in (0, 1))
    cov = sum(a <= t <= b for a, t, b in zip(lo, true, hi))
    cone = sum(0.7 * t <= m <= 1.3 * t for m, t in zip(median, true))
    assert f"covers the true RUL at {cov} of 5 points" in stdout
    assert f"(alpha-lambda cone) at {cone} of 5" in stdout
    assert (tmp_path / "ims_prognose_rul.png").stat().st_size > 0


@pytest.mark.parametrize(
    ("script", "figures"),
    [("user_csv.py", ("user_csv_forecast.png", "user_csv_rul.png")),
     ("ims_bearing.py", ("ims_forecast.png", "ims_rul.png"))],
)  # fmt: skip
def test_every_other_example_runs_to_the_end(script, figures, tmp_path):
    """The examples call the public API as a user would; without this test they fall behind
    when it moves (both failed once RULResult.summary() gained its text fields)."""
    run_script(ROOT / "examples" / script, ["--out", str(tmp_path)], tmp_path)
    for name in figures:
        assert (tmp_path / name).stat().st_size > 0
