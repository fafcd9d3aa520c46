"""Test-wide settings.

The filters work on many tiny matrices; OpenMP worker threads only add synchronisation cost
there, and on a busy 2-core CI machine spinning threads slow batched QR/Cholesky calls by
orders of magnitude. Tests therefore run torch single-threaded, and so do the BLAS libraries
that NumPy and SciPy load (OpenBLAS reads its thread count when it is loaded, so the variables
are set before anything imports numpy): the LLE health indicator's ``scipy.linalg.eigh``
rounds differently with 2 threads, and the study tests assert its numbers to 1e-6.

The parallelism goes to processes instead: the README's command runs the suite in two
single-threaded pytest-xdist workers (``-n 2 --dist loadscope``: a module's tests, and so its
module-scoped quick study, stay in one worker). No test may depend on another having run first.
"""

import os
import sys

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
if "numpy" in sys.modules:  # too late for OpenBLAS to see the setting
    import warnings

    warnings.warn(
        "numpy was imported before tests/conftest.py; BLAS threads are not pinned", stacklevel=2
    )

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _seed_global_stream():
    """Each test starts from the same global torch stream (modules draw their initial weights
    from it), so that no test depends on what earlier tests drew; the library itself draws only
    from explicit generators."""
    torch.manual_seed(0)
