"""The known-threshold RUL protocol of bearing run-to-failure studies, baselines and scores.

Protocol (:func:`known_threshold_protocol`) on a run-to-failure indicator ``y(t)``:

* the failure threshold is ``0.9 x`` the highest 5-point (trailing) moving median;
* end of life (EoL) is the first time the moving median reaches it;
* onset is the first of 5 consecutive moving medians above ``mean + 4 std`` of the first 30 % of
  life (``[t_0, t_EoL]``, by time);
* predictions are made at 20/40/60/80/90 % of ``[onset, EoL]``, each from the data observed up
  to that time; the true RUL is ``t_EoL - t``.

Baselines (point predictions, ``inf`` when the fit never reaches the threshold):
:func:`linear_slope_rul` (a straight line through the last quarter of the data since onset,
at least 5 values) and :func:`exponential_lsq_rul` (least squares of ``log(y - phi)`` on time
over all data since onset).

Scores (:func:`rul_scores`): per point the relative error and whether the prediction lies in the
alpha cone ``[(1 - alpha) r*, (1 + alpha) r*]``; overall the alpha-lambda fraction of points,
relative accuracy (RA) per point, CRA (the mean RA, [S10]), the prognostic horizon with the
alpha bounds taken as a fraction of ``[onset, EoL]`` (:func:`~prognos_torch.metrics.prognostic_horizon`
on times counted from onset), interval coverage and the median absolute error.

Prediction times on a sampled series: :func:`last_sample_indices` (the newest sample at or before
each time, each sample once).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.validation import is_real
from ..metrics import in_alpha_cone, prognostic_horizon
from .onset import Baseline, healthy_baseline, ksigma_onset, moving_median

__all__ = [
    "PROTOCOL_MIN_POINTS",
    "ProtocolCase",
    "known_threshold_protocol",
    "linear_slope_rul",
    "exponential_lsq_rul",
    "rul_scores",
    "last_sample_indices",
    "PROTOCOL_FRACTIONS",
]

PROTOCOL_FRACTIONS = (0.2, 0.4, 0.6, 0.8, 0.9)
#: Fewest values a series needs for :func:`known_threshold_protocol`.
PROTOCOL_MIN_POINTS = 20


def check_fractions(fractions) -> tuple[float, ...]:
    """Prediction times as distinct fractions in (0, 1) of [onset, end of life], as floats
    (``ValueError`` naming them: a fraction beyond 1 would replay rows past the end of life)."""
    try:  # (a 1-D tensor or array by its values: a tensor's entries are 0-d tensors)
        fr = tuple(fractions.tolist() if getattr(fractions, "ndim", None) == 1 else fractions)
    except (TypeError, AttributeError):
        fr = ()
    if not fr or any(not is_real(f) or not 0 < f < 1 for f in fr) or len(set(fr)) != len(fr):
        raise ValueError(
            f"fractions must be distinct numbers in (0, 1) of [onset, end of life], got "
            f"{fractions!r}"
        )
    return tuple(float(f) for f in fr)


@dataclass(frozen=True)
class ProtocolCase:
    """A run-to-failure series under the known-threshold protocol.

    Attributes:
        t, y: ``(T,)`` times and values (as given, NaN-free).
        threshold: ``0.9 x max`` moving median (or the known one given); t_eol, i_eol: end of
            life (first crossing; ``inf`` and ``T`` when the threshold is never reached).
        baseline: statistics of the first 30 % of life.
        t_onset, i_onset: protocol onset (``None`` if none before EoL).
        times: ``(P,)`` prediction times; true_rul: ``(P,)`` ``t_eol - times``.
        valid: whether the protocol is usable (onset found, at least 10 samples and a positive
            time between onset and EoL); reason: why not.
    """

    t: Tensor
    y: Tensor
    threshold: float
    t_eol: float
    i_eol: int
    baseline: Baseline
    t_onset: float | None
    i_onset: int | None
    times: Tensor
    true_rul: Tensor
    valid: bool
    reason: str = ""


def known_threshold_protocol(
    t: Tensor,
    y: Tensor,
    *,
    fractions: tuple[float, ...] = PROTOCOL_FRACTIONS,
    threshold: float | None = None,
) -> ProtocolCase:
    """Threshold, end of life, onset and prediction times of a series (module docstring).

    ``threshold``: a known failure level of a rising indicator instead of ``0.9 x`` the highest
    moving median; a series whose moving median never reaches it is not usable.
    """
    fractions = check_fractions(fractions)  # (1.5 gave a time past end of life, RUL < 0)
    t = torch.as_tensor(t, dtype=torch.float64)
    y = torch.as_tensor(y, dtype=torch.float64)
    if t.dim() != 1 or t.shape != y.shape or t.shape[0] < PROTOCOL_MIN_POINTS:
        raise ValueError(
            f"t and y must have the same shape (T,), T >= {PROTOCOL_MIN_POINTS}, got "
            f"t {tuple(t.shape)}, y {tuple(y.shape)}"
        )
    if bool(torch.isnan(y).any()):
        raise ValueError("y contains NaN; drop missing values first")
    # (only the times up to end of life were checked, by the onset)
    if not bool(torch.isfinite(t).all()) or not bool((t[1:] > t[:-1]).all()):
        raise ValueError("t must be finite and strictly increasing, shape (T,)")
    m = moving_median(y, 5)
    if threshold is not None:
        if not is_real(threshold):
            raise TypeError(f"threshold must be a real number or None, got {threshold!r}")
        if not math.isfinite(threshold):
            raise ValueError(f"threshold must be finite, got {threshold!r}")
    thr = 0.9 * float(m.max()) if threshold is None else float(threshold)
    if not bool((m >= thr).any()):
        empty = torch.empty(0, dtype=torch.float64, device=t.device)
        base = healthy_baseline(y, t, fraction=0.3)
        return ProtocolCase(t, y, thr, math.inf, t.shape[0], base, None, None, empty, empty,
                            False, f"the moving median never reaches the threshold {thr:g}")  # fmt: skip
    i_eol = int(torch.nonzero(m >= thr).flatten()[0])
    t_eol = float(t[i_eol])
    base = healthy_baseline(y[: i_eol + 1], t[: i_eol + 1], fraction=0.3)
    on = ksigma_onset(y[: i_eol + 1], t[: i_eol + 1], baseline=base)
    empty = torch.empty(0, dtype=torch.float64, device=t.device)
    if not on.detected:
        return ProtocolCase(t, y, thr, t_eol, i_eol, base, None, None, empty, empty, False,
                            "no onset before end of life")  # fmt: skip
    times = torch.tensor(
        [on.time + f * (t_eol - on.time) for f in fractions], dtype=torch.float64, device=t.device
    )
    valid, reason = True, ""
    if i_eol - on.index < 10 or not t_eol > on.time:
        valid, reason = False, f"onset only {i_eol - on.index} samples before end of life"
    return ProtocolCase(t, y, thr, t_eol, i_eol, base, on.time, on.index, times,
                        t_eol - times, valid, reason)  # fmt: skip


# --------------------------------------------------------------------------- baselines
def _crossing(a: float, b: float, level: float, t_now: float) -> float:
    """Time from ``t_now`` until ``a + b t`` reaches ``level`` (``inf`` if never)."""
    if b <= 0:
        return math.inf
    return max((level - a) / b - t_now, 0.0)


def _lsq(t: Tensor, y: Tensor) -> tuple[float, float]:
    tc = t - t.mean()
    denom = float((tc * tc).sum())
    b = float((tc * (y - y.mean())).sum()) / denom if denom > 0 else 0.0
    return float(y.mean()) - b * float(t.mean()), b


def linear_slope_rul(t: Tensor, y: Tensor, threshold: float, t_onset: float) -> float:
    """RUL by a least-squares line through the last quarter of the data since onset (>= 5
    values), extrapolated to ``threshold`` from the last time (``inf``: not rising)."""
    sel = t >= t_onset
    ts, ys = t[sel], y[sel]
    n = max(5, ts.numel() // 4)
    ts, ys = ts[-n:], ys[-n:]
    if ts.numel() < 2:
        return math.inf
    a, b = _lsq(ts, ys)
    return _crossing(a, b, threshold, float(t[-1]))


def exponential_lsq_rul(
    t: Tensor, y: Tensor, threshold: float, t_onset: float, phi: float
) -> float:
    """RUL by least squares of ``log(y - phi) = a + b t`` on the data since onset (values above
    ``phi`` only), extrapolated to ``threshold`` (``inf``: not rising)."""
    sel = (t >= t_onset) & (y > phi)
    ts, ys = t[sel], y[sel]
    if ts.numel() < 2 or threshold <= phi:
        return math.inf
    a, b = _lsq(ts, (ys - phi).log())
    return _crossing(a, b, math.log(threshold - phi), float(t[-1]))


# --------------------------------------------------------------------------- scores
def rul_scores(
    times: Tensor,
    true_rul: Tensor,
    pred_rul: Tensor,
    *,
    t_onset: float,
    t_eol: float,
    lower: Tensor | None = None,
    upper: Tensor | None = None,
    alphas: tuple[float, ...] = (0.2, 0.3),
) -> dict:
    """Per-point and overall scores of one series' RUL predictions (module docstring).

    ``pred_rul`` may hold ``inf`` (no crossing predicted) and NaN (no prediction): both count
    as outside every cone; RA and errors use them as infinite. ``lower``/``upper`` ``(P,)``
    bound the predicted interval (``upper = inf`` for an interval open to the right).
    """
    times = torch.as_tensor(times, dtype=torch.float64)
    r = torch.as_tensor(true_rul, dtype=torch.float64)
    p = torch.as_tensor(pred_rul, dtype=torch.float64)
    given = {"times": times, "true_rul": r, "pred_rul": p}
    if lower is not None and upper is not None:
        given.update(lower=torch.as_tensor(lower), upper=torch.as_tensor(upper))
    if times.dim() != 1 or any(v.shape != times.shape for v in given.values()):
        # (a (1,) prediction was broadcast, or failed with a mask IndexError)
        shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in given.items())
        raise ValueError(f"{', '.join(given)} must have the same shape (P,), got {shapes}")
    p = torch.where(torch.isnan(p), torch.full_like(p, math.inf), p)
    out: dict = {"n": int(r.numel())}
    err = (p - r).abs()
    out["abs_error"] = err
    out["rel_error"] = err / r
    for a in alphas:
        inside = in_alpha_cone(p, r, a)
        out[f"in_cone_{a:g}"] = inside
        out[f"alpha_lambda_{a:g}"] = float(inside.to(torch.float64).mean())
    ra = 1.0 - err / r
    out["ra"] = ra
    out["cra"] = float(ra.mean())
    finite = torch.isfinite(p)
    if bool(finite.any()):
        ph = prognostic_horizon(
            times[finite] - t_onset,
            r[finite],
            p[finite],
            alpha=0.2,
            t_eol=t_eol - t_onset,
        )
    else:
        ph = math.nan
    out["ph_0.2"] = ph
    out["median_abs_error"] = float(err.median()) if err.numel() else math.nan
    if lower is not None and upper is not None:
        lo = torch.as_tensor(lower, dtype=torch.float64)
        hi = torch.as_tensor(upper, dtype=torch.float64)
        hi = torch.where(torch.isnan(hi), torch.full_like(hi, math.inf), hi)
        lo = torch.where(torch.isnan(lo), torch.full_like(lo, math.inf), lo)
        cover = (r >= lo) & (r <= hi)
        out["covered"] = cover
        out["coverage"] = float(cover.to(torch.float64).mean())
    return out


def last_sample_indices(t, times, *, first: int = 0, tol: float = 1e-9) -> list[int]:
    """The index of the last sample at or before each prediction time, each index once.

    For every ``tp`` of ``times`` (in order) the largest ``i`` with ``t[i] <= tp + tol``; it is
    kept when ``i >= first`` and larger than the previous kept index (times between two samples
    map to the same sample, which is used once).

    Args:
        t: ``(T,)`` sample times, non-decreasing (a tensor or a sequence).
        times: prediction times, increasing (a tensor, an array or a sequence).
        first: the smallest admissible index (e.g. the first sample a filter has seen).
        tol: slack on ``t[i] <= tp`` for times computed by accumulation (``0.1 * k``).
    Returns:
        The kept indices, increasing (times before ``t[first]`` are skipped).
    """
    ts = torch.as_tensor(t, dtype=torch.float64)
    if ts.dim() != 1:
        raise ValueError(f"t must have shape (T,), got {tuple(ts.shape)}")
    out: list[int] = []
    for tp in torch.as_tensor(times, dtype=torch.float64).flatten().tolist():
        hit = torch.nonzero(ts <= tp + tol).flatten()
        if hit.numel() == 0:
            continue
        i = int(hit[-1])
        if i >= first and (not out or i > out[-1]):
            out.append(i)
    return out
