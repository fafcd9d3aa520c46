"""IMS bearing 3 (NASA IMS test 1): forecast and RUL of paper 002's health indicator.

The recipe of paper 002: time-domain features of the last 12 days, locally linear embedding to
a one-dimensional health indicator (:func:`prognos_torch.datasets.health_indicator`), an LS-SVR
of order m = 4 trained on channel 5 and tested on channel 6 (the other accelerometer of the same
bearing), the strong-tracking particle filter (STPF) for the RUL. Here the prediction starts at
day 10 of the window; the forecast covers the next 12 hours (72 snapshots) and the RUL is the
time until the indicator reaches 3.0.

Run from the repository root (about a minute on one core)::

    python examples/ims_bearing.py            # figures to docs/figures/
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from prognos_torch.datasets import health_indicator
from prognos_torch.workflow import fit_series, forecast, load_series, plot_forecast, plot_rul, rul

ORIGIN_DAY, HORIZON, THRESHOLD = 10.0, 72, 3.0


def main(out: Path) -> None:
    torch.set_num_threads(1)
    hi = health_indicator()  # bearing 3, channels 5 (train) and 6 (test), last 12 days
    days = hi.elapsed
    train = load_series(hi.train, time=days, name="HI channel 5", time_unit="days")
    test = load_series(hi.test, time=days, name="HI channel 6", time_unit="days")

    # paper 002: LS-SVR (closed-form KKT solve), fourth order; scores on channel 5's last 10 %
    held = fit_series(train, "lssvr", m=4, holdout=0.1)
    mt = held.metrics
    print(
        f"channel 5, held-out tail of {mt['horizon']} steps: forecast RMSE {mt['rmse']:.3f}, "
        f"one-step RMSE {mt['one_step_rmse']:.3f}, persistence RMSE "
        f"{mt['persistence_rmse']:.3f}, 95 % band coverage {mt['coverage']:.2f}"
    )
    model = fit_series(train, "lssvr", m=4, holdout=0)  # all of channel 5, as in the paper

    # forecast channel 6 from day 10 and compare with what followed
    n0 = int((days <= ORIGIN_DAY).sum())
    origin = test.head(n0)
    fc = forecast(model, origin, HORIZON)
    actual = test.values[n0 : n0 + HORIZON]
    rmse = float((fc.mean - actual).square().mean().sqrt())
    persistence = float((origin.values[-1] - actual).square().mean().sqrt())
    inside = float(((actual >= fc.lower) & (actual <= fc.upper)).double().mean())
    print(
        f"channel 6 from day {float(origin.t[-1]):.2f}, {HORIZON} steps: forecast RMSE {rmse:.3f}, "
        f"persistence RMSE {persistence:.3f}, 95 % band coverage {inside:.2f}"
    )
    plot_forecast(
        out / "ims_forecast.png",
        fc,
        truth=test,
        title="IMS bearing 3, channel 6: LS-SVR forecast from day 10",
    )

    r = rul(model, origin, THRESHOLD, horizon=300, filter="stpf", n_particles=300, seed=0)
    s = {
        k: "beyond the horizon" if v is None else f"{v:.2f} d"
        for k, v in r.summary().items()
        if k in ("mean", "median", "q05", "q95")
    }
    hit = int(torch.nonzero(test.values[n0:] >= THRESHOLD)[0]) + 1  # snapshots until crossing
    print(
        f"RUL at day {r.t_last:.2f} for threshold {THRESHOLD}: P(reached within "
        f"{r.bound:.2f} d) = {r.crossing_probability:.2f}, median {s['median']}, "
        f"5 % quantile {s['q05']}, 95 % quantile {s['q95']}; observed: {hit} snapshots later "
        f"({hit * r.dt:.2f} d at the median spacing, "
        f"{float(test.t[n0 + hit - 1] - r.t_last):.2f} d of calendar time)"
    )
    plot_rul(out / "ims_rul.png", r, title="IMS bearing 3, channel 6: RUL at day 10 (STPF)")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("docs/figures"), help="figure folder")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    main(args.out)
