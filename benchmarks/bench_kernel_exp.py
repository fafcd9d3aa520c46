"""Gaussian kernels evaluated far from their centres: the floored exp beside plain ``torch.exp``.

    python benchmarks/bench_kernel_exp.py [--windows 1259] [--batch 360] [--repeat 7]

An RBF LS-SVR (paper 002, Eq. 8 and 24; sigma = 3 x std of the series, as the multi-step
choice of the lssvr-stpf study) is fitted on ``--windows`` windows of 4 values of a random walk,
and its Gram evaluator (:class:`~prognos_torch.learners.LSSVRGram`) predicts ``--batch`` windows
(the paths of a particle filter) in three places: inside the training range, 10 sigma beyond
it, and 100 sigma beyond it (a forecast that diverged; its kernel arguments fall below -708,
where exp underflows). Beside it, in the same run and alternating with it, the same sum written
with plain ``torch.exp`` (the evaluator before :mod:`prognos_torch.core.kernel_exp`). Also
the ELM's Gaussian activation on the same three kinds of input. Reported: median times, their
ratio, and the largest difference of the outputs.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from prognos_torch.learners import ELM, LSSVRGram, fit_lssvr_gram


def _median_pair(fa, fb, repeat: int) -> tuple[float, float]:
    ta, tb = [], []
    for _ in range(repeat):  # A B A B: the machine's drift falls on both
        for f, acc in ((fa, ta), (fb, tb)):
            t0 = time.perf_counter()
            f()
            acc.append(time.perf_counter() - t0)
    return statistics.median(ta), statistics.median(tb)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--windows", type=int, default=1259)
    ap.add_argument("--batch", type=int, default=360)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--calls", type=int, default=20, help="evaluations per timed call")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    s = torch.cumsum(torch.randn(args.windows + 4, dtype=torch.float64, generator=g), 0)
    X = s.unfold(0, 4, 1)[:-1]
    y = s[4:]
    std = float(s.std())
    sigma = 3.0 * std
    gram: LSSVRGram = fit_lssvr_gram(X, y, sigma=sigma, C=1000.0)

    def plain(x):  # Eq. 8 with plain exp (the evaluator's former code), centred as it is
        x = x - gram.centre
        logk = torch.addmm(gram.sv_log_norm, x, gram.sv_scaled_t)
        c = gram.inv_two_sigma2
        return torch.exp(logk - c * (x * x).sum(-1, keepdim=True)) @ gram.alpha + gram.b

    elm = ELM(4, 200, 1, activation="gaussian", generator=torch.Generator().manual_seed(1))

    def elm_plain(x):
        z = x @ elm.a.mT + elm.b
        return torch.exp(-z * z)

    idx = torch.randint(0, X.shape[0], (args.batch,), generator=g)
    base = X[idx]
    span = float(s.max() - s.min())
    print(
        f"LS-SVR: {X.shape[0]} support vectors, sigma = 3 x std = {sigma:.3g}, "
        f"{args.batch} windows per call, {args.calls} calls per timing, median of "
        f"{args.repeat}, 1 thread"
    )
    print("| evaluator | inputs | floored exp (ms) | plain exp (ms) | plain / floored | max diff |")
    print("|---|---|---|---|---|---|")
    with torch.no_grad():
        for where, shift in (("in range", 0.0), ("10 sigma out", 10.0), ("100 sigma out", 100.0)):
            x = base + (0.0 if shift == 0 else float(s.max()) - float(base.min()) + shift * sigma)
            pairs = (
                ("LSSVRGram", lambda x=x: gram(x), lambda x=x: plain(x)),
                ("ELM gaussian", lambda x=x: elm.hidden(x / span), lambda x=x: elm_plain(x / span)),
            )
            for name, fa, fb in pairs:
                diff = float((fa() - fb()).abs().max())
                ta, tb = _median_pair(
                    lambda fa=fa: [fa() for _ in range(args.calls)],
                    lambda fb=fb: [fb() for _ in range(args.calls)],
                    args.repeat,
                )
                print(
                    f"| {name} | {where} | {1e3 * ta / args.calls:.3f} | "
                    f"{1e3 * tb / args.calls:.3f} | {tb / ta:.2f} | {diff:.1e} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
