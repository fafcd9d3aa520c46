"""Audit of learners/ros_elm.py and prognosis/learner_trend.py against exact references written
here (ridge and Bayesian linear-regression closed forms, a linear recursion by hand)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prognos_torch.learners import ELM, ros_elm_forecast, ros_elm_init, ros_elm_update
from prognos_torch.prognosis import fit_learner_trend, fit_learner_trends, fit_trends

F64 = torch.float64


def _gen(seed):
    return torch.Generator().manual_seed(seed)


# ------------------------------------------------------------------------------ ROS-ELM
def _ridge(H, T, lam):
    """``argmin |H b - T|^2 + lam |b|^2`` by least squares on ``[H; sqrt(lam) I]``, and
    ``(H^T H + lam I)^{-1}`` by a solve."""
    L = H.shape[-1]
    A = torch.cat([H, math.sqrt(lam) * torch.eye(L, dtype=F64)])
    b = torch.cat([T, torch.zeros(L, dtype=F64)])
    beta = torch.linalg.lstsq(A, b[:, None], driver="gelsd").solution[:, 0]
    K = torch.linalg.solve(H.T @ H + lam * torch.eye(L, dtype=F64), torch.eye(L, dtype=F64))
    return beta, K


def test_ros_elm_batch_and_sequential_solutions_are_the_ridge_closed_form():
    """Step I (Eq. 54) on N0 values and Step II (Eq. 55-56) after each further value give the
    ridge solution of all pairs seen so far, per channel and run; NumPy p and lam and a
    float32 z0 are taken; the window holds the last p values."""
    p, L, C, R = 3, 5, 2, 2
    g = _gen(0)
    elms = [ELM(p, L, generator=g) for _ in range(C)]
    z = torch.randn(16, R, C, generator=g, dtype=F64)
    lam = 0.25
    st = ros_elm_init(elms, z[:9].float(), np.int64(p), np.float32(lam))
    zr = torch.cat([z[:9].float().double(), z[9:]])  # (z0 was rounded to float32)
    seen = 9
    for k in (9, 12, 16):
        for j in range(seen, k):
            st = ros_elm_update(elms, st, z[j])
        seen = k
        for c in range(C):
            for r in range(R):
                s = zr[:k, r, c]
                X, T = s.unfold(0, p, 1)[:-1], s[p:]
                beta, K = _ridge(elms[c].hidden(X), T, lam)
                torch.testing.assert_close(st.beta[c][r], beta, rtol=1e-9, atol=1e-10)
                torch.testing.assert_close(st.K[c][r], K, rtol=1e-9, atol=1e-10)
        assert st.n_seen == k - p
        torch.testing.assert_close(st.window, zr[k - p : k].movedim(0, -1), rtol=0, atol=0)
    # the forecast is h(window) beta, the window absorbing the forecasts (Eq. 47, 12-14)
    out = ros_elm_forecast(elms, st, np.int64(2))
    w = st.window.clone()
    for j in range(2):
        zhat = torch.stack([(elms[c].hidden(w[:, c]) * st.beta[c]).sum(-1) for c in range(C)], -1)
        torch.testing.assert_close(out[j], zhat, rtol=1e-12, atol=1e-12)
        w = torch.cat([w[..., 1:], zhat[..., None]], -1)


def test_ros_elm_init_refuses_no_channel_a_static_learner_and_a_multi_output_elm():
    """An empty elms gave a state with no channel; a learner without a random hidden layer an
    AttributeError on 'a'; an ELM with n_out=2 was taken (its second output ignored)."""
    z0 = torch.randn(12, 1, dtype=F64, generator=_gen(1))
    with pytest.raises(ValueError, match=r"one ELM per measurement channel \(C >= 1\)"):
        ros_elm_init([], z0[:, :0], 2, 0.1)
    lin = torch.nn.Linear(2, 1).double()
    with pytest.raises(TypeError, match=r"elms\[0\] must be an ELM .* got Linear"):
        ros_elm_init([lin], z0, 2, 0.1)
    with pytest.raises(ValueError, match=r"elms\[0\] has n_out=2: .* n_out=1"):
        ros_elm_init([ELM(2, 4, 2)], z0, 2, 0.1)


def test_ros_elm_update_and_forecast_name_a_foreign_state_and_elms_of_another_p():
    """A state that is not a ROSELMState gave an AttributeError; ELMs of another input size an
    error on an unnamed 'x'."""
    elms = [ELM(2, 4)]
    st = ros_elm_init(elms, torch.randn(12, 1, dtype=F64, generator=_gen(2)), 2, 0.1)
    one = torch.zeros(1, dtype=F64)
    for call in (lambda s: ros_elm_update(elms, s, one), lambda s: ros_elm_forecast(elms, s, 1)):
        with pytest.raises(TypeError, match="state must be a ROSELMState .* got NoneType"):
            call(None)
    other = [ELM(3, 4)]
    with pytest.raises(ValueError, match=r"elms\[0\] has n_in=3, the state's window holds p=2"):
        ros_elm_update(other, st, one)
    with pytest.raises(ValueError, match=r"elms\[0\] has n_in=3, the state's window holds p=2"):
        ros_elm_forecast(other, st, 1)


def _devices():
    out = ["meta"]
    if torch.cuda.is_available():
        out.append("cuda")
    return out


@pytest.mark.parametrize("device", _devices())
def test_ros_elm_update_names_z_on_another_device(device):
    """z on another device than the state failed inside the finiteness check ('meta') or in
    the update's arithmetic ('cuda'), naming neither z nor the devices; the state is kept."""
    elms = [ELM(2, 4)]
    st = ros_elm_init(elms, torch.randn(12, 1, dtype=F64, generator=_gen(3)), 2, 0.1)
    z = torch.zeros(1, dtype=F64, device=device)
    with pytest.raises(ValueError, match=f"z is on {device}.*, the state on cpu"):
        ros_elm_update(elms, st, z)
    assert st.n_seen == 10  # (immutable: nothing half-written)


def test_ros_elm_forecast_checks_a_static_learners_output_shape():
    """A static learner's output must be (..., 1): an (..., 2) output was read by its first
    column silently, a (...,) one failed on 'new_value'. A conforming one gives the exact
    linear recursion."""
    from prognos_torch.learners.ros_elm import ROSELMState

    win = torch.tensor([[[1.0, 2.0]], [[3.0, 5.0]]], dtype=F64)  # (R=2, C=1, p=2)
    empty = win.new_zeros(0)
    st = ROSELMState(win, (empty,), (empty,), 0)
    two = lambda w: torch.stack([w[..., -1], w[..., -2]], -1)  # noqa: E731
    flat = lambda w: w.sum(-1)  # noqa: E731
    for lr, got in ((two, r"\(2, 2\)"), (flat, r"\(2,\)")):
        with pytest.raises(ValueError, match=rf"elms\[0\] .* to \(2, 1\) .* got {got}"):
            ros_elm_forecast([lr], st, 2)
    ar = lambda w: 0.5 * w[..., -1:] + 0.25 * w[..., -2:-1]  # noqa: E731
    out = ros_elm_forecast([ar], st, 3)
    ref = []
    a, b = win[:, 0, 0].clone(), win[:, 0, 1].clone()
    for _ in range(3):
        a, b = b, 0.5 * b + 0.25 * a
        ref.append(b)
    torch.testing.assert_close(out[..., 0], torch.stack(ref), rtol=0, atol=1e-15)


# ------------------------------------------------------------------------------ learner trend
@pytest.fixture(scope="module")
def level():
    g = _gen(0)
    t = torch.sort(torch.rand(30, generator=g, dtype=F64) * 10).values
    y = 1.0 + 0.5 * torch.exp(0.3 * t + 0.05 * torch.randn(30, generator=g, dtype=F64))
    y[7] = math.nan  # a missing value
    return fit_trends(t, y, phi=1.0, sigma0=0.05, shapes=("exponential",), filter="ekf")[
        "exponential"
    ]


def test_learner_trend_without_walk_is_bayesian_linear_regression(level):
    """With drift=0 the Kalman optimiser's belief after the data up to an index is the
    conjugate posterior of g = F theta with the module docstring's prior and noise R, whatever
    the block size; predictive_std is sqrt(f^T P f)."""
    L = 6
    fit = fit_learner_trend(level, n_hidden=L, drift=0.0, snapshots=(12,), max_steps=4)
    z, t = level.z, level.t
    ok = ~torch.isnan(z)
    zz, tt = z[ok], t[ok]
    R = float(level.noise.meas) + float(level.a[ok].median()) + float(level.noise.wander)
    rise, sd = float(zz.max() - zz.min()), float(zz.std())
    P0 = torch.tensor([(10 * sd) ** 2, (3 * rise) ** 2] + [rise**2 / (L / 4)] * L, dtype=F64)
    m0 = torch.zeros(L + 2, dtype=F64)
    m0[0] = zz[0]
    F = fit.module.features((tt - t[0]) / (t[-1] - t[0]))
    for index in (12, -1):
        upto = int(ok[: index % z.shape[0] + 1].sum())
        A = torch.diag(1 / P0) + F[:upto].T @ F[:upto] / R
        mean = torch.linalg.solve(A, m0 / P0 + F[:upto].T @ zz[:upto] / R)
        cov = torch.linalg.solve(A, torch.eye(L + 2, dtype=F64))
        b = fit.parameter_belief(index)
        torch.testing.assert_close(b.mean, mean, rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(b.chol @ b.chol.mT, cov, rtol=1e-8, atol=1e-10)
        tq = torch.tensor([5.0, 10.0, 12.0], dtype=F64)
        f = fit.module.features(fit.tau(tq))
        ref = torch.einsum("ji,ik,jk->j", f, cov, f).sqrt()
        torch.testing.assert_close(fit.predictive_std(tq, index), ref, rtol=1e-8, atol=1e-12)
        # float32 times (refused before, by the float64 ELM, as an unnamed 'x')
        torch.testing.assert_close(
            fit.predictive_std(tq.float(), index), ref, rtol=1e-8, atol=1e-12
        )


def test_learner_trend_index_out_of_range_is_refused_not_wrapped(level):
    """index % n read n + 5 as 5 (another snapshot's belief) and n as 0; a bool was taken as
    an index. TrendFit refuses an index out of range too."""
    n = level.t.shape[0]
    fit = fit_learner_trend(level, snapshots=(5,), max_steps=3)
    torch.testing.assert_close(fit.parameter_belief(np.int64(5)).mean, fit.snapshots[5].mean)
    torch.testing.assert_close(fit.parameter_belief(-n + 5).mean, fit.snapshots[5].mean)
    for bad in (n + 5, n, -n - 1):
        with pytest.raises(ValueError, match=rf"index must be an observation index in \[-{n}"):
            fit.parameter_belief(bad)
    with pytest.raises(TypeError, match="index must be an int"):
        fit.parameter_belief(True)
    grid = torch.tensor([10.5, 11.0], dtype=F64)
    with pytest.raises(ValueError, match=rf"index must be an observation index in \[-{n}"):
        fit.first_passage(n + 5, 30.0, grid, 4, _gen(1))
    with pytest.raises(ValueError, match=rf"index must be an observation index in \[-{n}"):
        fit.predictive_std(grid, n + 5)


def test_fit_learner_trend_refuses_bad_snapshots(level):
    """A snapshot at n was recorded at 0 (the prior), 2.7 at 2, True at 1; a bare int failed
    with "'int' object is not iterable"."""
    n = level.t.shape[0]
    for bad in (n, n + 2, -n - 1):
        with pytest.raises(ValueError, match=r"snapshots\[1\] must be an observation index"):
            fit_learner_trend(level, snapshots=(3, bad), max_steps=3)
    for bad in (2.7, True):
        with pytest.raises(TypeError, match=r"snapshots\[0\] must be an int"):
            fit_learner_trend(level, snapshots=(bad,), max_steps=3)
    with pytest.raises(TypeError, match="snapshots must be a sequence of observation indices"):
        fit_learner_trend(level, snapshots=5, max_steps=3)
    ok = fit_learner_trend(level, snapshots=np.array([4, -3]), max_steps=3)
    assert sorted(ok.snapshots) == [4, n - 3, n - 1]
    # an integer tensor of indices is read as its values; a float one is refused
    ok = fit_learner_trend(level, snapshots=torch.tensor([4, -3]), max_steps=3)
    assert sorted(ok.snapshots) == [4, n - 3, n - 1]
    with pytest.raises(TypeError, match=r"snapshots\[0\] must be an int"):
        fit_learner_trend(level, snapshots=torch.tensor([4.0]), max_steps=3)


def test_fit_learner_trend_refuses_bad_max_steps_seed_and_drift(level):
    """max_steps=0 raised ZeroDivisionError and -1, 2.5 or True were taken; seed 1.7 was read as
    1, '3' as 3 and True as 1; drift=inf was refused as 'Q contains non-finite values'.
    NumPy values are taken and give the same fit as Python ones."""
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="max_steps must be an int >= 1"):
            fit_learner_trend(level, max_steps=bad)
    for bad in (1.7, "3", True):
        with pytest.raises(TypeError, match="seed must be an int"):
            fit_learner_trend(level, seed=bad, max_steps=3)
    for bad in (math.inf, math.nan, -1.0, True):
        with pytest.raises(ValueError, match="drift must be a finite number >= 0"):
            fit_learner_trend(level, drift=bad, max_steps=3)
    a = fit_learner_trend(level, seed=3, max_steps=3, drift=0.5, n_hidden=4)
    b = fit_learner_trend(level, seed=np.int64(3), max_steps=np.int64(3),
                          drift=np.float64(0.5), n_hidden=np.int64(4))  # fmt: skip
    torch.testing.assert_close(b.parameter_belief().mean, a.parameter_belief().mean,
                               rtol=0, atol=0)  # fmt: skip


def test_fit_learner_trends_takes_numpy_members_and_an_iterator_of_snapshots(level):
    """members=np.int64(2) raised OverflowError in (seed * members + j) % 2**64; an iterator of
    snapshots gave its indices to the first member only. Member j is fit_learner_trend with
    seed seed * members + j."""
    kw = dict(max_steps=3, n_hidden=4)
    pool = fit_learner_trends(level, members=np.int64(2), seed=np.int64(5),
                              snapshots=iter((6,)), **kw)  # fmt: skip
    for j, m in enumerate(pool.members):
        one = fit_learner_trend(level, seed=10 + j, snapshots=(6,), **kw)
        assert 6 in m.snapshots
        torch.testing.assert_close(m.parameter_belief(6).mean, one.parameter_belief(6).mean,
                                   rtol=0, atol=0)  # fmt: skip
    with pytest.raises(TypeError, match="seed must be an int"):
        fit_learner_trends(level, members=2, seed=1.5, **kw)


def test_learner_trend_first_passage_checks_keep_and_grid(level):
    """keep=2.5 failed on slice indices, True kept one path and -1 none; a list grid raised
    AttributeError, a float32 grid was refused by the float64 ELM as an unnamed 'x' (it now
    gives the float64 grid's crossings in the grid's dtype), a grid on another device failed
    on its values."""
    fit = fit_learner_trend(level, max_steps=3)
    grid = torch.arange(10.5, 40.0, 0.5, dtype=F64)  # (exact in float32)
    lv = float(level.to_y(level.z[~torch.isnan(level.z)].max())) * 1.5
    for bad in (2.5, True, -1):
        with pytest.raises(ValueError, match="keep must be a non-negative int"):
            fit.first_passage(-1, lv, grid, 8, _gen(1), keep=bad)
    ref = fit.first_passage(-1, lv, grid, 64, _gen(1), keep=np.int64(3))
    assert ref.paths.shape == (3, grid.shape[0])
    assert bool(torch.isfinite(ref.times).any())
    got = fit.first_passage(-1, lv, grid.float(), 64, _gen(1), keep=3)
    assert got.times.dtype == torch.float32
    torch.testing.assert_close(got.times.double(), ref.times, rtol=0, atol=0)
    torch.testing.assert_close(got.paths, ref.paths, rtol=0, atol=0)
    with pytest.raises(TypeError, match=r"grid must be a torch.Tensor of shape \(J,\)"):
        fit.first_passage(-1, lv, [10.5, 11.0], 8, _gen(1))
    with pytest.raises(ValueError, match="grid is on meta, the fit on cpu"):
        fit.first_passage(-1, lv, grid.to("meta"), 8, _gen(1))
    with pytest.raises(ValueError, match="t is on meta, the fit on cpu"):
        fit.predictive_std(grid.to("meta"))
