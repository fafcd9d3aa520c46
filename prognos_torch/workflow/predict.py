"""Forecasts with an uncertainty band and RUL distributions from a fitted one-step learner.

The learner becomes the m-order state-space model of paper 002 (Eq. 15-19,
:func:`~prognos_torch.prognosis.learner_model.learner_transition_model`) on the scaled series::

    P_{s+1} = [x_{s-m+2}, ..., x_s, f(P_s)] + w_s,    y_s = x_s + v_s

Noise: the one-step training residual RMSE ``sigma`` (scaled units) is split equally between
process and measurement noise, ``q = r = sigma / sqrt(2)``, so that the one-step predictive
variance matches the training residuals. ``w_s`` acts on the newest element only (Eq. 19) for
the Gaussian filters and the bootstrap particle filter; the Gaussian-proposal particle filters
(EKPF, STPF) need a transition *density*, so their shifted elements get a small extra noise
``0.3 q`` (with ``0.01 q`` the STPF's effective sample size collapsed to about 1 of 500 on the
test series; ``0.3 q`` keeps it near 90).

Both :func:`forecast` and :func:`rul` first run a filter over the last ``filter_steps``
observations (the belief starts at the observed window with std ``r`` per element), then predict
``horizon`` steps from the filtered belief:

* Gaussian filters (``sckf``, :func:`forecast`'s default; ``stsckf``, ``ukf``, ``ekf``, ...):
  the band is the engine's predict-only propagation
  (:func:`~prognos_torch.prognosis.paths.gaussian_paths`), ``mean -+ z std`` of the next
  *measurements*; for the RUL, particles are drawn from the filtered Gaussian;
* particle filters (``pf`` = bootstrap SIR, ``ekpf``, ``stpf`` = paper 002's strong-tracking PF
  and :func:`rul`'s default, ``upf``): weighted sample paths
  (:func:`~prognos_torch.prognosis.paths.particle_paths`), band from weighted quantiles.

RUL (paper 002, Eq. 28 and Fig. 11): the first passage of each sample path of the *state*
``x`` (no measurement noise) through the threshold, weighted;
:func:`~prognos_torch.prognosis.rul.rul_distribution` keeps paths that do not cross within the
horizon apart as censored mass (their RUL only exceeds ``horizon * dt``).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .._text import json_number
from ..core.belief import GaussianBelief
from ..core.validation import check_count, check_levels, check_real, check_seed, is_real
from ..filters import make_filter, make_particle_filter
from ..filters import run as run_filter
from ..learners import LSSVR
from ..metrics import mae, rmse
from ..prognosis.learner_model import learner_transition_model
from ..prognosis.paths import gaussian_paths, particle_paths
from ..prognosis.rul import RULDistribution, rul_distribution
from . import extrapolation as _extra
from .data import Series
from .fitted import FittedModel
from .memory import check_forecast_memory, check_paths_memory

__all__ = [
    "ForecastResult",
    "RULResult",
    "forecast",
    "rul",
    "holdout_metrics",
    "ThresholdWarning",
    "FILTER_NAMES",
    "GAUSSIAN_FILTERS",
    "PARTICLE_NAMES",
    "JITTER",
    "HOLDOUT_FORECAST_STEPS",
]

#: Gaussian filters accepted by :func:`forecast` and :func:`rul` (engine configurations).
GAUSSIAN_FILTERS = ("sckf", "stsckf", "ckf", "ukf", "srukf", "stukf", "ekf", "stekf")
#: Particle filters accepted (``pf`` is the bootstrap SIR filter).
PARTICLE_NAMES = ("pf", "sir", "ekpf", "upf", "stpf")
FILTER_NAMES = GAUSSIAN_FILTERS + PARTICLE_NAMES
#: Relative noise on the shifted window elements for Gaussian-proposal particle filters.
JITTER = 0.3
_GAUSSIAN_PROPOSAL = ("ekpf", "upf", "stpf")
#: Fewest particles or sample paths of a forecast band or RUL distribution (one path is a
#: band of zero width; prognose asks as many).
MIN_PARTICLES = 10
#: Longest multi-step forecast scored by :func:`holdout_metrics` (the first steps of a longer
#: held-out tail; its one-step RMSE uses the whole tail).
HOLDOUT_FORECAST_STEPS = 1000


@dataclass(frozen=True)
class ForecastResult:
    """A ``horizon``-step forecast in data units.

    Attributes:
        time: ``(H,)`` forecast times ``t_last + dt * (1..H)``.
        mean: ``(H,)`` predicted mean; lower, upper: ``(H,)`` central ``level`` band.
        std: ``(H,)`` predictive std (Gaussian filters) or the weighted std of the paths.
        level: band probability.
        filter: filter name.
        history: the series the forecast starts from.
        samples: ``(N, H)`` sample paths (particle filters), else ``None``.
        weights: ``(N,)`` their weights, else ``None``.
        extrapolation: ``(H,)`` how far each step's inputs lie outside the training range
            (data units; the band and std include it, see
            :mod:`~prognos_torch.workflow.extrapolation`), or ``None``.
    """

    time: Tensor
    mean: Tensor
    lower: Tensor
    upper: Tensor
    std: Tensor
    level: float
    filter: str
    history: Series
    samples: Tensor | None = None
    weights: Tensor | None = None
    extrapolation: Tensor | None = None

    @property
    def horizon(self) -> int:
        return int(self.mean.shape[0])

    def observed(self, truth: Series) -> tuple[Tensor, Tensor]:
        """The values of ``truth`` that the steps are compared with: its first ``n <= H`` rows
        after the forecast origin, row ``k`` with step ``k``, as the learner forecasts row by
        row (its windows are rows, whatever their spacing).

        Args:
            truth: a series that goes on after the origin (the full series of a backtest).
        Returns:
            ``(values, times)``, each ``(n,)``. After a recording gap ``times`` lies later
            than the steps' :attr:`time` ``[:n]``; :meth:`row_offset` measures by how much.
        """
        after = truth.t > self.history.t[-1]
        return truth.values[after][: self.horizon], truth.t[after][: self.horizon]

    def row_offset(self, truth: Series) -> float:
        """Largest ``|t_row_k - time_k|`` over the rows :meth:`observed` pairs with the steps
        (0 when the rows keep the series' median step :attr:`Series.dt`; NaN without any)."""
        times = self.observed(truth)[1]
        if not times.numel():
            return math.nan
        return float((times - self.time[: times.numel()]).abs().max())


@dataclass(frozen=True)
class RULResult:
    """RUL distribution at the end of a series.

    Attributes:
        distribution: :class:`~prognos_torch.prognosis.rul.RULDistribution` in time units
            (``dt`` = the series' step).
        threshold: failure threshold (data units); direction: ``"above"`` or ``"below"``.
        horizon: predicted steps; dt: time per step; time_unit: unit of RUL values.
        t_last: time of the last observation.
        paths: ``(N, H)`` predicted state paths (data units; a ``prognose`` path of a log
            shape that runs far past the threshold can overflow to ``inf``: only its crossing
            time counts, and the figures draw it clipped near the data); weights: ``(N,)``.
        filter: filter name; n_particles: ``N``.
        history: the series.
        status: ``"ok"``, or ``"no degradation detected yet"`` (:func:`~.prognose.prognose`
            before onset: the median and quantiles are withheld and only ``lower_bound`` holds).
        onset: the :class:`~prognos_torch.prognosis.onset.Onset` found (``prognose``).
        model: the trend model used (``prognose``), e.g. ``"exponential"``, or the pooled
            models joined by ``+`` (``"exponential+elm"``, ``method="auto"``).
        flags: warnings on the forecast (extrapolation far beyond the data, diverging paths,
            censored mass, ...), one sentence each.
        lower_bound: a lower bound on the RUL where no distribution is reported.
        selection: how the noise was chosen, the backtest scores of the candidate models and
            the models pooled (``prognose``).
        rul_samples: ``(N,)`` RUL of each path (``inf``: censored), or ``None``.
    """

    distribution: RULDistribution
    threshold: float
    direction: str
    horizon: int
    dt: float
    time_unit: str
    t_last: float
    paths: Tensor
    weights: Tensor
    filter: str
    n_particles: int
    history: Series
    status: str = "ok"
    onset: object | None = None
    model: str | None = None
    flags: tuple[str, ...] = ()
    lower_bound: float | None = None
    selection: dict | None = None
    rul_samples: Tensor | None = None

    @property
    def crossing_probability(self) -> float:
        """Probability that the threshold is reached within the horizon (the pmf's total)."""
        return min(1.0, max(0.0, float(self.distribution.pmf.sum())))

    @property
    def censored_mass(self) -> float:
        """Probability that the threshold is not reached within the horizon."""
        return min(1.0, max(0.0, float(self.distribution.censored_mass)))

    @property
    def fully_censored(self) -> bool:
        """No path reaches the threshold within the horizon: only ``RUL > horizon * dt`` is known."""
        return not bool((self.distribution.pmf > 0).any())

    @property
    def bound(self) -> float:
        """``horizon * dt``: the censored mass has RUL beyond this."""
        return self.horizon * self.dt

    def _alive_ruls(self) -> Tensor | None:
        """The per-path RULs of the paths still running at ``t_last`` (``rul_samples`` without
        its NaN, the paths that crossed before; ``inf``: censored), or ``None``."""
        if self.rul_samples is None:
            return None
        return self.rul_samples[~torch.isnan(self.rul_samples)]

    def failure_probability(self, within: float) -> float | None:
        """``P(RUL <= within)``: the probability that the threshold is reached within
        ``within`` time units (``time_unit``) of ``t_last``, the question a maintenance
        planner asks of the next inspection window.

        From the per-path RULs where the result carries them (``rul_samples`` of
        :func:`~prognos_torch.workflow.prognose`: each path's own crossing time, among the
        paths still running at ``t_last``), otherwise from the distribution's pmf (its RULs lie on the
        grid ``dt * k``, exact for the step-wise paths of :func:`rul`), the same RULs that
        :meth:`quantile` reads, so ``failure_probability(quantile(q)) >= q`` holds (the
        median, q05 and q95 of :meth:`summary` included). Censored paths count as not failed;
        within ``bound`` that is exact.

        Returns:
            a probability in [0, 1]; ``None`` when no distribution is estimated
            (``status`` other than ``"ok"``, e.g. before onset: only ``bound`` is known).

        Raises:
            ValueError: ``within`` is not a finite number >= 0, or lies beyond ``bound`` while
                mass is censored (there only ``P >= crossing_probability`` is known).
        """
        h = check_real(within, "within")
        if h < 0:
            raise ValueError(f"within must be >= 0 (a time span in {self.time_unit}), got {h:g}")
        if self.status != "ok":
            return None
        if h > self.bound and self.censored_mass > 0:
            raise ValueError(
                f"within = {h:g} {self.time_unit} lies beyond the horizon bound "
                f"{self.bound:g} {self.time_unit} while {100 * self.censored_mass:.3g} % of the "
                f"paths are censored: only P >= {self.crossing_probability:.4g} is known there"
            )
        x = self._alive_ruls()
        if x is not None:
            return float((x <= h).to(torch.float64).mean()) if x.numel() else None
        d = self.distribution
        k = min(d.horizon, math.floor(h / d.dt + 1e-9))  # support points dt * (1..k) <= within
        return 0.0 if k == 0 else min(1.0, max(0.0, float(d.cdf[k - 1])))

    def quantile(self, q: float | Sequence[float]) -> Tensor:
        """Lower quantiles of the RUL, ``Q(q) = min{l : P(RUL <= l) >= q}``, ``q`` in (0, 1].

        From the per-path RULs where the result carries them (``rul_samples`` of
        :func:`~prognos_torch.workflow.prognose`: the crossing times of the equally weighted
        paths still running at ``t_last``, each the first time of its path's grid at or past
        the threshold, so up to one grid step late (the sampling step, then 1-2 % of the
        elapsed horizon); ``Q(q)`` the ``ceil(q N)``-th smallest of the ``N``), otherwise :meth:`RULDistribution.quantile
        <prognos_torch.prognosis.rul.RULDistribution.quantile>` (the upper edges ``dt * k`` of
        the bins, exact for the step-wise paths of :func:`rul`; for crossing times in
        continuous time they would read up to one ``dt`` late, which matters most when the RUL
        is a few steps). Censored mass is the upper tail: a quantile beyond ``bound`` is NaN.

        Args:
            q: a probability or a sequence of them.

        Returns:
            ``()`` for a scalar ``q``, else ``(Q,)`` (time units; NaN: beyond ``bound``, or no
            distribution estimated, ``status`` other than ``"ok"``).
        """
        qs = check_levels(q)
        if self.status != "ok":
            return torch.full(qs.shape, math.nan, dtype=torch.float64)
        x = self._alive_ruls()
        if x is None:
            return self.distribution.quantile(qs).to("cpu", torch.float64)
        x = x.to("cpu", torch.float64)
        if x.numel() == 0:
            return torch.full(qs.shape, math.nan, dtype=torch.float64)
        x = torch.where(x <= self.bound, x, math.inf).sort().values  # beyond bound: censored
        n = x.numel()
        # the ceil(q N)-th smallest; the 1e-12 keeps q N = k exact under rounding
        k = torch.ceil(qs * n - 1e-12).clamp(1, n).to(torch.int64) - 1
        v = x[k]
        return torch.where(torch.isfinite(v), v, math.nan)

    def failure_date(self, q: float = 0.5) -> str | None:
        """The date-time (ISO 8601, UTC, to the second) by which the threshold is reached with
        probability ``q``: ``t_last`` plus the RUL quantile :meth:`quantile` ``(q)``, where the
        series' time column holds date-times (``history.start``). ``None`` for numeric time,
        before onset (``status`` other than ``"ok"``) or for a quantile beyond ``bound``
        (censored paths: the date lies after ``history.date(t_last + bound)``)."""
        rul = float(self.quantile(q))
        return None if math.isnan(rul) else self.history.date(self.t_last + rul)

    def summary(self) -> dict:
        """Mean (Eq. 28, only when nothing is censored), median and the 5/95 % quantiles
        (:meth:`quantile`; from the exact per-path RULs where the result carries them; a
        value beyond the horizon is ``None``), ``censored_mass``, ``bound`` (the RUL exceeds it
        for the censored mass; before onset, the lower bound), ``status``, ``model``,
        ``onset_time`` and ``flags``. Before onset the median and quantiles are ``None``."""
        d = self.distribution

        def val(x) -> float | None:
            x = float(x)
            return None if math.isnan(x) else x

        q = self.quantile([0.05, 0.5, 0.95])
        mean = d.expectation
        x = self._alive_ruls()
        if x is not None:  # each path's crossing time, as for the quantiles
            whole = x.numel() > 0 and bool((x <= self.bound).all())
            mean = x.mean() if whole else math.nan
        out = {
            "mean": val(mean),
            "median": val(q[1]),
            "q05": val(q[0]),
            "q95": val(q[2]),
        }
        if self.status != "ok":
            out = dict.fromkeys(out)
        onset_time = getattr(self.onset, "time", None) if self.onset is not None else None
        out.update(
            censored_mass=self.censored_mass,
            bound=self.lower_bound if self.lower_bound is not None else self.bound,
            status=self.status,
            model=self.model,
            onset_time=onset_time,
            flags=list(self.flags),
        )
        return out

    def to_dict(self) -> dict:
        """A JSON-safe record of the result, for a planner's system or a log
        (``json.dumps(r.to_dict(), allow_nan=False)`` holds; a non-finite number is ``None``).

        Keys: ``status``, ``t`` (``t_last``) and its ``date``, ``time_zone`` of every date
        (``"UTC"``: a time column's offsets are applied when it is read; ``None`` for numeric
        time), ``time_unit``, ``threshold``, ``direction``, ``model``, ``filter`` (lower case,
        as ``filter=`` names it); ``rul``, :meth:`summary`'s ``mean``, ``median``,
        ``q05``, ``q95``, ``censored_mass`` and ``bound`` (a quantile beyond the horizon,
        withheld before onset, is ``None``; ``censored_mass`` of them lies beyond ``bound``);
        ``failure_date``, :meth:`failure_date` at 0.05, 0.5 and 0.95 and ``bound``, the date of
        ``t + bound`` (``None`` for numeric time); ``onset``, the
        :class:`~prognos_torch.prognosis.onset.Onset` found (``detected``, ``time``, ``date``,
        ``alarm_time``, ``method``, ``limit``, ``baseline`` mean, std, noise, n and ``t_end``;
        ``None`` for a result without one, as :func:`rul`'s); ``flags``.
        """
        s = self.summary()
        bound = s["bound"]
        num = json_number

        def date(t) -> str | None:
            return None if t is None else self.history.date(t)

        def after(rul) -> str | None:  # failure_date(q) from the summary's quantile
            return None if rul is None else date(self.t_last + rul)

        out = {
            "status": self.status,
            "t": num(self.t_last),
            "date": date(self.t_last),
            "time_zone": None if self.history.start is None else "UTC",
            "time_unit": self.time_unit,
            "threshold": num(self.threshold),
            "direction": self.direction,
            "model": self.model,
            "filter": self.filter.lower(),  # (as --filter and filter= name it)
            "rul": {k: num(s[k]) for k in ("mean", "median", "q05", "q95", "censored_mass")}
            | {"bound": num(bound)},
            "failure_date": {k: after(s[k]) for k in ("q05", "median", "q95")}
            | {"bound": after(num(bound))},
            "onset": None,
            "flags": list(self.flags),
        }
        on = self.onset
        if on is not None:
            b = on.baseline
            out["onset"] = {
                "detected": bool(on.detected),
                "time": num(on.time),
                "date": date(on.time),
                "alarm_time": num(on.alarm_time),
                "method": on.method,
                "limit": num(on.limit),
                "baseline": {
                    "mean": num(b.mean),
                    "std": num(b.std),
                    "noise": num(b.noise),
                    "n": int(b.n),
                    "t_end": num(b.t_end),
                },
            }
        return out


# ----------------------------------------------------------------------------- internals
def _check_filter(name) -> str:
    if not isinstance(name, str) or name.lower() not in FILTER_NAMES:
        raise ValueError(f"unknown filter {name!r}; choose one of {', '.join(FILTER_NAMES)}")
    return name.lower()


def _check_model(model) -> FittedModel:
    if isinstance(model, FittedModel):
        return model
    hint = ""
    if isinstance(model, (str, os.PathLike)):
        hint = f"; load the file first: load_model({str(model)!r})"
    raise TypeError(
        f"model must be a FittedModel (from fit_series or load_model), got "
        f"{type(model).__name__}{hint}"
    )


def _noise(model: FittedModel) -> tuple[float, float]:
    sigma = float(model.config["residual_rmse"])
    sigma = max(sigma, 1e-6)  # a perfect fit would leave no band and degenerate filters
    q = sigma / math.sqrt(2.0)
    return q, q


def _transition(model: FittedModel, name: str):
    m = model.m
    q, r = _noise(model)
    # Eq. 19 puts the noise on the newest element only; Gaussian-proposal particle filters
    # weight by the transition density and need a little on the shifted ones too
    shift = JITTER * q if name in _GAUSSIAN_PROPOSAL else 0.0
    # LS-SVR: its own input_gradient, the closed form of Eq. 25 for the fixed-size LS-SVR
    # (O(M) per particle) and autograd in row chunks for the exact one (the same numbers as
    # the "autograd" route, without a particles x N x m tensor beyond the block budget)
    jac = "input_gradient" if isinstance(model.learner, LSSVR) else "autograd"
    return learner_transition_model(model.learner, m, q, r, shift_std=shift, jacobian=jac), r


def _scaled(model: FittedModel, series: Series) -> Tensor:
    if not isinstance(series, Series):
        raise TypeError(f"series must be a Series (load_series(...)), got {type(series).__name__}")
    m = model.m
    if len(series) < m + 1:
        raise ValueError(
            f"series {series.name!r} has {len(series)} values; the model's embedding m={m} "
            f"needs at least m + 1 = {m + 1}"
        )
    if bool(torch.isinf(series.values).any()):
        raise ValueError(f"series {series.name!r} values must be finite numbers or NaN (missing)")
    t = series.t
    if not bool(torch.isfinite(t).all()) or not bool((t[1:] > t[:-1]).all()):
        raise ValueError(f"series {series.name!r} time must be finite and strictly increasing")
    dev = next(iter(model.learner.parameters())).device
    return model.scaler.transform(series.values.to(dev))


def _start(z: Tensor, m: int, filter_steps: int, what: str) -> int:
    """First row of the window the filter starts from: the window of ``m`` values that leaves
    ``filter_steps`` values to filter, or, where a value in it is missing (NaN), the last
    complete window before it (the missing values after it are the filter's gaps); without
    one before it (a series whose first value is missing, filtered whole), the first complete
    window after it."""
    s0 = z.shape[0] - min(filter_steps, z.shape[0] - m) - m
    complete = (~torch.isnan(z).unfold(0, m, 1).any(-1)).nonzero()[:, 0]
    if not complete.numel():  # (more filter_steps cannot help: they move the start earlier)
        raise ValueError(
            f"series {what!r} has no {m} consecutive observed values (NaN is missing): the "
            f"filter starts from one complete window of the model's embedding m = {m}; fill "
            "the missing values"
        )
    before = complete[complete <= s0]
    return int(before[-1] if before.numel() else complete[0])


def _filtered(
    model: FittedModel, z: Tensor, name: str, filter_steps: int, n_particles, seed, what: str
):
    """Run the filter over the last ``filter_steps`` values (more where the window it starts
    from has a missing value, :func:`_start`); return ``(kind, result, ssm)``."""
    m = model.m
    ssm, r = _transition(model, name)
    s0 = _start(z, m, filter_steps, what)
    steps = z.shape[0] - m - s0
    eye = torch.eye(m, dtype=z.dtype, device=z.device)
    belief = GaussianBelief(z[s0 : s0 + m].clone(), r * eye)
    ys = z[s0 + m :, None]
    if name in GAUSSIAN_FILTERS:
        filt = make_filter(name)
        if steps > 0:
            return "gaussian", (filt, run_filter(filt, ssm, belief, ys).final), ssm
        return "gaussian", (filt, belief), ssm
    gen = torch.Generator(device=z.device).manual_seed(seed)
    pf = make_particle_filter(name, num_particles=n_particles)
    if steps > 0:
        final = pf.run(ssm, belief, ys, generator=gen).final
        particles, weights = final.particles, final.weights
    else:
        state = pf.init(ssm, belief, generator=gen)
        particles, weights = state.particles, state.weights
    return "particle", (particles, weights, gen), ssm


def _future_time(series: Series, horizon: int) -> Tensor:
    t = series.t
    steps = torch.arange(1, horizon + 1, dtype=torch.float64, device=t.device)
    return t[-1] + series.dt * steps


# ----------------------------------------------------------------------------- public
def forecast(
    model: FittedModel,
    series: Series,
    horizon: int,
    *,
    level: float = 0.95,
    filter: str = "sckf",
    filter_steps: int = 100,
    n_particles: int = 500,
    seed: int | None = None,
) -> ForecastResult:
    """Forecast ``horizon`` steps after the end of ``series`` with a central ``level`` band.

    Args:
        model: a :class:`FittedModel`.
        series: the observed series (at least ``m + 1`` values; NaN: missing, which the
            filter predicts over); its end is the forecast origin.
        horizon: number of steps ``H >= 1``.
        level: band probability in (0, 1).
        filter: a Gaussian filter name (``sckf``, ``stsckf``, ``ukf``, ``ekf``, ...) or a particle
            filter (``pf``, ``ekpf``, ``stpf``, ``upf``); see the module notes.
        filter_steps: observations filtered before predicting (at most ``T - m``; more where
            a value of the window the filter would start from is missing, fewer where no
            complete window lies before it).
        n_particles: particles (particle filters).
        seed: particle draws (default: the model's seed).

    Returns:
        :class:`ForecastResult` in data units.
    """
    model = _check_model(model)
    horizon = check_count(horizon, "horizon", error=ValueError)
    filter_steps = check_count(filter_steps, "filter_steps", 0, error=ValueError)
    n_particles = check_count(n_particles, "n_particles", MIN_PARTICLES, error=ValueError)
    name = _check_filter(filter)
    if not is_real(level) or not 0 < level < 1:
        raise ValueError(f"level must be a number in (0, 1), got {level!r}")
    level = float(level)
    seed = int(model.config.get("seed", 0)) if seed is None else check_seed(seed)
    if name not in GAUSSIAN_FILTERS:
        check_paths_memory(n_particles, horizon, model.m)
    else:
        check_forecast_memory(horizon)
    z = _scaled(model, series)
    kind, res, ssm = _filtered(model, z, name, filter_steps, n_particles, seed, series.name)
    inv = model.scaler.inverse_transform
    span = float(model.scaler.data_max - model.scaler.data_min)
    if kind == "gaussian":
        filt, state = res
        try:
            gp = gaussian_paths(filt, ssm, state, horizon, level=float(level))
        except torch.linalg.LinAlgError as exc:  # (torch's "matrix is not positive definite")
            raise ValueError(
                f"the {name} forecast diverged within {horizon} steps: its covariance lost "
                "positive definiteness (the learner's output, iterated from this series, grows "
                "without bound); forecast fewer steps (horizon), or use a particle filter "
                "(filter='stpf'), whose forecast warns where it diverges"
            ) from exc
        mean, lower, upper = inv(gp.mean), inv(gp.lower), inv(gp.upper)
        std, samples, weights = gp.std * span, None, None
    else:
        particles, weights, gen = res
        sp = particle_paths(
            ssm,
            particles,
            horizon,
            generator=gen,
            weights=weights,
            measurement_noise=True,
            level=float(level),
        )
        mean, lower, upper = inv(sp.mean), inv(sp.lower), inv(sp.upper)
        std, samples, weights = sp.std * span, inv(sp.samples), sp.weights
    lo, hi = float(model.scaler.data_min), float(model.scaler.data_max)
    dist = _extra.extrapolation_distance(series.values, mean, model.m, lo, hi)
    _extra.diverged(mean)
    if bool((dist > 0).any()):  # outside the training range: the learner extrapolates
        lower, upper, std = _extra.widen(mean, lower, upper, std, dist, float(level))
        _extra.warn("the forecast", float(dist.max()), lo, hi)
    return ForecastResult(
        time=_future_time(series, horizon),
        mean=mean,
        lower=lower,
        upper=upper,
        std=std,
        level=float(level),
        filter=name,
        history=series,
        samples=samples,
        weights=weights,
        extrapolation=dist,
    )


def rul(
    model: FittedModel,
    series: Series,
    threshold: float,
    *,
    horizon: int = 200,
    direction: str = "auto",
    filter: str = "stpf",
    filter_steps: int = 100,
    n_particles: int = 500,
    seed: int | None = None,
) -> RULResult:
    """RUL distribution at the end of ``series`` for a failure ``threshold`` (data units).

    Args:
        model: a :class:`FittedModel`.
        series: the observed series (at least ``m + 1`` values; NaN: missing, as for
            :func:`forecast`; the direction and the check that the threshold is not yet
            reached read the last observed value).
        threshold: failure threshold in data units.
        horizon: predicted steps; paths not crossing by then are censored.
        direction: ``"above"`` (failure when the value reaches ``threshold`` from below),
            ``"below"``, or ``"auto"``: above when ``threshold`` exceeds the last observed value.
        filter: ``stpf`` (default, paper 002), ``pf``, ``ekpf``, ``upf``, or a Gaussian filter
            (``sckf``, ...) whose final belief is sampled.
        filter_steps, n_particles, seed: as :func:`forecast`.

    Returns:
        :class:`RULResult` (RUL in the series' time unit); where the observations it starts
        from lie outside the model's training range, its ``flags`` hold the sentence of the
        :class:`~prognos_torch.workflow.ExtrapolationWarning` issued.

    Raises:
        ValueError: bad arguments, or a last observed value that already reaches the threshold.

    Warns:
        ThresholdWarning: with ``direction="auto"``, a threshold beyond every observed value on
            the side the series has moved away from (its sentence is also in ``flags``).
    """
    model = _check_model(model)
    horizon = check_count(horizon, "horizon", error=ValueError)
    filter_steps = check_count(filter_steps, "filter_steps", 0, error=ValueError)
    n_particles = check_count(n_particles, "n_particles", MIN_PARTICLES, error=ValueError)
    name = _check_filter(filter)
    threshold = check_real(threshold, "threshold")
    if direction not in ("auto", "above", "below"):
        raise ValueError(f"direction must be 'auto', 'above' or 'below', got {direction!r}")
    z = _scaled(model, series)
    seen = series.values[~torch.isnan(series.values)]  # NaN: missing
    last = float(seen[-1]) if seen.numel() else math.nan
    side = None
    if direction == "auto":
        if threshold == last:
            raise ValueError(
                f"threshold {threshold:g} equals the last observed value; the RUL is 0"
            )
        direction = "above" if threshold > last else "below"
        side = _against_the_trend(seen, threshold, direction)
    elif (direction == "above" and last >= threshold) or (
        direction == "below" and last <= threshold
    ):
        raise ValueError(
            f"the last observed value {last:g} already reaches the threshold {threshold:g} "
            f"(direction {direction!r}); the RUL is 0"
        )
    seed = int(model.config.get("seed", 0)) if seed is None else check_seed(seed)
    check_paths_memory(n_particles, horizon, model.m)
    lo, hi = float(model.scaler.data_min), float(model.scaler.data_max)
    flag = _extra.warn(
        "the series the RUL starts from",
        _extra.origin_distance(series.values, model.m, lo, hi),
        lo,
        hi,
    )
    # a threshold beyond the training range is reached only where the learner extrapolates
    beyond = max(lo - threshold, threshold - hi, 0.0)
    thr_flag = _extra.warn(f"the threshold {threshold:g}", beyond, lo, hi)
    if side is not None:
        warnings.warn(side, ThresholdWarning, stacklevel=2)
    kind, res, ssm = _filtered(model, z, name, filter_steps, n_particles, seed, series.name)
    if kind == "gaussian":
        _, state = res
        belief = state.belief if hasattr(state, "belief") else state
        gen = torch.Generator(device=z.device).manual_seed(seed)
        e = torch.randn(n_particles, model.m, generator=gen, dtype=z.dtype, device=z.device)
        particles = belief.mean + e @ belief.chol.mT
        weights = None
    else:
        particles, weights, gen = res
    sp = particle_paths(ssm, particles, horizon, generator=gen, weights=weights)
    paths = model.scaler.inverse_transform(sp.samples)
    # (a path that overflowed to NaN was refused as "samples contains NaN")
    passable, div_flag = _extra.censor_diverged(paths, direction)
    dist = rul_distribution(passable, threshold, sp.weights, dt=series.dt, direction=direction)
    t = series.t
    return RULResult(
        distribution=dist,
        threshold=threshold,
        direction=direction,
        horizon=horizon,
        dt=series.dt,
        time_unit=series.time_unit,
        t_last=float(t[-1]),
        paths=paths,
        weights=sp.weights,
        filter=name,
        n_particles=int(particles.shape[-2]),
        history=series,
        flags=tuple(f for f in (flag, thr_flag, side, div_flag) if f is not None),
    )


class ThresholdWarning(UserWarning):
    """A threshold whose direction, read from the last value, goes against the series."""


def _against_the_trend(seen: Tensor, threshold: float, direction: str) -> str | None:
    """The sentence of a :class:`ThresholdWarning` where ``direction="auto"`` read a side from
    the last observed value that the series has moved away from: a threshold beyond every
    observed value, on the side opposite to the move from the median of the first tenth of
    ``seen`` to that of the last tenth (a threshold on the healthy side, or in other units).
    ``None`` otherwise."""
    n = max(1, seen.numel() // 10)
    first, last = float(seen[:n].median()), float(seen[-n:].median())
    if direction == "below" and last > first and threshold < float(seen.min()):
        moved, beyond = "rose", "below"
    elif direction == "above" and last < first and threshold > float(seen.max()):
        moved, beyond = "fell", "above"
    else:
        return None
    return (
        f"the threshold {threshold:g} lies {beyond} every observed value while the series "
        f"{moved} (median of its first tenth {first:.4g}, of its last {last:.4g}): direction "
        f"{direction!r} comes from the last value alone; a threshold on the healthy side, or "
        f"in other units? Pass direction={direction!r} where it is meant"
    )


def holdout_metrics(model: FittedModel, series: Series, n_train: int) -> dict[str, float]:
    """Scores on the held-out tail ``series.values[n_train:]`` (data units).

    * ``rmse``, ``mae``: the :func:`forecast` (SCKF, 95 % band) made at the end of the training
      part over the tail (its first :data:`HOLDOUT_FORECAST_STEPS` values: ``horizon``), against
      the tail;
    * ``coverage``: fraction of those tail values inside that band (widened where the forecast
      leaves the training range, :mod:`~prognos_torch.workflow.extrapolation`; no warning);
    * ``one_step_rmse``: the learner's one-step predictions from the true windows (whole tail,
      ``tail`` values);
    * ``persistence_rmse``: the last training value held constant over ``horizon`` steps (a
      baseline).
    """
    full_tail = series.values[n_train:]
    n_tail = full_tail.shape[0]
    H = min(n_tail, HOLDOUT_FORECAST_STEPS)
    tail = full_tail[:H]
    with warnings.catch_warnings():  # a tail beyond the training range is what it measures
        warnings.simplefilter("ignore", _extra.ExtrapolationWarning)
        fc = forecast(model, series.head(n_train), H)
    z = model.scaler.transform(series.values)
    m = model.m
    windows = z.unfold(0, m, 1)[n_train - m : -1]  # windows ending just before each tail value
    with torch.no_grad():
        one = model.scaler.inverse_transform(model.learner(windows)[..., 0])
    inside = ((tail >= fc.lower) & (tail <= fc.upper)).to(torch.float64).mean()
    persistence = series.values[n_train - 1].expand(H)
    return {
        "horizon": H,
        "tail": n_tail,
        "rmse": float(rmse(fc.mean, tail)),
        "mae": float(mae(fc.mean, tail)),
        "coverage": float(inside),
        "level": fc.level,
        "one_step_rmse": float(rmse(one, full_tail)),
        "persistence_rmse": float(rmse(persistence, tail)),
    }
