"""The ``deliffas`` command: ``run`` is the console script's entry point, and ``python -m deliffas`` (also what
``torchrun -m deliffas`` runs) calls it too.

Tiny on purpose: it installs the Ctrl-C handling before anything heavy is imported (the command line module
and, through it, torch), so an interrupt at any moment of start-up ends in one line and exit 130.
"""

import os
import signal
import sys


def _interrupted_at_start(signum, frame) -> None:
    """Ctrl-C while the command line module loads: one line, no traceback (``main`` handles it after)."""
    os.write(2, b"deliffas: interrupted\n")
    os._exit(130)


def run() -> None:
    """Run the command line (``sys.argv``) and exit with its code."""
    signal.signal(signal.SIGINT, _interrupted_at_start)
    from deliffas.cli import main  # after the handler: the import is part of start-up

    signal.signal(signal.SIGINT, signal.default_int_handler)
    code = main()
    if code == 130:
        # interrupted and reported: leave now. The interpreter's exit would join worker pools and threads that the
        # Ctrl-C also reached, and one of them could end the process by the signal after the line was printed.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    raise SystemExit(code)


if __name__ == "__main__":
    run()
