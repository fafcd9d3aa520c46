"""One entry point from a degradation series to a remaining-useful-life distribution.

::

    from prognos_torch.workflow import load_series, prognose

    s = load_series("bearing.csv", column="rms", time_column="timestamp", where={"channel": 5})
    r = prognose(s, threshold=0.45)
    print(r.summary())   # status, median, mean, q05, q95, censored_mass, bound, model,
                         # onset_time, flags

Pipeline of :func:`prognose` (every step a library function with its own tests):

1. **Checks.** NaN values are missing (dropped: the trend models are continuous-time, so a
   missing sample is just a longer step). At least :data:`MIN_POINTS` observed values. The
   threshold must lie outside the healthy band ``mu_0 +- 4 sigma_0`` of the baseline (the first
   ``baseline`` fraction of the time span), on the side of ``direction``; ``"auto"`` takes the
   side the threshold is on. A threshold already reached by the median of the last 5 values is
   an error (the RUL is 0). Isolated values far from their neighbours in the healthy window
   (sensor glitches, :func:`~prognos_torch.prognosis.onset.isolated_outliers`) count unless
   ``glitch_limit`` is set; one glitch can widen the band enough to hide the onset, so gross
   ones that widen it by half or more are flagged.
2. **Onset** (:mod:`prognos_torch.prognosis.onset`; k-sigma rule on the 5-point moving median,
   5 consecutive exceedances, or a CUSUM), searched after the healthy window (which is assumed
   healthy: a run-in transient in it is no onset). Before onset the answer is *"no degradation
   detected yet"*: no median or interval is reported, only a lower bound (below).
3. **Trend models** on the data since onset (:mod:`~prognos_torch.prognosis.trends`:
   exponential, power law, linear, all filtered at once by the engine, by default with the
   exact Kalman filter (``filter="ekf"``; ``"stekf"`` adds strong tracking), over a grid of
   noise levels;
   :mod:`~prognos_torch.prognosis.learner_trend`: an ELM growth
   rate trained online by the Kalman optimiser, as an equal-weight ensemble of
   ``learner_members`` ELMs with independent random features). Series with more than
   ``max_points`` values since onset are averaged over equal-count blocks first (the baseline
   noise of a block mean is ``sigma_0 / sqrt(count)``).
4. **Noise choice and the ``auto`` pool.** A backtest on the series' own past
   (:mod:`~prognos_torch.prognosis.backtest`): for the levels
   ``m_0 + f (max m - m_0)``, ``f in {0.5, 0.8}``, that the 5-point moving median ``m`` has
   already crossed since onset, each model predicts the crossing from origins at 40 % and 70 %
   of the way from onset to it (posterior at the origin: causal; the noise grid's scale uses
   all data). The score is the CRPS of the predicted log time to the crossing (Gneiting &
   Raftery 2007; a proper score, so it rewards calibrated as well as sharp predictions; censored
   paths count at 10 x the truth; :data:`BACKTEST_PATHS` paths per prediction). Each shape's
   noise is the grid point of best mean score (of highest likelihood when no level has been
   crossed yet). ``method="auto"`` then pools the RUL distributions of the exponential model
   (Gebraeel's) and the learner trend with equal weights (:data:`AUTO_POOL`; half the paths
   each) rather than choosing one: on the synthetic
   run-to-failure families of :mod:`prognos_torch.systems.run_to_failure` (processes that
   neither model contains) switching to the shape with the best backtest lowered the share of
   predictions within +-30 % and the 90 % coverage, while the pool tied the exponential model
   in log-time CRPS with coverage near nominal (docs/RESULTS.md, ``rul-synthetic``); switching
   only on strong evidence (2 standard errors) tied the pool there and lost to it on the IMS
   bearings. A shape whose backtest beats the exponential one by more than one standard error
   of the paired differences (:func:`one_standard_error_choice`) raises a "model doubt" flag
   that names it (a clearly linear wear, for example); the backtest scores of every shape are
   reported in ``selection``.
5. **RUL.** ``n_paths`` sample paths from the chosen model's posterior at the last observation,
   run until every path has crossed or until the horizon ``horizon_factor x`` the observed life
   (at least 10 x the time since onset), never a short fixed cap; paths that do not cross are
   the censored mass (RUL > ``bound``). Each path's RUL is the first time of the path grid at
   or past the threshold: steps of ``max(dt, horizon / 20000)``, then steps of 1-2 % of the
   elapsed horizon (:func:`~prognos_torch.prognosis.trends.path_grid`), so up to one such step
   late; a RUL of a few sampling steps, or a long history (whose horizon widens the step),
   reads late by up to that step. With ``at`` later than the last observation the RUL is
   counted from ``at``, conditioned on the asset still running then (paths that crossed
   before ``at`` are dropped; their mass is reported in ``flags``).
6. **Guard rails** (``flags``): a threshold far beyond the range seen since onset (more than 3
   times the rise observed so far in the model's measurement space, or more than 10 times the
   highest excess over the healthy level in data units), diverging paths, censored mass above
   5 %, few observations since onset, a last value beyond the threshold while the median is
   not, a threshold that the median of 5 values reached before and fell back from, a series
   whose last 5 values are back within one baseline std of the healthy mean (where the log
   shapes have no measurement), and before onset a run of newest medians beyond the onset
   limit that is still shorter than the 5 that declare onset ("onset pending").
   With ``direction="auto"`` a series that left its healthy band only on the side away from
   the threshold is refused as a threshold on the wrong side when its 5-value median has moved
   at least as far from the healthy mean as the threshold lies on the other side (a series
   that degrades the other way); a smaller excursion (a bearing's rms settling after run-in)
   is reported as "no degradation detected yet" towards the threshold, with a flag that names
   the excursion.

Before onset the lower bound is the 5 % quantile of the first passage under a local *linear*
trend (drift and Brownian level) fitted to the healthy data, or the horizon when even that is
censored: a statement about the data seen so far, not a forecast of when degradation will
start.

Units: every step uses only unit-free quantities, so the RUL is the same (to rounding) in any
units of the data (scale, offset, sign) and of the clock (scale, origin), for every ``method``
(``tests/test_prognose.py``).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Sequence
from dataclasses import replace

import torch
from torch import Tensor

from .._text import fmt_level, fmt_time
from ..core.validation import check_real, check_seed, has_missing, is_int
from ..filters import FILTERS, GaussianFilter
from ..prognosis.backtest import (
    backtest_scores,
    crossing_pairs,
    crps_log_time,
    one_standard_error_choice,
)
from ..prognosis.learner_trend import fit_learner_trends
from ..prognosis.onset import (
    GLITCH_SCREEN,
    GLITCH_WIDENING,
    Baseline,
    Onset,
    detect_onset,
    healthy_baseline,
    moving_median,
)
from ..prognosis.rul import RULDistribution
from ..prognosis.trends import TREND_SHAPES, TrendPool, fit_trends, path_grid
from .arrays import array_times, array_values, datetime_index, pandas_name
from .data import Series, check_magnitude, time_value
from .guards import (
    BAND_K,
    CENSORED_FLAG,
    away_from_threshold,
    baseline_flags,
    beyond_the_data,
    fit_flags,
    glitch_flags,
    onset_pending,
    threshold_side,
)
from .memory import check_prognose_memory
from .predict import RULResult
from .times import check_time_format

__all__ = [
    "prognose",
    "PROGNOSE_METHODS",
    "MIN_POINTS",
    "crps_log_time",
    "one_standard_error_choice",
    "AUTO_POOL",
    "BACKTEST_PATHS",
    "CENSORED_FLAG",
    "GLITCH_SCREEN",
    "GLITCH_WIDENING",
    "filter_pool",
    "check_prognose_options",
]

#: Trend models ``prognose`` accepts (``"auto"``: the :data:`AUTO_POOL`, every shape backtested).
PROGNOSE_METHODS = ("auto", *TREND_SHAPES, "elm")
#: The trend models whose RUL distributions ``method="auto"`` pools with equal weights.
AUTO_POOL = ("exponential", "elm")
#: Paths per backtest prediction. The noise of each shape is the argmin of Monte Carlo scores:
#: with 64 paths that choice alone moved the exponential model's median by a median factor of
#: 1.13 across seeds (256: 1.08; docs/RESULTS.md).
BACKTEST_PATHS = 256
#: Fewest observed values ``prognose`` accepts.
MIN_POINTS = 10
_MAX_BINS = 20_000


# ----------------------------------------------------------------------------- inputs
def _as_series(series, time, time_format=None) -> tuple[Tensor, Tensor, Series | None]:
    # one series is a few thousand values: computed on the CPU wherever the data live
    check_time_format(time_format)  # (as load_series: 5 failed inside strptime, unnamed)
    if time_format is not None and time is None:
        raise ValueError("time_format applies to time= given as text: pass time= as well")
    if isinstance(series, Series):
        if time is not None:
            raise ValueError("time is taken from the Series; do not pass time= as well")
        x = series.values.to("cpu", torch.float64)
        check_magnitude(x.numpy(), "series")  # a Series built by hand, as an array's values
        return x, series.t.to("cpu", torch.float64), series
    x = torch.from_numpy(array_values(series, "series"))
    if x.dim() != 1:
        raise ValueError(f"series must be a Series or have shape (T,), got {tuple(x.shape)}")
    check_magnitude(x.numpy(), "series")
    if time is None:
        time = datetime_index(series)
    src = None
    if time is None:
        t = torch.arange(x.shape[0], dtype=torch.float64)
    else:
        tv, unit, start = array_times(time, "time", time_format)
        t = torch.from_numpy(tv)
        if tuple(t.shape) != tuple(x.shape):
            raise ValueError(f"time must have shape {tuple(x.shape)} (T,), got {tuple(t.shape)}")
        # date-times: days since the first, as from a CSV; numbers: in the unit "time", as
        # load_series names an array's clock (never "steps", which would misstate the RUL)
        src = Series(x, t, pandas_name(series) or "series", "time", unit or "time", start)
    has_missing(x, "series")  # inf refused
    if not bool(torch.isfinite(t).all()):
        raise ValueError("time must be finite")
    if x.shape[0] > 1 and not bool((t[1:] > t[:-1]).all()):
        raise ValueError("time must be strictly increasing, shape (T,)")
    return x, t, src


def filter_pool(filter) -> tuple:
    """``prognose``'s ``filter`` argument as a tuple of Gaussian filter names (lower case) or
    :class:`GaussianFilter` s: one, several joined by ``+`` (``"ekf+stekf"``), or a tuple or
    list of them; a ``ValueError`` names what is wrong (the command line checks ``--filter``
    with it before anything runs)."""
    items = filter.split("+") if isinstance(filter, str) else filter
    items = (items,) if isinstance(items, GaussianFilter) else items
    if not isinstance(items, (tuple, list)) or not items:
        raise ValueError(
            "filter must be a filter name (ekf, sckf, stekf, stsckf), several joined by '+', a "
            f"GaussianFilter, or a tuple of them, got {filter!r}"
        )
    out = []
    for f in items:
        if isinstance(f, str):
            f = f.strip().lower()
            if f not in FILTERS:
                raise ValueError(
                    f"filter must name Gaussian filters among {', '.join(sorted(FILTERS))} "
                    f"(several joined by '+' are pooled), got {filter!r}"
                )
        elif not isinstance(f, GaussianFilter):
            raise ValueError(f"filter entries must be names or GaussianFilters, got {f!r}")
        out.append(f)
    if len(out) > 1 and len({f if isinstance(f, str) else id(f) for f in out}) < len(out):
        raise ValueError(f"filter names a filter twice: {filter!r}")
    return tuple(out)


def _level_fit(models: dict, pool: tuple[str, ...]):
    """The trend fit that the flags read: the first pooled model's (for the learner ensemble,
    the level fit its members share)."""
    fit = models[pool[0]]
    return fit.members[0] if isinstance(fit, TrendPool) else fit


def _filter_label(models: dict, pool: tuple[str, ...]) -> str:
    """The name of the filter a run's models were fitted under (for the learner trend, that of
    the exponential fit it learns from)."""
    fit = _level_fit(models, pool)
    return getattr(fit, "filter", None) or fit.level_fit.filter


def check_prognose_options(**options) -> None:
    """The checks ``prognose`` makes of its settings before it reads the data (``method``,
    ``direction``, ``seed``, ``n_paths``, ``horizon_factor``, ``filter``, ...; a name it does
    not take is a ``TypeError``), for a caller that passes the same ``options`` to many calls
    (the fleet: a bad option is then the call's error, not every asset's)."""
    bound = inspect.signature(prognose).bind_partial(None, 0.0, **options).arguments
    bound = {k: v for k, v in bound.items() if k not in ("series", "threshold")}
    defaults = {k: p.default for k, p in inspect.signature(prognose).parameters.items()}
    get = {**defaults, **bound}.get
    _settings(get("method"), get("direction"), get("seed"), get("n_paths"), get("max_points"),
              get("learner_hidden"), get("learner_members"), get("horizon_factor"),
              get("filter"))  # fmt: skip


def _settings(method, direction, seed, n_paths, max_points, learner_hidden, learner_members,
              horizon_factor, filter) -> tuple:  # fmt: skip
    """``prognose``'s settings checked (ValueError naming each), as it uses them."""
    if method not in PROGNOSE_METHODS:
        raise ValueError(f"method must be one of {', '.join(PROGNOSE_METHODS)}, got {method!r}")
    if direction not in ("auto", "above", "below"):
        raise ValueError(f"direction must be 'auto', 'above' or 'below', got {direction!r}")
    seeds = _check_seeds(seed)
    n_paths = _check_int(n_paths, "n_paths", 10)
    check_prognose_memory(n_paths)
    max_points = _check_int(max_points, "max_points", 20)
    learner_hidden = _check_int(learner_hidden, "learner_hidden", 1)
    learner_members = _check_int(learner_members, "learner_members", 1)
    horizon_factor = check_real(horizon_factor, "horizon_factor")
    if horizon_factor <= 0:
        raise ValueError(f"horizon_factor must be positive, got {horizon_factor}")
    filters = filter_pool(filter)
    return seeds, n_paths, max_points, learner_hidden, learner_members, horizon_factor, filters


def _check_seeds(seed) -> tuple[int, ...]:
    """``seed`` as a tuple of distinct ints: one seed, or a non-empty list or tuple of them."""
    if isinstance(seed, (list, tuple)):
        if not seed:
            raise ValueError("seed must be an int or a non-empty sequence of ints, got []")
        seeds = tuple(check_seed(s) for s in seed)
        if len(set(seeds)) < len(seeds):
            raise ValueError(f"seed names a seed twice: {list(seeds)} (pooled seeds must differ)")
        return seeds
    return (check_seed(seed),)


def _check_int(v, name: str, lo: int) -> int:
    if not is_int(v) or v < lo:
        raise ValueError(f"{name} must be an int >= {lo}, got {v!r}")
    return int(v)


def _blocks(t: Tensor, y: Tensor, sigma0: float, max_points: int):
    """Block means of ``size`` values when there are more than ``max_points`` values, ending
    at the newest value; the oldest block also takes the ``n mod size`` values left over (its
    mean's noise, below ``sigma0 / sqrt(size)``, is overstated). A short newest block would
    enter the filter with a full block's noise, and the RUL would follow the parity of the
    number of values."""
    n = t.shape[0]
    if n <= max_points:
        return t, y, sigma0, 1
    size = math.ceil(n / max_points)
    first = size + n % size
    tb = torch.cat([t[:first].mean().reshape(1), t[first:].reshape(-1, size).mean(1)])
    yb = torch.cat([y[:first].mean().reshape(1), y[first:].reshape(-1, size).mean(1)])
    return tb, yb, sigma0 / math.sqrt(size), size


# ----------------------------------------------------------------------------- RUL pieces
def _distribution(
    rul: Tensor, weights: Tensor, bin_width: float, bins: int, t_scale: float
) -> RULDistribution:
    """A :class:`RULDistribution` on ``bin_width * (1..bins)`` from per-path RULs (inf:
    censored); ``t_scale``: the magnitude of the clock's times the RULs were subtracted from."""
    # crossing times on the grid's linear part lie on the bin edges t_eval + k w, up to a few
    # ulp of the clock's magnitude: such a RUL is bin k whatever the clock's unit or origin
    x = rul / bin_width - (1e-9 + 8.0 * torch.finfo(torch.float64).eps * t_scale / bin_width)
    fp = torch.where(
        torch.isfinite(rul) & (x <= bins),
        torch.ceil(x).clamp(min=1, max=bins).to(torch.int64),
        torch.full_like(rul, -1, dtype=torch.int64),
    )
    idx = torch.where(fp > 0, fp - 1, torch.full_like(fp, bins))
    mass = torch.zeros(bins + 1, dtype=torch.float64)
    mass.scatter_add_(0, idx, weights)
    pmf, cens = mass[:bins], mass[bins]
    support = torch.arange(1, bins + 1, dtype=torch.float64) * bin_width
    crossing = pmf.sum()
    expectation = (pmf * support).sum() / crossing if crossing > 0 else torch.tensor(math.nan)
    if cens > 0:
        expectation = torch.tensor(math.nan, dtype=torch.float64)
    return RULDistribution(fp, weights, pmf, cens, expectation, float(bin_width), 0.0)


def _rul_grid(origin: float, t_last: float, t_eval: float, horizon: float, bin_width: float,
              rel: float) -> Tensor:  # fmt: skip
    """Path grid from ``origin`` (the fit's last time) to ``t_last + horizon`` with steps of at
    most ``bin_width`` from the evaluation time ``t_eval`` on: when ``t_eval`` lies beyond the
    linear part of :func:`path_grid` (``bin_width / rel``), a second grid starts there."""
    if t_eval - origin <= bin_width / rel:
        return path_grid(origin, horizon + (t_last - origin), bin_width, rel=rel)
    return torch.cat([path_grid(origin, t_eval - origin, bin_width, rel=rel),
                      path_grid(t_eval, horizon - (t_eval - t_last), bin_width, rel=rel)])  # fmt: skip


# ----------------------------------------------------------------------------- steps
def _trend_models(
    tb: Tensor, yb: Tensor, phi: float, s0b: float, method: str, filt, seed: int,
    gen: torch.Generator, hidden: int, members: int,
) -> tuple[dict, dict[str, Tensor], list[tuple[float, int, float]]]:  # fmt: skip
    """The trend models of ``method`` filtered on the data since onset, each shape with its
    noise chosen by the backtest (maximum likelihood when no level has been crossed yet), the
    learner trend beside them, and their backtest scores ``{name: (P,)}`` and pairs."""
    shapes = (
        TREND_SHAPES if method == "auto" else ("exponential",) if method == "elm" else (method,)
    )
    fits = fit_trends(tb, yb, phi=phi, sigma0=s0b, shapes=shapes, filter=filt)
    pairs = crossing_pairs(tb, yb, s0b)
    per_pair: dict[str, Tensor] = {}
    if pairs:  # noise (and model) chosen by multi-step crossing-time skill on the own past
        for name, fit in fits.items():
            sc = backtest_scores(fit, pairs, tb, gen, n_paths=BACKTEST_PATHS, every_noise=True)
            g = int(torch.argmin(torch.nan_to_num(sc.mean(-1), nan=math.inf)))
            fits[name] = fits[name].select(g)
            per_pair[name] = sc[g]
    models: dict = {k: v for k, v in fits.items() if method in ("auto", k)}
    if method in ("auto", "elm") and "exponential" in fits:
        origins = sorted({i for _, i, _ in pairs})
        models["elm"] = fit_learner_trends(fits["exponential"], members=members, n_hidden=hidden,
                                           seed=seed, snapshots=tuple(origins))  # fmt: skip
        if pairs:
            per_pair["elm"] = backtest_scores(models["elm"], pairs, tb, gen, n_paths=BACKTEST_PATHS)
    return models, per_pair, pairs


def _pool(
    models: dict, per_pair: dict[str, Tensor], n_pairs: int, method: str
) -> tuple[tuple[str, ...], dict, list[str]]:
    """The models whose RUL distributions are pooled (:data:`AUTO_POOL` for ``"auto"``), the
    ``selection`` record, and a "model doubt" flag when another shape's backtest beats the
    exponential one by more than one standard error."""
    flags: list[str] = []
    scores = {k: float(v.mean()) for k, v in per_pair.items()}
    if not models:
        raise ValueError(
            f"the {method!r} model cannot be fitted: fewer than 3 values since onset exceed the "
            "healthy level by one baseline standard deviation"
        )
    pool = tuple(k for k in AUTO_POOL if k in models) if method == "auto" else ()
    if pool and per_pair:
        better = one_standard_error_choice(per_pair, "exponential")
        if better not in pool:
            flags.append(
                f"model doubt: the {better} shape predicted the series' own past crossings "
                "better than the exponential one by more than one standard error; "
                f"prognose(method={better!r}) gives its RUL"
            )
    if not pool:
        pool = (next(iter(models)),)
    chosen = "+".join(pool)
    selection = {
        "criterion": (
            "equal-weight pool of the exponential and learner trend models; noise of each "
            "shape by mean CRPS of the log time to already crossed levels (backtest)"
            if method == "auto"
            else "noise by mean CRPS of the log time to already crossed levels (backtest)"
        )
        if n_pairs
        else "noise by maximum likelihood (no level crossed since onset yet)",
        "pairs": n_pairs,
        "scores": scores,
        "chosen": chosen,
        "pool": pool,
    }
    return pool, selection, flags


# ----------------------------------------------------------------------------- public
def prognose(
    series,
    threshold: float,
    *,
    time=None,
    time_format: str | None = None,
    method: str = "auto",
    seed: int | Sequence[int] = 0,
    direction: str = "auto",
    at: float | str | None = None,
    baseline: float | Baseline = 0.3,
    glitch_limit: float | None = None,
    onset: str = "ksigma",
    n_paths: int = 2000,
    horizon_factor: float = 2.0,
    filter="ekf",
    max_points: int = 500,
    learner_hidden: int = 10,
    learner_members: int = 4,
) -> RULResult:
    """RUL distribution of a degradation series for a failure ``threshold`` (module docstring).

    Args:
        series: a :class:`~prognos_torch.workflow.Series` or values ``(T,)`` (NaN: missing): a
            tensor on any device (the computation and the result are on the CPU), a NumPy
            array, a pandas Series (by position; on a ``DatetimeIndex`` that index is the
            time) or a sequence.
        threshold: failure threshold in data units.
        time: ``(T,)`` strictly increasing times for array input (default: the position):
            numbers, or date-times (NumPy ``datetime64``, pandas; zone-aware ones in UTC; ISO
            8601 texts), which become days since the first, so that the RUL is in days.
        time_format: the layout of ``time`` given as text that is not ISO 8601, in
            ``datetime.strptime`` codes (e.g. ``"%d/%m/%Y %H:%M"``; a ``%z`` offset applied,
            other times taken as UTC), as :func:`~prognos_torch.workflow.load_series` reads it.
        method: ``"auto"`` (the exponential + elm pool), ``"exponential"``, ``"power"``,
            ``"linear"`` or ``"elm"`` (:data:`PROGNOSE_METHODS`).
        seed: seeds the path draws, the backtest's draws (which choose each shape's noise)
            and the ELMs' random features, so the answer moves with it beyond the Monte Carlo
            noise of the final paths: over the 250 protocol points of the three RUL studies
            (docs/RESULTS.md) the ``auto`` median moved by a median factor of 1.14 across 3
            seeds (1.20 with one ELM and 64 backtest paths), and at 7 points it was finite for
            some seeds and censored for others; pool a few seeds for a steadier answer.
            A sequence of distinct seeds pools them: the models each seed's call would fit
            (its noise choice and ELMs) enter the RUL distribution with equal weights, and
            the paths are drawn with the first seed's generator (``(s,)`` is ``s``; ``model``
            and ``selection["by_run"]`` name each seed's models).
        direction: ``"above"``, ``"below"`` or ``"auto"`` (the side of the baseline the
            threshold is on; a series that has left its healthy band only on the other side,
            by at least the threshold's distance from the healthy mean, is then refused as a
            threshold on the wrong side; a smaller excursion is flagged).
        at: evaluation time ``>=`` the last observation (default: the last observation): a
            number on the series' time axis, or for a series timed by date-times a date-time
            (ISO 8601 text, ``datetime64``, pandas ``Timestamp``, ``datetime``).
        baseline: the healthy window as a fraction of the time span, or a
            :class:`~prognos_torch.prognosis.onset.Baseline` (data units). Onset is searched
            after the window's end (``Baseline.t_end``).
        glitch_limit: leave the healthy window's isolated outliers, values more than this
            many noise std from their neighbours (sensor glitches), out of its statistics
            (``healthy_baseline(..., glitch_limit=)``); ``None`` (default): every value counts,
            and a flag says when values beyond :data:`GLITCH_SCREEN` widen the healthy band by
            :data:`GLITCH_WIDENING` or more (one glitch can delay the onset by the whole
            degradation). Not a default: on the synthetic selection set leaving them out did
            not improve the RUL (docs/RESULTS.md).
        onset: ``"ksigma"`` (default) or ``"cusum"``.
        n_paths: sample paths of the RUL distribution.
        horizon_factor: the horizon is this multiple of the observed life (and at least 10
            times the time since onset).
        filter: engine configuration filtering the trend models: a filter name or a
            :class:`~prognos_torch.filters.GaussianFilter`; default ``"ekf"``, the exact Kalman
            filter on these linear-Gaussian models (calibrated when the data follow the model);
            ``"stekf"`` or :func:`~prognos_torch.prognosis.trends.strong_tracking_filter` add
            strong tracking (paper 000), which widens the posterior after jumps. Several
            filters, joined by ``+`` (``"ekf+stekf"``) or as a tuple, pool the models of
            ``method`` fitted under each with equal weights (each filter's models, noise choice
            included, are those of a call with that filter alone; ``model`` names them,
            ``selection["by_filter"]`` holds each filter's selection): a wider, more
            conservative interval (docs/RESULTS.md, ``pronostia-rul``: on bearings that surge
            ``"ekf+stekf"`` covered 0.79 of the truths where the default covered 0.67, counted
            on float64 bounds, at a worse median error and log-time CRPS on the IMS bearings).
        max_points: values since onset above which block means are used.
        learner_hidden: hidden nodes of each ELM of the learner trend
            (:func:`~prognos_torch.prognosis.learner_trend.fit_learner_trend`).
        learner_members: ELMs in the learner trend's ensemble
            (:func:`~prognos_torch.prognosis.learner_trend.fit_learner_trends`), each with its
            own random features and Kalman optimiser, pooled with equal weights (1: one ELM).

    Returns:
        :class:`~prognos_torch.workflow.RULResult` with ``status``, ``onset``, ``model``,
        ``flags``, ``selection`` and ``rul_samples``; ``summary()`` gives median, q05, q95,
        censored mass and bound.

    Raises:
        ValueError: bad input (too few values, a threshold inside the healthy band or on the
            wrong side of it, a threshold already reached, unknown options).
    """
    x, t, src = _as_series(series, time, time_format)
    thr = check_real(threshold, "threshold")
    s = _settings(method, direction, seed, n_paths, max_points, learner_hidden,
                  learner_members, horizon_factor, filter)  # fmt: skip
    seeds, n_paths, max_points, learner_hidden, learner_members, horizon_factor, filters = s
    keep = ~torch.isnan(x)
    x, t = x[keep], t[keep]
    if x.shape[0] < MIN_POINTS:
        raise ValueError(
            f"series has {x.shape[0]} observed values; prognose needs at least {MIN_POINTS} "
            "(a healthy baseline and a trend)"
        )
    t_last = float(t[-1])
    t_eval = t_last if at is None else time_value(at, src.start if src else None, "at")
    if t_eval < t_last:
        raise ValueError(
            f"at = {fmt_time(t_eval)} is before the last observation {fmt_time(t_last)}"
        )
    if isinstance(baseline, Baseline):
        if glitch_limit is not None:
            raise ValueError(
                "glitch_limit applies to the healthy window prognose computes; a given "
                "baseline=Baseline(...) is used as it is"
            )
        base = baseline
    else:
        base = healthy_baseline(x, t, fraction=baseline, glitch_limit=glitch_limit)
    auto_side = direction == "auto"
    direction = threshold_side(thr, direction, base)
    sign = 1.0 if direction == "above" else -1.0
    yo, thr_o = sign * x, sign * thr  # oriented: degradation raises yo
    medians = moving_median(yo, 5)
    now = float(medians[-1])
    if now >= thr_o:
        raise ValueError(
            f"threshold {fmt_level(thr, base.std)} already reached: the median of the last 5 "
            f"values is {fmt_level(sign * now, base.std)} (direction {direction!r}); the RUL is 0"
        )
    flags = baseline_flags(base)
    if not isinstance(baseline, Baseline) and glitch_limit is None:
        flags += glitch_flags(base, healthy_baseline(x, t, fraction=baseline,
                                                      glitch_limit=GLITCH_SCREEN))  # fmt: skip
    flags += _touched_threshold(t, yo, medians, thr_o)
    ons = detect_onset(x, t, method=onset, baseline=base, direction=direction, after=base.t_end)
    if auto_side and not ons.detected:
        flags += away_from_threshold(x, t, medians, thr, direction, base, onset)
    gen = torch.Generator().manual_seed(seeds[0])
    span_life = t_last - float(t[0])
    dt_data = float(torch.diff(t).median())
    phi = sign * base.mean
    common = dict(
        threshold=thr, direction=direction, time_unit=_unit(src), history=_history(x, t, src)
    )

    reported = _on_input(ons, keep)
    if not ons.detected:
        flags += onset_pending(medians, sign * base.mean + BAND_K * base.std, sign, base.std)
        return _no_degradation(t, yo, thr_o, sign, base, reported, gen, t_eval, span_life,
                               dt_data, filters[0], flags, common, horizon_factor,
                               n_paths)  # fmt: skip

    i0 = ons.index
    t_on, y_on = t[i0:], yo[i0:]
    noise0 = base.noise if base.noise is not None else base.std
    tb, yb, s0b, block = _blocks(t_on, y_on, noise0, max_points)
    runs = _fit_runs(tb, yb, phi, s0b, method, filters, seeds, gen, learner_hidden,
                     learner_members)  # fmt: skip
    for _, _, _, doubt in runs:
        flags += [f for f in doubt if f not in flags]
    models, pool, selection, _ = runs[0]
    fit = _level_fit(models, pool)
    pooled = tuple(m[k] for m, pl, _, _ in runs for k in pl)
    filter_names = [_filter_label(m, pl) for m, pl, _, _ in runs]
    chosen, selection = _pooled_selection(runs, filter_names, filters, seeds)
    horizon = max(horizon_factor * span_life, 10.0 * (t_last - float(t[i0])), 10 * dt_data)
    horizon += t_eval - t_last
    bin_width = max(dt_data, horizon / _MAX_BINS)
    grid = _rul_grid(float(tb[-1]), t_last, t_eval, horizon, bin_width, 0.02)
    passage = TrendPool(pooled).first_passage(-1, thr_o, grid, n_paths, gen, keep=100)
    dist, alive, bins = _rul_at(passage.times, t_eval, t_last, horizon, bin_width, grid)
    p_alive = float(alive.to(torch.float64).mean())
    if p_alive < 1.0:
        flags.append(
            f"{int((~alive).sum())} of {alive.numel()} paths ({100 * (1 - p_alive):.2g} %) "
            "crossed before the evaluation time "
            f"{fmt_time(t_eval)}; the RUL is conditioned on the asset still running then"
        )
    if p_alive == 0.0:
        raise ValueError(
            f"every predicted path crossed the threshold before at = {fmt_time(t_eval)}: the model says "
            "the asset has already failed; evaluate at the last observation instead"
        )
    censored = float(dist.censored_mass)
    flags += fit_flags(fit, thr_o, passage, int(t_on.shape[0]), censored)
    flags += beyond_the_data(y_on, phi, noise0, thr_o, method, flags)
    if block > 1:
        flags.append(f"{t_on.shape[0]} values since onset were averaged in blocks of {block}")
    paths = _uniform_paths(passage.paths, grid, t_eval, bin_width, bins, sign)
    return RULResult(
        distribution=dist,
        horizon=bins,
        dt=bin_width,
        t_last=t_eval,
        paths=paths,
        weights=torch.full((paths.shape[0],), 1.0 / paths.shape[0], dtype=torch.float64),
        filter=getattr(fit, "filter", "ekf (Kalman optimiser)")
        if len(runs) == 1
        else "+".join(dict.fromkeys(filter_names)),
        n_particles=n_paths,
        status="ok",
        onset=reported,
        model=chosen,
        flags=tuple(flags),
        selection=selection,
        rul_samples=torch.where(alive, passage.times - t_eval, math.nan),
        **common,
    )


# ----------------------------------------------------------------------------- helpers
def _touched_threshold(t: Tensor, yo: Tensor, medians: Tensor, thr_o: float) -> list[str]:
    """Flags of a threshold touched but not held: 5-value medians that reached it and fell
    back, and a last value beyond it while the newest median is not (``yo``, ``medians``
    ``(T,)``: the series and its medians oriented to the direction of degradation)."""
    out = []
    over = torch.nonzero(medians >= thr_o).flatten()
    if over.numel():  # (the newest median is below it: checked before)
        out.append(
            f"the median of 5 values already reached the threshold at {fmt_time(float(t[over[0]]))} "
            f"and fell back ({over.numel()} such medians): the asset may already count as "
            "failed; the RUL is that of a new crossing"
        )
    if float(yo[-1]) >= thr_o:
        out.append(
            "the last value is beyond the threshold while the median of the last 5 is not "
            "(a spike or the start of failure)"
        )
    return out


def _fit_runs(
    tb: Tensor, yb: Tensor, phi: float, s0b: float, method: str, filters: tuple, seeds: tuple,
    gen: torch.Generator, hidden: int, members: int,
) -> list[tuple]:  # fmt: skip
    """Steps 3-4 once per filter and seed (filters outer): each run's ``(models, pool,
    selection, doubt flags)``. Each run's noise choice draws from its own stream seeded with
    its seed, so its models are those of ``prognose(filter=that filter, seed=that seed)``; the
    first run draws from ``gen``, whose stream the final paths continue."""
    runs = []
    for j, (filt, s) in enumerate((filt, s) for filt in filters for s in seeds):
        g = gen if j == 0 else torch.Generator().manual_seed(s)
        models, per_pair, pairs = _trend_models(
            tb, yb, phi, s0b, method, filt, s, g, hidden, members
        )
        runs.append((models, *_pool(models, per_pair, len(pairs), method)))
    return runs


def _pooled_selection(
    runs: list[tuple], filter_names: list[str], filters: tuple, seeds: tuple
) -> tuple[str, dict]:
    """The model name and the ``selection`` record of the result: the first run's, or with
    several runs (filters x seeds, pooled with equal weights) every run's pool named by its
    filter (and seed), with each run's selection under ``by_filter`` (``by_run`` with seeds)."""
    selection = runs[0][2]
    if len(runs) == 1:
        return selection["chosen"], selection
    plan = [(filt, s) for filt in filters for s in seeds]
    names = [n + (f", seed {s}" if len(seeds) > 1 else "") for n, (_, s) in zip(filter_names, plan)]
    chosen = " + ".join(f"{sel['chosen']} ({n})" for (_, _, sel, _), n in zip(runs, names))
    key = "by_filter" if len(seeds) == 1 else "by_run"
    by = {n: sel for (_, _, sel, _), n in zip(runs, names)}
    return chosen, dict(selection, chosen=chosen, **{key: by})


def _unit(src: Series | None) -> str:
    return src.time_unit if src is not None else "steps"


def _history(x: Tensor, t: Tensor, src: Series | None) -> Series:
    if src is not None:
        return Series(x, t, src.name, src.time_name, src.time_unit, src.start, src.source)
    return Series(x, t)


def _uniform_paths(paths, grid, t_eval, bin_width, bins, sign) -> Tensor:
    """Kept paths ``(K, bins)`` interpolated onto the RUL bins ``t_eval + bin_width (1..bins)``
    (data units; ``bins`` is at most about ``_MAX_BINS``; past the grid's end a path holds its
    last value)."""
    import numpy as np

    if paths is None or paths.shape[0] == 0:
        return torch.zeros(1, bins, dtype=torch.float64)
    tq = t_eval + bin_width * np.arange(1, bins + 1)
    g = grid.numpy()
    out = np.stack([np.interp(tq, g, p) for p in paths.numpy()])
    return sign * torch.as_tensor(out, dtype=torch.float64)


def _on_input(ons: Onset, keep: Tensor) -> Onset:
    """The onset with its indices into the series as given and its statistic ``(T,)`` with
    NaN at the missing values (the detector saw the observed values only)."""
    if bool(keep.all()):
        return ons
    pos = torch.nonzero(keep).flatten()
    stat = torch.full(keep.shape, math.nan, dtype=ons.statistic.dtype)
    stat[pos] = ons.statistic
    return replace(
        ons,
        index=None if ons.index is None else int(pos[ons.index]),
        alarm_index=None if ons.alarm_index is None else int(pos[ons.alarm_index]),
        statistic=stat,
    )


def _rul_at(
    times: Tensor, t_eval: float, t_last: float, horizon: float, bin_width: float, grid: Tensor
) -> tuple[RULDistribution, Tensor, int]:
    """The RUL distribution at ``t_eval`` of first-passage ``times`` on ``grid``, among the
    paths still running then, in ``bins`` bins of ``bin_width`` up to ``t_last + horizon``;
    also the paths' ``alive`` mask and ``bins``."""
    alive = times > t_eval
    w = alive.to(torch.float64) / alive.sum().clamp(min=1)
    bins = max(1, math.ceil((horizon - (t_eval - t_last)) / bin_width))
    t_scale = max(abs(t_eval), abs(float(grid[-1])))
    rul = torch.where(alive, times - t_eval, torch.full_like(times, math.inf))
    return _distribution(rul, w, bin_width, bins, t_scale), alive, bins


def _no_degradation(
    t, yo, thr_o, sign, base, ons, gen, t_eval, span_life, dt_data, filt, flags, common,
    horizon_factor, n_paths,
):  # fmt: skip
    """Before onset: a lower bound from a linear trend on the healthy data (module doc), up to
    the horizon ``horizon_factor x`` the observed life, from ``n_paths`` paths."""
    n = t.shape[0]
    first = max(0, n - 1000)
    noise0 = base.noise if base.noise is not None else base.std
    fits = fit_trends(t[first:], yo[first:], phi=sign * base.mean, sigma0=noise0,
                      shapes=("linear",), filter=filt)  # fmt: skip
    fit = fits["linear"]
    horizon = max(horizon_factor * span_life, 10 * dt_data) + (t_eval - float(t[-1]))
    bin_width = max(dt_data, horizon / _MAX_BINS)
    grid = _rul_grid(float(t[-1]), float(t[-1]), t_eval, horizon, bin_width, 0.01)
    passage = fit.first_passage(-1, thr_o, grid, n_paths, gen)
    dist, _, bins = _rul_at(passage.times, t_eval, float(t[-1]), horizon, bin_width, grid)
    q05 = float(dist.quantile(0.05))
    bound = bins * bin_width if math.isnan(q05) else q05
    return RULResult(
        distribution=dist,
        horizon=bins,
        dt=bin_width,
        t_last=t_eval,
        paths=torch.zeros(1, bins, dtype=torch.float64),
        weights=torch.ones(1, dtype=torch.float64),
        filter=fit.filter,
        n_particles=n_paths,
        status="no degradation detected yet",
        onset=ons,
        model=None,
        flags=(
            "no degradation detected yet: the RUL is not estimated; the bound is the 5 % "
            "quantile of the first passage under a linear trend of the healthy data, a bound "
            "only while the asset stays healthy (a degradation that starts later can end "
            "sooner)",
            *flags,
        ),
        lower_bound=bound,
        **common,
    )
