"""What float32 does to the Gaussian filters on a stiff model (a numerics check, not a timing).

    python benchmarks/bench_float32.py [--steps 10000] [--runs 4]

A 4-state linear model with time constants 1e-4 .. 1 apart (one mode with eigenvalue 1e-4),
process-noise standard deviations from 1e-7 to 1, and very accurate measurements (standard
deviations 1e-5 and 1e-6), so that every update removes almost all of the prior variance in two
directions. Each filter runs in float64 and float32 from the same float64 data; reported: the
first step at which a covariance factor is non-finite or has a non-positive diagonal (or the
Cholesky factorisation of a full-form covariance fails), and the largest deviation of the
float32 means from the float64 ones, relative to the float64 posterior standard deviation.
"""

from __future__ import annotations

import argparse

import torch

from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import ckf, ekf, run, sckf, srukf, ukf


def stiff_model(dtype):
    F = torch.diag(torch.tensor([0.9999, 0.999, 0.2, 1e-4], dtype=torch.float64))
    F[0, 1] = 0.05
    H = torch.tensor([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]], dtype=torch.float64)
    SQ = torch.diag(torch.tensor([1e-7, 1e-4, 1.0, 1e-3], dtype=torch.float64))
    SR = torch.diag(torch.tensor([1e-5, 1e-6], dtype=torch.float64))
    return linear_gaussian_model(*(a.to(dtype) for a in (F, H, SQ, SR)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=10_000)
    ap.add_argument("--runs", type=int, default=4)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    T, B = args.steps, args.runs
    g = torch.Generator().manual_seed(0)
    ys = 1e-2 * torch.randn(T, B, 2, generator=g, dtype=torch.float64)
    filters = {
        "SCKF (square root)": sckf(),
        "SRUKF (square root)": srukf(),
        "EKF (square root)": ekf(),
        "CKF (full covariance)": ckf(),
        "UKF (full covariance)": ukf(),
        "EKF (full covariance)": ekf(sqrt=False),
    }
    print(f"stiff 4-state model, {T} steps, {B} runs")
    print("| filter | float64 | float32 | float32 mean error / float64 std (max) |")
    print("|---|---|---|---|")
    for name, filt in filters.items():
        res, trs = {}, {}
        for dtype in (torch.float64, torch.float32):
            b0 = GaussianBelief(
                torch.zeros(B, 4, dtype=dtype), torch.eye(4, dtype=dtype).expand(B, 4, 4).clone()
            )
            try:
                tr = run(filt, stiff_model(dtype), b0, ys.to(dtype))
            except torch.linalg.LinAlgError as exc:
                res[dtype] = f"fails: {str(exc).split(':')[0]}"
                continue
            d = torch.diagonal(tr.chols, dim1=-2, dim2=-1)
            bad = ~(torch.isfinite(tr.chols).all(-1).all(-1) & (d > 0).all(-1))  # (T, B)
            steps = bad.any(-1).nonzero()
            res[dtype] = (
                "SPD throughout" if steps.numel() == 0 else f"fails at step {int(steps[0])}"
            )
            trs[dtype] = tr
        err = "—"
        if len(trs) == 2:
            std = trs[torch.float64].chols.square().sum(-1).sqrt()
            dev = (trs[torch.float32].means.double() - trs[torch.float64].means).abs() / std
            err = f"{float(dev[torch.isfinite(dev)].max()):.2g}"
        print(f"| {name} | {res[torch.float64]} | {res[torch.float32]} | {err} |", flush=True)


if __name__ == "__main__":
    main()
