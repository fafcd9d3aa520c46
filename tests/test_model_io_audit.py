"""Audit of the safe model files (``prognos_torch.io``, ``workflow.store``, ``workflow.fitted``).

References are independent of the code under test: files are edited through a re-implementation
of the documented format-2 layout (length, JSON header, tensor bytes, SHA-256 of the file with
its digest zeroed), so a tampered file still passes its checksum and reaches the checks behind
it; round trips compare against the in-memory model's own forecasts, bit for bit.
"""

from __future__ import annotations

import copy
import json
import os
import warnings

import numpy as np
import pytest
import torch
from test_model_file import _pack, _split  # the format-2 file by definition

from prognos_torch import io as pio
from prognos_torch.datasets.windows import MinMaxScaler
from prognos_torch.io import ModelFileError, atomic_write, load_model_file, save_model_file
from prognos_torch.workflow import fit_series, forecast, load_model, load_series, save_model
from prognos_torch.workflow.fitted import FittedModel


def _series(T=40, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 0.5
    x = 1.0 + 0.01 * t + 0.3 * np.sin(2 * np.pi * t / 12) + 0.03 * rng.standard_normal(T)
    return load_series(x)


def _rewrite(path, config=None, tensors=None):
    """Rewrite a saved workflow file with another configuration and/or tensors (through
    save_model_file, whose own checks these edits pass)."""
    mf = load_model_file(path)
    save_model_file(
        path,
        mf.config if config is None else config,
        mf.tensors if tensors is None else tensors,
        kind="prognos-workflow",
    )


@pytest.fixture(scope="module")
def models():
    s = _series()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return s, {name: fit_series(s, name, "closed-form", 2, holdout=0) for name in
                   ("elm", "lssvr", "anfis")}  # fmt: skip


# ------------------------------------------------------------------ round trips
@pytest.mark.parametrize("learner", ["elm", "lssvr", "anfis"])
@pytest.mark.parametrize("optimizer", [None, "closed-form", "ekf", "srukf", "imsrukf", "adam",
                                       "lbfgs"])  # fmt: skip
def test_round_trip_forecasts_bit_for_bit(tmp_path, learner, optimizer):
    s = _series()
    opts = {"adam": {"epochs": 3}, "lbfgs": {"epochs": 1, "max_iter": 3}}.get(optimizer)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = fit_series(s, learner, optimizer, 2, holdout=0.2, optimizer_options=opts)
        path = tmp_path / "m.pt"
        save_model(model, str(path))  # a str path ...

        class P:  # ... and any os.PathLike
            def __fspath__(self):
                return str(path)

        back = load_model(P(), map_location=torch.device("cpu"))
        a, b = forecast(model, s, 6), forecast(back, s, 6)
    assert type(back.learner) is type(model.learner) and back.config == model.config
    for k, v in model.learner.state_dict().items():
        w = back.learner.state_dict()[k]
        assert w.dtype == v.dtype and torch.equal(w, v)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.lower, b.lower)
    assert torch.equal(a.upper, b.upper)


# ------------------------------------------------------------------ io: configuration values
def test_numpy_scalars_in_a_configuration_are_written_as_numbers(tmp_path):
    """np.int64 / np.float32 / np.bool_ raised 'config[...] must be a JSON value, got int64'."""
    path = tmp_path / "f.st"
    cfg = {"n": np.int64(3), "x": np.float32(0.5), "b": np.bool_(True), "l": [np.int32(-2)],
           "d": {"y": np.float64(0.1)}}  # fmt: skip
    save_model_file(path, cfg, {})
    back = load_model_file(path).config
    assert back == {"n": 3, "x": 0.5, "b": True, "l": [-2], "d": {"y": 0.1}}
    assert [type(back[k]) for k in ("n", "x", "b")] == [int, float, bool]
    assert type(back["l"][0]) is int
    with pytest.raises(ValueError, match=r"config\['x'\] is nan; store non-finite"):
        save_model_file(path, {"x": np.float32("nan")}, {})
    with pytest.raises(ValueError, match=r"config\['y'\]\[0\] is inf"):
        save_model_file(path, {"y": [np.float64("inf")]}, {})
    assert load_model_file(path).config == back  # the refused saves left the file intact


def test_a_model_fitted_with_numpy_options_saves_and_loads(tmp_path):
    s = _series()
    model = fit_series(s, "elm", None, np.int64(2), holdout=0, seed=np.int64(1),
                       learner_options={"n_hidden": np.int64(7), "lam": np.float32(1e-6)})  # fmt: skip
    path = tmp_path / "m.pt"
    save_model(model, path)
    back = load_model(path)
    assert back.config["learner_options"]["n_hidden"] == 7
    assert back.config["learner_options"]["lam"] == float(np.float32(1e-6))
    assert torch.equal(forecast(model, s, 5).mean, forecast(back, s, 5).mean)


def test_non_finite_numbers_in_a_stored_configuration_are_refused(tmp_path, models):
    """json reads NaN/Infinity; such a file loaded, and the model could not be saved again."""
    s, fitted = models
    path = tmp_path / "m.pt"
    save_model(fitted["elm"], path)
    header, data = _split(path.read_bytes())
    cfg = json.loads(header["__metadata__"]["prognos.config"])
    cfg["series"]["t_train_end"] = float("nan")
    header["__metadata__"]["prognos.config"] = json.dumps(cfg)  # writes the bare word NaN
    path.write_bytes(_pack(header, data))
    with pytest.raises(ModelFileError, match=r"config\['series'\]\['t_train_end'\] is nan"):
        load_model_file(path)
    with pytest.raises(ModelFileError, match="not plain JSON"):
        load_model(path)


# ------------------------------------------------------------------ io: atomic writes
def test_atomic_write_refuses_a_folder_name_and_keeps_the_old_file(tmp_path, monkeypatch):
    """'out/' (a folder that does not exist) wrote a file named 'out'."""
    with pytest.raises(FileNotFoundError, match="output folder does not exist"):
        atomic_write(str(tmp_path / "out") + os.sep, b"data")
    assert os.listdir(tmp_path) == []
    target = tmp_path / "f.bin"
    atomic_write(target, b"old")

    def boom(fd):
        raise OSError("disk full")

    monkeypatch.setattr(pio.os, "fsync", boom)
    with pytest.raises(OSError, match="disk full"):
        atomic_write(str(target), b"new content")
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["f.bin"]


# ------------------------------------------------------------------ store: tampered files
def test_a_tensor_outside_the_learner_is_refused(tmp_path, models):
    """A tensor without the 'learner.' prefix was silently ignored."""
    path = tmp_path / "m.pt"
    save_model(models[1]["elm"], path)
    tensors = dict(load_model_file(path).tensors, junk=torch.zeros(2, dtype=torch.float64))
    _rewrite(path, tensors=tensors)
    with pytest.raises(ModelFileError, match=r"unexpected tensor\(s\) \['junk'\]"):
        load_model(path)


@pytest.mark.parametrize("learner", ["elm", "lssvr", "anfis"])
def test_non_finite_weights_are_refused_on_load_and_on_save(tmp_path, models, learner):
    """NaN weights loaded; the forecast then failed with 'init.mean contains non-finite'."""
    model = models[1][learner]
    path = tmp_path / "m.pt"
    save_model(model, path)
    tensors = load_model_file(path).tensors
    name = next(k for k, v in tensors.items() if v.is_floating_point() and v.numel() > 1)
    tensors[name] = tensors[name].clone()
    tensors[name].view(-1)[1] = float("nan")
    _rewrite(path, tensors=tensors)
    with pytest.raises(ModelFileError, match=f"tensor '{name}' holds NaN or inf"):
        load_model(path)
    bad = copy.deepcopy(model)
    with torch.no_grad():  # (state_dict's tensors share the module's storage)
        bad.learner.state_dict()[name[len("learner.") :]].view(-1)[1] = float("nan")
    fresh = tmp_path / "fresh.pt"
    with pytest.raises(ValueError, match=f"model.learner's '{name}' holds NaN or inf"):
        save_model(bad, fresh)
    assert not fresh.exists()


def test_state_dict_mismatches_name_the_key(tmp_path, models):
    """The message stopped at its first line: 'Error(s) in loading state_dict for ELM:'."""
    path = tmp_path / "m.pt"
    save_model(models[1]["elm"], path)
    good = load_model_file(path).tensors
    _rewrite(path, tensors={k: v for k, v in good.items() if k != "learner.n_seen"})
    with pytest.raises(ModelFileError, match=r'Missing key\(s\) in state_dict: "n_seen"'):
        load_model(path)
    _rewrite(path, tensors=dict(good, **{"learner.beta": good["learner.beta"][:-1]}))
    with pytest.raises(ModelFileError, match="size mismatch for beta"):
        load_model(path)
    _rewrite(path, tensors=dict(good, **{"learner.extra": torch.zeros(1, dtype=torch.float64)}))
    with pytest.raises(ModelFileError, match=r'Unexpected key\(s\) in state_dict: "extra"'):
        load_model(path)


def test_float32_learners_are_refused_not_silently_widened(tmp_path, models):
    """A float32 learner was saved and came back float64 (config 'dtype' says float64)."""
    s, fitted = models
    path = tmp_path / "m.pt"
    save_model(fitted["elm"], path)
    good = load_model_file(path).tensors
    model = fit_series(s, "elm", None, 2, holdout=0)
    model.learner.float()
    fresh = tmp_path / "f32.pt"
    with pytest.raises(TypeError, match=r"'learner\.a' is torch\.float32; .*float64"):
        save_model(model, fresh)
    assert not fresh.exists()
    _rewrite(path, tensors=dict(good, **{"learner.beta": good["learner.beta"].float()}))
    with pytest.raises(ModelFileError, match=r"'learner\.beta' is torch\.float32, the ELM holds"):
        load_model(path)
    _rewrite(path, tensors=dict(good, **{"learner.n_seen": good["learner.n_seen"].int()}))
    with pytest.raises(ModelFileError, match=r"'learner\.n_seen' is torch\.int32"):
        load_model(path)


def test_configured_sizes_are_checked_against_the_tensors_before_building(tmp_path, models):
    """An edited n_hidden / n_mfs / m made load_model build the learner first: 2**40 hidden
    units asked for terabytes (or the process was killed); an LS-SVR with flattened support
    vectors loaded and its forecast raised IndexError."""
    path = tmp_path / "m.pt"
    for learner, edit, pattern in (
        ("elm", {"learner_options": {"n_hidden": 2**40}},
         r"'learner\.a' has shape \[20, 2\]; the configuration gives \[n_hidden, m\] = "
         r"\[1099511627776, 2\]"),
        ("elm", {"m": 3}, r"'learner\.a' has shape \[20, 2\]; .* = \[20, 3\]"),
        ("anfis", {"m": 40}, r"'learner\.alpha' has shape \[1, 3, 4\]; .*\[1, 41, 2\*\*40\]"),
        ("anfis", {"learner_options": {"n_mfs": "2"}}, r"n_mfs='2'; expected a positive int"),
        ("lssvr", {"m": 5}, r"'learner\.support_vectors' has shape \[38, 2\]; .*m=5"),
    ):  # fmt: skip
        model = models[1][learner]
        save_model(model, path)
        cfg = json.loads(json.dumps(model.config))
        for k, v in edit.items():
            cfg[k] = dict(cfg[k], **v) if isinstance(v, dict) else v
        _rewrite(path, config=cfg)
        with pytest.raises(ModelFileError, match=pattern):
            load_model(path)
    save_model(models[1]["lssvr"], path)
    good = load_model_file(path).tensors
    sv = good["learner.support_vectors"]
    _rewrite(path, tensors=dict(good, **{"learner.support_vectors": sv.reshape(-1)}))
    with pytest.raises(ModelFileError, match=r"support_vectors' has shape \[76\]"):
        load_model(path)
    # one more coefficient than support vectors: the sizes agree on paper, a window does not
    alpha = torch.cat([good["learner.alpha"], torch.zeros(1, 1, dtype=torch.float64)])
    _rewrite(path, tensors=dict(good, **{"learner.alpha": alpha}))
    with pytest.raises(ModelFileError, match="does not match its configuration"):
        load_model(path)


def test_malformed_configuration_entries_are_named(tmp_path, models):
    """'series': [1] raised AttributeError; a seed of 2**70 said 'Overflow when unpacking long
    long'; a broken scaler entry was reported as a learner mismatch."""
    path = tmp_path / "m.pt"
    model = models[1]["elm"]
    for key, value, pattern in (
        ("series", [1], "configuration entry 'series' is missing or malformed"),
        ("seed", 2**70, r"configuration entry 'seed': seed must lie in \[-2\*\*63, 2\*\*64\)"),
        ("scaler", {"data_min": None, "data_max": 1.0, "feature_range": [0.0, 1.0]},
         r"configuration entry 'scaler' is malformed \(float\(\) argument"),
        ("scaler", {"data_max": 1.0, "feature_range": [0.0, 1.0]},
         r"configuration entry 'scaler' is malformed \(missing entry 'data_min'\)"),
    ):  # fmt: skip
        save_model(model, path)
        _rewrite(path, config=dict(json.loads(json.dumps(model.config)), **{key: value}))
        with pytest.raises(ModelFileError, match=pattern):
            load_model(path)


# ------------------------------------------------------------------ fitted record
def test_fitted_metrics_without_a_holdout_record():
    """config 'holdout': None (no holdout) raised AttributeError in .metrics."""
    scaler = MinMaxScaler((0.0, 1.0)).fit(torch.tensor([0.0, 1.0], dtype=torch.float64))
    lin = torch.nn.Linear(2, 1).double()
    assert FittedModel(lin, scaler, {"m": 2, "holdout": None}).metrics == {}
    assert FittedModel(lin, scaler, {"m": 2, "holdout": {"metrics": None}}).metrics == {}
    rec = {"m": 2, "holdout": {"n": 3, "metrics": {"rmse": 0.5}}}
    got = FittedModel(lin, scaler, rec).metrics
    assert got == {"rmse": 0.5} and got is not rec["holdout"]["metrics"]


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions and folder fsync")
def test_atomic_write_keeps_a_replaced_files_permissions_and_flushes_the_folder(
    tmp_path, monkeypatch
):
    """A replaced file got the default permissions (a 0600 secret became 0644 on the next
    save), and the folder entry of the rename was never flushed (lost on a power cut)."""
    target = tmp_path / "f.bin"
    target.write_bytes(b"old")
    os.chmod(target, 0o600)
    synced = []
    real = pio.os.fsync
    monkeypatch.setattr(pio.os, "fsync", lambda fd: synced.append(os.fstat(fd).st_mode) or real(fd))
    atomic_write(target, b"new")
    assert target.read_bytes() == b"new" and (target.stat().st_mode & 0o777) == 0o600
    import stat

    assert [stat.S_ISDIR(m) for m in synced] == [False, True]  # the file, then its folder
