"""Audit of the conformal margin, the simulation to an event and the sigma-point rules against
exact references: the CQR rank rule in exact rational arithmetic (ties, infinite scores, small
n), first passages of deterministic dynamics in closed form, a Gaussian random walk against a
NumPy Monte Carlo, and Gaussian moments of every rule up to its degree in n = 1, 2, 5."""

from __future__ import annotations

import itertools
import math
from fractions import Fraction

import numpy as np
import pytest
import torch

from prognos_torch.core import StateSpaceModel
from prognos_torch.prognosis import simulate_to_event
from prognos_torch.prognosis.conformal import conformal_margin, points_needed
from prognos_torch.quadrature import cubature, gauss_hermite, julier, unscented

T = lambda *v: torch.tensor(v, dtype=torch.float64)  # noqa: E731


# ---------------------------------------------------------------- conformal rank rule


def _margin_reference(s: np.ndarray, c: float) -> float:
    """The ceil((n + 1) c)-th smallest non-NaN score, the rank in exact rational arithmetic."""
    s = np.sort(s[~np.isnan(s)])
    k = math.ceil((len(s) + 1) * Fraction(str(c)))
    return math.inf if k > len(s) else float(s[k - 1])


def test_margin_rank_in_exact_arithmetic_with_ties_and_infinite_scores():
    rng = np.random.default_rng(11)
    for _ in range(400):
        n = int(rng.integers(1, 45))
        c = float(rng.choice([0.1, 0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95]))
        s = np.round(rng.normal(size=n), 1)  # ties
        s[rng.random(n) < 0.15] = math.inf  # an interval [0, 0] or a miss by an infinite factor
        s[rng.random(n) < 0.15] = -math.inf  # an interval [0, inf)
        s[rng.random(n) < 0.1] = math.nan  # no interval
        if np.isnan(s).all():
            continue
        assert conformal_margin(torch.from_numpy(s), c) == _margin_reference(s, c), (n, c, s)
    # (n + 1) c an integer in exact arithmetic but not in floating point: 10 * 0.7 = 7.000...01
    assert conformal_margin(torch.arange(1.0, 10.0, dtype=torch.float64), 0.7) == 7.0
    # ties at the rank and an infinite score at the rank
    assert conformal_margin(T(0.3, 0.3, 0.3, -math.inf, math.inf), 0.5) == 0.3  # k = 3
    assert conformal_margin(T(0.1, math.inf, 0.2, 0.4), 0.8) == math.inf  # k = 4: the inf
    for c in (0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 0.975, 0.99):
        need = next(n for n in range(1, 10_000) if math.ceil((n + 1) * Fraction(str(c))) <= n)
        assert points_needed(c) == need


# ---------------------------------------------------------------- simulation to an event


def _scalar_model(f, std=0.0):
    return StateSpaceModel(f=f, h=lambda x, u, k: x, state_dim=1, obs_dim=1, chol_Q=T([std]).reshape(1, 1),
                           chol_R=T(1.0).reshape(1, 1), batched=True)  # fmt: skip


@pytest.mark.parametrize("chunk, active_only", [(1, False), (3, True), (None, False)])
def test_first_passage_of_deterministic_dynamics_in_closed_form(chunk, active_only):
    # x_k = x_{k-1} + v, event x >= thr: j = ceil((thr - x0) / v) (x0 < thr), censored beyond H
    v, thr, H, t0, dt = 0.25, 1.0, 10, 2.0, 0.5
    x0 = T(0.0, 0.1, 0.5, 0.9, -3.0, 0.99)
    res = simulate_to_event(_scalar_model(lambda x, u, k: x + v), x0[:, None],
                            lambda x: x[..., 0] >= thr, max_steps=H, t0=t0, dt=dt, chunk=chunk,
                            active_only=active_only)  # fmt: skip
    j = [math.ceil((thr - a) / v) for a in x0.tolist()]
    want = [t0 + dt * k if k <= H else math.nan for k in j]
    torch.testing.assert_close(res.time_of_event, T(*want), equal_nan=True, rtol=0, atol=1e-15)
    assert float(res.censored_mass) == pytest.approx(1 / 6, abs=1e-15)
    torch.testing.assert_close(res.final_state[:, 0], x0 + v * T(*[min(k, H) for k in j]),
                               rtol=0, atol=1e-14)  # fmt: skip
    # x_k = x_{k-1} / 2, event x <= 0.3: j = ceil(log2(x0 / 0.3)); weighted mean and quantiles
    x0 = T(1.0, 2.0, 4.0, 8.0)
    w = T(0.1, 0.2, 0.3, 0.4)
    res = simulate_to_event(_scalar_model(lambda x, u, k: 0.5 * x), x0[:, None],
                            lambda x: x[..., 0] <= 0.3, max_steps=20, weights=w, t0=1.0, dt=2.0,
                            chunk=chunk, active_only=active_only)  # fmt: skip
    j = [math.ceil(math.log2(a / 0.3)) for a in x0.tolist()]
    assert res.rul.first_passage.tolist() == j == [2, 3, 4, 5]
    times = [1.0 + 2.0 * k for k in j]  # 5, 7, 9, 11
    assert float(res.mean) == pytest.approx(
        sum(a * b for a, b in zip(w.tolist(), times)), abs=1e-12
    )
    assert res.quantile(T(0.1, 0.3, 0.31, 0.6, 1.0)).tolist() == [5.0, 7.0, 9.0, 9.0, 11.0]


def test_gaussian_random_walk_first_passage_against_numpy_monte_carlo():
    # x_k = x_{k-1} + mu + sigma e_k from 0, event x >= 5, H = 30 steps: the first-passage CDF
    # (censored mass included) of N = 4000 paths against 10^5 NumPy paths. Two-sample
    # Kolmogorov-Smirnov bound at level 1e-4: sqrt(ln(2e4) / 2) sqrt(1/4000 + 1/1e5) = 0.036.
    mu, sigma, thr, H, N, M = 0.3, 1.0, 5.0, 30, 4000, 100_000
    res = simulate_to_event(_scalar_model(lambda x, u, k: x + mu, sigma),
                            torch.zeros(N, 1, dtype=torch.float64), lambda x: x[..., 0] >= thr,
                            max_steps=H, process_noise=True,
                            generator=torch.Generator().manual_seed(3))  # fmt: skip
    rng = np.random.default_rng(0)
    X = np.cumsum(mu + sigma * rng.standard_normal((M, H)), axis=1)
    hit = X >= thr
    j = np.where(hit.any(1), hit.argmax(1) + 1, H + 1)
    cdf_np = (j[None, :] <= np.arange(1, H + 1)[:, None]).mean(1)
    tol = math.sqrt(math.log(2e4) / 2) * math.sqrt(1 / N + 1 / M)
    assert np.abs(res.rul.cdf.numpy() - cdf_np).max() < tol
    assert abs(float(res.censored_mass) - (j > H).mean()) < tol


# ---------------------------------------------------------------- sigma-point rules


def _gauss_moment(p) -> float:
    """E[prod_i x_i^p_i], x ~ N(0, I): prod (p_i - 1)!! over even p_i, 0 if any p_i is odd."""
    return float(np.prod([0 if a % 2 else math.prod(range(a - 1, 0, -2)) for a in p]))


def _monomials(n, degree):
    return [p for p in itertools.product(range(degree + 1), repeat=n) if sum(p) <= degree]


RULES = [  # (rule, degree exact in every dimension)
    (cubature(), 3),
    (unscented(), 3),
    (unscented(0.5, 2.0, 1.0), 3),
    (julier(1.0), 3),
    (julier(None), 3),
    (gauss_hermite(2), 3),
    (gauss_hermite(3), 5),
    (gauss_hermite(4), 7),
]


@pytest.mark.parametrize("n", [1, 2, 5])
def test_each_rule_integrates_gaussian_moments_up_to_its_degree(n):
    for rule, degree in RULES:
        xi, wm, wc = (a.numpy() for a in rule.points(n))
        assert wm.sum() == pytest.approx(1.0, abs=1e-14)
        for p in _monomials(n, degree):
            got = (wm * np.prod(xi ** np.array(p), axis=1)).sum()
            assert got == pytest.approx(_gauss_moment(p), abs=1e-11), (rule, n, p)
        if rule.kind != "unscented":
            continue
        # the documented parameters: lambda = alpha^2 (n + kappa) - n (kappa None: 3 - n),
        # points 0, +-sqrt(n + lambda) e_i; W_0 = lambda / (n + lambda), W_i = 1 / (2 (n + lambda)),
        # W_0^c = W_0 + 1 - alpha^2 + beta
        k = 3.0 - n if rule.kappa is None else rule.kappa
        lam = rule.alpha**2 * (n + k) - n
        assert np.allclose(xi[1 : n + 1], math.sqrt(n + lam) * np.eye(n), rtol=1e-15, atol=0)
        assert np.allclose(xi[n + 1 :], -math.sqrt(n + lam) * np.eye(n), rtol=1e-15, atol=0)
        assert wm[0] == pytest.approx(lam / (n + lam), abs=1e-15)
        assert np.allclose(wm[1:], 1 / (2 * (n + lam)), rtol=1e-15, atol=0)
        assert wc[0] == pytest.approx(wm[0] + 1 - rule.alpha**2 + rule.beta, abs=1e-15)
        # kappa = 3 - n also matches the diagonal fourth moments E[x_i^4] = 3
        if rule.kappa is None:
            assert np.allclose((wm[:, None] * xi**4).sum(0), 3.0, rtol=1e-13, atol=0)
    assert (unscented().alpha, unscented().beta, unscented().kappa) == (1.0, 2.0, 0.0)
    assert (julier().alpha, julier().beta, julier().kappa) == (1.0, 0.0, 1.0)
    # Gauss-Hermite: a product rule, exact for x_i^a x_j^b with a, b <= 2 order - 1 each
    xi, wm, _ = (a.numpy() for a in gauss_hermite(3).points(2))
    assert (wm * xi[:, 0] ** 4 * xi[:, 1] ** 4).sum() == pytest.approx(9.0, abs=1e-12)


def test_points_handed_out_do_not_share_memory_with_the_cached_rule():
    # the rule's points are cached per n; the tensors returned were views of the cached arrays,
    # so editing them in place changed every later call (weights 0.5 instead of 0.25 here)
    for rule in (cubature(), unscented(0.7, 2.0, 1.0), gauss_hermite(3)):
        xi, wm, wc = rule.points(2)
        ref = [a.clone() for a in (xi, wm, wc)]
        xi.mul_(3.0), wm.mul_(2.0), wc.zero_()
        for a, b in zip(rule.points(2), ref):
            assert torch.equal(a, b)


@pytest.mark.parametrize("n", [0, -1, 2.0, True, "2"])
def test_a_bad_dimension_is_refused_by_name(n):
    # (was ZeroDivisionError, 'math domain error', 'need at least one array to stack', a
    # 3-point rule for n=True, or an empty rule for julier(None) at n=0)
    for rule in (cubature(), unscented(), julier(None), gauss_hermite(3)):
        with pytest.raises(ValueError, match=r"n \(the state dimension\) must be an int >= 1"):
            rule.points(n)
    assert gauss_hermite(2).points(np.int64(2))[0].shape == (4, 2)
