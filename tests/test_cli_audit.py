"""``prognos`` as a reliability engineer runs it on CSV files: bad option values name their
option in one ``error:`` line (exit 2) before anything is written, no output replaces an
input, warnings reach stderr, and the caller's state is left as it was."""

from __future__ import annotations

import json
import math

import pytest
import torch
from _cli_helpers import healthy_csv, one_error

import prognos_torch.studies as studies  # (imported once, at collection, not in a test)
import prognos_torch.workflow  # noqa: F401
from prognos_torch._text import fmt_time
from prognos_torch.cli import build_parser, main


def test_negative_values_in_exponent_notation_or_inf_are_read_as_option_values(tmp_path, capsys):
    """argparse took ``-1e-3`` and ``-inf`` for options ('expected one argument', exit via
    SystemExit); they are the options' values, and ``-inf`` is refused by name."""
    from prognos_torch.cli import _join_negative_values

    argv = ["rul", "d.csv", "--threshold", "-1e-3", "--until", "-5", "--within", "-inf",
            "--seed", "-1,2", "--column", "-2E3"]  # fmt: skip
    args = build_parser().parse_args(_join_negative_values(argv))
    assert (args.threshold, args.until, args.seed, args.column) == (-1e-3, "-5", (-1, 2), "-2E3")
    assert args.within == -math.inf
    # what argparse reads as a number itself, a flag, and '--' stay as they were
    assert _join_negative_values(["--until", "-5", "--refit", "--", "--x", "-1e3"]) == [
        "--until", "-5", "--refit", "--", "--x", "-1e3"]  # fmt: skip
    data, _ = healthy_csv(tmp_path / "d.csv")
    argv = ["rul", str(data), "--column", "v", "--time-column", "t", "--threshold", "-inf"]
    assert main(argv) == 2
    one_error(capsys, "error: --threshold: threshold must be a finite number, got -inf")


@pytest.mark.parametrize(
    "extra, text",
    [
        (["--threshold", "nan"], "error: --threshold: threshold must be a finite number, got nan"),
        (["--method", "cubic"], "error: --method: method must be one of"),
        (["--direction", "up"], "error: --direction: direction must be 'auto', 'above' or"),
        (["--glitch-limit", "0"], "error: --glitch-limit: glitch_limit must be > 0, got 0.0"),
        (["--until", "nan"], "error: --until: until must be finite, got nan"),
        (["--last", "0"], "error: --last: last must be a positive int, got 0"),
        (["--fill", "zero"], "error: --fill: fill must be None, 'linear' or 'drop', got 'zero'"),
    ],
)
def test_a_bad_prognose_option_is_named_in_its_error(tmp_path, capsys, extra, text):
    data, _ = healthy_csv(tmp_path / "d.csv")
    base = ["rul", str(data), "--column", "v", "--time-column", "t", "--threshold", "3"]
    assert main(base + extra) == 2
    assert one_error(capsys, text) == ""


@pytest.mark.parametrize(
    "extra, text",
    [
        (["--holdout", "nan"], "error: --holdout: holdout must be a fraction in [0, 1)"),
        (["--embedding", "0"], "error: --embedding: embedding dimension m must be a positive"),
    ],
)
def test_a_bad_fit_option_is_named_in_its_error(tmp_path, capsys, extra, text):
    data, _ = healthy_csv(tmp_path / "d.csv")
    out = tmp_path / "m.pt"
    assert main(["fit", str(data), "--column", "v", "--out", str(out), *extra]) == 2
    one_error(capsys, text)
    assert not out.exists()


def test_until_at_or_past_the_last_row_warns_that_nothing_follows(tmp_path, capsys):
    """--until 1000 on rows ending at t = 19.5 reported 'observed RUL: not reached in the
    data' with no word that no row follows the cut; inside the data, no such warning."""
    data, t = healthy_csv(tmp_path / "d.csv")
    base = ["rul", str(data), "--column", "v", "--time-column", "t", "--threshold", "3",
            "--paths", "100"]  # fmt: skip
    for until in ("1000", repr(t[-1])):
        assert main(base + ["--until", until]) == 0
        err = capsys.readouterr().err.splitlines()
        want = (f"warning: --until {until}: the data end at t = {fmt_time(t[-1])}, at or before "
                "the cut, so there are no rows after it to compare with (a --until inside the "
                "data backtests)")  # fmt: skip
        assert want in err, err
    assert main(base + ["--until", repr(t[-5])]) == 0
    assert "--until" not in capsys.readouterr().err


def test_json_to_stdout_keeps_the_reports_warnings_on_stderr(tmp_path, capsys):
    """--json - silenced the whole report, and with it its 'warning:' lines (no degradation
    yet, a glitch, a calibration with too few histories): they go to stderr now."""
    data, _ = healthy_csv(tmp_path / "d.csv")
    argv = ["rul", str(data), "--column", "v", "--time-column", "t", "--threshold", "3",
            "--paths", "100"]  # fmt: skip
    assert main(argv + ["--json", "-"]) == 0
    cap = capsys.readouterr()
    record = json.loads(cap.out)  # standard output holds the record alone
    assert record["flags"], record
    assert cap.err.splitlines() == [f"warning: {f}" for f in record["flags"]]
    # the report itself still carries them on stdout, and stderr stays empty
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and all(f"warning: {f}" in cap.out for f in record["flags"])


def test_an_output_that_is_an_input_or_another_output_is_refused(tmp_path, capsys):
    """--csv DATA replaced the data just read with the forecast; fit --out DATA replaced the
    CSV with a model file; --plot and --csv on one name kept the last written."""
    data, _ = healthy_csv(tmp_path / "d.csv")
    before = data.read_bytes()
    model = tmp_path / "none.pt"  # (refused before the model file is read)
    assert main(["forecast", str(model), str(data), "--horizon", "3", "--csv", str(data)]) == 2
    one_error(capsys, f"error: --csv: {data} is the data file, which this run reads")
    assert main(["fit", str(data), "--column", "v", "--out", str(data)]) == 2
    one_error(capsys, f"error: --out: {data} is the data file, which this run reads")
    rul = ["rul", str(data), "--column", "v", "--time-column", "t", "--threshold", "3"]
    assert main(rul + ["--json", str(data)]) == 2
    one_error(capsys, f"error: --json: {data} is the data file, which this run reads")
    same = tmp_path / "f.png"
    argv = ["forecast", str(model), str(data), "--horizon", "3", "--csv", str(same), "--plot"]
    assert main(argv + [str(same)]) == 2
    one_error(capsys, f"error: --plot and --csv name the same file {same}")
    assert data.read_bytes() == before and not same.exists()


def test_json_naming_a_folder_is_refused_before_anything_is_written(tmp_path, capsys):
    """--json out/ (a folder) passed the up-front check (Path() drops the '/'): the report was
    printed and the figure written before the record failed with exit 2."""
    data, _ = healthy_csv(tmp_path / "d.csv")
    png = tmp_path / "r.png"
    argv = ["rul", str(data), "--column", "v", "--time-column", "t", "--threshold", "3",
            "--paths", "100", "--plot", str(png), "--json", str(tmp_path / "new") + "/"]  # fmt: skip
    assert main(argv) == 2
    assert one_error(capsys, "names a folder, expected a file name") == ""
    assert not png.exists() and not (tmp_path / "new").exists()


def test_calibration_options_where_they_do_nothing_are_refused(tmp_path, capsys):
    """--calibration-out with a model file wrote no file and said nothing (exit 0); --workers
    or --calibrate-group without --calibrate were ignored alike."""
    data, _ = healthy_csv(tmp_path / "d.csv")
    out = tmp_path / "cal.json"
    with_model = ["rul", str(tmp_path / "none.pt"), str(data), "--threshold", "3"]
    assert main(with_model + ["--calibration-out", str(out)]) == 2
    one_error(capsys, "error: --calibration-out applies without a model file, with --calibrate")
    assert main(with_model + ["--workers", "2", "--calibrate-threshold", "protocol"]) == 2
    one_error(capsys, "error: --calibrate-threshold, --workers apply without a model file")
    base = ["rul", str(data), "--column", "v", "--time-column", "t", "--threshold", "3"]
    assert main(base + ["--workers", "2"]) == 2
    one_error(capsys, "error: --workers applies with --calibrate TABLE")
    assert main(base + ["--calibrate-group", "unit"]) == 2
    one_error(capsys, "error: --calibrate-group applies with --calibrate TABLE")
    assert not out.exists()


def test_a_workflow_command_restores_the_callers_thread_count(tmp_path, capsys):
    """main() in a caller's process left torch at one thread after any fit, forecast or rul."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        assert main(["rul", str(tmp_path / "none.csv"), "--column", "v", "--threshold", "3"]) == 2
        capsys.readouterr()
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)


def test_study_without_a_name_says_why_it_fails(capsys, monkeypatch):
    """'prognos study' listed the studies and exited 2 without a word on stderr."""
    toy = studies.Study("elm-stsckf", "000", "Toy", run=None)
    monkeypatch.setattr(studies, "discover_studies", lambda: {toy.name: toy})
    assert main(["study"]) == 2
    out = one_error(capsys, "error: study needs a NAME from the list above, or all")
    assert "elm-stsckf" in out
