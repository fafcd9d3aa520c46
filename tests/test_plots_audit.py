"""Audit of prognos_torch.plots as a user calls it: tensors (float32/float64), NumPy arrays and
lists; bands from square-root covariances read back from the axes; the alpha cones against
their definition; NaN (missing) values, empty inputs, mismatched lengths named by argument; a
figure reaches its file whole or not at all (and leaves no folder behind when it fails)."""

import math
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from prognos_torch import plots  # noqa: E402
from prognos_torch.plots._arrays import write_png  # noqa: E402


@pytest.fixture(autouse=True)
def _no_figure_left_open():
    yield
    plt.close("all")  # the plots use no pyplot state; nothing may be left open either way
    assert plt.get_fignums() == []


def _band(ax, n, k=0):
    """(x, lower, upper) of the ``k``-th fill_between band of ``ax``, of ``n`` points: its path
    runs (x0, upper0), the lower edge forward, (x_{n-1}, upper_{n-1}), the upper edge back."""
    coll = [c for c in ax.collections if type(c).__name__.endswith("PolyCollection")][k]
    (path,) = coll.get_paths()
    v = path.vertices
    lo, hi = v[1 : n + 1], v[n + 2 : 2 * n + 2][::-1]
    np.testing.assert_array_equal(lo[:, 0], hi[:, 0])
    return lo[:, 0], lo[:, 1], hi[:, 1]


def _close(fig):
    fig.clear()


# ----------------------------------------------------------------------- bands and the cones
@pytest.mark.parametrize("kind", ["f64", "f32", "numpy", "list"])
def test_band_of_a_batched_square_root_belief_is_mean_pm_z_sqrt_diag_SST(tmp_path, kind):
    # beliefs (T, n) with square-root covariances (T, n, n): the std of component j is
    # sqrt(diag(S S^T))_j, the row norm of S; the drawn edges are mean -+ z std, read back
    g = torch.Generator().manual_seed(3)
    T, n, j, z = 9, 3, 1, 1.959963984540054
    mean = torch.randn(T, n, generator=g, dtype=torch.float64)
    S = torch.randn(T, n, n, generator=g, dtype=torch.float64).tril()
    std = torch.diagonal(S @ S.mT, dim1=-2, dim2=-1).sqrt()
    t = torch.arange(T, dtype=torch.float64)
    conv = {
        "f64": lambda x: x,
        "f32": lambda x: x.float(),
        "numpy": lambda x: x.numpy(),
        "list": lambda x: x.tolist(),
    }[kind]
    m, s = conv(mean[:, j]), conv(std[:, j])
    fig = plots.plot_prediction(None, conv(t), m, m, s, n_std=np.float32(z))
    x, lo, hi = _band(fig.axes[0], T)
    m64 = torch.as_tensor(np.asarray(m, dtype=np.float64)).numpy()  # float32 read exactly
    s64 = np.asarray(torch.as_tensor(np.asarray(s)).double())
    zf = float(np.float32(z))
    np.testing.assert_array_equal(x, t.numpy())
    np.testing.assert_array_equal(lo, m64 - zf * s64)
    np.testing.assert_array_equal(hi, m64 + zf * s64)
    # the closed form itself: row norms of S
    np.testing.assert_allclose(std[:, j], S[:, j, :].norm(dim=-1), rtol=1e-12, atol=0)
    _close(fig)


def test_std_must_be_non_negative_and_n_std_a_number(tmp_path):
    t = np.arange(5.0)
    with pytest.raises(ValueError, match=r"std must be >= 0 \(NaN: missing\), got -1"):
        plots.plot_prediction(tmp_path / "a.png", t, t, t, np.array([1, 1, -1, np.nan, 1.0]))
    with pytest.raises(ValueError, match="n_std must be a finite number >= 0, got -2"):
        plots.plot_prediction(tmp_path / "a.png", t, t, t, np.ones(5), n_std=-2.0)
    assert not (tmp_path / "a.png").exists()
    # NaN std (missing) leaves a gap; the rest of the band is mean +- 2 std
    fig = plots.plot_prediction(tmp_path / "a.png", t, t, t, np.array([1, 1, np.nan, 1, 1.0]))
    verts = np.concatenate([p.vertices for p in fig.axes[0].collections[0].get_paths()])
    assert np.isin(verts[:, 1], np.r_[t - 2, t + 2]).all() and 2.0 not in verts[:, 0]
    _close(fig)


# Saxena et al. 2010: the cone [(1 - a-) r*, (1 + a+) r*] around the true RUL r*
_T = np.array([0.0, 2.0, 5.0, 7.0])


def test_rul_band_cone_follows_its_definition():
    t, r = _T, 10.0 - _T
    pred = np.stack([r + 1, r - 1], 1)
    fig = plots.plot_rul_band(None, t, r, {"A": pred}, alpha=(0.2, 0.4))
    x, lo, hi = _band(fig.axes[0], 4)
    np.testing.assert_array_equal(x, t)
    np.testing.assert_allclose(lo, 0.8 * r, rtol=1e-15, atol=0)
    np.testing.assert_allclose(hi, 1.4 * r, rtol=1e-15, atol=0)
    _close(fig)


def test_alpha_lambda_cone_follows_its_definition():
    t, r = _T, 10.0 - _T
    fig = plots.plot_alpha_lambda(None, t, r, r, alpha=0.3)
    x, lo, hi = _band(fig.axes[0], 200)
    assert x[0] == 0.0 and x[-1] == 10.0  # from the first prediction time to t_eol = 7 + 3
    np.testing.assert_allclose(lo, 0.7 * (10.0 - x), rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(hi, 1.3 * (10.0 - x), rtol=1e-14, atol=1e-14)
    _close(fig)


def test_rul_trajectory_cone_follows_its_definition():
    t, r = _T, 10.0 - _T
    panel = {"title": "s", "times": torch.tensor(t), "true": r.tolist(), "t_eol": 10.0,
             "methods": {"m": {"pred": r}}}  # fmt: skip
    fig = plots.plot_rul_trajectory(None, [panel], alpha=np.float32(0.25), ncols=np.int64(1))
    x, lo, hi = _band(fig.axes[0], 50)
    assert x[-1] == 10.0 and math.isclose(x[0], -0.5)  # from 5 % of the span before t[0]
    a = float(np.float32(0.25))
    np.testing.assert_allclose(lo, (1 - a) * (10.0 - x), rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(hi, (1 + a) * (10.0 - x), rtol=1e-14, atol=1e-14)
    _close(fig)


# ------------------------------------------------------------------------ mismatched lengths
def test_rul_trajectory_checks_lengths_pairs_alpha_and_ncols():
    t = [1.0, 2.0, 3.0]

    def panel(**m):
        return {"title": "b", "times": t, "true": [3.0, 2.0, 1.0], "t_eol": 4.0,
                "methods": {"m": {"pred": [2.5, 2.0, 1.0], **m}}}  # fmt: skip

    bad = panel(pred=[2.5, 2.0])  # was matplotlib's 'x and y must have same first dimension'
    with pytest.raises(ValueError, match=r"panels\[0\]\['methods'\]\['m'\]\['pred'\] must have"):
        plots.plot_rul_trajectory(None, [bad])
    with pytest.raises(ValueError, match=r"\['lo'\] must have shape \(3,\) like the times, got"):
        plots.plot_rul_trajectory(None, [panel(lo=[2.0], hi=[3.0])])  # was broadcast silently
    with pytest.raises(ValueError, match="give both 'lo' and 'hi' or neither"):
        plots.plot_rul_trajectory(None, [panel(lo=[2.0, 1.0, 0.5])])  # was KeyError 'hi'
    with pytest.raises(ValueError, match="give both 'lo' and 'hi' or neither"):
        plots.plot_rul_trajectory(None, [panel(lo=[2.0, 1.0, 0.5], hi=None)])  # was NaN -> top
    short = {**panel(), "true": [3.0, 2.0]}
    with pytest.raises(ValueError, match=r"panels\[0\]\['true'\] must have shape \(3,\)"):
        plots.plot_rul_trajectory(None, [short])
    with pytest.raises(ValueError, match="alpha must be a finite number >= 0, got -0.3"):
        plots.plot_rul_trajectory(None, [panel()], alpha=-0.3)  # drew the +0.3 cone
    with pytest.raises(ValueError, match="ncols must be a positive int, got 0"):
        plots.plot_rul_trajectory(None, [panel()], ncols=0)  # was ZeroDivisionError
    with pytest.raises(ValueError, match=r"panels\[0\]\['times'\] must be finite"):
        plots.plot_rul_trajectory(None, [{**panel(), "times": [], "true": []}])


def test_rul_trajectory_reads_a_nan_true_rul_as_missing():
    # a missing true RUL made the y limit NaN ('Axis limits cannot be NaN or Inf')
    panel = {"title": "b", "times": [1.0, 2.0, 3.0], "true": [3.0, np.nan, 1.0], "t_eol": 4.0,
             "methods": {"m": {"pred": [2.5, np.inf, 1.0]}}}  # fmt: skip
    fig = plots.plot_rul_trajectory(None, [panel])
    ax = fig.axes[0]
    assert ax.get_ylim() == (0.0, 2.2 * 3.0 * 1.02)
    pred = [ln for ln in ax.get_lines() if ln.get_label() == "m"][0].get_ydata()
    np.testing.assert_array_equal(pred, [2.5, 2.2 * 3.0, 1.0])
    _close(fig)


def test_prediction_errors_name_a_prediction_of_another_length(tmp_path):
    t = np.arange(20.0)
    with pytest.raises(ValueError, match=r"predictions\['A'\] must have length 20 \(like t\)"):
        # was NumPy's 'operands could not be broadcast together with shapes (5,) (20,)'
        plots.plot_prediction_errors(
            tmp_path / "e.png", t, np.zeros(20), {"A": np.zeros(5)}, title="x", ylabel="y"
        )
    with pytest.raises(ValueError, match=r"truth must have length 20 \(like t\)"):
        plots.plot_prediction_errors(
            tmp_path / "e.png", t, np.zeros(7), {"A": np.zeros(7)}, title="x", ylabel="y"
        )
    assert not (tmp_path / "e.png").exists()


def test_a_mapping_entry_of_another_length_is_named(tmp_path):
    t = np.arange(5.0)
    with pytest.raises(ValueError, match=r"lam\['B'\] must have length 5 \(like t\), got"):
        plots.plot_fading_factor(tmp_path / "f.png", t, {"A": t, "B": t[:3]})
    with pytest.raises(ValueError, match=r"prob\['B'\] must have length 5"):
        plots.plot_fault_probability(tmp_path / "f.png", t, {"A": t / 5, "B": [0.1]})


def test_plot_values_refuse_complex_and_none_by_name(tmp_path):
    t = np.arange(5.0)
    with pytest.raises(TypeError, match="mean must be real, got complex values"):
        plots.plot_prediction(tmp_path / "c.png", t, t, t + 1j)  # imaginary part was dropped
    with pytest.raises(TypeError, match="truth must be real, got a complex tensor"):
        plots.plot_prediction(tmp_path / "c.png", t, torch.ones(5, dtype=torch.complex64), t)
    with pytest.raises(ValueError, match="std must be an array of real numbers"):
        plots.plot_prediction(tmp_path / "c.png", t, t, t, ["a"] * 5)
    with pytest.raises(TypeError, match="values must be an array or tensor of real numbers"):
        plots.plot_heatmaps(tmp_path / "c.png", [plots.HeatmapPanel(None, ["r"], ["c"])])
    assert not (tmp_path / "c.png").exists()


# ------------------------------------------------------------------------- weighted quantiles
def _brute_quantile(x, w, q):
    """The smallest sample whose cumulative (normalised) weight reaches q, by enumeration."""
    w = np.asarray(w, dtype=np.float64) / np.sum(w)
    best = None
    for v in x:
        if w[x <= v].sum() >= q - 1e-12 and (best is None or v < best):
            best = v
    return best


def test_weighted_quantiles_of_unnormalised_weights(tmp_path):
    # weights that do not sum to 1 (e.g. all ones) gave the smallest sample for every quantile
    x = np.random.default_rng(4).normal(size=(11, 2))
    w = np.arange(1.0, 12.0)
    got = plots.weighted_quantiles(x, w, (0.05, 0.5, 0.95))
    for c in range(2):
        ref = [_brute_quantile(x[:, c], w, q) for q in (0.05, 0.5, 0.95)]
        np.testing.assert_array_equal(got[:, c], ref)
    np.testing.assert_array_equal(got, plots.weighted_quantiles(x, w / w.sum(), (0.05, 0.5, 0.95)))
    # the band of plot_paths with weights of ones is the equal-weight order statistics
    paths = np.arange(40.0).reshape(20, 2)[::-1].copy()
    fig = plots.plot_paths(None, [0.0, 1.0], paths, np.ones(20))
    x_, lo, hi = _band(fig.axes[0], 2)
    s = np.sort(paths, 0)
    np.testing.assert_array_equal(lo, s[0])  # ceil(0.05 * 20) = 1st
    np.testing.assert_array_equal(hi, s[18])  # ceil(0.95 * 20) = 19th
    _close(fig)
    with pytest.raises(ValueError, match="weights must be finite, >= 0 and not all 0"):
        plots.weighted_quantiles(x, -w, (0.5,))
    with pytest.raises(ValueError, match=r"weights must have shape \(11,\), got \(3,\)"):
        plots.weighted_quantiles(x, w[:3], (0.5,))


# ---------------------------------------------------------------------------- empty inputs
def test_empty_inputs_get_a_named_error_or_draw(tmp_path):
    with pytest.raises(ValueError, match=r"paths must have shape \(N, 5\) with N >= 1"):
        plots.plot_paths(tmp_path / "e.png", np.arange(5.0), np.zeros((0, 5)))  # ZeroDivision
    with pytest.raises(ValueError, match="n_show must be an int >= 0, got -3"):
        plots.plot_paths(tmp_path / "e.png", np.arange(5.0), np.zeros((4, 5)), n_show=-3)
    with pytest.raises(ValueError, match="times must hold at least one prediction time"):
        plots.plot_alpha_lambda(tmp_path / "e.png", [], [], [], alpha=0.2)  # was IndexError
    with pytest.raises(ValueError, match="t and prob must hold at least one pair"):
        plots.plot_fault_probability_box(tmp_path / "e.png", [], [])
    with pytest.raises(ValueError, match=r"series must have at least one component"):
        plots.plot_panels(tmp_path / "e.png", np.arange(5.0), {"a": np.zeros((5, 0))})
    assert not (tmp_path / "e.png").exists()
    # an empty pmf support with censored mass: the note sits at 0 (was IndexError)
    fig = plots.plot_rul_pdf(None, [1.0, 2.0], [], np.zeros((2, 0)),
                             censored_mass=np.ones(2))  # fmt: skip
    assert [tx.get_position()[0] for tx in fig.axes[0].texts] == [0.0, 0.0]
    _close(fig)


# ----------------------------------------------------------------------- NaN means missing
def test_fault_probability_box_leaves_missing_values_out(tmp_path):
    # a NaN time was cast to int64 (-9.2e18): a bogus box; a NaN probability hid its period
    t = np.array([0.1, 0.5, np.nan, 1.2, 1.7, 1.9])
    p = np.array([0.1, 0.3, 0.9, 0.2, np.nan, 0.6])
    fig = plots.plot_fault_probability_box(None, t, p)
    ax = fig.axes[0]
    assert [x.get_text() for x in ax.get_xticklabels()] == ["0", "1"]
    medians = [ln.get_ydata()[0] for ln in ax.get_lines() if ln.get_color() in ("C1", "#ff7f0e")]
    np.testing.assert_allclose(medians, [0.2, 0.4], rtol=0, atol=1e-15)
    _close(fig)


def test_panels_clip_with_a_truth_missing_throughout_and_t_must_be_1d(tmp_path):
    t = np.arange(5.0)
    truth = np.c_[np.arange(5.0), np.full(5, np.nan)]
    fig = plots.plot_panels(None, t, {"a": truth + 1.0}, truth=truth, clip=0.5)
    assert fig.axes[0].get_ylim() == (-2.0, 6.0)  # truth range [0, 4] widened by 0.5 x 4
    _close(fig)
    with pytest.raises(ValueError, match=r"t must have shape \(T,\), got \(5, 1\)"):
        plots.plot_panels(tmp_path / "p.png", t[:, None], {"a": np.zeros(5)})


def test_rul_band_checks_its_percentiles_and_names_the_shape(tmp_path):
    t = np.arange(5.0)
    with pytest.raises(ValueError, match="band must be a pair of percentiles"):
        plots.plot_rul_band(tmp_path / "r.png", t, 5 - t, {"A": np.ones((5, 3))}, band=(10.0,))
    with pytest.raises(ValueError, match="band must be a pair of percentiles"):
        plots.plot_rul_band(tmp_path / "r.png", t, 5 - t, {"A": np.ones((5, 3))}, band=(90, 10))
    with pytest.raises(ValueError, match=r"must have shape \(5, R\), got \(3, 2\)"):
        plots.plot_rul_band(tmp_path / "r.png", t, 5 - t, {"A": np.ones((3, 2))})


# ------------------------------------------------------------ workflow and prognose figures
def test_history_zero_or_negative_is_refused_not_the_whole_series(tmp_path):
    # values[-0:] is the whole series and values[-n:] for n < 0 dropped the first |n| values
    fake = SimpleNamespace(lower=None, distribution=None, history=None, onset=None)
    for bad in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match="history must be None or a positive int"):
            plots.plot_forecast(tmp_path / "f.png", fake, history=bad)
        with pytest.raises(ValueError, match="history must be None or a positive int"):
            plots.plot_rul(tmp_path / "f.png", fake, history=bad)
    assert not (tmp_path / "f.png").exists()


def test_prognosis_truth_of_two_lengths_and_a_negative_n_paths_are_named(tmp_path):
    fake = SimpleNamespace(distribution=None, history=None)
    with pytest.raises(ValueError, match=r"truth must be a pair \(t, y\) of \(T,\) values, got"):
        # was an IndexError of a boolean index
        plots.plot_prognosis(tmp_path / "p.png", fake, truth=(np.arange(5.0), np.ones(3)))
    with pytest.raises(ValueError, match="n_paths must be an int >= 0, got -1"):
        plots.plot_prognosis(tmp_path / "p.png", fake, n_paths=-1)
    assert not (tmp_path / "p.png").exists()


# --------------------------------------------------------------------------- writing a file
def test_a_failed_render_leaves_no_file_and_no_folder(tmp_path, monkeypatch):
    def broken(self, fname, *a, **k):
        raise RuntimeError("renderer failed")

    monkeypatch.setattr(Figure, "savefig", broken)
    with pytest.raises(RuntimeError, match="renderer failed"):
        plots.plot_fading_factor(tmp_path / "new" / "sub" / "f.png", [0.0, 1.0], [1.0, 1.2])
    assert list(tmp_path.iterdir()) == []  # the folder was created before the render failed
    monkeypatch.undo()
    fig = plots.plot_fading_factor(tmp_path / "new" / "sub" / "f.png", [0.0, 1.0], [1.0, 1.2])
    assert (tmp_path / "new" / "sub" / "f.png").read_bytes()[:4] == b"\x89PNG"
    assert sorted(p.name for p in (tmp_path / "new" / "sub").iterdir()) == ["f.png"]
    _close(fig)
    with pytest.raises(ValueError, match="'f.jpeg' has the suffix '.jpeg'"):
        write_png(Figure(), tmp_path / "other" / "f.jpeg", make_folder=True)
    assert not (tmp_path / "other").exists()
