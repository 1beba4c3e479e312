"""The ``pmcal`` console script's entry point (pyproject ``[project.scripts]``): Ctrl-C is handled from the
first moment.

The console script imports this module, then calls :func:`run`, which imports :mod:`pmcal.cli`: 0.4 s of
imports (argparse, numpy, the commands). A Ctrl-C while Python's import machinery loaded ``pmcal.cli``
(before its own ``try``) reached the user as a traceback. This module imports nothing heavy and installs,
first thing, a SIGINT handler that ends the process at once with one line and exit status 130: while the
command line loads nothing has been opened or written. :func:`pmcal.cli.run` puts Python's own handler back
(Ctrl-C a KeyboardInterrupt, with every clean-up of a running command) before the command starts. A Ctrl-C
that is ignored (``nohup``, a background job) stays ignored.

A Ctrl-C before the interpreter runs this module's first line (its own start-up, ``site`` and the console
script's first imports: about 20 ms) is Python's own: the process ends by the signal, which a shell
reports as status 130, or Python prints its traceback.
"""

from __future__ import annotations

import os
import signal

#: exit status after Ctrl-C: what a shell reports for a command SIGINT ended
INTERRUPTED_STATUS = 128 + signal.SIGINT


def _stop_while_loading(signum, frame) -> None:
    """SIGINT while the command line loads: one line, exit 130 at once (nothing to clean up yet)."""
    os.write(2, b"pmcal: interrupted\n")
    os._exit(INTERRUPTED_STATUS)


if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
    signal.signal(signal.SIGINT, _stop_while_loading)


def run() -> None:
    """Entry point of the console script: :func:`pmcal.cli.run`, Ctrl-C handled before and while it loads."""
    from pmcal import cli

    cli.run(loading_handler=_stop_while_loading)
