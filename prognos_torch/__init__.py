"""prognos_torch: Kalman-filter training of small learners and prognostic filters in PyTorch.

Subpackages: ``core`` (state-space models, beliefs, square-root algebra), ``quadrature``
(sigma-point rules), ``filters`` (one Gaussian engine, particle filters), ``adapt`` (strong
tracking, noise estimation, robust update), ``optim`` (Kalman optimisers, training loop),
``learners`` (ELM, LS-SVR, ANFIS), ``prognosis`` (forecasting, RUL), ``metrics``, ``systems``
(simulators), ``datasets`` (IMS bearings, windows), ``plots`` (figures), ``studies``.
"""

__version__ = "0.1.0"
