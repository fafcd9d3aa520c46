"""Audit of the Kalman optimisers (EKF, SRUKF, ImSRUKF; ``prognos_torch.optim.kalman``).

References are exact and written here: a plain Kalman filter (recursive least squares with
the random walk's ``Q`` added before each update) for a model linear in its parameters, the
Sage-Husa recursion of paper 003 Eq. 41/43 in the optimiser's form (diagonal ``Q``, post-fit
``R``, prior weight ``k0``), and the state before a failed step.
"""

from __future__ import annotations

import copy
import io

import numpy as np
import pytest
import torch
from torch import nn

from prognos_torch.optim import EKF, SRUKF, ImSRUKF, KalmanOptimizer
from prognos_torch.optim.kalman import OPTIMIZER_NOISE

D, N_OUT, B = 3, 2, 4


def _data(T: int = 5, seed: int = 1, n_out: int = N_OUT):
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(T, B, D, generator=g, dtype=torch.float64)
    Y = torch.randn(T, B, n_out, generator=g, dtype=torch.float64)
    return X, Y


def _lin(n_out: int = N_OUT, seed: int = 0) -> nn.Linear:
    torch.manual_seed(seed)
    return nn.Linear(D, n_out, bias=False, dtype=torch.float64)


def _close(a: torch.Tensor, b: torch.Tensor, atol: float) -> None:
    """``|a - b| <= atol`` (the first call of torch's assert_close costs about 0.7 s)."""
    np.testing.assert_allclose(a.detach().numpy(), b.detach().numpy(), rtol=0, atol=atol)


def _design(x: np.ndarray, n_out: int) -> np.ndarray:
    """``H`` of ``y = x W^T`` flattened sample after sample, ``theta = W`` row-major."""
    H = np.zeros((x.shape[0] * n_out, D * n_out))
    for b in range(x.shape[0]):
        for o in range(n_out):
            H[b * n_out + o, o * D : (o + 1) * D] = x[b]
    return H


def _plain_kf(theta0, P0, Q, R1, lr, X, Y):
    """Random walk + linear measurement: P += Q, then the update with the observed entries
    (``R = kron(I_B, R1) / lr``, its observed block)."""
    n = theta0.shape[0]
    m, P = theta0.copy(), P0 * np.eye(n)
    for x, y in zip(X, Y):
        H = _design(x, y.shape[-1])
        R = np.kron(np.eye(x.shape[0]), R1) / lr
        P = P + Q * np.eye(n)
        y = y.reshape(-1)
        ok = ~np.isnan(y)
        if ok.any():
            Ho = H[ok]
            S = Ho @ P @ Ho.T + R[np.ix_(ok, ok)]
            K = np.linalg.solve(S, Ho @ P).T
            m = m + K @ (y[ok] - Ho @ m)
            P = P - K @ S @ K.T
    return m, P


# --------------------------------------------------------------------------- exact references
@pytest.mark.parametrize("filt", ["ekf", "srukf", "ukf", "sckf"])
def test_linear_model_with_missing_targets_correlated_R_and_lr_equals_a_plain_kalman_filter(
    filt,
):
    X, Y = _data()
    Y[1, 2, 0] = float("nan")  # one output of a sample
    Y[2] = float("nan")  # a whole mini-batch: the random walk's prediction only
    Y[3, 0, 1] = float("nan")
    R1 = torch.tensor([[0.3, 0.1], [0.1, 0.5]], dtype=torch.float64)
    theta0 = torch.randn(D * N_OUT, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    m, P = _plain_kf(theta0.numpy(), 0.7, 0.01, R1.numpy(), 0.5, X.numpy(), Y.numpy())
    lin = _lin()
    opt = KalmanOptimizer(lin, filter=filt, P0=0.7, Q=0.01, R=R1, lr=0.5, theta0=theta0)
    for x, y in zip(X, Y):
        opt.step(x, y)
    np.testing.assert_allclose(opt.theta.numpy(), m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(opt.parameter_covariance().numpy(), P, rtol=0, atol=1e-12)
    np.testing.assert_allclose(lin.weight.detach().reshape(-1).numpy(), m, rtol=0, atol=1e-12)


def test_runs_and_per_run_data_equal_separate_plain_kalman_filters():
    X, Y = _data()
    g = torch.Generator().manual_seed(3)
    theta0 = torch.randn(3, D * N_OUT, generator=g, dtype=torch.float64)
    Yr = torch.stack([Y, Y + 1.0, Y - 0.5], 1)  # (T, R, B, n_out)
    Yr[2, 1] = float("nan")  # run 1 skips step 2
    opt = EKF(_lin(), P0=0.7, Q=0.01, R=0.2, runs=3, per_run_data=True, theta0=theta0)
    for t in range(X.shape[0]):
        res = opt.step(X[t].expand(3, B, D), Yr[t])
        assert res.loss.shape == (3,)
    for r in range(3):
        m, P = _plain_kf(theta0[r].numpy(), 0.7, 0.01, 0.2 * np.eye(N_OUT), 1.0, X.numpy(),
                         Yr[:, r].numpy())  # fmt: skip
        np.testing.assert_allclose(opt.theta[r].numpy(), m, rtol=0, atol=1e-12)
        np.testing.assert_allclose(opt.parameter_covariance()[r].numpy(), P, rtol=0, atol=1e-12)


def test_srukf_equals_ekf_on_a_linear_model_and_float32_parameters_follow_float64():
    X, Y = _data()
    runs = [(torch.float64, "ekf"), (torch.float64, "srukf"), (torch.float32, "srukf")]
    opts = []
    for dtype, filt in runs:
        o = KalmanOptimizer(_lin().to(dtype), filter=filt, P0=0.5, Q=1e-3, R=0.1)
        for x, y in zip(X.to(dtype), Y.to(dtype)):
            o.step(x, y)
        opts.append(o)
    ekf, srukf, srukf32 = opts
    _close(srukf.theta, ekf.theta, 1e-12)
    _close(srukf.parameter_covariance(), ekf.parameter_covariance(), 1e-12)
    # the model in float32, the belief in float64
    assert srukf32.theta.dtype == torch.float64 and srukf32.module.weight.dtype == torch.float32
    _close(srukf32.theta, ekf.theta, 1e-6)


def test_imsrukf_follows_the_sage_husa_recursion_of_eq_41_and_43():
    """OPTIMIZER_NOISE: diagonal Q (Eq. 41), post-fit R (the class docstring), ``d_k = 1 /
    (k0 - 1 + k)``, floors ``1e-6`` times the prior's mean variance."""
    n_out = 1
    X, Y = _data(T=6, n_out=n_out)
    theta0 = torch.randn(D, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    P0, Q0, R0, k0 = 0.7, 0.01, 0.3, OPTIMIZER_NOISE.k0
    m, P = theta0.numpy().copy(), P0 * np.eye(D)
    Qd, Rd = np.full(D, Q0), np.full(B, R0)
    for k, (x, y) in enumerate(zip(X.numpy(), Y.numpy()), 1):
        H, Rm, P_prev = x, np.diag(Rd), P
        Pp = P + np.diag(Qd)
        S = H @ Pp @ H.T + Rm
        e = y.reshape(-1) - H @ m
        K = np.linalg.solve(S, H @ Pp).T
        m, P = m + K @ e, Pp - K @ S @ K.T
        d = 1.0 / (k0 - 1 + k)
        term_Q = (K @ e) ** 2 + np.diag(P) - np.diag(P_prev)  # Eq. 41, diagonal
        rho = Rm @ np.linalg.solve(S, e)  # post-fit residual
        term_R = rho**2 + np.diag(Rm - Rm @ np.linalg.solve(S, Rm))
        Qd = np.maximum((1 - d) * Qd + d * term_Q, 1e-6 * Q0)
        Rd = np.maximum((1 - d) * Rd + d * term_R, 1e-6 * R0)
    opt = ImSRUKF(_lin(n_out), P0=P0, Q=Q0, R=R0, theta0=theta0)
    for x, y in zip(X, Y):
        opt.step(x, y)
    ns = opt.filter_state.noise
    np.testing.assert_allclose(opt.theta.numpy(), m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(opt.parameter_covariance().numpy(), P, rtol=0, atol=1e-12)
    np.testing.assert_allclose(torch.diagonal(ns.Q).numpy(), Qd, rtol=0, atol=1e-14)
    np.testing.assert_allclose(torch.diagonal(ns.R).numpy(), Rd, rtol=0, atol=1e-14)


# --------------------------------------------------------------------------- fixes
@pytest.mark.parametrize("case", ["R of another output size", "lr of group 1", "batch size"])
def test_a_group_that_fails_leaves_every_group_and_the_module_as_before(case):
    """Formerly group 0 was updated (belief, step count, module weights) before group 1
    raised: the optimiser was left half-stepped."""
    X, Y = _data()
    lin = nn.Linear(D, N_OUT, dtype=torch.float64)
    second = {"params": [lin.bias]}
    if case == "R of another output size":
        second["R"] = torch.eye(3, dtype=torch.float64)
    if case == "batch size":
        second["noise"] = copy.deepcopy(OPTIMIZER_NOISE)
    opt = KalmanOptimizer(
        [{"params": [lin.weight]}, second], module=lin, filter="srukf", P0=0.5, Q=1e-3
    )
    x, y = X[0], Y[0]
    if case == "batch size":
        opt.step(x, y)
        x, y = x[:3], y[:3]
    if case == "lr of group 1":
        opt.param_groups[1]["lr"] = 0.0
    theta, chol = opt.theta, opt.belief.chol
    weight, steps = lin.weight.detach().clone(), opt.state["kalman"]["step"]
    with pytest.raises(ValueError):
        opt.step(x, y)
    assert torch.equal(opt.theta, theta) and torch.equal(opt.belief.chol, chol)
    assert torch.equal(lin.weight.detach(), weight)
    assert opt.state["kalman"]["step"] == steps


class _SqrtNet(nn.Module):
    """BatchNorm, then a square root: NaN outputs where the linear layer is negative."""

    def __init__(self):
        super().__init__()
        self.bn = nn.BatchNorm1d(D, dtype=torch.float64)
        self.lin = nn.Linear(D, N_OUT, dtype=torch.float64)

    def forward(self, x):
        return torch.sqrt(self.lin(self.bn(x)))


def test_a_failed_step_puts_back_the_batch_norm_running_statistics():
    """Formerly the step's one forward pass had moved the running statistics (and the batch
    count) before the update was refused as non-finite."""
    X, Y = _data()
    torch.manual_seed(0)
    net = _SqrtNet()
    opt = SRUKF(net)
    saved = [b.clone() for b in net.bn.buffers()]
    with pytest.raises(ValueError, match="non-finite estimate"):
        opt.step(X[0], Y[0])
    assert all(torch.equal(a, b) for a, b in zip(net.bn.buffers(), saved))


def test_steps_undo_the_batch_norm_running_statistics_of_the_rows_before_a_failing_one():
    X, Y = _data(T=3)
    Y[2, 0, 0] = float("inf")
    torch.manual_seed(0)
    net = nn.Sequential(nn.BatchNorm1d(D), nn.Linear(D, N_OUT)).double()
    opt = SRUKF(net)
    saved = [b.clone() for b in net[0].buffers()]
    with pytest.raises(ValueError, match="row 2 of 3"):
        opt.steps(X, Y)
    assert all(torch.equal(a, b) for a, b in zip(net[0].buffers(), saved))
    assert int(net[0].num_batches_tracked) == 0


@pytest.mark.parametrize("value", [np.float32(1.25), np.int64(2)])
def test_a_numpy_fading_factor_is_accepted_as_its_python_number(value):
    """Formerly ``TypeError: fading must be None, True/False, a float >= 1 or
    StrongTracking`` for ``np.float32`` and ``np.int64`` (``np.float64`` is a float)."""
    X, Y = _data(T=2)
    a = KalmanOptimizer(_lin(), filter="ekf", fading=value)
    b = KalmanOptimizer(_lin(), filter="ekf", fading=float(value))
    assert a.filter.fading == float(value)
    for x, y in zip(X, Y):
        a.step(x, y)
        b.step(x, y)
    assert torch.equal(a.theta, b.theta)


def test_numpy_scalar_options_are_kept_as_python_numbers_that_torch_load_reads():
    """Formerly ``runs``, ``chunk_size``, ``lr``, ``P0``, ... given as NumPy scalars were kept
    in ``param_groups``, which ``state_dict()`` saves: ``torch.load`` (``weights_only=True``,
    its default) refused the saved file (``UnpicklingError``)."""
    X, Y = _data(T=2)
    kw = dict(P0=np.float64(0.5), Q=np.float32(1e-3), R=np.float64(0.2), lr=np.float64(0.5),
              fading=np.float64(1.1), chunk_size=np.int64(4))  # fmt: skip
    opt = KalmanOptimizer(_lin(), filter="srukf", runs=np.int64(2), **kw)
    ref = KalmanOptimizer(_lin(), filter="srukf", runs=2, **{k: v.item() for k, v in kw.items()})
    for x, y in zip(X, Y):
        opt.step(x, y)
        ref.step(x, y)
    assert torch.equal(opt.theta, ref.theta)
    group = opt.param_groups[0]
    for key in ("P0", "Q", "R", "lr", "fading", "chunk_size", "runs"):
        assert type(group[key]) in (int, float), key
    # what state_dict() saves of the groups (its first call imports torch._dynamo: ~1.5 s)
    saved = [{k: v for k, v in g.items() if k != "params"} for g in opt.param_groups]
    buf = io.BytesIO()
    torch.save(saved, buf)
    buf.seek(0)
    assert torch.load(buf) == saved  # weights_only=True


def test_numpy_scalar_options_of_an_added_group_are_python_numbers():
    lin = nn.Linear(D, N_OUT, dtype=torch.float64)
    opt = KalmanOptimizer([lin.weight], module=lin)
    opt.add_param_group({"params": [lin.bias], "P0": np.float64(0.3), "lr": np.float32(0.5)})
    assert type(opt.param_groups[1]["P0"]) is float and type(opt.param_groups[1]["lr"]) is float


@pytest.mark.parametrize(
    "name, value",
    [
        ("R", True),
        ("R", np.bool_(True)),
        ("R", torch.tensor(True)),
        ("R", torch.tensor([1.0 + 1.0j, 1.0])),
        ("P0", np.bool_(True)),
        ("P0", np.array([True] * (D * N_OUT))),
        ("Q", torch.tensor(1e-3 + 0j)),
        ("Q", 1e-3 + 0j),
    ],
)
def test_a_bool_or_complex_covariance_is_refused_by_name(name, value):
    """Formerly ``R=True`` (and any NumPy/torch bool, for ``P0`` and ``Q`` too) was read as a
    variance of 1, and a complex value lost its imaginary part with a warning."""
    with pytest.raises(TypeError, match=f"{name} must be a real number, a vector or a matrix"):
        KalmanOptimizer(_lin(), **{name: value})


def test_a_parameter_replaced_by_a_new_object_is_refused_not_silently_left_untrained():
    """Formerly the step read the new parameter (its values became the mean) but wrote the
    update into the old object: the module's weight never changed."""
    X, Y = _data(T=2)
    lin = _lin()
    opt = EKF(lin, P0=0.5, Q=1e-3, R=0.1)
    opt.step(X[0], Y[0])
    lin.weight = nn.Parameter(torch.zeros(N_OUT, D, dtype=torch.float64))
    theta = opt.theta
    with pytest.raises(ValueError, match="'weight' was replaced by a new Parameter object"):
        opt.step(X[1], Y[1])
    assert torch.equal(opt.theta, theta)
    # values written in place are continued from (the documented way)
    lin2 = _lin()
    opt2 = EKF(lin2, P0=0.5, Q=1e-3, R=0.1)
    with torch.no_grad():
        lin2.weight.zero_()
    opt2.step(X[1], Y[1])
    assert not torch.equal(lin2.weight.detach(), torch.zeros(N_OUT, D, dtype=torch.float64))


@pytest.mark.parametrize(
    "edit",
    [
        lambda e: e.pop("mean"),
        lambda e: e.pop("chol"),
        lambda e: e.pop("step"),
        lambda e: e.__setitem__("step", "3"),
        lambda e: e["mean"].fill_(float("nan")),
    ],
    ids=["no mean", "no chol", "no step", "step a str", "NaN mean"],
)
def test_load_state_dict_names_a_malformed_belief_entry(edit):
    """Formerly ``KeyError: 'mean'`` (or a ``TypeError`` from ``"3" + 1`` at the next step)."""
    X, Y = _data(T=1)
    opt = SRUKF(_lin(), P0=0.5, Q=1e-3, R=0.1)
    opt.step(X[0], Y[0])
    sd = copy.deepcopy(opt.state_dict())
    edit(sd["state"]["kalman"])
    fresh = SRUKF(_lin(seed=5), P0=0.5, Q=1e-3, R=0.1)
    theta = fresh.theta
    with pytest.raises(ValueError, match=r"state_dict(\['state'\]\['kalman'\]| belief 'kalman')"):
        fresh.load_state_dict(sd)
    assert torch.equal(fresh.theta, theta)


def test_state_dict_and_load_state_dict_skip_torch_optims_dynamo_wrapper(monkeypatch):
    """``torch.optim.Optimizer.state_dict``/``load_state_dict`` are wrapped in
    ``_disable_dynamo``, whose first call imports ``torch._dynamo`` (formerly about 1.5 s, more
    on a busy machine, at a fresh process's first save or ``fit(early_stopping=...)``). The
    Kalman optimiser calls the unwrapped methods, as it does for ``add_param_group``; the
    round trip stays bit-identical."""

    def wrapped(*args, **kwargs):
        raise AssertionError("the dynamo-wrapped torch.optim method was called")

    X, Y = _data(T=2)
    opt = SRUKF(_lin(), P0=0.5, Q=1e-3, R=0.1)
    opt.step(X[0], Y[0])
    monkeypatch.setattr(torch.optim.Optimizer, "state_dict", wrapped)
    monkeypatch.setattr(torch.optim.Optimizer, "load_state_dict", wrapped)
    sd = copy.deepcopy(opt.state_dict())
    again = SRUKF(_lin(seed=3), P0=0.5, Q=1e-3, R=0.1)
    again.load_state_dict(sd)
    opt.step(X[1], Y[1])
    again.step(X[1], Y[1])
    assert torch.equal(again.theta, opt.theta) and torch.equal(again.belief.chol, opt.belief.chol)


@pytest.mark.parametrize("bad", [True, np.bool_(True), torch.tensor(True), 1.0 + 0j, "1e-2"])
def test_a_per_parameter_prior_refuses_bools_complex_values_and_text(bad):
    """A dict prior (``P0={"weight": ...}``) read a bool as a variance of 1 and dropped a
    complex value's imaginary part; text failed inside torch."""
    lin = _lin()
    good = EKF(lin, P0={"weight": np.float32(0.25)}, Q=1e-3, R=0.1)
    want = torch.full((lin.weight.numel(),), 0.25, dtype=torch.float64)
    torch.testing.assert_close(good.belief.chol.diagonal() ** 2, want, rtol=1e-12, atol=0)
    with pytest.raises(TypeError, match=r"P0\['weight'\] must be a real number or a tensor"):
        EKF(lin, P0={"weight": bad}, Q=1e-3, R=0.1)
