"""Reader of the PRONOSTIA (FEMTO-ST, IEEE PHM 2012 challenge) bearing run-to-failure records.

PRONOSTIA (Nectoux et al. 2012) ran 17 bearings to failure under three conditions (1: 1800 rpm,
4000 N; 2: 1650 rpm, 4200 N; 3: 1500 rpm, 5000 N). Every 10 s it recorded 0.1 s of horizontal
and vertical acceleration at 25.6 kHz (2,560 samples); each record is one file ``acc_NNNNN.csv``
with the columns hour, minute, second, microsecond, horizontal, vertical (``,`` or ``;``
separated) in a folder per bearing. The challenge's archive holds the six learning bearings
(``Learning_set/Bearing1_1`` ...) and the eleven test bearings, truncated (``Test_set``) and
whole (``Full_Test_Set``). The data are not shipped with the library (their licence is not
stated); :func:`find_pronostia_bearings` finds the run-to-failure folders in a local copy and
:func:`read_pronostia_bearing` turns one into features, with the same time-domain features as
the IMS reader (:func:`~prognos_torch.datasets.ims.snapshot_features`).

Reference: P. Nectoux et al., "PRONOSTIA: An experimental platform for bearings accelerated
degradation tests", IEEE PHM 2012.
"""

from __future__ import annotations

import io
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .ims import FEATURE_NAMES, _check_expected_samples, _feature_position, snapshot_features

__all__ = [
    "PRONOSTIA_AXES",
    "PRONOSTIA_RECORD_SAMPLES",
    "PronostiaFeatures",
    "find_pronostia_bearings",
    "read_pronostia_bearing",
]

#: Axes of a record, in file order (columns 5 and 6).
PRONOSTIA_AXES: tuple[str, ...] = ("horizontal", "vertical")
#: Samples per axis in every record (0.1 s at 25.6 kHz).
PRONOSTIA_RECORD_SAMPLES = 2560
_PERIOD_S = 10.0  # one record every 10 s (Nectoux et al. 2012)
_RECORD = re.compile(r"^acc_(\d+)\.csv$")
_BEARING = re.compile(r"^Bearing(\d)_(\d+)$")
# whole run-to-failure records first; Test_set holds the test bearings cut before failure
_RUN_TO_FAILURE_SETS = ("Learning_set", "Full_Test_Set")


@dataclass(frozen=True)
class PronostiaFeatures:
    """Per-record features of one PRONOSTIA bearing.

    Attributes:
        bearing: the bearing's name, e.g. ``"Bearing1_1"``; condition: its operating condition
            (1, 2 or 3).
        hours: ``(T,)`` float64, hours since the first record: the record number times the
            platform's 10 s acquisition period (the records' own clock has defects, below).
        clock_mismatch: records whose clock step from the previous record (midnight wraps
            allowed) is not the 10 s per record number that ``hours`` assumes, to within 1 s
            (in ``Learning_set/Bearing1_1`` two records are stamped hours off, so the steps
            into them and out of them are listed: ``acc_02121`` to ``acc_02123``).
        values: ``(T, 2, F)`` float64: ``values[record, axis, feature]``, axes
            :data:`PRONOSTIA_AXES`, features :data:`~prognos_torch.datasets.ims.FEATURE_NAMES`.
        files: the record files read, in time order.
    """

    bearing: str
    condition: int
    hours: Tensor
    values: Tensor
    files: tuple[str, ...]
    clock_mismatch: tuple[str, ...] = ()

    def feature(self, name: str) -> Tensor:
        """``(T, 2)``: one feature of both axes (horizontal, vertical)."""
        return self.values[:, :, _feature_position(FEATURE_NAMES, name)]


def find_pronostia_bearings(root: str | os.PathLike) -> dict[str, Path]:
    """The run-to-failure bearing folders of a PRONOSTIA copy, by bearing name.

    Looks for ``Bearing<c>_<k>`` folders holding ``acc_*.csv`` files under ``root`` (``root``
    itself may be one), taking ``Learning_set`` and ``Full_Test_Set`` over the truncated
    ``Test_set`` (which is skipped: its bearings stop before failure).

    Returns:
        ``{name: folder}`` in name order.

    Raises:
        FileNotFoundError: ``root`` is no folder, or holds no bearing folder.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"PRONOSTIA root {root} is not a folder")
    found: dict[str, Path] = {}
    candidates = [root] if _BEARING.match(root.name) else sorted(root.rglob("Bearing*_*"))
    for d in candidates:
        if not (d.is_dir() and _BEARING.match(d.name)):
            continue
        if d.parent.name == "Test_set" or not any(_RECORD.match(f.name) for f in d.iterdir()):
            continue
        if d.name in found and found[d.name].parent.name in _RUN_TO_FAILURE_SETS:
            continue
        found[d.name] = d
    if not found:
        truncated = root.name == "Test_set" or (root / "Test_set").is_dir()
        raise FileNotFoundError(
            f"no PRONOSTIA bearing folder (Bearing<c>_<k> with acc_*.csv records) under {root}"
            + (
                " but those of Test_set, which stop before failure: give the archive's root, "
                "Learning_set or Full_Test_Set"
                if truncated
                else ""
            )
        )
    return dict(sorted(found.items()))


_COLUMNS = "hour, minute, second, microsecond, horizontal, vertical"


def _read_record(path: Path, expected_samples: int | None) -> np.ndarray:
    raw = path.read_bytes().replace(b";", b",")
    if not raw.strip():
        raise ValueError(f"{path}: the record holds no rows (an empty file)")
    try:
        a = np.loadtxt(io.BytesIO(raw), delimiter=",", dtype=np.float64, ndmin=2)
    except ValueError as exc:
        for number, line in enumerate(raw.splitlines(), start=1):  # a row cut short?
            n = len(line.split(b",")) if line.strip() else 6
            if n != 6:
                raise ValueError(
                    f"{path}, row {number}: {n} columns, expected 6 ({_COLUMNS}); a truncated file?"
                ) from None
        raise ValueError(f"{path}: not a numeric record ({exc})") from None
    if a.shape[1] != 6:
        raise ValueError(f"{path}: expected rows of 6 columns ({_COLUMNS}), got shape {a.shape}")
    if a.shape[0] < 2:  # (was "expected rows of 6 columns" for one row of 6 columns)
        raise ValueError(f"{path}: {a.shape[0]} row, need at least 2 samples per record")
    if expected_samples is not None and a.shape[0] != expected_samples:
        raise ValueError(f"{path}: expected {expected_samples} rows, got {a.shape[0]}")
    bad = ~np.isfinite(a)
    if bad.any():  # (the IMS reader refuses them too: a feature would be NaN or inf)
        r, c = np.argwhere(bad)[0]
        raise ValueError(f"{path}, row {r + 1}, column {c + 1}: non-finite value {a[r, c]}")
    return a


def read_pronostia_bearing(
    folder: str | os.PathLike, *, expected_samples: int | None = PRONOSTIA_RECORD_SAMPLES
) -> PronostiaFeatures:
    """Features of every record of one bearing folder (module docstring).

    Args:
        folder: a ``Bearing<c>_<k>`` folder of ``acc_NNNNN.csv`` records.
        expected_samples: rows every record must have (``None``: any number from 2).

    Returns:
        :class:`PronostiaFeatures`, records in file-number order.

    Raises:
        FileNotFoundError: no such folder, or no record in it.
        ValueError: a record that is not 6 numeric columns or has another number of rows than
            ``expected_samples`` (named with its path).
    """
    expected_samples = _check_expected_samples(expected_samples)
    folder = Path(folder)
    m = _BEARING.match(folder.name)
    if m is None or not folder.is_dir():
        raise FileNotFoundError(f"{folder} is no PRONOSTIA bearing folder (Bearing<c>_<k>)")
    records = sorted(
        ((int(r.group(1)), f) for f in folder.iterdir() if (r := _RECORD.match(f.name))),
        key=lambda p: p[0],
    )
    if not records:
        raise FileNotFoundError(f"{folder} holds no acc_NNNNN.csv record")
    for (k, f), (k2, f2) in zip(records, records[1:]):
        if k == k2:  # acc_5.csv beside acc_00005.csv: one record number twice
            raise ValueError(f"{folder}: {f.name} and {f2.name} are both record {k}")
    clock = np.empty(len(records))
    feats = np.empty((len(records), 2, len(FEATURE_NAMES)))
    for i, (_, f) in enumerate(records):
        a = _read_record(f, expected_samples)
        h, mi, s, us = a[0, :4]
        clock[i] = 3600.0 * h + 60.0 * mi + s + 1e-6 * us
        feats[i] = snapshot_features(a[:, 4:6])
    number = np.array([k for k, _ in records], dtype=np.float64)
    step = np.diff(clock) % 86400.0  # the clock wraps at midnight
    bad = np.abs(step - _PERIOD_S * np.diff(number)) > 1.0
    return PronostiaFeatures(
        bearing=folder.name,
        condition=int(m.group(1)),
        hours=torch.from_numpy((number - number[0]) * (_PERIOD_S / 3600.0)),
        values=torch.from_numpy(feats),
        files=tuple(f.name for _, f in records),
        clock_mismatch=tuple(records[i + 1][1].name for i in np.nonzero(bad)[0]),
    )
