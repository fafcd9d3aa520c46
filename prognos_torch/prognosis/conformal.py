"""Split-conformal calibration of RUL intervals on assets of the same population.

A 90 % RUL interval is calibrated when the true RUL falls in it 90 % of the time. A model's own
interval is calibrated only as far as the data follow the model; on real bearings that fail by
a surge the trend did not show, the lower end sits too late (docs/RESULTS.md,
``pronostia-rul``). Where earlier assets of the same population have run to failure, their
predictions and true RULs calibrate the interval without any assumption on the model:
conformalized quantile regression (CQR, Romano, Patterson & Candes 2019, Sec. 3), here on the
log RUL, where errors scale with the RUL::

    E_i = max(log lo_i - log r*_i, log r*_i - log hi_i)        conformity score of point i
    Q   = the ceil((n + 1) c)-th smallest of E_1 .. E_n        (inf when that exceeds n)
    C   = [lo e^-Q, hi e^Q]                                    the calibrated interval

``lo``/``hi`` are the model's interval ends (for :func:`~prognos_torch.workflow.prognose`, q05
and q95), ``r*`` the true RUL, ``c`` the target coverage. If the ``n`` calibration points and
the new one are exchangeable, ``P(r* in C) >= c`` (their Theorem 1), whatever the model; with
distinct scores also ``<= c + 1 / (n + 1)``. ``Q < 0`` narrows an interval that covered more
than asked; one narrower than the factor ``e^{-2Q}`` then comes out empty (``lower > upper``) and
covers nothing, as in CQR. Points of one asset are not exchangeable with each other's neighbours in time, so
an honest check leaves out a whole asset at a time (:func:`leave_one_group_out`).

An open upper end (``hi = inf``: more than 5 % of the paths censored) stays open; a lower end
of 0 stays 0.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

__all__ = [
    "interval_scores",
    "conformal_margin",
    "RULCalibration",
    "calibrate_intervals",
    "leave_one_group_out",
]


def _vectors(lower, upper, truth=None) -> tuple[Tensor, ...]:
    names = ("lower", "upper", "truth")
    xs = [torch.as_tensor(v, dtype=torch.float64) for v in (lower, upper, truth) if v is not None]
    for name, x in zip(names, xs):
        if x.dim() != 1:
            raise ValueError(f"{name} must have shape (n,), got {tuple(x.shape)}")
    if any(x.shape != xs[0].shape for x in xs):
        shapes = ", ".join(f"{n} {tuple(x.shape)}" for n, x in zip(names, xs))
        raise ValueError(f"lower, upper and truth must have the same shape (n,), got {shapes}")
    lo, hi = xs[0], xs[1]
    ok = ~(torch.isnan(lo) | torch.isnan(hi))
    if bool((lo[ok] < 0).any()) or bool((lo[ok] == math.inf).any()):
        raise ValueError("lower must be finite and >= 0 (NaN: no interval at that point)")
    if bool((hi[ok] < lo[ok]).any()):
        raise ValueError("upper must be >= lower at every point")
    if truth is not None:
        tr = xs[2]
        if bool((~(tr[~torch.isnan(tr)] > 0)).any()) or bool(torch.isinf(tr).any()):
            raise ValueError("truth must be finite and > 0 (a true RUL; NaN: unknown)")
    return tuple(xs)


def interval_scores(lower, upper, truth) -> Tensor:
    """CQR conformity scores on the log RUL, ``(n,)`` each -> ``(n,)`` (module docstring).

    Args:
        lower, upper: the predicted interval ends (``0 <= lower <= upper <= inf``).
        truth: the true RULs (``> 0``).

    Returns:
        ``E_i = max(log lower_i - log truth_i, log truth_i - log upper_i)``; positive where the
        truth lies outside the interval, by the log factor it misses by. NaN where any input is
        NaN (no interval, or no truth, at that point).
    """
    lo, hi, tr = _vectors(lower, upper, truth)
    y = tr.log()
    return torch.maximum(lo.log() - y, y - hi.log())


def conformal_margin(scores, coverage: float = 0.9) -> float:
    """``Q``: the ``ceil((n + 1) coverage)``-th smallest of the ``n`` non-NaN ``scores``
    (``inf`` when that rank exceeds ``n``: too few points for the coverage asked)."""
    if isinstance(coverage, bool) or not isinstance(coverage, (int, float)):
        raise TypeError(f"coverage must be a float in (0, 1), got {coverage!r}")
    if not 0.0 < coverage < 1.0:
        raise ValueError(f"coverage must lie in (0, 1), got {coverage!r}")
    s = torch.as_tensor(scores, dtype=torch.float64)
    if s.dim() != 1:
        raise ValueError(f"scores must have shape (n,), got {tuple(s.shape)}")
    s = s[~torch.isnan(s)]
    n = s.numel()
    if n == 0:
        raise ValueError("scores has no non-NaN entry: nothing to calibrate on")
    k = math.ceil((n + 1) * coverage - 1e-9)  # (guard against 0.9 * 10 = 9.000000000000002)
    return math.inf if k > n else float(torch.sort(s).values[k - 1])


@dataclass(frozen=True)
class RULCalibration:
    """A conformal margin for RUL intervals, learnt on assets that ran to failure.

    Attributes:
        margin: ``Q`` on the log RUL (module docstring); ``inf``: too few calibration points.
        coverage: the coverage ``c`` it guarantees under exchangeability.
        n: the calibration points it was computed from.
        settings: how the calibrated intervals were made (for
            :func:`~prognos_torch.workflow.calibrate_rul`: ``prognose``'s settings, the failure
            threshold and direction); the guarantee holds for intervals made the same way.
    """

    margin: float
    coverage: float
    n: int
    settings: Mapping = field(default_factory=dict)

    def to_dict(self) -> dict:
        """A JSON-ready record (``margin`` ``None`` when infinite); :meth:`from_dict` reads it."""
        inf = math.isinf(self.margin)
        return {"margin": None if inf else self.margin, "coverage": self.coverage, "n": self.n,
                "settings": dict(self.settings)}  # fmt: skip

    @classmethod
    def from_dict(cls, record: Mapping) -> RULCalibration:
        """The calibration of a :meth:`to_dict` record, checked field by field."""
        if not isinstance(record, Mapping):
            raise TypeError(f"a calibration record must be a mapping, got {type(record).__name__}")
        missing = [k for k in ("margin", "coverage", "n") if k not in record]
        if missing:
            raise ValueError(f"the calibration record has no {', '.join(missing)}")
        m, c, n = record["margin"], record["coverage"], record["n"]
        real = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)  # noqa: E731
        if m is not None and not (real(m) and not math.isnan(m)):
            raise ValueError(f"margin must be a number or null (infinite), got {m!r}")
        if not (real(c) and 0.0 < c < 1.0):
            raise ValueError(f"coverage must lie in (0, 1), got {c!r}")
        if not (isinstance(n, int) and not isinstance(n, bool) and n >= 0):
            raise ValueError(f"n must be a count >= 0, got {n!r}")
        settings = record.get("settings") or {}
        if not isinstance(settings, Mapping):
            raise ValueError(f"settings must be a mapping, got {settings!r:.80}")
        return cls(math.inf if m is None else float(m), float(c), n, dict(settings))

    def interval(self, lower, upper) -> tuple[Tensor, Tensor]:
        """The calibrated ends ``(lower e^-Q, upper e^Q)``, ``(n,)`` or scalars each (an open
        upper end stays ``inf``; NaN stays NaN)."""
        scalar = torch.as_tensor(lower).dim() == 0 and torch.as_tensor(upper).dim() == 0
        lo, hi = _vectors(torch.as_tensor(lower).reshape(-1), torch.as_tensor(upper).reshape(-1))
        f = math.exp(self.margin) if self.margin < math.inf else math.inf
        new_lo = lo / f if f < math.inf else torch.zeros_like(lo).where(~torch.isnan(lo), lo)
        new_hi = torch.where(hi == 0, hi * 0 if f < math.inf else hi + math.inf, hi * f)
        return (new_lo[0], new_hi[0]) if scalar else (new_lo, new_hi)

    def summary(self, result) -> dict:
        """``result.summary()`` (a :class:`~prognos_torch.workflow.RULResult`) with a
        ``"calibrated"`` entry ``{"q05", "q95", "margin", "coverage", "n"}``: its 90 % interval
        calibrated (``q95`` ``None`` when open). Before onset there is no interval, only a lower
        bound, and the summary comes back unchanged. Where more than 95 % of the paths are
        censored, ``q05`` is beyond the horizon and the horizon ``bound`` stands in for it."""
        s = result.summary()
        if s["status"] != "ok":
            return s
        lo = s["q05"] if s["q05"] is not None else s["bound"]
        hi = math.inf if s["q95"] is None else s["q95"]
        new_lo, new_hi = self.interval(float(lo), float(hi))
        s["calibrated"] = {
            "q05": float(new_lo),
            "q95": float(new_hi) if math.isfinite(float(new_hi)) else None,
            "margin": self.margin,
            "coverage": self.coverage,
            "n": self.n,
        }
        return s


def calibrate_intervals(lower, upper, truth, coverage: float = 0.9) -> RULCalibration:
    """:class:`RULCalibration` from predicted intervals and true RULs ``(n,)`` each, of assets
    of the population the calibration will serve (NaN entries are left out)."""
    scores = interval_scores(lower, upper, truth)
    n = int((~torch.isnan(scores)).sum())
    return RULCalibration(conformal_margin(scores, coverage), float(coverage), n)


def leave_one_group_out(
    lower, upper, truth, groups: Sequence[Hashable], coverage: float = 0.9
) -> tuple[Tensor, Tensor, Tensor]:
    """Each point's interval calibrated on the points of every *other* group (an asset, a
    bearing): the honest check of :func:`calibrate_intervals` on assets it has not seen.

    Args:
        lower, upper, truth: ``(n,)`` as in :func:`interval_scores`.
        groups: ``n`` labels; the points of a label are left out together.
        coverage: the target coverage.

    Returns:
        ``(lower, upper, margin)``, ``(n,)`` each: the calibrated ends and the margin used
        (NaN where the point has no interval).
    """
    lo, hi, tr = _vectors(lower, upper, truth)
    if len(groups) != lo.shape[0]:
        raise ValueError(
            f"groups must have {lo.shape[0]} labels (one per point), got {len(groups)}"
        )
    scores = interval_scores(lo, hi, tr)
    labels = list(groups)
    margin = torch.full_like(lo, math.nan)
    new_lo, new_hi = lo.clone(), hi.clone()
    for g in dict.fromkeys(labels):
        mine = torch.tensor([x == g for x in labels])
        others = scores[~mine]
        if bool((~torch.isnan(others)).any()):
            cal = RULCalibration(conformal_margin(others, coverage), float(coverage), 0)
            a, b = cal.interval(lo[mine], hi[mine])
            new_lo[mine], new_hi[mine] = a, b
            margin[mine] = cal.margin
        else:
            new_lo[mine], new_hi[mine] = math.nan, math.nan
    margin[torch.isnan(lo)] = math.nan
    return new_lo, new_hi, margin
