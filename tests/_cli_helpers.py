"""Shared set-up of the command-line tests: a small CSV series and the one-line error check."""

from __future__ import annotations

import math
from pathlib import Path


def healthy_csv(path: Path, n: int = 40, slope: float = 0.0) -> tuple[Path, list[float]]:
    """A slowly oscillating series (plus ``slope`` per row) on t = 0, 0.5, ... written to
    ``path`` with columns ``t`` and ``v``; the path and the times."""
    t = [0.5 * i for i in range(n)]
    y = [1.0 + 0.05 * math.sin(1.3 * i) + slope * i for i in range(n)]
    path.write_text("t,v\n" + "".join(f"{a!r},{b!r}\n" for a, b in zip(t, y)))
    return path, t


def one_error(capsys, text: str) -> str:
    """The command wrote exactly one ``error: ...`` line holding ``text`` to stderr; its
    stdout."""
    cap = capsys.readouterr()
    err = cap.err
    assert err.count("\n") == 1 and err.startswith("error: "), err
    assert text in err, err
    return cap.out
