"""The ``deliffas`` command: ``run`` is the console script's entry point, and ``python -m deliffas`` (also what
``torchrun -m deliffas`` runs) calls it too.

Tiny on purpose: it installs the Ctrl-C handling before anything heavy is imported (the command line module
and, through it, torch), so an interrupt at any moment of start-up ends in the same one line as a later one
(for ``convert`` and ``train``: what is kept and the command that resumes) and exit 130.
"""

import os
import signal
import sys
import _thread
import time


def _deliver_lost_interrupt(hook_args) -> None:
    """``sys.unraisablehook``: a Ctrl-C that landed in a finaliser or weakref callback (one of importlib's module
    locks, say) is not lost with a printed traceback; it is sent again, to arrive in the command's own code."""
    if not issubclass(hook_args.exc_type, KeyboardInterrupt):
        sys.__unraisablehook__(hook_args)
        return
    # Not from here: a signal raised inside the hook runs its handler inside the hook, and is lost again. A thread
    # sends it once the hook has returned (``_thread``: ``threading``'s start waits, and the wait can take it too).
    _thread.start_new_thread(_send_ctrl_c_after, (0.01,))


def _send_ctrl_c_after(delay_s: float) -> None:
    time.sleep(delay_s)
    signal.raise_signal(signal.SIGINT)


def run() -> None:
    """Run the command line (``sys.argv``) and exit with its code."""
    interrupted = []
    signal.signal(signal.SIGINT, lambda *_: interrupted.append(True))  # reported once the imports below are done
    from deliffas.cli import main, report_interrupted  # local: after the Ctrl-C handler (the import is start-up)

    if interrupted:  # Ctrl-C while the command line loaded: the line of a later one (what is kept, how to resume)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        code = report_interrupted(None, sys.argv[1:])
    else:
        sys.unraisablehook = _deliver_lost_interrupt
        signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            code = main()
        except SystemExit as exit_:  # --help, or a command line argparse refused: ended as well
            code = exit_.code
    if code == 130:
        # interrupted and reported: leave now. The interpreter's exit would join worker pools and threads that the
        # Ctrl-C also reached, and one of them could end the process by the signal after the line was printed.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    # the work is done and reported: a Ctrl-C while the interpreter exits (it restores the default handler late in
    # its exit, and that one would end the process by the signal) no longer changes the outcome
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    raise SystemExit(code)


if __name__ == "__main__":
    run()
