"""Degradation onset (first prediction time) against a healthy baseline.

Two detectors on a univariate indicator ``x_1..x_T`` (NaN: missing, skipped), both one-sided in
the direction of degradation and both measured against a *baseline* ``(mu_0, sigma_0)``: the
mean and standard deviation (ddof = 1) of a healthy window, by default the first 30 % of the
observed time span (:func:`healthy_baseline`).

**k-sigma rule on a moving median** (:func:`ksigma_onset`; the bearing-prognostics protocol of
Saxena-style RUL studies): ``m_i = median(x_{i-w+1..i})`` (trailing window ``w``), an exceedance
is ``m_i > mu_0 + k sigma_0`` and the onset is the *first* of ``c`` consecutive exceedances; the
alarm (the time at which the rule knows) is the last of them. Defaults ``k = 4``, ``w = 5``,
``c = 5``.

False-alarm rate (derived; ``p = Q(k) = P(Z > k)`` for a standard normal ``Z``; ``Q(4) = 3.17e-5``).
An alarm at sample ``i`` needs ``m_i > mu_0 + k sigma_0``, i.e. at least ``j* = floor(w/2) + 1``
of the ``w`` samples of its window above the limit (for even ``w`` the lower median is used).
Hence, for a baseline that is marginally Gaussian with the estimated mean and std,

* for independent samples the per-sample alarm probability is at most
  ``P(Bin(w, p) >= j*)`` (``w = 5, k = 4``: ``10 p^3 = 3.2e-13``; over 10,000 samples the
  probability of any false alarm is below ``3.2e-9``);
* for *any* dependence between samples (Markov's inequality on the number of exceedances in a
  window) it is at most ``w p / j*`` (``w = 5, k = 4``: ``5.3e-5`` per sample).

:attr:`Onset.false_alarm_rate` holds the independent-sample bound and
:attr:`Onset.false_alarm_bound` the dependence-free one. Both assume known ``mu_0, sigma_0``; a
baseline of ``n_0`` samples estimates them to a relative ``1 / sqrt(n_0)``, which for the
hundreds of samples of a 30 % window moves ``k`` by a few hundredths. Heavy-tailed baselines
raise the rate (``tests/test_onset.py`` measures it).

**Glitches in the healthy window** (:func:`isolated_outliers`, ``healthy_baseline(...,
glitch_limit=L)``): one corrupted sample (a sensor glitch, a bad record) in the window inflates
``sigma_0`` and with it the band, and can delay the onset by the whole degradation. A value is an
isolated outlier when it lies more than ``L`` noise standard deviations from the median of the
centred window of five values around it (the Hampel identifier, Hampel 1974, with the scale
of :attr:`Baseline.noise`, the short-term noise). A level shift or a ramp has its window median
on the value's own level and is never one. For Gaussian noise the deviation from the window
median has std ``0.94`` noise std (10^6 samples), so ``L = 20`` is exceeded with a probability
below ``1e-60`` per sample: only gross glitches are left out.

**One-sided CUSUM** (:func:`cusum_onset`; Page 1954): on ``z_i = (x_i - mu_0) / sigma_0``,
``S_i = max(0, S_{i-1} + z_i - kappa)``, alarm at the first ``S_i > h``; the change point is
Page's estimate, the sample after the last zero of ``S`` before the alarm. ``S`` is computed in
closed form by the Lindley identity ``S_i = C_i - min(0, min_{j <= i} C_j)`` with
``C_i = sum_{j <= i} (z_j - kappa)``. Defaults ``kappa = 0.5`` (optimal for a shift of one
``sigma_0``) and ``h = 12``. False-alarm rate: Siegmund's approximation of the in-control
average run length for independent standard normal ``z``,
``ARL_0 = (exp(2 kappa b) - 2 kappa b - 1) / (2 kappa^2)``, ``b = h + 1.166``
(``kappa = 0.5, h = 12``: ``ARL_0 = 1.04e6`` samples, a per-sample rate of ``9.6e-7``, so about
1 % of 10,000-sample stationary series give a false alarm). The CUSUM reacts to small sustained
shifts that the k-sigma rule misses, but unlike it it assumes independent samples: an
autocorrelated baseline shortens ``ARL_0`` by orders of magnitude.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.validation import as_tensor, has_missing, holds_bool_or_complex, is_int, is_real

__all__ = [
    "Baseline",
    "Onset",
    "ONSET_METHODS",
    "GLITCH_SCREEN",
    "GLITCH_WIDENING",
    "moving_median",
    "healthy_baseline",
    "isolated_outliers",
    "ksigma_onset",
    "cusum_onset",
    "detect_onset",
    "ksigma_false_alarm_rate",
    "cusum_arl0",
]

ONSET_METHODS = ("ksigma", "cusum")
#: Glitch screen: isolated values more than this many noise std from their window median
#: (:func:`isolated_outliers`) are reported when, left out, the healthy std falls by a factor of
#: :data:`GLITCH_WIDENING` or more (``prognose``'s flag, the fleet's ``glitch_in_baseline``).
GLITCH_SCREEN = 20.0
GLITCH_WIDENING = 1.5


@dataclass(frozen=True)
class Baseline:
    """Healthy-baseline statistics of an indicator (data units, oriented as given).

    Attributes:
        mean, std: mean and standard deviation (ddof = 1) of the healthy window.
        median: its median.
        n: number of samples in the window.
        t_end: time of the last sample of the window.
        noise: short-term noise std of the window, ``1.4826 MAD(diff x) / sqrt(2)`` (the std
            of independent noise on a slowly varying level; unlike ``std`` it ignores slow
            wander), or ``None``.
        resolution: the step ``q`` of quantised data when the window is constant and ``std``
            (and ``noise``) are the quantisation noise ``q / sqrt(12)``; else ``None``.
        glitches: times of the window's values left out of ``mean``, ``std`` and ``median`` as
            isolated outliers (``healthy_baseline(..., glitch_limit=L)``); empty: none left out.
    """

    mean: float
    std: float
    median: float
    n: int
    t_end: float
    noise: float | None = None
    resolution: float | None = None
    glitches: tuple[float, ...] = ()


@dataclass(frozen=True)
class Onset:
    """Result of an onset detector.

    Attributes:
        detected: whether the rule fired.
        index: 0-based index (into the series given) of the onset sample, or ``None``.
        time: its time, or ``None``.
        alarm_index, alarm_time: the sample at which the rule fires (the first time the onset is
            known), or ``None``.
        statistic: ``(T,)`` the monitored statistic: ``(m_i - mu_0) / sigma_0`` (k-sigma, in
            baseline standard deviations, oriented so that degradation is positive) or the
            CUSUM ``S_i``; NaN at missing samples.
        limit: the decision limit on ``statistic`` (``k`` or ``h``).
        method: ``"ksigma"`` or ``"cusum"``.
        direction: ``"above"`` or ``"below"`` (degradation direction).
        baseline: the :class:`Baseline` used.
        false_alarm_rate: per-sample false-alarm probability for independent Gaussian baseline
            samples (k-sigma: the binomial bound; CUSUM: ``1 / ARL_0``).
        false_alarm_bound: k-sigma only: the dependence-free per-sample bound ``w p / j*``.
    """

    detected: bool
    index: int | None
    time: float | None
    alarm_index: int | None
    alarm_time: float | None
    statistic: Tensor
    limit: float
    method: str
    direction: str
    baseline: Baseline
    false_alarm_rate: float
    false_alarm_bound: float | None = None


# --------------------------------------------------------------------------- helpers
def _q(k: float) -> float:
    """Standard normal upper tail ``P(Z > k)``."""
    return 0.5 * math.erfc(k / math.sqrt(2.0))


def ksigma_false_alarm_rate(k: float, window: int) -> tuple[float, float]:
    """Per-sample false-alarm bounds of the k-sigma moving-median rule (module docstring).

    Returns:
        ``(independent, any_dependence)``: ``P(Bin(w, p) >= j*)`` and ``w p / j*`` with
        ``p = Q(k)`` and ``j* = floor(w / 2) + 1``.
    """
    k = _check_pos(k, "k")
    window = _check_int(window, "window", 1)
    p = _q(k)
    j_star = window // 2 + 1
    indep = sum(
        math.comb(window, j) * p**j * (1.0 - p) ** (window - j) for j in range(j_star, window + 1)
    )
    return indep, min(1.0, window * p / j_star)


def cusum_arl0(drift: float, limit: float) -> float:
    """Siegmund's approximation of the in-control ARL of a one-sided CUSUM (module docstring);
    ``inf`` where ``exp(2 kappa b)`` overflows (a per-sample rate of 0)."""
    kappa = _check_pos(drift, "drift", allow_zero=True)
    b = _check_pos(limit, "limit") + 1.166
    a = 2.0 * kappa * b
    if a >= 0.5:
        try:
            return (math.exp(a) - a - 1.0) / (2.0 * kappa * kappa)
        except OverflowError:  # (exp overflows past a = 709.78: an ARL beyond 1e300 samples)
            return math.inf
    # small drift: exp(a) - a - 1 cancels (to 0 below kappa ~ 1e-9); its series,
    # (exp(a) - a - 1) / (2 kappa^2) = b^2 sum_n 2 a^n / (n + 2)!, is b^2 at kappa = 0
    total, term, n = 1.0, 1.0, 0
    while term > 1e-17 * total:
        n += 1
        term *= a / (n + 2)
        total += term
    return b * b * total


def _series(values, time, name: str = "values") -> tuple[Tensor, Tensor]:
    if holds_bool_or_complex(values):  # (read as 0/1, or stripped of its imaginary part)
        raise TypeError(f"{name} must hold real numbers, got bool or complex values")
    x = as_tensor(values, name)
    if not x.is_floating_point():
        x = x.to(torch.float64)
    x = x.to(torch.float64)
    if x.dim() != 1:
        raise ValueError(f"{name} must have shape (T,), got {tuple(x.shape)}")
    has_missing(x, name)  # inf refused
    if time is None:
        t = torch.arange(x.shape[0], dtype=torch.float64, device=x.device)
    else:
        t = as_tensor(time, "time", device=x.device).to(torch.float64)
        if tuple(t.shape) != tuple(x.shape):
            raise ValueError(
                f"time must have the shape of {name} {tuple(x.shape)}, got {tuple(t.shape)}"
            )
        if not bool(torch.isfinite(t).all()):
            raise ValueError("time must be finite")
        if t.shape[0] > 1 and not bool((t[1:] > t[:-1]).all()):
            raise ValueError("time must be strictly increasing, shape (T,)")
    return x, t


def _check_direction(direction: str) -> str:
    if direction not in ("above", "below"):
        raise ValueError(f"direction must be 'above' or 'below', got {direction!r}")
    return direction


def _check_int(v, name: str, lo: int) -> int:
    if not is_int(v) or v < lo:
        raise ValueError(f"{name} must be an int >= {lo}, got {v!r}")
    return int(v)


def _check_pos(v, name: str, allow_zero: bool = False, allow_negative: bool = False) -> float:
    if not is_real(v) or not math.isfinite(v):
        raise ValueError(f"{name} must be a finite number, got {v!r}")
    if allow_negative:
        return float(v)
    if v < 0 or (v == 0 and not allow_zero):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {v!r}")
    return float(v)


def moving_median(values, window: int = 5) -> Tensor:
    """Trailing moving median ``m_i = median(x_{i-w+1..i})``, ``(T,)`` -> ``(T,)``.

    The first ``w - 1`` entries use the samples available so far; NaN entries are ignored (a
    window of NaN only gives NaN). For an even count the lower of the two middle values is taken.
    """
    window = _check_int(window, "window", 1)
    x = as_tensor(values, "values").to(torch.float64)
    if x.dim() != 1:
        raise ValueError(f"values must have shape (T,), got {tuple(x.shape)}")
    if x.shape[0] == 0:
        return x.clone()
    pad = torch.full((window - 1,), math.nan, dtype=x.dtype, device=x.device)
    windows = torch.cat([pad, x]).unfold(0, window, 1)  # (T, w)
    return windows.nanmedian(-1).values


def isolated_outliers(values, scale: float, limit: float) -> Tensor:
    """Values far from their neighbourhood: ``|x_i - median(x_{i-2..i+2})| > limit * scale``
    (the Hampel identifier over a centred window of 5; at the ends the values that exist, for
    even counts the lower middle one; NaN values are skipped, and never outliers). A single
    value or a pair of values off their level is found; a level shift or a ramp, whose window
    median lies on the value's own level, is not.

    Args:
        values: ``(T,)``.
        scale: the noise standard deviation, ``> 0`` (:attr:`Baseline.noise`).
        limit: ``L``, in units of ``scale``, ``> 0`` (module docstring).

    Returns:
        ``(T,)`` bool.
    """
    x = as_tensor(values, "values").to(torch.float64)
    if x.dim() != 1:
        raise ValueError(f"values must have shape (T,), got {tuple(x.shape)}")
    scale = _check_pos(scale, "scale")
    limit = _check_pos(limit, "limit")
    if x.shape[0] < 2:
        return torch.zeros(x.shape, dtype=torch.bool, device=x.device)
    return window_median_deviation(x) > limit * scale


def window_median_deviation(x: Tensor) -> Tensor:
    """``|x_i - median(x_{i-2..i+2})|`` along the last dim, ``(..., T)`` (NaN skipped, lower
    middle for even counts; NaN at NaN values): the statistic of :func:`isolated_outliers`."""
    pad = torch.full((*x.shape[:-1], 2), math.nan, dtype=x.dtype, device=x.device)
    local = torch.cat([pad, x, pad], -1).unfold(-1, 5, 1).nanmedian(-1).values
    return (x - local).abs()


def short_term_noise(x: Tensor) -> Tensor:
    """``1.4826 MAD(diff x) / sqrt(2)`` along the last dim, ``(..., T) -> (...)`` (differences
    with a NaN end skipped): :attr:`Baseline.noise`; NaN with fewer than 2 values."""
    if x.shape[-1] < 2:  # no difference (a padded batch of one-row assets)
        return torch.full(x.shape[:-1], math.nan, dtype=x.dtype, device=x.device)
    d = x[..., 1:] - x[..., :-1]
    mad = (d - d.nanmedian(-1, keepdim=True).values).abs().nanmedian(-1).values
    return mad * 1.4826 / math.sqrt(2.0)


def healthy_baseline(
    values, time=None, *, fraction: float = 0.3, glitch_limit: float | None = None
) -> Baseline:
    """Baseline statistics of the first ``fraction`` of the observed time span.

    The window holds the samples with ``t <= t_0 + fraction (t_T - t_0)`` (the first ``fraction``
    of the samples when ``time`` is ``None``); NaN samples are skipped. At least 3 finite
    samples and a positive spread are required, with one exception: when the window is constant
    and every value of the series lies on a common grid ``x_0 + k q`` (quantised data, e.g. a
    sensor that reports whole degrees), the spread is the quantisation noise ``q / sqrt(12)``
    of a uniform rounding error (Widrow & Kollar 2008) and ``resolution`` is ``q``.

    With ``glitch_limit`` ``L``, the window's isolated outliers (:func:`isolated_outliers`
    against its short-term noise, module docstring) are left out of the mean, std and median
    (their times in :attr:`Baseline.glitches`; ``n`` counts the values kept).

    Args:
        values: ``(T,)`` indicator (NaN: missing).
        time: ``(T,)`` strictly increasing times, or ``None`` (sample index).
        fraction: in (0, 1].
        glitch_limit: ``L > 0`` in noise standard deviations, or ``None`` (every value counts).

    Returns:
        :class:`Baseline`.
    """
    x, t = _series(values, time)
    if glitch_limit is not None:
        glitch_limit = _check_pos(glitch_limit, "glitch_limit")
    if not is_real(fraction) or not (0.0 < fraction <= 1.0):
        raise ValueError(f"baseline fraction must be a number in (0, 1], got {fraction!r}")
    ok = ~torch.isnan(x)
    if int(ok.sum()) < 3:
        raise ValueError(f"values has {int(ok.sum())} finite samples; a baseline needs at least 3")
    t0, t1 = t[ok][0], t[ok][-1]
    inside = ok & (t <= window_end(t0, t1, fraction))
    xb = x[inside]
    if xb.shape[0] < 3:
        raise ValueError(
            f"the baseline window (first {100 * fraction:g} % of the time span) holds "
            f"{xb.shape[0]} samples; at least 3 are needed"
        )
    noise = float(short_term_noise(xb))
    glitches: tuple[float, ...] = ()
    if glitch_limit is not None and noise > 0:
        out = isolated_outliers(xb, noise, glitch_limit)
        if bool(out.any()) and int((~out).sum()) >= 3:  # (a window of glitches stays as it is)
            glitches = tuple(t[inside][out].tolist())
            xb = xb[~out]
    # (a constant window has no spread: its std's round-off, 1e-17 for 0.1, 0.1, 0.1, is none)
    std = 0.0 if bool((xb == xb[0]).all()) else float(xb.std(correction=1))
    q = None
    if not std > 0:
        q = _resolution(x[ok])
        if q is None and bool((x[ok] == xb[0]).all()):
            raise ValueError(
                f"the series is constant (every observed value is {float(xb[0]):g}): there is "
                "no spread to set a healthy band from and no degradation to see"
            )
        if q is None:
            raise ValueError(
                "the baseline window is constant (zero spread) and the series is not quantised "
                "on a common step, so onset is undefined (a stuck sensor?); pass the healthy "
                "statistics as baseline=Baseline(mean, std, median, n, t_end) with the sensor's "
                "noise std, or a longer baseline window"
            )
        std = q / math.sqrt(12.0)  # uniform rounding error of step q
    return Baseline(
        mean=float(xb.mean()),
        std=std,
        median=float(xb.median()),
        n=int(xb.shape[0]),
        t_end=float(t[inside][-1]),
        noise=noise if noise > 0 else std,
        resolution=q,
        glitches=glitches,
    )


def window_end(t0: Tensor, t1: Tensor, fraction: float) -> Tensor:
    """The end ``t0 + fraction (t1 - t0)`` of a healthy window over ``[t0, t1]`` (``(...)``
    times), widened by its rounding: relative to the span plus a few ulp of the clock's
    magnitude, so that the window does not depend on the clock's origin."""
    eps = torch.finfo(t0.dtype).eps
    tol = 1e-12 * (t1 - t0) + 4.0 * eps * torch.maximum(t0.abs(), t1.abs())
    return t0 + fraction * (t1 - t0) + tol


#: Most grid levels a quantised series may span (a 16-bit converter has 65,536).
MAX_LEVELS = 100_000


def _resolution(x: Tensor) -> float | None:
    """The step ``q`` of values that all lie on ``x_0 + k q`` (integer ``k``, to 1e-6 of a
    step): the greatest common step of the gaps between distinct values (Euclid's algorithm,
    a remainder within 1e-6 of the smallest gap counting as none), so ``40, 42, 45`` are on a
    step of 1, not of their smallest gap 2; ``None`` for a single value or values on no grid
    of at most :data:`MAX_LEVELS` levels."""
    u = torch.unique(x)
    if u.shape[0] < 2:
        return None
    gaps = torch.diff(u).tolist()
    tol = 1e-6 * min(gaps)
    q = gaps[0]
    for g in gaps[1:]:
        a, b = max(q, g), min(q, g)
        while b > tol:
            r = math.fmod(a, b)
            a, b = b, (0.0 if r <= tol or b - r <= tol else r)
        q = a
    if (float(u[-1]) - float(u[0])) / q > MAX_LEVELS:
        return None
    k = (u - u[0]) / q
    return q if bool(((k - k.round()).abs() <= 1e-6).all()) else None


def _resolve_baseline(x: Tensor, t: Tensor, baseline, sign: float) -> Baseline:
    if isinstance(baseline, Baseline):
        # (a std of 0 made every median above the mean an exceedance, a negative one turned the
        # direction round, NaN never alarmed)
        _check_pos(baseline.mean, "baseline.mean", allow_negative=True)
        _check_pos(baseline.std, "baseline.std")
        return baseline
    b = healthy_baseline(sign * x, t, fraction=baseline)  # statistics of the oriented series
    return Baseline(sign * b.mean, b.std, sign * b.median, b.n, b.t_end, b.noise, b.resolution)


def _after_mask(t: Tensor, after) -> Tensor:
    if after is None:
        return torch.ones_like(t, dtype=torch.bool)
    if not is_real(after) or math.isnan(after):
        raise ValueError(f"after must be a time (a number) or None, got {after!r}")
    return t > float(after)


# --------------------------------------------------------------------------- detectors
def ksigma_onset(
    values,
    time=None,
    *,
    baseline: float | Baseline = 0.3,
    k: float = 4.0,
    window: int = 5,
    consecutive: int = 5,
    direction: str = "above",
    after: float | None = None,
) -> Onset:
    """Onset by the k-sigma rule on a trailing moving median (module docstring).

    Args:
        values: ``(T,)`` indicator (NaN: missing; skipped).
        time: ``(T,)`` strictly increasing times, or ``None`` (index).
        baseline: a :class:`Baseline` (data units, as returned by :func:`healthy_baseline` on
            the series as given), or the fraction of the time span that forms it.
        k: limit in baseline standard deviations.
        window: moving-median window ``w`` (for even ``w`` the lower middle value of the series
            oriented to ``direction``).
        consecutive: number ``c`` of consecutive exceedances (of observed samples).
        direction: ``"above"`` (degradation raises the indicator) or ``"below"``.
        after: only exceedances at times later than ``after`` count (``None``: all). The end
            of the healthy window (``Baseline.t_end``) treats that window as healthy: a
            transient inside it (a run-in, say) is no onset.

    Returns:
        :class:`Onset`; ``index`` is the first of the ``c`` exceedances, ``alarm_index`` the last.
        The first ``w - 1`` observed samples, whose trailing window is partial, raise no alarm
        (a median of one or two samples exceeds the limit far more often than the documented
        rate). The median trails a step: its first exceedance, ``index``, lies about
        ``floor(w / 2)`` samples after the change itself.
    """
    direction = _check_direction(direction)
    k = _check_pos(k, "k")
    window = _check_int(window, "window", 1)
    consecutive = _check_int(consecutive, "consecutive", 1)
    x, t = _series(values, time)
    late = _after_mask(t, after)
    sign = 1.0 if direction == "above" else -1.0
    base = _resolve_baseline(x, t, baseline, sign)
    obs = torch.nonzero(~torch.isnan(x)).flatten()
    stat = torch.full_like(x, math.nan)
    rate, bound = ksigma_false_alarm_rate(k, window)
    if obs.numel():
        med = moving_median(sign * x[obs], window)  # of the oriented series (lower middle)
        z = (med - sign * base.mean) / base.std
        stat[obs] = z
        above = ((z > k) & late[obs]).to(torch.int64)
        above[: window - 1] = 0  # partial windows (1 .. w - 1 samples): not the documented rate
        if above.shape[0] >= consecutive:
            runs = above.unfold(0, consecutive, 1).sum(-1)  # (n - c + 1,)
            hits = torch.nonzero(runs == consecutive).flatten()
            if hits.numel():
                first = int(hits[0])
                i, a = int(obs[first]), int(obs[first + consecutive - 1])
                return Onset(True, i, float(t[i]), a, float(t[a]), stat, k, "ksigma",
                             direction, base, rate, bound)  # fmt: skip
    return Onset(False, None, None, None, None, stat, k, "ksigma", direction, base, rate, bound)


def cusum_onset(
    values,
    time=None,
    *,
    baseline: float | Baseline = 0.3,
    drift: float = 0.5,
    limit: float = 12.0,
    direction: str = "above",
    after: float | None = None,
) -> Onset:
    """Onset by a one-sided CUSUM on the standardised indicator (module docstring).

    Args:
        values, time, baseline, direction: as :func:`ksigma_onset`.
        after: the CUSUM starts at the first sample later than ``after`` (``None``: at the
            first sample).
        drift: reference value ``kappa >= 0`` (baseline standard deviations).
        limit: decision limit ``h > 0``.

    Returns:
        :class:`Onset`; ``index`` is Page's change-point estimate, ``alarm_index`` the first
        ``S_i > h``.
    """
    direction = _check_direction(direction)
    drift = _check_pos(drift, "drift", allow_zero=True)
    limit = _check_pos(limit, "limit")
    x, t = _series(values, time)
    late = _after_mask(t, after)
    sign = 1.0 if direction == "above" else -1.0
    base = _resolve_baseline(x, t, baseline, sign)
    obs = torch.nonzero(~torch.isnan(x) & late).flatten()
    stat = torch.full_like(x, math.nan)
    rate = 1.0 / cusum_arl0(drift, limit)
    if obs.numel():
        d = sign * (x[obs] - base.mean) / base.std - drift
        C = torch.cat([d.new_zeros(1), d.cumsum(0)])  # C_0 = 0, C_i
        low = C.cummin(0).values  # min_{j <= i} C_j (includes C_0 = 0)
        S = (C - low)[1:]
        stat[obs] = S
        hits = torch.nonzero(S > limit).flatten()
        if hits.numel():
            j = int(hits[0])
            # Page's estimate: after the last zero of S before the alarm = after argmin C_{0..j}
            # S_j belongs to C_{j+1}; the last minimum of C_0..C_{j+1} is the last zero of S,
            # at C-index m, so the onset is sample m (C-index m + 1)
            r = int(torch.argmin(torch.flip(C[: j + 2], (0,))))  # first minimum of the flip
            m = j + 1 - r
            i, a = int(obs[min(m, j)]), int(obs[j])
            return Onset(True, i, float(t[i]), a, float(t[a]), stat, limit, "cusum",
                         direction, base, rate)  # fmt: skip
    return Onset(False, None, None, None, None, stat, limit, "cusum", direction, base, rate)


def detect_onset(values, time=None, *, method: str = "ksigma", **options) -> Onset:
    """:func:`ksigma_onset` (``method="ksigma"``) or :func:`cusum_onset` (``"cusum"``)."""
    if method == "ksigma":
        return ksigma_onset(values, time, **options)
    if method == "cusum":
        return cusum_onset(values, time, **options)
    raise ValueError(f"onset method must be one of {', '.join(ONSET_METHODS)}, got {method!r}")
