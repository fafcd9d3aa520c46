"""Audit of the resamplers (``filters.resampling``) and the sequence loop (``filters.sequence``,
``filters.run``) against exact references.

- Resamplers: the documented inverse-CDF points drawn from the generator's own uniforms and
  looked up row by row with NumPy; ``E[N_i] = N w_i`` by averaging the offspring counts over a
  fine grid of the shared uniform (a step function with at most two jumps per particle: the
  grid mean is within ``2 / M`` of the exact one); floor/ceil counts where guaranteed.
- Runs: a plain NumPy Kalman filter written here (observed components of partially missing
  vectors, per-step controls, a time-varying transition, batch dims) to 1e-12.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import ckf, ekf, forecast, run, scan, sckf
from prognos_torch.filters import resampling as rs
from prognos_torch.filters.resampling import (
    ess,
    multinomial,
    residual,
    stratified,
    systematic,
)

sys.path.insert(0, str(Path(__file__).parent))
from _kalman_reference import kalman_filter_observed  # noqa: E402

F64 = torch.float64
SCHEMES = {
    "multinomial": multinomial,
    "stratified": stratified,
    "systematic": systematic,
    "residual": residual,
}
t = lambda a: torch.as_tensor(a, dtype=F64)  # noqa: E731
gen = lambda s: torch.Generator().manual_seed(s)  # noqa: E731


def _counts(anc: torch.Tensor, N: int) -> np.ndarray:
    return torch.nn.functional.one_hot(anc, N).sum(-2).numpy()


def _lookup_rows(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Each row alone: ``min(#{i : cdf_i <= u_j}, N - 1)`` with ``cdf = cumsum(w) / sum(w)``."""
    w2, u2 = w.reshape(-1, w.shape[-1]), u.reshape(-1, u.shape[-1])
    out = np.empty(u2.shape, dtype=np.int64)
    for b in range(w2.shape[0]):
        c = np.cumsum(w2[b])
        out[b] = np.minimum(np.searchsorted(c / c[-1], u2[b], side="right"), w.shape[-1] - 1)
    return out.reshape(u.shape)


# ---------------------------------------------------------------------- resampling references
def test_draws_are_the_documented_points_row_by_row_and_the_generator_alone_fixes_them():
    g = gen(1)
    w = torch.rand(3, 2, 9, generator=g, dtype=F64)
    w[0, 1, :4] = 0.0  # zero-weight particles
    lw = w.log()  # -inf log-weights there
    N, eps = 9, torch.finfo(F64).eps
    j = np.arange(N)
    for name in ("multinomial", "stratified", "systematic"):
        for arg, log in ((lw, True), (w, False), (7.0 * w, False)):  # (un-normalised)
            got = SCHEMES[name](arg, gen(5), log=log)
            assert torch.equal(got, SCHEMES[name](arg, gen(5), log=log))  # the seed alone
            if name == "systematic":
                U = torch.rand(3, 2, 1, generator=gen(5), dtype=F64).numpy()
            else:
                U = torch.rand(3, 2, N, generator=gen(5), dtype=F64).numpy()
            u = U if name == "multinomial" else np.minimum((j + U) / N, 1.0 - eps)
            want = _lookup_rows(w.numpy(), u)
            assert np.array_equal(got.numpy(), want), name
            assert not bool((got[0, 1] < 4).any())  # zero weight: never an ancestor


def test_expected_offspring_is_n_w_over_a_grid_of_the_shared_uniform():
    """Systematic (and, by linearity, stratified) points at ``(j + U) / N``: the mean count over
    the midpoints of ``M`` cells of ``U`` is within ``2 / M`` of ``N w_i``; every count is
    ``floor(N w_i)`` or ``ceil(N w_i)``; the ancestors are sorted."""
    w = np.array([0.31, 0.0, 0.02, 0.17, 0.25, 0.125, 0.001, 0.124])
    N, M = len(w), 4000
    U = ((np.arange(M) + 0.5) / M)[:, None]
    anc = rs._lookup(rs._cdf(t(w)), t((np.arange(N) + U) / N))  # (M, N)
    c = _counts(anc, N)
    assert np.all(np.abs(c.mean(0) - N * w) <= 2.0 / M + 1e-12)
    assert np.all((c == np.floor(N * w)) | (c == np.ceil(N * w)))
    assert bool((anc[:, 1:] >= anc[:, :-1]).all())
    # the public function gives one of these rows: the one at its own uniform
    got = systematic(t(w), gen(3), log=False)
    u0 = float(torch.rand(1, generator=gen(3), dtype=F64))
    want = _lookup_rows(w, np.minimum((np.arange(N) + u0) / N, 1 - 2.0**-52)[None])[0]
    assert np.array_equal(got.numpy(), want)


def test_residual_counts_exceed_the_floors_and_sum_to_n():
    w = np.array([[0.31, 0.0, 0.02, 0.17, 0.25, 0.125, 0.001, 0.124], [0.5, 0.5, 0, 0, 0, 0, 0, 0]])
    anc = residual(t(w).expand(2000, 2, 8), gen(4), log=False)
    c = _counts(anc, 8)
    assert np.all(c >= np.floor(8 * w)) and np.all(c.sum(-1) == 8)
    assert np.all(c[:, 1] == [4, 4, 0, 0, 0, 0, 0, 0])  # no residual draw
    assert np.all(c[:, 0, 1] == 0)  # zero weight
    # E[N_i] = N w_i: residual draws multinomial on (N w_i - floor) / R, R = 3 here
    frac = 8 * w[0] - np.floor(8 * w[0])
    sd = np.sqrt(3 * frac / 3 * (1 - frac / 3) / 2000)
    assert np.all(np.abs(c[:, 0].mean(0) - 8 * w[0]) <= 4.5 * sd + 1e-12)


@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_degenerate_weight_vectors(name):
    f = SCHEMES[name]
    assert f(t([-3.0]), gen(0)).tolist() == [0]  # one particle
    assert f(t([2.5]), gen(0), log=False).tolist() == [0]
    one = t([-math.inf, -math.inf, 4.0, -math.inf])  # all weight on one particle
    assert f(one, gen(0)).tolist() == [2] * 4
    assert f(t([0.0, 0.0, 1e-300, 0.0]), gen(0), log=False).tolist() == [2] * 4
    anc = f(torch.randn(5, 6, generator=gen(1), dtype=F64), gen(2))
    assert anc.shape == (5, 6) and anc.dtype == torch.int64
    assert bool(((anc >= 0) & (anc < 6)).all())


@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_bad_weights_are_refused_by_name(name):
    f = SCHEMES[name]
    with pytest.raises(ValueError, match="finite and non-negative"):
        f(t([0.5, float("nan")]), gen(0), log=False)
    with pytest.raises(ValueError, match="finite and non-negative"):
        f(t([0.5, -0.1]), gen(0), log=False)
    with pytest.raises(ValueError, match="sum to zero"):
        f(t([[1.0, 2.0], [0.0, 0.0]]), gen(0), log=False)
    with pytest.raises(ValueError, match="NaN or \\+inf"):
        f(t([0.0, math.inf]), gen(0))
    with pytest.raises(ValueError, match="-inf for every particle"):
        f(t([[0.0, 1.0], [-math.inf, -math.inf]]), gen(0))
    with pytest.raises(TypeError, match="floating-point"):
        f(torch.tensor([1, 2]), gen(0), log=False)


# ---------------------------------------------------------------------- resampling fixes
@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_weights_whose_sum_overflows_resample_as_their_scaled_copy(name):
    """``[1e308, 1e308, 0]`` summed to inf: the probabilities were 0, the cdf NaN, and every
    ancestor the zero-weight particle 2. They are ``[1, 1, 0]`` scaled."""
    f = SCHEMES[name]
    big = t([[1e308, 1e308, 0.0], [0.2, 0.3, 0.5]])
    got = f(big, gen(7), log=False)
    assert torch.equal(got, f(t([[1.0, 1.0, 0.0], [0.2, 0.3, 0.5]]), gen(7), log=False))
    assert not bool((got[0] == 2).any())


@pytest.mark.parametrize("name", sorted(SCHEMES))
@pytest.mark.parametrize("N", [5, 3000])
def test_an_empty_batch_gives_empty_ancestors(name, N):
    """Weights ``(0, N)`` with ``log=False`` failed in ``amin()`` ('Expected reduction dim'),
    residual and the counting systematic path failed with log-weights too."""
    for log in (True, False):
        anc = SCHEMES[name](torch.zeros(0, N, dtype=F64), gen(0), log=log)
        assert anc.shape == (0, N) and anc.dtype == torch.int64


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("name", ["systematic", "stratified", "residual"])
def test_half_precision_weights_keep_the_floor_ceil_counts(name, dtype):
    """Half precision holds integers only to 2048 (bfloat16: 256): systematic counts of 3000
    float16 weights were off by 2 and bfloat16 ones indexed out of range (3008 of 3001); from
    8192 particles the residual and stratified NumPy look-ups refused bfloat16. The weights here are integers
    (exact in both dtypes), so ``N w_i`` is known exactly."""
    N = 9000  # (past _COUNT_MIN and _NUMPY_SEARCH_MIN)
    k = torch.randint(1, 9, (N,), generator=gen(3)).to(dtype)
    anc = SCHEMES[name](k, gen(4), log=False)
    assert anc.shape == (N,) and bool(((anc >= 0) & (anc < N)).all())
    Nw = N * k.double().numpy() / float(k.double().sum())
    c = np.bincount(anc.numpy(), minlength=N)
    if name == "systematic":
        assert np.all((c >= np.floor(Nw - 1e-9)) & (c <= np.ceil(Nw + 1e-9)))
    elif name == "residual":
        assert np.all(c >= np.floor(Nw - 1e-9))
    else:  # stratified: each stratum's point in the particle's interval, |N_i - N w_i| < 2
        assert np.all(np.abs(c - Nw) < 2.0)
    assert c.sum() == N


def test_ess_of_far_from_zero_log_weights_is_exact():
    """``2 logsumexp(l) - logsumexp(2 l)`` cancelled: float32 log-weights ``[-1e4, -1e4 - 1]``
    gave 1.64872 (exact 1.64805), and ``[1e308, 1e308]`` NaN (``2 l`` overflowed)."""
    exact = (1 + math.exp(-1)) ** 2 / (1 + math.exp(-2))
    for off in (0.0, -1e4, -1e6):
        got = ess(torch.tensor([off, off - 1.0], dtype=torch.float32))
        assert abs(float(got) / exact - 1) < 1e-6, off
    assert float(ess(t([1e308, 1e308]))) == pytest.approx(2.0, rel=1e-15)
    w = t([0.5, 0.25, 0.125, 0.125, 0.0])
    assert float(ess(w.log() - 700.0)) == pytest.approx(1.0 / float((w * w).sum()), rel=1e-12)


def test_ess_refuses_what_has_no_weights():
    """NaN, +inf or all -inf log-weights gave an ESS of NaN, silently; an empty particle axis
    NaN too."""
    with pytest.raises(ValueError, match="log_w must not contain NaN"):
        ess(t([0.0, float("nan")]))
    with pytest.raises(ValueError, match="log_w must not contain NaN or \\+inf"):
        ess(t([0.0, math.inf]))
    with pytest.raises(ValueError, match="log_w are -inf for every particle"):
        ess(t([[0.0, 1.0], [-math.inf, -math.inf]]))
    with pytest.raises(ValueError, match=r"log_w must be a tensor of shape \(\.\.\., N\)"):
        ess(torch.zeros(3, 0, dtype=F64))
    assert ess(torch.zeros(0, 4, dtype=F64)).shape == (0,)


# ---------------------------------------------------------------------- runs: references
def _setup(k0: int):
    rng = np.random.default_rng(0)
    n, m, p, T, bs = 3, 2, 2, 7, (2, 3)
    F0 = rng.normal(size=(n, n)) * 0.3 + 0.6 * np.eye(n)
    H = rng.normal(size=(m, n))
    Bm = rng.normal(size=(n, p))
    LQ = np.tril(rng.normal(size=(n, n))) * 0.2 + 0.5 * np.eye(n)
    LR = np.tril(rng.normal(size=(m, m))) * 0.2 + 0.7 * np.eye(m)
    F_of = lambda k: F0 + 0.05 * k * np.eye(n)  # noqa: E731  (time-varying: checks k)
    Ft = t(F0)

    def f(x, u, k):
        return (Ft + 0.05 * k * torch.eye(n, dtype=F64)) @ x + t(Bm) @ u

    model = StateSpaceModel(
        f=f,
        h=lambda x, u, k: t(H) @ x,
        state_dim=n,
        obs_dim=m,
        chol_Q=t(LQ),
        chol_R=t(LR),
        control_dim=p,
        jac_f=lambda x, u, k: Ft + 0.05 * k * torch.eye(n, dtype=F64),
        jac_h=lambda x, u, k: t(H),
    )  # fmt: skip  (analytic Jacobians: the EKF's autodiff warm-up takes seconds)
    m0 = rng.normal(size=bs + (n,))
    L0 = np.tril(rng.normal(size=(n, n))) * 0.3 + np.eye(n)
    ys = rng.normal(size=(T,) + bs + (m,))
    ys[2] = np.nan  # a missing step
    ys[4, 0, 1, 1] = np.nan  # partially missing vectors
    ys[5, 1, 2, 0] = np.nan
    us = rng.normal(size=(T,) + bs + (p,))
    F_k = lambda k: F_of(k + k0)  # noqa: E731
    return model, (F_k, H, LQ @ LQ.T, LR @ LR.T, Bm), m0, L0, ys, us


@pytest.mark.parametrize("factory", [ckf, ekf, sckf])
@pytest.mark.parametrize("shared_u", [False, True])
def test_run_is_a_plain_kalman_filter_with_missing_steps_inputs_and_batch_dims(factory, shared_u):
    k0 = 2
    model, (F_k, H, Q, R, Bm), m0, L0, ys, us = _setup(k0)
    if shared_u:
        us = np.ascontiguousarray(us[:, 0, 0])  # (T, p): one control row for the batch
    init = GaussianBelief(t(m0), t(L0).expand(2, 3, 3, 3).clone())
    tr = run(factory(), model, init, t(ys), t(us), k0=np.int64(k0))
    T = ys.shape[0]
    assert tr.means.shape == (T, 2, 3, 3) and tr.chols.shape == (T, 2, 3, 3, 3)
    assert tr.pred_means.shape == (T, 2, 3, 3) and tr.innovations.shape == (T, 2, 3, 2)
    assert tr.chol_innovations.shape == (T, 2, 3, 2, 2)
    assert tr.log_likelihoods.shape == (T, 2, 3) and tr.nis.shape == (T, 2, 3)
    assert tr.log_likelihood.shape == (2, 3) and tr.chol_Q is None
    for i in range(2):
        for j in range(3):
            u_ij = us if shared_u else us[:, i, j]
            mm, PP, ll = kalman_filter_observed(
                F_k, H, Q, R, m0[i, j], L0 @ L0.T, ys[:, i, j], Bm, u_ij
            )
            assert np.allclose(tr.means[:, i, j].numpy(), mm, rtol=0, atol=1e-12)
            assert np.allclose(tr.covs[:, i, j].numpy(), PP, rtol=0, atol=1e-12)
            assert np.allclose(tr.log_likelihoods[:, i, j].numpy(), ll, rtol=0, atol=1e-12)
    assert bool(torch.isnan(tr.nis[2]).all()) and bool((tr.log_likelihoods[2] == 0).all())


def test_forecast_is_the_kalman_prediction():
    k0 = 1
    model, (F_k, H, Q, R, Bm), m0, L0, _, us = _setup(k0)
    init = GaussianBelief(t(m0[0, 0]), t(L0))
    fc = forecast(ckf(), model, init, 4, t(us[:4, 0, 0]), k0=k0)
    m, P = m0[0, 0], L0 @ L0.T
    for h in range(4):
        F = F_k(h + 1)
        m, P = F @ m + Bm @ us[h, 0, 0], F @ P @ F.T + Q
        assert np.allclose(fc.means[h].numpy(), m, rtol=0, atol=1e-12)
        assert np.allclose((fc.chols[h] @ fc.chols[h].mT).numpy(), P, rtol=0, atol=1e-12)
        assert np.allclose(fc.y_means[h].numpy(), H @ m, rtol=0, atol=1e-12)
        Sy = (fc.y_chols[h] @ fc.y_chols[h].mT).numpy()
        assert np.allclose(Sy, H @ P @ H.T + R, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------- runs: bad input
def _small():
    model, _, m0, L0, ys, us = _setup(0)
    return model, GaussianBelief(t(m0), t(L0).expand(2, 3, 3, 3).clone()), t(ys), t(us)


@pytest.mark.parametrize("k0", [True, "0", None, 1.0, -1])
def test_run_and_forecast_name_a_k0_that_is_not_a_non_negative_int(k0):
    """``k0=True`` ran as ``k0 = 1``; text and ``None`` failed in ``k0 + 1`` ('can only
    concatenate str')."""
    model, init, ys, us = _small()
    with pytest.raises(ValueError, match="k0 must be a non-negative int"):
        run(ckf(), model, init, ys, us, k0=k0)
    with pytest.raises(ValueError, match="k0 must be a non-negative int"):
        forecast(ckf(), model, init, 2, us[:2], k0=k0)


def test_a_resumed_state_of_another_state_dimension_is_named():
    """A :class:`FilterState` for ``n = 3`` resumed on a model with ``n = 2`` failed inside the
    model ('mat1 and mat2 shapes cannot be multiplied')."""
    model, init, ys, us = _small()
    other = StateSpaceModel(
        f=lambda x, u, k: x, h=lambda x, u, k: x, state_dim=2, obs_dim=2,
        chol_Q=t(np.eye(2)), chol_R=t(np.eye(2)),
    )  # fmt: skip
    state = ckf().init(other, GaussianBelief(t(np.zeros(2)), t(np.eye(2))))
    with pytest.raises(ValueError, match=r"init.belief.mean must have shape \(\.\.\., 3\)"):
        run(ckf(), model, state, ys[:, 0, 0], us[:, 0, 0])
    with pytest.raises(ValueError, match=r"init.belief.mean must have shape \(\.\.\., 3\)"):
        forecast(ckf(), model, state, 2, us[:2, 0, 0])


def test_run_names_non_finite_ys_and_us():
    """inf in ``ys`` and NaN in ``us`` were reported as the step's ``y`` and ``u``."""
    model, init, ys, us = _small()
    bad = ys.clone()
    bad[3, 1, 1, 0] = math.inf
    with pytest.raises(ValueError, match="ys contains inf"):
        run(ckf(), model, init, bad, us)
    bad = us.clone()
    bad[5, 0, 2, 1] = math.nan
    with pytest.raises(ValueError, match="us contains non-finite"):
        run(ckf(), model, init, ys, bad)
    with pytest.raises(ValueError, match="us contains non-finite"):
        forecast(ckf(), model, init, 6, bad[:6])


def test_forecast_names_controls_for_a_model_without_them():
    """Controls for a model with ``control_dim = 0`` were refused as the step's ``u``."""
    _, init, _, us = _small()
    model = StateSpaceModel(
        f=lambda x, u, k: x, h=lambda x, u, k: x[:2], state_dim=3, obs_dim=2,
        chol_Q=t(np.eye(3)), chol_R=t(np.eye(2)),
    )  # fmt: skip
    with pytest.raises(ValueError, match="us was given but the model has control_dim=0"):
        forecast(ckf(), model, init, 2, us[:2])


def test_scan_names_its_bad_arguments():
    """A float ``k0`` reached the step as ``k = 2.5`` and ``None`` failed in ``k0 + t + 1``; a
    0-dim ``ys`` (a tensor) was called not a tensor; a ``record`` giving no mapping failed on
    ``.items()``."""
    step = lambda s, y, u, k: (s, k)  # noqa: E731
    rec = lambda s, k: {"k": torch.tensor(k)}  # noqa: E731
    ys = torch.zeros(2, 1, dtype=F64)
    for k0 in (1.5, None, True, -1):
        with pytest.raises(ValueError, match="k0 must be a non-negative int"):
            scan(step, 0, ys, record=rec, k0=k0)
    assert scan(step, 0, ys, record=rec, k0=np.int64(3))[1]["k"].tolist() == [4, 5]
    with pytest.raises(ValueError, match=r"ys must have shape \(T, \.\.\., m\).*got \(\)"):
        scan(step, 0, torch.tensor(1.0), record=rec)
    with pytest.raises(TypeError, match="record must return a mapping"):
        scan(step, 0, ys, record=lambda s, k: 5)
