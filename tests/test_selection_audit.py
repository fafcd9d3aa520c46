"""Audit of the LS-SVR model selection (learners.selection, learners.lssvr_gram): every grid
cell's one-step, multi-step and time-to-cross scores against NumPy refits of the KKT system
(paper 002 Eq. 4) without each held block, scored per origin by plain loops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prognos_torch.learners import blocked_multistep_cv, lssvr_gram_fitter, lssvr_grid_cv

F64 = torch.float64


def _kkt(X, y, sigma, C):
    """LS-SVR by the bordered KKT system [[0, 1^T], [1, K + I/C]] solved densely (NumPy)."""
    n = X.shape[0]
    K = np.exp(-((X[:, None] - X[None]) ** 2).sum(-1) / (2 * sigma**2))
    A = np.zeros((n + 1, n + 1))
    A[0, 1:] = A[1:, 0] = 1.0
    A[1:, 1:] = K + np.eye(n) / C
    sol = np.linalg.solve(A, np.r_[0.0, y])
    b, alpha = sol[0], sol[1:]
    return lambda Q: np.exp(-((Q[:, None] - X[None]) ** 2).sum(-1) / (2 * sigma**2)) @ alpha + b


def _reference(z, m, H, k, sigma, C, thr, above, stride):
    """blocked_multistep_cv's docstring by loops: fold of window i is floor(i k / N)."""
    n, N = len(z), len(z) - m
    X, y = np.stack([z[i : i + m] for i in range(N)]), z[m:]
    hit = (lambda v: v >= thr) if above else (lambda v: v <= thr)
    sq1 = sqh = sqc = 0.0
    nh = no = nc = 0
    for f in range(k):
        held = [i for i in range(N) if i * k // N == f]
        train = [i for i in range(N) if i * k // N != f]
        p = _kkt(X[train], y[train], sigma, C)
        sq1 += sum((p(X[i : i + 1])[0] - y[i]) ** 2 for i in held)
        for i in held[::stride]:
            w, o, path = X[i].copy(), i + m - 1, []
            for _ in range(H):
                v = p(w[None])[0]
                path.append(v)
                w = np.r_[w[1:], v]
            L = min(H, n - 1 - o)
            sqh += sum((path[j - 1] - z[o + j]) ** 2 for j in range(1, L + 1))
            nh, no = nh + L, no + 1
            if thr is not None and not hit(z[o]):  # the safe side
                jh = next((j for j in range(1, L + 1) if hit(path[j - 1])), L + 1)
                jt = next((j for j in range(1, L + 1) if hit(z[o + j])), L + 1)
                sqc, nc = sqc + (jh - jt) ** 2, nc + 1
    return math.sqrt(sq1 / N), math.sqrt(sqh / nh), math.sqrt(sqc / nc) if nc else math.nan, no, nc


def _series(n=47, seed=3):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=F64)
    return 0.03 * t + 0.4 * torch.sin(t / 2.5) + 0.05 * torch.randn(n, generator=g, dtype=F64)


def _assert_scores(got, ref):
    assert got.one_step == pytest.approx(ref[0], rel=1e-10)
    assert got.multi_step == pytest.approx(ref[1], rel=1e-10)
    assert got.crossing == pytest.approx(ref[2], rel=1e-12)  # integer steps: exact
    assert (got.origins, got.crossing_origins) == (ref[3], ref[4])


def test_lssvr_grid_cv_every_cell_and_choice_match_kkt_refits():
    # N = 44 windows in 5 folds (9, 9, 9, 9, 8: the last block short), every 2nd origin
    z = _series()
    scores = lssvr_grid_cv(
        z, 3, 7, sigmas=(0.5, 2.0), Cs=(3.0, 300.0), scale=0.7, folds=5, threshold=1.0, stride=2
    )
    refs = {k: _reference(z.numpy(), 3, 7, 5, k[0] * 0.7, k[1], 1.0, True, 2) for k in scores}
    for k, got in scores.items():
        _assert_scores(got, refs[k])
    for i, name in enumerate(("one_step", "multi_step", "crossing")):
        # the chosen cell by each criterion (min over the grid order: first on a tie)
        chosen = min(scores, key=lambda k: getattr(scores[k], name))
        assert chosen == min(refs, key=lambda k: refs[k][i])


@pytest.mark.parametrize("m, folds, H, stride", [(1, 5, 4, 1), (2, 45, 3, 1), (4, 43, 9, 3)])
def test_blocked_multistep_cv_of_the_lssvr_below_threshold_matches_kkt_refits(m, folds, H, stride):
    # direction="below" with a real LS-SVR; as many folds as windows (one window each)
    z = _series()
    got = blocked_multistep_cv(
        lssvr_gram_fitter(0.9, 50.0), z, m, H, folds, threshold=0.2, direction="below",
        stride=stride,
    )  # fmt: skip
    _assert_scores(got, _reference(z.numpy(), m, H, folds, 0.9, 50.0, 0.2, False, stride))


def test_lssvr_grid_cv_of_a_float32_series():
    # the fold evaluator is float64: a float32 series was refused ("x has dtype torch.float32
    # but the module has dtype torch.float64"); it is now fitted and scored in float64
    z32 = _series().float()
    got = lssvr_grid_cv(z32, 3, 4, sigmas=(1.0,), Cs=(30.0,), folds=4, threshold=1.0)[1.0, 30.0]
    ref = _reference(z32.double().numpy(), 3, 4, 4, 1.0, 30.0, 1.0, True, 1)
    assert got.one_step == pytest.approx(ref[0], rel=1e-6)
    assert got.multi_step == pytest.approx(ref[1], rel=1e-5)
    assert (got.origins, got.crossing_origins) == (ref[3], ref[4])
    predict = lssvr_gram_fitter(1.0, 30.0)(z32.unfold(0, 3, 1)[:-1], z32[3:])
    assert predict(z32[:3][None]).dtype == torch.float32


def test_lssvr_grid_cv_reads_a_generator_grid_once():
    # a generator of Cs was exhausted by the first width: 2 of the 4 cells silently missing
    z = _series(30)
    got = lssvr_grid_cv(z, 3, 2, sigmas=(1.0, 2.0), Cs=(c for c in (10.0, 100.0)), folds=3)
    assert list(got) == [(1.0, 10.0), (1.0, 100.0), (2.0, 10.0), (2.0, 100.0)]
    ref = _reference(z.numpy(), 3, 2, 3, 2.0, 100.0, None, True, 1)
    assert got[2.0, 100.0].one_step == pytest.approx(ref[0], rel=1e-10)


def test_lssvr_grid_cv_rejects_a_bad_grid_by_name():
    z = _series(30)
    kw = dict(sigmas=(1.0,), Cs=(10.0,), folds=3)
    with pytest.raises(ValueError, match=r"sigmas must be a non-empty"):  # returned {}
        lssvr_grid_cv(z, 3, 2, **(kw | dict(sigmas=())))
    with pytest.raises(TypeError, match=r"Cs\[1\] must be a finite number > 0"):
        lssvr_grid_cv(z, 3, 2, **(kw | dict(Cs=(10.0, "a"))))
    with pytest.raises(TypeError, match=r"sigmas must be a non-empty sequence"):
        lssvr_grid_cv(z, 3, 2, **(kw | dict(sigmas=1.0)))
    with pytest.raises(ValueError, match=r"scale must be a finite number > 0, got nan"):
        lssvr_grid_cv(z, 3, 2, **kw, scale=float("nan"))


def test_best_setting_skips_nan_scores_keeps_grid_order_on_ties_and_names_an_empty_choice():
    """The study chose with min(scores, key=...): a NaN first cell (no origin qualified for the
    crossing score) was kept, since nothing compares below NaN."""
    from prognos_torch.learners import MultiStepCV, best_setting

    def cv(one, cross):
        return MultiStepCV(one, 1.0, cross, 3, 2)

    nan = float("nan")
    scores = {(1.0, 10.0): cv(0.3, nan), (1.0, 100.0): cv(0.2, 5.0), (3.0, 10.0): cv(0.2, 4.0),
              (3.0, 100.0): cv(0.5, 4.0)}  # fmt: skip
    assert min(scores, key=lambda k: scores[k].crossing) == (1.0, 10.0)  # the former choice
    assert best_setting(scores, "crossing") == (3.0, 10.0)  # lowest finite, first of the tie
    assert best_setting(scores, "one_step") == (1.0, 100.0)
    with pytest.raises(ValueError, match="no setting has a finite crossing score"):
        best_setting({(1.0, 1.0): cv(0.1, nan)}, "crossing")
    with pytest.raises(ValueError, match="criterion must be"):
        best_setting(scores, "rmse")
