"""studies.training_report: the figures of an optimiser comparison, from hand-made results."""

from __future__ import annotations

import numpy as np
import torch

from prognos_torch.studies import TrainTest
from prognos_torch.studies import training_report as tr

F64 = torch.float64


def _result(R, N, online):
    g = torch.Generator().manual_seed(R + N)
    pred = torch.rand(R, N, generator=g, dtype=F64)
    return TrainTest(pred, pred[:, :3], 0.1, 0.01, torch.rand(4, R, generator=g, dtype=F64),
                     [5, 10, 15, 20], pred + 0.01 if online else None)  # fmt: skip


def test_training_figures_write_four_files_and_keep_common_readings(tmp_path, monkeypatch):
    R, N = 3, 12
    res = {"EKF": _result(R, N, True), "Adam": _result(R, N, False)}
    truth = torch.linspace(0, 1, N, dtype=F64)
    seen = {}
    real = tr.plots.plot_panels

    def spy(path, x, panels, **kw):
        seen["panels"], seen["names"] = list(panels), kw["names"]
        return real(path, x, panels, **kw)

    monkeypatch.setattr(tr.plots, "plot_panels", spy)
    files = ["a.png", "b.png", "c.png", "d.png"]
    readings = {"frozen": "pred", "online": "online_pred"}
    out = tr.training_figures(tmp_path, res, np.arange(N), truth, name="toy", block=5,
                              files=files, readings=readings)  # fmt: skip
    assert out == files and all((tmp_path / f).stat().st_size > 0 for f in files)
    # Adam has no online reading, so only the frozen one is drawn, for both optimisers
    assert seen["panels"] == ["frozen, run 0"] and seen["names"] == ["EKF", "Adam"]
    res["Adam"] = _result(R, N, True)
    tr.training_figures(tmp_path, res, np.arange(N), truth, name="toy", block=5, files=files,
                        readings=readings)  # fmt: skip
    assert seen["panels"] == ["frozen, run 0", "online, run 0"]
