"""RUL of an IMS bearing from its own vibration rms with ``prognose``, point by point.

The known-threshold protocol of the ``ims-rul`` study
(:func:`prognos_torch.prognosis.protocol.known_threshold_protocol`): the failure threshold is
0.9 x the highest 5-point moving median of the whole record (known only in hindsight: a
maintenance planner would set it from a standard or from earlier failures), end of life its
first crossing, and predictions at 20/40/60/80/90 % of the way from the protocol's onset to end
of life. At each point ``prognose`` sees only the data up to that time: it finds its own onset,
fits its trend models and returns the RUL distribution (median, 90 % interval, censored mass)
with its warnings, counted from the prediction time (``at=``: test 1 has recording gaps, so
the last snapshot can be hours earlier). The same numbers are rows of ``prognos study
ims-rul``.

Run from the repository root (about 10 s on one core)::

    python examples/ims_rul.py                       # test 1, bearing 3; figure to docs/figures/
    python examples/ims_rul.py --test 2 --bearing 1  # another run-to-failure bearing
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from prognos_torch.datasets import load_ims_features
from prognos_torch.metrics import alpha_bounds
from prognos_torch.plots import plot_rul_trajectory
from prognos_torch.prognosis.protocol import known_threshold_protocol
from prognos_torch.workflow import load_series, prognose

#: the channel of each bearing's first accelerometer (test 1 has two per bearing)
FIRST_CHANNEL = {1: {1: 1, 2: 3, 3: 5, 4: 7}, 2: {b: b for b in range(1, 5)}}
FIRST_CHANNEL[3] = FIRST_CHANNEL[2]


def main(test: int, bearing: int, out: Path | None) -> None:
    torch.set_num_threads(1)
    feats = load_ims_features(test)
    ch = FIRST_CHANNEL[test][bearing]
    rms = feats.feature("rms")[:, ch - 1]
    series = load_series(rms, time=feats.days, name=f"test {test} bearing {bearing} rms",
                         time_unit="days")  # fmt: skip
    case = known_threshold_protocol(series.t, series.values)
    if not case.valid:
        raise SystemExit(f"no protocol on this series: {case.reason}")
    print(f"{series.name}: threshold {case.threshold:.4f} (0.9 x the highest moving median), "
          f"end of life {case.t_eol:.2f} d, protocol onset {case.t_onset:.2f} d")  # fmt: skip
    print(" t (d)  true RUL   median       90 % interval   censored  onset   warnings")
    preds, lo, hi = [], [], []
    for t_p, true in zip(case.times.tolist(), case.true_rul.tolist()):
        # the data up to t_p; the RUL counts from t_p (a recording gap can end the data earlier)
        r = prognose(series.head(int((series.t <= t_p).sum())), case.threshold, at=t_p)
        s = r.summary()
        med, q05, q95 = (float("inf") if s[k] is None else s[k] for k in ("median", "q05", "q95"))
        on = f"{r.onset.time:6.2f}" if r.onset.detected else "  none"
        print(f"{t_p:6.2f} {true:9.3f} {med:8.3f}  [{q05:7.3f}, {q95:7.3f}]  "
              f"{s['censored_mass']:8.3f}  {on}  {len(r.flags)}")  # fmt: skip
        preds.append(med), lo.append(q05), hi.append(q95)
    true, pred = case.true_rul, torch.tensor(preds, dtype=torch.float64)
    a, b = alpha_bounds(true, 0.3)
    cone = int(((pred >= a) & (pred <= b)).sum())
    covered = int(((torch.tensor(lo) <= true) & (true <= torch.tensor(hi))).sum())
    print(f"90 % interval covers the true RUL at {covered} of {len(preds)} points; the median "
          f"lies within +-30 % of it (alpha-lambda cone) at {cone} of {len(preds)}")  # fmt: skip
    if out is None:
        return
    out.mkdir(parents=True, exist_ok=True)
    panel = {"title": series.name, "times": case.times, "true": case.true_rul,
             "t_eol": case.t_eol, "methods": {"prognose": {"pred": preds, "lo": lo, "hi": hi}}}  # fmt: skip
    plot_rul_trajectory(out / "ims_prognose_rul.png", [panel], ncols=1, time_unit="days")
    print(f"figure: {out / 'ims_prognose_rul.png'} (paths of one result: plots.plot_prognosis)")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--test", type=int, default=1, choices=(1, 2, 3), help="IMS test")
    ap.add_argument("--bearing", type=int, default=3, choices=(1, 2, 3, 4), help="bearing")
    ap.add_argument("--out", type=Path, default=Path("docs/figures"), help="figure folder")
    ap.add_argument("--no-figures", action="store_true", help="print the table only")
    args = ap.parse_args()
    main(args.test, args.bearing, None if args.no_figures else args.out)
