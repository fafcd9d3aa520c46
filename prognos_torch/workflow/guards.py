"""The guard rails of :func:`~prognos_torch.workflow.prognose`: the side of the threshold, and
the flags that say where a result rests on more than the data (pipeline steps 1 and 6 of
:mod:`~prognos_torch.workflow.prognosing`).

Each function returns a list of one-line flags (empty when nothing is wrong) or raises a
``ValueError`` that names the threshold and the healthy band.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._text import fmt_level, fmt_time
from ..prognosis.onset import GLITCH_SCREEN, GLITCH_WIDENING, Baseline, detect_onset

__all__ = [
    "BAND_K",
    "CENSORED_FLAG",
    "threshold_side",
    "away_from_threshold",
    "glitch_flags",
    "baseline_flags",
    "fit_flags",
    "beyond_the_data",
    "onset_pending",
]

#: Healthy band and onset limit in baseline standard deviations (``mean -+ BAND_K std``).
BAND_K = 4.0
#: Censored mass above which a result is flagged (its 95 % quantile is then unknown).
CENSORED_FLAG = 0.05


def glitch_flags(base: Baseline, screened: Baseline) -> list[str]:
    """A flag when the healthy window's gross isolated outliers (``screened``, the baseline
    without them) widen its band by :data:`GLITCH_WIDENING` or more."""
    if not screened.glitches or not base.std >= GLITCH_WIDENING * screened.std:
        return []
    n = len(screened.glitches)
    return [
        f"glitches in the healthy window: {n} isolated value{'s' * (n > 1)} more than "
        f"{GLITCH_SCREEN:g} noise std from {'their' if n > 1 else 'its'} neighbours (first at "
        f"t = {fmt_time(screened.glitches[0])}) widen{'s' * (n == 1)} the healthy band {base.std / screened.std:.1f} "
        f"times (std {base.std:.4g}, {screened.std:.4g} without them), which can delay the "
        f"onset; glitch_limit={GLITCH_SCREEN:g} (--glitch-limit) leaves them out"
    ]


def baseline_flags(base: Baseline) -> list[str]:
    """What the healthy window's statistics left out or assumed: the glitches screened out of
    it (``glitch_limit``), and a constant window whose spread is the data's quantisation."""
    out = []
    if base.glitches:
        n = len(base.glitches)
        out.append(
            f"glitches left out of the healthy window: {n} isolated value{'s' * (n > 1)} "
            f"(first at t = {fmt_time(base.glitches[0])})"
        )
    if base.resolution is None:
        return out
    return out + [
        "the healthy window is constant: its spread is the quantisation noise of the data's "
        f"step {base.resolution:.4g} (step / sqrt(12))"
    ]


def fit_flags(fit, level_thr: float, passage, n_since: int, censored: float) -> list[str]:
    """Flags of a trend fit and its paths: a threshold more than 3 x the rise seen since onset
    away in the model's measurement space, paths that diverge (over 1 %), a censored mass above
    :data:`CENSORED_FLAG`, and fewer than 20 values since onset (``level_thr``: the threshold
    on the fit's level; ``passage``: its first-passage result)."""
    out = []
    z = fit.level_fit.z if hasattr(fit, "level_fit") else fit.z
    zz = z[~torch.isnan(z)]
    zt = fit.to_z(level_thr)
    rise = float(zz.max() - zz.min()) if zz.numel() else 0.0
    now = float(fit.level_fit.means[-1, 0] if hasattr(fit, "level_fit") else fit.means[-1, 0])
    if rise > 0 and math.isfinite(zt) and (zt - now) > 3.0 * rise:
        out.append(
            f"extrapolation: the threshold is {(zt - now) / rise:.1f} times the rise seen since "
            "onset away (in the model's measurement space); the RUL rests on the model's shape "
            "far beyond the data"
        )
    div = float(passage.diverged.to(torch.float64).mean())
    if div > 0.01:
        out.append(f"diverging paths: {100 * div:.1f} % of the paths left every sensible range")
    if censored > CENSORED_FLAG:
        out.append(
            f"censored: {100 * censored:.0f} % of the paths do not reach the threshold within "
            "the horizon"
        )
    if n_since < 20:
        out.append(
            f"few data since onset ({n_since} values): the interval rests mostly on the prior"
        )
    return out


def beyond_the_data(
    y_on: Tensor, phi: float, sigma0: float, thr_o: float, method: str, flags: list[str]
) -> list[str]:
    """Flags of the data since onset (oriented ``y_on``) that the fits cannot see
    (``method``: ``prognose``'s, whatever the number of filters and seeds pooled).

    * The extrapolation flag in data units: a threshold more than 10 x as far above the
      healthy level as the highest value since onset (in the log space of the shapes the
      measurement-space rule of :func:`fit_flags` can miss a threshold 1000 x beyond the data).
    * Back at the healthy level: the last 5 values within ``sigma0`` of it, where the log
      shapes have no measurement (``y - phi < sigma0`` is missing), so their RUL extrapolates
      the values before them.
    """
    out = []
    seen = float((y_on - phi).max())
    far = seen > 0 and (thr_o - phi) > 10.0 * seen
    if far and not any(f.startswith("extrapolation") for f in flags):
        out.append(
            f"extrapolation: the threshold is {(thr_o - phi) / seen:.3g} times as far from the "
            "healthy level as the highest value since onset (in data units); the RUL rests on "
            "the model's shape far beyond the data"
        )
    if method != "linear" and bool((y_on[-5:] - phi < sigma0).all()):
        out.append(
            "back at the healthy level: the last 5 values lie within one baseline std of the "
            "healthy mean, where the log-shape trends have no measurement; the RUL extrapolates "
            "the values before them and is doubtful (the degradation may have receded)"
        )
    return out


def onset_pending(medians: Tensor, limit: float, sign: float, spread: float) -> list[str]:
    """Before onset: the newest 5-value medians (oriented) above the onset limit, fewer than
    the 5 in a row that declare onset (``spread``: the healthy std, for the digits printed)."""
    above = (medians >= limit).flip(0).to(torch.int64)
    run = int(above.cumprod(0).sum())
    if run == 0:
        return []
    return [
        f"onset pending: the last {run} median(s) of 5 values lie beyond the onset limit "
        f"{fmt_level(sign * limit, spread)} (healthy mean -+ {BAND_K:g} std); onset is declared "
        "after 5 in a row, so a degradation may be starting and the bound may not hold"
    ]


def threshold_side(thr: float, direction: str, base: Baseline) -> str:
    """``"above"`` or ``"below"``: the side of the healthy band ``mean -+ 4 std`` that the
    threshold must lie on (``"auto"``: the side it is on; inside the band it is refused)."""
    lo_band, hi_band = base.mean - BAND_K * base.std, base.mean + BAND_K * base.std

    def lv(v: float) -> str:  # digits that resolve the band
        return fmt_level(v, base.std)

    if direction == "auto":
        if lo_band <= thr <= hi_band:
            raise ValueError(
                f"threshold {lv(thr)} lies inside the healthy band [{lv(lo_band)}, {lv(hi_band)}] "
                f"(baseline mean -+ {BAND_K:g} std): the healthy asset would already count as failed"
            )
        direction = "above" if thr > hi_band else "below"
    elif (direction == "above" and thr <= hi_band) or (direction == "below" and thr >= lo_band):
        side = "above" if direction == "above" else "below"
        edge = hi_band if direction == "above" else lo_band
        raise ValueError(
            f"threshold {lv(thr)} is on the wrong side for direction {direction!r}: it must lie "
            f"{side} the healthy band edge {lv(edge)} (baseline mean {lv(base.mean)}, std "
            f"{base.std:.4g})"
        )
    return direction


def away_from_threshold(
    x: Tensor, t: Tensor, medians: Tensor, thr: float, direction: str, base: Baseline, onset: str
) -> list[str]:
    """The wrong-side rule of ``direction="auto"`` for a series with no onset towards the
    threshold: an excursion from the healthy band on the other side, at least as far from the
    healthy mean as the threshold lies on its side, is refused (the threshold looks to be on the
    wrong side); a smaller one is returned as a flag (a drift of the healthy level).
    ``medians``: ``(T,)`` the 5-point moving medians of the series oriented to ``direction``."""
    other = "below" if direction == "above" else "above"
    sign = 1.0 if direction == "above" else -1.0
    away = detect_onset(x, t, method=onset, baseline=base, direction=other, after=base.t_end)
    if away.detected:  # the series left the band, away from the threshold
        # how far the median went the other way, against the threshold's distance
        low = torch.nan_to_num(medians[away.index :], nan=math.inf).min()
        gone, dist = sign * base.mean - float(low), sign * (thr - base.mean)
        if gone >= dist:
            raise ValueError(
                f"threshold {fmt_level(thr, base.std)} is {direction} the healthy band, but the series "
                f"left the band {other} it (onset at {fmt_time(away.time)}, last value "
                f"{fmt_level(float(x[-1]), base.std)}; its median moved {gone:.4g} from the "
                f"healthy mean {fmt_level(base.mean, base.std)}, the threshold lies {dist:.4g} on the other side): the "
                f"threshold looks to be on the wrong side; set direction={direction!r} "
                f"(--direction {direction} on the command line) to predict a crossing on that "
                "side regardless"
            )
        return [
            f"the series left its healthy band {other} it at {fmt_time(away.time)}, away from the "
            f"threshold (its median moved {gone:.4g} from the healthy mean, the threshold "
            f"lies {dist:.4g} on the other side): read as a drift of the healthy level; if "
            f"failure is an excursion {other} the band, the threshold is on the wrong side"
        ]
    return []
