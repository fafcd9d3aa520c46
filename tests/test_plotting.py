"""Every plot writes a non-empty PNG and returns its Figure; bad lengths raise ValueError."""

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure

from prognos_torch.plots import (
    plot_alpha_lambda,
    plot_fading_factor,
    plot_fault_probability,
    plot_fault_probability_box,
    plot_prediction,
    plot_rul_pdf,
    plot_training_curves,
)
from prognos_torch.prognosis import fault_probability, rul_distribution

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _check_png(fig, path):
    assert isinstance(fig, Figure)
    data = path.read_bytes()
    assert len(data) > 1000 and data[:8] == PNG_MAGIC


@pytest.fixture
def paths():
    g = torch.Generator().manual_seed(0)
    return torch.randn(6, 50, 12, generator=g, dtype=torch.float64).cumsum(-1)


def test_plot_prediction(tmp_path):
    t = torch.arange(20.0)
    truth = torch.sin(t / 3)
    mean = truth + 0.1
    fig = plot_prediction(tmp_path / "a" / "pred.png", t, truth, mean, 0.2 * torch.ones(20))
    _check_png(fig, tmp_path / "a" / "pred.png")
    fig = plot_prediction(tmp_path / "band.png", t, truth, mean, lower=mean - 1, upper=mean + 1)
    _check_png(fig, tmp_path / "band.png")
    with pytest.raises(ValueError, match="mean"):
        plot_prediction(tmp_path / "bad.png", t, truth, mean[:5])


def test_plot_fading_factor(tmp_path):
    t = torch.arange(30.0)
    lam = {"STSCKF": 1 + torch.rand(30), "SCKF": torch.ones(30)}
    _check_png(plot_fading_factor(tmp_path / "fade.png", t, lam), tmp_path / "fade.png")


def test_plot_rul_pdf(tmp_path, paths):
    d = rul_distribution(paths, 3.0, dt=0.5)
    times = torch.arange(6.0)
    fig = plot_rul_pdf(
        tmp_path / "pdf.png",
        times,
        d.support,
        d.pmf,
        true_rul=torch.full((6,), 3.0),
        censored_mass=d.censored_mass,
    )
    _check_png(fig, tmp_path / "pdf.png")
    with pytest.raises(ValueError, match="pmf"):
        plot_rul_pdf(tmp_path / "bad.png", times[:3], d.support, d.pmf)


def test_plot_alpha_lambda(tmp_path):
    t = torch.tensor([0.0, 10.0, 20.0, 30.0, 40.0])
    r_true = 50 - t
    r_pred = torch.tensor([60.0, 44.0, 36.0, 21.0, 10.5])
    fig = plot_alpha_lambda(
        tmp_path / "al.png",
        t,
        r_true,
        r_pred,
        alpha=0.3,
        lower=r_pred - 3,
        upper=r_pred + 4,
        lam=0.5,
    )
    _check_png(fig, tmp_path / "al.png")


def test_plot_fault_probability_and_box(tmp_path, paths):
    p = fault_probability(paths[0], 2.0)
    steps = torch.arange(1.0, 13.0)
    fig = plot_fault_probability(tmp_path / "fp.png", steps, {"PF": p, "STPF": p.sqrt()})
    _check_png(fig, tmp_path / "fp.png")
    days = torch.linspace(0.0, 11.9, 120)
    prob = torch.rand(120, generator=torch.Generator().manual_seed(1))
    fig = plot_fault_probability_box(tmp_path / "box.png", days, prob, period=1.0)
    _check_png(fig, tmp_path / "box.png")
    with pytest.raises(ValueError, match="period"):
        plot_fault_probability_box(tmp_path / "bad.png", days, prob, period=0.0)


def test_plot_training_curves(tmp_path):
    curves = {"Adam": [1.0, 0.5, 0.2, 0.1], "EKF": torch.tensor([1.0, 0.1, 0.05, 0.04])}
    fig = plot_training_curves(tmp_path / "train.png", curves)
    _check_png(fig, tmp_path / "train.png")


# ----------------------------------------------------------------- shared study figure helpers
def test_line_panels_and_prediction_errors(tmp_path):
    from prognos_torch.plots import LinePanel, plot_line_panels, plot_prediction_errors

    t = torch.arange(30.0, dtype=torch.float64)
    truth = torch.sin(t / 5)
    preds = {"A": truth + 0.1, "B": truth - 0.01 * t}
    fig = plot_prediction_errors(
        tmp_path / "pe.png", t, truth, preds, title="x", ylabel="y", threshold=0.5, alternate=True
    )
    _check_png(fig, tmp_path / "pe.png")
    a, b = fig.axes
    # (b) draws |prediction - truth| of each method, in order
    for line, p in zip(b.get_lines(), preds.values()):
        np.testing.assert_allclose(line.get_ydata(), (p - truth).abs().numpy(), rtol=0, atol=0)
    assert b.get_yscale() == "log" and a.get_lines()[1].get_ydata()[0] == 0.5  # threshold
    panels = [LinePanel({"u": t}, title="p1", logy=True), LinePanel({"v": -t}, style=".-")]
    fig = plot_line_panels(tmp_path / "lp.png", t, panels, ncols=2, sharey=False, title="T")
    _check_png(fig, tmp_path / "lp.png")
    with pytest.raises(ValueError, match="lines\\['v'\\]"):
        plot_line_panels(tmp_path / "bad.png", t, [LinePanel({"v": t[:3]})])


def test_heatmaps(tmp_path):
    from prognos_torch.plots import HeatmapPanel, plot_heatmaps

    v = np.array([[0.1, np.nan], [0.3, 0.4]])
    p = HeatmapPanel(v, ["r1", "r2"], ["c1", "c2"], title="h", colorbar="RMSE", clim=(0, 1))
    fig = plot_heatmaps(tmp_path / "h.png", [p, HeatmapPanel(v, ["a", "b"], ["x", "y"])])
    _check_png(fig, tmp_path / "h.png")
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert texts == ["0.1", "", "0.3", "0.4"]  # default labels; NaN cell grey, no text
    with pytest.raises(ValueError, match="shape \\(3, 2\\)"):
        plot_heatmaps(tmp_path / "bad.png", [HeatmapPanel(v, ["a", "b", "c"], ["x", "y"])])


def test_rul_band_paths_and_weighted_quantiles(tmp_path):
    from prognos_torch.plots import plot_paths, plot_rul_band, weighted_quantiles

    g = torch.Generator().manual_seed(1)
    times = torch.arange(5.0)
    true = 10.0 - times
    pred = true[:, None] + torch.randn(5, 7, generator=g, dtype=torch.float64)
    pred[0] = float("nan")  # every run censored at the first time
    fig = plot_rul_band(tmp_path / "r.png", times, true, {"STSCKF": pred}, alpha=0.3)
    _check_png(fig, tmp_path / "r.png")
    med = fig.axes[0].get_lines()[1].get_ydata()
    assert np.isnan(med[0])
    np.testing.assert_allclose(med[1:], pred[1:].median(1).values.numpy(), rtol=0, atol=0)
    paths = torch.randn(40, 12, generator=g, dtype=torch.float64).cumsum(-1)
    _check_png(
        plot_paths(
            tmp_path / "p.png",
            torch.arange(12.0),
            paths,
            threshold=2.0,
            history=(t := torch.arange(-5.0, 0.0), t),
        ),
        tmp_path / "p.png",
    )
    # equal weights: the weighted quantile is the order statistic at ceil(q N)
    x = np.random.default_rng(0).normal(size=(40, 3))
    q = weighted_quantiles(x, np.full(40, 1 / 40), (0.05, 0.5, 0.95))
    s = np.sort(x, axis=0)
    np.testing.assert_array_equal(q, s[[1, 19, 37]])
    with pytest.raises(ValueError, match="predictions\\['A'\\]"):
        plot_rul_band(tmp_path / "bad.png", times, true, {"A": pred[:3]})


def test_figures_reach_their_file_whole_or_not_at_all(tmp_path, monkeypatch):
    # one writer for every figure: a failure while rendering leaves the old file as it was and
    # no temporary file behind; study figures create their folder, user-facing ones name it
    from prognos_torch.plots._arrays import write_png

    t = torch.arange(20.0)
    target = tmp_path / "pred.png"
    target.write_bytes(b"old")

    def broken(self, fname, *a, **k):  # a renderer that dies half-way through the PNG
        if hasattr(fname, "write"):
            fname.write(b"\x89PNG half")
        else:
            with open(fname, "wb") as f:
                f.write(b"\x89PNG half")
        raise RuntimeError("renderer failed")

    monkeypatch.setattr(Figure, "savefig", broken)
    with pytest.raises(RuntimeError, match="renderer failed"):
        plot_prediction(target, t, t, t + 0.1)
    assert target.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == [
        "pred.png"
    ]
    monkeypatch.undo()
    fig = Figure()
    with pytest.raises(FileNotFoundError, match="output folder does not exist"):
        write_png(fig, tmp_path / "missing" / "f.png")
    write_png(fig, tmp_path / "made" / "f.png", make_folder=True)
    _check_png(fig, tmp_path / "made" / "f.png")


def test_rul_trajectory_draws_the_cone_the_truth_and_names_the_unit(tmp_path):
    from prognos_torch.plots import plot_rul_trajectory

    t = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    panel = {"title": "b3", "times": t, "true": 4.0 - t, "t_eol": 4.0,
             "methods": {"m": {"pred": [2.5, float("inf"), 1.1], "lo": [2.0, 1.0, 0.5],
                               "hi": [3.0, float("inf"), 2.0]}}}  # fmt: skip
    fig = plot_rul_trajectory(tmp_path / "r.png", [panel], ncols=1, time_unit="days")
    ax = fig.axes[0]
    assert ax.get_xlabel() == "prediction time (days)" and ax.get_ylabel() == "RUL (days)"
    # the truth is t_eol - t; an infinite prediction is drawn at the top edge (2.2 x max truth)
    true_line = [ln for ln in ax.get_lines() if ln.get_label() == "true RUL"][0]
    x, y = true_line.get_data()
    np.testing.assert_allclose(y, 4.0 - x)
    pred = [ln for ln in ax.get_lines() if ln.get_label() == "m"][0].get_ydata()
    np.testing.assert_allclose(pred, [2.5, 2.2 * 3.0, 1.1])
    assert (tmp_path / "r.png").read_bytes()[:4] == b"\x89PNG"
    assert plot_rul_trajectory(None, [panel]).axes[0].get_ylabel() == "RUL"


def test_a_dated_axis_beyond_the_year_9999_counts_days():
    # matplotlib's dates end at the year 9999: a horizon of millennia on a dated series drew
    # nothing but a ValueError; it keeps round day counts since the first date-time instead
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from prognos_torch.plots import time_axis
    from prognos_torch.workflow import load_series

    start = np.datetime64("2004-02-12T10:32:39")
    s = load_series(np.arange(10.0), time=start + np.arange(10).astype("timedelta64[D]"))
    for span, dated in ((3.0, True), (1e3, True), (1e7, False)):
        fig = Figure()
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
        ax.plot([0.0, span], [0.0, 1.0])
        time_axis(ax, s)
        fig.canvas.draw()
        labels = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
        offset = ax.xaxis.get_offset_text().get_text()
        if dated:
            assert not any(x.replace("−", "-").lstrip("-").replace(".", "").isdigit()
                           and len(x) > 4 for x in labels)  # fmt: skip
            assert offset != "days since 2004-02-12T10:32:39"
        else:
            assert offset == "days since 2004-02-12T10:32:39"
            values = [float(x.replace("−", "-")) for x in labels]
            assert values == [float(f"{v:g}") for v in ax.get_xticks()][: len(values)]
