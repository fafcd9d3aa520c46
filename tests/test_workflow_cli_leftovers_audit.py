"""``prognos fit`` options given in float notation or twice, ``calibrate_rul``'s settings checked
before any replay, and ``forecast``/``rul`` on a series whose first value is missing, against
references written here (a plain Kalman filter, the model file of the integer option)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _ar2_reference import ar2_kalman_forecast, ar2_model
from _cli_helpers import healthy_csv, one_error
from _prognosis_helpers import degradation_history

import prognos_torch.workflow.calibrate as calibrate_mod
from prognos_torch.cli import main
from prognos_torch.workflow import Series, calibrate_rul, forecast, load_model, rul

F64 = torch.float64


# ------------------------------------------------------------------------------ cli.py
def test_an_integer_learner_option_in_float_notation_is_that_integer(tmp_path, capsys):
    """n_hidden=3e1 was read as the float 30.0 and refused ('must be an int (like 20), got
    30.0'), though --holdout 1e3 is a count; it is the model of n_hidden=30. A value that is
    not whole stays refused."""
    data, _ = healthy_csv(tmp_path / "d.csv", slope=0.01)
    fit = ["fit", str(data), "--column", "v", "--learner", "elm", "--embedding", "2",
           "--holdout", "0"]  # fmt: skip
    a, b = tmp_path / "a.pt", tmp_path / "b.pt"
    assert main(fit + ["--learner-option", "n_hidden=3e1", "--out", str(a)]) == 0
    assert main(fit + ["--learner-option", "n_hidden=30", "--out", str(b)]) == 0
    ma, mb = load_model(a), load_model(b)
    assert ma.config["learner_options"]["n_hidden"] == 30
    assert type(ma.config["learner_options"]["n_hidden"]) is int
    for pa, pb in zip(ma.learner.state_dict().values(), mb.learner.state_dict().values()):
        assert torch.equal(pa, pb)
    capsys.readouterr()
    bad = tmp_path / "c.pt"
    assert main(fit + ["--learner-option", "n_hidden=30.5", "--out", str(bad)]) == 2
    one_error(capsys, "elm learner option n_hidden must be an int (like 20), got 30.5")
    assert not bad.exists()


def test_an_option_and_its_key_value_twin_together_are_refused(tmp_path, capsys):
    """--epochs 1 replaced --optimizer-option epochs=2 (and --max-support 10 replaced
    --learner-option max_support=20) without a word."""
    data, _ = healthy_csv(tmp_path / "d.csv", slope=0.01)
    out = tmp_path / "m.pt"
    fit = ["fit", str(data), "--column", "v", "--embedding", "2", "--out", str(out)]
    assert main(fit + ["--learner", "elm", "--optimizer", "adam", "--epochs", "1",
                       "--optimizer-option", "epochs=2"]) == 2  # fmt: skip
    one_error(capsys, "error: --epochs and --optimizer-option epochs=2 both set epochs")
    assert main(fit + ["--learner", "lssvr", "--max-support", "10", "--learner-option",
                       "max_support=20"]) == 2  # fmt: skip
    one_error(capsys, "error: --max-support and --learner-option max_support=20 both set")
    assert not out.exists()


def test_a_bad_seed_names_the_seed_option(tmp_path, capsys):
    """'error: seed must lie in ...' named the Python argument, not --seed."""
    data, _ = healthy_csv(tmp_path / "d.csv", slope=0.01)
    assert main(["fit", str(data), "--column", "v", "--out", str(tmp_path / "m.pt"),
                 "--seed", str(2**70)]) == 2  # fmt: skip
    one_error(capsys, "error: --seed: seed must lie in [-2**63, 2**64)")
    assert main(["rul", str(data), "--column", "v", "--time-column", "t", "--threshold", "3",
                 "--seed", "1,1"]) == 2  # fmt: skip
    one_error(capsys, "error: --seed: seed names a seed twice")


# ------------------------------------------------------------------------------ calibrate.py


def test_calibrate_rul_refuses_an_unknown_setting_before_any_replay(monkeypatch):
    """n_path=500 (for n_paths) reached prognose only in the first replay, after every
    history's protocol; a stand-in for the replays shows none runs now."""
    calls = []
    monkeypatch.setattr(calibrate_mod, "_predict", lambda *a: calls.append(a))
    h = {"a": degradation_history(0), "b": degradation_history(1)}
    for bad, names in (({"n_path": 500}, "'n_path'"), ({"series": 1, "zz": 2}, "'series', 'zz'")):
        with pytest.raises(TypeError, match="unexpected keyword argument") as exc:
            calibrate_rul(h, threshold=5.0, **bad)
        text = str(exc.value)
        assert names in text and "n_paths" in text and "method" in text
        for own in ("seed", "direction", "time,", "at,"):  # (calibrate_rul's own)
            assert f" {own}" not in text.split("passes on:")[1]
    assert not calls


# ------------------------------------------------------------------------------ predict.py
def test_a_missing_first_value_starts_the_filter_at_the_first_complete_window():
    """x[0] missing and filter_steps >= T - m (the default 100 on 10 values): 'has no 2
    consecutive observed values up to row 1 ... or filter more steps', though rows 1-9 are
    complete (and more steps cannot help); the filter starts from rows 1-2. The same where no
    complete window lies before the one filter_steps=3 asks (rows 5-6): rows 7-8 start it."""
    sigma, H = 0.04, 4
    model, x = ar2_model(sigma)
    lo, span = 1.0, 2.3
    for missing, steps, start in (((0,), 100, 1), ((0, 2, 4, 6), 3, 7)):
        xn = x.clone()
        xn[list(missing)] = math.nan
        means, stds = ar2_kalman_forecast(((xn - lo) / span).numpy(), start, H, sigma)
        fc = forecast(model, Series(xn), H, filter="sckf", filter_steps=steps)
        np.testing.assert_allclose(fc.mean.numpy(), lo + span * means, rtol=0, atol=1e-12)
        np.testing.assert_allclose(fc.std.numpy(), span * stds, rtol=0, atol=1e-12)
    xn = x.clone()
    xn[0] = math.nan
    r = rul(model, Series(xn), 2.0, direction="below", filter="sckf", n_particles=20, horizon=3)
    assert r.paths.shape == (20, 3) and bool(torch.isfinite(r.paths).all())
    none = x.clone()
    none[::2] = math.nan  # no two consecutive values: refused, without the hint
    with pytest.raises(ValueError, match="has no 2 consecutive observed values") as exc:
        forecast(model, Series(none), H)
    assert "filter more steps" not in str(exc.value)


def test_rul_quantile_refuses_bool_and_text_and_takes_numpy_reals():
    """RULResult.quantile(True) was read as q = 1 (the largest RUL), '0.5' and None failed
    inside torch ('new(): invalid data type')."""
    model, x = ar2_model()
    r = rul(model, Series(x), 2.5, direction="below", filter="sckf", n_particles=20, horizon=30)
    q = r.quantile(0.5)
    assert math.isfinite(float(q))
    assert torch.equal(r.quantile(np.float32(0.5)), q)
    assert torch.equal(r.quantile(np.array([0.5])), q.reshape(1))
    for bad in (True, np.bool_(True), "0.5", None, [0.5, True], torch.tensor(True)):
        with pytest.raises(ValueError, match="q must be a probability"):
            r.quantile(bad)


# ------------------------------------------------------------------------- model.py
def test_an_lbfgs_max_iter_that_is_not_a_positive_int_is_refused(tmp_path, capsys):
    """LBFGS with max_iter=0 took no iteration and the fit reported success (exit 0)."""
    data, _ = healthy_csv(tmp_path / "d.csv", slope=0.01)
    for bad in ("0", "-2"):
        code = main(["fit", str(data), "--column", "v", "--time-column", "t", "--learner",
                     "elm", "--optimizer", "lbfgs", "--embedding", "2", "--optimizer-option",
                     f"max_iter={bad}", "--out", str(tmp_path / "m.pt")])  # fmt: skip
        assert code == 2
        one_error(capsys, f"lbfgs optimizer option max_iter must be a positive int, got {bad}")
        assert not (tmp_path / "m.pt").exists()
