"""The ``colorps`` command as a process: ``colorps ...`` or ``python -m colorps ...``.

:func:`entry` runs :func:`colorps.cli.main` and then ends the process at once.
Past the last file written, the interpreter's own teardown would free the
objects numba made when it loaded the kernels one by one, and collect them
again and again: 0.25-0.4 s of every run (a 1 MP reconstruction's exit took
0.37 s, 0.04 s ended so), which the user waits for and nothing needs. The exit
handlers still run and the standard streams are flushed first (mypy's
``hard_exit`` ends its command the same way, without the handlers).
Calling :func:`colorps.cli.main` from Python ends nothing.
"""

from __future__ import annotations

import atexit
import os
import sys

from .cli import main

__all__ = ["entry"]


def entry() -> None:
    """Run the ``colorps`` command on ``sys.argv`` and end the process with its
    exit code (an exception or ``SystemExit`` from it ends it as Python does)."""
    code = main()
    atexit._run_exitfuncs()  # what the interpreter's exit runs first (logging, tqdm)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    entry()
