"""The prognos command and the study result files."""

import json

import pytest
import torch

from prognos_torch.cli import main
from prognos_torch.studies import Study, StudyConfig, StudyResult, format_table, write_outputs


def test_format_table_mean_std_and_paper_column():
    res = StudyResult(
        rows=[
            {"run": 0, "method": "A", "MAE": 1.0, "time_s": 0.5},
            {"run": 1, "method": "A", "MAE": 3.0, "time_s": 0.5},
            {"run": 0, "method": "B", "MAE": 2.0, "time_s": 1.0},
        ],
        metrics=["MAE", "time_s"],
        paper={"A": {"MAE": 0.25}},
    )
    table = format_table(res)
    lines = table.splitlines()
    assert lines[0] == "| method | runs | MAE (ours) | MAE (paper) | time_s (ours) |"
    assert lines[2].startswith("| A | 2 | 2.0000 ± 1.4142 | 0.2500 |")  # std with ddof=1
    assert lines[3].startswith("| B | 1 | 2.0000 ± 0.0000 | — |")


def test_write_outputs_files(tmp_path):
    st = Study("toy", "000", "Toy", run=lambda cfg, out: None, default_runs=2)
    res = StudyResult(rows=[{"run": 0, "method": "A", "MAE": 1.0}], metrics=["MAE"], notes="n")
    text = write_outputs(st, StudyConfig(out=tmp_path), res, tmp_path, 0.1)
    assert "| A | 1 |" in text and (tmp_path / "table.md").read_text() == text
    assert (tmp_path / "results.csv").read_text().splitlines() == ["run,method,MAE", "0,A,1.0"]
    meta = json.loads((tmp_path / "run.json").read_text())
    assert meta["study"] == "toy" and "torch" in meta["versions"] and "machine" in meta
    # the CPU and its vector instruction set, which decide the rounding of a run
    assert meta["machine"]["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert "cpu" in meta["machine"]


@pytest.mark.parametrize(
    "argv",
    [["trainers/toy.py", "--quick"], ["/x/prognos_torch/__main__.py", "study", "toy", "--quick"]],
)
def test_run_json_command_is_repeatable(tmp_path, monkeypatch, argv):
    # the recorded command is the module form whatever the entry point, with the thread setting
    st = Study("toy", "000", "Toy", run=lambda cfg, out: None, default_runs=2)
    res = StudyResult(rows=[{"run": 0, "method": "A", "MAE": 1.0}], metrics=["MAE"])
    monkeypatch.setattr("sys.argv", argv)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    write_outputs(st, StudyConfig(out=tmp_path), res, tmp_path, 0.1)
    meta = json.loads((tmp_path / "run.json").read_text())
    assert meta["command"] == "OMP_NUM_THREADS=1 python -m prognos_torch study toy --quick"


def test_bad_study_options(capsys):
    assert main(["study", "no-such-study"]) == 2
    err = capsys.readouterr().err
    assert "unknown study 'no-such-study'; valid:" in err
    with pytest.raises(ValueError, match="runs must be a positive int"):
        StudyConfig(runs=0)
    with pytest.raises(ValueError, match="device must be 'cpu' or 'cuda'"):
        StudyConfig(device="tpu")
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            StudyConfig(device="cuda")
        assert main(["study", "no-such-study", "--device", "cuda"]) == 2
        assert "CUDA is not available" in capsys.readouterr().err
    assert main(["study", "no-such-study", "--runs", "0"]) == 2
    assert "runs must be a positive int" in capsys.readouterr().err
    assert main(["study", "--list"]) == 0
    assert main(["study", "elm-stsckf", "--threads", "0"]) == 2
    assert "--threads must be a positive integer, got 0" in capsys.readouterr().err


def test_study_runs_with_the_requested_threads_and_restores_the_callers(monkeypatch, capsys):
    import torch

    import prognos_torch.studies as studies_mod

    seen = []
    monkeypatch.setattr(
        studies_mod, "run_study", lambda st, cfg: seen.append(torch.get_num_threads()) or (0, "")
    )
    before = torch.get_num_threads()
    assert main(["study", "elm-stsckf"]) == 0 and seen == [1]  # default: one thread
    assert main(["study", "elm-stsckf", "--threads", "2"]) == 0 and seen == [1, 2]
    assert torch.get_num_threads() == before


def test_python_m_prognos_torch_lists_the_studies():
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "prognos_torch", "study", "--list"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "elm-stsckf" in out and "forecaster-matrix" in out


def test_no_trainer_imports_the_cli():
    # the command line drives the studies (cli -> studies -> trainers); an import of the cli in
    # a trainer, even a lazy one under ``if __name__ == "__main__"``, would close a loop
    import ast

    from prognos_torch.studies import trainers_dir

    scripts = sorted(trainers_dir().glob("*.py"))
    assert len(scripts) >= 6
    for path in scripts:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            assert not any(n.startswith("prognos_torch.cli") for n in names), path.name


def test_run_jobs_timed_and_load_trainer(tmp_path):
    from prognos_torch.studies import load_trainer, run_jobs, timed

    order = []
    jobs = {("a", 1): lambda: order.append("a") or 1, "b": lambda: order.append("b") or 2}
    assert run_jobs(jobs, desc="t", progress=False) == {("a", 1): 1, "b": 2}
    assert order == ["a", "b"]
    out, secs = timed(sum, [1, 2, 3])
    assert out == 6 and secs >= 0.0
    script = tmp_path / "toy_study.py"
    script.write_text(
        "from prognos_torch.studies import Study\nSTUDY = Study('toy', '000', 'T', run=None)\n"
    )
    assert load_trainer(script).STUDY.name == "toy"
    with pytest.raises(FileNotFoundError, match="no study script"):
        load_trainer(tmp_path / "missing.py")
