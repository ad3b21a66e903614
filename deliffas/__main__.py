"""``python -m deliffas`` = the ``deliffas`` command (also what ``torchrun -m deliffas`` runs)."""

import os
import signal
import sys


def _interrupted_at_start(signum, frame) -> None:
    """Ctrl-C while the command line module loads: one line, no traceback (``main`` handles it after)."""
    os.write(2, b"deliffas: interrupted\n")
    os._exit(130)


signal.signal(signal.SIGINT, _interrupted_at_start)
from deliffas.cli import main  # noqa: E402  (after the handler: the import is part of start-up)

signal.signal(signal.SIGINT, signal.default_int_handler)
code = main()
if code == 130:
    # interrupted and reported: leave now. The interpreter's exit would join worker pools and threads that the
    # Ctrl-C also reached, and one of them could end the process by the signal after the line was printed.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(130)
raise SystemExit(code)
