"""learners.selection: blocked folds and blocked cross-validation against closed forms."""

from __future__ import annotations

import math

import pytest
import torch

from prognos_torch.learners import (
    LSSVR,
    LSSVRGram,
    blocked_cv_rmse,
    blocked_folds,
    blocked_multistep_cv,
)


def test_blocked_folds_are_contiguous_and_balanced():
    for n, k in ((10, 5), (11, 3), (7, 7), (23, 4)):
        f = blocked_folds(n, k)
        assert f.dtype == torch.int64 and f.shape == (n,)
        assert f[0] == 0 and f[-1] == k - 1
        assert bool((f.diff() >= 0).all()) and bool((f.diff() <= 1).all())  # contiguous blocks
        sizes = torch.bincount(f, minlength=k)
        assert int(sizes.max() - sizes.min()) <= 1 and int(sizes.sum()) == n
    with pytest.raises(ValueError, match="folds"):
        blocked_folds(5, 1)
    with pytest.raises(ValueError, match="folds"):
        blocked_folds(3, 4)
    with pytest.raises(ValueError, match="n"):
        blocked_folds(0, 2)


def test_blocked_cv_of_the_training_mean_has_a_closed_form():
    # predictor = mean of the training targets: the out-of-fold error of fold f is
    # y_i - (S - S_f) / (n - n_f), with S the total and S_f the fold sum.
    g = torch.Generator().manual_seed(0)
    y = torch.randn(17, generator=g, dtype=torch.float64)
    X = torch.arange(17.0, dtype=torch.float64)[:, None]
    got = blocked_cv_rmse(lambda Xt, yt: lambda Xh: yt.mean().expand(Xh.shape[0]), X, y, 4)
    folds = [list(range(0, 5)), list(range(5, 9)), list(range(9, 13)), list(range(13, 17))]
    assert [int(torch.sum(blocked_folds(17, 4) == f)) for f in range(4)] == [5, 4, 4, 4]
    S, sq = float(y.sum()), 0.0
    for idx in folds:
        Sf = float(y[idx].sum())
        mu = (S - Sf) / (17 - len(idx))
        sq += sum((float(y[i]) - mu) ** 2 for i in idx)
    assert got == pytest.approx(math.sqrt(sq / 17), rel=1e-14)


def test_blocked_cv_never_trains_on_the_held_block():
    X = torch.arange(12.0, dtype=torch.float64)[:, None]
    y = X[:, 0].clone()
    seen = []

    def fit(Xt, yt):
        seen.append(set(Xt[:, 0].tolist()))
        return lambda Xh: Xh[:, 0]  # perfect predictor: RMSE 0

    assert blocked_cv_rmse(fit, X, y, 3) == 0.0
    assert seen == [set(range(4, 12)), set(range(0, 4)) | set(range(8, 12)), set(range(0, 8))]


def test_blocked_cv_with_the_lssvr_matches_a_manual_loop():
    g = torch.Generator().manual_seed(1)
    z = torch.randn(60, generator=g, dtype=torch.float64).cumsum(0) * 0.1
    X = torch.stack([z[i : i + 3] for i in range(56)])
    y = z[3:59]

    def fit(Xt, yt):
        lr = LSSVRGram(LSSVR(kernel="rbf", sigma=0.5, C=100.0).fit(Xt, yt))
        return lambda Xh: lr(Xh)[:, 0]

    got = blocked_cv_rmse(fit, X, y, 5)
    sq = 0.0
    for f in range(5):
        hold = torch.arange(56) * 5 // 56 == f
        lr = LSSVR(kernel="rbf", sigma=0.5, C=100.0).fit(X[~hold], y[~hold])
        with torch.no_grad():
            sq += float(((lr(X[hold])[:, 0] - y[hold]) ** 2).sum())
    assert got == pytest.approx(math.sqrt(sq / 56), rel=1e-10)


def test_blocked_cv_rejects_bad_input():
    X, y = torch.zeros(6, 2, dtype=torch.float64), torch.zeros(6, dtype=torch.float64)
    with pytest.raises(ValueError, match="same number of rows"):
        blocked_cv_rmse(lambda a, b: a, X, y[:5])
    with pytest.raises(TypeError, match="fit"):
        blocked_cv_rmse(3, X, y)
    with pytest.raises(TypeError, match="tensors"):
        blocked_cv_rmse(lambda a, b: a, X.numpy(), y)
    with pytest.raises(ValueError, match="predictor returned shape"):
        blocked_cv_rmse(lambda a, b: lambda Xh: Xh, X, y, 2)


# --------------------------------------------------------------------------- multi-step selection
def _persistence(Xt, yt):
    return lambda Xh: Xh[:, -1]


def _endpoint_trend(Xt, yt):  # x^ = x_m + (x_m - x_1) / (m - 1): the window's end-point slope
    return lambda Xh: Xh[:, -1] + (Xh[:, -1] - Xh[:, 0]) / (Xh.shape[1] - 1)


def _reference(predict, z, m, H, folds, thr, stride):
    """Plain per-origin loops (fits ignore the data here, so the folds only pick the origins)."""
    n, zs = len(z), z.tolist()
    nw = n - m
    sq1 = sqh = sqc = 0.0
    nh = no = nc = 0
    for f in range(folds):
        held = [i for i in range(nw) if i * folds // nw == f]
        for i in held:
            w = torch.tensor(zs[i : i + m], dtype=torch.float64)[None]
            sq1 += (float(predict(w)[0]) - zs[i + m]) ** 2
        for i in held[::stride]:
            w = torch.tensor(zs[i : i + m], dtype=torch.float64)[None]
            o = i + m - 1
            path = []
            for _ in range(H):
                nxt = float(predict(w)[0])
                path.append(nxt)
                w = torch.cat([w[:, 1:], torch.tensor([[nxt]], dtype=torch.float64)], 1)
            L = min(H, n - 1 - o)
            for j in range(1, L + 1):
                sqh += (path[j - 1] - zs[o + j]) ** 2
                nh += 1
            no += 1
            if zs[o] < thr and L >= 1:
                jh = next((j for j in range(1, L + 1) if path[j - 1] >= thr), L + 1)
                jt = next((j for j in range(1, L + 1) if zs[o + j] >= thr), L + 1)
                sqc += (jh - jt) ** 2
                nc += 1
    return math.sqrt(sq1 / nw), math.sqrt(sqh / nh), math.sqrt(sqc / nc), no, nc


@pytest.mark.parametrize("fit", [_persistence, _endpoint_trend])
def test_blocked_multistep_cv_matches_per_origin_loops(fit):
    g = torch.Generator().manual_seed(4)
    z = 0.05 * torch.arange(83, dtype=torch.float64) + 0.2 * torch.randn(83, generator=g)
    got = blocked_multistep_cv(fit, z, 4, 9, 4, threshold=2.5, stride=2)
    ref = _reference(fit(None, None), z, 4, 9, 4, 2.5, 2)
    assert got.one_step == pytest.approx(ref[0], rel=1e-12)
    assert got.multi_step == pytest.approx(ref[1], rel=1e-12)
    assert got.crossing == pytest.approx(ref[2], rel=1e-12)
    assert (got.origins, got.crossing_origins) == (ref[3], ref[4])


def test_blocked_multistep_cv_closed_form_on_a_ramp():
    # z_k = d k: persistence misses by j d at step j; it never crosses, the ramp does
    d, n, m, H = 0.1, 40, 3, 5
    z = d * torch.arange(n, dtype=torch.float64)
    got = blocked_multistep_cv(_persistence, z, m, H, 2, threshold=100.0)
    assert got.one_step == pytest.approx(d, rel=1e-12)
    # every origin o = i + m - 1 (i = 0..n-m-1) covers L_o = min(H, n - 1 - o) steps
    sq = cnt = 0
    for i in range(n - m):
        L = min(H, n - 1 - (i + m - 1))
        sq += sum((j * d) ** 2 for j in range(1, L + 1))
        cnt += L
    assert got.multi_step == pytest.approx(math.sqrt(sq / cnt), rel=1e-12)
    assert got.crossing == 0.0  # nothing crosses 100: both capped at L + 1
    perfect = blocked_multistep_cv(_endpoint_trend, z, m, H, 2, threshold=2.05)
    assert perfect.one_step == pytest.approx(0.0, abs=1e-12)
    assert perfect.multi_step == pytest.approx(0.0, abs=1e-12)
    assert perfect.crossing == 0.0


def test_multistep_selection_prefers_the_iterated_model_that_one_step_cv_rejects():
    # noisy ramp z_k = d k + e_k, e ~ N(0, s^2), d = 0.8 s, m = 4. One step: persistence errs by
    # d + e' - e (variance d^2 + 2 s^2 = 2.64 s^2), the end-point trend by a slope error
    # (variance (1 + 16/9 + 1/9) s^2 = 2.89 s^2): persistence wins. Iterated j steps: persistence
    # errs by j d (RMSE over j = 1..20: sqrt(0.64 * 143.5 + 2) s = 9.7 s), the trend's recursion
    # keeps the ramp's slope up to the noise in it (7.5 s): the trend wins, and it crosses a
    # threshold on the ramp when the ramp does, which persistence never does.
    g = torch.Generator().manual_seed(0)
    s, n = 1.0, 4000
    z = 0.8 * s * torch.arange(n, dtype=torch.float64) + s * torch.randn(n, generator=g)
    cands = {"persistence": _persistence, "trend": _endpoint_trend}
    sc = {k: blocked_multistep_cv(f, z, 4, 20, 5, threshold=1600.0) for k, f in cands.items()}
    assert min(sc, key=lambda k: sc[k].one_step) == "persistence"
    assert min(sc, key=lambda k: sc[k].multi_step) == "trend"
    assert min(sc, key=lambda k: sc[k].crossing) == "trend"
    assert sc["persistence"].multi_step == pytest.approx(math.sqrt(0.64 * 143.5 + 2), rel=0.04)
    assert sc["trend"].multi_step < 0.85 * sc["persistence"].multi_step
    assert sc["trend"].crossing < 0.5 * sc["persistence"].crossing
    # the expected one-step RMSEs to a few per cent
    assert sc["persistence"].one_step == pytest.approx(math.sqrt(2.64), rel=0.04)
    assert sc["trend"].one_step == pytest.approx(math.sqrt(1 + 16 / 9 + 1 / 9), rel=0.04)


def test_blocked_multistep_one_step_equals_blocked_cv_rmse():
    g = torch.Generator().manual_seed(1)
    z = torch.randn(70, generator=g, dtype=torch.float64).cumsum(0) * 0.1
    X = torch.stack([z[i : i + 3] for i in range(67)])
    y = z[3:]

    def fit(Xt, yt):
        lr = LSSVRGram(LSSVR(kernel="rbf", sigma=0.5, C=100.0).fit(Xt, yt))
        return lambda Xh: lr(Xh)[:, 0]

    got = blocked_multistep_cv(fit, z, 3, 6, 5, threshold=0.0)
    assert got.one_step == pytest.approx(blocked_cv_rmse(fit, X, y, 5), rel=1e-12)
    assert math.isfinite(got.multi_step) and math.isfinite(got.crossing)
    assert math.isnan(blocked_multistep_cv(fit, z, 3, 6, 5).crossing)


def test_blocked_multistep_cv_rejects_bad_input():
    z = torch.zeros(20, dtype=torch.float64)
    with pytest.raises(TypeError, match="fit"):
        blocked_multistep_cv(3, z, 3, 2)
    with pytest.raises(ValueError, match=r"series must be a floating-point tensor \(n,\)"):
        blocked_multistep_cv(_persistence, z[:, None], 3, 2)
    with pytest.raises(ValueError, match="horizon"):
        blocked_multistep_cv(_persistence, z, 3, 0)
    with pytest.raises(ValueError, match="direction"):
        blocked_multistep_cv(_persistence, z, 3, 2, direction="up")
    with pytest.raises(ValueError, match="predictor returned shape"):
        blocked_multistep_cv(lambda a, b: lambda Xh: Xh, z, 3, 2)


def test_blocked_cv_rmse_refuses_missing_values():
    # a missing target gave a NaN score, which any min() over candidates mis-ranks; a
    # non-finite input scored whatever the predictor made of it
    X = torch.arange(10.0, dtype=torch.float64)[:, None].repeat(1, 2)
    y = X[:, 0].clone()
    y[3] = float("nan")
    with pytest.raises(ValueError, match=r"Y has a missing or non-finite value at row 3"):
        blocked_cv_rmse(lambda a, b: lambda Xh: Xh[:, 0], X, y, 2)
    X[7, 1] = float("inf")
    with pytest.raises(ValueError, match=r"X has a missing or non-finite value at row 7"):
        blocked_cv_rmse(lambda a, b: lambda Xh: Xh[:, 0], X, X[:, 0], 2)


def test_blocked_multistep_cv_with_as_many_folds_as_windows():
    # n = 8, m = 3: 5 windows, so at most 5 folds; the message counts windows (it said n=5
    # of a series of 8 samples)
    z = torch.tensor([0.0, 1.0, 3.0, 2.0, 5.0, 4.0, 6.0, 8.0], dtype=torch.float64)
    got = blocked_multistep_cv(_endpoint_trend, z, 3, 2, 5, threshold=4.5)
    ref = _reference(_endpoint_trend(None, None), z, 3, 2, 5, 4.5, 1)
    assert got.one_step == pytest.approx(ref[0], rel=1e-12)
    assert got.multi_step == pytest.approx(ref[1], rel=1e-12)
    assert got.crossing == pytest.approx(ref[2], rel=1e-12)
    assert (got.origins, got.crossing_origins) == (ref[3], ref[4]) == (5, 3)
    with pytest.raises(ValueError, match=r"folds must satisfy 2 <= folds <= n - m = 5 \(the "):
        blocked_multistep_cv(_endpoint_trend, z, 3, 2, 6)
