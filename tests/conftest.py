"""Test-wide settings.

The filters work on many tiny matrices; OpenMP worker threads only add synchronisation cost
there, and on a busy 2-core CI machine spinning threads slow batched QR/Cholesky calls by
orders of magnitude. Tests therefore run torch single-threaded.
"""

import torch

torch.set_num_threads(1)
