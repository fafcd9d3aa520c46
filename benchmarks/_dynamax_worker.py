"""dynamax side of ``bench_peers.py``; runs in the benchmark's own virtual environment.

Reads the problem from an ``.npz`` file (``Xtr (N, 3)``, ``Ytr (N,)``, ``Xte``, ``Yte``,
``theta0 (R, 44)``, ``P0 (44, 44)``, ``Q (44, 44)``, ``R (1, 1)``), then answers one JSON
request per line on stdin (``{"filter": "ekf" | "ukf", "runs": 1 | R}``) with one JSON line:
the filter pass time (compiled function, result blocked on), the compile time of its first
call, the test MAE of every run and the final parameters.

The ANFIS here is written from paper 003 Eq. 1-5 (3 inputs, 2 sigmoid MFs, 8 grid rules,
parameters in the order of Eq. 44), as in ``prognos_torch/learners/anfis.py``: consequents
``alpha (4, 8)`` (rule index fastest), slopes ``b (3, 2)``, centres ``beta (3, 2)``.
"""

from __future__ import annotations

import json
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from dynamax.nonlinear_gaussian_ssm import (  # noqa: E402
    ParamsNLGSSM,
    UKFHyperParams,
    extended_kalman_filter,
    unscented_kalman_filter,
)

#: only the final mean is needed (the covariances of every step are not kept)
FIELDS = ["filtered_means"]


def anfis(theta, u):
    """Paper 003 Eq. 1-5: ``theta (44,)``, ``u (3,)`` -> ``(1,)``."""
    alpha = theta[:32].reshape(4, 8)
    b = theta[32:38].reshape(3, 2)
    beta = theta[38:44].reshape(3, 2)
    log_mu = jax.nn.log_sigmoid(b * (u[:, None] - beta))  # log of Eq. 2
    log_w = log_mu[0][:, None, None] + log_mu[1][None, :, None] + log_mu[2][None, None, :]
    w = jax.nn.softmax(log_w.reshape(8))  # Eq. 3-4, rules with the last input fastest
    return jnp.atleast_1d(w @ (alpha[:3].T @ u + alpha[3]))  # Eq. 5


def main():
    d = np.load(sys.argv[1])
    Xtr, Ytr = jnp.asarray(d["Xtr"]), jnp.asarray(d["Ytr"]).reshape(-1, 1)
    Xte, Yte = jnp.asarray(d["Xte"]), jnp.asarray(d["Yte"]).reshape(-1)
    theta0 = jnp.asarray(d["theta0"])
    P0, Q, R = jnp.asarray(d["P0"]), jnp.asarray(d["Q"]), jnp.asarray(d["R"])
    # dynamax updates with y_1 from the initial belief and predicts afterwards; the library
    # predicts first (theta_1 = theta_0 + w_1), so dynamax's initial covariance is P0 + Q.
    P_init = P0 + Q
    hyper = UKFHyperParams(alpha=1.0, beta=0.0, kappa=1.0)

    def one(filter_name, m0):
        params = ParamsNLGSSM(
            initial_mean=m0,
            initial_covariance=P_init,
            dynamics_function=lambda z, u: z,
            dynamics_covariance=Q,
            emission_function=anfis,
            emission_covariance=R,
        )
        if filter_name == "ekf":
            post = extended_kalman_filter(params, Ytr, inputs=Xtr, output_fields=FIELDS)
        else:
            post = unscented_kalman_filter(params, Ytr, hyper, inputs=Xtr, output_fields=FIELDS)
        theta = post.filtered_means[-1]
        pred = jax.vmap(anfis, in_axes=(None, 0))(theta, Xte)[:, 0]
        return theta, jnp.mean(jnp.abs(pred - Yte))

    cache = {}
    for line in sys.stdin:
        req = json.loads(line)
        name, runs = req["filter"], int(req["runs"])
        key = (name, runs)
        compile_s = None
        if key not in cache:
            if runs == 1:
                fn = jax.jit(lambda m0, name=name: one(name, m0))
                arg = theta0[0]
            else:
                fn = jax.jit(jax.vmap(lambda m0, name=name: one(name, m0)))
                arg = theta0[:runs]
            t0 = time.perf_counter()
            fn = fn.lower(arg).compile()
            compile_s = time.perf_counter() - t0
            cache[key] = (fn, arg)
        fn, arg = cache[key]
        t0 = time.perf_counter()
        theta, mae = jax.block_until_ready(fn(arg))
        dt = time.perf_counter() - t0
        out = {
            "time": dt,
            "compile": compile_s,
            "mae": np.atleast_1d(np.asarray(mae)).tolist(),
            "theta": np.atleast_2d(np.asarray(theta)).tolist(),
        }
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
