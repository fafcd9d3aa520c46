"""The library's main algorithms give the CPU result when their inputs are on another device.

The device is ``PROGNOS_TEST_DEVICE`` (e.g. ``cuda:1``, ``mps``, or ``cpu`` to check the logic
of these tests anywhere), default ``"cuda"``; the whole module is skipped when that device cannot
hold float64 tensors (no CUDA build or GPU, MPS without float64, a misspelt name).

Each test runs a computation on the CPU and again with every input on the device (float64) and
compares the device result, moved back with ``.cpu()``, with the CPU one. Random draws are shared
where the test draws the inputs on the CPU and where the library draws on the generator's own
device and moves the draws (``TrendFit.first_passage`` and the learner trend's paths, given a CPU
generator here; the fleet's per-asset CPU generators); the particle filters
and the noisy event simulation draw from a generator on the device, whose stream differs from the
CPU's, and are checked against the exact Kalman filter or a CPU Monte-Carlo run instead.

Tolerances (``RTOL``, ``ATOL``). The device's linear algebra (cuBLAS/cuSOLVER QR, Cholesky,
triangular solves, products and reductions in another order) and its elementary functions round
differently from the CPU's, each operation in its last bits (about 1e-16 relative), and a filter
carries that through tens of steps. On the small, well-conditioned problems below this stays far
inside ``rtol=1e-8, atol=1e-10``: inputs perturbed at random by 1e-15 (relative) moved every
compared output by less than 0.5 % of these tolerances, by 1e-13 (a thousand times one rounding)
by less than 15 %, while a perturbation of 1e-6 fails every one of the exact comparisons; a
wrong device result (a constant left on the CPU, a dropped step, wrong noise) is off by more.
"""

from __future__ import annotations

import copy
import math
import os
from dataclasses import replace

import pytest
import torch
from test_likelihood import two_state_model  # the oscillator of the likelihood tests

from prognos_torch.core import GaussianBelief, StateSpaceModel, linear_gaussian_model
from prognos_torch.datasets.windows import embed
from prognos_torch.filters import (
    FILTERS,
    arukf,
    ekf,
    make_filter,
    make_particle_filter,
    rukf,
    run,
    run_in_segments,
    sckf,
    smooth,
)
from prognos_torch.fleet import exponential_trend_rul, pad_batch, read_fleet_table, synthetic_fleet
from prognos_torch.fleet.trend import RUL_COLUMNS
from prognos_torch.learners import (
    ANFIS,
    ELM,
    LSSVR,
    ros_elm_forecast,
    ros_elm_init,
    ros_elm_update,
)
from prognos_torch.optim import (
    KalmanOptimizer,
    ParameterBridge,
    StackedLearner,
    em_linear_gaussian,
    fit,
    fit_likelihood,
)
from prognos_torch.prognosis import (
    MeasurementForecaster,
    fit_learner_trend,
    fit_trends,
    gaussian_paths,
    path_grid,
    predict_paths,
    sample_belief,
    simulate_to_event,
    strong_tracking_filter,
    window_belief,
)

F64 = torch.float64
RTOL, ATOL = 1e-8, 1e-10


def _probe(name: str) -> tuple[torch.device | None, str | None]:
    """The device named ``name`` and ``None``, or ``None`` and why it cannot be used."""
    try:
        dev = torch.device(name)
        x = torch.ones(3, dtype=F64, device=dev)
        if float((x @ x).cpu()) != 3.0:
            return None, "float64 arithmetic gives a wrong result"
        return dev, None
    except Exception as exc:  # no CUDA build, no device, no float64 (MPS), a bad name
        return None, f"{type(exc).__name__}: {exc}"


DEVICE_NAME = os.environ.get("PROGNOS_TEST_DEVICE", "cuda")
DEVICE, _WHY = _probe(DEVICE_NAME)

pytestmark = pytest.mark.skipif(
    DEVICE is None, reason=f"device {DEVICE_NAME!r} is not usable here ({_WHY})"
)


def _dev(x):
    """``x`` (a tensor or a belief) on the device under test."""
    if isinstance(x, GaussianBelief):
        return GaussianBelief(x.mean.to(DEVICE), x.chol.to(DEVICE))
    return None if x is None else x.to(DEVICE)


def _same(got, want, what: str = "", rtol: float = RTOL, atol: float = ATOL) -> None:
    """``got`` (a device tensor) equals ``want`` (the CPU tensor): to the tolerances for floating
    point, exactly otherwise; both ``None`` is equal too."""
    if want is None or got is None:
        assert got is None and want is None, f"{what}: {got} against {want}"
        return
    assert got.device.type == DEVICE.type, f"{what} is on {got.device}, expected {DEVICE}"
    got = got.detach().cpu()
    want = want.detach()
    assert got.shape == want.shape and got.dtype == want.dtype, what
    if want.is_floating_point():
        torch.testing.assert_close(
            got, want, rtol=rtol, atol=atol, equal_nan=True, msg=lambda m: f"{what}: {m}"
        )
    else:
        assert torch.equal(got, want), what


def _gen(seed: int, device=None) -> torch.Generator:
    return torch.Generator(device=device or "cpu").manual_seed(seed)


# ============================================================= a small nonlinear model and data
N_STATE, N_OBS, RUNS, STEPS = 3, 2, 3, 30


def nonlinear_model(device) -> StateSpaceModel:
    """A nonlinear 3-state, 2-measurement model with a control and noise means; per-sample
    ``f`` and ``h`` (batched by ``vmap``), its constants on ``device``."""
    A = torch.tensor([[1.0, 0.1, 0.0], [-0.08, 0.9, 0.05], [0.0, 0.0, 0.97]], dtype=F64)
    SQ = torch.tensor([[0.08, 0.0, 0.0], [0.02, 0.06, 0.0], [0.0, 0.01, 0.03]], dtype=F64)
    SR = torch.tensor([[0.2, 0.0], [0.05, 0.15]], dtype=F64)
    q = torch.tensor([0.01, 0.0, -0.005], dtype=F64)
    r = torch.tensor([0.02, -0.01], dtype=F64)
    A, SQ, SR, q, r = (v.to(device) for v in (A, SQ, SR, q, r))

    def f(x, u, k):
        bend = torch.stack([0.05 * u[0], -0.1 * torch.sin(x[0]), torch.zeros_like(x[0])])
        return A @ x + bend

    def h(x, u, k):
        return torch.stack([torch.atan(x[0]) + 0.5 * x[2], x[1] + 0.1 * x[0] ** 2])

    return StateSpaceModel(f, h, N_STATE, N_OBS, chol_Q=SQ, chol_R=SR, q=q, r=r, control_dim=1)


def nonlinear_data():
    """CPU inputs: initial belief ``(RUNS, 3)``, controls ``(STEPS, 1)`` (shared by the runs) and
    measurements ``(STEPS, RUNS, 2)`` simulated from the model, with a row missing for every run,
    one run missing at a step and one partially observed vector."""
    g = _gen(11)
    model = nonlinear_model("cpu")
    m0 = torch.tensor([[0.5, -0.2, 1.0], [0.0, 0.3, 0.6], [-0.4, 0.1, 1.4]], dtype=F64)
    C0 = 0.3 * torch.eye(N_STATE, dtype=F64) + 0.05 * torch.tril(
        torch.randn(RUNS, N_STATE, N_STATE, generator=g, dtype=F64)
    )
    C0 = C0 * C0.diagonal(dim1=-2, dim2=-1).sign().unsqueeze(-2)  # positive diagonal
    b0 = GaussianBelief(m0, C0)
    us = torch.sin(0.3 * torch.arange(STEPS, dtype=F64)).unsqueeze(-1)
    x = m0 + (C0 @ torch.randn(RUNS, N_STATE, 1, generator=g, dtype=F64)).squeeze(-1)
    ys = []
    for t in range(STEPS):
        w = torch.randn(RUNS, N_STATE, generator=g, dtype=F64)
        x = model.transition(x, us[t], t + 1) + model.q + w @ model.chol_Q.mT
        v = torch.randn(RUNS, N_OBS, generator=g, dtype=F64)
        ys.append(model.observe(x, us[t], t + 1) + model.r + v @ model.chol_R.mT)
    ys = torch.stack(ys)
    ys[7] = math.nan  # missing for every run: predict only
    ys[15, 1, 0] = math.nan  # partially observed
    ys[22, 2] = math.nan  # one run missing
    return b0, us, ys


def gaussian_filter(name: str, device):
    """A Gaussian filter by name: the nine of ``make_filter`` and the robust ones of paper 004
    (their uncertainty direction ``M`` on ``device``)."""
    M = torch.tensor([0.1, 0.05], dtype=F64, device=device)
    if name == "rukf":
        return rukf(3.0, M, N=1.0)  # Eq. 28-29 as printed
    if name == "rukf-lemma":
        return rukf(2.0, M, N=0.5, form="lemma")
    if name == "rukf-optimised":
        return rukf(1.05, M, N=1.0, bound="optimised")  # the per-step search for the bound
    if name == "arukf":
        return arukf(3.0, M, 1.0, window=10)
    return make_filter(name)


GAUSSIAN_FILTERS = [*FILTERS, "rukf", "rukf-lemma", "rukf-optimised", "arukf"]

TRAJECTORY_FIELDS = (
    "means",
    "chols",
    "pred_means",
    "pred_chols",
    "innovations",
    "chol_innovations",
    "log_likelihoods",
    "nis",
    "fading_factors",
    "noise_fallback",
    "chol_Q",
    "chol_R",
    "q",
    "r",
)


# ============================================================= 1. the Gaussian filters
@pytest.mark.parametrize("name", GAUSSIAN_FILTERS)
def test_gaussian_filter_run_matches_cpu(name):
    b0, us, ys = nonlinear_data()
    ref = run(gaussian_filter(name, "cpu"), nonlinear_model("cpu"), b0, ys, us)
    got = run(gaussian_filter(name, DEVICE), nonlinear_model(DEVICE), _dev(b0), _dev(ys), _dev(us))
    assert bool(torch.isfinite(ref.means).all()) and bool(torch.isfinite(ref.log_likelihood).all())
    assert float(ref.means.std()) > 0.1  # the runs and steps differ: a real comparison
    for key in TRAJECTORY_FIELDS:
        _same(getattr(got, key), getattr(ref, key), f"{name}: {key}")
    _same(got.log_likelihood, ref.log_likelihood, f"{name}: log_likelihood")
    _same(got.final.belief.chol, ref.final.belief.chol, f"{name}: final chol")


# ============================================================= 2. the smoothers
@pytest.mark.parametrize(
    "name,lag",
    [("ekf", None), ("ukf", None), ("srukf", 4), ("sckf", 3), ("stsckf", None), ("imsrukf", None)],
)
def test_smoothers_match_cpu(name, lag):
    b0, us, ys = nonlinear_data()
    ref = smooth(make_filter(name), nonlinear_model("cpu"), b0, ys, us, lag=lag)
    got = smooth(make_filter(name), nonlinear_model(DEVICE), _dev(b0), _dev(ys), _dev(us), lag=lag)
    for key in ("means", "chols", "cross_covs", "gains", "cond_chols"):
        _same(getattr(got, key), getattr(ref, key), f"{name} lag={lag}: {key}")
    _same(got.initial.mean, ref.initial.mean, "initial mean")
    _same(got.initial.chol, ref.initial.chol, "initial chol")
    _same(got.log_likelihood, ref.log_likelihood, "log_likelihood")
    # the smoother moved the filtered estimates (a smoother that only filters would pass the
    # device comparison too, but not this)
    assert float((ref.means[:-1] - ref.filtered.means[:-1]).abs().max()) > 1e-3


# ============================================================= 3. long sequences in segments
@pytest.mark.parametrize("name", ["srukf", "imsrukf"])
def test_run_in_segments_matches_cpu(name):
    b0, us, ys = nonlinear_data()
    ref = run_in_segments(make_filter(name), nonlinear_model("cpu"), b0, ys, us, segment=7)
    got = run_in_segments(
        make_filter(name), nonlinear_model(DEVICE), _dev(b0), _dev(ys), _dev(us), segment=7
    )
    for key in ("means", "var_Q", "var_R"):
        _same(getattr(got, key), getattr(ref, key), f"{name}: {key}")
    _same(got.final.belief.mean, ref.final.belief.mean, "final mean")
    _same(got.final.belief.chol, ref.final.belief.chol, "final chol")


def _skip_without_triton() -> None:
    """``torch.compile`` on CUDA generates Triton kernels."""
    if DEVICE.type == "cuda":
        try:
            from torch.utils._triton import has_triton
        except ImportError:  # (a torch without the helper: let the compile decide)
            has_triton = None
        if has_triton is not None and not has_triton():
            pytest.skip("torch.compile on CUDA needs Triton")


# ============================================================= 4. particle filters
# Monte Carlo tolerances. The device draws its own random stream, so the particle filters are
# compared with the exact Kalman filter (the engine's EKF on a linear-Gaussian model) through
# z = (mean_PF - mean_KF) / std_KF * sqrt(N) at every step, run and state component (60 values
# per filter), and likewise z_std = (std_PF / std_KF - 1) * sqrt(N) for the posterior spread.
# Measured on the CPU on this very set-up, over 130 seeds per filter (70 for the UPF): the
# largest |z| of a run was 8.1 (SIR), 9.9 (EKPF, UPF), 15.1 (STPF), the root mean square of a
# run's 60 z at most 3.1, 4.1, 4.1, 5.8 (STPF: mean 3.3, sd 0.75); over 40 seeds the largest
# |z_std| 4.1, 5.4, 10.4 (SIR, EKPF, STPF) and its root mean square at most 1.4, 2.1, 2.7. The
# bounds Z_MAX = 25 and Z_RMS = 10 leave a correct filter a negligible chance to fail (the
# errors are near Gaussian; the worst step's sd of z is about 5), while a device result off by
# 0.1 posterior std at every step (z = 14) or by 0.18 std at one step fails (a shift of the
# measurements by 1/6 of their noise std gives an rms z of 21).
Z_MAX, Z_RMS = 25.0, 10.0
N_PARTICLES, PF_STEPS, PF_RUNS = 20000, 15, 2


def linear_gaussian(device) -> StateSpaceModel:
    F = torch.tensor([[0.95, 0.1], [-0.1, 0.9]], dtype=F64)
    H = torch.tensor([[1.0, 0.5]], dtype=F64)
    LQ = torch.tensor([[0.4, 0.0], [0.1, 0.3]], dtype=F64)
    LR = torch.tensor([[0.6]], dtype=F64)
    q, r = torch.tensor([0.05, -0.02], dtype=F64), torch.tensor([0.1], dtype=F64)
    F, H, LQ, LR, q, r = (v.to(device) for v in (F, H, LQ, LR, q, r))
    return linear_gaussian_model(F, H, LQ, LR, q=q, r=r)


def linear_gaussian_data(gaps: bool = True):
    g = _gen(5)
    model = linear_gaussian("cpu")
    b0 = GaussianBelief(
        torch.tensor([[0.5, -0.3], [-0.2, 0.4]], dtype=F64),
        torch.diag(torch.tensor([1.0, 0.7], dtype=F64)).expand(PF_RUNS, 2, 2).clone(),
    )
    x = b0.mean + (b0.chol @ torch.randn(PF_RUNS, 2, 1, generator=g, dtype=F64)).squeeze(-1)
    ys = []
    for t in range(PF_STEPS):
        x = model.transition(x, None, t + 1) + model.q
        x = x + torch.randn(PF_RUNS, 2, generator=g, dtype=F64) @ model.chol_Q.mT
        y = model.observe(x, None, t + 1) + model.r
        ys.append(y + torch.randn(PF_RUNS, 1, generator=g, dtype=F64) @ model.chol_R.mT)
    ys = torch.stack(ys)
    if gaps:
        ys[6, 0] = math.nan  # run 0 missing at step 7
        ys[10] = math.nan  # both runs missing at step 11
    return b0, ys


@pytest.mark.parametrize("name", ["sir", "ekpf", "upf", "stpf"])
def test_particle_filter_on_device_matches_the_exact_kalman_filter(name):
    b0, ys = linear_gaussian_data()
    ref = run(ekf(), linear_gaussian("cpu"), b0, ys)  # exact on a linear-Gaussian model
    pf = make_particle_filter(name, num_particles=N_PARTICLES)
    tr = pf.run(linear_gaussian(DEVICE), _dev(b0), _dev(ys), generator=_gen(3, DEVICE))
    for key in ("means", "covs", "ess", "log_likelihoods", "fading_factors"):
        v = getattr(tr, key)
        assert v.device.type == DEVICE.type, f"{key} on {v.device}"
        assert bool(torch.isfinite(v).all()), key
    assert tr.final.particles.device.type == DEVICE.type
    assert tr.final.particles.shape == (PF_RUNS, N_PARTICLES, 2)
    _same(tr.missing, torch.isnan(ys).any(-1), "missing")
    assert not bool(tr.collapsed.any()) and int(tr.prior_fallback.sum()) == 0
    _near_the_kalman_filter(tr, ref, name)
    assert bool((tr.log_likelihoods.cpu()[torch.isnan(ys).any(-1)] == 0).all())


def _near_the_kalman_filter(tr, ref, name: str) -> None:
    """The particle means and spreads within Monte Carlo error of the exact filter's (z)."""
    means, stds, ess = tr.means.cpu(), tr.stds.cpu(), tr.ess.cpu()
    assert float(ess.min()) > 100.0  # (the STPF's smallest over 130 CPU seeds: 469)
    ref_std = torch.diagonal(ref.covs, dim1=-2, dim2=-1).sqrt()
    root_n = math.sqrt(N_PARTICLES)
    for what, z in (
        ("mean", (means - ref.means) / ref_std * root_n),
        ("std", (stds / ref_std - 1.0) * root_n),
    ):
        big, rms = float(z.abs().max()), float(z.square().mean().sqrt())
        assert big <= Z_MAX and rms <= Z_RMS, f"{name} {what}: max |z| {big:.2f}, rms {rms:.2f}"


def test_compiled_sir_on_device_matches_the_exact_kalman_filter():
    """``sir().run(compile=True)`` on the device (on CUDA: inductor and Triton; its own random
    stream) within Monte Carlo error of the exact filter, as the eager filters above (complete
    measurements: the compiled pass takes no missing ones)."""
    _skip_without_triton()
    b0, ys = linear_gaussian_data(gaps=False)
    ref = run(ekf(), linear_gaussian("cpu"), b0, ys)
    pf = make_particle_filter("sir", num_particles=N_PARTICLES)
    tr = pf.run(
        linear_gaussian(DEVICE), _dev(b0), _dev(ys), generator=_gen(3, DEVICE), compile=True
    )
    for key in ("means", "covs", "ess", "log_likelihoods", "resampled"):
        assert getattr(tr, key).device.type == DEVICE.type, key
    assert tr.final.particles.device.type == DEVICE.type
    _near_the_kalman_filter(tr, ref, "compiled sir")


# ============================================================= 5. the optimiser face
ANFIS_P0 = {"alpha": 1.0, "b": 1e-2, "beta": 1e-4}
OPT_RUNS = 3


def anfis_data(T: int = 40, runs: int | None = None):
    """Inputs ``(T, 3)`` and targets ``(T, 1)`` (one target missing), or ``(runs, T, ...)``
    with per-run noise."""
    g = _gen(3)
    X = torch.rand(T, 3, generator=g, dtype=F64)
    Y = torch.sin(3 * X[:, :1]) + X[:, 1:2] * X[:, 2:3]
    if runs is not None:
        X = X.expand(runs, T, 3).clone()
        Y = Y + 0.05 * torch.randn(runs, T, 1, generator=g, dtype=F64)
    Y[..., 9, 0] = math.nan  # a missing target: the filter updates with the observed ones
    return X, Y


def anfis_optimizer(filt: str, device, runs: int | None, per_run: bool = False):
    X = anfis_data()[0]
    inits = [
        ANFIS(3, 2, generator=_gen(s)).init_premises(X) for s in range(runs or 1)
    ]  # premises on the CPU inputs: the same start on every device
    model = copy.deepcopy(inits[0]).to(device)
    theta0 = ParameterBridge(inits[0]).stack(inits).to(device) if runs else None
    opt = KalmanOptimizer(
        model,
        filter=filt,
        P0=ANFIS_P0,
        Q=1e-6,
        R=1e-3,
        runs=runs,
        theta0=theta0,
        per_run_data=per_run,
    )
    return model, opt


@pytest.mark.parametrize(
    "filt,runs,per_run",
    [
        ("ekf", OPT_RUNS, False),
        ("srukf", OPT_RUNS, False),
        ("imsrukf", OPT_RUNS, False),
        ("ekf", OPT_RUNS, True),
        ("srukf", None, False),
    ],
    ids=["ekf-runs", "srukf-runs", "imsrukf-runs", "ekf-per-run-data", "srukf-one-run"],
)
def test_kalman_optimizer_fit_matches_cpu(filt, runs, per_run):
    X, Y = anfis_data(runs=runs if per_run else None)
    out = []
    for dev in ("cpu", DEVICE):
        model, opt = anfis_optimizer(filt, dev, runs, per_run)
        hist = fit(model, opt, (X.to(dev), Y.to(dev)), epochs=2, batch_size=2, progress=False)
        assert hist.steps == 40
        out.append((opt, hist, ParameterBridge(model).flatten()))
    (ref, href, mref), (got, hgot, mgot) = out
    _same(got.theta, ref.theta, "theta")
    _same(got.belief.chol, ref.belief.chol, "belief chol")
    _same(mgot, mref, "module parameters")
    for e in range(2):
        _same(hgot.loss[e], href.loss[e], f"epoch {e + 1} loss")
        _same(hgot.train["rmse"][e], href.train["rmse"][e], f"epoch {e + 1} rmse")
    # training moved the parameters (the comparison is not of the initial values)
    start = anfis_optimizer(filt, "cpu", runs, per_run)[1].theta
    assert float((ref.theta - start).abs().max()) > 1e-3


def test_compiled_kalman_optimizer_fit_matches_eager_cpu():
    """``fit(compile=True)`` on the device (on CUDA: inductor and Triton) against the eager CPU
    fit: the compiled pass equals the eager steps to rounding (tests/test_compiled_steps.py)."""
    _skip_without_triton()
    X, Y = anfis_data(T=25)
    Y[9, 0] = 0.5  # the compiled pass takes complete targets
    model_c, ref = anfis_optimizer("srukf", "cpu", None)
    href = fit(model_c, ref, (X, Y), batch_size=2, progress=False)
    model_d, got = anfis_optimizer("srukf", DEVICE, None)
    hgot = fit(model_d, got, (_dev(X), _dev(Y)), batch_size=2, progress=False, compile=True)
    assert hgot.steps == href.steps == 13 and hgot.compile_time[0] > 0.0  # compiled, not eager
    _same(got.theta, ref.theta, "theta")
    _same(got.belief.chol, ref.belief.chol, "belief chol")
    _same(hgot.loss[0], href.loss[0], "loss")


# ============================================================= 6. parameter learning


def test_fit_likelihood_matches_cpu():
    g = _gen(3)
    ys = torch.randn(20, 2, generator=g, dtype=F64) * 0.5 + torch.tensor([0.3, 0.0], dtype=F64)
    ys[6] = math.nan
    ys[11, 0] = math.nan
    p0 = {
        "a": torch.tensor(1.3, dtype=F64),
        "c": torch.tensor(0.8, dtype=F64),
        "lq": torch.tensor([[-1.5, 0.0], [0.2, -1.0]], dtype=F64),
        "lr": torch.tensor([[-0.7, 0.0], [0.1, -0.4]], dtype=F64),
    }
    b0 = GaussianBelief(torch.tensor([0.2, 0.0], dtype=F64), 0.5 * torch.eye(2, dtype=F64))
    res = []
    for dev in ("cpu", DEVICE):
        res.append(
            fit_likelihood(
                two_state_model,
                {k: v.to(dev) for k, v in p0.items()},
                sckf(),
                GaussianBelief(b0.mean.to(dev), b0.chol.to(dev)),
                ys.to(dev),
                # (SGD: each step linear in the gradient; Adam's first step, lr * sign(g), would
                # turn a component that is zero up to rounding into a full step of either sign)
                optimizer=lambda p: torch.optim.SGD(p, lr=0.02),
                steps=6,
            )
        )
    ref, got = res
    assert got.steps == ref.steps == 6
    _same(got.trace, ref.trace, "log-likelihood trace")
    for k in p0:
        _same(got.params[k], ref.params[k], f"param {k}")
    assert float(ref.trace[-1] - ref.trace[0]) > 1e-2  # the fit moved


def em_problem():
    """Two series of a 2-state linear-Gaussian model with missing rows (tests/test_em.py)."""
    g = _gen(7)
    A = torch.tensor([[[0.9, 0.2], [-0.1, 0.7]], [[0.85, 0.1], [0.0, 0.75]]], dtype=F64)
    C = torch.tensor([[1.0, 0.0], [0.5, 1.0]], dtype=F64)
    SQ = torch.diag(torch.tensor([0.3, 0.1], dtype=F64).sqrt())
    SR = torch.diag(torch.tensor([0.5, 0.2], dtype=F64).sqrt())
    x, ys = torch.zeros(2, 2, dtype=F64), []
    for _ in range(60):
        x = (A @ x.unsqueeze(-1)).squeeze(-1) + torch.randn(2, 2, generator=g, dtype=F64) @ SQ
        ys.append(x @ C.T + torch.randn(2, 2, generator=g, dtype=F64) @ SR)
    ys = torch.stack(ys)
    ys[[5, 17, 59]] = math.nan
    start = (
        A + 0.1 * torch.randn(2, 2, 2, generator=g, dtype=F64),
        C + 0.1 * torch.randn(2, 2, generator=g, dtype=F64),
        0.7 * torch.eye(2, dtype=F64),
        torch.eye(2, dtype=F64),
        GaussianBelief(torch.zeros(2, 2, dtype=F64), 1.4 * torch.eye(2, dtype=F64).expand(2, 2, 2)),
    )
    return start, ys


def test_em_matches_cpu():
    (A, C, SQ, SR, b0), ys = em_problem()
    ref = em_linear_gaussian(A, C, SQ, SR, b0, ys, iterations=5)
    got = em_linear_gaussian(*(_dev(v) for v in (A, C, SQ, SR, b0, ys)), iterations=5)
    assert got.iterations == ref.iterations == 5
    for key in ("A", "C", "chol_Q", "chol_R", "trace"):
        _same(getattr(got, key), getattr(ref, key), f"EM {key}")
    _same(got.init.mean, ref.init.mean, "EM init mean")
    _same(got.init.chol, ref.init.chol, "EM init chol")
    assert bool((ref.trace[-1] > ref.trace[0] + 1e-3).all())  # EM raised the likelihood


# ============================================================= 7. prognosis
def _dev_noise(noise):
    """A :class:`TrendNoise` with its tensors on the device."""
    return type(noise)(*(_dev(v) for v in noise._fields()))


def degradation(n: int = 80, seed: int = 0):
    """An exponential degradation with irregular times and gaps (tests/test_trends.py)."""
    g = _gen(seed)
    t = torch.sort(torch.rand(n, generator=g, dtype=F64) * 10).values
    L = math.log(0.5) + 0.3 * t + 0.05 * torch.randn(n, generator=g, dtype=F64).cumsum(0)
    y = 1.0 + L.exp() * torch.exp(0.1 * torch.randn(n, generator=g, dtype=F64))
    y[[10, 11, 40]] = math.nan
    return t, y


@pytest.mark.parametrize("filt", ["ekf", "strong-tracking"])
def test_trend_fits_and_first_passage_match_cpu(filt):
    t, y = degradation()
    ref = fit_trends(t, y, phi=1.0, sigma0=0.05)  # EKF over the noise grid (on the CPU)
    got = fit_trends(_dev(t), _dev(y), phi=1.0, sigma0=0.05)
    if filt == "strong-tracking":
        # the SFEKF of the trend models at the noise the EKF chose: over the whole grid some
        # points drive the fading factor to thousands, where any rounding is amplified by 1e7
        noise = {shape: fit_.noise for shape, fit_ in ref.items()}
        kw = dict(phi=1.0, sigma0=0.05, filter=strong_tracking_filter(), noise=noise)
        ref = fit_trends(t, y, **kw)
        got = fit_trends(
            _dev(t), _dev(y), **{**kw, "noise": {k: _dev_noise(v) for k, v in noise.items()}}
        )
        assert float(ref["exponential"].fading.max()) > 1.5  # strong tracking acted
    assert set(got) == set(ref) == {"exponential", "power", "linear"}
    for shape, r in ref.items():
        d = got[shape]
        for key in ("z", "s", "a", "grid_means", "grid_chols", "grid_log_likelihood", "fading"):
            _same(getattr(d, key), getattr(r, key), f"{shape}: {key}")
        assert d.choice == r.choice, shape
    # RUL paths of the exponential trend: drawn on the generator's device (the CPU here) and
    # moved to the data's, so both devices see the same draws
    grid = path_grid(float(t[-1]), 20.0, 0.05)
    level = float(y[~torch.isnan(y)].max()) * 1.5
    a, b = (
        fit_["exponential"].first_passage(-1, level, grid.to(dev), 2000, _gen(1)).times
        for fit_, dev in ((ref, "cpu"), (got, DEVICE))
    )
    assert b.device.type == DEVICE.type
    crossed = torch.isfinite(a)
    assert 0.3 < float(crossed.float().mean())  # many paths cross within the grid
    # a crossing step flips only for a path within rounding of the level at a grid time
    same = torch.isclose(b.cpu(), a, rtol=RTOL, atol=ATOL) | (torch.isinf(a) & torch.isinf(b.cpu()))
    assert float(same.float().mean()) >= 0.999


def test_learner_trend_and_its_paths_match_cpu():
    """The online-trained ELM of time (issue: the learner trend that keeps learning) on the
    device: its optimiser, parameter beliefs and crossing times (drawn from a CPU generator,
    so shared) equal the CPU's. Noise levels given as CPU tensors join the data's device."""
    t, y = degradation()
    kw = dict(phi=1.0, sigma0=0.05, shapes=("exponential",), filter="ekf")
    ref_level = fit_trends(t, y, **kw)["exponential"]
    noise = {"exponential": ref_level.noise}  # CPU tensors, also for the device data
    ref = fit_learner_trend(fit_trends(t, y, **kw, noise=noise)["exponential"], snapshots=(30,))
    got = fit_learner_trend(
        fit_trends(_dev(t), _dev(y), **kw, noise=noise)["exponential"], snapshots=(30,)
    )
    _same(got.optimizer.theta, ref.optimizer.theta, "theta")
    _same(got.optimizer.belief.chol, ref.optimizer.belief.chol, "belief chol")
    for i in ref.snapshots:
        _same(got.snapshots[i].mean, ref.snapshots[i].mean, f"snapshot {i} mean")
        _same(got.snapshots[i].chol, ref.snapshots[i].chol, f"snapshot {i} chol")
    torch.testing.assert_close(got.trace.cpu(), ref.trace, rtol=RTOL, atol=ATOL)
    assert torch.equal(got.seen.cpu(), ref.seen)
    grid = path_grid(float(t[-1]), 20.0, 0.05)
    level = float(y[~torch.isnan(y)].max()) * 1.5
    a = ref.first_passage(-1, level, grid, 2000, _gen(1))
    b = got.first_passage(-1, level, _dev(grid), 2000, _gen(1))
    assert b.times.device.type == DEVICE.type
    assert 0.3 < float(torch.isfinite(a.times).float().mean())  # many paths cross
    bt = b.times.cpu()
    same = torch.isclose(bt, a.times, rtol=RTOL, atol=ATOL) | (
        torch.isinf(a.times) & torch.isinf(bt)
    )
    assert float(same.float().mean()) >= 0.999
    assert torch.equal(b.diverged.cpu(), a.diverged)


def test_fit_shuffles_with_a_device_generator_and_skips_unobserved_batches():
    """``fit`` with ``shuffle`` and a generator on the device, and a gradient optimiser whose
    mini-batch has no observed target (NaN loss, no step) on the device: the same epochs as
    on the CPU when the permutation is the same (a CPU generator on both)."""
    g = _gen(3)
    X = torch.randn(24, 3, generator=g, dtype=F64)
    Y = X @ torch.tensor([[0.5], [-1.0], [2.0]], dtype=F64) + 0.1
    Y[4:8] = math.nan  # batch 2 in order: nothing observed
    out = []
    for dev in ("cpu", DEVICE):
        torch.manual_seed(0)
        lin = torch.nn.Linear(3, 1, dtype=F64).to(dev)
        opt = torch.optim.SGD(lin.parameters(), lr=0.05)
        h = fit(lin, opt, (X.to(dev), Y.to(dev)), epochs=3, batch_size=4, progress=False)
        out.append((lin, h))
    (lr, hr), (ld, hd) = out
    for e in range(3):
        _same(hd.loss[e], hr.loss[e], f"epoch {e + 1} loss")
    _same(ld.weight.detach(), lr.weight.detach(), "weights")
    # shuffled with a generator on the device (its own stream): runs there, learns
    torch.manual_seed(0)
    lin = torch.nn.Linear(3, 1, dtype=F64).to(DEVICE)
    opt = torch.optim.SGD(lin.parameters(), lr=0.05)
    h = fit(lin, opt, (_dev(X), _dev(Y)), epochs=20, batch_size=4, shuffle=True,
            generator=_gen(0, DEVICE), progress=False)  # fmt: skip
    assert h.loss[-1].device.type == DEVICE.type
    assert float(h.loss[-1]) < 0.5 * float(h.loss[0])


def event_model(device) -> StateSpaceModel:
    """x = [level, rate]: the level grows by a rate that drifts with the level (batched f)."""
    SQ = torch.diag(torch.tensor([0.05, 0.002], dtype=F64)).to(device)

    def f(x, u, k):
        lev, rate = x[..., 0], x[..., 1]
        return torch.stack([lev + 0.1 * rate * (1.0 + 0.1 * torch.sin(lev)), rate], -1)

    return StateSpaceModel(
        f, lambda x, u, k: x[..., :1], 2, 1, chol_Q=SQ, chol_R=SQ[:1, :1], batched=True
    )


def test_simulate_to_event_matches_cpu():
    belief = GaussianBelief(
        torch.tensor([[0.0, 1.0], [0.5, 0.8]], dtype=F64),
        torch.diag(torch.tensor([0.1, 0.15], dtype=F64)).expand(2, 2, 2).clone(),
    )
    x0 = sample_belief(belief, 3000, _gen(4))  # (2, 3000, 2) drawn on the CPU
    event = lambda x: x[..., 0] >= 5.0  # noqa: E731
    kw = dict(max_steps=70, t0=2.0, dt=0.5)  # a few samples censored
    ref = simulate_to_event(event_model("cpu"), x0, event, **kw)
    got = simulate_to_event(event_model(DEVICE), _dev(x0), event, **kw)
    assert got.steps_run == ref.steps_run
    _same(got.rul.first_passage, ref.rul.first_passage, "first passage step")
    _same(got.final_state, ref.final_state, "state at the event")
    _same(got.rul.pmf, ref.rul.pmf, "pmf")
    _same(got.censored_mass, ref.censored_mass, "censored mass")
    _same(got.mean, ref.mean, "mean event time")  # NaN: censored mass
    _same(got.quantile([0.25, 0.5]), ref.quantile([0.25, 0.5]), "event time quartiles")
    assert 0.0 < float(ref.censored_mass.min()) and float(ref.censored_mass.max()) < 0.5
    # with process noise the device draws its own stream: a Monte-Carlo comparison of the mean
    # event time against the CPU (difference of two independent sample means, within 7 standard
    # errors) and of its spread (the sample std of 4,000 event times varies by 2 % between
    # seeds here, so a 20 % bound is 7 sd of the ratio)
    kw = dict(max_steps=1000, process_noise=True)
    n = 4000
    ref = simulate_to_event(
        event_model("cpu"), sample_belief(belief, n, _gen(5)), event, generator=_gen(6), **kw
    )
    x0d = sample_belief(_dev(belief), n, _gen(5, DEVICE))
    assert x0d.device.type == DEVICE.type and x0d.shape == (2, n, 2)
    got = simulate_to_event(event_model(DEVICE), x0d, event, generator=_gen(6, DEVICE), **kw)
    assert got.final_state.device.type == DEVICE.type
    assert float(ref.censored_mass.max()) == 0.0 and float(got.censored_mass.max()) == 0.0
    t_ref, t_dev = ref.time_of_event, got.time_of_event.cpu()
    se = (t_ref.var(-1) / n + t_dev.var(-1) / n).sqrt()
    assert bool(((got.mean.cpu() - ref.mean).abs() <= 7.0 * se).all()), (got.mean, ref.mean)
    assert bool(((t_dev.std(-1) / t_ref.std(-1) - 1.0).abs() < 0.2).all())


def test_gaussian_paths_match_cpu():
    """Gaussian multistep prediction (the engine's forecast) on the nonlinear model from the
    filter's final state, and through a learner turned into an m-order model (EKF, Jacobian by
    ``torch.func`` through the learner)."""
    b0, us, ys = nonlinear_data()
    H = 12
    fut = torch.cos(0.2 * torch.arange(H, dtype=F64)).unsqueeze(-1)
    out = []
    for dev in ("cpu", DEVICE):
        model = nonlinear_model(dev)
        tr = run(
            make_filter("srukf"),
            model,
            GaussianBelief(b0.mean.to(dev), b0.chol.to(dev)),
            ys.to(dev),
            us.to(dev),
        )
        out.append(
            gaussian_paths(
                sckf(), model, tr.final, H, us=fut.to(dev), k0=STEPS, channel=1, level=0.9
            )
        )
    ref, got = out
    for key in ("mean", "std", "lower", "upper", "state_mean", "state_chol"):
        _same(getattr(got, key), getattr(ref, key), f"model paths: {key}")

    g = _gen(2)
    series = torch.sin(0.25 * torch.arange(120, dtype=F64)) + 0.05 * torch.randn(
        120, generator=g, dtype=F64
    )
    X, T = embed(series[:100], 4)
    elm = ELM(4, 10, activation="tanh", generator=_gen(8)).fit_ridge(X, T, 1e-3)
    out = []
    for dev in ("cpu", DEVICE):
        learner = copy.deepcopy(elm).to(dev)
        init = window_belief(series.to(dev), 100, 4, 0.05, runs=2)
        out.append(
            predict_paths(
                learner, init, 15, method="gaussian", filt=ekf(), chol_Q=0.05, chol_R=0.05
            )
        )
    ref, got = out
    for key in ("mean", "std", "state_mean", "state_chol"):
        _same(getattr(got, key), getattr(ref, key), f"learner paths: {key}")
    assert float(ref.std[..., -1].min()) > float(ref.std[..., 0].max())  # the spread grows


def test_fleet_exponential_trend_rul_matches_cpu():
    """The batched fleet RUL on a shard whose tensors are on the device (its posterior draws come
    from per-asset CPU generators, so both devices use the same draws)."""
    sf = synthetic_fleet(12, 150, seed=3, ragged=0.5, healthy_fraction=0.1)
    tab = read_fleet_table(sf.table)
    batch = pad_batch(tab.assets, tab.times, tab.values, seed=0)
    on_dev = replace(
        batch, values=_dev(batch.values), times=_dev(batch.times), lengths=_dev(batch.lengths)
    )
    kw = dict(samples=500, horizon=40.0, drift_std=(0.01, 1e-3), return_posterior=True)
    import numpy as np

    for phi in ("baseline", "auto"):  # (the data-scale fit, and the choice per asset)
        a = exponential_trend_rul(batch, sf.threshold, phi=phi, samples=200)
        b = exponential_trend_rul(on_dev, sf.threshold, phi=phi, samples=200)
        assert a["flags"] == b["flags"]
        np.testing.assert_allclose(a["phi"], b["phi"], rtol=1e-12)
        for c in RUL_COLUMNS:
            np.testing.assert_allclose(a[c], b[c], rtol=1e-8, equal_nan=True)
    kw["phi"] = 0.0
    ref = exponential_trend_rul(batch, sf.threshold, **kw)
    got = exponential_trend_rul(on_dev, sf.threshold, **kw)
    assert got["flags"] == ref["flags"]
    for c in RUL_COLUMNS:
        torch.testing.assert_close(
            torch.as_tensor(got[c]), torch.as_tensor(ref[c]), rtol=RTOL, atol=ATOL, equal_nan=True
        )
    for key in ("posterior_mean", "posterior_chol", "onset_index", "log_noise_std"):
        _same(got[key], ref[key], key)
    assert int((ref["onset_index"] >= 0).sum()) >= 6  # most assets have a trend to compare


# ============================================================= 8. ROS-ELM over runs
def test_ros_elm_batched_over_runs_matches_cpu():
    p, L, C, R, lam = 3, 8, 2, 4, 0.1
    g = _gen(9)
    k = torch.arange(40, dtype=F64)
    z = torch.stack([torch.sin(0.3 * k), torch.cos(0.2 * k) + 0.1 * torch.sin(0.7 * k)], -1)
    z = z[:, None, :] + 0.05 * torch.randn(40, R, C, generator=g, dtype=F64)  # (T, R, C)
    elms = [ELM(p, L, activation="tanh", generator=_gen(20 + c)) for c in range(C)]
    out = []
    for dev in ("cpu", DEVICE):
        learners = [copy.deepcopy(e).to(dev) for e in elms]
        zd = z.to(dev)
        s = ros_elm_init(learners, zd[:20], p, lam)
        for t in range(20, 35):
            s = ros_elm_update(learners, s, zd[t])
        out.append((s, ros_elm_forecast(learners, s, 5)))
    (sr, fr), (sg, fg) = out
    assert sg.n_seen == sr.n_seen == 32
    _same(sg.window, sr.window, "window")
    for c in range(C):
        _same(sg.beta[c], sr.beta[c], f"beta[{c}]")
        _same(sg.K[c], sr.K[c], f"K[{c}]")
    _same(fg, fr, "forecast")
    assert fr.shape == (5, R, C) and float(fr.std(1).min()) > 0  # the runs differ


# ============================================================= figures from device tensors
def test_figures_take_device_tensors(tmp_path):
    """The plots take tensors on any device (their inputs are copied to the CPU): the weighted
    quantiles of device samples equal the CPU's, and a heatmap, an RUL trajectory chart and
    a paths chart draw from device tensors."""
    from prognos_torch.plots import (
        HeatmapPanel,
        plot_heatmaps,
        plot_paths,
        plot_rul_trajectory,
        weighted_quantiles,
    )

    g = _gen(5)
    samples = torch.randn(200, 4, generator=g, dtype=F64)
    w = torch.rand(200, 1, generator=g, dtype=F64).expand(200, 4)
    w = w / w.sum(0)
    qs = (0.05, 0.5, 0.95)
    ref = weighted_quantiles(samples, w, qs)
    got = weighted_quantiles(_dev(samples), _dev(w), qs)
    assert (got == ref).all()
    values = _dev(torch.tensor([[1.0, math.nan], [0.5, 2.0]], dtype=F64))
    plot_heatmaps(tmp_path / "h.png", [HeatmapPanel(values, ["a", "b"], ["x", "y"])])
    times, true = _dev(torch.tensor([1.0, 2.0, 3.0])), _dev(torch.tensor([3.0, 2.0, 1.0]))
    pred = {"pred": _dev(torch.tensor([2.5, 2.2, math.inf])), "lo": None, "hi": None}
    panel = {"title": "s", "times": times, "true": true, "t_eol": 4.0, "methods": {"m": pred}}
    plot_rul_trajectory(tmp_path / "r.png", [panel])
    paths = _dev(torch.linspace(0.0, 2.0, 10, dtype=F64).expand(5, 10))
    plot_paths(tmp_path / "p.png", _dev(torch.arange(10.0, dtype=F64)), paths, threshold=1.5)
    assert all((tmp_path / f).stat().st_size > 0 for f in ("h.png", "r.png", "p.png"))


# ============================================================= stacked learners, forecasters
def test_stacked_lssvr_moves_to_the_device_with_its_support_vectors():
    """``StackedLearner.to(device)`` carries the base's buffers (the LS-SVR's support vectors,
    no stacked parameter) along: the stack on the device gives the CPU stack's outputs."""
    X = torch.rand(20, 3, generator=_gen(4), dtype=F64)
    mods = [LSSVR(sigma=0.5 + 0.1 * r, C=10.0).fit(X, X.sum(-1, keepdim=True)) for r in range(2)]
    st = StackedLearner.from_modules(mods)
    xr = X.expand(2, 20, 3)
    _same(copy.deepcopy(st).to(DEVICE)(_dev(xr)).detach(), st(xr).detach(), "stacked LS-SVR")


def test_measurement_forecaster_on_the_device():
    """``MeasurementForecaster.ros_elm(device=...)``: ROS-ELMs drawn from a CPU generator and
    moved; initialise, update and forecast on device measurements give the CPU's numbers. ELMs
    on another device than the measurements are refused by name."""
    t = torch.arange(40, dtype=F64)
    z = torch.stack([torch.sin(0.2 * t), 0.5 * torch.cos(0.1 * t)], -1)  # (T, C)
    out = []
    for dev in ("cpu", DEVICE):
        fc = MeasurementForecaster.ros_elm(2, n_hidden=12, generator=_gen(9), device=dev)
        fc.initialize(z[:20].to(dev))
        for k in range(20, 30):
            fc.update(z[k].to(dev))
        out.append(fc.forecast(4))
    _same(out[1], out[0], "forecast")
    if DEVICE.type != "cpu":
        fc = MeasurementForecaster.ros_elm(2, n_hidden=12, generator=_gen(9))  # on the CPU
        with pytest.raises(ValueError, match=r"elms\[0\] is on cpu"):
            fc.initialize(_dev(z[:20]))


def test_known_threshold_protocol_on_the_device():
    """The RUL protocol (threshold, end of life, onset, prediction times, true RUL) of a
    synthetic run to failure given on the device: the CPU's numbers, its tensors on the
    device."""
    from prognos_torch.prognosis.protocol import known_threshold_protocol
    from prognos_torch.systems.run_to_failure import simulate_run_to_failure

    r = simulate_run_to_failure("hump", _gen(2), life=(30.0, 30.0), gaps=False)
    ref = known_threshold_protocol(r.t, r.y)
    got = known_threshold_protocol(_dev(r.t), _dev(r.y))
    assert ref.valid and got.valid
    assert (got.threshold, got.t_eol, got.i_eol, got.t_onset, got.i_onset) == (
        ref.threshold, ref.t_eol, ref.i_eol, ref.t_onset, ref.i_onset
    )  # fmt: skip
    _same(got.times, ref.times, "prediction times")
    _same(got.true_rul, ref.true_rul, "true RUL")


def test_conformal_calibration_on_the_device_matches_cpu():
    from prognos_torch.prognosis.conformal import calibrate_intervals, interval_scores

    g = torch.Generator().manual_seed(3)
    med = torch.exp(3 * torch.rand(200, generator=g, dtype=torch.float64))
    lo, hi = med / 2, med * 2
    tr = med * torch.exp(0.8 * torch.randn(200, generator=g, dtype=torch.float64))
    want = calibrate_intervals(lo, hi, tr, median=med, bins=3)
    got = calibrate_intervals(_dev(lo), _dev(hi), _dev(tr), median=_dev(med), bins=3)
    assert got == want
    _same(interval_scores(_dev(lo), _dev(hi), _dev(tr)), interval_scores(lo, hi, tr), "scores")
    for a, b in zip(got.interval(_dev(lo), _dev(hi), _dev(med)), want.interval(lo, hi, med)):
        _same(a, b, "calibrated interval")
