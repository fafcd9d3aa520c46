"""plots.lines: a panel's own x, lines broken at recording gaps, a vertical marker."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prognos_torch.plots import LinePanel, break_at_gaps, plot_line_panels, plot_line_row


def test_break_at_gaps_inserts_nan_at_each_pause():
    t = np.array([0.0, 1.0, 2.0, 10.0, 11.0, 30.0])
    x, y = break_at_gaps(t, t * 2, gap=5.0)
    np.testing.assert_array_equal(np.isnan(x), [0, 0, 0, 1, 0, 0, 1, 0])
    np.testing.assert_array_equal(x[~np.isnan(x)], t)
    np.testing.assert_array_equal(y[~np.isnan(y)], t * 2)
    assert len(break_at_gaps(t, gap=100.0)[0]) == 6  # no gap: unchanged
    with pytest.raises(ValueError, match="ys\\[0\\]"):
        break_at_gaps(t, t[:2], gap=1.0)


def test_panels_with_own_x_gaps_and_vline(tmp_path):
    t = torch.tensor([0.0, 1.0, 2.0, 10.0, 11.0], dtype=torch.float64)
    tail = t[3:]
    panels = [
        LinePanel({"a": t**2}, truth=t, gap=5.0, vline=2.5, vline_label="EoL"),
        LinePanel({"b": tail + 1}, x=tail, hline=11.0),
    ]
    fig = plot_line_panels(tmp_path / "p.png", t, panels, ncols=2)
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    a, b = fig.axes
    truth_line, vline, series = a.get_lines()
    assert np.isnan(truth_line.get_xdata()).sum() == 1  # broken at the 2 -> 10 pause
    np.testing.assert_array_equal(series.get_ydata()[~np.isnan(series.get_ydata())], t**2)
    assert list(vline.get_xdata()) == [2.5, 2.5] and a.get_legend_handles_labels()[1][1] == "EoL"
    np.testing.assert_array_equal(b.get_lines()[-1].get_xdata(), tail.numpy())
    with pytest.raises(ValueError, match="lines\\['b'\\]"):
        plot_line_panels(tmp_path / "q.png", t, [LinePanel({"b": t}, x=tail)])


def test_line_row_one_y_scale_label_on_the_first_axes(tmp_path):
    x = np.arange(1, 5)
    panels = {"frozen": {"a": x * 1.0, "b": x * 2.0}, "online": {"a": x * 10.0, "b": x * 0.5}}
    fig = plot_line_row(tmp_path / "r.png", x, panels, ylabel="error", logy=True, style="o-")
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    a, b = fig.axes
    assert [a.get_title(), b.get_title()] == ["frozen", "online"]
    assert (a.get_ylabel(), b.get_ylabel()) == ("error", "")
    assert a.get_yscale() == b.get_yscale() == "log"
    assert a.get_ylim() == b.get_ylim()  # shared: spans 0.5 .. 40 on both
    np.testing.assert_array_equal(b.get_lines()[0].get_ydata(), x * 10.0)
    assert b.get_lines()[1].get_marker() == "o" and b.get_lines()[1].get_color() == "C1"
    assert tuple(fig.get_size_inches()) == (11.0, 4.2)
    one = plot_line_row(tmp_path / "s.png", x, {"t": {"a": x}})
    assert tuple(one.get_size_inches()) == (7.5, 4.2) and one.axes[0].get_yscale() == "linear"
