"""Maximum-likelihood fitting through the square-root filter: gradients and recovery."""

import math

import pytest
import torch

from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.core.linalg import tria
from prognos_torch.filters import ekf, run, sckf, srukf, ukf
from prognos_torch.filters.gaussian import GaussianFilter
from prognos_torch.optim import fit_likelihood, from_log_cholesky, log_cholesky
from prognos_torch.quadrature import unscented

dt = torch.float64


def two_state_model(p):
    """A damped oscillator with a nonlinear spring (parameter ``a`` of f), a saturating sensor
    (parameter ``c`` of h), full Q and scalar R; per-sample functions (vmapped)."""
    a, c = p["a"], p["c"]

    def f(x, u, k):
        return torch.stack([x[0] + 0.1 * x[1], x[1] - 0.1 * (a * torch.sin(x[0]) + 0.3 * x[1])])

    def h(x, u, k):
        return torch.stack([torch.tanh(c * x[0]), x[1]])

    return StateSpaceModel(
        f=f,
        h=h,
        state_dim=2,
        obs_dim=2,
        chol_Q=from_log_cholesky(p["lq"]),
        chol_R=from_log_cholesky(p["lr"]),
    )


def two_state_data(T=15):
    g = torch.Generator().manual_seed(3)
    ys = torch.randn(T, 2, generator=g, dtype=dt) * 0.5 + torch.tensor([0.3, 0.0], dtype=dt)
    ys[T // 3] = float("nan")  # missing
    ys[T // 2 + 1, 0] = float("nan")  # partially observed
    return ys


def params0():
    return {
        "a": torch.tensor(1.3, dtype=dt),
        "c": torch.tensor(0.8, dtype=dt),
        "lq": torch.tensor([[-1.5, 0.0], [0.2, -1.0]], dtype=dt),
        "lr": torch.tensor([[-0.7, 0.0], [0.1, -0.4]], dtype=dt),
    }


def loglik(filt, p, ys):
    b0 = GaussianBelief(torch.tensor([0.2, 0.0], dtype=dt), 0.5 * torch.eye(2, dtype=dt))
    return run(filt, two_state_model(p), b0, ys).log_likelihood


@pytest.mark.parametrize(
    "filt",
    [sckf(), srukf(), ekf(), ukf(), GaussianFilter(unscented(0.5, 2.0, 0.0), sqrt=True)],
    ids=["sckf", "srukf", "ekf", "ukf-full", "unscented-negative-w0"],
)
def test_log_likelihood_gradient_matches_central_differences(filt):
    ys = two_state_data()
    p = {k: v.clone().requires_grad_(True) for k, v in params0().items()}
    ll = loglik(filt, p, ys)
    grads = torch.autograd.grad(ll, list(p.values()))
    h = 1e-6
    for (name, v), g in zip(p.items(), grads):
        fd = torch.zeros_like(v)
        for i in range(v.numel()):
            if name in ("lq", "lr") and i == 1:  # the unused upper triangle
                continue
            e = torch.zeros_like(v).reshape(-1)
            e[i] = h
            e = e.reshape(v.shape)
            with torch.no_grad():
                up = {**{k: w.detach() for k, w in p.items()}, name: v.detach() + e}
                dn = {**{k: w.detach() for k, w in p.items()}, name: v.detach() - e}
                fd.reshape(-1)[i] = (loglik(filt, up, ys) - loglik(filt, dn, ys)) / (2 * h)
        scale = max(1.0, float(fd.abs().max()))
        assert torch.allclose(g, fd, atol=1e-6 * scale, rtol=0), (name, g, fd)
        assert float(g.abs().max()) > 1e-3  # the gradient is not trivially zero


def test_gradient_finite_where_the_posterior_downdate_fails():
    # a very informative measurement next to an ordinary one: the downdate fails for the first
    # batch element, whose posterior comes from the Joseph QR; no NaN reaches the gradient
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=dt)
    ys = torch.randn(8, 2, 1, dtype=dt, generator=torch.Generator().manual_seed(0))
    b0 = GaussianBelief(torch.zeros(2, 2, dtype=dt), 100 * torch.eye(2, dtype=dt).expand(2, 2, 2))

    def ll(lr):
        model = StateSpaceModel(
            f=lambda x, u, k: F @ x,
            h=lambda x, u, k: x[:1],
            state_dim=2,
            obs_dim=1,
            chol_Q=0.3 * torch.eye(2, dtype=dt),
            chol_R=lr.exp().reshape(2, 1, 1),
        )
        return run(ekf(), model, b0, ys).log_likelihood.sum()

    lr = torch.tensor([math.log(1e-7), 0.0], dtype=dt, requires_grad=True)
    (g,) = torch.autograd.grad(ll(lr), [lr])
    assert bool(torch.isfinite(g).all())
    h = 1e-6
    with torch.no_grad():
        e = torch.tensor([0.0, h], dtype=dt)
        fd = (ll(lr + e) - ll(lr - e)) / (2 * h)
    assert abs(float(g[1] - fd)) < 1e-6 * max(1.0, abs(float(fd)))


def test_tria_gradient_matches_finite_differences():
    A = torch.randn(2, 3, 5, dtype=dt, generator=torch.Generator().manual_seed(0))
    assert torch.autograd.gradcheck(tria, (A.requires_grad_(True),))


def test_log_cholesky_round_trip():
    S = torch.tensor([[0.5, 0.0], [-0.3, 2.0]], dtype=dt)
    torch.testing.assert_close(from_log_cholesky(log_cholesky(S)), S)
    with pytest.raises(ValueError, match="positive diagonal"):
        log_cholesky(-S)
    with pytest.raises(ValueError, match=r"\(..., n, n\)"):
        from_log_cholesky(torch.zeros(3, dtype=dt))
    # an upper or symmetric square root of the same covariance: its upper part was dropped
    # (S^T round-tripped to a factor of another covariance)
    with pytest.raises(ValueError, match="chol must be lower-triangular"):
        log_cholesky(S.mT.contiguous())


# ---------------------------------------------------------------- recovery from simulated data
A_TRUE, Q_TRUE, R_TRUE = 0.7, 0.5, 0.3
SEEDS, SERIES, T = 5, 20, 120


def lead(p, x):
    """A per-seed parameter ``(S, ...)`` against points ``(S, B, ..., n)`` (batch dims first)."""
    return p.reshape(p.shape + (1,) * (x.dim() - p.dim()))


def growth_model(p):
    """``x_k = a x_{k-1} + 0.5 sin(x_{k-1}) + w``, ``y_k = x_k + v``; ``a``, ``Q``, ``R`` per seed
    (batch dims (seed, series), parameters shared by a seed's series)."""
    a = p["a"]
    return StateSpaceModel(
        f=lambda x, u, k: lead(a, x) * x + 0.5 * torch.sin(x),
        h=lambda x, u, k: x,
        state_dim=1,
        obs_dim=1,
        chol_Q=from_log_cholesky(p["lq"]).expand(SEEDS, SERIES, 1, 1),
        chol_R=from_log_cholesky(p["lr"]).expand(SEEDS, SERIES, 1, 1),
        batched=True,
    )


def simulate_growth():
    ys = []
    for seed in range(SEEDS):
        g = torch.Generator().manual_seed(seed)
        x, yy = torch.zeros(SERIES, 1, dtype=dt), []
        for _ in range(T):
            w = math.sqrt(Q_TRUE) * torch.randn(SERIES, 1, generator=g, dtype=dt)
            x = A_TRUE * x + 0.5 * torch.sin(x) + w
            yy.append(x + math.sqrt(R_TRUE) * torch.randn(SERIES, 1, generator=g, dtype=dt))
        ys.append(torch.stack(yy))
    return torch.stack(ys, 1)  # (T, SEEDS, SERIES, 1)


def test_recovers_q_r_and_a_parameter_of_f_from_five_seeds():
    ys = simulate_growth()
    ys[::17, :, ::3] = float("nan")  # some missing measurements
    p0 = {
        "a": torch.full((SEEDS, 1), 0.3, dtype=dt),
        "lq": torch.zeros(SEEDS, 1, 1, 1, dtype=dt),
        "lr": torch.zeros(SEEDS, 1, 1, 1, dtype=dt),
    }
    b0 = GaussianBelief(
        torch.zeros(SEEDS, SERIES, 1, dtype=dt), torch.ones(SEEDS, SERIES, 1, 1, dtype=dt)
    )
    res = fit_likelihood(
        growth_model,
        p0,
        sckf(),
        b0,
        ys,
        optimizer=lambda p: torch.optim.LBFGS(p, line_search_fn="strong_wolfe", max_iter=12),
        steps=1,
    )
    a = res.params["a"].squeeze(-1)
    q = from_log_cholesky(res.params["lq"]).reshape(SEEDS) ** 2
    r = from_log_cholesky(res.params["lr"]).reshape(SEEDS) ** 2
    # 2,400 measurements per seed: sampling spread about 0.02 in a and 7 % in Q and R
    assert bool(((a - A_TRUE).abs() < 0.05).all()), a
    assert bool(((q / Q_TRUE - 1).abs() < 0.2).all()), q
    assert bool(((r / R_TRUE - 1).abs() < 0.2).all()), r
    assert res.trace.shape == (2, SEEDS, SERIES)
    assert bool((res.trace[-1].sum((-1)) > res.trace[0].sum(-1)).all())
    # the fitted model is usable as is
    ll = run(sckf(), res.model, b0, ys).log_likelihood
    torch.testing.assert_close(ll, res.log_likelihood)


def test_optimizer_instance_updates_the_given_tensors_and_tol_stops():
    ys = two_state_data(T=12)
    p = {k: v.clone().requires_grad_(True) for k, v in params0().items()}
    opt = torch.optim.Adam(p.values(), lr=0.02)
    b0 = GaussianBelief(torch.tensor([0.2, 0.0], dtype=dt), 0.5 * torch.eye(2, dtype=dt))
    before = p["a"].detach().clone()
    res = fit_likelihood(two_state_model, p, sckf(), b0, ys, optimizer=opt, steps=5)
    assert res.steps == 5 and res.trace.shape == (6,)
    assert not torch.equal(p["a"].detach(), before)  # updated in place
    torch.testing.assert_close(res.params["a"], p["a"].detach())
    assert float(res.trace[-1]) > float(res.trace[0])
    # the trace is the log-likelihood at each iterate
    torch.testing.assert_close(res.trace[-1], loglik(sckf(), res.params, ys))
    res2 = fit_likelihood(two_state_model, params0(), sckf(), b0, ys, steps=50, tol=1e-1)
    assert res2.steps < 50


def test_learns_the_initial_belief_through_a_function():
    ys = two_state_data(T=10)
    p = {**params0(), "m0": torch.zeros(2, dtype=dt)}

    def belief(p):
        return GaussianBelief(p["m0"], 0.5 * torch.eye(2, dtype=dt))

    res = fit_likelihood(two_state_model, p, ekf(), belief, ys, steps=3)
    assert not torch.equal(res.belief.mean, torch.zeros(2, dtype=dt))
    assert float(res.trace[-1]) > float(res.trace[0])


def test_bad_arguments():
    ys = two_state_data(T=5)
    b0 = GaussianBelief(torch.zeros(2, dtype=dt), torch.eye(2, dtype=dt))
    with pytest.raises(TypeError, match="params"):
        fit_likelihood(two_state_model, {}, sckf(), b0, ys)
    with pytest.raises(TypeError, match="floating-point"):
        fit_likelihood(two_state_model, {"a": 1.0}, sckf(), b0, ys)
    with pytest.raises(TypeError, match="GaussianFilter"):
        fit_likelihood(two_state_model, params0(), sckf, b0, ys)
    with pytest.raises(ValueError, match="steps"):
        fit_likelihood(two_state_model, params0(), sckf(), b0, ys, steps=-1)
    other = torch.zeros(1, requires_grad=True)
    with pytest.raises(ValueError, match="does not hold"):
        fit_likelihood(
            two_state_model, params0(), sckf(), b0, ys, optimizer=torch.optim.SGD([other], lr=1)
        )
    with pytest.raises(FloatingPointError, match="non-finite"):
        fit_likelihood(
            two_state_model,
            params0(),
            sckf(),
            b0,
            ys,
            optimizer=lambda p: torch.optim.SGD(p, lr=1e6),
            steps=5,
        )


def test_a_diverging_optimizer_instance_gets_its_last_finite_iterate_back():
    ys = two_state_data(T=5)
    b0 = GaussianBelief(torch.zeros(2, dtype=dt), torch.eye(2, dtype=dt))
    p = {k: v.clone().requires_grad_(True) for k, v in params0().items()}
    opt = torch.optim.SGD(list(p.values()), lr=1e6)
    with pytest.raises(FloatingPointError, match="non-finite after") as err:
        fit_likelihood(two_state_model, p, sckf(), b0, ys, optimizer=opt, steps=5)
    trace = err.value.trace
    assert trace is not None and bool(torch.isfinite(trace).all())
    # the tensors hold the iterate of the last finite log-likelihood, which they reproduce
    with torch.no_grad():
        ll = run(sckf(), two_state_model(p), b0, ys).log_likelihood
    torch.testing.assert_close(ll, trace[-1], rtol=1e-12, atol=0)
    # non-finite at the start: said so; a build_model that is no model: named
    bad = dict(params0(), a=torch.tensor(math.nan, dtype=dt))
    with pytest.raises(FloatingPointError, match="at the starting parameters"):
        fit_likelihood(two_state_model, bad, sckf(), b0, ys, steps=1)
    with pytest.raises(TypeError, match="build_model must return a StateSpaceModel, got tuple"):
        fit_likelihood(lambda q: (1, 2), params0(), sckf(), b0, ys, steps=1)


def test_a_divergence_in_the_last_step_gives_the_last_finite_iterate_back():
    # the last step's result is only evaluated after the loop: there the optimiser's tensors
    # stayed at the non-finite iterate and the exception carried no trace
    ys = two_state_data(T=5)
    b0 = GaussianBelief(torch.zeros(2, dtype=dt), torch.eye(2, dtype=dt))
    p = {k: v.clone().requires_grad_(True) for k, v in params0().items()}
    start = {k: v.detach().clone() for k, v in p.items()}
    opt = torch.optim.SGD(list(p.values()), lr=1e6)
    with pytest.raises(FloatingPointError, match="non-finite after 1 steps") as err:
        fit_likelihood(two_state_model, p, sckf(), b0, ys, optimizer=opt, steps=1)
    for k in p:
        assert torch.equal(p[k].detach(), start[k]), k
    with torch.no_grad():
        ll = run(sckf(), two_state_model(p), b0, ys).log_likelihood
    assert err.value.trace.shape == (1,)
    torch.testing.assert_close(err.value.trace[-1], ll, rtol=1e-12, atol=0)
    # with no step taken the message says it is the starting point
    bad = dict(params0(), a=torch.tensor(math.nan, dtype=dt))
    with pytest.raises(FloatingPointError, match="at the starting parameters") as err:
        fit_likelihood(two_state_model, bad, sckf(), b0, ys, steps=0)
    assert err.value.trace is None


def test_a_bad_tol_is_refused():
    # tol=-1 or NaN never stopped, a string failed inside torch after two steps
    ys = two_state_data(T=5)
    b0 = GaussianBelief(torch.zeros(2, dtype=dt), torch.eye(2, dtype=dt))
    for tol in (-1.0, math.nan, "1e-3", True):
        with pytest.raises(ValueError, match="tol must be a number >= 0 or None"):
            fit_likelihood(two_state_model, params0(), sckf(), b0, ys, steps=3, tol=tol)


def test_sgd_step_is_the_gradient_of_the_exact_joint_gaussian_log_likelihood():
    # one SGD step moves each parameter by lr / T times the derivative of log p(y_{1:T}),
    # here by central differences of the brute-force joint Gaussian (controls, a partly
    # observed and a missing row, parameters of f, Q, R and the initial mean)
    import numpy as np
    from _kalman_reference import joint_gaussian_reference

    g = np.random.default_rng(5)
    n, m, T = 2, 3, 4
    B, H = g.normal(size=(n, 1)), g.normal(size=(m, n))
    us, ys = g.normal(size=(T, 1)), g.normal(size=(T, m))
    ys[1], ys[3, 0] = np.nan, np.nan

    def build(p):
        return StateSpaceModel(
            f=lambda x, u, k: p["A"] @ x + torch.as_tensor(B) @ u,
            h=lambda x, u, k: torch.as_tensor(H) @ x,
            state_dim=n,
            obs_dim=m,
            chol_Q=from_log_cholesky(p["lq"]),
            chol_R=from_log_cholesky(p["lr"]),
            control_dim=1,
        )

    def belief(p):
        return GaussianBelief(p["m0"], 0.8 * torch.eye(n, dtype=dt))

    p0 = {
        "A": torch.tensor([[0.8, 0.2], [-0.1, 0.5]], dtype=dt),
        "lq": torch.tensor([[-0.5, 0.0], [0.3, -0.8]], dtype=dt),
        "lr": torch.tensor([[-0.2, 0, 0], [0.1, -0.4, 0], [0.2, 0.1, -0.3]], dtype=dt),
        "m0": torch.tensor([0.3, -0.2], dtype=dt),
    }

    def exact(p):
        SQ, SR = from_log_cholesky(p["lq"]).numpy(), from_log_cholesky(p["lr"]).numpy()
        Qs, Rs = [SQ @ SQ.T] * T, [SR @ SR.T] * T
        args = (p["A"].numpy(), H, Qs, Rs, p["m0"].numpy(), 0.64 * np.eye(n), ys)
        return joint_gaussian_reference(*args, Bu=us @ B.T)[3]

    lr, h = 1e-3, 1e-6
    for filt in (ekf(), sckf()):
        res = fit_likelihood(build, p0, filt, belief, torch.as_tensor(ys), torch.as_tensor(us),
                             optimizer=lambda q: torch.optim.SGD(q, lr=lr), steps=1)  # fmt: skip
        assert abs(float(res.trace[0]) - exact(p0)) < 1e-10
        assert abs(float(res.trace[1]) - exact(res.params)) < 1e-10
        for name, v in p0.items():
            for i in range(v.numel()):
                e = torch.zeros(v.numel(), dtype=dt)
                e[i] = h
                e = e.reshape(v.shape)
                fd = (exact({**p0, name: v + e}) - exact({**p0, name: v - e})) / (2 * h)
                step = float((res.params[name] - v).reshape(-1)[i]) * T / lr
                assert abs(step - fd) < 1e-6 * max(1.0, abs(fd)), (name, i, step, fd)
