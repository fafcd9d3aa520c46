"""``python -m prognos_torch COMMAND ...``: the ``prognos`` command line (see :mod:`.cli`)."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
