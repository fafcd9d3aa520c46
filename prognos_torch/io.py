"""Safe model files: safetensors tensors, JSON configuration and a SHA-256 checksum; no pickle.

A model file from someone else must not be able to run code on the reader's machine, so this
format never uses :mod:`pickle` (which ``torch.load`` without ``weights_only=True`` relies on).
Files are in the `safetensors <https://huggingface.co/docs/safetensors>`_ format (format
version 2), so any safetensors reader (``safetensors.safe_open``) opens the tensors::

    offset  size  field
    0       8     N: header length in bytes (uint64, little-endian)
    8       N     header: UTF-8 JSON, padded with spaces to a multiple of 8 bytes
    8 + N   ...   tensor bytes: raw little-endian values, row-major, one tensor after another

The header maps every tensor name to ``{"dtype": "F64" | "F32" | "I64" | "I32" | "BOOL",
"shape": [...], "data_offsets": [begin, end]}`` (offsets relative to the tensor bytes, which
they tile exactly) and holds ``"__metadata__"``, string to string::

    "format": "pt"
    "prognos.library": "prognos_torch"
    "prognos.format_version": "2"
    "prognos.library_version": "0.1.0"
    "prognos.kind": e.g. "prognos-workflow"
    "prognos.config": the configuration as JSON text
    "prognos.sha256": SHA-256 (hex) of the whole file with these 64 hex digits set to "0"

Order of checks on reading: file size and the header length (truncation of the header), the
header as JSON (plain JSON: parsing it cannot run code; duplicate keys refused), the prognos
metadata and format version, the extent of the tensor bytes (truncation, trailing bytes), the
SHA-256 of the whole file, then library-version compatibility, ``kind``, the configuration
and each tensor (allowed dtype, shape, bounds, exact tiling). No tensor byte and no
configuration value is used before the checksum has been verified.

The digest detects corruption and accidental edits; it is not a signature (anyone can write a
file with a valid digest). Safety does not rest on it: the reader only ever parses JSON and
copies bytes into tensors of allowed dtypes, so even a hostile file with a valid digest can at
worst carry wrong numbers, never code.

The format is written here directly (it is a few lines: length, JSON, bytes), so the
``safetensors`` package is not a dependency; the tests use it as an independent reader.

Format version 1 (``MAGIC``, a fixed preamble with the digest, then header and tensor bytes;
written by prognos_torch 0.1.0 before the move to safetensors) is still read. Compatibility:
files are readable by the same major.minor release that wrote them (for 0.x: the same
0.minor); :func:`load_model_file` raises :class:`ModelFileError` naming both versions
otherwise, and for any other format version.
"""

from __future__ import annotations

import csv
import hashlib
import hmac
import json
import math
import os
import re
import stat
import struct
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from . import __version__

__all__ = [
    "sniffed_csv",
    "MAGIC",
    "FORMAT_VERSION",
    "ModelFile",
    "ModelFileError",
    "save_model_file",
    "load_model_file",
    "atomic_write",
    "figure_format",
    "FIGURE_FORMATS",
    "versions_compatible",
]

#: Signature of format-1 files (read, no longer written).
MAGIC = b"\x89PROGNOS\r\n\x1a\n"
#: The format version written: 2 (safetensors).
FORMAT_VERSION = 2
_PREAMBLE = struct.Struct("<12sIQ32s")  # format 1: magic, format version, body length, sha256
_U64 = struct.Struct("<Q")
#: Header size limit: a model file's JSON header is a few kB; refuse absurd values early.
_MAX_HEADER = 64 * 1024 * 1024
_META = "__metadata__"
_DIGEST_KEY = "prognos.sha256"
_DIGEST_PLACEHOLDER = "0" * 64

#: dtype name in a format-1 header -> (torch dtype, little-endian numpy dtype).
_DTYPES: dict[str, tuple[torch.dtype, np.dtype]] = {
    "float64": (torch.float64, np.dtype("<f8")),
    "float32": (torch.float32, np.dtype("<f4")),
    "int64": (torch.int64, np.dtype("<i8")),
    "int32": (torch.int32, np.dtype("<i4")),
    "bool": (torch.bool, np.dtype("?")),
}
_BY_TORCH = {v[0]: k for k, v in _DTYPES.items()}
#: safetensors dtype codes of the allowed dtypes.
_ST_CODES = {"float64": "F64", "float32": "F32", "int64": "I64", "int32": "I32", "bool": "BOOL"}
_FROM_ST = {v: k for k, v in _ST_CODES.items()}


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
        format_version: container format version (2: safetensors; 1: the earlier format).
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


@contextmanager
def sniffed_csv(path: Path, *, missing: str, not_a_file: str) -> Iterator:
    """A ``csv.reader`` over the UTF-8 text table at ``path``, its delimiter sniffed from the
    first 64 KiB (``,``, ``;`` or tab). A missing path, a folder, a file that is not UTF-8 text
    and malformed CSV (also while the caller reads rows) become one-line ``FileNotFoundError`` /
    ``ValueError``s; ``missing`` and ``not_a_file`` name the path in the first two
    (``"data file not found: ..."``, ``"data path is not a file: ..."``)."""
    if not path.exists():
        raise FileNotFoundError(f"{missing} not found: {path}")
    if not path.is_file():
        raise ValueError(f"{not_a_file} is not a file: {path}")
    try:
        with open(path, encoding="utf-8-sig", newline="") as handle:
            sample = handle.read(64 * 1024)
            handle.seek(0)
            try:
                dialect = csv.Sniffer().sniff(sample, delimiters=",;\t")
            except csv.Error:
                dialect = csv.excel
            # a space after the delimiter is no part of the cell: 'a, "b"' holds a and b
            yield csv.reader(handle, dialect, skipinitialspace=True)
    except UnicodeDecodeError as exc:
        bad = exc.object[exc.start : exc.start + 1]
        raise ValueError(
            f"{path}: not a UTF-8 text CSV file (the byte {bad!r} is not valid UTF-8 where it "
            "stands; Latin-1 or Windows-1252 text?): save it as UTF-8 (in a spreadsheet: "
            "'CSV UTF-8')"
        ) from None
    except csv.Error as exc:
        raise ValueError(f"{path}: malformed CSV ({exc})") from None


#: Figure file suffixes and the format written (no suffix: PNG).
FIGURE_FORMATS = {".png": "png", ".pdf": "pdf", ".svg": "svg", "": "png"}


def figure_format(path: str | os.PathLike, what: str = "path") -> str:
    """The format of a figure file from its suffix (:data:`FIGURE_FORMATS`); another suffix
    is a ``ValueError`` naming ``what`` (a PNG under a ``.jpeg`` name would mislead)."""
    suffix = Path(path).suffix.lower()
    if suffix not in FIGURE_FORMATS:
        raise ValueError(
            f"{what}: {Path(path).name!r} has the suffix {suffix!r}; figures are written as "
            ".png, .pdf or .svg"
        )
    return FIGURE_FORMATS[suffix]


def atomic_write(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and an atomic
    rename: readers see the old file or the complete new one, never a partial write.

    Raises:
        IsADirectoryError: ``path`` is a folder (give a file name inside it).
        FileNotFoundError: the folder of ``path`` does not exist.
    """
    raw = os.fspath(path)
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder; give a file name, e.g. {path / 'model.pt'}")
    if isinstance(raw, str) and raw.endswith(("/", os.sep)):  # (Path("out/") is Path("out"))
        raise FileNotFoundError(
            f"output folder does not exist: {raw}; give a file name in an existing folder"
        )
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {folder}")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        # mkstemp creates 0600: a replaced file keeps its permissions, a new one the usual
        try:
            mode = stat.S_IMODE(os.stat(path).st_mode)
        except FileNotFoundError:
            mode = 0o666 & ~_umask()
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_folder(folder)


def _fsync_folder(folder: Path) -> None:
    """Flush the folder's entry of the renamed file, so that the new file survives a power
    loss (POSIX; a no-op where folders cannot be opened, e.g. Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _check_json(value, where: str):
    """Only plain JSON values (no NaN/inf: JSON has none); raise TypeError naming the key.
    Returns the value with NumPy scalars (``np.int64``, ``np.float32``, ``np.bool_``) as the
    Python numbers they hold, which ``json`` writes (it refuses NumPy integers)."""
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        value = value.item()
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"config{where} is {value}; store non-finite numbers as None")
        return value
    if isinstance(value, (list, tuple)):
        return [_check_json(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"config{where} has a non-string key {k!r}")
            out[k] = _check_json(v, f"{where}[{k!r}]")
        return out
    raise TypeError(f"config{where} must be a JSON value, got {type(value).__name__}")


def _stored_config(path, config) -> dict:
    """A stored configuration holds only what :func:`_check_json` passes: ``json`` reads
    ``NaN``/``Infinity`` that no writer here produces, and a model loaded with them could not be
    saved again; such a file is refused, naming the entry."""
    try:
        _check_json(config, "")
    except (TypeError, ValueError) as exc:
        raise ModelFileError(
            f"{path}: the stored configuration is not plain JSON ({exc}); prognos_torch never "
            "writes such a file"
        ) from None
    return config


def _dumps(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _digest_field(digest: str) -> bytes:
    """The bytes of the digest entry as written in the header."""
    return f"{json.dumps(_DIGEST_KEY)}:{json.dumps(digest)}".encode()


def _file_digest(head: bytes, data: bytes | memoryview) -> str:
    """SHA-256 (hex) of length + header + tensor bytes, the header's digest set to zeros."""
    h = hashlib.sha256(_U64.pack(len(head)))
    h.update(head)
    h.update(data)
    return h.hexdigest()


def save_model_file(
    path: str | os.PathLike,
    config: Mapping,
    tensors: Mapping[str, Tensor],
    *,
    kind: str = "prognos-model",
) -> None:
    """Write a model file in the safetensors format (atomically: temporary file, then rename).

    Args:
        path: destination (its folder must exist; not a folder itself).
        config: JSON-serialisable configuration (dicts, lists, str, int, finite float, bool,
            None; NumPy scalars are written as the Python numbers they hold).
        tensors: name -> tensor of a dtype in ``float64, float32, int64, int32, bool`` (any
            device; stored from CPU copies). Names must not be ``"__metadata__"``.
        kind: a short label checked by readers that expect a particular kind of file.
    """
    if not isinstance(kind, str) or not kind:
        raise ValueError(f"kind must be a non-empty string, got {kind!r}")
    if not isinstance(config, Mapping):
        raise TypeError(f"config must be a mapping, got {type(config).__name__}")
    config = _check_json(config, "")
    if not isinstance(tensors, Mapping):
        raise TypeError(f"tensors must be a mapping name -> tensor, got {type(tensors).__name__}")
    items = []
    for name, t in tensors.items():
        if not isinstance(name, str) or name == _META:
            raise TypeError(f"tensor names must be strings other than {_META!r}, got {name!r}")
        if not isinstance(t, Tensor):
            raise TypeError(f"tensors[{name!r}] must be a torch.Tensor, got {type(t).__name__}")
        if t.dtype not in _BY_TORCH:
            raise TypeError(f"tensors[{name!r}] has dtype {t.dtype}; allowed: {sorted(_DTYPES)}")
        if t.layout != torch.strided or t.is_meta:
            what = "on the meta device (no data)" if t.is_meta else f"of layout {t.layout}"
            raise TypeError(f"tensors[{name!r}] is {what}; a model file holds dense tensors")
        items.append((name, t.resolve_conj().resolve_neg()))
    # widest dtypes first: every tensor then starts at a multiple of its item size
    items.sort(key=lambda it: -it[1].element_size())
    header: dict = {
        _META: {
            "format": "pt",
            "prognos.library": "prognos_torch",
            "prognos.format_version": str(FORMAT_VERSION),
            "prognos.library_version": __version__,
            "prognos.kind": kind,
            "prognos.config": _dumps(config),
            _DIGEST_KEY: _DIGEST_PLACEHOLDER,
        }
    }
    chunks, offset = [], 0
    for name, t in items:
        dname = _BY_TORCH[t.dtype]
        arr = t.detach().to("cpu").contiguous().numpy().astype(_DTYPES[dname][1], copy=False)
        raw = arr.tobytes()
        header[name] = {
            "dtype": _ST_CODES[dname],
            "shape": list(t.shape),
            "data_offsets": [offset, offset + len(raw)],
        }
        chunks.append(raw)
        offset += len(raw)
    head = json.dumps(header, separators=(",", ":"), allow_nan=False).encode()
    head += b" " * (-(len(head) + _U64.size) % 8)  # tensor bytes start 8-byte aligned
    data = b"".join(chunks)
    field = _digest_field(_DIGEST_PLACEHOLDER)
    assert head.count(field) == 1
    digest = _file_digest(head, data)
    head = head.replace(field, _digest_field(digest))
    atomic_write(path, _U64.pack(len(head)) + head + data)


def _sniff(prefix: bytes) -> str:
    if prefix.startswith(b"PK\x03\x04"):
        return (
            "it is a zip archive (the format of torch.save); such files contain pickled objects "
            "and are never loaded here, because unpickling can run arbitrary code"
        )
    # a pickle opens with PROTO (0x80, protocol 2-5) or, protocols 0-1, one of "(c]}"; a
    # safetensors-like length of 0x..80 bytes is followed by its JSON header at byte 8
    json_at_8 = prefix[8:9] in (b"{", b"[")
    if (prefix[:1] == b"\x80" and prefix[1:2] in (b"\x02", b"\x03", b"\x04", b"\x05")
            and not json_at_8) or prefix[:1] in (b"(", b"c", b"]", b"}"):  # fmt: skip
        return (
            "it looks like a Python pickle; pickles are never loaded here, because unpickling "
            "can run arbitrary code"
        )
    if json_at_8:
        return "its header is not the JSON object of a safetensors file"
    return "it is neither a safetensors file nor a prognos model file of format 1"


def _format_version_error(path, fmt) -> ModelFileError:
    return ModelFileError(
        f"{path} uses model-file format version {fmt}; prognos_torch {__version__} reads "
        f"versions 1 and {FORMAT_VERSION} (re-save the model with this version, or use the "
        "prognos_torch release that wrote it)"
    )


def load_model_file(
    path: str | os.PathLike,
    *,
    kind: str | None = None,
    map_location: str | torch.device = "cpu",
) -> ModelFile:
    """Read a model file written by :func:`save_model_file` (format 2) or an earlier release
    (format 1), checking it before using anything in it (order in the module notes). Nothing
    is unpickled, ever.

    Args:
        path: the file.
        kind: when given, the file's kind must equal it.
        map_location: device of the returned tensors (a device this torch build has).

    Raises:
        FileNotFoundError: no such file.
        IsADirectoryError: ``path`` is a folder.
        ValueError: ``map_location`` is not a device this torch build can use.
        ModelFileError: not a model file, truncated, checksum mismatch, malformed header,
            incompatible version or kind (each message names the problem).
    """
    path = Path(path)
    device = _device(map_location)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder, not a model file")
    if path.exists() and not path.is_file():  # (a FIFO, a device: reading could block)
        raise ModelFileError(f"{path} is not a regular file (a pipe or a device), not a model file")
    if not path.is_file():
        raise FileNotFoundError(f"model file not found: {path}")
    size = path.stat().st_size
    with open(path, "rb") as handle:
        prefix = handle.read(_PREAMBLE.size)
        if prefix.startswith(MAGIC):
            handle.seek(0)
            return _load_v1(path, handle, size, kind, device)
        if len(prefix) < _U64.size + 1:
            raise ModelFileError(
                f"{path} is not a prognos model file ({size} bytes): {_sniff(prefix)}"
            )
        (head_len,) = _U64.unpack_from(prefix, 0)
        if head_len > _MAX_HEADER or prefix[_U64.size : _U64.size + 1] != b"{":
            raise ModelFileError(f"{path} is not a prognos model file: {_sniff(prefix)}")
        if size < _U64.size + head_len:
            raise ModelFileError(
                f"{path} is truncated: {size} bytes, shorter than its "
                f"{_U64.size + head_len}-byte header"
            )
        handle.seek(_U64.size)
        head = handle.read(head_len)
        data = handle.read()
    if len(head) != head_len:  # the file changed while being read
        raise ModelFileError(f"{path} is truncated: read {len(head)} of {head_len} header bytes")
    header = _parse_header(path, head)
    meta = header.get(_META)
    if not isinstance(meta, dict) or meta.get("prognos.library") != "prognos_torch":
        raise ModelFileError(
            f"{path} is a safetensors file but not a prognos model file (no prognos_torch metadata)"
        )
    if not all(isinstance(v, str) for v in meta.values()):
        raise ModelFileError(f"{path}: header metadata values must be strings")
    fmt = meta.get("prognos.format_version")
    if fmt != str(FORMAT_VERSION):
        raise _format_version_error(path, fmt)
    digest = meta.get(_DIGEST_KEY)
    if not isinstance(digest, str) or not re.fullmatch(r"[0-9a-f]{64}", digest):
        raise ModelFileError(f"{path}: header has no valid {_DIGEST_KEY!r} checksum")
    entries = []
    for name, e in header.items():
        if name == _META:
            continue
        if not isinstance(e, dict) or not isinstance(e.get("data_offsets"), list):
            raise ModelFileError(f"{path}: tensor {name!r} has a malformed header entry")
        offs = e["data_offsets"]
        if len(offs) != 2 or not all(_nonneg_int(v) for v in offs) or offs[1] < offs[0]:
            raise ModelFileError(f"{path}: tensor {name!r} has malformed data_offsets {offs}")
        entries.append(
            {
                "name": name,
                "dtype": e.get("dtype"),
                "shape": e.get("shape"),
                "offset": offs[0],
                "nbytes": offs[1] - offs[0],
            }
        )
    extent = max((e["offset"] + e["nbytes"] for e in entries), default=0)
    if len(data) < extent:
        raise ModelFileError(f"{path} is truncated: {len(data)} of {extent} tensor bytes present")
    if len(data) > extent:
        raise ModelFileError(
            f"{path} has {len(data) - extent} unexpected bytes after the tensor data "
            "(corrupted or modified)"
        )
    field = _digest_field(digest)
    if head.count(field) != 1 or not hmac.compare_digest(
        _file_digest(head.replace(field, _digest_field(_DIGEST_PLACEHOLDER)), data), digest
    ):
        raise ModelFileError(
            f"{path} failed its SHA-256 check: the file is corrupted or was modified"
        )

    # ---- from here on the bytes are exactly what the writer produced; parse defensively anyway
    written = meta.get("prognos.library_version")
    _check_library_version(path, written)
    file_kind = meta.get("prognos.kind")
    _check_kind(path, file_kind, kind)
    try:
        config = json.loads(meta.get("prognos.config", ""))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ModelFileError(f"{path}: malformed JSON configuration ({exc})") from None
    if not isinstance(config, dict):
        raise ModelFileError(f"{path}: header lacks a configuration object")
    _stored_config(path, config)
    for e in entries:
        if e["dtype"] not in _FROM_ST:
            raise ModelFileError(
                f"{path}: tensor {e['name']!r} has dtype {e['dtype']!r}; allowed: "
                f"{sorted(_FROM_ST)}"
            )
        e["dtype"] = _FROM_ST[e["dtype"]]
    tensors = _decode_tensors(path, entries, memoryview(data), device)
    return ModelFile(
        kind=file_kind,
        config=config,
        tensors=tensors,
        library_version=written,
        format_version=FORMAT_VERSION,
    )


def _device(map_location) -> torch.device:
    """``map_location`` as a ``torch.device`` that this torch build can allocate on.

    Raises:
        ValueError: not a device name or ``torch.device``, or a device type this torch build
            or machine does not have (e.g. ``"cuda"`` with a CPU-only build).
    """
    if isinstance(map_location, bool) or not isinstance(map_location, (str, torch.device)):
        raise TypeError(f"map_location must be a device name or torch.device, got {map_location!r}")
    try:
        device = torch.device(map_location)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(
            f"map_location={map_location!r} is not a device name (e.g. 'cpu', 'cuda:0')"
        ) from exc
    try:
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError, ValueError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(
            f"map_location={map_location!r}: this torch build or machine cannot use that "
            f"device ({why}); load on 'cpu' instead"
        ) from None
    return device


def _nonneg_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _parse_header(path, head: bytes) -> dict:
    def no_duplicates(pairs):
        keys = [k for k, _ in pairs]
        if len(set(keys)) != len(keys):
            raise ModelFileError(f"{path}: header repeats a key")
        return dict(pairs)

    try:
        header = json.loads(head.decode("utf-8"), object_pairs_hook=no_duplicates)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ModelFileError(f"{path}: malformed JSON header ({exc})") from None
    if not isinstance(header, dict):
        raise ModelFileError(f"{path}: header is not a JSON object")
    return header


def _check_library_version(path, written) -> None:
    if not isinstance(written, str) or _version_tuple(written) is None:
        raise ModelFileError(f"{path}: header has no valid library_version ({written!r})")
    if not versions_compatible(written):
        raise ModelFileError(
            f"{path} was written by prognos_torch {written}, which is incompatible with the "
            f"installed {__version__} (files are read by the release line that wrote them: "
            f"{_version_tuple(written)[0]}.{_version_tuple(written)[1]}.x); refit the model or "
            f"install prognos_torch {written}"
        )


def _check_kind(path, file_kind, kind) -> None:
    if not isinstance(file_kind, str):
        raise ModelFileError(f"{path}: header has no kind")
    if kind is not None and file_kind != kind:
        raise ModelFileError(f"{path} holds a {file_kind!r}, expected a {kind!r}")


def _decode_tensors(path, entries: list, data: memoryview, device) -> dict[str, Tensor]:
    """Tensors from checked header entries ``{name, dtype, shape, offset, nbytes}``; the
    entries must tile ``data`` exactly (no overlap, no unreferenced bytes)."""
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
        if not all(_nonneg_int(v) for v in ints):
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
        tensors[name] = t.to(device)
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
    return tensors


def _load_v1(path, handle, size: int, kind, device) -> ModelFile:
    """Format 1: magic, version, body length, SHA-256 of the body, then the body (header
    length, JSON header with ``config`` and ``tensors`` entries, tensor bytes)."""
    pre = handle.read(_PREAMBLE.size)
    if len(pre) < _PREAMBLE.size:
        raise ModelFileError(
            f"{path} is truncated: {size} bytes, shorter than the {_PREAMBLE.size}-byte preamble"
        )
    _, fmt, body_len, digest = _PREAMBLE.unpack(pre)
    if fmt != 1:
        raise _format_version_error(path, fmt)
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
    header = _parse_header(path, body[_U64.size : _U64.size + head_len])
    if header.get("library") != "prognos_torch":
        raise ModelFileError(f"{path}: header does not describe a prognos_torch model")
    written = header.get("library_version")
    _check_library_version(path, written)
    file_kind = header.get("kind")
    _check_kind(path, file_kind, kind)
    config = header.get("config")
    entries = header.get("tensors")
    if not isinstance(config, dict) or not isinstance(entries, list):
        raise ModelFileError(f"{path}: header lacks config or tensors")
    _stored_config(path, config)
    tensors = _decode_tensors(path, entries, memoryview(body)[_U64.size + head_len :], device)
    return ModelFile(
        kind=file_kind, config=config, tensors=tensors, library_version=written, format_version=1
    )
