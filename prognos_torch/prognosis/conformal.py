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
an honest check leaves out a whole asset at a time (:func:`leave_one_group_out`), and the
guarantee for a new asset needs :func:`points_needed` assets (9 for 90 %), not only points.

An open upper end (``hi = inf``: more than 5 % of the paths censored) stays open; a lower end
of 0 stays 0.

**Bins by the predicted RUL** (Mondrian conformal prediction, Vovk, Gammerman & Shafer 2005,
Sec. 4.5): one margin for all points is calibrated on average, but a model's misses often
depend on how far ahead it predicts (a lag between the model's event and the failure
definition weighs most on a short RUL). With ``bins = B > 1`` the calibration points are cut
into ``B`` equal-count bins of their predicted median RUL (in log; a censored median in the top
bin), each bin gets its own ``Q``, and a new point takes the margin of its bin: the guarantee
then holds within each bin (given the bin edges, which the calibration medians set). Every
bin needs its own points (``Q`` is ``inf`` below :func:`points_needed` of them, 9 at
``c = 0.9``), so bins are for large calibration sets, a fleet's.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..core.validation import holds_bool_or_complex, is_int, is_real

__all__ = [
    "interval_scores",
    "conformal_margin",
    "RULCalibration",
    "calibrate_intervals",
    "leave_one_group_out",
    "points_needed",
    "record_settings",
]


def _vectors(lower, upper, truth=None) -> tuple[Tensor, ...]:
    names = ("lower", "upper", "truth")
    xs = []
    for name, v in zip(names, (lower, upper, truth)):
        if v is None:
            continue
        if holds_bool_or_complex(v):  # (True was a RUL of 1; complex lost its imaginary part)
            raise TypeError(f"{name} must hold real numbers, got bool or complex values")
        try:
            xs.append(torch.as_tensor(v, dtype=torch.float64))
        except (TypeError, ValueError, RuntimeError) as exc:  # ("too many dimensions 'str'")
            raise TypeError(
                f"{name} must be a tensor or array-like of numbers, got {v!r:.60}"
            ) from exc
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


def _log_median(median: Tensor) -> Tensor:
    """The log predicted median RUL on which bins are cut; a censored median (``inf`` or NaN)
    is ``+inf``, the top bin."""
    m = torch.as_tensor(median, dtype=torch.float64)
    return torch.where(torch.isnan(m) | (m == math.inf), math.inf, m.clamp_min(1e-300).log())


def record_settings(settings: Mapping) -> dict:
    """``settings`` as a calibration record holds them (:attr:`RULCalibration.settings`): a
    value JSON holds as it is (text, number, bool, ``None``), any other as its ``repr``."""
    plain = (str, int, float, bool, type(None))
    return {k: v if isinstance(v, plain) else repr(v) for k, v in settings.items()}


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
    _check_coverage(coverage)
    s = torch.as_tensor(scores, dtype=torch.float64)
    if s.dim() != 1:
        raise ValueError(f"scores must have shape (n,), got {tuple(s.shape)}")
    s = s[~torch.isnan(s)]
    n = s.numel()
    if n == 0:
        raise ValueError("scores has no non-NaN entry: nothing to calibrate on")
    k = _rank(n, coverage)
    return math.inf if k > n else float(torch.sort(s).values[k - 1])


def _check_coverage(coverage) -> None:
    if not is_real(coverage):
        raise TypeError(f"coverage must be a float in (0, 1), got {coverage!r}")
    if not 0.0 < coverage < 1.0:
        raise ValueError(f"coverage must lie in (0, 1), got {coverage!r}")


def _check_bins(bins) -> int:
    if not is_int(bins) or bins < 1:
        raise ValueError(f"bins must be an int >= 1, got {bins!r}")
    return int(bins)


def _rank(n: int, coverage: float) -> int:
    return math.ceil((n + 1) * coverage - 1e-9)  # (guard against 0.9 * 10 = 9.000000000000002)


def points_needed(coverage: float = 0.9) -> int:
    """The fewest calibration points with a finite margin at ``coverage``: the smallest ``n``
    with ``ceil((n + 1) coverage) <= n`` (9 for 0.9, 19 for 0.95). Points of one asset move
    together, so this is also the number of assets from which the guarantee holds for a new
    asset when each gives one point."""
    _check_coverage(coverage)
    n = max(1, math.floor(coverage / (1.0 - coverage)) - 1)
    while _rank(n, coverage) > n:
        n += 1
    return n


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
        edges: with bins (module docstring), the ``B - 1`` boundaries between them on the log
            predicted median RUL; empty: one margin for every point.
        margins: with bins, the ``B`` margins, lowest median first (``margin`` is then the
            margin of all points pooled, for reference).
        assets: the assets (histories) the points came from; ``None``: not recorded. A new
            asset's coverage is assured from :func:`points_needed` of them on
            (:meth:`warning`).
    """

    margin: float
    coverage: float
    n: int
    settings: Mapping = field(default_factory=dict)
    edges: tuple[float, ...] = ()
    margins: tuple[float, ...] = ()
    assets: int | None = None

    def warning(self, noun: str = "assets") -> str | None:
        """A sentence when the margin is finite but rests on fewer assets than
        :func:`points_needed` (a calibration on them is an estimate: an asset's points move
        together); ``None`` otherwise, or when ``assets`` is not recorded. ``noun`` names the
        assets (``"histories"``, ``"failed assets"``)."""
        need = points_needed(self.coverage)
        if self.assets is None or self.assets >= need or math.isinf(self.margin):
            return None
        return (
            f"the points come from {self.assets} {noun}; an asset's points move together, and "
            f"{100 * self.coverage:g} % coverage for a new asset is assured from {need} {noun} "
            "on (one point each): read the calibrated interval as an estimate"
        )

    def margin_for(self, median=None) -> Tensor:
        """The margin of each point: ``margin``, or with bins that of the bin of its predicted
        median RUL ``median`` (``(n,)``; ``inf`` or NaN, a censored median: the top bin)."""
        if not self.edges:
            m = None if median is None else torch.as_tensor(median)
            shape, device = ((), None) if m is None else (m.shape, m.device)
            return torch.full(shape, self.margin, dtype=torch.float64, device=device)
        if median is None:
            raise ValueError(
                "this calibration has bins by the predicted median RUL: pass median= (the "
                "points' median RULs)"
            )
        m = torch.as_tensor(median, dtype=torch.float64)
        z = _log_median(m)
        idx = torch.searchsorted(
            torch.tensor(self.edges, dtype=torch.float64, device=m.device), z.reshape(-1)
        )
        return torch.tensor(self.margins, dtype=torch.float64, device=m.device)[idx].reshape(
            m.shape
        )

    def to_dict(self) -> dict:
        """A JSON-ready record (a margin ``None`` when ``+inf``, ``"-inf"`` when ``-inf``: the
        calibration intervals were ``[0, inf)``); :meth:`from_dict` reads it."""
        num = lambda q: q if math.isfinite(q) else (None if q > 0 else "-inf")  # noqa: E731
        out = {"margin": num(self.margin), "coverage": self.coverage, "n": self.n,
               "settings": dict(self.settings)}  # fmt: skip
        if self.edges:
            out.update(edges=list(self.edges), margins=[num(q) for q in self.margins])
        if self.assets is not None:
            out["assets"] = self.assets
        return out

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
        if m is not None and m != "-inf" and not (real(m) and not math.isnan(m)):
            raise ValueError(f'margin must be a number, null (inf) or "-inf", got {m!r}')
        if not (real(c) and 0.0 < c < 1.0):
            raise ValueError(f"coverage must lie in (0, 1), got {c!r}")
        if not (isinstance(n, int) and not isinstance(n, bool) and n >= 0):
            raise ValueError(f"n must be a count >= 0, got {n!r}")
        settings = record.get("settings") or {}
        if not isinstance(settings, Mapping):
            raise ValueError(f"settings must be a mapping, got {settings!r:.80}")
        edges, margins = record.get("edges") or [], record.get("margins") or []
        if not (isinstance(edges, list) and isinstance(margins, list)
                and all(real(e) and math.isfinite(e) for e in edges)
                and list(edges) == sorted(edges)
                and len(margins) == (len(edges) + 1 if edges else 0)
                and all(q is None or q == "-inf" or (real(q) and not math.isnan(q))
                        for q in margins)):  # fmt: skip
            raise ValueError(
                "edges must be increasing finite numbers and margins one more numbers, nulls "
                '(inf) or "-inf", '
                f"got edges {edges!r:.80}, margins {margins!r:.80}"
            )
        assets = record.get("assets")
        if assets is not None and not (isinstance(assets, int) and not isinstance(assets, bool)
                                       and assets >= 1):  # fmt: skip
            raise ValueError(f"assets must be a count >= 1 or null, got {assets!r}")
        qs = tuple(math.inf if q is None else float(q) for q in margins)
        return cls(math.inf if m is None else float(m), float(c), n, dict(settings),
                   tuple(float(e) for e in edges), qs, assets)  # fmt: skip

    def interval(self, lower, upper, median=None) -> tuple[Tensor, Tensor]:
        """The calibrated ends ``(lower e^-Q, upper e^Q)``, ``(n,)`` or scalars each (an open
        upper end stays ``inf``; NaN stays NaN); ``median``: the predicted median RULs, needed
        with bins (:meth:`margin_for`)."""
        for name, v in (("lower", lower), ("upper", upper)):
            if torch.as_tensor(v).dim() > 1:  # (was flattened to (n,) and returned so)
                raise ValueError(f"{name} must have shape (n,) or be a scalar, got "
                                 f"{tuple(torch.as_tensor(v).shape)}")  # fmt: skip
        scalar = torch.as_tensor(lower).dim() == 0 and torch.as_tensor(upper).dim() == 0
        lo, hi = _vectors(torch.as_tensor(lower).reshape(-1), torch.as_tensor(upper).reshape(-1))
        med = None if median is None else torch.as_tensor(median, dtype=torch.float64).reshape(-1)
        if med is not None and med.shape != lo.shape:
            raise ValueError(f"median must have shape {tuple(lo.shape)}, got {tuple(med.shape)}")
        q = self.margin_for(med) if self.edges else torch.full_like(lo, self.margin)
        new_lo, new_hi = _widen(lo, hi, q)
        return (new_lo[0], new_hi[0]) if scalar else (new_lo, new_hi)

    def summary(self, result) -> dict:
        """``result.summary()`` (a :class:`~prognos_torch.workflow.RULResult`) with a
        ``"calibrated"`` entry ``{"q05", "q95", "margin", "empty", "coverage", "n", "assets",
        "warning"}`` (``warning``: :meth:`warning`'s sentence or ``None``): its 90 % interval
        calibrated (``q95`` ``None`` when open). ``empty`` is ``True`` where a negative margin
        narrowed the interval past its own width (``q05 > q95``, or ``q05 = inf`` for a margin
        of ``-inf``): the calibrated set is empty, as in CQR, and covers no RUL. Before onset there is no interval, only a lower
        bound, and the summary comes back unchanged. Where more than 95 % of the paths are
        censored, ``q05`` is beyond the horizon and the horizon ``bound`` stands in for it.

        Raises:
            ValueError: the calibration was made with another threshold (where it names one),
                direction or number of paths than ``result``: its guarantee holds for intervals
                made the same way.
        """
        s = result.summary()
        if s["status"] != "ok":
            return s
        st = self.settings or {}
        mine = {"threshold": getattr(result, "threshold", None),
                "direction": getattr(result, "direction", None),
                "n_paths": getattr(result, "n_particles", None)}  # fmt: skip
        for key, here in mine.items():
            made = st.get(key)  # (threshold "protocol": the histories' own, any threshold)
            if made is None or here is None or isinstance(made, bool) or made == "protocol":
                continue
            same = (math.isclose(made, here, rel_tol=1e-9) if isinstance(made, (int, float))
                    else made == here)  # fmt: skip
            if not same:
                raise ValueError(
                    f"the calibration was made with {key}={made!r}, this result has "
                    f"{key}={here!r}: the guarantee holds for intervals made the same way"
                )
        lo = s["q05"] if s["q05"] is not None else s["bound"]
        hi = math.inf if s["q95"] is None else s["q95"]
        med = math.inf if s.get("median") is None else s["median"]
        q = self.margin_for(torch.tensor([med], dtype=torch.float64))
        new_lo, new_hi = (float(v[0]) for v in _widen(*_vectors([float(lo)], [float(hi)]), q))
        s["calibrated"] = {
            "q05": new_lo,
            "q95": new_hi if math.isfinite(new_hi) else None,
            "margin": float(q[0]),
            "empty": new_lo > new_hi or new_lo == math.inf,
            "coverage": self.coverage,
            "n": self.n,
            "assets": self.assets,
            "warning": self.warning(),
        }
        return s


def _widen(lo: Tensor, hi: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
    """``(lo e^-q, hi e^q)``, ``(n,)`` each: ``q = inf`` opens the interval to ``(0, inf)``;
    an open upper end stays ``inf``, a lower end of 0 stays 0, NaN stays NaN, and ``hi = 0``
    stays 0. ``q = -inf`` (or one whose ``e^q`` underflows) keeps ``[0, inf)`` and empties
    every other interval (a lower end ``> 0`` goes to ``inf``, a finite upper end to 0), as
    the CQR set ``{r: E(r) <= Q}`` does."""
    inf = q == math.inf
    f = torch.where(inf, 1.0, q.clamp_max(700.0).exp())
    new_lo = torch.where(inf & ~torch.isnan(lo), 0.0, torch.where(lo == 0, 0.0, lo / f))
    new_hi = torch.where(inf, torch.where(torch.isnan(hi), hi, math.inf), hi * f)
    new_hi = torch.where(hi == math.inf, math.inf, new_hi)
    return new_lo, torch.where((hi == 0) & ~inf, 0.0, new_hi)


def calibrate_intervals(
    lower,
    upper,
    truth,
    coverage: float = 0.9,
    *,
    median=None,
    bins: int = 1,
    groups: Sequence[Hashable] | None = None,
) -> RULCalibration:
    """:class:`RULCalibration` from predicted intervals and true RULs ``(n,)`` each, of assets
    of the population the calibration will serve (NaN entries are left out).

    Args:
        lower, upper, truth: ``(n,)`` as in :func:`interval_scores`.
        coverage: the target coverage.
        median: ``(n,)`` predicted median RULs (``inf``: censored), needed for ``bins > 1``.
        bins: ``B`` equal-count bins of the log median, each with its own margin (module
            docstring); 1: one margin.
        groups: ``n`` labels, the asset of each point: recorded as ``assets``, the count of
            assets among the points with an interval (:meth:`RULCalibration.warning`).
    """
    scores = interval_scores(lower, upper, truth)
    ok = ~torch.isnan(scores)
    n = int(ok.sum())
    assets = None
    if groups is not None:
        if (isinstance(groups, (str, bytes)) or getattr(groups, "ndim", 1) != 1
                or len(groups) != scores.shape[0]):  # fmt: skip
            raise ValueError(
                f"groups must be {scores.shape[0]} labels (one per point), got {groups!r:.80}"
            )
        labels = _labels(groups)  # (a tensor's labels counted each point as an asset)
        assets = len({g for g, k in zip(labels, ok.tolist()) if k})
    pooled = conformal_margin(scores, coverage)
    bins = _check_bins(bins)
    if bins == 1:
        return RULCalibration(pooled, float(coverage), n, assets=assets)
    if median is None:
        raise ValueError("bins > 1 needs median= (the points' predicted median RULs)")
    m = torch.as_tensor(median, dtype=torch.float64)
    if m.shape != scores.shape:
        raise ValueError(f"median must have shape {tuple(scores.shape)}, got {tuple(m.shape)}")
    if n < bins:
        raise ValueError(f"bins = {bins} needs at least as many points, got {n}")
    z = _log_median(m)[ok]
    order = torch.sort(z).values
    cuts = [int(round(n * j / bins)) for j in range(1, bins)]
    # a boundary halfway between neighbours; two equal medians stay in one bin, and a boundary
    # that a tie of medians leaves with no point on one side (e.g. tied top medians) is dropped
    # (between a finite and a censored median the boundary is the finite one: the midpoint is
    # inf, and the boundary was dropped, leaving the censored medians in a finite bin)
    mids = sorted({_cut(float(order[c - 1]), float(order[c])) for c in cuts})
    edges: list[float] = []
    for e in (e for e in mids if math.isfinite(e)):
        below = edges[-1] if edges else -math.inf
        if bool(((z > below) & (z <= e)).any()) and bool((z > e).any()):
            edges.append(e)
    idx = torch.searchsorted(torch.tensor(edges, dtype=torch.float64, device=z.device), z)
    s = scores[ok]
    margins = tuple(
        conformal_margin(s[idx == j], coverage) if bool((idx == j).any()) else math.inf
        for j in range(len(edges) + 1)
    )
    if not edges:
        return RULCalibration(pooled, float(coverage), n, assets=assets)
    return RULCalibration(pooled, float(coverage), n, {}, tuple(edges), margins, assets)


def _cut(a: float, b: float) -> float:
    """The boundary between neighbouring log medians ``a <= b``: halfway, or ``a`` when ``b``
    is a censored median (``+inf``) and ``a`` is not."""
    return a if b == math.inf and a < b else 0.5 * (a + b)


def _labels(groups) -> list:
    """Group labels as a list; a 1-D tensor's or array's by their values (a tensor's entries are
    0-d tensors, each equal only to itself as a set member or dict key)."""
    return groups.tolist() if getattr(groups, "ndim", None) == 1 else list(groups)


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
    if isinstance(groups, (str, bytes)) or len(groups) != lo.shape[0]:
        got = f"the string {groups!r:.40}" if isinstance(groups, (str, bytes)) else len(groups)
        raise ValueError(f"groups must have {lo.shape[0]} labels (one per point), got {got}")
    labels = _labels(groups)
    scores = interval_scores(lo, hi, tr)
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
