"""Audit of the RTS smoother, EM and likelihood fitting against exact NumPy references (brute-force
joint Gaussian conditioning, a plain Kalman filter, closed-form M-steps, finite differences),
and of their handling of bad input and of the caller's optimiser after an error."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import ekf, run, sckf, smooth, smooth_trajectory
from prognos_torch.optim import em_linear_gaussian, fit_likelihood, linear_model

sys.path.insert(0, str(Path(__file__).parent))
from _kalman_reference import (  # noqa: E402
    joint_gaussian_reference,
    kalman_filter_observed,
    numpy_em_step,
    rts_reference,
)

d = torch.float64
t = lambda a: torch.as_tensor(np.asarray(a), dtype=d)  # noqa: E731


# ------------------------------------------------------------------------------ smoother
def test_smoother_equals_joint_conditioning_batched_time_varying_with_controls_and_missing():
    # batch (2, 3), per-series F_k = F0 + sin(k) F1, B, H, R, per-step Q_k, k0 = 2, rows
    # missing throughout and in part: each element against the brute-force joint Gaussian
    g = np.random.default_rng(3)
    bs, n, m, p, T, k0 = (2, 3), 2, 2, 1, 4, 2
    N = 6
    F0, F1 = 0.6 * g.normal(size=(N, n, n)), 0.3 * g.normal(size=(N, n, n))
    Bm, H = g.normal(size=(N, n, p)), g.normal(size=(N, m, n))
    SQs = np.tril(g.normal(size=(T, n, n))) * 0.3 + 0.4 * np.eye(n)
    SR = np.tril(g.normal(size=(N, m, m))) * 0.3 + 0.5 * np.eye(m)
    m0, S0 = g.normal(size=(N, n)), np.tril(g.normal(size=(N, n, n))) * 0.3 + np.eye(n)
    us, ys = g.normal(size=(T, N, p)), g.normal(size=(T, N, m))
    ys[1, 0], ys[3, 2, 0], ys[T - 1, 4, 1], ys[0, 5] = np.nan, np.nan, np.nan, np.nan
    F0t, F1t, Bt, Ht = (t(a).reshape(*bs, *a.shape[1:]) for a in (F0, F1, Bm, H))

    def lead(x, M):  # per-series matrices against (*bs, n) or (*bs, L, n) points
        return M.reshape(*bs, *([1] * (x.dim() - 1 - len(bs))), *M.shape[-2:])

    def f(x, u, k):
        uu = u.reshape(*bs, *([1] * (x.dim() - 1 - len(bs))), p, 1)
        return (lead(x, F0t + math.sin(k) * F1t) @ x[..., None] + lead(x, Bt) @ uu)[..., 0]

    model = StateSpaceModel(
        f=f, h=lambda x, u, k: (lead(x, Ht) @ x[..., None])[..., 0], state_dim=n, obs_dim=m,
        chol_Q=lambda k: t(SQs[k - k0 - 1]), chol_R=t(SR).reshape(*bs, m, m), control_dim=p,
        batched=True, jac_f=lambda x, u, k: lead(x, F0t + math.sin(k) * F1t).expand(
            *x.shape[:-1], n, n), jac_h=lambda x, u, k: lead(x, Ht).expand(*x.shape[:-1], m, n),
    )  # fmt: skip
    b0 = GaussianBelief(t(m0).reshape(*bs, n), t(S0).reshape(*bs, n, n))
    Y, U = t(ys).reshape(T, *bs, m), t(us).reshape(T, *bs, p)
    refs = []
    for i in range(N):
        Fs = [F0[i] + math.sin(k) * F1[i] for k in range(k0 + 1, k0 + T + 1)]
        args = (Fs, H[i], SQs @ SQs.swapaxes(1, 2), [SR[i] @ SR[i].T] * T, m0[i],
                S0[i] @ S0[i].T, ys[:, i])  # fmt: skip
        Bu = [Bm[i] @ us[k, i] for k in range(T)]
        refs.append((joint_gaussian_reference(*args, Bu=Bu), (args, Bu)))
    close = lambda a, b: np.testing.assert_allclose(a.numpy(), b, atol=1e-10, rtol=0)  # noqa: E731
    for filt in (ekf(), ekf(sqrt=False), sckf()):
        sm = smooth(filt, model, b0, Y, U, k0=k0)
        lag1 = smooth(filt, model, b0, Y, U, k0=k0, lag=1)
        for i, ((ms, Ps, cr, ll), (args, Bu)) in enumerate(refs):
            j = np.unravel_index(i, bs)
            close(sm.means[(slice(None), *j)], ms[1:]), close(sm.covs[(slice(None), *j)], Ps[1:])
            close(sm.cross_covs[(slice(None), *j)], cr)
            close(sm.initial.mean[j], ms[0]), close(sm.initial.cov[j], Ps[0])
            assert abs(float(sm.log_likelihood[j]) - ll) < 1e-10
            # x_1 given y_{1:2}: the fixed-lag (lag 1) row 0
            ms1, Ps1, cr1, _ = joint_gaussian_reference(*args, Bu=Bu, upto=2)
            close(lag1.means[(0, *j)], ms1[1]), close(lag1.covs[(0, *j)], Ps1[1])
            close(lag1.cross_covs[(0, *j)], cr1[0])


def test_smoother_float32_follows_the_float64_reference():
    g = np.random.default_rng(7)
    n, m, T = 2, 2, 5
    F, H = 0.5 * g.normal(size=(n, n)), g.normal(size=(m, n))
    Q, R, m0, P0 = 0.3 * np.eye(n), 0.5 * np.eye(m), g.normal(size=n), np.eye(n)
    ys = g.normal(size=(T, m))
    ys[1], ys[3, 0] = np.nan, np.nan
    ref = rts_reference(F, H, Q, R, m0, P0, ys)
    f32 = lambda a: t(a).float()  # noqa: E731
    model = linear_model(f32(F), f32(H), f32(np.linalg.cholesky(Q)), f32(np.linalg.cholesky(R)))
    b0 = GaussianBelief(f32(m0), f32(np.linalg.cholesky(P0)))
    for filt in (ekf(), ekf(sqrt=False), sckf()):
        sm = smooth(filt, model, b0, f32(ys))
        assert sm.means.dtype == sm.chols.dtype == sm.cross_covs.dtype == torch.float32
        np.testing.assert_allclose(sm.means.double().numpy(), ref["means"][1:], atol=1e-5)
        np.testing.assert_allclose(sm.covs.double().numpy(), ref["covs"][1:], atol=1e-5)
        np.testing.assert_allclose(sm.cross_covs.double().numpy(), ref["cross"], atol=1e-5)


def test_smooth_trajectory_takes_a_numpy_bool_for_sqrt():
    # GaussianFilter(sqrt=np.True_) is taken (check_flag); smooth_trajectory refused it
    g = np.random.default_rng(1)
    F, H, Q, R = np.array([[0.9, 0.2], [0.0, 0.7]]), np.array([[1.0, 0.5]]), np.eye(2), np.eye(1)
    m0, P0, ys = np.zeros(2), np.eye(2), g.normal(size=(4, 1))
    ref = rts_reference(F, H, Q, R, m0, P0, ys)
    model = linear_model(t(F), t(H), t(Q), t(R))
    b0 = GaussianBelief(t(m0), t(P0))
    tr = run(ekf(), model, b0, t(ys), keep_steps=True)
    for flag in (np.True_, np.False_):
        sm = smooth_trajectory(tr, b0, sqrt=flag)
        assert (sm.cond_chols is not None) == bool(flag)
        np.testing.assert_allclose(sm.means.numpy(), ref["means"][1:], atol=1e-12, rtol=0)
        np.testing.assert_allclose(sm.covs.numpy(), ref["covs"][1:], atol=1e-12, rtol=0)
    with pytest.raises(TypeError, match="sqrt must be a bool, got 1"):
        smooth_trajectory(tr, b0, sqrt=1)


# ------------------------------------------------------------------------------ EM
@pytest.mark.parametrize("learn", [("A", "C", "Q", "R", "init"), ("Q", "R")])
def test_one_em_step_equals_the_closed_form_m_step_per_element_of_a_2d_batch(learn):
    g = np.random.default_rng(0)
    bs, n, m, T, N = (2, 3), 2, 3, 5, 6
    A, C = 0.5 * g.normal(size=(N, n, n)), g.normal(size=(N, m, n))
    Q, R, P0 = 0.4 * np.eye(n), np.diag([0.5, 0.3, 0.7]), 1.2 * np.eye(n)
    m0, ys = g.normal(size=(N, n)), g.normal(size=(T, N, m))
    ys[2, 1], ys[0, 4], ys[T - 1] = np.nan, np.nan, np.nan
    ch = np.linalg.cholesky
    b0 = GaussianBelief(t(m0).reshape(*bs, n), t(ch(P0)).expand(*bs, n, n))
    fit = em_linear_gaussian(t(A).reshape(*bs, n, n), t(C).reshape(*bs, m, n), t(ch(Q)),
                             t(ch(R)), b0, t(ys).reshape(T, *bs, m), iterations=1, learn=learn)  # fmt: skip
    assert fit.A.shape == (*bs, n, n) and fit.chol_R.shape == (*bs, m, m)
    assert fit.trace.shape == (2, *bs)
    for i in range(N):
        j = np.unravel_index(i, bs)
        An, Cn, Qn, Rn, m0n, P0n, ll = numpy_em_step(A[i], C[i], Q, R, m0[i], P0, ys[:, i], learn)
        got = (fit.A[j], fit.C[j], (fit.chol_Q @ fit.chol_Q.mT)[j],
               (fit.chol_R @ fit.chol_R.mT)[j], fit.init.mean[j], fit.init.cov[j])  # fmt: skip
        for a, b in zip(got, (An, Cn, Qn, Rn, m0n, P0n)):
            np.testing.assert_allclose(a.numpy(), b, atol=1e-10, rtol=0)
        assert abs(float(fit.trace[(0, *j)]) - ll) < 1e-10
        ll1 = rts_reference(An, Cn, Qn, Rn, m0n, P0n, ys[:, i])["ll"]
        assert abs(float(fit.trace[(1, *j)]) - ll1) < 1e-10


def test_em_refuses_a_non_tensor_c_a_none_learn_and_bool_or_complex_matrices():
    # C as a list: ValueError "... got ()"; learn=None: "'NoneType' object is not iterable";
    # bool or complex matrices were cast (True read as 1, the imaginary part dropped)
    n = 2
    eye = torch.eye(n, dtype=d)
    b0 = GaussianBelief(torch.zeros(n, dtype=d), eye)
    ys = torch.ones(3, n, dtype=d)
    with pytest.raises(TypeError, match=r"C must be a torch.Tensor of shape \(m, 2\), got list"):
        em_linear_gaussian(eye, eye.tolist(), eye, eye, b0, ys)
    with pytest.raises(TypeError, match="learn must be a collection of names"):
        em_linear_gaussian(eye, eye, eye, eye, b0, ys, learn=None)
    for name in ("A", "C", "chol_Q", "chol_R"):
        for dtype in (torch.bool, torch.complex128):
            args = {"A": eye, "C": eye, "chol_Q": eye, "chol_R": eye}
            args[name] = torch.eye(n, dtype=dtype)
            with pytest.raises(TypeError, match=f"{name} must hold real numbers, got dtype"):
                em_linear_gaussian(**args, init=b0, ys=ys, iterations=1)
    # integer matrices are numbers: converted, as before
    fit = em_linear_gaussian(torch.eye(n, dtype=torch.int64), eye, eye, eye, b0, ys,
                             iterations=0)  # fmt: skip
    assert fit.A.dtype == d and torch.equal(fit.A, eye)


def test_linear_model_refuses_bad_matrices_and_a_size_one_belief_dim_against_several():
    n, B = 2, 3
    A = torch.tensor([0.5, 0.7, 0.9], dtype=d)[:, None, None] * torch.eye(n, dtype=d)
    C, SQ, SR = torch.ones(1, n, dtype=d), torch.eye(n, dtype=d), torch.eye(1, dtype=d)
    with pytest.raises(ValueError, match=r"A must have shape \(..., n, n\) and C \(..., m, n\)"):
        linear_model(torch.ones(2, 3, dtype=d), C, SQ, SR)  # (was: init.mean must have (..., 3))
    with pytest.raises(ValueError, match=r"got A \(2, 2\) and C \(1, 3\)"):
        linear_model(SQ, torch.ones(1, 3, dtype=d), SQ, SR)  # (was: mat1 and mat2 shapes ...)
    with pytest.raises(TypeError, match="A must be a torch.Tensor, got ndarray"):
        linear_model(np.eye(2), C, SQ, SR)  # (was accepted, then failed inside f)
    # per-series A (3, n, n) on a belief of batch (1,): the one series became three (the
    # sigma-point update then refused y (1, 1)) or torch's expand failed (EKF)
    b1 = GaussianBelief(torch.zeros(1, n, dtype=d), torch.eye(n, dtype=d).expand(1, n, n))
    ys = torch.ones(4, 1, 1, dtype=d)
    for filt in (ekf(), sckf()):
        with pytest.raises(ValueError, match=r"A has batch dims \(3,\), the states \(1,"):
            run(filt, linear_model(A, C, SQ, SR), b1, ys)
    # matrices with a dim of size 1 still broadcast over the belief's: equal to a loop
    bB = GaussianBelief(torch.zeros(B, n, dtype=d), torch.eye(n, dtype=d).expand(B, n, n))
    yB = torch.linspace(-1, 1, 4 * B, dtype=d).reshape(4, B, 1)
    got = run(sckf(), linear_model(A[:1], C, SQ, SR), bB, yB).log_likelihood
    for b in range(B):
        _, _, ll = kalman_filter_observed(A[0].numpy(), C.numpy(), np.eye(n), np.eye(1),
                                          np.zeros(n), np.eye(n), yB[:, b].numpy())  # fmt: skip
        assert abs(float(got[b]) - ll.sum()) < 1e-12


# ------------------------------------------------------------------------------ likelihood
def ar_model(p, fail="nan"):
    """``x_k = a x_{k-1} + w``, ``y_k = x_k + v``, outside ``a <= 1.2`` with a NaN in R
    (``fail="nan"``) or a ``ValueError`` from the builder (a user's domain check)."""
    a = p["a"]
    out = bool(a.detach() > 1.2)
    if out and fail == "raise":
        raise ValueError("a outside the model's domain")
    R = torch.full((1, 1), math.nan if out else 0.5, dtype=d)
    return linear_model(a.reshape(1, 1), torch.ones(1, 1, dtype=d), 0.3 * torch.eye(1, dtype=d), R)


AR_YS = torch.tensor([[1.0], [1.6], [2.5], [3.9], [6.0]], dtype=d)
AR_B0 = GaussianBelief(torch.ones(1, dtype=d), torch.eye(1, dtype=d))


@pytest.mark.parametrize("fail", ["nan", "raise"])
def test_an_error_puts_the_optimizer_instance_state_back_with_its_tensors(fail):
    # Adam (lr 0.3) from a = 0.5: iterates 0.8, 1.1, then 1.4, which is non-finite or refused
    # by the model builder. Before, the tensors went back to a = 1.1 on a FloatingPointError
    # but Adam's moments and step count kept the step to 1.4; a ValueError left the tensors
    # at the refused a = 1.4.
    build = lambda q: ar_model(q, fail)  # noqa: E731
    p = {"a": torch.tensor(0.5, dtype=d, requires_grad=True)}
    opt = torch.optim.Adam([p["a"]], lr=0.3)
    with pytest.raises(FloatingPointError if fail == "nan" else ValueError) as err:
        fit_likelihood(build, p, ekf(), AR_B0, AR_YS, optimizer=opt, steps=10)
    # the same fit stopped at the last iterate that evaluated: tensors and state agree
    q = {"a": torch.tensor(0.5, dtype=d, requires_grad=True)}
    ref_opt = torch.optim.Adam([q["a"]], lr=0.3)
    fit = fit_likelihood(build, q, ekf(), AR_B0, AR_YS, optimizer=ref_opt, steps=2)
    assert float(q["a"].detach()) == pytest.approx(1.1, abs=0.01)
    assert float(p["a"].detach()) == pytest.approx(float(q["a"].detach()), abs=1e-12)
    got, want = opt.state_dict()["state"], ref_opt.state_dict()["state"]
    assert got.keys() == want.keys()
    for key in want[0]:
        torch.testing.assert_close(got[0][key], want[0][key], rtol=0, atol=1e-12)
    if fail == "nan":
        torch.testing.assert_close(err.value.trace, fit.trace, rtol=0, atol=1e-12)
    # the restored optimiser goes on as the uninterrupted one does
    opt.param_groups[0]["lr"] = ref_opt.param_groups[0]["lr"] = 0.01
    fit_likelihood(build, p, ekf(), AR_B0, AR_YS, optimizer=opt, steps=2)
    fit_likelihood(build, q, ekf(), AR_B0, AR_YS, optimizer=ref_opt, steps=2)
    assert float(p["a"].detach()) == pytest.approx(float(q["a"].detach()), abs=1e-12)


def test_an_optimizer_instance_over_tensors_without_grad_is_refused_by_name():
    # was torch's "element 0 of tensors does not require grad and does not have a grad_fn"
    p = {"a": torch.tensor(0.5, dtype=d)}
    opt = torch.optim.SGD([p["a"]], lr=0.1)
    with pytest.raises(ValueError, match=r"params \['a'\] do not require grad"):
        fit_likelihood(ar_model, p, ekf(), AR_B0, AR_YS, optimizer=opt, steps=1)


def test_trace_and_one_sgd_step_follow_the_innovation_density_and_its_finite_differences():
    # per-series a (batch 2) and a shared log R; a missing and a partly observed row; numpy
    # scalars for steps and k0. One SGD step moves each parameter by lr / T times the
    # gradient of sum_series log p(y), here by central differences of the reference filter
    g = np.random.default_rng(5)
    B, T, m = 2, 4, 2
    H = np.array([[1.0, 0.0], [0.5, 1.0]])
    ys = g.normal(size=(T, B, m))
    ys[1, 0], ys[2, 1, 0] = np.nan, np.nan

    def build(p):
        F = torch.stack([torch.stack([p["a"], 0.1 * torch.ones_like(p["a"])], -1),
                         torch.tensor([0.0, 0.8], dtype=d).expand(B, 2)], -2)  # fmt: skip
        SR = p["lr"].exp() * torch.eye(m, dtype=d)
        return linear_model(F, t(H), 0.4 * torch.eye(2, dtype=d), SR)

    def ref_ll(a, lr):
        tot = []
        for b in range(B):
            F = np.array([[a[b], 0.1], [0.0, 0.8]])
            _, _, ll = kalman_filter_observed(F, H, 0.16 * np.eye(2), math.exp(2 * lr) * np.eye(m),
                                              np.zeros(2), np.eye(2), ys[:, b])  # fmt: skip
            tot.append(ll.sum())
        return np.array(tot)

    a0, lr0, step = np.array([0.6, 0.9]), -0.3, 0.05
    b0 = GaussianBelief(torch.zeros(B, 2, dtype=d), torch.eye(2, dtype=d).expand(B, 2, 2))
    params = {"a": t(a0), "lr": torch.tensor(lr0, dtype=d)}
    fit = fit_likelihood(build, params, ekf(), b0, t(ys), steps=np.int64(1), k0=np.int64(0),
                         optimizer=lambda q: torch.optim.SGD(q, lr=step))  # fmt: skip
    np.testing.assert_allclose(fit.trace[0].numpy(), ref_ll(a0, lr0), atol=1e-12, rtol=0)
    h = 1e-6
    da = [(ref_ll(a0 + h * e, lr0).sum() - ref_ll(a0 - h * e, lr0).sum()) / (2 * h)
          for e in np.eye(B)]  # fmt: skip
    dr = (ref_ll(a0, lr0 + h).sum() - ref_ll(a0, lr0 - h).sum()) / (2 * h)
    np.testing.assert_allclose(fit.params["a"].numpy(), a0 + step * np.array(da) / T, atol=1e-8)
    assert float(fit.params["lr"]) == pytest.approx(lr0 + step * dr / T, abs=1e-8)
    np.testing.assert_allclose(fit.trace[1].numpy(), ref_ll(fit.params["a"].numpy(),
                               float(fit.params["lr"])), atol=1e-12, rtol=0)  # fmt: skip
