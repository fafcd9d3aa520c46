"""A shard of a fleet as one padded batch, and the degradation onset of every asset in it.

The fleet's RUL methods (:mod:`prognos_torch.fleet.trend`, :mod:`prognos_torch.fleet.per_asset`)
take ONE padded batch of ragged series (:class:`PaddedBatch`, made by :func:`pad_batch`: left
aligned, NaN padding) and return per-asset results. Each asset draws from its own seed
(:func:`asset_seed`, from the fleet seed and the asset id), so that no result depends on how
the fleet was sharded.

**Onset** (first prediction time, :func:`ksigma_onset_batch`): the k-sigma rule on a trailing
moving median against a healthy baseline (the first ``baseline`` fraction of each asset's
observed time span; mean and standard deviation ddof = 1; moving median over the observed
samples, window ``w``; onset = first of ``c`` consecutive medians beyond ``mean + k std`` in the
degradation direction, after the healthy window, which is taken as healthy: a run-in transient
in it is no onset). This is the rule of :func:`prognos_torch.prognosis.onset.ksigma_onset` with
``after`` the window's end, as in :func:`~prognos_torch.workflow.prognose`, batched over assets
with NaN padding.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..core.validation import check_seed, is_int, is_real
from ..prognosis.onset import (
    GLITCH_SCREEN,
    short_term_noise,
    window_end,
    window_median_deviation,
)

__all__ = [
    "DIRECTIONS",
    "PaddedBatch",
    "asset_seed",
    "pad_batch",
    "check_rows",
    "check_min_rows",
    "check_onset_rule",
    "BatchOnset",
    "ksigma_onset_batch",
]

#: the failure directions the exponential trend takes
DIRECTIONS = ("above", "below")


def check_min_rows(min_rows) -> int:
    """``min_rows``, the observed rows an asset needs for a RUL: an int >= 1 (``TypeError``,
    ``ValueError``); 0 or less would send assets without a value to the trend fit."""
    if not is_int(min_rows):
        raise TypeError(f"min_rows must be an int (observed rows), got {min_rows!r}")
    if min_rows < 1:
        raise ValueError(f"min_rows must be >= 1 (observed rows), got {min_rows}")
    return int(min_rows)


def check_onset_rule(baseline, k, window, consecutive, direction) -> tuple:
    """The onset rule's settings as :func:`~prognos_torch.prognosis.onset.ksigma_onset` and
    ``healthy_baseline`` take them (``ValueError`` naming the setting): ``baseline`` in (0, 1],
    ``k`` finite > 0, ``window`` and ``consecutive`` ints >= 1, ``direction`` a side."""
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be 'above' or 'below', got {direction!r}")
    if not is_real(baseline) or not 0.0 < baseline <= 1.0:
        raise ValueError(f"baseline fraction must be a number in (0, 1], got {baseline!r}")
    if not is_real(k) or not 0.0 < k < math.inf:
        raise ValueError(f"k must be a finite number > 0, got {k!r}")
    for name, v in (("window", window), ("consecutive", consecutive)):
        if not is_int(v) or v < 1:
            raise ValueError(f"{name} must be an int >= 1, got {v!r}")
    return float(baseline), float(k), int(window), int(consecutive), direction


def asset_seed(seed: int, asset: str) -> int:
    """A 63-bit seed from the fleet seed and the asset id (BLAKE2b of both; stable everywhere)."""
    h = hashlib.blake2b(f"{int(seed)}\x1f{asset}".encode(), digest_size=8).digest()
    return int.from_bytes(h, "little") & (2**63 - 1)


@dataclass(frozen=True, eq=False)
class PaddedBatch:
    """A shard of ragged series, left-aligned and padded with NaN.

    Attributes:
        assets: the ``B`` asset ids.
        values: ``(B, T)`` float64 (NaN: missing or padding).
        times: ``(B, T)`` float64 (NaN in the padding).
        lengths: ``(B,)`` int64 number of rows of each asset.
        seeds: ``(B,)`` per-asset seeds (:func:`asset_seed`).
    """

    assets: list[str]
    values: Tensor
    times: Tensor
    lengths: Tensor
    seeds: list[int]

    def __len__(self) -> int:
        return len(self.assets)


def pad_batch(assets, times, values, seed: int = 0) -> PaddedBatch:
    """Pad per-asset 1-D arrays into a :class:`PaddedBatch` (float64, NaN padding). Each
    asset's times must be finite and strictly increasing (as a fleet table's are); its values
    may be NaN (missing), not infinite."""
    seed = check_seed(seed)
    B = len(assets)
    if not (len(times) == len(values) == B) or B == 0:
        raise ValueError("assets, times and values must be non-empty and of one length")
    for name, arrays in (("times", times), ("values", values)):
        for a, arr in zip(assets, arrays):  # (a cast would read True as 1, drop an imaginary part)
            if np.asarray(arr).dtype.kind in "bc":
                raise ValueError(f"asset {a!r}: {name} must be real numbers, got dtype "
                                 f"{np.asarray(arr).dtype}")  # fmt: skip
    times = [np.asarray(t, dtype=np.float64) for t in times]
    values = [np.asarray(v, dtype=np.float64) for v in values]
    lengths = [len(v) if v.ndim == 1 else -1 for v in values]
    T = max(max(lengths), 1)
    V = np.full((B, T), np.nan)
    X = np.full((B, T), np.nan)
    for i, (t, v) in enumerate(zip(times, values)):
        if t.ndim != 1 or v.ndim != 1:
            raise ValueError(
                f"asset {assets[i]!r}: times and values must be 1-D, got shapes {t.shape} and "
                f"{v.shape}"
            )
        if len(t) != len(v):
            raise ValueError(f"asset {assets[i]!r}: {len(t)} times but {len(v)} values")
        if not np.isfinite(t).all() or not (np.diff(t) > 0).all():
            raise ValueError(
                f"asset {assets[i]!r}: times must be finite and strictly increasing, got "
                f"{t.tolist() if t.size <= 6 else t}"
            )
        if np.isinf(v).any():  # (the engine refused it for the whole shard, naming no asset)
            raise ValueError(
                f"asset {assets[i]!r}: values must be numbers or NaN (missing), got "
                f"{v[np.isinf(v)][0]} at row {int(np.flatnonzero(np.isinf(v))[0]) + 1}"
            )
        V[i, : len(v)] = v
        X[i, : len(t)] = t
    return PaddedBatch(
        assets=list(assets),
        values=torch.from_numpy(V),
        times=torch.from_numpy(X),
        lengths=torch.tensor(lengths, dtype=torch.int64),
        seeds=[asset_seed(seed, a) for a in assets],
    )


def check_rows(values, times, lengths) -> None:
    """A padded batch's ``values`` and ``times`` ``(B, T)`` float tensors and ``lengths`` ``(B,)``
    ints in ``[0, T]``; within each row's length, finite and strictly increasing times and values
    that are numbers or NaN (missing), as :func:`pad_batch` makes them and the per-series rule
    takes them (``ValueError`` naming the argument; a ``(1,)`` ``lengths`` was broadcast to
    every row, infinite values were taken as numbers)."""
    for name, x in (("values", values), ("times", times)):
        if not isinstance(x, Tensor) or x.dim() != 2 or not x.is_floating_point():
            got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
            raise ValueError(f"{name} must be a (B, T) float tensor, got {got}")
    if times.shape != values.shape:
        raise ValueError(
            f"times must have the shape of values {tuple(values.shape)}, got {tuple(times.shape)}"
        )
    B, T = values.shape
    if (
        not isinstance(lengths, Tensor)
        or lengths.shape != (B,)
        or lengths.dtype.is_floating_point
        or lengths.dtype in (torch.bool, torch.complex64, torch.complex128)
    ):
        got = tuple(lengths.shape) if isinstance(lengths, Tensor) else type(lengths).__name__
        raise ValueError(f"lengths must be a ({B},) int tensor, got {got}")
    if B and not bool(((lengths >= 0) & (lengths <= T)).all()):
        raise ValueError(
            f"lengths must lie in [0, {T}] (the rows of values), got {lengths.tolist()}"
        )
    rows = torch.arange(T, device=values.device) < lengths[:, None]
    if bool((rows & torch.isinf(values)).any()):
        raise ValueError(
            "values must be numbers or NaN (missing) within each row's length, got inf"
        )
    gaps = torch.diff(times, dim=1) > 0
    if not bool(torch.isfinite(times[rows]).all()) or not bool((gaps | ~rows[:, 1:]).all()):
        raise ValueError("times must be finite and strictly increasing within each row's length")


# --------------------------------------------------------------------------- onset
@dataclass(frozen=True)
class BatchOnset:
    """Per-asset onset of :func:`ksigma_onset_batch` (``(B,)`` tensors)."""

    index: Tensor  # int64 original row index of the onset, -1 if none
    time: Tensor  # float64, NaN if none
    baseline_ok: Tensor  # bool
    base_mean: Tensor
    base_std: Tensor
    in_baseline: Tensor  # (B, T) bool: row belongs to the baseline window
    # std of the window over its std without the isolated outliers beyond GLITCH_SCREEN noise
    # std (healthy_baseline(..., glitch_limit=GLITCH_SCREEN)); 1 where there are none
    glitch_widening: Tensor


def ksigma_onset_batch(
    values: Tensor,
    times: Tensor,
    lengths: Tensor,
    *,
    baseline: float = 0.3,
    k: float = 4.0,
    window: int = 5,
    consecutive: int = 5,
    direction: str = "above",
    skip_window: bool = False,
) -> BatchOnset:
    """The k-sigma moving-median onset rule (module docstring), batched over ``(B, T)`` rows.

    ``skip_window=True`` counts only exceedances after each row's healthy window (the
    per-series rule with ``after=Baseline.t_end``): a run-in transient in it is no onset, and,
    as in the per-series rule, neither are the first ``window - 1`` observed samples of a row,
    whose trailing window is partial (the fleet's rule)."""
    baseline, k, window, consecutive, direction = check_onset_rule(
        baseline, k, window, consecutive, direction
    )
    check_rows(values, times, lengths)
    B, T = values.shape
    sign = 1.0 if direction == "above" else -1.0
    cols = torch.arange(T, device=values.device)
    obs = ~torch.isnan(values) & (cols < lengths[:, None])
    n_obs = obs.sum(1)
    # observed samples first, in time order (stable sort on the missing flag)
    perm = torch.sort((~obs).to(torch.int8), dim=1, stable=True).indices
    xc = values.gather(1, perm)
    tc = times.gather(1, perm)
    valid = cols < n_obs[:, None]
    xc = torch.where(valid, xc, torch.full_like(xc, math.nan))
    last = (n_obs - 1).clamp(min=0)
    t0 = tc[:, 0]
    t1 = tc.gather(1, last[:, None])[:, 0]
    inside = valid & (tc <= window_end(t0, t1, baseline)[:, None])  # as healthy_baseline
    nb = inside.sum(1)
    xs = torch.where(inside, xc, torch.zeros_like(xc))
    mean = xs.sum(1) / nb.clamp(min=1)
    dev = torch.where(inside, xc - mean[:, None], torch.zeros_like(xc))
    std = torch.sqrt((dev * dev).sum(1) / (nb - 1).clamp(min=1))
    # a window of one repeated value has no spread (its round-off std, 1.5e-17 for 0.1s, none)
    std = torch.where((inside & (xc != xc[:, :1])).any(1), std, torch.zeros_like(std))
    ok = (nb >= 3) & (std > 0) & (n_obs >= 1)
    pad = torch.full((B, window - 1), math.nan, dtype=xc.dtype, device=xc.device)
    # the median of the series oriented to the direction (the lower middle of an even window),
    # as prognosis.ksigma_onset: a falling series needs the documented majority past the limit
    med = torch.cat([pad, sign * xc], 1).unfold(1, window, 1).nanmedian(-1).values  # (B, T)
    z = (med - sign * mean[:, None]) / torch.where(ok, std, torch.ones_like(std))[:, None]
    # after the window, as the per-series rule, the first w - 1 observed samples (a partial
    # trailing window, not the documented rate) raise no alarm; without skip_window they do
    late = valid & ~inside & (cols >= window - 1) if skip_window else valid
    above = (late & (z > k)).to(torch.int64)
    if T < consecutive:
        above = torch.cat([above, above.new_zeros(B, consecutive - T)], 1)
    runs = above.unfold(1, consecutive, 1).sum(-1) == consecutive  # (B, T - c + 1)
    found = runs.any(1) & ok
    first_c = torch.argmax(runs.to(torch.int8), dim=1)
    first_c = torch.where(found, first_c, torch.zeros_like(first_c))
    index = torch.where(found, perm.gather(1, first_c[:, None])[:, 0], torch.full_like(n_obs, -1))
    time = torch.where(found, tc.gather(1, first_c[:, None])[:, 0], torch.full_like(t0, math.nan))
    in_base = torch.zeros_like(obs)
    in_base.scatter_(1, perm, inside)
    return BatchOnset(index, time, ok, mean, std, in_base, _glitch_widening(xc, inside, std))


def _glitch_widening(xc: Tensor, inside: Tensor, std: Tensor) -> Tensor:
    """``(B,)`` healthy std over the std without the window's isolated outliers beyond
    :data:`~prognos_torch.prognosis.onset.GLITCH_SCREEN` noise std, as ``healthy_baseline``
    computes both for one asset (``xc``: observed values first, in time order; ``inside``: the
    healthy window, a prefix of them)."""
    xw = torch.where(inside, xc, torch.full_like(xc, math.nan))
    noise = short_term_noise(xw)  # Baseline.noise of each window
    dev_w = window_median_deviation(xw)
    out = inside & (dev_w > GLITCH_SCREEN * noise[:, None]) & (noise > 0)[:, None]
    kept = inside & ~out
    nk = kept.sum(1)
    mean = torch.where(kept, xc, 0.0).sum(1) / nk.clamp(min=1)
    dev = torch.where(kept, xc - mean[:, None], 0.0)
    std_kept = torch.sqrt((dev * dev).sum(1) / (nk - 1).clamp(min=1))
    use = out.any(1) & (nk >= 3) & (std_kept > 0)
    return torch.where(use, std / torch.where(use, std_kept, 1.0), torch.ones_like(std))
