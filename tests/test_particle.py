"""Particle filters and resamplers against exact references.

- Linear-Gaussian models: SIR, EKPF and UPF posterior means against a plain NumPy Kalman filter
  (``tests/_kalman_reference.py`` and an independent per-step-noise version below), within a
  Monte Carlo tolerance ``K_MC * posterior std / sqrt(ESS)``.
- Resamplers: offspring counts against their exact expectation ``N w_i`` and exact variances.
- A saltatory (jump) state: the strong-tracking PF of paper 002 against SIR and EKPF.
"""

import math
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from prognos_torch.adapt.strong_tracking import StrongTrackingState
from prognos_torch.core import GaussianBelief, StateSpaceModel, linear_gaussian_model
from prognos_torch.filters import (
    FilterState,
    ParticleFilter,
    ekf,
    ekpf,
    make_particle_filter,
    sir,
    stpf,
    upf,
)
from prognos_torch.filters.particle import (
    ParticleState,
    ProposalFallbackWarning,
    WeightCollapseWarning,
    gather_particles,
    where_particles,
)
from prognos_torch.filters.resampling import (
    ess,
    get_resampler,
    multinomial,
    normalize_log_weights,
    residual,
    stratified,
    systematic,
)

sys.path.insert(0, str(Path(__file__).parent))
from _kalman_reference import kalman_filter  # noqa: E402

t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
gen = lambda s: torch.Generator().manual_seed(s)  # noqa: E731

# Monte Carlo tolerance: |mean_PF - mean_KF| <= K_MC * std_KF / sqrt(ESS) at every step. For an
# importance sampler the standard error of the weighted mean is about std / sqrt(ESS); resampling
# adds correlated noise on top (path degeneracy), so the ratio is not N(0, 1): over 4 seeds x
# 4 filters x 60 compared values the largest observed |error| / (std / sqrt(ESS)) was 5.0.
# A wrong weight (e.g. the proposal PF without its p(x|x_prev) / q factor) gives ratios > 50.
K_MC = 7.0


# ---------------------------------------------------------------------- linear-Gaussian models
def _lgssm_2d():
    F = np.array([[0.95, 0.1], [-0.1, 0.9]])
    H = np.array([[1.0, 0.5]])
    LQ = np.array([[0.4, 0.0], [0.1, 0.3]])
    LR = np.array([[0.6]])
    q, r = np.array([0.05, -0.02]), np.array([0.1])
    m0, P0 = np.array([0.5, -0.3]), np.diag([1.0, 0.5])
    return F, H, LQ, LR, q, r, m0, P0


def _simulate(F, H, LQ, LR, q, r, m0, P0, T, seed):
    rng = np.random.default_rng(seed)
    x = m0 + np.linalg.cholesky(P0) @ rng.normal(size=len(m0))
    ys = []
    for _ in range(T):
        x = F @ x + q + LQ @ rng.normal(size=len(m0))
        ys.append(H @ x + r + LR @ rng.normal(size=H.shape[0]))
    return np.array(ys)


@pytest.mark.parametrize("factory", [sir, ekpf, upf])
def test_linear_gaussian_matches_kalman(factory):
    F, H, LQ, LR, q, r, m0, P0 = _lgssm_2d()
    T = 30
    ys = _simulate(F, H, LQ, LR, q, r, m0, P0, T, seed=3)
    ys[[8, 9, 20]] = np.nan  # missing: propagate only
    means, covs, ll = kalman_filter(F, H, LQ @ LQ.T, LR @ LR.T, m0, P0, ys, q=q, r=r)
    model = linear_gaussian_model(t(F), t(H), t(LQ), t(LR), q=t(q), r=t(r))
    pf = factory(20000, resample_threshold=0.5)
    tr = pf.run(model, GaussianBelief.from_cov(t(m0), t(P0)), t(ys), generator=gen(0))
    std = np.sqrt(np.diagonal(covs, axis1=1, axis2=2))
    tol = K_MC * std / np.sqrt(tr.ess.numpy())[:, None]
    err = np.abs(tr.means.numpy() - means)
    assert np.all(err <= tol), (err / (std / np.sqrt(tr.ess.numpy())[:, None])).max()
    # posterior spread: relative error of a variance estimate ~ sqrt(2 / ESS)
    rel = np.abs(tr.stds.numpy() ** 2 / std**2 - 1.0)
    assert np.all(rel <= K_MC * np.sqrt(2.0 / tr.ess.numpy())[:, None] + 0.02)
    # missing steps: no reweighting, zero log-likelihood contribution
    assert bool(tr.missing[[8, 9, 20]].all()) and int(tr.missing.sum()) == 3
    assert np.all(tr.log_likelihoods.numpy()[[8, 9, 20]] == 0.0)
    # log p(y_{1:T}) estimate (SIR: unbiased in p; proposal PFs too); within 0.3 nats of exact
    assert abs(float(tr.log_likelihood) - ll) < 0.3
    assert tr.means.shape == (T, 2) and tr.covs.shape == (T, 2, 2)


def _kf_per_step(F, H, Q_of, R_of, q_of, r_of, m0, P0, ys):
    """Independent NumPy KF with per-step noise (k = 1..T)."""
    m, P, out = m0.copy(), P0.copy(), []
    for k, y in enumerate(ys, start=1):
        m = F @ m + q_of(k)
        P = F @ P @ F.T + Q_of(k)
        S = H @ P @ H.T + R_of(k)
        K = P @ H.T @ np.linalg.inv(S)
        m = m + K @ (y - H @ m - r_of(k))
        P = (np.eye(len(m)) - K @ H) @ P
        out.append((m.copy(), np.sqrt(np.diag(P))))
    return np.array([o[0] for o in out]), np.array([o[1] for o in out])


@pytest.mark.parametrize("factory", [sir, stpf])
def test_batched_runs_and_per_step_noise(factory):
    """Leading batch dims (3 runs), per-run and per-step noise callables with means."""
    B, T, N = 3, 15, 4000
    F, H = np.array([[0.9]]), np.array([[1.0]])
    sq = np.array([0.3, 0.5, 0.8])  # per-run process noise

    def chol_Q(k):
        return t(sq * (1.0 + 0.05 * k)).reshape(B, 1, 1)

    def chol_R(k):
        return t([[0.5 + 0.02 * k]])

    q_of = lambda k: t([0.1 * math.sin(k)])  # noqa: E731
    r_of = lambda k: t([-0.2]).expand(B, 1)  # noqa: E731
    model = StateSpaceModel(
        f=lambda x, u, k: 0.9 * x,
        h=lambda x, u, k: x,
        state_dim=1,
        obs_dim=1,
        chol_Q=chol_Q,
        chol_R=chol_R,
        q=q_of,
        r=r_of,
    )
    rng = np.random.default_rng(5)
    ys = rng.normal(size=(T, B, 1))
    m0, P0 = np.zeros((B, 1)), np.ones((B, 1, 1))
    pf = factory(N, resample_threshold=0.5)
    tr = pf.run(model, GaussianBelief(t(m0), t(P0)), t(ys), generator=gen(1))
    for b in range(B):
        ref_m, ref_s = _kf_per_step(
            F,
            H,
            lambda k, b=b: np.array([[(sq[b] * (1 + 0.05 * k)) ** 2]]),
            lambda k: np.array([[(0.5 + 0.02 * k) ** 2]]),
            lambda k: q_of(k).numpy(),
            lambda k: np.array([-0.2]),
            m0[b],
            P0[b],
            ys[:, b],
        )
        tol = K_MC * ref_s / np.sqrt(tr.ess[:, b].numpy())[:, None]
        # STPF targets the same posterior, but its inflated proposal makes the weights far more
        # variable than the ESS suggests early on; allow it twice the SIR tolerance
        tol = tol * (1.0 if pf.proposal is None else 2.0)
        assert np.all(np.abs(tr.means[:, b].numpy() - ref_m) <= tol)
    assert tr.ess.shape == (T, B) and tr.resampled.shape == (T, B)


@pytest.mark.parametrize("factory", [sir, ekpf])
def test_controls_per_run_and_kept_particles(factory):
    """Controls ``(T, B, p)`` per run: x_k = 0.8 x_{k-1} + 0.5 u_k + w_k (KF with q_k = B u_k)."""
    B, T, N = 2, 12, 4000
    model = linear_gaussian_model(t([[0.8]]), t([[1.0]]), t([[0.4]]), t([[0.5]]), B=t([[0.5]]))
    rng = np.random.default_rng(7)
    us = rng.normal(size=(T, B, 1)) * 2.0
    ys = rng.normal(size=(T, B, 1)) + us
    b0 = GaussianBelief(
        torch.zeros(B, 1, dtype=torch.float64), torch.ones(B, 1, 1, dtype=torch.float64)
    )
    pf = factory(N)
    tr = pf.run(model, b0, t(ys), t(us), generator=gen(3), keep_particles=True)
    for b in range(B):
        ref_m, ref_s = _kf_per_step(
            np.array([[0.8]]),
            np.array([[1.0]]),
            lambda k: np.array([[0.16]]),
            lambda k: np.array([[0.25]]),
            lambda k, b=b: 0.5 * us[k - 1, b],
            lambda k: np.zeros(1),
            np.zeros(1),
            np.eye(1),
            ys[:, b],
        )
        tol = K_MC * ref_s / np.sqrt(tr.ess[:, b].numpy())[:, None]
        assert np.all(np.abs(tr.means[:, b].numpy() - ref_m) <= tol)
    # the kept weighted particle sets reproduce the reported estimates exactly
    assert tr.particles.shape == (T, B, N, 1) and tr.log_weights.shape == (T, B, N)
    W = tr.log_weights.exp()
    assert torch.allclose((W.unsqueeze(-1) * tr.particles).sum(-2), tr.means, atol=1e-12)
    with pytest.raises(ValueError, match="us must have shape"):
        pf.run(model, b0, t(ys), generator=gen(3))


def test_predict_and_state_consistency():
    F, H, LQ, LR, q, r, m0, P0 = _lgssm_2d()
    model = linear_gaussian_model(t(F), t(H), t(LQ), t(LR), q=t(q), r=t(r))
    pf = stpf(20000)
    b0 = GaussianBelief.from_cov(t(m0), t(P0))
    g = gen(4)
    state = pf.init(model, b0, generator=g)
    ys = t(_simulate(F, H, LQ, LR, q, r, m0, P0, 6, seed=9))
    for k in range(1, 7):
        state, info = pf.step(model, state, ys[k - 1], k=k, generator=g)
        # the per-particle Gaussians travel with their particles through resampling
        assert torch.equal(state.proposal.belief.mean, state.particles)
        assert state.proposal.fading.V.shape == (20000, 1, 1)
        assert torch.allclose(torch.logsumexp(state.log_weights, -1), t(0.0), atol=1e-12)
    # predict: E[x_{k+1}] = F E[x_k] + q, weights unchanged
    W = state.log_weights.exp()
    m_now = (W[:, None] * state.particles).sum(0)
    pred = pf.predict(model, state, k=7, generator=g)
    m_pred = (W[:, None] * pred.particles).sum(0)
    se = LQ.diagonal().max() / math.sqrt(float(ess(state.log_weights)))
    assert torch.allclose(m_pred, t(F) @ m_now + t(q), atol=5 * se)
    assert torch.equal(pred.log_weights, state.log_weights)


@pytest.mark.parametrize("factory", [sir, ekpf, upf, stpf])
def test_predict_equals_a_step_with_a_missing_measurement(factory):
    """predict moved the particles but kept each particle's Gaussian factor of the last update,
    so a step after a prediction proposed from a factor that had not grown by Q (EKPF, UPF,
    STPF: the next particles differed by 0.15-1.6 from those after a missing-measurement step)."""
    F, H, LQ, LR, q, r, m0, P0 = _lgssm_2d()
    model = linear_gaussian_model(t(F), t(H), t(LQ), t(LR), q=t(q), r=t(r))
    pf = factory(40)
    b0 = GaussianBelief.from_cov(t(m0).expand(3, 2), t(P0).expand(3, 2, 2))
    state = pf.init(model, b0, generator=gen(2))
    state, _ = pf.step(model, state, t([[0.7], [0.1], [1.2]]), k=1, generator=gen(3))
    pred = pf.predict(model, state, k=2, generator=gen(4))
    miss, _ = pf.step(model, state, t([[math.nan]] * 3), k=2, generator=gen(4))
    for a, b in ((pred, miss), *(
        (pf.step(model, pred, t([[1.5], [0.2], [2.0]]), k=3, generator=gen(5))[0],
         pf.step(model, miss, t([[1.5], [0.2], [2.0]]), k=3, generator=gen(5))[0]),
    )):  # fmt: skip
        assert torch.equal(a.particles, b.particles)
        # (a step renormalises the unchanged weights: equal up to rounding)
        torch.testing.assert_close(a.log_weights, b.log_weights, rtol=0, atol=1e-14)
        if factory is not sir:
            assert torch.equal(a.proposal.belief.chol, b.proposal.belief.chol)
    if factory in (ekpf, upf):  # the factor grew: P_pred = F P F^T + Q per particle (exact)
        P = state.proposal.belief.chol @ state.proposal.belief.chol.mT
        Pp = pred.proposal.belief.chol @ pred.proposal.belief.chol.mT
        want = t(F) @ P @ t(F).T + t(LQ) @ t(LQ).T
        torch.testing.assert_close(Pp, want, rtol=1e-12, atol=1e-12)


def test_reproducible_with_generator():
    model = linear_gaussian_model(t([[1.0]]), t([[1.0]]), t([[0.2]]), t([[0.5]]))
    ys = torch.randn(10, 1, generator=gen(2), dtype=torch.float64)
    b0 = GaussianBelief(t([0.0]), t([[1.0]]))
    a = stpf(300).run(model, b0, ys, generator=gen(11))
    b = stpf(300).run(model, b0, ys, generator=gen(11))
    c = stpf(300).run(model, b0, ys, generator=gen(12))
    assert torch.equal(a.means, b.means) and torch.equal(a.ess, b.ess)
    assert not torch.equal(a.means, c.means)


def _jump_model(batched: bool, calls: list | None = None):
    """``x + 0.01 sin x``, observed directly; with ``calls`` the analytic Jacobians record the
    shapes they are called with."""
    f = lambda x, u, k: x + 0.01 * torch.sin(x)  # noqa: E731
    h = lambda x, u, k: x  # noqa: E731
    kw = {}
    if calls is not None:

        def jac_f(x, u, k):
            calls.append(("f", tuple(x.shape)))
            return (1.0 + 0.01 * torch.cos(x)).unsqueeze(-1)

        def jac_h(x, u, k):
            calls.append(("h", tuple(x.shape)))
            return torch.ones_like(x).unsqueeze(-1)

        kw = dict(jac_f=jac_f, jac_h=jac_h)
    return StateSpaceModel(
        f=f,
        h=h,
        state_dim=1,
        obs_dim=1,
        chol_Q=t([[0.05]]),
        chol_R=t([[0.3]]),
        batched=batched,
        **kw,
    )


@pytest.mark.parametrize("factory", [ekpf, stpf])
def test_batched_closed_form_jacobians_are_used_without_vmap(factory, monkeypatch):
    """A model with ``batched=True`` and ``jac_f``/``jac_h``: each step calls them once on the
    whole ``(runs, N, n)`` particle batch, never ``vmap(jacfwd)``, and filters as the per-sample
    model does (whose Jacobians come from ``jacfwd``)."""
    import prognos_torch.core.model as model_mod

    N, T = 64, 12
    ys = torch.cumsum(0.1 * torch.randn(T, 2, 1, generator=gen(3), dtype=torch.float64), 0)
    b0 = GaussianBelief(torch.zeros(2, 1, dtype=torch.float64), t([[0.5]]).expand(2, 1, 1))
    ref = factory(N).run(_jump_model(False), b0, ys, generator=gen(4))

    def no_autodiff(*a, **k):
        raise AssertionError("vmap(jacfwd) used although the model gives batched Jacobians")

    monkeypatch.setattr(model_mod, "_jacobian", no_autodiff)
    monkeypatch.setattr(model_mod, "vmap", no_autodiff)
    calls: list = []
    out = factory(N).run(_jump_model(True, calls), b0, ys, generator=gen(4))
    assert calls.count(("f", (2, N, 1))) == T and calls.count(("h", (2, N, 1))) == T
    assert len(calls) == 2 * T
    torch.testing.assert_close(out.means, ref.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.log_likelihoods, ref.log_likelihoods, rtol=0, atol=1e-9)


@pytest.mark.parametrize("factory", [sir, stpf])
def test_run_equals_its_checked_steps(factory):
    """``run`` checks once and then steps without the checks: the same numbers as calling the
    public ``step`` (which checks every call) in a loop, with missing rows and controls."""
    f = lambda x, u, k: 0.9 * x + 0.1 * u  # noqa: E731
    model = StateSpaceModel(
        f=f,
        h=lambda x, u, k: x,
        state_dim=1,
        obs_dim=1,
        chol_Q=t([[0.1]]),
        chol_R=lambda k: t([[0.2 + 0.01 * k]]),
        control_dim=1,
    )
    T = 15
    ys = torch.randn(T, 3, 1, generator=gen(5), dtype=torch.float64)
    ys[4] = float("nan")
    ys[9, 1] = float("nan")
    us = torch.linspace(0.0, 1.0, T, dtype=torch.float64).reshape(T, 1)
    b0 = GaussianBelief(torch.zeros(3, 1, dtype=torch.float64), t([[1.0]]).expand(3, 1, 1))
    pf = factory(300, resample_threshold=0.6)
    tr = pf.run(model, b0, ys, us, generator=gen(6), k0=2)
    g = gen(6)
    state = pf.init(model, b0, generator=g, k=2)
    for i in range(T):
        state, info = pf.step(model, state, ys[i], us[i], 3 + i, generator=g)
        assert torch.equal(info.mean, tr.means[i]) and torch.equal(info.ess, tr.ess[i])
        assert torch.equal(info.missing, tr.missing[i])
    assert torch.equal(state.particles, tr.final.particles)
    assert bool(tr.missing[4].all()) and tr.missing[9].tolist() == [False, True, False]


def test_numpy_and_torch_lookups_agree(monkeypatch):
    """The CPU look-up switches to NumPy's searchsorted for long rows: same indices as
    ``torch.searchsorted`` on sorted and unsorted queries, ties, batches and short queries."""
    import prognos_torch.filters.resampling as rs

    g = gen(8)
    w = torch.rand(3, 5000, generator=g, dtype=torch.float64)
    w[:, ::7] = 0.0  # flat cdf steps (zero-weight particles)
    cdf = rs._cdf(w)
    u_sorted = (torch.arange(5000, dtype=torch.float64) + 0.5) / 5000
    queries = [
        u_sorted.expand(3, 5000),
        torch.rand(3, 5000, generator=g, dtype=torch.float64),
        cdf[:, ::2].contiguous(),  # ties with the cdf values themselves
        torch.rand(3, 17, generator=g, dtype=torch.float64),
    ]
    monkeypatch.setattr(rs, "_NUMPY_SEARCH_MIN", 4096)  # NumPy for these rows
    got = [rs._lookup(cdf, u) for u in queries]
    monkeypatch.setattr(rs, "_NUMPY_SEARCH_MIN", 10**9)  # torch
    for u, a in zip(queries, got):
        assert torch.equal(a, rs._lookup(cdf, u)) and a.dtype == torch.int64


def test_systematic_by_counts_gives_the_search_indices():
    """From ``_COUNT_MIN`` particles a CPU systematic resampling counts offspring instead of
    searching: the same ancestors as the look-up, on peaked, uniform (every ``N cdf_i - U``
    near an integer) and zero-weight rows, batches, and on ``U`` chosen to put the points
    exactly on, one ulp below and one ulp above cdf values (the rounding corrections)."""
    import prognos_torch.filters.resampling as rs

    def searched(cdf, U):
        N = cdf.shape[-1]
        u = (torch.arange(N, dtype=cdf.dtype) + U) / N
        return rs._lookup(cdf, u.clamp_max(1.0 - torch.finfo(cdf.dtype).eps))

    g = gen(21)
    N = 5000
    peaked = torch.softmax(
        -0.5 * ((3.0 * torch.randn(N, generator=g, dtype=torch.float64) - 1) / 0.3) ** 2, -1
    )
    zeros = torch.rand(N, generator=g, dtype=torch.float64)
    zeros[::3] = 0.0
    rows = [peaked, torch.full((N,), 1.0 / N, dtype=torch.float64), zeros / zeros.sum(),
            torch.rand(2, 3, N, generator=g, dtype=torch.float64)]  # fmt: skip
    fixed = 0
    for w in rows:
        cdf = rs._cdf(w / w.sum(-1, keepdim=True))
        Us = [torch.rand(*cdf.shape[:-1], 1, generator=g, dtype=torch.float64) for _ in range(5)]
        # points on a cdf value: U = N cdf_i - j for a middle particle, and its neighbours
        i = N // 2
        on = (cdf[..., i : i + 1] * N) % 1.0
        Us += [
            on,
            torch.nextafter(on, torch.zeros_like(on)),
            torch.nextafter(on, torch.ones_like(on)),
        ]
        Us.append(torch.zeros_like(Us[0]))
        for U in Us:
            got = rs._systematic_by_counts(cdf, U)
            assert got.dtype == torch.int64 and torch.equal(got, searched(cdf, U))
            x = cdf * N - U
            fixed += int(((torch.ceil(x) - x) < 1e-9).sum())  # near-integer cases exercised
    assert fixed > N  # the uniform row and the chosen U put many points on the edge
    # the public function takes that path and draws as before (one uniform per run)
    w = torch.rand(3, N, generator=g, dtype=torch.float64)
    got = systematic(w.log(), gen(4))
    U = torch.rand(3, 1, generator=gen(4), dtype=torch.float64)
    assert torch.equal(got, searched(rs._cdf(w / w.sum(-1, keepdim=True)), U))


# ---------------------------------------------------------------------- resamplers
def _stratified_var(w):
    """Exact offspring variance of stratified resampling: sum over strata of p (1 - p)."""
    N = len(w)
    c = np.concatenate([[0.0], np.cumsum(w)])
    var = np.zeros(N)
    for i in range(N):
        for j in range(N):
            lo, hi = max(c[i], j / N), min(c[i + 1], (j + 1) / N)
            p = max(hi - lo, 0.0) * N
            var[i] += p * (1 - p)
    return var


W_TEST = np.array(
    [[0.31, 0.0, 0.02, 0.17, 0.25, 0.125, 0.001, 0.124], [1 / 8] * 4 + [0.05, 0.2] + [0.125] * 2]
)


def _exact_var(name, w):
    N = len(w)
    Nw = N * w
    frac = Nw - np.floor(Nw)
    if name == "multinomial":
        return N * w * (1 - w)
    if name == "systematic":
        return frac * (1 - frac)
    if name == "residual":
        R = N - np.floor(Nw).sum()
        rw = frac / R if R > 0 else frac
        return R * rw * (1 - rw)
    return _stratified_var(w)


@pytest.mark.parametrize("name", ["multinomial", "systematic", "stratified", "residual"])
@pytest.mark.parametrize("log", [True, False])
def test_resampler_offspring_moments(name, log):
    reps, N = 20000, W_TEST.shape[1]
    w = t(W_TEST).expand(reps, 2, N)
    arg = torch.log(w) if log else w
    anc = get_resampler(name)(arg, gen(21), log=log)
    assert anc.shape == (reps, 2, N) and anc.dtype == torch.int64
    counts = torch.nn.functional.one_hot(anc, N).sum(-2).double().numpy()  # (reps, 2, N)
    assert np.all(counts.sum(-1) == N)
    assert np.all(counts[:, 0, 1] == 0)  # a zero-weight particle is never selected
    for b in range(2):
        wb = W_TEST[b]
        var = _exact_var(name, wb)
        mean = counts[:, b].mean(0)
        se = np.sqrt(var / reps)
        exact = var < 1e-12
        # E[#offspring] = N w_i: z-score bound 4.5 (a false alarm has probability ~1e-5 per entry)
        assert np.all(np.abs(mean - N * wb)[~exact] <= 4.5 * se[~exact])
        assert np.allclose(counts[:, b][:, exact], (N * wb)[exact])
        # sample variance against the exact variance (relative s.e. ~ sqrt(2/reps) ~ 1%)
        svar = counts[:, b].var(0)
        assert np.allclose(svar, var, rtol=0.1, atol=2e-3)
        if name != "multinomial":
            mult = _exact_var("multinomial", wb)
            assert svar.sum() < 0.8 * mult.sum()


def test_residual_one_run_counts_and_ragged_batches():
    """One run (1-D weights, the repeat-interleave path): floor(N w_i) copies exactly, N in all,
    and E[#offspring] = N w_i over repeated calls; a batch whose runs need different numbers
    of residual draws (one none at all) keeps each run's deterministic part."""
    N, reps = W_TEST.shape[1], 4000
    g = gen(5)
    for b in range(2):
        wb = W_TEST[b]
        counts = np.zeros((reps, N))
        for r in range(reps):
            anc = residual(t(wb), g, log=False)
            assert anc.shape == (N,) and anc.dtype == torch.int64
            counts[r] = np.bincount(anc.numpy(), minlength=N)
        assert np.all(counts >= np.floor(N * wb)) and np.all(counts.sum(1) == N)
        var = _exact_var("residual", wb)
        se = np.sqrt(var / reps)
        live = var > 1e-12
        assert np.all(np.abs(counts.mean(0) - N * wb)[live] <= 4.5 * se[live])
    w = t([[0.25, 0.25, 0.25, 0.25], [0.7, 0.1, 0.1, 0.1], [0.4, 0.35, 0.2, 0.05]])
    anc = residual(w, g, log=False)
    assert anc[0].tolist() == [0, 1, 2, 3]  # no residual draw
    assert anc[1, :2].tolist() == [0, 0] and anc[2, :2].tolist() == [0, 1]
    assert bool(((anc >= 0) & (anc < 4)).all())
    # equal weights 1/13 normalise to N w_i a few ulps below 1: each particle still keeps its
    # one copy, with no residual draw
    for N in (13, 26, 29):
        anc = residual(torch.full((3, N), 1.0 / N, dtype=torch.float64), g, log=False)
        assert (anc == torch.arange(N)).all(), N


def test_ess_closed_form():
    w = t([0.5, 0.25, 0.125, 0.125])
    assert torch.allclose(ess(torch.log(w) + 3.0), 1.0 / (w * w).sum())
    assert torch.allclose(ess(torch.zeros(2, 7, dtype=torch.float64)), t([7.0, 7.0]))
    one = t([0.0, -math.inf, -math.inf])
    assert torch.allclose(ess(one), t(1.0))
    lw, lse = normalize_log_weights(torch.log(w) + 3.0)
    assert torch.allclose(lw.exp(), w) and torch.allclose(lse, t(3.0))


def test_resampler_bad_inputs():
    with pytest.raises(ValueError, match="resampler"):
        get_resampler("bogus")
    with pytest.raises(TypeError, match="generator"):
        systematic(torch.zeros(4, dtype=torch.float64), None)
    with pytest.raises(ValueError, match="-inf for every particle"):
        multinomial(t([-math.inf, -math.inf]), gen(0))
    with pytest.raises(ValueError, match="non-negative"):
        stratified(t([0.5, -0.1]), gen(0), log=False)
    with pytest.raises(ValueError, match="NaN"):
        residual(t([0.0, float("nan")]), gen(0))
    with pytest.raises(ValueError, match=r"\(\.\.\., N\)"):
        systematic(torch.zeros(0, dtype=torch.float64), gen(0))


# ---------------------------------------------------------------------- gather helper
@dataclass(frozen=True)
class _Buffers:
    buf_Q: torch.Tensor  # (W, ..., N, n, n): window dim first
    count: torch.Tensor  # (..., N)


def test_gather_particles_matches_indexing():
    g = gen(3)
    B, N, n, m, W = 2, 5, 3, 2, 4
    fs = FilterState(
        GaussianBelief(torch.randn(B, N, n, generator=g), torch.randn(B, N, n, n, generator=g)),
        StrongTrackingState(
            torch.randn(B, N, m, m, generator=g), torch.rand(B, N, generator=g) > 0.5
        ),
        _Buffers(torch.randn(W, B, N, n, n, generator=g), torch.randn(B, N, generator=g)),
    )
    anc = torch.randint(0, N, (B, N), generator=g)
    out = gather_particles(fs, anc)
    for b in range(B):
        a = anc[b]
        assert torch.equal(out.belief.mean[b], fs.belief.mean[b, a])
        assert torch.equal(out.belief.chol[b], fs.belief.chol[b, a])
        assert torch.equal(out.fading.V[b], fs.fading.V[b, a])
        assert torch.equal(out.fading.started[b], fs.fading.started[b, a])
        assert torch.equal(out.noise.buf_Q[:, b], fs.noise.buf_Q[:, b, a])
        assert torch.equal(out.noise.count[b], fs.noise.count[b, a])
    mask = torch.rand(B, N, generator=g) > 0.5
    mixed = where_particles(mask, fs, out)
    assert torch.equal(mixed.fading.V[mask], fs.fading.V[mask])
    assert torch.equal(mixed.fading.V[~mask], out.fading.V[~mask])
    with pytest.raises(ValueError, match="batch and particle dims"):
        gather_particles(fs, anc[:, :3])


# ---------------------------------------------------------------------- saltatory state
def test_stpf_tracks_jump_better_than_sir_and_ekpf():
    """Random-walk model with small Q; the truth jumps by 3 (10 sigma_R, 60 sigma_Q) at k = 30.

    20 independent seeded runs (batched), 200 particles, the same resampling rule (N_eff < N/3)
    for all three filters. Measured: RMSE STPF 0.25, SIR 1.05, EKPF 0.96; STPF wins 20/20
    runs. We assert STPF's mean RMSE is below half of the others' and that it wins >= 18/20.
    """
    R, T, kj, N = 20, 60, 30, 200
    sq, sr, jump = 0.05, 0.3, 3.0
    model = StateSpaceModel(
        f=None, h=lambda x, u, k: x, state_dim=1, obs_dim=1, chol_Q=t([[sq]]), chol_R=t([[sr]])
    )
    g = gen(123)
    w = sq * torch.randn(T, R, 1, generator=g, dtype=torch.float64)
    w[kj - 1] += jump
    x = torch.cumsum(w, 0)
    ys = x + sr * torch.randn(T, R, 1, generator=g, dtype=torch.float64)
    b0 = GaussianBelief(
        torch.zeros(R, 1, dtype=torch.float64), torch.ones(R, 1, 1, dtype=torch.float64)
    )
    rmse = {}
    for pf in (sir(N, resample_threshold=1 / 3), ekpf(N, resample_threshold=1 / 3), stpf(N)):
        tr = pf.run(model, b0, ys, generator=gen(7))
        assert bool(torch.isfinite(tr.means).all())
        rmse[pf.name] = (tr.means - x)[..., 0].pow(2).mean(0).sqrt()  # (R,)
    s, p, e = rmse["STPF"], rmse["PF"], rmse["EKPF"]
    assert s.mean() < 0.5 * p.mean() and s.mean() < 0.5 * e.mean()
    assert int((s < p).sum()) >= 18 and int((s < e).sum()) >= 18


# ---------------------------------------------------------------------- robustness
@pytest.mark.filterwarnings("ignore::prognos_torch.filters.particle.ProposalFallbackWarning")
@pytest.mark.parametrize("factory", [sir, ekpf, stpf])
def test_weight_collapse_warns_and_recovers(factory):
    # at k = 4 the measurement function returns NaN for every particle (a broken sensor model)
    model = StateSpaceModel(
        f=lambda x, u, k: x,
        h=lambda x, u, k: x * (math.nan if k == 4 else 1.0),
        state_dim=1,
        obs_dim=1,
        chol_Q=t([[0.1]]),
        chol_R=t([[0.1]]),
    )
    ys = torch.zeros(6, 1, dtype=torch.float64)
    with pytest.warns(WeightCollapseWarning, match="collapsed"):
        tr = factory(100).run(model, GaussianBelief(t([0.0]), t([[1.0]])), ys, generator=gen(0))
    assert bool(torch.isfinite(tr.means).all()) and bool(torch.isfinite(tr.covs).all())
    assert bool(tr.collapsed[3]) and int(tr.collapsed.sum()) == 1
    assert tr.log_likelihoods[3] == -math.inf
    assert torch.isfinite(tr.log_likelihoods[[0, 1, 2, 4, 5]]).all()
    assert float(tr.ess[3]) == pytest.approx(100.0)  # reset to uniform weights


def test_weight_collapse_by_underflow():
    """A finite but absurd measurement underflows every likelihood to zero."""
    model = linear_gaussian_model(t([[1.0]]), t([[1.0]]), t([[0.1]]), t([[0.1]]))
    ys = torch.zeros(6, 1, dtype=torch.float64)
    ys[3] = 1e200
    with pytest.warns(WeightCollapseWarning):
        tr = sir(100).run(model, GaussianBelief(t([0.0]), t([[1.0]])), ys, generator=gen(0))
    assert bool(torch.isfinite(tr.means).all()) and bool(tr.collapsed[3])


def _one_sir_step(f, h, x_prev, lw_prev, y):
    """One SIR step without resampling from the particles ``x_prev`` ``(..., 5, 1)`` with
    log-weights ``lw_prev``, a noise-free transition ``f`` and ``y = h(x) + N(0, 0.4^2)``."""
    model = StateSpaceModel(
        f=f, h=h, state_dim=1, obs_dim=1, chol_Q=t([[0.0]]), chol_R=t([[0.4]]), batched=True
    )
    state = ParticleState(x_prev.clone(), lw_prev.clone(), None)
    return sir(5, resample_threshold=0.0).step(model, state, y, generator=gen(0))[1]


def _exact_bayes_1d(x, lw_prev, y, h):
    """The weights, mean and variance ``(1, 1)`` of the exact update of the particles ``x``
    ``(K, 1)`` with log-weights ``lw_prev`` ``(K,)`` by ``y = h(x) + N(0, 0.4^2)``."""
    e = (y - h(x, None, 1)[:, 0]) / 0.4
    w = torch.softmax(lw_prev - 0.5 * e * e, 0)
    m = w @ x[:, 0]
    return w, m.reshape(1), (w @ (x[:, 0] - m) ** 2).reshape(1, 1)


def test_ruled_out_and_non_finite_particles_get_zero_weight_in_one_step():
    """A particle the measurement rules out (log-likelihood -inf) and one that left the reals
    (x = inf with a finite h) get weight zero; the other weights are the exact Bayes update."""
    x_prev = t([[0.5], [1.0], [2.0], [3.0], [-1.0]])
    lw_prev = torch.log(t([0.1, 0.2, 0.3, 0.2, 0.2]))
    for f, h, y, ruled_out in (
        # f: -1 -> 0, where log 0 = -inf: ruled out by any y (every particle finite)
        (lambda x, u, k: x.clamp_min(0.0), lambda x, u, k: torch.log(x), 0.3, [4]),
        # f: 3 -> inf, where tanh(inf) = 1 is finite: a particle that left the reals
        (
            lambda x, u, k: torch.where(x > 2.5, math.inf, x),
            lambda x, u, k: torch.tanh(x),
            0.8,
            [3],
        ),
    ):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no collapse: the other particles carry the weight
            info = _one_sir_step(f, h, x_prev, lw_prev, t([y]))
        keep = [i for i in range(5) if i not in ruled_out]
        w, m, var = _exact_bayes_1d(f(x_prev, None, 1)[keep], lw_prev[keep], y, h)
        assert torch.isneginf(info.log_weights[ruled_out]).all()
        torch.testing.assert_close(info.log_weights[keep], torch.log(w), rtol=0, atol=1e-14)
        torch.testing.assert_close(info.mean, m, rtol=0, atol=1e-14)
        torch.testing.assert_close(info.cov, var, rtol=0, atol=1e-14)


def test_invalid_particles_get_zero_weight_and_invalid_proposals_fall_back():
    # h is NaN for x < 0: those particles must get zero weight, the estimate stays finite
    model = StateSpaceModel(
        f=None,
        h=lambda x, u, k: torch.sqrt(x),
        state_dim=1,
        obs_dim=1,
        chol_Q=t([[0.3]]),
        chol_R=t([[0.2]]),
        jac_h=lambda x, u, k: torch.where(x > 0, 0.5 / torch.sqrt(x.abs()), torch.nan).reshape(
            1, 1
        ),
    )
    ys = torch.full((5, 1), 1.0, dtype=torch.float64)
    b0 = GaussianBelief(t([0.5]), t([[1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("error", WeightCollapseWarning)
        tr = sir(500).run(model, b0, ys, generator=gen(0))
    assert bool(torch.isfinite(tr.means).all())
    with pytest.warns(ProposalFallbackWarning, match="transition prior"):
        tr = ekpf(500).run(model, b0, ys, generator=gen(0))
    assert bool(torch.isfinite(tr.means).all()) and int(tr.prior_fallback[0]) > 0
    assert bool(torch.isfinite(tr.final.proposal.belief.chol).all())


def test_bad_inputs():
    model = linear_gaussian_model(t([[1.0]]), t([[1.0]]), t([[0.1]]), t([[0.1]]))
    b0 = GaussianBelief(t([0.0]), t([[1.0]]))
    ys = torch.zeros(3, 1, dtype=torch.float64)
    for bad in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match="num_particles"):
            ParticleFilter(bad)
    for bad in (-0.1, 1.5, "x"):
        with pytest.raises(ValueError, match="resample_threshold"):
            ParticleFilter(10, resample_threshold=bad)
    with pytest.raises(ValueError, match="resampler"):
        ParticleFilter(10, resampler="nope")
    with pytest.raises(TypeError, match="proposal"):
        ParticleFilter(10, proposal="ekf")
    with pytest.raises(ValueError, match="unknown particle filter"):
        make_particle_filter("kalman")
    pf = sir(10)
    with pytest.raises(TypeError, match="generator"):
        pf.run(model, b0, ys, generator=np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"ys must have shape \(T, 1\)"):
        pf.run(model, b0, torch.zeros(3, 2, dtype=torch.float64), generator=gen(0))
    with pytest.raises(ValueError, match="belief.mean"):
        pf.init(
            model,
            GaussianBelief(t([0.0, 1.0]), torch.eye(2, dtype=torch.float64)),
            generator=gen(0),
        )
    state = pf.init(model, b0, generator=gen(0))
    with pytest.raises(ValueError, match=r"y must have shape \(1,\)"):
        pf.step(model, state, torch.zeros(2, dtype=torch.float64), generator=gen(0))
    with pytest.raises(ValueError, match="inf"):
        pf.step(model, state, t([math.inf]), generator=gen(0))
    with pytest.raises(ValueError, match="control_dim=0"):
        pf.step(model, state, t([0.0]), u=t([1.0]), generator=gen(0))
    with pytest.raises(ValueError, match="state.proposal"):
        ekpf(10).step(model, state, t([0.0]), generator=gen(0))
    singular = linear_gaussian_model(t([[1.0]]), t([[1.0]]), t([[0.0]]), t([[0.1]]))
    with pytest.raises(ValueError, match="chol_Q"):
        ekpf(10).run(singular, b0, ys, generator=gen(0))
    sir(10).run(singular, b0, ys, generator=gen(0))  # the bootstrap PF needs no density of Q
    with pytest.raises(ValueError, match="model.chol_Q must have shape"):
        bad_noise = linear_gaussian_model(
            t([[1.0]]), t([[1.0]]), torch.ones(4, 1, 1, dtype=torch.float64), t([[0.1]])
        )
        pf.run(bad_noise, b0, ys, generator=gen(0))


def test_exact_on_linear_model_with_engine_reference():
    """The engine's EKF is exact on linear models: the EKPF and SIR agree with it too."""
    model = linear_gaussian_model(t([[0.8]]), t([[2.0]]), t([[0.5]]), t([[1.0]]))
    ys = torch.randn(20, 1, generator=gen(8), dtype=torch.float64)
    b0 = GaussianBelief(t([1.0]), t([[2.0]]))
    from prognos_torch.filters import run

    ref = run(ekf(), model, b0, ys)
    tr = ekpf(20000).run(model, b0, ys, generator=gen(5))
    std = ref.chols[..., 0, 0]
    assert bool(((tr.means[:, 0] - ref.means[:, 0]).abs() <= K_MC * std / tr.ess.sqrt()).all())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_runs_on_cuda():
    dev = torch.device("cuda")
    model = linear_gaussian_model(
        *(
            torch.tensor(v, dtype=torch.float64, device=dev)
            for v in ([[0.9]], [[1.0]], [[0.3]], [[0.5]])
        )
    )
    ys = torch.randn(10, 4, 1, dtype=torch.float64, device=dev)
    b0 = GaussianBelief(
        torch.zeros(4, 1, dtype=torch.float64, device=dev),
        torch.ones(4, 1, 1, dtype=torch.float64, device=dev),
    )
    for pf in (sir(1000), stpf(1000)):
        tr = pf.run(model, b0, ys, generator=torch.Generator(device=dev).manual_seed(0))
        assert tr.means.device.type == "cuda" and bool(torch.isfinite(tr.means).all())


def test_sir_log_likelihood_gradient_matches_finite_differences_without_warnings():
    """Without resampling the SIR log-likelihood is smooth in the model's parameters for a fixed
    random stream: autograd through the run equals central differences, and the host reads of
    the step's decisions raise no autograd warning."""
    ys = torch.randn(20, 1, generator=gen(0), dtype=torch.float64)

    def loglik(r):
        model = StateSpaceModel(
            f=lambda x, u, k: 0.9 * x,
            h=lambda x, u, k: x,
            state_dim=1,
            obs_dim=1,
            chol_Q=t([[0.3]]),
            chol_R=r.reshape(1, 1),
            batched=True,
        )
        pf = sir(2000, resample_threshold=0.0)
        tr = pf.run(model, GaussianBelief(t([0.0]), t([[1.0]])), ys, generator=gen(1))
        return tr.log_likelihood.sum()

    r = t([0.5]).requires_grad_()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (grad,) = torch.autograd.grad(loglik(r), r)
    h = 1e-6
    fd = (loglik(t([0.5 + h])) - loglik(t([0.5 - h]))) / (2 * h)
    torch.testing.assert_close(grad, fd.reshape(1), rtol=1e-7, atol=0)


def test_one_state_variance_ignores_a_zero_weight_particle_far_out():
    """A particle so far out that (x - mean)^2 overflows, with weight zero (ruled out by the
    measurement, or underflowed), adds nothing to the variance, batched or not."""
    x_prev = t([[0.5], [1.0], [2.0], [1.5], [1e160]])
    lw_prev = torch.log(t([0.2, 0.2, 0.2, 0.2, 0.2]))
    h = lambda x, u, k: x  # noqa: E731
    _, _, want = _exact_bayes_1d(x_prev[:4], lw_prev[:4], 1.2, h)
    for B in (None, 2):
        xp, lp, y = x_prev, lw_prev, t([1.2])
        if B:
            xp, lp, y = xp.expand(B, 5, 1), lp.expand(B, 5), y.expand(B, 1)
        info = _one_sir_step(None, h, xp, lp, y)
        got = info.cov if B is None else info.cov[1]
        torch.testing.assert_close(got, want, rtol=1e-14, atol=0)


def test_particle_weights_refuse_an_upper_triangular_noise_factor():
    """A valid but upper triangular square root of R: the Gaussian filters use S S^T and are
    right; the particle weights solved with its lower triangle and came out wrong (posterior
    means -0.133 against the Kalman filter's -0.395). Refused by name now."""
    from prognos_torch.filters import ekf, run, sir

    F64 = torch.float64
    upper = torch.tensor([[1.0, 0.8], [0.0, 0.6]], dtype=F64)
    model = linear_gaussian_model(torch.eye(1, dtype=F64), torch.ones(2, 1, dtype=F64),
                                  0.5 * torch.eye(1, dtype=F64), upper)  # fmt: skip
    b = GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    y = torch.tensor([[0.5, -0.4], [1.0, 1.2], [0.3, 0.1]], dtype=F64)
    with pytest.raises(ValueError, match=r"model.chol_R must be lower triangular for a particle "
                       r"filter"):  # fmt: skip
        sir(100).run(model, b, y, generator=torch.Generator().manual_seed(0))
    lower = torch.linalg.cholesky(upper @ upper.mT)
    ok = linear_gaussian_model(torch.eye(1, dtype=F64), torch.ones(2, 1, dtype=F64),
                               0.5 * torch.eye(1, dtype=F64), lower)  # fmt: skip
    ref = run(ekf(), model, b, y).means  # the Gaussian filters take either root
    torch.testing.assert_close(run(ekf(), ok, b, y).means, ref)
    pf = sir(20000).run(ok, b, y, generator=torch.Generator().manual_seed(0)).means
    torch.testing.assert_close(pf, ref, atol=0.02, rtol=0)


# ---------------------------------------------------------------------- weights given by hand
def _two_runs_one_degenerate(N=50):
    """Two runs of ``N`` particles: uniform weights (``N_eff = N``) and one particle carrying
    almost all the weight (``N_eff`` near 1), with a model and a missing measurement, which
    leaves the weights as they are."""
    model = linear_gaussian_model(t([[1.0]]), t([[1.0]]), t([[0.1]]), t([[0.1]]))
    x = torch.linspace(-1.0, 1.0, N, dtype=torch.float64).reshape(1, N, 1).repeat(2, 1, 1)
    lw = torch.full((2, N), -math.log(N), dtype=torch.float64)
    lw[1] = torch.log_softmax(torch.where(torch.arange(N) == 3, 0.0, -20.0).double(), -1)
    return model, ParticleState(x, lw), t([[math.nan], [math.nan]])


def test_a_custom_resampler_of_the_wrong_shape_is_refused_when_some_runs_resample():
    """Only run 1 resamples: ancestors ``(N,)`` for weights ``(2, N)`` broadcast against the
    other run's own indices and passed the shape check."""
    model, state, y = _two_runs_one_degenerate()

    def one_row(lw, g):  # the ancestors of run 1 only: shape (N,)
        return systematic(lw[1], g)

    with pytest.raises(ValueError, match=r"ancestors of shape \(2, 50\), got \(50,\)"):
        sir(50, resampler=one_row).step(model, state, y, generator=gen(0))


def test_threshold_one_keeps_uniform_weights_and_resamples_any_other():
    """``resample_threshold=1`` resamples whenever the weights are not uniform: uniform weights
    (a missing measurement after resampling) have ``N_eff = N`` up to rounding, which fell
    below ``N`` for N = 50 and resampled them (multinomially: Monte Carlo noise for nothing)."""
    model, state, y = _two_runs_one_degenerate()
    for name in ("multinomial", "systematic"):
        pf = sir(50, resample_threshold=1.0, resampler=name)
        new, info = pf.step(model, state, y, generator=gen(1))
        assert info.resampled.tolist() == [False, True]
        assert torch.equal(new.particles[0], info.particles[0])
        assert torch.equal(new.log_weights[0], state.log_weights[0])


def test_log_weights_given_by_hand_must_be_a_normalised_distribution():
    """A state's log-weights are normalised: unnormalised ones shifted the log-likelihood
    estimate log sum_i w_i p(y | x_i) by their log-sum (here 5 nats); NaN and all -inf ones were
    reset to uniform with a collapse warning. Each is refused by name."""
    model, state, _ = _two_runs_one_degenerate()
    y = t([[0.2], [0.1]])
    pf = sir(50, resample_threshold=0.0)
    _, info = pf.step(model, state, y, generator=gen(2))
    # the exact estimate from the same draws: x_k = x + 0.1 eps
    eps = torch.randn(2, 50, 1, generator=gen(2), dtype=torch.float64)
    x = state.particles + 0.1 * eps
    logp = -0.5 * (((y.unsqueeze(-2) - x) / 0.1) ** 2).squeeze(-1) - math.log(
        0.1 * math.sqrt(2 * math.pi)
    )
    want = torch.logsumexp(state.log_weights + logp, -1)
    assert float((info.log_likelihood - want).abs().max()) < 1e-12
    for bad, msg in (
        (state.log_weights + 5.0, "normalised"),
        (torch.where(torch.arange(50) == 7, math.nan, state.log_weights), "NaN"),
        (torch.full_like(state.log_weights, -math.inf), "-inf for every particle"),
    ):
        with pytest.raises(ValueError, match=f"state.log_weights.*{msg}"):
            pf.step(model, ParticleState(state.particles, bad), y, generator=gen(2))
        with pytest.raises(ValueError, match=f"state.log_weights.*{msg}"):
            pf.run(model, ParticleState(state.particles, bad), y[None], generator=gen(2))


def _two_sensor_model(rows):
    """The 2-D model of _lgssm_2d seen by two sensors (rows ``rows`` of H, R, r)."""
    F, _, LQ, _, q, _, m0, P0 = _lgssm_2d()
    H = np.array([[1.0, 0.5], [0.3, -1.0]])
    LR = np.array([[0.6, 0.0], [0.2, 0.5]])
    r = np.array([0.1, -0.2])
    R = LR @ LR.T
    Hs, Rs, rs = H[rows], R[np.ix_(rows, rows)], r[rows]
    model = linear_gaussian_model(t(F), t(Hs), t(LQ), t(np.linalg.cholesky(Rs)), q=t(q), r=t(rs))
    return model, GaussianBelief.from_cov(t(m0), t(P0)), F, LQ, q


@pytest.mark.parametrize("factory", [sir, ekpf, upf, stpf])
def test_a_partly_missing_vector_weighs_by_its_observed_components(factory):
    """A partly NaN measurement was treated as missing (propagate only). The second sensor
    silent throughout: the run equals the filter on the first sensor's model (its row of H, r
    and R_00), draw for draw, to rounding. STPF: strong tracking skips a partly observed vector,
    as in the Gaussian filters (lambda = 1), so it equals the EKPF on the first sensor."""
    full, b0, *_ = _two_sensor_model([0, 1])
    first, *_ = _two_sensor_model([0])
    ys = t(_simulate(*_lgssm_2d()[:1], np.array([[1.0, 0.5]]), *_lgssm_2d()[2:3],
                     np.array([[0.6]]), *_lgssm_2d()[4:5], np.array([0.1]), *_lgssm_2d()[6:], 25,
                     seed=4))  # fmt: skip
    y2 = torch.cat([ys, torch.full_like(ys, math.nan)], -1)
    pf = factory(200)
    a = pf.run(full, b0, y2, generator=gen(1), keep_particles=True)
    if factory is stpf:
        pf = ekpf(200, resample_threshold=pf.resample_threshold)
    b = pf.run(first, b0, ys, generator=gen(1), keep_particles=True)
    assert not bool(a.missing.any()) and torch.equal(a.resampled, b.resampled)
    for name in ("means", "log_likelihoods", "particles", "log_weights", "fading_factors"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-9, atol=1e-11)


def test_partly_missing_runs_in_a_batch_get_the_observed_density_in_one_step():
    """Three runs, one step: both sensors, the second only, neither. The weights are the prior
    weights times N(y_o; H_o x + r_o, R_oo) of each run's own observed part (closed form), the
    log-likelihood their log-sum; the silent run keeps its weights and is flagged missing."""
    model, b0, *_ = _two_sensor_model([0, 1])
    H = np.array([[1.0, 0.5], [0.3, -1.0]])
    LR = np.array([[0.6, 0.0], [0.2, 0.5]])
    R, r = LR @ LR.T, np.array([0.1, -0.2])
    pf = sir(300)
    b3 = GaussianBelief.from_cov(b0.mean.expand(3, 2), b0.cov.expand(3, 2, 2))
    state = pf.init(model, b3, generator=gen(0))
    state, _ = pf.step(model, state, t([[0.4, 0.1], [0.2, -0.3], [0.9, 0.0]]), k=1,
                       generator=gen(1))  # fmt: skip
    y = t([[0.5, -0.2], [math.nan, 0.3], [math.nan, math.nan]])
    new, info = pf.step(model, state, y, k=2, generator=gen(2))
    assert info.missing.tolist() == [False, False, True]
    x = info.particles.numpy()  # (3, N, 2), before resampling
    lw0 = state.log_weights.numpy()
    for run, rows in ((0, [0, 1]), (1, [1])):
        e = y.numpy()[run, rows] - (x[run] @ H[rows].T + r[rows])
        Ro = R[np.ix_(rows, rows)]
        quad = np.einsum("ni,ij,nj->n", e, np.linalg.inv(Ro), e)
        logp = -0.5 * (quad + len(rows) * math.log(2 * math.pi) + np.linalg.slogdet(Ro)[1])
        want_ll = np.logaddexp.reduce(lw0[run] + logp)
        assert float(info.log_likelihood[run]) == pytest.approx(want_ll, abs=1e-10)
        np.testing.assert_allclose(info.log_weights[run].numpy(), lw0[run] + logp - want_ll,
                                   atol=1e-10)  # fmt: skip
    np.testing.assert_allclose(info.log_weights[2].numpy(), lw0[2], atol=1e-14)
    assert float(info.log_likelihood[2]) == 0.0
