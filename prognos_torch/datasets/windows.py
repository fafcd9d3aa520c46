"""Time-delay windows, recursive multi-step inputs, min-max scaling and chronological splits.

Paper 002, Eq. 9-10 (recursive prediction with an m-th order model): the input matrix P stacks
sliding windows ``p_i = [x_i, ..., x_{i+m-1}]`` and the target vector holds the next samples
``x_{i+m}``. As printed, Eq. 9-10 end with the row ``[x_{k-m+1}, ..., x_k]`` paired with
``x_{k+1}``, a sample not observed at time k (the indices are off by one, and Eq. 11-13 switch
between ``l - m`` and ``k - m + 1`` rows); :func:`embed` pairs every window with the next
*observed* sample, so T samples give T - m pairs. Eq. 12-14 then forecast recursively: the
window for step j + 1 drops its oldest entry and appends the forecast for step j
(``P_{k-m+j} = [x_{k-m+j}, ..., x_k, x^_{k+1}, ..., x^_{k+j-1}]``), see :func:`shift_append`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from prognos_torch.core.validation import as_tensor, broadcast_shape, is_int, is_real

__all__ = [
    "embed",
    "shift_append",
    "MinMaxScaler",
    "NormalizedSeries",
    "minmax_normalize",
    "minmax_denormalize",
    "chronological_split",
    "OneStepPairs",
    "one_step_pairs",
]


def _check_m(m, T: int) -> int:
    if not is_int(m) or m < 1:
        raise ValueError(f"embedding dimension m must be a positive int, got {m!r}")
    if m >= T:
        raise ValueError(
            f"embedding dimension m={m} is too large for a series of length T={T}: "
            f"need T >= m + 1 to form at least one (window, target) pair"
        )
    return int(m)


def embed(series: Tensor, m: int) -> tuple[Tensor, Tensor]:
    """Sliding-window (input, target) pairs of paper 002, Eq. 9-10.

    Args:
        series: shape (T,) for a scalar series or (T, d) for a vector series; time first.
        m: embedding dimension (model order), 1 <= m <= T - 1.

    Returns:
        ``inputs`` of shape (T - m, m) (or (T - m, m, d)) with row i = ``[x_i, ..., x_{i+m-1}]``,
        oldest first, and ``targets`` of shape (T - m,) (or (T - m, d)) with ``x_{i+m}``.
        Fresh tensors with the dtype and device of ``series``. A NaN (missing) sample is
        copied into every window and target it falls in: a pair with a NaN target is a
        missing measurement to the Kalman optimisers and is left out of the gradient
        baselines' loss; inputs with a NaN are refused by :func:`~prognos_torch.optim.fit`
        (``train inputs X contains non-finite values``): drop those rows first
        (``keep = ~inputs.isnan().flatten(1).any(-1)``).
    """
    x = as_tensor(series, "series")
    if x.dim() not in (1, 2):
        raise ValueError(f"series must have shape (T,) or (T, d), got {tuple(x.shape)}")
    m = _check_m(m, x.shape[0])
    windows = x.unfold(0, m, 1)  # (T - m + 1, m) or (T - m + 1, d, m)
    if x.dim() == 2:
        windows = windows.transpose(1, 2)  # (T - m + 1, m, d)
    return windows[:-1].clone(), x[m:].clone()


def shift_append(window: Tensor, new_value: Tensor, *, time_dim: int = -1) -> Tensor:
    """Recursive multi-step input update of paper 002, Eq. 12-14.

    Drops the oldest entry along ``time_dim`` and appends ``new_value`` as the newest:
    ``[x_{k-m+j}, ..., x^_{k+j-1}] -> [x_{k-m+j+1}, ..., x^_{k+j-1}, new_value]``.

    Args:
        window: shape (..., m) for a scalar series (``time_dim=-1``, batch dims leading, e.g.
            particles), or (..., m, d) for a vector series with ``time_dim=-2``.
        new_value: the window's shape with ``time_dim`` removed: (...) or (..., d).
        time_dim: the window's time axis.

    Returns:
        A new tensor shaped like ``window`` (differentiable, vmap-friendly; no in-place ops).
    """
    if not isinstance(window, Tensor):
        raise TypeError(f"window must be a tensor of shape (..., m), got {type(window)}")
    if window.dim() == 0:
        raise ValueError("window must have shape (..., m) with m >= 1, got a scalar")
    if not is_int(time_dim):
        raise TypeError(f"time_dim must be an int, got {time_dim!r}")
    dim = time_dim % window.dim() if -window.dim() <= time_dim < window.dim() else None
    if dim is None:
        raise ValueError(
            f"time_dim={time_dim} is out of range for window of shape {tuple(window.shape)}"
        )
    new_value = torch.as_tensor(new_value, dtype=window.dtype, device=window.device)
    expected = window.shape[:dim] + window.shape[dim + 1 :]
    if tuple(new_value.shape) != tuple(expected):
        raise ValueError(
            f"new_value must have shape {tuple(expected)} (window {tuple(window.shape)} without "
            f"time_dim={time_dim}), got {tuple(new_value.shape)}"
        )
    m = window.shape[dim]
    if m == 0:  # (narrow() failed with "length must be non-negative")
        raise ValueError(
            f"window must hold m >= 1 samples along time_dim={time_dim}, got shape "
            f"{tuple(window.shape)}"
        )
    return torch.cat((window.narrow(dim, 1, m - 1), new_value.unsqueeze(dim)), dim=dim)


def _minmax_forward(x: Tensor, data_min: Tensor, data_max: Tensor, lo: float, hi: float) -> Tensor:
    return lo + (x - data_min) * ((hi - lo) / (data_max - data_min))


def _minmax_inverse(y: Tensor, data_min: Tensor, data_max: Tensor, lo: float, hi: float) -> Tensor:
    return data_min + (y - lo) * ((data_max - data_min) / (hi - lo))


class MinMaxScaler:
    """Min-max scaling to ``feature_range`` with a remembered range.

    ``y = lo + (x - x_min) (hi - lo) / (x_max - x_min)`` per feature (last axis of a 2-D input,
    or the whole series for a 1-D input). Values outside the fitted range map outside
    ``feature_range``: nothing is clipped. Fitting a constant feature raises ``ValueError``
    (the scale would divide by zero).

    ``transform``/``inverse_transform`` follow the dtype and device of their argument. The state
    is plain: ``{"data_min": Tensor, "data_max": Tensor, "feature_range": (lo, hi)}``.
    """

    def __init__(self, feature_range: tuple[float, float] = (0.0, 1.0)) -> None:
        lo, hi = self._check_range(feature_range)
        self.feature_range = (lo, hi)
        self.data_min: Tensor | None = None
        self.data_max: Tensor | None = None

    @staticmethod
    def _check_range(feature_range) -> tuple[float, float]:
        try:
            lo, hi = (float(v) for v in feature_range)
        except (TypeError, ValueError) as exc:
            raise TypeError(
                f"feature_range must be a pair (lo, hi), got {feature_range!r}"
            ) from exc
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"feature_range must be finite with lo < hi, got {(lo, hi)}")
        return lo, hi

    @property
    def fitted(self) -> bool:
        return self.data_min is not None

    def fit(self, x: Tensor) -> MinMaxScaler:
        """Remember the range of ``x``: shape (T,) (one range) or (T, d) (one per column)."""
        x = as_tensor(x, "x")
        if x.dim() not in (1, 2) or x.shape[0] == 0:
            raise ValueError(f"x must have shape (T,) or (T, d) with T >= 1, got {tuple(x.shape)}")
        if not x.is_floating_point():
            x = x.to(torch.float64)
        if not bool(torch.isfinite(x).all()):
            raise ValueError("x contains non-finite values; cannot fit a min-max range")
        data_min, data_max = x.amin(0), x.amax(0)
        constant = (data_max == data_min).reshape(-1)
        if bool(constant.any()):
            cols = torch.nonzero(constant).flatten().tolist()
            where = "the series is" if x.dim() == 1 else f"column(s) {cols} are"
            raise ValueError(f"x: {where} constant; min-max scaling is undefined (max == min)")
        self.data_min, self.data_max = data_min, data_max
        return self

    def _state_for(self, x: Tensor) -> tuple[Tensor, Tensor]:
        if not self.fitted:
            raise RuntimeError("MinMaxScaler is not fitted: call fit() or load_state_dict() first")
        per_column = self.data_min.dim() == 1
        if per_column and (x.dim() == 0 or x.shape[-1] != self.data_min.shape[0]):
            raise ValueError(
                f"x must have shape (..., {self.data_min.shape[0]}) to match the fitted range, "
                f"got {tuple(x.shape)}"
            )
        return (
            self.data_min.to(dtype=x.dtype, device=x.device),
            self.data_max.to(dtype=x.dtype, device=x.device),
        )

    def _as_input(self, x) -> Tensor:
        x = as_tensor(x, "x")
        if not x.is_floating_point():
            x = x.to(self.data_min.dtype if self.fitted else torch.float64)
        return x

    def transform(self, x: Tensor) -> Tensor:
        """Scale ``x``: any shape for a 1-D fit, shape (..., d) for a per-column fit."""
        x = self._as_input(x)
        data_min, data_max = self._state_for(x)
        return _minmax_forward(x, data_min, data_max, *self.feature_range)

    def inverse_transform(self, y: Tensor) -> Tensor:
        """Undo :meth:`transform` (same shapes)."""
        y = self._as_input(y)
        data_min, data_max = self._state_for(y)
        return _minmax_inverse(y, data_min, data_max, *self.feature_range)

    def fit_transform(self, x: Tensor) -> Tensor:
        return self.fit(x).transform(x)

    def state_dict(self) -> dict:
        """Plain state (tensors and floats): safe for ``torch.save(..., weights_only=True)``."""
        if not self.fitted:
            raise RuntimeError("MinMaxScaler is not fitted: nothing to save")
        return {
            "data_min": self.data_min.clone(),
            "data_max": self.data_max.clone(),
            "feature_range": self.feature_range,
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore a state from :meth:`state_dict` (validated, no pickling involved)."""
        missing = {"data_min", "data_max", "feature_range"} - set(state)
        if missing:
            raise ValueError(f"state is missing keys {sorted(missing)}")
        data_min = as_tensor(state["data_min"], "state['data_min']")
        data_max = as_tensor(state["data_max"], "state['data_max']")
        if data_min.shape != data_max.shape or data_min.dim() > 1:
            raise ValueError(
                "state['data_min'] and state['data_max'] must have the same shape () or (d,), "
                f"got {tuple(data_min.shape)} and {tuple(data_max.shape)}"
            )
        if not (bool(torch.isfinite(data_min).all()) and bool(torch.isfinite(data_max).all())):
            # (an infinite extreme mapped every value to NaN or to lo)
            raise ValueError("state['data_min'] and state['data_max'] must be finite")
        if not bool((data_max > data_min).all()):
            raise ValueError("state['data_max'] must exceed state['data_min'] elementwise")
        self.feature_range = self._check_range(state["feature_range"])
        self.data_min, self.data_max = data_min.clone(), data_max.clone()


class NormalizedSeries(NamedTuple):
    """``values = (series - lo) / (hi - lo)``; ``lo``/``hi`` are kept to undo the scaling."""

    values: Tensor
    lo: Tensor
    hi: Tensor


def _extreme(v, name: str, series: Tensor) -> Tensor:
    """A given ``lo``/``hi`` as a tensor of the series' dtype and device, finite, broadcastable
    to the series (one value per column)."""
    try:
        v = torch.as_tensor(v, dtype=series.dtype).to(series)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise TypeError(f"{name} must be a number or a tensor of numbers, got {v!r}") from exc
    try:  # (broadcast_shape: torch.broadcast_shapes imports SymPy on its first call, ~1 s)
        fits = broadcast_shape(v.shape, series.shape) == series.shape
    except ValueError:
        fits = False
    # one row, not one value per sample: an (N, ...) extreme scaled each sample by its own range
    lead = v.dim() - (series.dim() - 1)
    if lead > 0 and any(size != 1 for size in v.shape[:lead]):
        fits = False
    if not fits:
        raise ValueError(
            f"{name} must broadcast to one row of series {tuple(series.shape[1:])} (one value "
            f"per column), got shape {tuple(v.shape)}"
        )
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"{name} must be finite, got {v.tolist()}")
    return v


def minmax_normalize(series: Tensor, lo=None, hi=None) -> NormalizedSeries:
    """Affine min-max scaling to ``[0, 1]`` (paper 003 Sec. V: "normalized into 0 to 1").

    The functional form of :class:`MinMaxScaler` with ``feature_range=(0, 1)``, for series of
    any trailing shape and for extremes taken from elsewhere: ``(x - lo) / (hi - lo)``, where
    the scaler multiplies by the reciprocal range, so the two agree to rounding. Both forms are
    kept because published results were computed with each.

    By default ``lo``/``hi`` are the minimum and maximum over the whole ``series`` (paper 003
    scales all 1000 Lorenz / all CSTR points at once, test part included). Pass ``lo``/``hi``
    (e.g. from the training part only) to avoid that look-ahead; values outside ``[lo, hi]`` then
    map outside ``[0, 1]`` and are not clipped.

    Args:
        series: ``(N, ...)``; the extremes are taken over dim 0 (per column). An integer series
            is scaled in float64.
        lo, hi: numbers or tensors broadcastable to one row ``series.shape[1:]``.
    """
    if not isinstance(series, Tensor) or series.dim() < 1 or series.shape[0] < 1:
        raise ValueError("series must be a tensor of shape (N, ...) with N >= 1")
    if not series.is_floating_point():
        series = series.to(torch.float64)  # (lo/hi were cast to an integer dtype, 0.5 to 0)
    if not bool(torch.isfinite(series).all()):
        raise ValueError("series contains non-finite values")
    lo = series.amin(0) if lo is None else _extreme(lo, "lo", series)
    hi = series.amax(0) if hi is None else _extreme(hi, "hi", series)
    if not bool((hi > lo).all()):
        raise ValueError("minmax_normalize needs hi > lo (a constant series cannot be scaled)")
    return NormalizedSeries((series - lo) / (hi - lo), lo, hi)


def minmax_denormalize(values: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Inverse of :func:`minmax_normalize`: ``values * (hi - lo) + lo``."""
    return values * (hi - lo) + lo


def chronological_split(
    x: Tensor | np.ndarray | Sequence,
    train_fraction: float | None = None,
    *,
    n_train: int | None = None,
) -> tuple:
    """Split along the first (time) axis without shuffling: ``x[:n_train], x[n_train:]``.

    Give exactly one of ``train_fraction`` in (0, 1) (``n_train = floor(fraction * T)``) or
    ``n_train``; both parts must be non-empty (1 <= n_train <= T - 1).
    """
    if (train_fraction is None) == (n_train is None):
        raise ValueError("give exactly one of train_fraction or n_train")
    try:
        T = len(x)
    except TypeError as exc:
        raise TypeError(
            f"x must be a tensor, array or sequence with a time axis, got {type(x)}"
        ) from exc
    if train_fraction is not None:
        if not (is_real(train_fraction) and 0.0 < train_fraction < 1.0):
            raise ValueError(f"train_fraction must lie in (0, 1), got {train_fraction!r}")
        # floor(fraction * T), the product rounded first where it misses an integer by rounding
        # only (0.29 * 100 = 28.999999999999996 gave 28 rows)
        product = float(train_fraction) * T
        n_train = round(product)
        if abs(product - n_train) > 1e-9 * max(1.0, product):
            n_train = int(math.floor(product))
    elif not is_int(n_train):
        raise ValueError(f"n_train must be an int, got {n_train!r}")
    if not 1 <= n_train <= T - 1:
        raise ValueError(
            f"n_train={n_train} leaves an empty part of a series of length {T}: "
            f"need 1 <= n_train <= {T - 1}"
        )
    return x[:n_train], x[n_train:]


class OneStepPairs(NamedTuple):
    """One-step-ahead (window, next sample) pairs of a scalar series, split in time.

    Attributes:
        X_train: ``(n_train - m, m)`` windows whose targets lie among the first ``n_train``
            samples; Y_train: ``(n_train - m, 1)`` their targets.
        X_test: ``(T - n_train, m)`` the remaining windows; Y_test: ``(T - n_train, 1)``.
        k_test: ``(T - n_train,)`` the 1-based sample index of each test target
            (``n_train + 1, ..., T``).
    """

    X_train: Tensor
    Y_train: Tensor
    X_test: Tensor
    Y_test: Tensor
    k_test: np.ndarray


def one_step_pairs(series: Tensor, m: int, n_train: int) -> OneStepPairs:
    """:func:`embed` a series with order ``m`` and split the pairs chronologically so that the
    targets among the first ``n_train`` samples train and the later ones test (paper 003
    Sec. V: the first 500 Lorenz points train, the last 500 are predicted one step ahead; the
    first ``m`` samples are inputs only, so ``n_train - m`` pairs train).

    Args:
        series: ``(T,)``, time first; m: embedding dimension; n_train: ``m < n_train < T``.
    Returns:
        :class:`OneStepPairs` (targets with a trailing unit dim, the shape of a one-output
        learner's predictions).
    """
    x = as_tensor(series, "series")
    if x.dim() != 1:
        raise ValueError(f"series must have shape (T,), got {tuple(x.shape)}")
    inputs, targets = embed(x, m)
    if not is_int(n_train):
        raise ValueError(f"n_train must be an int, got {n_train!r}")
    if not m < n_train < x.shape[0]:
        raise ValueError(
            f"n_train={n_train} must lie between m={m} and T={x.shape[0]} (exclusive): "
            f"both parts need at least one target"
        )
    X_train, X_test = chronological_split(inputs, n_train=n_train - m)
    Y_train, Y_test = chronological_split(targets.unsqueeze(-1), n_train=n_train - m)
    return OneStepPairs(X_train, Y_train, X_test, Y_test, np.arange(n_train + 1, x.shape[0] + 1))
