"""Ctrl-C and SIGTERM kept from libraries that swallow them.

Some libraries colorps calls (trimesh, which writes the meshes, among them)
wrap optional imports and fallbacks in ``except BaseException``, and so catch
the KeyboardInterrupt a Ctrl-C raises: the run goes on as if nothing happened,
or fails later with an unrelated error, or takes a fallback that changes what
it writes. :func:`interrupts_kept` raises such an interrupt again once the
block it guards ends, so it is never lost and no file written meanwhile is
kept.
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["interrupts_kept"]


@contextlib.contextmanager
def interrupts_kept():
    """Within the context, remember every exception the SIGINT and SIGTERM
    handlers raise; when the block ends, raise the first of them again if the
    block swallowed it (or let it turn into another error).

    Only Python-level handlers are watched (Python's default for SIGINT, and
    those the CLI installs); outside the main thread, where signals are never
    handled, the block runs unguarded.

    Examples
    --------
    >>> with interrupts_kept():
    ...     total = sum(range(10))
    >>> total
    45
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    raised: list[BaseException] = []

    def recording(previous):
        def handler(signum, frame):
            try:
                previous(signum, frame)
            except BaseException as exc:
                raised.append(exc)
                raise
        return handler

    watched = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    watched = {signum: handler for signum, handler in watched.items() if callable(handler)}
    for signum, previous in watched.items():
        signal.signal(signum, recording(previous))
    try:
        yield
    except BaseException as exc:
        if raised and exc is not raised[0]:
            raise raised[0] from None
        raise
    finally:
        for signum, previous in watched.items():
            signal.signal(signum, previous)
    if raised:
        raise raised[0]
