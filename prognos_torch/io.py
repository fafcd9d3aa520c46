"""Safe model files: JSON configuration and raw tensors behind a SHA-256 checksum; no pickle.

A model file from someone else must not be able to run code on the reader's machine, so this
format never uses :mod:`pickle` (which ``torch.load`` without ``weights_only=True`` relies on):
the configuration is JSON and every tensor is stored as raw little-endian bytes described by the
JSON header (dtype from a fixed allow-list, shape, offset). A tampered or truncated file is
rejected *before anything is deserialised*: the whole body (header and tensor bytes) is covered
by a SHA-256 digest stored in the fixed-size preamble, and the length is checked first.

Layout (all integers little-endian)::

    offset  size  field
    0       12    magic  b"\\x89PROGNOS\\r\\n\\x1a\\n"
    12      4     format version (uint32), currently 1
    16      8     body length in bytes (uint64)
    24      32    SHA-256 of the body
    56      ...   body: header length (uint64), header (UTF-8 JSON), tensor bytes

The header is ``{"library": "prognos_torch", "library_version": "0.1.0", "kind": ...,
"config": {...}, "tensors": [{"name", "dtype", "shape", "offset", "nbytes"}, ...]}`` with
offsets relative to the start of the tensor bytes.

The digest detects corruption and accidental edits; it is not a signature (anyone can write a
file with a valid digest). Safety does not rest on it: the reader only ever parses JSON and
copies bytes into tensors of allowed dtypes, so even a hostile file with a valid digest can at
worst carry wrong numbers, never code.

Compatibility: files are readable by the same major.minor release that wrote them (for 0.x:
the same 0.minor); :func:`load_model_file` raises :class:`ModelFileError` naming both versions
otherwise, and for any other format version.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import os
import re
import struct
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from . import __version__

__all__ = [
    "MAGIC",
    "FORMAT_VERSION",
    "ModelFile",
    "ModelFileError",
    "save_model_file",
    "load_model_file",
    "atomic_write",
    "versions_compatible",
]

MAGIC = b"\x89PROGNOS\r\n\x1a\n"
FORMAT_VERSION = 1
_PREAMBLE = struct.Struct("<12sIQ32s")  # magic, format version, body length, sha256
_U64 = struct.Struct("<Q")
#: Header size limit: a model file's JSON header is a few kB; refuse absurd values early.
_MAX_HEADER = 64 * 1024 * 1024

#: dtype name in the header -> (torch dtype, little-endian numpy dtype).
_DTYPES: dict[str, tuple[torch.dtype, np.dtype]] = {
    "float64": (torch.float64, np.dtype("<f8")),
    "float32": (torch.float32, np.dtype("<f4")),
    "int64": (torch.int64, np.dtype("<i8")),
    "int32": (torch.int32, np.dtype("<i4")),
    "bool": (torch.bool, np.dtype("?")),
}
_BY_TORCH = {v[0]: k for k, v in _DTYPES.items()}


class ModelFileError(ValueError):
    """A file that is not a readable prognos model file (wrong type, corrupted, incompatible)."""


@dataclass(frozen=True)
class ModelFile:
    """What :func:`load_model_file` returns.

    Attributes:
        kind: the file's kind string (e.g. ``"prognos-workflow"``).
        config: the JSON configuration (plain dicts, lists, strings, numbers, bools, None).
        tensors: name -> tensor (fresh CPU tensors, or on ``map_location``).
        library_version: version of prognos_torch that wrote the file.
        format_version: container format version.
    """

    kind: str
    config: dict
    tensors: dict[str, Tensor]
    library_version: str
    format_version: int


def _version_tuple(v: str) -> tuple[int, int, int] | None:
    m = re.match(r"^(\d+)\.(\d+)\.(\d+)", v) if isinstance(v, str) else None
    return (int(m.group(1)), int(m.group(2)), int(m.group(3))) if m else None


def versions_compatible(written: str, reader: str = __version__) -> bool:
    """Whether a file written by version ``written`` is readable by ``reader``: same major and,
    while the major is 0, same minor (semantic versioning's rule for 0.x releases); a reader
    never accepts files from a newer minor release of its own major."""
    a, b = _version_tuple(written), _version_tuple(reader)
    if a is None or b is None:
        return False
    if a[0] != b[0]:
        return False
    return a[1] == b[1] if a[0] == 0 else a[1] <= b[1]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and an atomic
    rename: readers see the old file or the complete new one, never a partial write."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {folder}")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; use the usual permissions
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def _check_json(value, where: str) -> None:
    """Only plain JSON values (no NaN/inf: JSON has none); raise TypeError naming the key."""
    if value is None or isinstance(value, (bool, int, str)):
        return
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"config{where} is {value}; store non-finite numbers as None")
        return
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _check_json(v, f"{where}[{i}]")
        return
    if isinstance(value, Mapping):
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"config{where} has a non-string key {k!r}")
            _check_json(v, f"{where}[{k!r}]")
        return
    raise TypeError(f"config{where} must be a JSON value, got {type(value).__name__}")


def save_model_file(
    path: str | os.PathLike,
    config: Mapping,
    tensors: Mapping[str, Tensor],
    *,
    kind: str = "prognos-model",
) -> None:
    """Write a model file (atomically: temporary file, then rename).

    Args:
        path: destination (its folder must exist).
        config: JSON-serialisable configuration (dicts, lists, str, int, finite float, bool,
            None).
        tensors: name -> tensor of a dtype in ``float64, float32, int64, int32, bool`` (any
            device; stored from CPU copies).
        kind: a short label checked by readers that expect a particular kind of file.
    """
    if not isinstance(kind, str) or not kind:
        raise ValueError(f"kind must be a non-empty string, got {kind!r}")
    if not isinstance(config, Mapping):
        raise TypeError(f"config must be a mapping, got {type(config).__name__}")
    _check_json(config, "")
    entries, chunks, offset = [], [], 0
    for name, t in tensors.items():
        if not isinstance(name, str):
            raise TypeError(f"tensor names must be strings, got {name!r}")
        if not isinstance(t, Tensor):
            raise TypeError(f"tensors[{name!r}] must be a torch.Tensor, got {type(t).__name__}")
        if t.dtype not in _BY_TORCH:
            raise TypeError(f"tensors[{name!r}] has dtype {t.dtype}; allowed: {sorted(_DTYPES)}")
        dname = _BY_TORCH[t.dtype]
        arr = t.detach().to("cpu").contiguous().numpy().astype(_DTYPES[dname][1], copy=False)
        raw = arr.tobytes()
        entries.append(
            {
                "name": name,
                "dtype": dname,
                "shape": list(t.shape),
                "offset": offset,
                "nbytes": len(raw),
            }
        )
        chunks.append(raw)
        offset += len(raw)
    header = {
        "library": "prognos_torch",
        "library_version": __version__,
        "kind": kind,
        "config": config,
        "tensors": entries,
    }
    head = json.dumps(header, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()
    body = _U64.pack(len(head)) + head + b"".join(chunks)
    digest = hashlib.sha256(body).digest()
    atomic_write(path, _PREAMBLE.pack(MAGIC, FORMAT_VERSION, len(body), digest) + body)


def _sniff(prefix: bytes) -> str:
    if prefix.startswith(b"PK\x03\x04"):
        return (
            "it is a zip archive (the format of torch.save); such files contain pickled objects "
            "and are never loaded here, because unpickling can run arbitrary code"
        )
    if prefix[:1] == b"\x80" or prefix[:1] in (b"(", b"c", b"]", b"}"):
        return (
            "it looks like a Python pickle; pickles are never loaded here, because unpickling "
            "can run arbitrary code"
        )
    return "it does not start with the prognos model-file signature"


def load_model_file(
    path: str | os.PathLike,
    *,
    kind: str | None = None,
    map_location: str | torch.device = "cpu",
) -> ModelFile:
    """Read a model file written by :func:`save_model_file`, checking it before parsing.

    Order of checks: size and signature, format version, body length (truncation), SHA-256 of
    the body, then the JSON header, library-version compatibility, ``kind``, and each tensor
    entry (allowed dtype, shape, bounds). Nothing is unpickled, ever.

    Args:
        path: the file.
        kind: when given, the file's kind must equal it.
        map_location: device of the returned tensors.

    Raises:
        FileNotFoundError: no such file.
        ModelFileError: not a model file, truncated, checksum mismatch, malformed header,
            incompatible version or kind (each message names the problem).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file not found: {path}")
    size = path.stat().st_size
    with open(path, "rb") as handle:
        pre = handle.read(_PREAMBLE.size)
        if len(pre) < len(MAGIC) or pre[: len(MAGIC)] != MAGIC:
            raise ModelFileError(f"{path} is not a prognos model file: {_sniff(pre)}")
        if len(pre) < _PREAMBLE.size:
            raise ModelFileError(
                f"{path} is truncated: {size} bytes, shorter than the {_PREAMBLE.size}-byte "
                "preamble"
            )
        _, fmt, body_len, digest = _PREAMBLE.unpack(pre)
        if fmt != FORMAT_VERSION:
            raise ModelFileError(
                f"{path} uses model-file format version {fmt}; prognos_torch {__version__} "
                f"reads version {FORMAT_VERSION} (re-save the model with this version, or use "
                "the prognos_torch release that wrote it)"
            )
        if size - _PREAMBLE.size < body_len:
            raise ModelFileError(
                f"{path} is truncated: {size - _PREAMBLE.size} of {body_len} body bytes present"
            )
        if size - _PREAMBLE.size > body_len:
            raise ModelFileError(
                f"{path} has {size - _PREAMBLE.size - body_len} unexpected bytes after the body "
                "(corrupted or modified)"
            )
        body = handle.read(body_len)
    if len(body) != body_len:  # the file changed while being read
        raise ModelFileError(f"{path} is truncated: read {len(body)} of {body_len} body bytes")
    if not hmac.compare_digest(hashlib.sha256(body).digest(), digest):
        raise ModelFileError(
            f"{path} failed its SHA-256 check: the file is corrupted or was modified"
        )

    # ---- from here on the bytes are exactly what the writer produced; parse defensively anyway
    if body_len < _U64.size:
        raise ModelFileError(f"{path}: body too short for its header length field")
    (head_len,) = _U64.unpack_from(body, 0)
    if head_len > min(_MAX_HEADER, body_len - _U64.size):
        raise ModelFileError(f"{path}: header length {head_len} exceeds the body")
    try:
        header = json.loads(body[_U64.size : _U64.size + head_len].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ModelFileError(f"{path}: malformed JSON header ({exc})") from None
    if not isinstance(header, dict) or header.get("library") != "prognos_torch":
        raise ModelFileError(f"{path}: header does not describe a prognos_torch model")
    written = header.get("library_version")
    if not isinstance(written, str) or _version_tuple(written) is None:
        raise ModelFileError(f"{path}: header has no valid library_version ({written!r})")
    if not versions_compatible(written):
        raise ModelFileError(
            f"{path} was written by prognos_torch {written}, which is incompatible with the "
            f"installed {__version__} (files are read by the release line that wrote them: "
            f"{_version_tuple(written)[0]}.{_version_tuple(written)[1]}.x); refit the model or "
            f"install prognos_torch {written}"
        )
    file_kind = header.get("kind")
    if not isinstance(file_kind, str):
        raise ModelFileError(f"{path}: header has no kind")
    if kind is not None and file_kind != kind:
        raise ModelFileError(f"{path} holds a {file_kind!r}, expected a {kind!r}")
    config = header.get("config")
    entries = header.get("tensors")
    if not isinstance(config, dict) or not isinstance(entries, list):
        raise ModelFileError(f"{path}: header lacks config or tensors")

    data = memoryview(body)[_U64.size + head_len :]
    tensors: dict[str, Tensor] = {}
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            raise ModelFileError(f"{path}: tensor entry {i} is not an object")
        name, dname, shape = e.get("name"), e.get("dtype"), e.get("shape")
        offset, nbytes = e.get("offset"), e.get("nbytes")
        if not isinstance(name, str) or name in tensors:
            raise ModelFileError(f"{path}: tensor entry {i} has a missing or repeated name")
        if dname not in _DTYPES:
            raise ModelFileError(
                f"{path}: tensor {name!r} has dtype {dname!r}; allowed: {sorted(_DTYPES)}"
            )
        ints = (offset, nbytes, *(shape if isinstance(shape, list) else [None]))
        if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in ints):
            raise ModelFileError(f"{path}: tensor {name!r} has a malformed shape or extent")
        tdtype, ndtype = _DTYPES[dname]
        count = math.prod(shape)
        if count * ndtype.itemsize != nbytes or offset + nbytes > len(data):
            raise ModelFileError(
                f"{path}: tensor {name!r} of shape {shape} does not fit its {nbytes} bytes at "
                f"offset {offset} (tensor data holds {len(data)} bytes)"
            )
        arr = np.frombuffer(data[offset : offset + nbytes], dtype=ndtype, count=count)
        t = torch.from_numpy(arr.astype(ndtype.newbyteorder("="), copy=True)).reshape(shape)
        tensors[name] = t.to(map_location)
    # the entries must tile the tensor bytes exactly: no overlap, no unreferenced bytes
    spans = sorted((e["offset"], e["nbytes"]) for e in entries)
    pos = 0
    for off, nb in spans:
        if off != pos:
            raise ModelFileError(f"{path}: tensor data has overlapping or unreferenced bytes")
        pos += nb
    if pos != len(data):
        raise ModelFileError(
            f"{path}: tensor data has {len(data) - pos} unreferenced bytes (corrupted or modified)"
        )
    return ModelFile(
        kind=file_kind,
        config=config,
        tensors=tensors,
        library_version=written,
        format_version=fmt,
    )
