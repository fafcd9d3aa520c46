"""Prediction and prognostic performance metrics (PHM).

Point-prediction errors (:func:`mae`, :func:`rmse`, :func:`mape`) return float64 tensors on the
input device. Prognostic metrics summarise one run-to-failure trajectory of RUL predictions and
return Python floats/bools; they follow

* [S09] A. Saxena, J. Celaya, B. Saha, S. Saha, K. Goebel, "On applying the prognostic
  performance metrics", Annual Conf. of the PHM Society, 2009;
* [S10] A. Saxena, J. Celaya, B. Saha, S. Saha, K. Goebel, "Metrics for offline evaluation of
  prognostic performance", Int. J. Prognostics and Health Management 1(1), 2010;
* [V06] G. Vachtsevanos, F. L. Lewis, M. Roemer, A. Hess, B. Wu, "Intelligent fault diagnosis
  and prognosis for engineering systems", Wiley, 2006 (prognosis performance metrics).

Paper 002 (Li et al. 2014) evaluates its RUL predictions by accuracy, RMSE, alpha-lambda
(alpha = 30 %, lambda = 0.5) and CRA (lambda in {0, 0.25, 0.5, 0.75}) in its Table 2.

Notation ([S10]): prediction times ``t_i`` (``times``, strictly increasing), true RUL
``r*(t_i)`` (``true_rul``), predicted RUL ``r(t_i)`` (``pred_rul``), end of life ``t_EoL``,
first prediction time ``t_P`` (default ``times[0]``), error ``Delta(i) = r*(t_i) - r(t_i)``.
When ``t_eol`` is not given it is inferred as ``times + true_rul``, which must then be constant.

Predicted RUL distributions (for the probability-mass versions of PH and alpha-lambda) are given
either as weighted samples (``rul_samples`` ``(n, S)``, optional ``sample_weights`` ``(n, S)``
summing to one per row) or as a pmf on a grid (``rul_pmf`` ``(n, K)`` on ``rul_support``
``(K,)``). A pmf may sum to less than one (e.g. ``RULDistribution.pmf``, whose censored mass
lies beyond the horizon); missing mass counts as outside any bounds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from .core.validation import as_tensor, check_scalar, check_weights

__all__ = [
    "mae",
    "rmse",
    "mape",
    "lambda_time",
    "lambda_index",
    "alpha_bounds",
    "in_alpha_cone",
    "probability_in_bounds",
    "prognostic_horizon",
    "alpha_lambda",
    "relative_accuracy",
    "cumulative_relative_accuracy",
    "convergence",
    "exponential_accuracy",
    "first_crossing_time",
    "PointRULScores",
    "point_rul_scores",
]


# --------------------------------------------------------------------------- helpers
def _pair(pred, target, pred_name: str, target_name: str) -> tuple[Tensor, Tensor]:
    pred = as_tensor(pred, pred_name)
    target = as_tensor(target, target_name, device=pred.device)
    if tuple(pred.shape) != tuple(target.shape):
        raise ValueError(
            f"{pred_name} and {target_name} must have the same shape, got "
            f"{tuple(pred.shape)} and {tuple(target.shape)}"
        )
    if pred.numel() == 0:
        raise ValueError(f"{pred_name} is empty")
    pred = pred.to(torch.float64)
    target = target.to(torch.float64)
    for x, name in ((pred, pred_name), (target, target_name)):
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"{name} contains non-finite values")
    return pred, target


def _slack(x: Tensor) -> Tensor:
    """Round-off allowance of an inclusive bound, ``1e-9 max(1, |x|)`` as in :func:`lambda_index`:
    ``(1 - 0.2) * 3`` is ``2.4000000000000004``, which must not exclude a prediction of 2.4."""
    return 1e-9 * x.abs().clamp_min(1.0)


def _reduce(x: Tensor, dim) -> Tensor:
    return x.mean() if dim is None else x.mean(dim=dim)


def _vec(x, name: str, n: int | None = None, device=None) -> Tensor:
    x = as_tensor(x, name, device=device).to(torch.float64)
    if x.dim() != 1:
        raise ValueError(f"{name} must be 1-D with shape (n,), got {tuple(x.shape)}")
    if n is not None and x.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n},), got {tuple(x.shape)}")
    if x.shape[0] == 0:
        raise ValueError(f"{name} is empty; shape (n,) with n >= 1")
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        raise ValueError(
            f"{name} contains non-finite values (first at index {i}: {x[i].item()}); a censored "
            "RUL has no point value: score its distribution (rul_samples with inf for the "
            "censored paths, or rul_pmf) or leave the point out"
            if name == "pred_rul"
            else f"{name} contains non-finite values (first at index {i}: {x[i].item()})"
        )
    return x


def _trajectory(times, true_rul, pred_rul, t_eol, *, need_pred: bool = True):
    times = _vec(times, "times")
    n = times.shape[0]
    if n > 1 and not bool((times[1:] > times[:-1]).all()):
        raise ValueError("times must be strictly increasing, shape (n,)")
    true_rul = _vec(true_rul, "true_rul", n, times.device)
    if pred_rul is None:
        if need_pred:
            raise ValueError("pred_rul is required, shape (n,)")
    else:
        pred_rul = _vec(pred_rul, "pred_rul", n, times.device)
    if t_eol is None:
        eol = times + true_rul
        spread = (eol.max() - eol.min()).item()
        if spread > 1e-9 * max(1.0, eol.abs().max().item()):
            raise ValueError(
                "t_eol is not given and times + true_rul is not constant; pass t_eol explicitly"
            )
        t_eol = eol.mean().item()
    else:
        t_eol = check_scalar(t_eol, "t_eol")
    if not t_eol > times[0].item():
        raise ValueError(
            f"t_eol ({t_eol:g}) must be later than the first prediction time ({times[0].item():g})"
        )
    return times, true_rul, pred_rul, t_eol


def _point_or_distribution(pred_rul, beta, dist: dict) -> float:
    """``beta`` (default 0.5) for a distribution; refuses a point prediction given beside a
    distribution (one of them would be ignored) and ``beta`` without a distribution."""
    given = any(v is not None for v in dist.values())
    if given and pred_rul is not None:
        raise ValueError(
            "give pred_rul (point predictions) or a distribution (rul_samples or rul_pmf), "
            "not both: the criterion reads one of them"
        )
    if not given and beta is not None:
        raise ValueError("beta applies to a distribution (rul_samples or rul_pmf), not to pred_rul")
    return _beta(0.5 if beta is None else beta)


def _alpha(alpha) -> tuple[float, float]:
    if isinstance(alpha, (tuple, list)):
        if len(alpha) != 2:
            raise ValueError("alpha must be a number or a pair (alpha_minus, alpha_plus)")
        a_minus, a_plus = check_scalar(alpha[0], "alpha"), check_scalar(alpha[1], "alpha")
    else:
        a_minus = a_plus = check_scalar(alpha, "alpha")
    if a_minus < 0 or a_plus < 0:
        raise ValueError(f"alpha must be >= 0, got {alpha}")
    return a_minus, a_plus


def _beta(beta) -> float:
    beta = check_scalar(beta, "beta")
    if not 0.0 < beta <= 1.0:
        raise ValueError(f"beta must lie in (0, 1], got {beta}")
    return beta


def _lam(lam) -> float:
    lam = check_scalar(lam, "lam")
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lam must lie in [0, 1], got {lam}")
    return lam


# --------------------------------------------------------------------------- point errors
def mae(pred: Tensor, target: Tensor, dim: int | tuple[int, ...] | None = None) -> Tensor:
    """Mean absolute error ``mean |pred - target|`` (float64, over all entries or ``dim``).

    ``pred`` and ``target`` must have the same shape (no broadcasting).
    """
    pred, target = _pair(pred, target, "pred", "target")
    return _reduce((pred - target).abs(), dim)


def rmse(pred: Tensor, target: Tensor, dim: int | tuple[int, ...] | None = None) -> Tensor:
    """Root-mean-square error ``sqrt(mean (pred - target)^2)`` (float64).

    Paper 002 Table 1 (one-step prediction) and Table 2 (RUL predictions).
    """
    pred, target = _pair(pred, target, "pred", "target")
    return _reduce((pred - target).square(), dim).sqrt()


def mape(pred: Tensor, target: Tensor, dim: int | tuple[int, ...] | None = None) -> Tensor:
    """Mean absolute percentage error ``100 * mean |(pred - target) / target|`` in percent.

    Zero targets make the ratio undefined: any ``target == 0`` raises ``ValueError`` (no epsilon
    is added, so the result is never an arbitrary huge number). For RUL, drop the prediction at
    end of life (true RUL 0) or use :func:`mae`.
    """
    pred, target = _pair(pred, target, "pred", "target")
    if bool((target == 0).any()):
        raise ValueError("target contains zeros; MAPE is undefined there (use mae or drop them)")
    return 100.0 * _reduce(((pred - target) / target).abs(), dim)


# --------------------------------------------------------------------------- time points
def lambda_time(t_p: float, t_eol: float, lam: float) -> float:
    """``t_lambda = t_P + lambda (t_EoL - t_P)`` ([S10], alpha-lambda accuracy)."""
    return check_scalar(t_p, "t_p") + _lam(lam) * (
        check_scalar(t_eol, "t_eol") - check_scalar(t_p, "t_p")
    )


def lambda_index(times: Tensor, lam: float, *, t_eol: float, t_p: float | None = None) -> int:
    """Index of the prediction evaluated at ``t_lambda``: the first ``t_i >= t_lambda``.

    Predictions exist only at discrete times; [S10] evaluates at the time index ``i_lambda``
    reached once the fraction lambda of ``[t_P, t_EoL]`` has elapsed, i.e. the first prediction
    made at or after ``t_lambda`` (a relative tolerance of 1e-9 absorbs round-off).
    Raises ``ValueError`` if no prediction is made in ``[t_lambda, t_EoL]`` (a prediction made
    after the end of life has a negative true RUL and no place in the metrics).
    """
    times = _vec(times, "times")
    if times.shape[0] > 1 and not bool((times[1:] > times[:-1]).all()):
        raise ValueError("times must be strictly increasing, shape (n,)")
    t_eol = check_scalar(t_eol, "t_eol")
    t_p = times[0].item() if t_p is None else check_scalar(t_p, "t_p")
    if not t_eol > t_p:
        raise ValueError(f"t_eol ({t_eol:g}) must be later than t_P ({t_p:g})")
    t_lam = lambda_time(t_p, t_eol, lam)
    slack = 1e-9 * max(1.0, abs(t_lam))
    idx = torch.nonzero(times >= t_lam - slack).flatten()
    if idx.numel() == 0:
        raise ValueError(
            f"no prediction at or after t_lambda = {t_lam:g} (lam = {lam}); last time is "
            f"{times[-1].item():g}"
        )
    i = int(idx[0].item())
    if times[i].item() > t_eol + 1e-9 * max(1.0, abs(t_eol)):
        raise ValueError(
            f"no prediction in [t_lambda, t_EoL] = [{t_lam:g}, {t_eol:g}] (lam = {lam}): the "
            f"first one at or after t_lambda is at {times[i].item():g}, after the end of life"
        )
    return i


def alpha_bounds(true_rul: Tensor, alpha: float | tuple[float, float]) -> tuple[Tensor, Tensor]:
    """Alpha-lambda cone ``[(1 - alpha^-) r*, (1 + alpha^+) r*]`` ([S10] Eq. for alpha-lambda).

    ``alpha`` is a number (symmetric) or a pair ``(alpha_minus, alpha_plus)``.
    """
    true_rul = as_tensor(true_rul, "true_rul").to(torch.float64)
    a_minus, a_plus = _alpha(alpha)
    return (1.0 - a_minus) * true_rul, (1.0 + a_plus) * true_rul


def in_alpha_cone(pred_rul: Tensor, true_rul: Tensor, alpha: float | tuple[float, float]) -> Tensor:
    """Whether each predicted RUL lies in its alpha cone :func:`alpha_bounds` (bounds inclusive
    to a round-off of ``1e-9 max(1, |bound|)``, as every criterion here); ``inf`` and NaN
    predictions lie outside. Shapes broadcast; returns a bool tensor."""
    pred = as_tensor(pred_rul, "pred_rul").to(torch.float64)
    lower, upper = alpha_bounds(true_rul, alpha)
    lower, upper = lower.to(pred.device), upper.to(pred.device)
    return (pred >= lower - _slack(lower)) & (pred <= upper + _slack(upper))


def probability_in_bounds(
    lower: Tensor,
    upper: Tensor,
    *,
    rul_samples: Tensor | None = None,
    sample_weights: Tensor | None = None,
    rul_pmf: Tensor | None = None,
    rul_support: Tensor | None = None,
) -> Tensor:
    """Probability mass ``pi[r(i)]`` of each predicted RUL distribution in ``[lower_i, upper_i]``.

    [S09]/[S10]: the probability-mass criterion ``pi[r(i)]_{-alpha}^{+alpha} >= beta`` of PH and
    alpha-lambda. Bounds are inclusive (to a round-off of ``1e-9 max(1, |bound|)``, as are the
    point criteria of PH and alpha-lambda). Give either ``rul_samples`` ``(n, S)`` (optional
    normalised ``sample_weights`` ``(n, S)``; default ``1/S``) or ``rul_pmf`` ``(n, K)`` with
    ``rul_support`` ``(K,)`` (pmf entries >= 0, row sums <= 1; missing mass is outside).

    Returns:
        ``(n,)`` float64 masses.
    """
    lower = _vec(lower, "lower")
    n = lower.shape[0]
    upper = _vec(upper, "upper", n, lower.device)
    if (rul_samples is None) == (rul_pmf is None):
        raise ValueError("give exactly one of rul_samples or rul_pmf")
    if rul_samples is not None:
        if rul_support is not None:
            raise ValueError("rul_support goes with rul_pmf, not with rul_samples")
        s = as_tensor(rul_samples, "rul_samples", device=lower.device).to(torch.float64)
        if s.dim() != 2 or s.shape[0] != n or s.shape[1] < 1:
            raise ValueError(
                f"rul_samples must have shape ({n}, S) with S >= 1, got {tuple(s.shape)}"
            )
        if bool(torch.isnan(s).any()):
            i = int(torch.isnan(s).any(-1).nonzero()[0, 0])
            raise ValueError(
                f"rul_samples contains NaN (first in row {i}); a censored path's RUL is inf "
                "(beyond every bound): pass inf for it, and leave out paths that do not count"
            )
        w = check_weights(sample_weights, (n,), s.shape[1], s.device, name="sample_weights")
        lo, hi = lower - _slack(lower), upper + _slack(upper)
        inside = (s >= lo[:, None]) & (s <= hi[:, None])
        return (w * inside.to(torch.float64)).sum(-1)
    if sample_weights is not None:
        raise ValueError("sample_weights goes with rul_samples, not with rul_pmf")
    if rul_support is None:
        raise ValueError("rul_pmf needs rul_support, shape (K,)")
    p = as_tensor(rul_pmf, "rul_pmf", device=lower.device)
    # rows of a float32 pmf (a softmax, say) sum to one to float32 rounding, as sample weights
    low = str(getattr(rul_pmf, "dtype", "")).replace("torch.", "") in ("float32", "float16",
                                                                      "bfloat16")  # fmt: skip
    tol = 1e-6 + 4.0 * p.shape[-1] * torch.finfo(torch.float32).eps if low else 1e-9
    p = p.to(torch.float64)
    support = _vec(rul_support, "rul_support", device=lower.device)
    k = support.shape[0]
    if tuple(p.shape) != (n, k):
        raise ValueError(f"rul_pmf must have shape ({n}, {k}) (n, K), got {tuple(p.shape)}")
    if not bool(torch.isfinite(p).all()) or bool((p < 0).any()):
        raise ValueError("rul_pmf must be finite and non-negative")
    over = p.sum(-1) - 1.0
    if bool((over > tol).any()):
        i = int(over.argmax())
        raise ValueError(
            f"rul_pmf rows must sum to at most one (within {tol:.2g}); row {i} sums to "
            f"1 + {over[i].item():.3g}"
        )
    lo, hi = lower - _slack(lower), upper + _slack(upper)
    inside = (support[None, :] >= lo[:, None]) & (support[None, :] <= hi[:, None])
    return (p * inside.to(torch.float64)).sum(-1)


def _within(pred_rul, lower, upper, beta, dist: dict) -> Tensor:
    """Point criterion ``lower <= r <= upper`` or mass criterion ``pi >= beta`` ([S10])."""
    if any(v is not None for v in dist.values()):
        return probability_in_bounds(lower, upper, **dist) >= beta
    return (pred_rul >= lower - _slack(lower)) & (pred_rul <= upper + _slack(upper))


# --------------------------------------------------------------------------- prognostic metrics
def prognostic_horizon(
    times: Tensor,
    true_rul: Tensor,
    pred_rul: Tensor | None = None,
    *,
    alpha: float | tuple[float, float],
    beta: float | None = None,
    t_eol: float | None = None,
    persistent: bool = False,
    rul_samples: Tensor | None = None,
    sample_weights: Tensor | None = None,
    rul_pmf: Tensor | None = None,
    rul_support: Tensor | None = None,
) -> float:
    """Prognostic horizon ``PH = t_EoL - t_{i_alpha}`` ([S10]; [S09]).

    ``i_alpha = min{ i : criterion(i) }`` with alpha bounds of constant width around the true RUL
    line, expressed as a fraction of the end of life: ``[r*(t_i) - alpha^- t_EoL,
    r*(t_i) + alpha^+ t_EoL]`` (times measured from the start of life). The criterion is
    ``lower <= r(t_i) <= upper`` for point predictions or the probability mass
    ``pi[r(t_i)] >= beta`` when a predicted distribution is given.

    Args:
        times, true_rul, pred_rul: ``(n,)`` trajectory (``pred_rul`` may be None with a
            distribution).
        alpha: bound half-width as a fraction of ``t_EoL`` (number or ``(minus, plus)`` pair).
        beta: probability-mass threshold in (0, 1] (distributions only; default 0.5).
        t_eol: end of life; inferred from ``times + true_rul`` when None; later than the
            first prediction time.
        persistent: if True, ``i_alpha`` is the first index from which *every* later prediction
            meets the criterion (a stricter reading that ignores predictions which enter
            the bounds and leave them again).
        rul_samples, sample_weights, rul_pmf, rul_support: see :func:`probability_in_bounds`.

    Returns:
        PH in the units of ``times``; NaN when the criterion is never met. Prediction times
        after ``t_eol`` raise ``ValueError``.
    """
    dist = dict(
        rul_samples=rul_samples,
        sample_weights=sample_weights,
        rul_pmf=rul_pmf,
        rul_support=rul_support,
    )
    need_pred = all(v is None for v in dist.values())
    beta = _point_or_distribution(pred_rul, beta, dist)
    times, true_rul, pred_rul, t_eol = _trajectory(
        times, true_rul, pred_rul, t_eol, need_pred=need_pred
    )
    if times[-1].item() > t_eol + 1e-9 * max(1.0, abs(t_eol)):
        raise ValueError(
            f"times must not be later than t_eol ({t_eol:g}); the last is {times[-1].item():g} "
            "(a prediction after the end of life would give a negative horizon): leave it out"
        )
    a_minus, a_plus = _alpha(alpha)
    lower = true_rul - a_minus * t_eol
    upper = true_rul + a_plus * t_eol
    ok = _within(pred_rul, lower, upper, beta, dist)
    if persistent:
        # ok_suffix[i] = all(ok[i:]): reverse cumulative minimum.
        ok = ok.flip(0).to(torch.int8).cummin(0).values.flip(0).bool()
    idx = torch.nonzero(ok).flatten()
    if idx.numel() == 0:
        return math.nan
    return t_eol - times[idx[0]].item()


def alpha_lambda(
    times: Tensor,
    true_rul: Tensor,
    pred_rul: Tensor | None = None,
    *,
    alpha: float | tuple[float, float],
    lam: float,
    beta: float | None = None,
    t_eol: float | None = None,
    t_p: float | None = None,
    rul_samples: Tensor | None = None,
    sample_weights: Tensor | None = None,
    rul_pmf: Tensor | None = None,
    rul_support: Tensor | None = None,
) -> bool:
    """Alpha-lambda accuracy ([S10]): is the prediction at ``t_lambda`` in the cone?

    ``t_lambda = t_P + lambda (t_EoL - t_P)``; evaluated at the first prediction made at or
    after ``t_lambda`` (:func:`lambda_index`). Point version:
    ``(1 - alpha^-) r*(t_lambda) <= r(t_lambda) <= (1 + alpha^+) r*(t_lambda)``; distribution
    version: ``pi[r(t_lambda)]_{-alpha}^{+alpha} >= beta`` (``beta`` default 0.5; given only
    with a distribution, which replaces ``pred_rul``). ``t_EoL`` must be later than ``t_P``.
    Paper 002 uses alpha = 0.3 and lambda = 0.5 (Table 2).

    Returns:
        True when the criterion holds.
    """
    dist = dict(
        rul_samples=rul_samples,
        sample_weights=sample_weights,
        rul_pmf=rul_pmf,
        rul_support=rul_support,
    )
    need_pred = all(v is None for v in dist.values())
    beta = _point_or_distribution(pred_rul, beta, dist)
    times, true_rul, pred_rul, t_eol = _trajectory(
        times, true_rul, pred_rul, t_eol, need_pred=need_pred
    )
    i = lambda_index(times, lam, t_eol=t_eol, t_p=t_p)
    lower, upper = alpha_bounds(true_rul, alpha)
    ok = _within(pred_rul, lower, upper, beta, dist)
    return bool(ok[i].item())


def _ra(true_rul: Tensor, pred_rul: Tensor, times: Tensor) -> Tensor:
    # RA = 1 - |r* - r| / r*  ([S10]); undefined at the end of life (r* = 0)
    if bool((true_rul <= 0).any()):
        t = times[true_rul <= 0][0].item()
        raise ValueError(
            f"relative accuracy needs true_rul > 0 at the evaluated times; it is "
            f"{true_rul[true_rul <= 0][0].item():g} at t = {t:g} (at the end of life RA is "
            "undefined: evaluate up to a lam < 1, or leave that point out)"
        )
    return 1.0 - (true_rul - pred_rul).abs() / true_rul


def relative_accuracy(
    times: Tensor,
    true_rul: Tensor,
    pred_rul: Tensor,
    *,
    lam: float,
    t_eol: float | None = None,
    t_p: float | None = None,
) -> float:
    """Relative accuracy at ``t_lambda`` ([S10]).

    ``RA_lambda = 1 - |r*(t_lambda) - r(t_lambda)| / r*(t_lambda)``, evaluated at
    :func:`lambda_index`. 1 is perfect; it is negative when the error exceeds the true RUL.
    """
    times, true_rul, pred_rul, t_eol = _trajectory(times, true_rul, pred_rul, t_eol)
    i = lambda_index(times, lam, t_eol=t_eol, t_p=t_p)
    return float(_ra(true_rul[i : i + 1], pred_rul[i : i + 1], times[i : i + 1]).item())


def cumulative_relative_accuracy(
    times: Tensor,
    true_rul: Tensor,
    pred_rul: Tensor,
    *,
    lam: float | None = None,
    lambdas: Sequence[float] | None = None,
    weights: Tensor | None = None,
    t_eol: float | None = None,
    t_p: float | None = None,
) -> float:
    """Cumulative relative accuracy ([S10]), plain or weighted mean of RA.

    Saxena's form (``lambdas`` None; ``lam`` default 1): ``CRA_lambda = sum_{i in p_lambda} w_i RA(i) /
    sum_{i in p_lambda} w_i`` over the prediction times ``p_lambda = {i : t_P <= t_i <=
    t_lambda}``. [S10] writes ``(1/|p_lambda|) sum w(r(i)) RA(i)``; normalising by ``sum w``
    makes it a weighted mean that reduces to the plain mean for equal weights (identical when
    the weights average to one). Weights (``(n,)``, >= 0, not all zero on ``p_lambda``) may,
    e.g., grow towards end of life.

    Paper 002's form (``lambdas`` given, e.g. ``(0, 0.25, 0.5, 0.75)`` as in its Table 2): the
    mean of ``RA_lambda`` at those lambda points (each at :func:`lambda_index`); ``weights``
    then has one entry per lambda (``lam`` is not given then).

    RA is undefined where the true RUL is 0 (the end of life): with ``lam = 1`` on a trajectory
    that holds its end-of-life point, evaluate up to a ``lam < 1`` or leave the point out.
    """
    times, true_rul, pred_rul, t_eol = _trajectory(times, true_rul, pred_rul, t_eol)
    if lambdas is not None and lam is not None:
        raise ValueError(
            "give lam (Saxena's CRA up to t_lambda) or lambdas (paper 002's), not both"
        )
    lam = 1.0 if lam is None else lam
    if lambdas is not None:
        idx = torch.tensor(
            [lambda_index(times, lam_k, t_eol=t_eol, t_p=t_p) for lam_k in lambdas],
            dtype=torch.long,
            device=times.device,
        )
        if idx.numel() == 0:
            raise ValueError("lambdas is empty")
    else:
        t_p_val = times[0].item() if t_p is None else check_scalar(t_p, "t_p")
        t_lam = lambda_time(t_p_val, t_eol, lam)
        slack = 1e-9 * max(1.0, abs(t_lam))
        mask = (times >= t_p_val - slack) & (times <= t_lam + slack)
        idx = torch.nonzero(mask).flatten()
        if idx.numel() == 0:
            raise ValueError(f"no prediction time in [t_P, t_lambda] = [{t_p_val:g}, {t_lam:g}]")
    ra = _ra(true_rul[idx], pred_rul[idx], times[idx])
    if weights is None:
        return float(ra.mean().item())
    if lambdas is not None:
        w = _vec(weights, "weights", len(lambdas), times.device)
    else:
        w = _vec(weights, "weights", times.shape[0], times.device)[idx]
    if bool((w < 0).any()) or not bool((w > 0).any()):
        raise ValueError("weights must be >= 0 and not all zero on the evaluated times")
    return float(((w * ra).sum() / w.sum()).item())


def convergence(
    times: Tensor,
    true_rul: Tensor,
    pred_rul: Tensor,
    *,
    metric: Tensor | None = None,
    t_p: float | None = None,
    t_end: float | None = None,
) -> float:
    """Convergence: distance from ``(t_P, 0)`` to the centroid of the area under ``M(i)``.

    [S10]: ``C_M = sqrt((x_c - t_P)^2 + y_c^2)`` with
    ``x_c = sum_i (t_{i+1}^2 - t_i^2) M(i) / (2 sum_i (t_{i+1} - t_i) M(i))`` and
    ``y_c = sum_i (t_{i+1} - t_i) M(i)^2 / (2 sum_i (t_{i+1} - t_i) M(i))``: the centroid of
    the step curve that holds ``M(i)`` on ``[t_i, t_{i+1})``. Lower is better (faster
    convergence). ``M(i)`` defaults to the absolute error ``|r*(t_i) - r(t_i)|``; any
    non-negative per-time metric ``(n,)`` may be passed as ``metric``. The sums run over the
    ``n - 1`` intervals between prediction times; with ``t_end`` (> last time, e.g. ``t_EoL``)
    the last prediction holds until ``t_end`` and all ``n`` points contribute. With ``t_p``
    the sums start at ``i = P``, the first prediction at or after ``t_p`` ([S10]: ``i`` from
    ``P`` to ``EoUP``), and the distance is measured from ``(t_p, 0)``.

    Returns:
        ``C_M``; NaN when the area under ``M`` is zero (centroid undefined).
    """
    times = _vec(times, "times")
    n = times.shape[0]
    if n > 1 and not bool((times[1:] > times[:-1]).all()):
        raise ValueError("times must be strictly increasing, shape (n,)")
    if metric is None:
        true_rul = _vec(true_rul, "true_rul", n, times.device)
        pred_rul = _vec(pred_rul, "pred_rul", n, times.device)
        m = (true_rul - pred_rul).abs()
    else:
        m = _vec(metric, "metric", n, times.device)
        if bool((m < 0).any()):
            raise ValueError("metric must be non-negative, shape (n,)")
    t_p_val = times[0].item() if t_p is None else check_scalar(t_p, "t_p")
    if t_p is not None:  # i from P: the first prediction at or after t_p
        keep = times >= t_p_val - 1e-9 * max(1.0, abs(t_p_val))
        if not bool(keep.any()):
            raise ValueError(
                f"t_p ({t_p_val:g}) is later than the last prediction time ({times[-1].item():g})"
            )
        times, m = times[keep], m[keep]
        n = times.shape[0]
    if t_end is not None:
        t_end = check_scalar(t_end, "t_end")
        if t_end <= times[-1].item():
            raise ValueError("t_end must be later than the last prediction time")
        edges = torch.cat([times, times.new_tensor([t_end])])
    else:
        if n < 2:
            raise ValueError("convergence needs at least two prediction times (or t_end)")
        edges = times
        m = m[:-1]
    t0, t1 = edges[:-1], edges[1:]
    area = ((t1 - t0) * m).sum()
    if area.item() <= 0:
        return math.nan
    x_c = ((t1.square() - t0.square()) * m).sum() / (2.0 * area)
    y_c = ((t1 - t0) * m.square()).sum() / (2.0 * area)
    return float(torch.sqrt((x_c - t_p_val) ** 2 + y_c**2).item())


def exponential_accuracy(true_rul: Tensor, pred_rul: Tensor, *, d0: float) -> float:
    """Exponential prognostic accuracy ([V06]): ``mean_i exp(-|D_i| / D_0)``.

    ``D_i`` is the distance between predicted and actual failure time; for a prediction made at
    ``t_i`` it equals the RUL error ``r(t_i) - r*(t_i)``. ``D_0 > 0`` is a normalising constant
    chosen for the application's time scale (same units as the RUL). The score lies in
    ``(0, 1]``, 1 being perfect.

    This is the "Accuracy" column of paper 002's Table 2, which cites its reference 36 for it.
    The extracted reference list of paper 002 stops at 35; its in-text numbers at the end are
    one ahead of the list (text 30/32 = list 29/31: NASA repository, LLE; text 35, cited for
    alpha-lambda and CRA, = list 34, Saxena et al. 2009), so reference 36 is list 35,
    Vachtsevanos et al. 2006 [V06], whose prognosis accuracy is this exponential of the
    normalised absolute error. It is not the PHM'08 asymmetric score
    ``sum(exp(-d/13) - 1 | d < 0) + sum(exp(d/10) - 1 | d >= 0)``, which is unbounded and
    lower-is-better, unlike Table 2's values in (0, 1) where higher is better.
    """
    true_rul, pred_rul = _pair(true_rul, pred_rul, "true_rul", "pred_rul")
    d0 = check_scalar(d0, "d0")
    if d0 <= 0:
        raise ValueError(f"d0 must be positive, got {d0}")
    return float(torch.exp(-(pred_rul - true_rul).abs() / d0).mean().item())


# --------------------------------------------------------------------------- end of life, bundles
def first_crossing_time(times, values, threshold: float, direction: str = "above") -> float:
    """Time of the first sample that reaches the threshold: ``times[i*]`` with ``i*`` the first
    ``i`` where ``values[i] >= threshold`` (``direction="above"``) or ``<=`` (``"below"``).

    The end of life ``t_EoL`` of a measured run-to-failure indicator. Returns NaN when no sample
    reaches the threshold. NaN values are missing samples (they never cross).

    Args:
        times: ``(n,)`` sample times; values: ``(n,)`` indicator values.
        threshold: finite scalar failure threshold.
        direction: ``"above"`` or ``"below"``.
    """
    times = _vec(times, "times")
    values = as_tensor(values, "values", device=times.device)
    if tuple(values.shape) != tuple(times.shape):
        raise ValueError(f"values must have shape {tuple(times.shape)}, got {tuple(values.shape)}")
    thr = check_scalar(threshold, "threshold")
    if direction not in ("above", "below"):
        raise ValueError(f"direction must be 'above' or 'below', got {direction!r}")
    hit = values >= thr if direction == "above" else values <= thr
    idx = torch.nonzero(hit).flatten()
    return float(times[idx[0]]) if idx.numel() else math.nan


class PointRULScores(NamedTuple):
    """Point-RUL scores of one run (paper 002 Table 2): :func:`exponential_accuracy`, RMSE,
    :func:`alpha_lambda` (1.0 when met) and paper 002's :func:`cumulative_relative_accuracy`."""

    accuracy: float
    rmse: float
    alpha_lambda: float
    cra: float


def point_rul_scores(
    times: Tensor,
    true_rul: Tensor,
    pred_rul: Tensor,
    *,
    t_eol: float,
    d0: float,
    alpha: float | tuple[float, float] = 0.3,
    lam: float = 0.5,
    cra_lambdas: Sequence[float] = (0.0, 0.25, 0.5, 0.75),
) -> PointRULScores:
    """The four RUL scores of paper 002 Table 2 for one run of point predictions.

    Args:
        times: ``(n,)`` prediction times; true_rul, pred_rul: ``(n,)``.
        t_eol: end of life.
        d0: normaliser of the exponential accuracy (time units of the RUL).
        alpha, lam: the alpha-lambda cone and time (paper 002: 0.3, 0.5).
        cra_lambdas: the lambda points averaged by the CRA (paper 002: 0, 0.25, 0.5, 0.75).
    Returns:
        :class:`PointRULScores`.
    """
    return PointRULScores(
        accuracy=exponential_accuracy(true_rul, pred_rul, d0=d0),
        rmse=float(rmse(pred_rul, true_rul)),
        alpha_lambda=float(
            alpha_lambda(times, true_rul, pred_rul, alpha=alpha, lam=lam, t_eol=t_eol)
        ),
        cra=cumulative_relative_accuracy(
            times, true_rul, pred_rul, lambdas=cra_lambdas, t_eol=t_eol
        ),
    )
