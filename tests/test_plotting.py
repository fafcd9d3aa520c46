"""Every plot writes a non-empty PNG and returns its Figure; bad lengths raise ValueError."""

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
