"""studies.indicator_protocol (paper 002's protocol on a measured indicator) against closed
forms and small cases by hand."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from torch import nn

from prognos_torch.filters import ekpf, sir
from prognos_torch.learners import MultiStepCV
from prognos_torch.prognosis import learner_transition_model
from prognos_torch.studies import indicator_protocol as ip
from prognos_torch.studies.indicator_report import protocol_figures

F64 = torch.float64


# --------------------------------------------------------------------------- the case
def test_indicator_case_by_hand():
    t = 0.5 * torch.arange(12, dtype=F64)  # dt = 0.5
    z = 0.125 * torch.arange(12, dtype=F64)  # reaches 0.8 first at k = 7 (0.875), t = 3.5
    case = ip.indicator_case(z, t, 2, threshold=0.8, rul_start=1.2, rul_every=0.5, horizon=2.2)
    assert case.k0 == 2 and case.t_eol == 3.5 and case.dt == 0.5 and case.cap == 4
    # nominal times 1.2, 1.7, ..., 3.2: last samples at t = 1.0, 1.5, 2.0, 2.5, 3.0
    assert case.rul_idx == [2, 3, 4, 5, 6]
    torch.testing.assert_close(case.times, torch.tensor([1.0, 1.5, 2.0, 2.5, 3.0], dtype=F64))
    torch.testing.assert_close(case.true_rul, torch.tensor([2.5, 2.0, 1.5, 1.0, 0.5], dtype=F64))
    torch.testing.assert_close(case.windows, 0.125 * torch.tensor([[1.0, 2], [2, 3], [3, 4],
                                                                   [4, 5], [5, 6]], dtype=F64))  # fmt: skip
    assert torch.equal(case.truth, z[2:]) and torch.equal(case.t_target, t[2:])
    w = case.one_step_windows  # the window before each predicted sample z[2:]
    assert w.shape == (10, 2) and torch.equal(w[0], z[0:2]) and torch.equal(w[-1], z[9:11])
    late = ip.indicator_case(z, t, 2, threshold=0.8, rul_start=1.2, rul_every=0.5, horizon=2.2,
                             start=1.9)  # fmt: skip
    assert late.k0 == 4 and late.rul_idx == [4, 5, 6]  # no prediction before the filter starts
    early = ip.indicator_case(z, t, 2, threshold=0.8, rul_start=1.2, rul_every=0.5, horizon=2.2,
                              start=0.2)  # fmt: skip
    assert early.k0 == 2  # never before the first full window


# --------------------------------------------------------------------------- the protocol
class _Drift(nn.Module):
    """x_{s+1} = x_s + c: the recursion of a straight line, with its Jacobian (Eq. 25 form)."""

    n_in, n_out = 2, 1

    def __init__(self, c: float):
        super().__init__()
        self.register_buffer("c", torch.tensor(c, dtype=F64))

    def forward(self, x):
        return x[..., -1:] + self.c

    def input_gradient(self, x):
        g = torch.zeros(x.shape[0], 1, 2, dtype=x.dtype)
        g[..., -1] = 1.0
        return g


@pytest.fixture(scope="module")
def drift_run():
    # z_k = 0.125 k at t_k = 0.5 k crosses 0.8 first at k = 7 (t_eol = 3.5); from a window
    # ending at z_i the recursion needs j = 7 - i steps: RUL = 0.5 (7 - i) = t_eol - t_i exactly
    t = 0.5 * torch.arange(12, dtype=F64)
    z = 0.125 * torch.arange(12, dtype=F64)
    case = ip.indicator_case(z, t, 2, threshold=0.8, rul_start=1.2, rul_every=0.5, horizon=5.0)
    learner = _Drift(0.125)
    Q = 1e-5 * torch.eye(2, dtype=F64)  # on every window element, as the study's q^2 I
    model = learner_transition_model(learner, 2, Q, 1e-5, jacobian="input_gradient")
    filters = {"PF": sir(16, resample_threshold=0.5), "EKPF": ekpf(16, resample_threshold=0.5)}
    res = ip.evaluate_learner_filters(
        learner, model, filters, case, runs=2, seeds=[0, 1], name="drift"
    )
    return case, res


def test_learner_alone_predicts_and_crosses_as_the_closed_form(drift_run):
    case, res = drift_run
    assert list(res) == ["drift", "PF", "EKPF"]
    alone = res["drift"]
    assert alone.filter is None and alone.seconds >= 0
    assert torch.equal(alone.pred, case.truth)  # z_{k-1} + 0.125 = z_k, exact in binary
    assert alone.rul_pred.shape == (5, 1)
    torch.testing.assert_close(alone.rul_pred[:, 0], case.true_rul, rtol=0, atol=1e-12)
    assert float(alone.rul.censored_mass.max()) == 0.0


def test_filters_follow_the_line_and_their_paths_cross_on_time(drift_run):
    case, res = drift_run
    T = case.truth.shape[0]
    for name in ("PF", "EKPF"):
        r = res[name]
        p = r.filter
        assert p.pred.shape == p.fault.shape == p.filtered.shape == p.ess.shape == (T, 2)
        assert p.particles.shape == (5, 2, 16, 2) and p.weights.shape == (5, 2, 16)
        truth = case.truth[:, None].expand(T, 2)
        torch.testing.assert_close(p.pred, truth, rtol=0, atol=1e-3)  # made before z_k is seen
        torch.testing.assert_close(p.filtered, truth, rtol=0, atol=1e-3)  # newest element
        # fault(1, k) = P(x_{k|k-1} >= 0.8): 1 for the samples at or above the threshold
        torch.testing.assert_close(p.fault, (case.truth >= 0.8).to(F64)[:, None].expand(T, 2))
        torch.testing.assert_close(r.rul_pred, case.true_rul[:, None].expand(5, 2), atol=1e-12,
                                   rtol=0)  # fmt: skip
        assert bool((p.ess >= 1.0 - 1e-9).all()) and bool((p.ess <= 16 + 1e-9).all())
    with pytest.raises(ValueError, match="one seed per filter"):
        ip.evaluate_learner_filters(
            _Drift(0.125), None, {"PF": sir(4)}, case, runs=1, seeds=[], name="x"
        )


def test_particle_pass_without_keep_returns_no_sets():
    z = 0.125 * torch.arange(8, dtype=F64)
    model = learner_transition_model(_Drift(0.125), 2, 1e-4, 1e-4, jacobian="input_gradient")
    gen = torch.Generator().manual_seed(0)
    p = ip.particle_pass(sir(8), model, z, 2, 3, gen, threshold=0.5)
    assert p.particles is None and p.weights is None and p.pred.shape == (6, 3)
    assert p.prior_fallback == 0 and p.collapsed >= 0


def test_protocol_rows_by_hand(drift_run):
    case, res = drift_run
    T = case.truth.shape[0]
    late = case.t_target >= 3.0  # the last 6 of the 10 predicted samples
    twice = (1.0 + late.to(F64))[:, None]  # errors s before, 2 s from t = 3 on
    shift = torch.tensor([0.1, 0.2], dtype=F64)
    hand = dict(res)
    hand["drift"] = replace(res["drift"], pred=case.truth + 0.5 * twice[:, 0])
    p = replace(res["PF"].filter, pred=case.truth[:, None] + shift * twice)
    p = replace(p, filtered=case.truth[:, None] - shift, fault=late.to(F64)[:, None].expand(T, 2))
    hand["PF"] = replace(res["PF"], filter=p, pred=p.pred)
    del hand["EKPF"]
    rul_kw = dict(t_eol=case.t_eol, d0=2.5, alpha=0.3, lam=0.5, cra_lambdas=(0.0, 0.5))
    rows = ip.protocol_rows(
        hand, case, spans={"all": None, "late": late}, fault_spans={"Pf_late": late}, rul_kw=rul_kw
    )
    assert [r["method"] for r in rows] == ["drift", "PF", "PF"]
    assert list(rows[0]) == ["run", "method", "RMSE_all", "RMSE_late", *ip.POINT_RUL_KEYS,
                             "censored", "time_s"]  # fmt: skip
    assert list(rows[1]) == ["run", "method", "RMSE_all", "RMSE_late", "filt_RMSE_all",
                             "filt_RMSE_late", "Pf_late", *ip.POINT_RUL_KEYS, "censored", "ess",
                             "time_s"]  # fmt: skip
    whole = math.sqrt((4 * 1 + 6 * 4) / 10)  # RMSE over all 10 samples, in units of s
    assert rows[0]["RMSE_all"] == pytest.approx(0.5 * whole)
    assert rows[0]["RMSE_late"] == pytest.approx(1.0)
    for i, (r, s) in enumerate(zip(rows[1:], (0.1, 0.2))):
        assert r["run"] == i
        assert r["RMSE_all"] == pytest.approx(s * whole) and r["RMSE_late"] == pytest.approx(2 * s)
        assert r["filt_RMSE_all"] == pytest.approx(s) and r["Pf_late"] == 1.0
        assert r["ess"] == pytest.approx(float(res["PF"].filter.ess[:, i].mean()))
    # exact RULs: accuracy exp(0) = 1, RMSE 0, alpha-lambda met, CRA = mean RA = 1
    for r in rows:
        assert r["Accuracy"] == pytest.approx(1.0) and r["RUL_RMSE"] == pytest.approx(
            0.0, abs=1e-12
        )
        assert r["alpha_lambda"] == 1.0 and r["CRA"] == pytest.approx(1.0)
        assert r["censored"] == 0.0


def test_tables_by_hand(drift_run):
    case, res = drift_run
    table = ip.rul_table(res, case, ["drift", "PF"], every=2)
    assert table.splitlines() == [
        "| prediction time (d) | true RUL (d) | drift | PF |",
        "|---|---|---|---|",
        "| 1.000 | 2.500 | 2.500 | 2.500 |",
        "| 2.000 | 1.500 | 1.500 | 1.500 |",
        "| 3.000 | 0.500 | 0.500 | 0.500 |",
    ]
    scores = {
        (3.0, 10.0): MultiStepCV(0.012345, 0.5, 4.0, 10, 8),
        (30.0, 1e4): MultiStepCV(0.01, 0.25, math.nan, 10, 0),
    }
    cv = ip.selection_table(scores, dt=0.25, test_rmse={(3.0, 10.0): 0.1, (30.0, 1e4): 0.2},
                            chosen={"one-step": (30.0, 1e4), "ms": (30.0, 1e4)})  # fmt: skip
    assert cv.splitlines()[2:] == [
        "| 3 | 10 | 0.01235 | 0.50000 | 1.000 | 0.10000 |",
        "| 30 **(one-step)** **(ms)** | 10000 | 0.01000 | 0.25000 | nan | 0.20000 |",
    ]
    assert cv.splitlines()[0].startswith("| sigma / std | C | one-step CV RMSE |")


def test_protocol_figures_write_the_paper_figures(drift_run, tmp_path):
    case, res = drift_run
    figs = protocol_figures(
        tmp_path, res, res, case, short={"drift": "d", "PF": "pf", "EKPF": "ekpf"},
        tail=case.t_target >= 3.0, span_labels=("all", "late"), paper_idx=[0, 2], alpha=0.3,
        lam=0.5, pmf_bin=(2, "1 d"), gap=0.75,
    )  # fmt: skip
    expected = ["fig8_one_step.png", "fig9_abs_error.png"]
    for s in ("pf", "ekpf"):
        expected += [f"fig10_fault_probability_{s}.png", f"fig10_fault_probability_box_{s}.png",
                     f"fig12_rul_pdf_{s}.png"]  # fmt: skip
    expected += [f"fig13_alpha_lambda_{s}.png" for s in ("d", "pf", "ekpf")]
    assert figs == expected
    for f in figs:
        assert (tmp_path / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f


# --------------------------------------------------------------------------- diagnostics
def test_candidate_test_rmse_fits_each_grid_point_on_the_training_pairs():
    from prognos_torch.datasets import embed
    from prognos_torch.learners import fit_lssvr_gram

    t = 0.5 * torch.arange(30, dtype=F64)
    k = torch.arange(30, dtype=F64)
    z = 0.04 * k + 0.1 * torch.sin(0.7 * k)  # reaches 0.9 near k = 22
    case = ip.indicator_case(z, t, 2, threshold=0.9, rul_start=1.0, rul_every=1.0, horizon=2.0)
    X, y = embed(z[:20], 2)
    keys = [(1.0, 10.0), (3.0, 1e3)]
    got = ip.candidate_test_rmse(X, y, keys, scale=0.5, case=case)
    assert list(got) == keys
    for s, C in keys:  # sigma = key[0] x scale, scored on the windows before each predicted sample
        f = fit_lssvr_gram(X, y, sigma=0.5 * s, C=C)
        pred = f(case.one_step_windows)[:, 0].detach()
        ref = float((pred - case.truth).pow(2).mean().sqrt())
        assert got[(s, C)] == pytest.approx(ref, rel=1e-12)
    assert all(math.isfinite(v) and v > 0 for v in got.values())


def test_proposal_ess_is_the_jittered_ekpf_pass(drift_run):
    case, _ = drift_run
    learner, q = _Drift(0.125), 1e-3
    kw = dict(n_particles=16, steps=6, resample_threshold=0.5, threshold=0.8, seed=3)
    ess = ip.proposal_ess(learner, 2, q, case.z, jitter=0.1, **kw)
    model = learner_transition_model(learner, 2, q, q, jacobian="input_gradient",
                                     shift_std=0.1 * q)  # fmt: skip
    gen = torch.Generator().manual_seed(3)
    ref = ip.particle_pass(ekpf(16, resample_threshold=0.5), model, case.z[:8], 2, 1, gen,
                           threshold=0.8).ess  # fmt: skip
    assert ref.shape[0] == 6 and ess == pytest.approx(float(ref.mean()), rel=1e-12)
    assert 1.0 <= ess <= 16.0


def test_indicator_figure_writes_its_file(tmp_path):
    from prognos_torch.studies.indicator_report import indicator_figure

    t = torch.arange(10, dtype=F64)
    indicator_figure(tmp_path / "fig1.png", t, {"a": 0.1 * t, "b": 0.05 * t}, threshold=0.5,
                     t_eol=5.0, title="x", ylabel="y", xlabel="t", gap=None)  # fmt: skip
    assert (tmp_path / "fig1.png").stat().st_size > 0
