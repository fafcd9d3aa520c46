"""NASA IMS bearing run-to-failure data: snapshot features, the shipped table, paper 002's index.

Three layers:

* :func:`read_raw_features` streams the original ASCII archive (one file per 1 s snapshot, named
  by its acquisition time, e.g. ``2003.10.22.12.06.24``; 20,480 rows; 8 whitespace-separated
  channels in test 1, 4 in tests 2 and 3) into per-snapshot, per-channel time-domain features,
  with a cache so that re-reading is instant.
* :func:`load_ims_features` reads the shipped table ``datasets/ims/test1_features.csv`` (same tidy
  format; see ``datasets/ims/README.md`` for provenance and conventions).
* :func:`health_indicator` builds paper 002's monitoring index for bearing 3 of test 1: time-domain
  features, standardisation, locally linear embedding to one dimension, last 12 days.

Feature conventions (identical to ``datasets/ims/build_features.py``; m_k are central moments with
1/n normalisation): mean; median; std with ddof = 1; skewness m3 / m2^1.5 (biased); rms
sqrt(mean(x^2)) including the DC offset; std_error = std / sqrt(n); kurtosis m4 / m2^2 (not excess,
Gaussian = 3); peak max|x|; crest_factor peak / rms.
"""

from __future__ import annotations

import csv
import math
import os
import re
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from prognos_torch.datasets.lle import LLEFit, lle_fit

from ..core.validation import is_int, is_real

__all__ = [
    "FEATURE_NAMES",
    "PAPER_FEATURES",
    "HI_FEATURES",
    "IMS_CHANNELS",
    "IMS_SAMPLES",
    "IMSFeatures",
    "IMSFormatError",
    "SkippedFile",
    "HealthIndicator",
    "bearing_channels",
    "snapshot_time",
    "snapshot_features",
    "read_snapshot",
    "read_raw_features",
    "load_ims_features",
    "default_data_dir",
    "health_indicator",
]

#: Feature columns of the tidy table, in order.
FEATURE_NAMES: tuple[str, ...] = (
    "mean",
    "median",
    "std",
    "skewness",
    "rms",
    "std_error",
    "kurtosis",
    "peak",
    "crest_factor",
)
#: The seven features of paper 002 (Sec. "Experiments").
PAPER_FEATURES: tuple[str, ...] = FEATURE_NAMES[:7]
#: The six of them available for the whole of test 1 in the shipped table (no median).
HI_FEATURES: tuple[str, ...] = ("mean", "std", "skewness", "rms", "std_error", "kurtosis")
#: Channels (columns of a raw file) per test.
IMS_CHANNELS: dict[int, int] = {1: 8, 2: 4, 3: 4}
#: Samples per channel in every IMS snapshot (1 s at 20.48 kHz).
IMS_SAMPLES = 20480

_SNAPSHOT_NAME = re.compile(r"^(\d{4})\.(\d{2})\.(\d{2})\.(\d{2})\.(\d{2})\.(\d{2})$")
_CSV_HEADER = ("timestamp", "channel") + FEATURE_NAMES
_CACHE_VERSION = 2  # 2: entries hold the row count (checked against expected_samples)


def _feature_position(feature_names: Sequence[str], name: str) -> int:
    """Position of ``name`` in ``feature_names``; a ``ValueError`` naming it and the choices."""
    if name not in feature_names:
        raise ValueError(
            f"unknown feature {name!r}; feature must be one of {', '.join(feature_names)}"
        )
    return list(feature_names).index(name)


class IMSFormatError(ValueError):
    """A raw snapshot file that cannot be parsed; the message names the file and line."""

    def __init__(self, path: str | os.PathLike, message: str, line: int | None = None) -> None:
        self.path = str(path)
        self.line = line
        where = f"{self.path}, line {line}" if line is not None else self.path
        super().__init__(f"{where}: {message}")


@dataclass(frozen=True)
class SkippedFile:
    """A file that :func:`read_raw_features` did not use, with the reason."""

    path: str
    reason: str


def _check_test(test) -> int:
    if not is_int(test) or test not in IMS_CHANNELS:
        raise ValueError(f"test must be one of {sorted(IMS_CHANNELS)} (IMS tests), got {test!r}")
    return int(test)


def _check_expected_samples(expected_samples) -> int | None:
    if expected_samples is None:
        return None
    if not is_int(expected_samples) or expected_samples < 2:
        # ("20480" gave "20480 sample rows, expected 20480"; 0 made every file a bad file)
        raise ValueError(
            f"expected_samples must be None or an int >= 2 (rows per file), "
            f"got {expected_samples!r}"
        )
    return int(expected_samples)


def bearing_channels(test: int, bearing: int) -> tuple[int, ...]:
    """1-based channels of a bearing: test 1 has (2b - 1, 2b), tests 2 and 3 have (b,)."""
    test = _check_test(test)
    if not is_int(bearing) or not 1 <= bearing <= 4:
        raise ValueError(f"bearing must be 1, 2, 3 or 4 (IMS test {test}), got {bearing!r}")
    return (2 * bearing - 1, 2 * bearing) if test == 1 else (bearing,)


def snapshot_time(name: str) -> datetime | None:
    """Acquisition time from a snapshot file name ``YYYY.MM.DD.hh.mm.ss``; ``None`` otherwise."""
    match = _SNAPSHOT_NAME.match(os.path.basename(name))
    if match is None:
        return None
    try:
        return datetime(*(int(part) for part in match.groups()))
    except ValueError:  # e.g. month 13
        return None


def snapshot_features(x: np.ndarray) -> np.ndarray:
    """Time-domain features of one snapshot.

    Args:
        x: samples, shape (n, C) float64 (n >= 2 samples of C channels).

    Returns:
        shape (C, 9), columns in :data:`FEATURE_NAMES` order. Skewness, kurtosis and crest
        factor are NaN for a channel with zero variance (resp. zero rms).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"x must have shape (n, C) with n >= 2, got {x.shape}")
    n = x.shape[0]
    # a constant channel's mean is its value, exactly (x.mean rounds: 20480 x 0.1 gave m2 > 0,
    # skewness 1 and kurtosis 1 instead of NaN)
    mean = np.where(x.max(0) == x.min(0), x[0], x.mean(0))
    centred = x - mean
    c2 = centred * centred
    m2 = c2.mean(0)
    m3 = (c2 * centred).mean(0)
    m4 = (c2 * c2).mean(0)
    std = np.sqrt(m2 * (n / (n - 1)))
    rms = np.sqrt((x * x).mean(0))
    peak = np.abs(x).max(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        skewness = np.where(m2 > 0, m3 / m2**1.5, np.nan)
        kurtosis = np.where(m2 > 0, m4 / (m2 * m2), np.nan)
        crest = np.where(rms > 0, peak / rms, np.nan)
    median = np.median(x, axis=0)
    return np.stack(
        [mean, median, std, skewness, rms, std / math.sqrt(n), kurtosis, peak, crest], axis=1
    )


def _locate_problem(path: Path, n_channels: int) -> IMSFormatError | None:
    """Slow scan for the first bad line (only run after the fast parser failed)."""
    with open(path, encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            tokens = line.split()
            if not tokens:
                continue
            if len(tokens) != n_channels:
                return IMSFormatError(
                    path, f"{len(tokens)} columns, expected {n_channels} channels", number
                )
            for column, token in enumerate(tokens, start=1):
                try:
                    value = float(token)
                except ValueError:
                    return IMSFormatError(
                        path, f"non-numeric value {token[:40]!r} in column {column}", number
                    )
                if not math.isfinite(value):
                    return IMSFormatError(
                        path, f"non-finite value {token!r} in column {column}", number
                    )
    return None


def read_snapshot(
    path: str | os.PathLike, n_channels: int, expected_samples: int | None = None
) -> np.ndarray:
    """Samples of one raw snapshot file, shape (n, n_channels) float64.

    Raises:
        FileNotFoundError: the file does not exist.
        IMSFormatError: (a ``ValueError``) wrong number of columns, a non-numeric or non-finite
            value (the message names the file and line), fewer than 2 rows, or a row count other
            than ``expected_samples`` when given.
    """
    if not is_int(n_channels) or n_channels < 1:
        # ("8" gave "8 columns, expected 8 channels")
        raise ValueError(f"n_channels must be a positive int, got {n_channels!r}")
    n_channels = int(n_channels)
    expected_samples = _check_expected_samples(expected_samples)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"IMS snapshot file not found: {path}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            data = np.loadtxt(path, dtype=np.float64, ndmin=2, comments=None)
    except ValueError as exc:
        problem = _locate_problem(path, n_channels)
        raise (problem or IMSFormatError(path, f"cannot parse: {exc}")) from None
    if data.shape[0] == 0:
        raise IMSFormatError(path, "file holds no samples")
    if data.shape[1] != n_channels or not np.isfinite(data).all():
        problem = _locate_problem(path, n_channels)
        raise problem or IMSFormatError(path, f"{data.shape[1]} columns, expected {n_channels}")
    if data.shape[0] < 2:
        raise IMSFormatError(path, f"{data.shape[0]} sample rows, need at least 2")
    if expected_samples is not None and data.shape[0] != expected_samples:
        raise IMSFormatError(path, f"{data.shape[0]} sample rows, expected {expected_samples}")
    return data


@dataclass(frozen=True)
class IMSFeatures:
    """Per-snapshot, per-channel features of one IMS test (tidy, time first).

    Attributes:
        test: IMS test number (1, 2 or 3).
        timestamps: acquisition times, shape (T,), ``numpy.datetime64[s]``.
        days: float64 tensor (T,), days since ``start`` (the first snapshot read).
        values: float64 tensor (T, C, F): ``values[snapshot, channel, feature]``; NaN where a
            feature is missing (the median of the shipped table).
        channels: the C 1-based raw-file channels, in order.
        feature_names: the F feature names, in order.
        start: the reference time of ``days``.
        skipped: files the raw reader did not use, with reasons (empty for the shipped table).
    """

    test: int
    timestamps: np.ndarray
    days: Tensor
    values: Tensor
    channels: tuple[int, ...]
    feature_names: tuple[str, ...]
    start: np.datetime64
    skipped: tuple[SkippedFile, ...] = field(default=())

    def __len__(self) -> int:
        return int(self.values.shape[0])

    @property
    def n_snapshots(self) -> int:
        return len(self)

    def _channel_index(self, channel: int) -> int:
        # (is_int: True was channel 1, 5.0 channel 5)
        if not is_int(channel) or channel not in self.channels:
            raise ValueError(f"channel must be one of {list(self.channels)}, got {channel!r}")
        return self.channels.index(channel)

    def _feature_index(self, name: str) -> int:
        return _feature_position(self.feature_names, name)

    def channel(self, channel: int) -> Tensor:
        """Features of one 1-based channel, shape (T, F)."""
        return self.values[:, self._channel_index(channel)]

    def feature(self, name: str) -> Tensor:
        """One feature for all channels, shape (T, C)."""
        return self.values[:, :, self._feature_index(name)]

    def select(
        self,
        features: Sequence[str] | None = None,
        channels: Sequence[int] | None = None,
    ) -> IMSFeatures:
        """A copy restricted to ``features`` and/or ``channels``, in the order given."""
        f_idx = list(range(len(self.feature_names)))
        c_idx = list(range(len(self.channels)))
        if features is not None:
            if isinstance(features, str):
                raise TypeError("features must be a sequence of names, not a single string")
            f_idx = [self._feature_index(name) for name in features]
        if channels is not None:
            c_idx = [self._channel_index(c) for c in channels]
        values = self.values[:, c_idx][:, :, f_idx]
        return replace(
            self,
            values=values,
            channels=tuple(self.channels[i] for i in c_idx),
            feature_names=tuple(self.feature_names[i] for i in f_idx),
        )

    def bearing(self, bearing: int) -> IMSFeatures:
        """The channels of one bearing (test 1: 2b - 1 and 2b; tests 2 and 3: b)."""
        return self.select(channels=bearing_channels(self.test, bearing))

    def take(self, index) -> IMSFeatures:
        """Snapshots selected by a slice, a boolean mask (T,) or integer indices."""
        if isinstance(index, Tensor):
            index = index.cpu().numpy()
        if isinstance(index, np.ndarray) and index.dtype == bool and index.shape != (len(self),):
            raise ValueError(f"boolean index must have shape ({len(self)},), got {index.shape}")
        sel = np.arange(len(self))[index]
        sel_t = torch.as_tensor(np.atleast_1d(sel), dtype=torch.long, device=self.values.device)
        return replace(
            self,
            timestamps=self.timestamps[np.atleast_1d(sel)],
            days=self.days[sel_t],
            values=self.values[sel_t],
        )

    def last_days(self, span: float) -> IMSFeatures:
        """Snapshots with ``days >= days[-1] - span`` (paper 002 uses the last 12 days)."""
        if not (is_real(span) and span > 0):
            raise ValueError(f"span must be a positive number of days, got {span!r}")
        mask = (self.days >= self.days[-1] - span).cpu().numpy()
        return self.take(mask)

    def to_csv(self, path: str | os.PathLike) -> None:
        """Write the tidy table (one row per snapshot and channel, 9 significant digits).

        The columns are ``timestamp, channel`` and :data:`FEATURE_NAMES`; features this object
        lacks are written as empty cells, as NaNs are.
        """
        values = self.values.detach().cpu().numpy()
        cols = [
            self.feature_names.index(n) if n in self.feature_names else -1 for n in FEATURE_NAMES
        ]
        with open(path, "w", encoding="utf-8", newline="") as handle:
            writer = csv.writer(handle, lineterminator="\n")
            writer.writerow(_CSV_HEADER)
            for t, stamp in enumerate(self.timestamps):
                iso = str(stamp.astype("datetime64[s]"))
                for c, channel in enumerate(self.channels):
                    row = [iso, str(channel)]
                    for col in cols:
                        value = values[t, c, col] if col >= 0 else math.nan
                        row.append("" if math.isnan(value) else format(float(value), ".9g"))
                    writer.writerow(row)


def _days_since(stamps: np.ndarray, start: np.datetime64) -> Tensor:
    seconds = (stamps - start).astype("timedelta64[s]").astype(np.float64)
    return torch.as_tensor(seconds / 86400.0, dtype=torch.float64)


def _build(test, stamps, values, channels, skipped=()) -> IMSFeatures:
    stamps = np.asarray(stamps, dtype="datetime64[s]")
    start = stamps[0] if len(stamps) else np.datetime64("NaT", "s")
    return IMSFeatures(
        test=test,
        timestamps=stamps,
        days=_days_since(stamps, start),
        values=torch.as_tensor(values, dtype=torch.float64),
        channels=tuple(channels),
        feature_names=FEATURE_NAMES,
        start=start,
        skipped=tuple(skipped),
    )


# --------------------------------------------------------------------------- raw archive reader


def _default_cache_path(directory: Path, test: int) -> Path:
    return directory / f".prognos_ims_test{test}_features_cache.npz"


def _load_cache(path: Path, n_channels: int) -> dict[str, tuple[int, int, int, np.ndarray]]:
    if not path.is_file():
        return {}
    try:
        with np.load(path, allow_pickle=False) as npz:
            if int(npz["version"]) != _CACHE_VERSION or int(npz["n_channels"]) != n_channels:
                return {}
            names, sizes, mtimes = npz["names"], npz["sizes"], npz["mtimes"]
            rows, values = npz["rows"], npz["values"]
    except Exception as exc:  # a broken cache is recomputed, never fatal
        warnings.warn(f"ignoring unreadable feature cache {path}: {exc}", stacklevel=3)
        return {}
    return {
        str(name): (int(size), int(mtime), int(n), vals)
        for name, size, mtime, n, vals in zip(names, sizes, mtimes, rows, values)
    }


def _save_cache(path: Path, n_channels: int, entries: dict) -> None:
    names = sorted(entries)
    tmp = path.with_name(path.name + ".tmp.npz")
    try:
        np.savez(
            tmp,
            version=np.int64(_CACHE_VERSION),
            n_channels=np.int64(n_channels),
            names=np.array(names, dtype=str),
            sizes=np.array([entries[n][0] for n in names], dtype=np.int64),
            mtimes=np.array([entries[n][1] for n in names], dtype=np.int64),
            rows=np.array([entries[n][2] for n in names], dtype=np.int64),
            values=np.stack([entries[n][3] for n in names]).astype(np.float64),
        )
        os.replace(tmp, path)
    except OSError as exc:
        warnings.warn(f"could not write the feature cache {path}: {exc}", stacklevel=3)


def _list_snapshot_files(
    directory: Path, exclude: set[Path]
) -> tuple[list[Path], list[SkippedFile]]:
    found, skipped = [], []
    for entry in sorted(directory.iterdir()):
        if entry in exclude or entry.name.endswith(".tmp.npz") or not entry.is_file():
            continue
        if snapshot_time(entry.name) is None:
            skipped.append(
                SkippedFile(str(entry), "name is not a snapshot time YYYY.MM.DD.hh.mm.ss")
            )
        else:
            found.append(entry)
    return found, skipped


def read_raw_features(
    directory: str | os.PathLike,
    test: int = 1,
    files: Iterable[str | os.PathLike] | None = None,
    cache: bool | str | os.PathLike = True,
    on_error: Literal["raise", "skip"] = "raise",
    expected_samples: int | None = None,
) -> IMSFeatures:
    """Time-domain features of raw IMS snapshot files, streamed one snapshot at a time.

    Args:
        directory: folder holding the ASCII snapshot files (e.g. the archive's ``1st_test``).
        test: IMS test number; sets the expected channel count (8 for test 1, 4 for 2 and 3).
        files: the snapshot files to read (paths relative to ``directory``, or absolute); ``None``
            reads every snapshot-named file directly in ``directory``. Files are ordered by the
            time in their names.
        cache: ``True`` keeps a cache ``.prognos_ims_test{test}_features_cache.npz`` in
            ``directory``; a path puts it there; ``False`` disables it. Entries are keyed by file
            name, size and modification time (ns) and hold full-precision features and the row
            count (checked against ``expected_samples``), so re-reading unchanged files is a
            lookup. A cache that cannot be written only warns.
        on_error: ``"raise"`` (default) raises :class:`IMSFormatError` naming the file and line
            of the first bad file; ``"skip"`` leaves bad files out, lists them in ``skipped`` and
            warns.
        expected_samples: when given, a file with another number of rows is a bad file
            (every IMS snapshot has :data:`IMS_SAMPLES` = 20,480).

    Returns:
        :class:`IMSFeatures` with ``values`` (T, C, 9) in :data:`FEATURE_NAMES` order, channels
        1..C, ``days`` since the first snapshot read; ``skipped`` lists files left out (bad
        content with ``on_error="skip"``, or files in ``directory`` whose name is not a snapshot
        time, which are never read). :meth:`IMSFeatures.to_csv` writes the shipped CSV format.

    Raises:
        FileNotFoundError: ``directory`` or a listed file does not exist, or no snapshot file
            was found.
        ValueError: unknown ``test``/``on_error``; a listed file whose name is not a snapshot
            time; two listed files of one snapshot time; no readable snapshot left.
        IMSFormatError: bad file content (with ``on_error="raise"``).
    """
    test = _check_test(test)
    n_channels = IMS_CHANNELS[test]
    if on_error not in ("raise", "skip"):
        raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    expected_samples = _check_expected_samples(expected_samples)
    if isinstance(cache, np.bool_):
        cache = bool(cache)
    if not isinstance(cache, (bool, str, os.PathLike)) and cache is not None:
        # (1 failed in Path() with "expected str, bytes or os.PathLike object, not int")
        raise TypeError(f"cache must be True, False or a file path, got {cache!r}")
    directory = Path(directory)
    if not directory.exists():
        raise FileNotFoundError(f"IMS raw data directory not found: {directory}")
    if not directory.is_dir():
        raise NotADirectoryError(f"IMS raw data path is not a directory: {directory}")

    if cache is True:
        cache_path: Path | None = _default_cache_path(directory, test)
    elif cache is False or cache is None:
        cache_path = None
    else:
        cache_path = Path(cache)

    skipped: list[SkippedFile] = []
    if files is None:
        exclude = {cache_path} if cache_path is not None else set()
        paths, skipped = _list_snapshot_files(directory, exclude)
        if not paths:
            raise FileNotFoundError(
                f"no snapshot files named YYYY.MM.DD.hh.mm.ss found in {directory}"
            )
    else:
        if isinstance(files, (str, os.PathLike)):
            raise TypeError("files must be a sequence of file names or paths, not a single one")
        paths = []
        for item in files:
            path = Path(item)
            path = path if path.is_absolute() else directory / path
            if not path.is_file():
                raise FileNotFoundError(f"IMS snapshot file not found: {path}")
            if snapshot_time(path.name) is None:
                raise ValueError(f"files: {path.name!r} is not a snapshot name YYYY.MM.DD.hh.mm.ss")
            paths.append(path)
        if not paths:
            raise ValueError("files is empty: give at least one snapshot file")
    paths.sort(key=lambda p: (snapshot_time(p.name), p.name))
    for a, b in zip(paths, paths[1:]):
        if snapshot_time(a.name) == snapshot_time(b.name):  # (one name, listed twice)
            raise ValueError(
                f"files: two files for the snapshot time {a.name}: {a} and {b} (one snapshot "
                "per time; list each once)"
            )

    entries = _load_cache(cache_path, n_channels) if cache_path is not None else {}
    changed = False
    stamps, values = [], []
    bad: list[SkippedFile] = []
    for path in paths:
        stat = path.stat()
        key = path.name
        hit = entries.get(key)
        try:
            if hit is not None and hit[0] == stat.st_size and hit[1] == stat.st_mtime_ns:
                if expected_samples is not None and hit[2] != expected_samples:
                    # (the check read_snapshot makes, on the row count the cache kept)
                    raise IMSFormatError(path, f"{hit[2]} sample rows, expected {expected_samples}")
                feats = hit[3]
            else:
                data = read_snapshot(path, n_channels, expected_samples)
                feats = snapshot_features(data)
                entries[key] = (stat.st_size, stat.st_mtime_ns, data.shape[0], feats)
                del data  # one snapshot in memory at a time
                changed = True
        except IMSFormatError as exc:
            if on_error == "raise":
                raise
            bad.append(SkippedFile(str(path), str(exc)))
            continue
        stamps.append(np.datetime64(snapshot_time(path.name), "s"))
        values.append(feats)

    skipped.extend(bad)
    if bad:
        listing = "; ".join(f"{s.path}: {s.reason}" for s in bad[:5])
        more = f" (and {len(bad) - 5} more)" if len(bad) > 5 else ""
        warnings.warn(
            f"skipped {len(bad)} unreadable snapshot file(s): {listing}{more}", stacklevel=2
        )
    if not values:
        raise ValueError(f"no readable snapshot in {directory}; skipped: {skipped}")
    if cache_path is not None and changed:
        _save_cache(cache_path, n_channels, entries)
    return _build(test, stamps, np.stack(values), range(1, n_channels + 1), skipped)


# --------------------------------------------------------------------------- shipped table


def default_data_dir() -> Path:
    """The repository's ``datasets/ims`` folder (two levels above this package)."""
    return Path(__file__).resolve().parents[2] / "datasets" / "ims"


def load_ims_features(test: int = 1, path: str | os.PathLike | None = None) -> IMSFeatures:
    """Read a tidy IMS feature table such as the shipped ``datasets/ims/test1_features.csv``.

    Args:
        test: IMS test number (1, 2 or 3); all three are shipped (tests 2 and 3 without the
            first-50 raw cross-check, see ``datasets/ims/README.md``).
        path: the CSV file, or a folder holding ``test{test}_features.csv``; ``None`` uses
            :func:`default_data_dir`.

    Returns:
        :class:`IMSFeatures`: for the shipped test 1, 2,156 snapshots x 8 channels x 9 features
        over 34.5 days; the median is NaN except where the table has it.

    Raises:
        ValueError: unknown ``test``; a malformed table (header, no row, channel numbers, a
            missing or duplicated (timestamp, channel) row, a non-numeric or infinite cell).
        FileNotFoundError: no such table.
    """
    test = _check_test(test)
    n_channels = IMS_CHANNELS[test]
    if path is None:
        path = default_data_dir() / f"test{test}_features.csv"
        if not path.is_file():
            hint = (
                "tests 1, 2 and 3 are shipped in datasets/ims; pass path= to locate the table, "
                "or build one with read_raw_features(...).to_csv()"
            )
            raise FileNotFoundError(f"IMS feature table not found: {path} ({hint})")
    path = Path(path)
    if path.is_dir():
        path = path / f"test{test}_features.csv"
    if not path.is_file():
        raise FileNotFoundError(f"IMS feature table not found: {path}")

    with open(path, encoding="utf-8", newline="") as handle:
        reader = csv.reader(handle)
        header = tuple(next(reader, ()))
        if header != _CSV_HEADER:
            raise ValueError(f"{path}: header must be {','.join(_CSV_HEADER)}, got {header}")
        rows = list(reader)
    if not any(rows):
        raise ValueError(f"{path}: the table holds no rows (its header alone)")
    # snapshots in time order, one per instant however its date-time is written ("T" or a
    # space, an offset): sorting the texts put "2004-02-12 12:02:39" before every "...T..."
    second: dict[str, int] = {}
    for line, row in enumerate(rows, start=2):
        if row and row[0] not in second:
            try:
                v = np.datetime64(row[0].strip(), "s")
            except ValueError:
                v = np.datetime64("NaT")
            if np.isnat(v):
                raise ValueError(
                    f"{path}, line {line}: timestamp {row[0]!r} is not an ISO 8601 date-time "
                    "(every row names its snapshot's date-time)"
                )
            second[row[0]] = int(v.astype("int64"))
    order = sorted(set(second.values()))
    index = {s: i for i, s in enumerate(order)}
    stamps = np.array(order, dtype="int64").astype("datetime64[s]")
    values = np.full((len(order), n_channels, len(FEATURE_NAMES)), np.nan)
    seen = np.zeros((len(order), n_channels), dtype=bool)
    for line, row in enumerate(rows, start=2):
        if not row:
            continue
        if len(row) != len(_CSV_HEADER):
            raise ValueError(f"{path}, line {line}: {len(row)} cells, expected {len(_CSV_HEADER)}")
        try:
            channel = int(row[1])
            feats = [float(cell) if cell else math.nan for cell in row[2:]]
        except ValueError as exc:
            raise ValueError(f"{path}, line {line}: {exc}") from None
        for name, value, cell in zip(FEATURE_NAMES, feats, row[2:]):
            if math.isinf(value):  # (an empty cell or NaN is a missing feature)
                raise ValueError(
                    f"{path}, line {line}: non-finite value {cell!r} in column {name!r}"
                )
        if not 1 <= channel <= n_channels:
            raise ValueError(
                f"{path}, line {line}: channel {channel} outside 1..{n_channels} (test {test})"
            )
        t = index[second[row[0]]]
        if seen[t, channel - 1]:
            raise ValueError(
                f"{path}, line {line}: duplicate row {stamps[t]} channel {channel}"
                + (f" (written {row[0]!r} here)" if row[0] != str(stamps[t]) else "")
            )
        seen[t, channel - 1] = True
        values[t, channel - 1] = feats
    if not seen.all():
        t, c = np.argwhere(~seen)[0]
        raise ValueError(f"{path}: no row for {stamps[t]} channel {c + 1}")
    return _build(test, stamps, values, range(1, n_channels + 1))


# --------------------------------------------------------------------------- health indicator


@dataclass(frozen=True)
class HealthIndicator:
    """Paper 002's LLE monitoring index of one bearing, on a training and a test channel.

    Attributes:
        days: float64 (T,), days since the start of the test.
        timestamps: (T,) ``numpy.datetime64[s]``.
        train: float64 (T,), the index of ``train_channel``.
        test: float64 (T,), the index of ``test_channel``.
        train_channel, test_channel: 1-based channels.
        feature_names: the features embedded.
        mode: ``"transform"`` or ``"separate"`` (see :func:`health_indicator`).
        fit: the LLE fitted on the training channel (standardised features).
        center, scale: the standardisation applied before the training channel's fit, (F,).
    """

    days: Tensor
    timestamps: np.ndarray
    train: Tensor
    test: Tensor
    train_channel: int
    test_channel: int
    feature_names: tuple[str, ...]
    mode: str
    fit: LLEFit
    center: Tensor
    scale: Tensor

    @property
    def elapsed(self) -> Tensor:
        """Days since the first snapshot of the window, (T,) (paper 002's 0-12 day axis)."""
        return self.days - self.days[0]


def _standardise_stats(X: Tensor, name: str, names: Sequence[str]) -> tuple[Tensor, Tensor]:
    if X.shape[0] < 2:  # (one snapshot gave a NaN std and "X ... contains non-finite values")
        raise ValueError(
            f"{name}: {X.shape[0]} snapshot(s) in the window, need at least 2 to standardise "
            "(a longer last_days?)"
        )
    if not bool(torch.isfinite(X).all()):
        bad = [names[j] for j in range(X.shape[1]) if not bool(torch.isfinite(X[:, j]).all())]
        raise ValueError(
            f"{name}: feature(s) {bad} have missing values in this window (the shipped table has "
            "no median after the first 50 snapshots); choose other feature_names"
        )
    center, scale = X.mean(0), X.std(0, correction=1)
    if bool((scale == 0).any()):
        const = [names[j] for j in range(X.shape[1]) if float(scale[j]) == 0]
        raise ValueError(f"{name}: feature(s) {const} are constant; cannot standardise")
    return center, scale


def _orient(y: Tensor, rms: Tensor) -> Tensor:
    """+1 or -1 so that ``sign * y`` correlates positively with ``rms`` (both (T,))."""
    yc, rc = y - y.mean(), rms - rms.mean()
    return torch.where((yc * rc).sum() < 0, -1.0, 1.0).to(y.dtype)


def health_indicator(
    features: IMSFeatures | None = None,
    *,
    bearing: int = 3,
    train_channel: int | None = None,
    test_channel: int | None = None,
    feature_names: Sequence[str] = HI_FEATURES,
    last_days: float | None = 12.0,
    n_neighbors: int = 12,
    reg: float = 1e-3,
    mode: Literal["transform", "separate"] = "transform",
) -> HealthIndicator:
    """Paper 002's monitoring index: features -> standardisation -> LLE (K = 12, d = 1).

    Recipe (paper 002, Sec. "Experiments", Fig. 7): for bearing 3 of IMS test 1 (inner-race
    defect) take the per-snapshot time-domain features of the last 12 days, standardise them,
    and reduce them to one dimension with locally linear embedding with 12 nearest neighbours
    (:mod:`prognos_torch.datasets.lle`). The predictor is trained on one accelerometer channel and
    tested on the other one of the same bearing.

    Missing median: the paper embeds seven features (mean, median, std, skewness, rms, std_error,
    kurtosis). The shipped table has the median only for the first 50 snapshots, so the default
    uses the other six (:data:`HI_FEATURES`). In test 1 the median is a quantised (0.001 g)
    near-copy of the mean (DC offset about -0.09 g; correlation with the mean 0.67 and 0.81 on
    channels 5 and 6 over the first 50 snapshots), so after standardisation it mostly doubled the
    weight of the mean in the Euclidean neighbour search; without it the neighbourhoods weigh the
    mean once. (std and std_error are exactly proportional and stay counted twice, as in the
    paper.) Pass ``feature_names=PAPER_FEATURES`` with a table that has the median (built from
    the raw archive) to follow the paper exactly.

    Standardisation: z-scores (mean, std with ddof = 1) over the window.

    Train/test (``mode``):

    * ``"transform"`` (default): the standardisation and the LLE are fitted on the training
      channel only; the test channel is standardised with the *training* statistics and mapped by
      LLE's out-of-sample rule (reconstruction weights of each test point from its 12 nearest
      training points, applied to their embedding). Both series then share one coordinate, so a
      predictor trained on one applies to the other. This is a choice of this library; the paper
      does not say how the test index was produced.
    * ``"separate"``: each channel is standardised with its own statistics and embedded on its
      own. The two coordinates are then unrelated up to scale and sign.

    Sign: LLE's sign is arbitrary; the training index is oriented to correlate positively with the
    training channel's rms (so it grows with degradation) and, in ``"transform"`` mode, the test
    index inherits that orientation; in ``"separate"`` mode the test index is oriented by its own
    rms. Scale: Roweis & Saul's constraint, unit mean square over the training window.

    Measured on the shipped table with the defaults (channels 5 -> 6): Spearman correlation with
    time over the last 12 days (1,263 snapshots) is about 0.65 for channel 5 and 0.75 for channel
    6 (0.52 for channel 6 in ``"separate"`` mode).

    Args:
        features: an IMS feature table; ``None`` loads the shipped test 1.
        bearing: bearing number (paper: 3).
        train_channel, test_channel: 1-based channels; default the bearing's two channels in
            order (the IMS documentation does not say which of the pair is vertical).
        feature_names: features to embed, default :data:`HI_FEATURES`.
        last_days: window length in days, counted back from the last snapshot; ``None`` keeps all.
        n_neighbors: K of LLE (paper: 12).
        reg: LLE regulariser.
        mode: ``"transform"`` or ``"separate"``.

    Returns:
        :class:`HealthIndicator` with the two (T,) series and their time.
    """
    if features is None:
        features = load_ims_features(1)
    if mode not in ("transform", "separate"):
        raise ValueError(f"mode must be 'transform' or 'separate', got {mode!r}")
    channels = bearing_channels(features.test, bearing)
    if train_channel is None:
        train_channel = channels[0]
    if test_channel is None:
        if len(channels) < 2:
            raise ValueError(
                f"bearing {bearing} of test {features.test} has one channel; give test_channel"
            )
        test_channel = channels[1]
    if train_channel == test_channel:
        raise ValueError(f"train_channel and test_channel must differ, both are {train_channel}")
    if isinstance(feature_names, str):
        raise TypeError("feature_names must be a sequence of names, not a single string")
    names = tuple(feature_names)
    if "rms" not in features.feature_names:
        raise ValueError("features must include 'rms' (used to orient the indicator)")
    window = features if last_days is None else features.last_days(last_days)
    sub = window.select(names, [train_channel, test_channel])
    X_train, X_test = sub.values[:, 0], sub.values[:, 1]  # (T, F)
    rms = window.feature("rms")
    rms_train = rms[:, window.channels.index(train_channel)]
    rms_test = rms[:, window.channels.index(test_channel)]

    center, scale = _standardise_stats(X_train, f"channel {train_channel}", names)
    fit = lle_fit((X_train - center) / scale, 1, n_neighbors, reg)
    y_train = fit.embedding[:, 0]
    sign = _orient(y_train, rms_train)
    y_train = sign * y_train
    if mode == "transform":
        y_test = sign * fit.transform((X_test - center) / scale)[:, 0]
    else:
        c_test, s_test = _standardise_stats(X_test, f"channel {test_channel}", names)
        y_test = lle_fit((X_test - c_test) / s_test, 1, n_neighbors, reg).embedding[:, 0]
        y_test = _orient(y_test, rms_test) * y_test
    return HealthIndicator(
        days=window.days,
        timestamps=window.timestamps,
        train=y_train,
        test=y_test,
        train_channel=train_channel,
        test_channel=test_channel,
        feature_names=names,
        mode=mode,
        fit=fit,
        center=center,
        scale=scale,
    )
