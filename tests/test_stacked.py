"""R runs of one learner as one predictor: the stack equals a loop over separate learners."""

from __future__ import annotations

import pytest
import torch
from torch.func import jacrev

from prognos_torch.learners import ANFIS, ELM, LSSVR
from prognos_torch.optim import (
    KalmanOptimizer,
    ParameterBridge,
    StackedForecaster,
    StackedLearner,
    fit,
    fit_kalman_runs,
    fit_together,
    run_sum_mse,
)
from prognos_torch.prognosis import MeasurementForecaster, learner_transition_model

F64 = torch.float64
TOL = dict(rtol=1e-12, atol=1e-12)


def _anfis(R, p=3):
    g = torch.Generator().manual_seed(11)
    mods = [ANFIS(p, 2, generator=torch.Generator().manual_seed(r)) for r in range(R)]
    for m in mods:  # distinct premises per run
        m.init_premises(torch.rand(20, p, generator=g, dtype=F64))
    return mods


def _x(*shape, seed=9):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=F64)


@pytest.mark.parametrize(
    "make",
    [_anfis, lambda R: [ELM(3, 6, generator=torch.Generator().manual_seed(r)) for r in range(R)]],
)
def test_vmap_stack_equals_each_module(make):
    mods = make(3)
    st = StackedLearner.from_modules(mods)
    assert st.runs == 3 and st.n_in == 3 and st.n_out == 1
    for shape in [(3, 4), (3, 5, 3), (3, 2, 5, 3)]:
        x = _x(*shape[:-1], 3) if len(shape) > 2 else _x(3, 3)
        out = st(x)
        assert out.shape == (*x.shape[:-1], 1)
        for r, m in enumerate(mods):
            torch.testing.assert_close(out[r], m(x[r]).detach(), **TOL)
    # samples leading (the layout fit batches over)
    stb = StackedLearner.from_modules(mods, run_dim=1)
    x = _x(7, 3, 3)
    out = stb(x)
    for r, m in enumerate(mods):
        torch.testing.assert_close(out[:, r], m(x[:, r]).detach(), **TOL)
    for r in range(3):  # module(r) gives run r back as a plain module
        torch.testing.assert_close(st.module(r)(x[:, r]), mods[r](x[:, r]), **TOL)


def test_broadcast_and_scaling_equal_each_module():
    R, p = 4, 3
    mods = _anfis(R, p)
    g = torch.Generator().manual_seed(3)
    lo = 400.0 + torch.rand(R, generator=g, dtype=F64)
    hi = lo + 1.0 + torch.rand(R, generator=g, dtype=F64)
    theta = ParameterBridge(mods[0]).stack(mods)
    for evaluate in ("vmap", "broadcast"):
        st = StackedLearner.from_theta(ANFIS(p, 2), theta, evaluate=evaluate, lo=lo, hi=hi)
        for x in (lo[:, None] + (hi - lo)[:, None] * _x(R, p), lo[:, None, None] + _x(R, 5, p)):
            got = st(x)
            assert got.shape == (*x.shape[:-1], 1)
            for r in range(R):
                s = hi[r] - lo[r]
                ref = mods[r]((x[r] - lo[r]) / s) * s + lo[r]
                torch.testing.assert_close(got[r], ref.detach(), **TOL)
        sub = st.select(slice(1, 3))
        torch.testing.assert_close(sub(x[1:3]), got[1:3], **TOL)
    with pytest.raises(ValueError, match="broadcast"):
        StackedLearner.from_modules([ELM(3, 4)], evaluate="broadcast", run_dim=1)


def test_input_gradient_and_select():
    mods = _anfis(3)
    st = StackedLearner.from_modules(mods)
    x = _x(3, 5, 7, 3)
    g = st.input_gradient(x.reshape(-1, 3)).reshape(3, 35, 1, 3)  # run-major flattening
    for r, mod in enumerate(mods):
        ref = torch.stack([jacrev(mod)(xi) for xi in x[r].reshape(-1, 3)])  # (35, 1, 3)
        torch.testing.assert_close(g[r], ref, **TOL)
    torch.testing.assert_close(st.input_gradient(x), g.reshape(3, 5, 7, 1, 3), **TOL)
    sel = st.select(torch.tensor([True, False, True]))
    assert sel.runs == 2
    torch.testing.assert_close(sel(x[[0, 2]]), st(x)[[0, 2]], rtol=0, atol=0)
    torch.testing.assert_close(st.select(torch.tensor([2]))(x[2:]), st(x)[2:], **TOL)
    with pytest.raises(ValueError, match="R=3"):
        st(x[:2])
    with pytest.raises(ValueError, match="boolean run mask"):
        st.select(torch.tensor([True, False]))


def test_stack_as_transition_model_equals_per_run_models():
    mods = _anfis(2, 4)
    st = StackedLearner.from_modules(mods)
    model = learner_transition_model(st, 4, 0.01, 0.1, jacobian="input_gradient")
    x = _x(2, 6, 4)
    fx, J = model.transition(x, None, 1), model.jac_f(x, None, 1)
    for r, mod in enumerate(mods):
        ref = learner_transition_model(mod, 4, 0.01, 0.1)
        torch.testing.assert_close(fx[r], ref.transition(x[r], None, 1), **TOL)
        torch.testing.assert_close(J[r], ref.jac_f(x[r], None, 1), **TOL)


def test_adam_stack_equals_independent_runs():
    # the summed loss separates over runs and Adam is element-wise: one stacked optimiser is R
    # independent Adam runs on the same mini-batches
    X = _x(40, 3, seed=4)
    Y = X.sum(-1, keepdim=True).sin()
    mods = [ELM(3, 6, generator=torch.Generator().manual_seed(i)) for i in range(2)]
    st = StackedLearner.from_modules(mods, run_dim=1, trainable=True)
    assert [n for n, _ in st.named_parameters()] == ["beta"]  # a, b are fixed (buffers)
    opt = torch.optim.Adam(st.parameters(), lr=1e-2)
    Xr, Yr = X.unsqueeze(1).expand(-1, 2, -1), Y.unsqueeze(1).expand(-1, 2, -1)
    fit(st, opt, (Xr, Yr), epochs=3, batch_size=8, progress=False, loss_fn=run_sum_mse)
    together = fit_together(
        mods,
        lambda ps: torch.optim.Adam(ps, lr=1e-2),
        (X, Y),
        epochs=3,
        batch_size=8,
        progress=False,
    )
    assert together.run_dim == 0 and not list(together.parameters())
    torch.testing.assert_close(
        together.parameter_sets()["beta"], st.parameter_sets()["beta"], rtol=0, atol=0
    )
    for r, mod in enumerate(mods):
        o = torch.optim.Adam([mod.beta], lr=1e-2)
        fit(mod, o, (X, Y), epochs=3, batch_size=8, progress=False)
        sets = st.parameter_sets()
        torch.testing.assert_close(sets["beta"][r], mod.beta.detach(), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(sets["a"][r], mod.a.detach(), rtol=0, atol=0)


def test_kalman_runs_as_stack_equal_separate_trainings():
    X = _x(30, 3, seed=5)
    Y = X.prod(-1, keepdim=True).cos()
    kw = dict(filter="ekf", P0={"alpha": 1.0, "b": 1e-2, "beta": 1e-4}, Q=1e-6, R=1e-3)
    fkw = dict(epochs=1, batch_size=5, progress=False)
    st = fit_kalman_runs(_anfis(2), (X, Y), fit_options=fkw, **kw)  # one optimiser, runs=2
    loop = fit_kalman_runs(_anfis(2), (X, Y), batched=False, fit_options=fkw, **kw)
    x = _x(2, 9, 3)
    out = st(x)
    for r, mod in enumerate(_anfis(2)):
        fit(mod, KalmanOptimizer(mod, **kw), (X, Y), **fkw)
        torch.testing.assert_close(out[r], mod(x[r]).detach(), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(loop(x)[r], mod(x[r]).detach(), rtol=0, atol=0)
    # ELMs with their own hidden layers cannot share one optimiser: one per run
    elms = [ELM(3, 5, generator=torch.Generator().manual_seed(r)) for r in range(2)]
    ekw = dict(filter="ekf", P0={"beta": 10.0}, Q=0.0, R=1e-3)
    st = fit_kalman_runs(elms, (X, Y), fit_options=fkw, **ekw)
    for r in range(2):
        ref = ELM(3, 5, generator=torch.Generator().manual_seed(r))
        fit(ref, KalmanOptimizer(ref, **ekw), (X, Y), **fkw)
        torch.testing.assert_close(st(x)[r], ref(x[r]).detach(), **TOL)


def test_stacked_forecaster_equals_one_forecaster_per_run():
    R, C, N0, n = 3, 3, 20, 4
    g = torch.Generator().manual_seed(5)
    z = 1.0 + 0.1 * torch.randn(N0 + 3, R, C, generator=g, dtype=F64).cumsum(0)

    def per_run():
        return [
            MeasurementForecaster.ros_elm(
                C, p=3, n_hidden=8, generator=torch.Generator().manual_seed(r)
            )
            for r in range(R)
        ]

    ref = per_run()
    view = StackedForecaster.from_forecasters(per_run())
    sub = view.select(slice(1, 3)).initialize(z[:N0, 1:3])
    view.initialize(z[:N0])
    for r, f in enumerate(ref):
        f.initialize(z[:N0, r])
    for t in range(N0, N0 + 3):
        got = view.copy().forecast(n)
        want = torch.stack([f.forecast(n) for f in ref], dim=1)
        torch.testing.assert_close(got, want, rtol=0, atol=0)
        torch.testing.assert_close(sub.forecast(n), want[:, 1:3], rtol=0, atol=0)
        view.update(z[t])
        sub.update(z[t, 1:3])
        for r, f in enumerate(ref):
            f.update(z[t, r])
    assert view.initialized and got.shape == (n, R, C)
    with pytest.raises(ValueError, match="initialised"):
        StackedForecaster.from_forecasters(ref)


def test_dtype_and_device_moves_carry_the_base_buffers_along():
    """``.float()`` / ``.to(device)`` move the base's buffers that forward uses (an LS-SVR's
    support vectors are no stacked parameter) with the stack; the caller's base is untouched."""
    X = _x(20, 3)
    mods = [LSSVR(sigma=0.5 + 0.1 * r, C=10.0).fit(X, X.sum(-1, keepdim=True)) for r in range(2)]
    st = StackedLearner.from_modules(mods)
    want = torch.stack([m(X) for m in mods])
    st32 = st.float()
    got = st32(X.float().expand(2, 20, 3))
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-5)
    base = ELM(3, 6, generator=torch.Generator().manual_seed(0))
    st = StackedLearner.from_theta(base, ParameterBridge(base).flatten().expand(2, -1)).float()
    assert base.a.dtype == F64 and st.base.a.dtype == torch.float32  # a copy moved
    same = st.base
    assert st.to(torch.float32).base is same  # nothing to move: no copy


def test_bad_arguments():
    m = ELM(3, 4)
    with pytest.raises(ValueError, match="no parameter"):
        StackedLearner(m, {"w": torch.zeros(2, 3)})
    with pytest.raises(ValueError, match=r"params\['beta'\] must have shape"):
        StackedLearner(m, {"beta": torch.zeros(2, 3)})
    with pytest.raises(ValueError, match="run_dim"):
        StackedLearner.from_modules([m], run_dim=2)
    with pytest.raises(ValueError, match="both lo and hi"):
        StackedLearner.from_modules([m], lo=torch.zeros(1))


def test_kalman_runs_optimizer_starts_each_run_from_its_module():
    from prognos_torch.optim import kalman_runs_optimizer

    mods = _anfis(3)
    opt = kalman_runs_optimizer(mods[0], mods, filter="ekf", P0=1e-2, Q=1e-6, R=1e-3)
    assert isinstance(opt, KalmanOptimizer)
    for r, m in enumerate(mods):
        torch.testing.assert_close(opt.theta[r], ParameterBridge(m).flatten())


def test_per_run_data_and_subsets_on_every_stacking_path():
    X = _x(2, 12, 3, seed=6)
    Y = X.sum(-1, keepdim=True).sin() + torch.tensor([0.0, 0.5], dtype=F64).reshape(2, 1, 1)
    fkw = dict(batch_size=4, progress=False)
    kw = dict(filter="ekf", P0=1.0, Q=1e-6, R=1e-2, per_run_data=True)

    def lins():
        return [torch.nn.Linear(3, 1, dtype=F64) for _ in range(2)]

    # per-run data on the non-batched path (modules with their own fixed layers: one
    # optimiser each) trained module r on run r's data, as the batched path does; it raised
    # "per_run_data=True needs runs=R"
    for batched in (True, False):
        torch.manual_seed(0)
        st = fit_kalman_runs(lins(), (X, Y), batched=batched, fit_options=fkw, **kw)
        torch.manual_seed(0)
        for r, mod in enumerate(lins()):
            fit(mod, KalmanOptimizer(mod, **{**kw, "per_run_data": False}), (X[r], Y[r]), **fkw)
            torch.testing.assert_close(st(X)[r], mod(X[r]).detach(), **TOL)
            if not batched:  # one optimiser per module: the same parameters, bit for bit
                assert torch.equal(st.weight[r], mod.weight) and torch.equal(st.bias[r], mod.bias)
    with pytest.raises(TypeError, match="runs"):  # it trained R runs per module, kept none
        fit_kalman_runs(lins(), (X[0], Y[0]), batched=False, runs=2, fit_options=fkw)
    # theta of an optimiser over a subset of the parameters: from_theta takes its names
    m = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Tanh(), torch.nn.Linear(4, 1)).double()
    opt = KalmanOptimizer([m[2].weight, m[2].bias], module=m, runs=2, P0=1.0, R=1e-2)
    fit(m, opt, (X[0], Y[0]), **fkw)
    with pytest.raises(ValueError, match="params=\\[names\\]"):
        StackedLearner.from_theta(m, opt.theta)
    st = StackedLearner.from_theta(m, opt.theta, params=opt.bridge.names)
    torch.testing.assert_close(st(X[0].expand(2, -1, -1)), opt.predict(X[0]), **TOL)


def test_fit_together_repeats_the_validation_data_over_the_runs():
    # val was passed to fit unrepeated: "x must have shape (B, R, ..., n_in)" (and with as
    # many validation samples as runs it was taken as runs)
    X, Xv = _x(20, 3, seed=7), _x(6, 3, seed=8) + 2.0
    Y, Yv = X.sum(-1, keepdim=True).sin(), Xv.sum(-1, keepdim=True).sin()
    mods = [ELM(3, 5, generator=torch.Generator().manual_seed(i)) for i in range(2)]
    fkw = dict(epochs=30, batch_size=5, progress=False, early_stopping=2)
    st = StackedLearner.from_modules(mods, run_dim=1, trainable=True)

    def rep(v):
        return v.unsqueeze(1).expand(-1, 2, -1)

    opt = torch.optim.Adam(st.parameters(), lr=0.5)
    h = fit(st, opt, (rep(X), rep(Y)), val=(rep(Xv), rep(Yv)), loss_fn=run_sum_mse, **fkw)
    assert h.stopped_early and h.best_epoch < h.epoch[-1]  # the best epoch restored
    together = fit_together(
        mods, lambda ps: torch.optim.Adam(ps, lr=0.5), (X, Y), val=(Xv, Yv), **fkw
    )
    torch.testing.assert_close(
        together.parameter_sets()["beta"], st.parameter_sets()["beta"], rtol=0, atol=0
    )
