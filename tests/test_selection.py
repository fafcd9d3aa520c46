"""learners.selection: blocked folds and blocked cross-validation against closed forms."""

from __future__ import annotations

import math

import pytest
import torch

from prognos_torch.learners import LSSVR, LSSVRGram, blocked_cv_rmse, blocked_folds


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
