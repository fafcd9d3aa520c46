"""Running a script of the repository (a benchmark, an example) as ``__main__`` in the test
process: an interpreter of its own costs about 3 s of start-up (torch's import) per script."""

from __future__ import annotations

import contextlib
import io
import os
import runpy
import sys
import warnings
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def run_script(path: Path, args: list[str], cwd: Path) -> str:
    """Run ``path`` as ``__main__`` with the command-line ``args`` in the folder ``cwd`` and
    return what it printed. ``sys.argv``, ``sys.path`` (the repository root is put first, as
    ``PYTHONPATH`` would), the working folder, the warning filters and the torch thread count
    (which the scripts set) are restored afterwards. A non-zero exit fails the caller's test."""
    argv, path0, here, threads = sys.argv, list(sys.path), os.getcwd(), torch.get_num_threads()
    out = io.StringIO()
    try:
        sys.argv, sys.path[:0] = [str(path), *args], [str(ROOT)]
        os.chdir(cwd)
        with warnings.catch_warnings(), contextlib.redirect_stdout(out):
            runpy.run_path(str(path), run_name="__main__")
    except SystemExit as exc:  # (argparse or an explicit exit)
        if exc.code not in (None, 0):
            tail = out.getvalue()[-3000:]
            raise AssertionError(f"{path.name} exited with {exc.code}:\n{tail}") from None
    finally:
        sys.argv, sys.path[:] = argv, path0
        os.chdir(here)
        torch.set_num_threads(threads)
    return out.getvalue()
