"""torch.optim conformity of the Kalman optimisers: parameter groups, learning rate and
schedulers, BatchNorm and other buffers, closures.

References: single-group optimisers stepped in the documented order, the closed-form posterior
of Bayesian linear regression (NumPy), and one plain forward pass for running statistics.
"""

from __future__ import annotations

import copy
import io

import numpy as np
import pytest
import torch
from torch import nn

from prognos_torch.learners import ELM
from prognos_torch.optim import KalmanOptimizer, fit

torch.set_num_threads(1)


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _data(N=12, d=3, n_out=1, seed=0):
    g = _gen(seed)
    X = torch.randn(N, d, generator=g, dtype=torch.float64)
    Y = torch.tanh(X @ torch.randn(d, n_out, generator=g, dtype=torch.float64))
    return X, Y + 0.05 * torch.randn(N, n_out, generator=g, dtype=torch.float64)


def _mlp(seed=0, d=3, hidden=4, n_out=1) -> nn.Sequential:
    torch.manual_seed(seed)
    return nn.Sequential(
        nn.Linear(d, hidden, dtype=torch.float64),
        nn.Tanh(),
        nn.Linear(hidden, n_out, dtype=torch.float64),
    )


GROUP_A = dict(P0=0.5, Q=1e-6, R=2e-2)
GROUP_B = dict(P0=2.0, Q=1e-5, R=5e-2)


# --------------------------------------------------------------------------- parameter groups
@pytest.mark.parametrize("filters", [("ekf", "ekf"), ("srukf", "ckf"), ("imsrukf", "ekf")])
def test_two_groups_equal_two_optimisers_stepped_in_order(filters):
    """Interacting groups (two layers of one MLP): the two-group optimiser is exactly two
    single-group optimisers on the two layers, stepped one after the other."""
    X, Y = _data(N=10)
    m1 = _mlp(1)
    m2 = copy.deepcopy(m1)
    fa, fb = filters
    grouped = KalmanOptimizer(
        [
            {"params": m1[0].parameters(), "filter": fa, **GROUP_A},
            {"params": m1[2].parameters(), "filter": fb, **GROUP_B},
        ],
        module=m1,
    )
    opt_a = KalmanOptimizer(m2[0].parameters(), module=m2, filter=fa, **GROUP_A)
    opt_b = KalmanOptimizer(m2[2].parameters(), module=m2, filter=fb, **GROUP_B)
    for i in range(0, 10, 2):
        out = grouped.step(X[i : i + 2], Y[i : i + 2])
        ra = opt_a.step(X[i : i + 2], Y[i : i + 2])
        opt_b.step(X[i : i + 2], Y[i : i + 2])
        torch.testing.assert_close(out.loss, ra.loss, rtol=0, atol=1e-12)
        assert len(out.infos) == 2 and out.infos[0] is out.info
    ref_theta = torch.cat([opt_a.theta, opt_b.theta])
    torch.testing.assert_close(grouped.theta, ref_theta, rtol=0, atol=1e-12)
    ref_cov = torch.block_diag(opt_a.parameter_covariance(), opt_b.parameter_covariance())
    torch.testing.assert_close(grouped.parameter_covariance(), ref_cov, rtol=0, atol=1e-12)
    torch.testing.assert_close(
        grouped.parameter_std(), torch.cat([opt_a.parameter_std(), opt_b.parameter_std()])
    )
    for p1, p2 in zip(m1.parameters(), m2.parameters()):
        torch.testing.assert_close(p1, p2, rtol=0, atol=1e-12)
    torch.testing.assert_close(grouped.predict(X), m1(X), rtol=0, atol=1e-14)
    b = grouped.belief  # block-diagonal, lower triangular
    assert torch.equal(b.chol, torch.tril(b.chol))
    torch.testing.assert_close(b.cov, ref_cov, rtol=0, atol=1e-12)
    assert [f.noise is not None for f in grouped.filters] == [fa == "imsrukf", False]
    with pytest.raises(ValueError, match="filters"):
        _ = grouped.filter
    with pytest.raises(ValueError, match="filter_states"):
        _ = grouped.filter_state
    assert len(grouped.filter_states) == len(grouped.beliefs) == 2


@pytest.mark.parametrize("filt", ["ekf", "srukf"])
def test_independent_groups_equal_separate_optimisers_on_separate_modules(filt):
    """Two sub-models that share nothing (outputs side by side): block-diagonal beliefs stay
    independent, each group trains exactly as its sub-model alone on its own output."""

    class Pair(nn.Module):
        def __init__(self, a, b):
            super().__init__()
            self.a, self.b = a, b

        def forward(self, x):
            return torch.cat([self.a(x), self.b(x)], -1)

    X, Y2 = _data(N=8, n_out=2, seed=3)
    a, b = _mlp(2), _mlp(3)
    pair = Pair(copy.deepcopy(a), copy.deepcopy(b))
    grouped = KalmanOptimizer(
        [{"params": pair.a.parameters(), **GROUP_A}, {"params": pair.b.parameters(), **GROUP_B}],
        module=pair,
        filter=filt,
    )
    opt_a = KalmanOptimizer(a, filter=filt, **GROUP_A)
    opt_b = KalmanOptimizer(b, filter=filt, **GROUP_B)
    for i in range(0, 8, 2):
        grouped.step(X[i : i + 2], Y2[i : i + 2])
        opt_a.step(X[i : i + 2], Y2[i : i + 2, :1])
        opt_b.step(X[i : i + 2], Y2[i : i + 2, 1:])
    ga, gb = grouped.beliefs
    torch.testing.assert_close(ga.mean, opt_a.theta, rtol=0, atol=1e-12)
    torch.testing.assert_close(gb.mean, opt_b.theta, rtol=0, atol=1e-12)
    torch.testing.assert_close(ga.cov, opt_a.parameter_covariance(), rtol=0, atol=1e-12)
    torch.testing.assert_close(gb.cov, opt_b.parameter_covariance(), rtol=0, atol=1e-12)


def test_add_param_group_equals_groups_given_at_construction():
    X, Y = _data(N=6)
    m1 = _mlp(4)
    m2 = copy.deepcopy(m1)
    both = KalmanOptimizer(
        [{"params": m1[0].parameters()}, {"params": m1[2].parameters(), "R": 0.2}],
        module=m1,
        filter="srukf",
        P0=0.3,
    )
    grown = KalmanOptimizer(m2[0].parameters(), module=m2, filter="srukf", P0=0.3)
    grown.add_param_group({"params": m2[2].parameters(), "R": 0.2})
    assert len(grown.param_groups) == 2 and grown.param_groups[1]["filter"] == "srukf"
    for i in range(6):
        both.step(X[i : i + 1], Y[i : i + 1])
        grown.step(X[i : i + 1], Y[i : i + 1])
    assert torch.equal(both.theta, grown.theta)
    assert torch.equal(both.belief.chol, grown.belief.chol)
    # a group added after training starts at the module's current values with its own P0
    m3 = _mlp(5)
    late = KalmanOptimizer(m3[0].parameters(), module=m3, P0=0.3)
    late.step(X[:2], Y[:2])
    late.add_param_group({"params": m3[2].parameters(), "P0": 4.0})
    last = torch.cat([p.detach().reshape(-1) for p in m3[2].parameters()])
    assert torch.equal(late.beliefs[1].mean, last)
    assert torch.equal(late.beliefs[1].cov, 4.0 * torch.eye(last.numel(), dtype=torch.float64))
    late.step(X[2:4], Y[2:4])
    assert late.state["kalman"]["step"] == 2 and late.state["kalman.1"]["step"] == 1


def test_parameter_group_errors():
    m = _mlp(0)
    o = KalmanOptimizer(m[0].parameters(), module=m)
    with pytest.raises(ValueError, match="more than one parameter group"):
        o.add_param_group({"params": m[0].parameters()})
    with pytest.raises(ValueError, match="whole optimiser"):
        o.add_param_group({"params": m[2].parameters(), "runs": 2})
    with pytest.raises(ValueError, match="parameters of module only"):
        o.add_param_group({"params": [nn.Parameter(torch.zeros(2))]})
    with pytest.raises(TypeError, match="got a module"):
        o.add_param_group({"params": m[2]})
    with pytest.raises(ValueError, match="P0"):
        o.add_param_group({"params": m[2].parameters(), "P0": -1.0})
    assert len(o.param_groups) == 1  # nothing half-added
    runs = KalmanOptimizer(m[0].parameters(), module=m, runs=2)
    with pytest.raises(ValueError, match="runs=None"):
        runs.add_param_group({"params": m[2].parameters()})
    with pytest.raises(TypeError, match="mixes"):
        KalmanOptimizer([{"params": m[0].parameters()}, m[2].weight], module=m)
    two = KalmanOptimizer([{"params": m[0].parameters()}, {"params": m[2].parameters()}], module=m)
    with pytest.raises(ValueError, match="theta0"):
        KalmanOptimizer([{"params": m[0].parameters()}], module=m, theta0=torch.zeros(3))
    sd = two.state_dict()
    del sd["state"]["kalman.1"]
    with pytest.raises(ValueError, match="kalman.1"):
        two.load_state_dict(sd)
    with pytest.raises(ValueError, match="parameter groups"):
        KalmanOptimizer(m, filter="ekf").load_state_dict(two.state_dict())


def _save_load(obj):
    buf = io.BytesIO()
    torch.save(obj, buf)
    buf.seek(0)
    return torch.load(buf, weights_only=True)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_two_group_state_dict_round_trip_is_bit_identical(dtype):
    X, Y = _data(N=12)
    X, Y = X.to(dtype), Y.to(dtype)
    m1 = _mlp(6).to(dtype)
    m2 = copy.deepcopy(m1)

    def make(m):
        return KalmanOptimizer(
            [
                {"params": m[0].parameters(), "filter": "imsrukf", **GROUP_A},
                {"params": m[2].parameters(), "filter": "stsckf", **GROUP_B},
            ],
            module=m,
        )

    o1 = make(m1)
    for i in range(6):
        o1.step(X[i : i + 1], Y[i : i + 1])
    saved_model, saved_opt = _save_load(m1.state_dict()), _save_load(o1.state_dict())
    for i in range(6, 12):
        o1.step(X[i : i + 1], Y[i : i + 1])
    o2 = make(m2)
    m2.load_state_dict(saved_model)
    o2.load_state_dict(saved_opt)
    for key in ("kalman", "kalman.1"):
        assert o2.state[key]["mean"].dtype == torch.float64
    for i in range(6, 12):
        o2.step(X[i : i + 1], Y[i : i + 1])
    assert torch.equal(o1.theta, o2.theta)
    assert torch.equal(o1.belief.chol, o2.belief.chol)
    for f1, f2 in zip(o1.filter_states, o2.filter_states):
        if f1.noise is not None:
            assert torch.equal(f1.noise.R, f2.noise.R)
        if f1.fading is not None:
            assert torch.equal(f1.fading.V, f2.fading.V)
    for p1, p2 in zip(m1.parameters(), m2.parameters()):
        assert torch.equal(p1, p2)
    dup = copy.deepcopy(o2)  # a copy carries both groups and steps on its own module
    dup.step(X[:1], Y[:1])
    assert not torch.equal(dup.theta, o2.theta)


# --------------------------------------------------------------------------- learning rate
def _posterior_numpy(H, t, lrs, P0, R):
    """Bayesian linear regression, theta_0 = 0, P_0 = P0 I, sample k weighted lr_k / R."""
    n = H.shape[1]
    A = np.eye(n) / P0
    b = np.zeros(n)
    for h, y, lr in zip(H, t, lrs):
        A += np.outer(h, h) * lr / R
        b += h * y * lr / R
    return np.linalg.solve(A, b), np.linalg.inv(A)


def test_step_lr_scales_the_measurement_noise():
    """lr divides R; StepLR then anneals the measurement noise. A linear model with Q = 0 has
    the closed-form posterior of weighted least squares."""
    X, Y = _data(N=9, d=3, seed=7)
    lin = nn.Linear(3, 1, bias=False, dtype=torch.float64)
    with torch.no_grad():
        lin.weight.zero_()
    P0, R = 2.0, 0.1
    opt = KalmanOptimizer(lin, filter="srukf", P0=P0, R=R, lr=0.8)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=3, gamma=0.25)
    lrs = []
    for i in range(9):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step(X[i : i + 1], Y[i : i + 1])
        sched.step()
    assert lrs == pytest.approx([0.8] * 3 + [0.2] * 3 + [0.05] * 3)
    mean, cov = _posterior_numpy(X.numpy(), Y[:, 0].numpy(), lrs, P0, R)
    np.testing.assert_allclose(opt.theta.numpy(), mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(opt.parameter_covariance().numpy(), cov, rtol=0, atol=1e-12)
    # lr = 1 is the plain filter; a different constant lr is the filter with R / lr
    a = KalmanOptimizer(copy.deepcopy(lin), filter="ekf", R=R, lr=4.0)
    b = KalmanOptimizer(copy.deepcopy(lin), filter="ekf", R=R / 4.0)
    a.step(X[:3], Y[:3])
    b.step(X[:3], Y[:3])
    torch.testing.assert_close(a.theta, b.theta, rtol=0, atol=1e-14)


def test_lr_errors():
    m = nn.Linear(2, 1, dtype=torch.float64)
    for bad in (0.0, -1.0, float("nan"), "fast"):
        with pytest.raises(ValueError, match="lr"):
            KalmanOptimizer(m, lr=bad)
    with pytest.raises(ValueError, match="estimates R"):
        KalmanOptimizer(m, filter="imsrukf", lr=0.5)
    opt = KalmanOptimizer(m, filter="imsrukf")
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.5)
    x, t = torch.ones(2, 2, dtype=torch.float64), torch.ones(2, 1, dtype=torch.float64)
    opt.step(x, t)
    sched.step()
    with pytest.raises(ValueError, match=r"param_groups\[0\]\['lr'\] = 0.5.*estimates R"):
        opt.step(x, t)
    # estimating Q only leaves lr its meaning
    from prognos_torch.adapt.noise import SageHusa

    KalmanOptimizer(m, filter="srukf", noise=SageHusa(estimate=("Q",), diagonal=True), lr=0.5)
    old = KalmanOptimizer(m).state_dict()  # written before lr existed: loads with lr = 1
    for g in old["param_groups"]:
        del g["lr"]
    fresh = KalmanOptimizer(m)
    fresh.load_state_dict(old)
    assert fresh.param_groups[0]["lr"] == 1.0


# --------------------------------------------------------------------------- buffers
def _bn_net(seed=0):
    torch.manual_seed(seed)
    return nn.Sequential(
        nn.Linear(3, 4, dtype=torch.float64),
        nn.BatchNorm1d(4, dtype=torch.float64),
        nn.Tanh(),
        nn.Linear(4, 1, dtype=torch.float64),
    )


@pytest.mark.parametrize("filt", ["srukf", "ekf"])
def test_batch_norm_in_training_mode(filt):
    """The filter's evaluations use batch statistics (= the same net without running
    statistics), and the running statistics move once per step, as one forward pass at the
    parameters before the step moves them."""
    X, Y = _data(N=12, seed=8)
    net = _bn_net(1)
    twin = copy.deepcopy(net)
    twin[1].track_running_stats = False  # batch statistics only, no buffers
    probe = copy.deepcopy(net)  # replays the running statistics
    opt = KalmanOptimizer(net, filter=filt, P0=0.1, Q=1e-6, R=1e-2)
    ref = KalmanOptimizer(twin, filter=filt, P0=0.1, Q=1e-6, R=1e-2)
    for i in range(0, 12, 4):
        with torch.no_grad():
            probe.load_state_dict(net.state_dict())
            probe(X[i : i + 4])
            expect = (probe[1].running_mean.clone(), probe[1].running_var.clone())
        opt.step(X[i : i + 4], Y[i : i + 4])
        ref.step(X[i : i + 4], Y[i : i + 4])
        assert torch.equal(net[1].running_mean, expect[0])
        assert torch.equal(net[1].running_var, expect[1])
    assert int(net[1].num_batches_tracked) == 3
    torch.testing.assert_close(opt.theta, ref.theta, rtol=0, atol=1e-12)
    stats = net[1].running_mean.clone()
    opt.predict(X)  # predicting changes nothing
    assert torch.equal(net[1].running_mean, stats) and net[1].track_running_stats


def test_batch_norm_in_eval_mode_uses_fixed_statistics():
    X, Y = _data(N=8, seed=9)
    net = _bn_net(2)
    net(X)  # some running statistics
    net.eval()
    before = {k: v.clone() for k, v in net.state_dict().items() if "running" in k}
    opt = KalmanOptimizer(net, filter="srukf", P0=0.1, R=1e-2)
    for i in range(0, 8, 2):
        opt.step(X[i : i + 2], Y[i : i + 2])
    for k, v in before.items():
        assert torch.equal(net.state_dict()[k], v)
    torch.testing.assert_close(opt.predict(X), net(X), rtol=0, atol=1e-14)


def test_other_buffers_and_randomness_get_clear_errors():
    class Tracker(nn.Module):
        def __init__(self):
            super().__init__()
            self.lin = nn.Linear(2, 1, dtype=torch.float64)
            self.register_buffer("last", torch.zeros(1, dtype=torch.float64))

        def forward(self, x):
            y = self.lin(x)
            self.last.copy_(y.mean().reshape(1))
            return y

    x, t = torch.ones(4, 2, dtype=torch.float64), torch.zeros(4, 1, dtype=torch.float64)
    for filt in ("srukf", "ekf"):
        with pytest.raises(ValueError, match="in-place buffer update"):
            KalmanOptimizer(Tracker(), filter=filt).step(x, t)
        drop = nn.Sequential(nn.Linear(2, 1, dtype=torch.float64), nn.Dropout(0.5))
        with pytest.raises(ValueError, match="Dropout"):
            KalmanOptimizer(drop, filter=filt).step(x, t)
    bn = _bn_net()
    with pytest.raises(ValueError, match="BatchNorm"):
        KalmanOptimizer(bn, runs=2).step(torch.ones(4, 3, dtype=torch.float64), t)
    assert bn[1].track_running_stats and int(bn[1].num_batches_tracked) == 0


# --------------------------------------------------------------------------- closures
def test_closures():
    X, Y = _data(N=4, d=2, seed=10)
    elm = ELM(2, 5, generator=_gen(0))
    opt = KalmanOptimizer(elm, filter="ekf")
    with pytest.raises(TypeError, match="closure returned a loss"):
        opt.step(lambda: nn.functional.mse_loss(elm(X), Y))
    with pytest.raises(TypeError, match="closure returned a loss"):
        opt.step(closure=lambda: 0.5)
    with pytest.raises(TypeError, match="not both"):
        opt.step(X, Y, closure=lambda: (X, Y))
    twin = KalmanOptimizer(copy.deepcopy(elm), filter="ekf")
    opt.step(closure=lambda: (X, Y))
    twin.step(X, Y)
    assert torch.equal(opt.theta, twin.theta)
    hist = fit(elm, opt, (X, Y), epochs=1, batch_size=2, progress=False)
    assert len(hist.train["mae"]) == 1


def test_changes_around_the_optimiser_are_adopted_or_refused_never_ignored():
    """A write through .data is adopted as the mean (it moves no version counter and was lost);
    a tensor option changed in place, other params, a parameter frozen after the optimiser was
    built, a state of other runs or of parameters of other shapes are refused (each was
    ignored, and a reload would have applied it)."""
    X, Y = _data(N=16)

    def net():
        torch.manual_seed(1)
        return nn.Sequential(nn.Linear(3, 4), nn.Tanh(), nn.Linear(4, 1)).double()

    lins, opts = [], []
    for how in ("data", "no_grad"):  # a write through .data as one under no_grad
        torch.manual_seed(0)
        lin = nn.Linear(3, 1).double()
        opt = KalmanOptimizer(lin, filter="ekf", R=0.1)
        opt.step(X[:4], Y[:4])
        if how == "data":
            lin.bias.data.fill_(5.0)
        else:
            with torch.no_grad():
                lin.bias.fill_(5.0)
        opt.step(X[4:8], Y[4:8])
        lins.append(lin)
        opts.append(opt)
    assert torch.equal(opts[0].theta, opts[1].theta) and float(lins[0].bias) > 1.0

    q = torch.tensor(0.0, dtype=torch.float64)
    opt = KalmanOptimizer(net(), filter="ekf", Q=q, R=0.1)
    opt.step(X[:4], Y[:4])
    q.fill_(1.0)
    with pytest.raises(ValueError, match=r"param_groups\[0\]\['Q'\] changed after"):
        opt.step(X[4:8], Y[4:8])
    m = net()
    opt = KalmanOptimizer(m, filter="ekf", R=0.1)
    opt.param_groups[0]["params"] = list(m[0].parameters())
    with pytest.raises(ValueError, match=r"param_groups\[0\]\['params'\] changed after"):
        opt.step(X[:4], Y[:4])
    m = net()
    opt = KalmanOptimizer(m, filter="ekf", R=0.1)
    m[0].weight.requires_grad_(False)
    with pytest.raises(ValueError, match="frozen or unfrozen .requires_grad. after"):
        opt.step(X[:4], Y[:4])
    multi = KalmanOptimizer(nn.Linear(3, 1).double(), filter="ekf", runs=3)
    multi.step(X[:4], Y[:4])
    with pytest.raises(ValueError, match="saved with runs=3, this optimiser has runs=None"):
        KalmanOptimizer(nn.Linear(3, 1).double(), filter="ekf").load_state_dict(
            multi.state_dict()
        )
    opt = KalmanOptimizer(net(), filter="ekf", R=0.1)
    opt.step(X[:2], Y[:2])
    other = nn.Sequential(nn.Linear(2, 5), nn.Linear(5, 1)).double()  # 21 values, 4 tensors
    with pytest.raises(ValueError, match=r"shapes \[\[4, 3\], \[4\], \[1, 4\], \[1\]\], this "
                       r"optimiser's are \[\[5, 2\]"):  # fmt: skip
        KalmanOptimizer(other, filter="ekf", R=0.1).load_state_dict(opt.state_dict())
    same = KalmanOptimizer(net(), filter="ekf", R=0.1)
    same.load_state_dict(opt.state_dict())
    assert torch.equal(same.theta, opt.theta) and "shapes" not in same.state["kalman"]
