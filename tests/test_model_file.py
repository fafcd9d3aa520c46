"""Model files: the safetensors container (format 2), format-1 files, and every refusal.

References are independent: the ``safetensors`` package (test-only) reads the files; the
checksum and the format-1 layout are re-implemented here from their documented definitions;
crafted files would run code if they were ever unpickled.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import pickle
import struct

import numpy as np
import pytest
import torch

from prognos_torch import __version__
from prognos_torch.io import (
    FORMAT_VERSION,
    MAGIC,
    ModelFileError,
    load_model_file,
    save_model_file,
    versions_compatible,
)
from prognos_torch.workflow import fit_series, forecast, load_model, load_series, save_model

safetensors = pytest.importorskip("safetensors")
from safetensors import safe_open  # noqa: E402
from safetensors.torch import load_file, save_file  # noqa: E402

U64 = struct.Struct("<Q")
DIGEST = "prognos.sha256"


def _series(T=40, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 0.5
    return 1.0 + 0.01 * t + 0.3 * np.sin(2 * np.pi * t / 12) + 0.03 * rng.standard_normal(T)


def _tensors():
    return {
        "f64": torch.tensor([[1.0, -2.5e-300], [math.pi, 0.1]], dtype=torch.float64),
        "f32": torch.tensor([0.1, 2.0], dtype=torch.float32),
        "i64": torch.tensor([1, -(2**60)], dtype=torch.int64),
        "i32": torch.tensor([[7]], dtype=torch.int32),
        "b": torch.tensor([True, False, True]),
        "empty": torch.zeros(0, 3, dtype=torch.float64),
        "scalar": torch.tensor(2.5, dtype=torch.float64),
    }


# ----------------------------------------------------------------- format 2 by definition
def _split(raw: bytes):
    (n,) = U64.unpack(raw[:8])
    return json.loads(raw[8 : 8 + n]), raw[8 + n :]


def _pack(header: dict, data: bytes) -> bytes:
    """A format-2 file with a valid checksum, from the module's definition: SHA-256 of the
    whole file with the digest's 64 hex digits set to zeros (no digest: none is written)."""
    meta = header.get("__metadata__", {})
    if DIGEST in meta:
        meta[DIGEST] = "0" * 64
    head = json.dumps(header, separators=(",", ":")).encode()
    head += b" " * (-(len(head) + 8) % 8)
    digest = hashlib.sha256(U64.pack(len(head)) + head + data).hexdigest()
    head = head.replace(b'"' + b"0" * 64 + b'"', b'"' + digest.encode() + b'"')
    return U64.pack(len(head)) + head + data


def _edit(path, header_edit=None, data_edit=None):
    header, data = _split(path.read_bytes())
    if header_edit:
        header_edit(header)
    if data_edit:
        data = data_edit(data)
    path.write_bytes(_pack(header, data))


def _edit_config(header, **changes):
    meta = header["__metadata__"]
    cfg = json.loads(meta["prognos.config"])
    cfg.update(changes)
    meta["prognos.config"] = json.dumps(cfg)


# ----------------------------------------------------------------- format 1 (test-only writer)
def _write_format1(path, config, tensors, kind, version=__version__, fmt=1):
    """The format-1 layout of prognos_torch 0.1.0: preamble (magic, version, body length,
    SHA-256 of the body), then header length, JSON header, tensor bytes."""
    entries, chunks, offset = [], [], 0
    names = {torch.float64: "float64", torch.float32: "float32", torch.int64: "int64"}
    for name, t in tensors.items():
        raw = t.numpy().astype(t.numpy().dtype.newbyteorder("<")).tobytes()
        entries.append(
            {
                "name": name,
                "dtype": names[t.dtype],
                "shape": list(t.shape),
                "offset": offset,
                "nbytes": len(raw),
            }
        )
        chunks.append(raw)
        offset += len(raw)
    header = {
        "library": "prognos_torch",
        "library_version": version,
        "kind": kind,
        "config": config,
        "tensors": entries,
    }
    head = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
    body = U64.pack(len(head)) + head + b"".join(chunks)
    pre = struct.pack("<12sIQ32s", MAGIC, fmt, len(body), hashlib.sha256(body).digest())
    path.write_bytes(pre + body)


class _Evil:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (exec, (f"open({self.marker!r}, 'w').close()",))


# --------------------------------------------------------------------------- tests
def test_file_is_safetensors_and_round_trips_exactly(tmp_path):
    tensors = _tensors()
    cfg = {"a": 0.1, "b": [1, 2.5e-17, None, True], "c": {"d": "x"}, "zeros": "0" * 64}
    path = tmp_path / "f.safetensors"
    save_model_file(path, cfg, tensors, kind="k")
    raw = path.read_bytes()
    (n,) = U64.unpack(raw[:8])
    assert (8 + n) % 8 == 0 and raw[8:9] == b"{"
    with safe_open(str(path), framework="pt") as f:
        assert sorted(f.keys()) == sorted(tensors)
        for k, v in tensors.items():
            got = f.get_tensor(k)
            assert got.dtype == v.dtype and torch.equal(got, v)
        meta = f.metadata()
    assert json.loads(meta["prognos.config"]) == cfg
    assert meta["prognos.kind"] == "k" and meta["prognos.library_version"] == __version__
    assert meta["prognos.format_version"] == str(FORMAT_VERSION) == "2"
    assert all(torch.equal(load_file(str(path))[k], v) for k, v in tensors.items())
    mf = load_model_file(path, kind="k")
    assert mf.config == cfg and mf.library_version == __version__ and mf.format_version == 2
    for k, v in tensors.items():
        assert mf.tensors[k].dtype == v.dtype and torch.equal(mf.tensors[k], v)
    with pytest.raises(ModelFileError, match="holds a 'k', expected a 'other'"):
        load_model_file(path, kind="other")
    with pytest.raises(ValueError, match="non-finite numbers"):
        save_model_file(path, {"x": float("nan")}, {})
    with pytest.raises(TypeError, match="allowed"):
        save_model_file(path, {}, {"c": torch.zeros(2, dtype=torch.complex128)})
    with pytest.raises(TypeError, match="__metadata__"):
        save_model_file(path, {}, {"__metadata__": torch.zeros(2)})
    assert load_model_file(path).config == cfg  # the failed saves left the file intact
    assert sorted(os.listdir(tmp_path)) == ["f.safetensors"]


def test_workflow_model_file_opens_with_safetensors_and_forecasts_identically(tmp_path):
    s = load_series(_series())
    model = fit_series(s, "elm", None, 2, holdout=0)
    path = tmp_path / "model.pt"
    save_model(model, path)
    with safe_open(str(path), framework="pt") as f:
        keys = set(f.keys())
        assert json.loads(f.metadata()["prognos.config"]) == model.config
    assert keys == {"learner." + k for k in model.learner.state_dict()}
    back = load_model(path)
    a, b = forecast(model, s, 10), forecast(back, s, 10)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.upper, b.upper)


def test_model_file_refuses_tampering_truncation_versions_and_pickles(tmp_path):
    s = load_series(_series())
    model = fit_series(s, "elm", None, 2, holdout=0)
    good = tmp_path / "good.pt"
    save_model(model, good)
    raw = good.read_bytes()
    bad = tmp_path / "bad.pt"

    def refused(content, pattern):
        bad.write_bytes(content)
        with pytest.raises(ModelFileError, match=pattern):
            load_model(bad)

    flipped = bytearray(raw)
    flipped[-3] ^= 0x01  # one bit of the tensor bytes
    refused(bytes(flipped), "failed its SHA-256 check")
    pos = raw.index(b'\\"m\\":2')  # a configuration value inside the header
    refused(raw[: pos + 5] + b"3" + raw[pos + 6 :], "failed its SHA-256 check")
    refused(raw[:-100], "is truncated")
    refused(raw[:30], "is truncated")
    refused(raw[:5], "not a prognos model file")
    refused(raw + b"\0" * 8, "unexpected bytes after the tensor data")

    for edit, pattern in (
        (
            lambda h: h["__metadata__"].update({"prognos.library_version": "9.0.0"}),
            r"written by prognos_torch 9.0.0, which is incompatible",
        ),
        (lambda h: h["__metadata__"].update({"prognos.format_version": "3"}), "format version 3"),
        (lambda h: _edit_config(h, m=3), "does not match its configuration"),
        (lambda h: h["__metadata__"].pop(DIGEST), "no valid 'prognos.sha256'"),
        (lambda h: h["__metadata__"].update({"extra": 1}), "must be strings"),
        (lambda h: h.pop("__metadata__"), "not a prognos model file"),
    ):
        bad.write_bytes(raw)
        _edit(bad, edit)
        with pytest.raises(ModelFileError, match=pattern):
            load_model(bad)
    assert versions_compatible(__version__) and not versions_compatible("0.99.0")

    # files whose payload would run code when unpickled: never executed
    live = tmp_path / "live_marker"
    pickle.loads(pickle.dumps(_Evil(live)))  # the payload is live ...
    assert live.exists()
    marker = tmp_path / "marker"
    evil = pickle.dumps(_Evil(marker))
    refused(evil, "looks like a Python pickle")
    torch.save({"model": _Evil(marker)}, bad)
    with pytest.raises(ModelFileError, match="zip archive .* never loaded"):
        load_model(bad)
    # well-formed containers (valid digest) that carry the pickle as tensor bytes
    header, data = _split(raw)
    extra = {"dtype": "O", "shape": [len(evil)], "data_offsets": [len(data), len(data) + len(evil)]}
    bad.write_bytes(_pack({**header, "x": extra}, data + evil))
    with pytest.raises(ModelFileError, match="dtype 'O'; allowed"):
        load_model(bad)
    u8 = {**extra, "dtype": "U8"}
    bad.write_bytes(_pack({**header, "x": u8}, data + evil))
    with pytest.raises(ModelFileError, match="dtype 'U8'; allowed"):
        load_model(bad)
    header, data = _split(raw)
    name = max((k for k in header if k != "__metadata__"), key=lambda k: header[k]["data_offsets"])
    header[name]["data_offsets"][1] += 8  # a tensor that claims 8 more bytes than its shape
    bad.write_bytes(_pack(header, data + evil[:8]))
    with pytest.raises(ModelFileError, match="does not fit"):
        load_model(bad)
    header, data = _split(raw)
    dup = json.dumps(header, separators=(",", ":"))
    dup = dup[:-1] + ',"__metadata__":{}}'
    refused(U64.pack(len(dup)) + dup.encode() + data, "repeats a key")
    # a plain safetensors file (no prognos metadata)
    plain = tmp_path / "plain.safetensors"
    save_file({"w": torch.zeros(2)}, str(plain))
    with pytest.raises(ModelFileError, match="safetensors file but not a prognos model"):
        load_model(plain)
    assert not marker.exists()


def test_format_1_files_are_still_read_and_checked(tmp_path):
    s = load_series(_series())
    model = fit_series(s, "elm", None, 2, holdout=0)
    tensors = {"learner." + k: v for k, v in model.learner.state_dict().items()}
    old = tmp_path / "old.pt"
    _write_format1(old, model.config, tensors, "prognos-workflow")
    mf = load_model_file(old)
    assert mf.format_version == 1 and mf.config == model.config
    assert all(torch.equal(mf.tensors[k], v) for k, v in tensors.items())
    back = load_model(old)
    assert torch.equal(forecast(back, s, 8).mean, forecast(model, s, 8).mean)
    raw = old.read_bytes()
    bad = tmp_path / "bad.pt"
    flipped = bytearray(raw)
    flipped[-3] ^= 0x01
    for content, pattern in (
        (bytes(flipped), "failed its SHA-256 check"),
        (raw[:-100], "is truncated"),
        (raw[:30], "is truncated"),
    ):
        bad.write_bytes(content)
        with pytest.raises(ModelFileError, match=pattern):
            load_model(bad)
    _write_format1(bad, model.config, tensors, "prognos-workflow", fmt=7)
    with pytest.raises(ModelFileError, match="format version 7"):
        load_model(bad)
    _write_format1(bad, model.config, tensors, "prognos-workflow", version="9.0.0")
    with pytest.raises(ModelFileError, match="9.0.0, which is incompatible"):
        load_model(bad)


def test_paths_and_devices_get_clear_errors(tmp_path):
    s = load_series(_series())
    model = fit_series(s, "elm", None, 2, holdout=0)
    folder = tmp_path / "some_dir"
    folder.mkdir()
    with pytest.raises(IsADirectoryError, match="is a folder; give a file name"):
        save_model(model, folder)
    assert os.listdir(folder) == []
    with pytest.raises(IsADirectoryError, match="is a folder, not a model file"):
        load_model(folder)
    path = tmp_path / "m.pt"
    save_model(model, path)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="map_location='cuda'.*cannot use that device"):
            load_model(path, map_location="cuda")
    with pytest.raises(ValueError, match="not a device name"):
        load_model(path, map_location="gpu please")
    with pytest.raises(TypeError, match="map_location"):
        load_model(path, map_location=3)
    assert load_model(path, map_location=torch.device("cpu")).config == model.config


def test_a_hand_edited_noise_level_is_refused(tmp_path):
    """A residual_rmse of -0.5 ran as 0 and 1e200 gave a confident RUL of one step (with the
    checksum recomputed, the file was valid)."""
    import numpy as np

    from prognos_torch.io import ModelFileError
    from prognos_torch.workflow import fit_series, load_model, load_series, save_model

    model = fit_series(load_series(np.sin(np.arange(80) / 5.0)), "elm", None, 3)
    for bad in (-0.5, 1e200):
        model.config["residual_rmse"] = bad
        path = tmp_path / "m.pt"
        save_model(model, path)
        with pytest.raises(ModelFileError, match="configuration entry 'residual_rmse' is"):
            load_model(path)


def test_messages_for_odd_files_and_tensors(tmp_path):
    from prognos_torch.io import ModelFileError, load_model_file, save_model_file

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(ModelFileError, match="not a regular file"):  # (it said "not found")
        load_model_file(fifo)
    # a safetensors-like file with a JSON array for its header, 0x180 bytes long: its first
    # byte 0x80 was read as a pickle's
    h = b"[" + b" " * (0x180 - 2) + b"]"
    (tmp_path / "arr.st").write_bytes(struct.pack("<Q", len(h)) + h)
    with pytest.raises(ModelFileError, match="its header is not the JSON object"):
        load_model_file(tmp_path / "arr.st")
    # tensors the format cannot hold are named; a negated view is stored by value
    for t, match in ((torch.eye(3).to_sparse(), "layout torch.sparse_coo"),
                     (torch.empty(3, device="meta"), "on the meta device")):  # fmt: skip
        with pytest.raises(TypeError, match=f"tensors\\['w'\\] is .*{match}"):
            save_model_file(tmp_path / "a", {}, {"w": t})
    with pytest.raises(TypeError, match="tensors must be a mapping name -> tensor, got list"):
        save_model_file(tmp_path / "a", {}, [torch.ones(1)])
    save_model_file(
        tmp_path / "neg", {}, {"w": torch._neg_view(torch.ones(3, dtype=torch.float64))}
    )
    assert torch.equal(
        load_model_file(tmp_path / "neg").tensors["w"], -torch.ones(3, dtype=torch.float64)
    )
