"""What the two command lines (``prognos ...`` and the fleet's ``prognos rul TABLE --group-by``)
share: the checks of their output files, one torch thread per command, and the option an
error message is about. No torch import at module level: ``--help`` stays fast."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "check_output_file",
    "check_overwrites",
    "one_torch_thread",
    "option_of",
    "where_message",
    "calibrate_message",
]


def check_output_file(path: str | Path | None, what: str) -> None:
    """An output file's folder exists and it is no folder itself (``what`` names the option);
    a figure (``--plot``) has a figure suffix (:func:`~prognos_torch.io.figure_format`)."""
    if path is None:
        return
    if str(path).endswith(("/", os.sep)):  # (a folder: Path() would drop the separator)
        raise ValueError(f"{what}: {path} names a folder, expected a file name")
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{what}: folder {folder} does not exist")
    if path.is_dir():
        raise ValueError(f"{what}: {path} is a folder, expected a file name")
    if what == "--plot":
        from .io import figure_format

        figure_format(path, what)


def check_overwrites(outputs: dict, inputs: dict) -> None:
    """No output file is a file this run reads or another output (``--csv data.csv`` replaced
    the data it had read; ``--plot`` and ``--json`` on one name kept the last one written).
    ``outputs`` and ``inputs`` map an option or a description to a path (or ``None``)."""
    seen: dict = {}
    for what, path in outputs.items():
        if path is None or str(path) == "-":  # (--json -: standard output)
            continue
        key = os.path.realpath(path)
        for name, src in inputs.items():
            if src is not None and os.path.realpath(src) == key:
                raise ValueError(
                    f"{what}: {path} is {name}, which this run reads; writing it would replace "
                    "it (give another file name)"
                )
        if key in seen:
            raise ValueError(
                f"{seen[key]} and {what} name the same file {path}: one would replace the other"
            )
        seen[key] = what


@contextmanager
def one_torch_thread() -> Iterator[None]:
    """torch on one thread while a command runs (tiny matrices: threads only add overhead, see
    tests/conftest), the caller's count restored afterwards."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def option_of(text: str, options: dict[str, str]) -> str | None:
    """The command-line option whose value the error message ``text`` is about: the option of
    the first key of ``options`` (the first words of such messages) that ``text`` starts with,
    followed by a space or ``=`` (``"until='2003-01-01' is a date-time ..."``); else ``None``."""
    return next((o for k, o in options.items() if text.startswith((k + " ", k + "="))), None)


def where_message(text: str, option: str) -> str:
    """An error message of ``where`` (``parse_where``, ``read_fleet_table``) in the words of the
    command-line option that gave it (``--where``, ``--calibrate-where``): a message about the
    selection itself (``"where: ..."``) starts with the option, and a table's ``(where)`` names
    it; any other message is returned as it is."""
    if text.startswith("where: "):
        return f"{option}: " + text[len("where: ") :].replace("--where", option)
    return text.replace("(where)", f"({option})")


def calibrate_message(text: str) -> str:
    """An error of reading or replaying the ``--calibrate`` table, in the command line's
    words: one about ``--calibrate-where``'s own value names that option (:func:`where_message`),
    any other is prefixed ``--calibrate:``, the table it is about."""
    text = where_message(text, "--calibrate-where")
    return text if text.startswith("--calibrate-where: ") else f"--calibrate: {text}"
