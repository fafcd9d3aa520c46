"""The bad-input cases of ``docs/bad_input.md``: each gives a clear one-line error or the
documented behaviour.

References are independent: the training range and the extrapolation distance recomputed with
NumPy from the series and the model's scaler, exit codes and stderr lines read as a user would.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from prognos_torch.cli import main
from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import forecast as filter_forecast
from prognos_torch.filters import make_filter, run, sckf
from prognos_torch.workflow import fit_series, forecast, load_series, rul, save_model
from prognos_torch.workflow.extrapolation import ExtrapolationWarning

F64 = torch.float64


def _values(T=80, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 0.5
    return t, 1.0 + 0.01 * t + 0.3 * np.sin(2 * np.pi * t / 12) + 0.03 * rng.standard_normal(T)


def _csv(path: Path, t, x) -> Path:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "hi"])
        for a, b in zip(t, x):
            w.writerow([repr(float(a)), repr(float(b))])
    return path


def _linear_model():
    eye = torch.eye(2, dtype=F64)
    return StateSpaceModel(
        f=lambda x, u, k: x,
        h=lambda x, u, k: x[..., :1],
        state_dim=2,
        obs_dim=1,
        chol_Q=0.1 * eye,
        chol_R=eye[:1, :1],
    )


def test_fit_refuses_values_whose_squares_overflow_before_any_output(tmp_path, capsys):
    t, x = _values()
    data = _csv(tmp_path / "huge.csv", t, x * 1e300)
    out = tmp_path / "m.pt"
    argv = ["fit", str(data), "--column", "hi", "--time-column", "t", "--learner", "elm"]
    assert main(argv + ["-m", "3", "--out", str(out)]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""  # refused before the report
    assert cap.err.count("\n") == 1 and cap.err.startswith("error: ")
    assert "line 2: value 1.00" in cap.err and "exceeds 1e+150 in magnitude" in cap.err
    assert not out.exists()
    # at the limit's scale the whole workflow runs and every score is finite
    big = _csv(tmp_path / "big.csv", t, x * 1e149)
    argv[1] = str(big)
    assert main(argv + ["-m", "3", "--out", str(out)]) == 0
    report = capsys.readouterr().out
    assert "inf" not in report and "nan" not in report
    with pytest.raises(ValueError, match="index 2: value 1e\\+200"):
        load_series([1.0, 2.0, 1e200])


def test_rul_exit_codes_are_consistent_and_the_plot_is_written(tmp_path, capsys):
    t, x = _values(120)
    data = _csv(tmp_path / "d.csv", t, x)
    model = tmp_path / "m.pt"
    fit = ["fit", str(data), "--column", "hi", "--time-column", "t", "--learner", "elm"]
    assert main(fit + ["-m", "3", "--out", str(model)]) == 0
    capsys.readouterr()
    png = tmp_path / "rul.png"
    base = ["rul", str(model), str(data), "--filter", "pf", "--particles", "200", "--plot"]
    # partly censored: some paths cross within the horizon, some do not
    assert main(base + [str(png), "--threshold", "1.4", "--horizon", "10"]) == 3
    cap = capsys.readouterr()
    (line,) = cap.err.strip().splitlines()
    assert line.startswith("censored RUL: ") and "% of the predicted paths do not reach" in line
    assert "the mean is withheld" in line
    assert "figure written to" in cap.out and png.read_bytes()[:4] == b"\x89PNG"
    lines = {ln.split("  ")[0]: ln for ln in cap.out.splitlines()}
    p = float(lines["P(threshold reached within horizon)"].split()[-1])
    assert 0 < p < 1
    # nothing censored: exit 0, the mean is reported
    png.unlink()
    assert main(base + [str(png), "--threshold", "1.4", "--horizon", "100"]) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and png.exists()
    mean_line = next(ln for ln in cap.out.splitlines() if ln.startswith("mean RUL"))
    assert "n/a" not in mean_line
    with pytest.raises(SystemExit):
        main(["rul", "--help"])
    assert "3 censored\n  RUL (rul with a model file: part or all of the distribution" in (
        capsys.readouterr().out
    )


def test_forecast_far_outside_the_training_range_warns_and_widens(tmp_path, capsys):
    t, x = _values()
    s = load_series(x, time=t)
    model = fit_series(s, "anfis", None, 3, holdout=0, seed=1)
    far = x.copy()
    far[-10:] += 1e6  # the learner saturates: without widening the band was ~1e-6 wide
    s_far = load_series(far, time=t)
    with pytest.warns(ExtrapolationWarning, match="outside the model's training range"):
        fc = forecast(model, s_far, 8)
    lo, hi = float(model.scaler.data_min), float(model.scaler.data_max)
    d1 = max(0.0, float(np.max(far[-3:])) - hi, lo - float(np.min(far[-3:])))
    assert fc.extrapolation[0].item() == pytest.approx(d1, rel=1e-12)
    z = math.sqrt(2) * float(torch.special.erfinv(torch.tensor(0.95, dtype=F64)))
    assert bool((fc.upper - fc.mean >= z * fc.extrapolation * (1 - 1e-12)).all())
    assert bool((fc.mean - fc.lower >= z * fc.extrapolation * (1 - 1e-12)).all())
    assert bool((fc.std >= fc.extrapolation).all())
    assert float(fc.upper[0] - fc.lower[0]) >= 2 * z * d1 * (1 - 1e-12)
    # inside the range: no warning, no widening
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", ExtrapolationWarning)
        inside = forecast(model, s, 8, filter="ekf")
    assert inside.extrapolation is not None
    with pytest.warns(ExtrapolationWarning, match="RUL starts from"):
        rul(model, s_far, 2e6, horizon=20, filter="sckf", n_particles=50)
    # the command line: exit 0 and one warning line
    path = tmp_path / "m.pt"
    save_model(model, path)
    far_csv = _csv(tmp_path / "far.csv", t, far)
    assert main(["forecast", str(path), str(far_csv), "--column", "hi", "--horizon", "5"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: the forecast lies outside")


def test_workflow_functions_name_a_path_given_as_model(tmp_path):
    t, x = _values()
    s = load_series(x, time=t)
    with pytest.raises(TypeError, match=r"got str; load the file first: load_model\('model.pt'\)"):
        forecast("model.pt", s, 5)
    with pytest.raises(TypeError, match="model must be a FittedModel"):
        rul(tmp_path / "m.pt", s, 2.0)


def test_load_series_names_the_source_type():
    for bad in (123, 1.5, None, b"x.csv"):
        with pytest.raises(TypeError, match="source must be a CSV path or a 1-D array"):
            load_series(bad, "x")


def test_gaussian_belief_checks_n_at_construction_and_blames_both():
    with pytest.raises(ValueError, match=r"mean \(3,\) and chol \(2, 2\) disagree on n"):
        GaussianBelief(torch.zeros(3, dtype=F64), torch.eye(2, dtype=F64))
    with pytest.raises(ValueError, match="chol must be square"):
        GaussianBelief(torch.zeros(3, dtype=F64), torch.zeros(3, 2, dtype=F64))
    with pytest.raises(TypeError, match="needs torch.Tensor"):
        GaussianBelief([0.0, 1.0], torch.eye(2, dtype=F64))
    GaussianBelief(torch.zeros(4, 2, dtype=F64), torch.eye(2, dtype=F64).expand(4, 2, 2))


def test_tuple_beliefs_and_uncalled_factories_are_named():
    model = _linear_model()
    b = GaussianBelief(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    ys = torch.zeros(4, 1, dtype=F64)
    with pytest.raises(TypeError, match=r"init must be a GaussianBelief, got a tuple.*wrap it"):
        run(sckf(), model, (b.mean, b.chol), ys)
    with pytest.raises(TypeError, match=r"got the function sckf itself: call it, e\.g\. sckf\(\)"):
        run(sckf, model, b, ys)
    with pytest.raises(TypeError, match="call it"):
        filter_forecast(sckf, model, b, 3)
    with pytest.raises(TypeError, match="belief must be a GaussianBelief, got a tuple"):
        make_filter("ukf").init(model, (b.mean, b.chol))
    with pytest.raises(TypeError, match=r"state must be a FilterState.*filter\.init"):
        sckf().step(model, b, ys[0])
    from prognos_torch.filters import make_particle_filter

    with pytest.raises(TypeError, match="got a list of two items"):
        make_particle_filter("pf", num_particles=10).init(
            model, [b.mean, b.chol], generator=torch.Generator().manual_seed(0)
        )


def test_cli_out_folder_and_a_csv_given_as_model(tmp_path, capsys):
    t, x = _values()
    data = _csv(tmp_path / "d.csv", t, x)
    fit = ["fit", str(data), "--column", "hi", "--learner", "elm", "-m", "3", "--out"]
    assert main(fit + [str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: --out: {tmp_path} is a folder, expected a file name"
    assert main(["forecast", str(data), str(data), "--horizon", "3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {data} is not a prognos model file: it is neither a safetensors "
                   "file nor a prognos model file of format 1"]  # fmt: skip


@pytest.mark.parametrize(
    "values, word",
    [
        (np.r_[np.zeros(30, bool), np.ones(30, bool)], "booleans"),
        (torch.ones(60, dtype=torch.bool), "booleans"),
        ([True] * 60, "booleans"),
        (np.linspace(1, 2, 60) + 0.5j, "complex"),
        (torch.linspace(1, 2, 60, dtype=torch.complex128), "complex"),
    ],
)
def test_booleans_and_complex_values_are_refused_not_read(values, word):
    # read as numbers they would become 0/1 or lose their imaginary part without a word
    from prognos_torch.workflow import prognose

    with pytest.raises(TypeError, match=rf"^series must be (real )?numbers, got {word}"):
        prognose(values, 3.0)
    with pytest.raises(TypeError, match=rf"^source must be (real )?numbers, got {word}"):
        load_series(values)
    with pytest.raises(TypeError, match=rf"^time must be (real )?numbers, got {word}"):
        prognose(np.linspace(1, 2, 60), 3.0, time=values)


def test_a_fleet_table_refuses_complex_values_as_it_does_booleans():
    from prognos_torch.fleet import fleet_rul

    table = {"asset": ["a"] * 40, "t": list(range(40)), "value": [1.0 + 0.5j] * 40}
    with pytest.raises(ValueError, match="value"):
        fleet_rul(table, 3.0, group_by="asset", column="value", time_column="t")


def test_a_seed_that_is_not_an_int_is_a_type_error_naming_it(tmp_path):
    from prognos_torch.workflow import calibrate_rul, prognose

    t, x = _values()
    s = load_series(x, time=t)
    for bad in ("a", 1.5, True, None):
        with pytest.raises(TypeError, match=rf"^seed must be an int, got {bad!r}$"):
            prognose(x, 3.0, seed=bad)
        with pytest.raises(TypeError, match="^seed must be an int"):
            fit_series(s, learner="elm", seed=bad)
        with pytest.raises(TypeError, match="^seed must be an int"):
            calibrate_rul({"a": (t, x)}, threshold=3.0, seed=bad)
    model = fit_series(s, learner="elm", m=2, seed=np.int64(3))  # NumPy's ints are seeds
    assert model.config["seed"] == 3 and isinstance(model.config["seed"], int)
    for bad in ("a", 2.0):
        with pytest.raises(TypeError, match="^seed must be an int"):
            forecast(model, s, 5, seed=bad)
        with pytest.raises(TypeError, match="^seed must be an int"):
            rul(model, s, 3.0, seed=bad)


def test_prognose_refuses_values_whose_squares_overflow_or_underflow_as_load_series_does():
    # they gave "threshold 3e+200 lies inside the healthy band [-inf, inf]"
    from prognos_torch.workflow import prognose

    t, x = _values()
    msg = (
        r"^index 0: value 1.\d+e\+200 of 'series' exceeds 1e\+150 in magnitude; .* divide by 1e200"
    )
    with pytest.raises(ValueError, match=msg):
        prognose(x * 1e200, 3e200)
    with pytest.raises(ValueError, match=msg):
        load_series(x * 1e200)
    # values so small that the squares of their spread underflow: a band of zero width
    tiny = r"^the values of 'series' are at most 1.\d+e-160 in magnitude, below 1e-150: .* 1e160\)$"
    with pytest.raises(ValueError, match=tiny):
        prognose(x * 1e-160, 3e-160)
    with pytest.raises(ValueError, match=tiny):
        load_series(x * 1e-160)
    assert prognose(x * 1e-140, 3e-140).status == prognose(x, 3.0).status  # scale-free above
    assert float(load_series(np.zeros(5)).values.abs().max()) == 0.0  # zeros: not this error


def test_numpy_scalars_are_taken_where_a_number_is_asked_and_bools_are_not():
    """Counts from NumPy (``np.arange``, a table's column) were refused by local
    ``isinstance(v, int)`` checks (embedding dimension, LLE sizes, IMS test and bearing,
    moving-median window, fit epochs, particle count), and float32 scalars by
    ``isinstance(v, (int, float))`` (a constant fading factor: a TypeError; the protocol's
    threshold); EM's ``iterations`` and the likelihood fit's ``steps`` took ``True`` as 1."""
    from prognos_torch.datasets import bearing_channels, embed, lle_fit
    from prognos_torch.optim.em import em_linear_gaussian
    from prognos_torch.prognosis.onset import moving_median

    x = torch.linspace(0.0, 1.0, 40, dtype=torch.float64) ** 2
    for a, b in zip(embed(x, np.int64(3)), embed(x, 3)):
        assert torch.equal(a, b)
    assert bearing_channels(np.int64(1), np.int32(3)) == bearing_channels(1, 3) == (5, 6)
    assert torch.equal(moving_median(x, np.int64(5)), moving_median(x, 5))
    X = torch.stack([torch.cos(x * 6), torch.sin(x * 6), x], -1)
    assert torch.equal(lle_fit(X, np.int64(1), np.int16(6)).embedding, lle_fit(X, 1, 6).embedding)
    for bad in (True, np.bool_(True), 2.0):
        with pytest.raises(ValueError, match="embedding dimension m must be a positive int"):
            embed(x, bad)
    eye = torch.eye(1, dtype=torch.float64)
    init = GaussianBelief(torch.zeros(1, dtype=torch.float64), eye)
    with pytest.raises(ValueError, match="iterations must be a non-negative int, got True"):
        em_linear_gaussian(eye, eye, eye, eye, init, x[:, None], iterations=True)
    # NumPy reals (a float32 array's max, say) where a number is asked
    from prognos_torch.filters import ekf, sir
    from prognos_torch.prognosis.protocol import known_threshold_protocol

    assert ekf(fading=np.float32(1.25)).fading == 1.25 and ekf(fading=1.25) == ekf(fading=1.25)
    pf = sir(np.int64(10), resample_threshold=np.float32(0.5))
    assert (pf.num_particles, pf.resample_threshold) == (10, 0.5)
    t = torch.arange(300.0, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    y = 0.1 + 0.01 * torch.randn(300, generator=g, dtype=torch.float64)
    y = y + torch.where(t > 150, 0.02 * torch.exp((t - 150) / 30), torch.zeros_like(t))
    a = known_threshold_protocol(t, y, threshold=np.float32(1.5))
    b = known_threshold_protocol(t, y, threshold=float(np.float32(1.5)))
    assert a.valid and a.t_eol == b.t_eol and torch.equal(a.times, b.times)
    fit = em_linear_gaussian(eye, eye, eye, eye, init, x[:, None], iterations=np.int64(2))
    assert torch.equal(fit.A, em_linear_gaussian(eye, eye, eye, eye, init, x[:, None],
                                                 iterations=2).A)  # fmt: skip
