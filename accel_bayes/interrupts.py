"""SIGINT/SIGTERM as a flag that long loops and the output writers check (issue #29).

A Python signal handler runs between any two bytecodes of the main thread, also inside a
garbage-collection finalizer or a ``finally`` block of library code; an exception raised there is
printed as "Exception ignored in …" and swallowed, and the run goes on.  So the handlers that
:func:`handle_signals` installs only *record* the signal; the exception
(:class:`Interrupted`, a ``KeyboardInterrupt``) is raised by :func:`check`, which the code calls
at safe points: every iteration of the LM solvers and of the PmMH chains, and every writer just
before it makes a file or an output set visible (:mod:`accel_bayes.data.outputs`).  A writer that
sees the flag discards what it staged, so an interrupted command leaves its earlier outputs as
they were.  Without :func:`handle_signals` (plain library use) nothing is recorded and
:func:`check` never raises: Ctrl-C then behaves as Python's default.  The ``accel-bayes``
process records from its first line (:func:`install`, before the seconds of imports) and, once
the command has decided its exit status, ignores later signals (:func:`hold_until_exit`), so a
signal at any moment gives status 130 or, after that decision, none at all.
"""
from __future__ import annotations

import contextlib
import signal

__all__ = ["Interrupted", "install", "handle_signals", "check", "requested", "hold_until_exit"]

_received: list[int] = []  # signal numbers recorded by the handler since handle_signals began
_exiting = [False]  # hold_until_exit was called: the handlers are not restored
_process = [False]  # install() was called: the whole process is one command


class Interrupted(KeyboardInterrupt):
    """Raised by :func:`check` after SIGINT or SIGTERM; handled like Ctrl-C (CLI exit 130)."""


def _record(signum, frame):  # only records: raising here could land in any code (see module docstring)
    _received.append(signum)


def requested() -> bool:
    """Whether SIGINT/SIGTERM arrived since :func:`handle_signals` began."""
    return bool(_received)


def check() -> None:
    """Raise :class:`Interrupted` if SIGINT/SIGTERM arrived; call it where stopping is safe."""
    if _received:
        raise Interrupted(signal.Signals(_received[0]).name)


def install() -> None:
    """For a process that *is* one command (``accel-bayes``, ``python -m accel_bayes``): record
    SIGINT/SIGTERM from now on, before the package's heavy imports (seconds, during which a
    SIGTERM would otherwise kill the process with another status and SIGINT print a traceback).
    :func:`handle_signals` then keeps these handlers and what they recorded."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _record)
    _process[0] = True


@contextlib.contextmanager
def handle_signals():
    """Within the block, SIGINT and SIGTERM only set the flag that :func:`check` reads; the
    previous handlers come back after it.  Outside the main thread (where Python cannot set
    handlers) the block runs with the handlers as they are."""
    if _process[0]:  # installed for the whole process already; a signal recorded so far counts
        yield
        return
    old = {}
    _received.clear()  # before the handlers go in: a signal arriving right after must count
    try:
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, _record)
    except ValueError:  # not the main thread
        for s, h in old.items():
            signal.signal(s, h)
        yield
        return
    try:
        yield
    finally:
        if not _exiting[0]:
            for s, h in old.items():
                signal.signal(s, h)
            _received.clear()  # the flag belonged to this block: library code after it runs on


def hold_until_exit() -> bool:
    """For a process that ends right after: ignore SIGINT/SIGTERM from now on and say whether one
    arrived before.  The answer is the command's last word, so a signal that beats it gives
    status 130 and one that comes later (while the interpreter shuts down) is ignored rather than
    killing the process with a different status or a traceback from its finalizers."""
    _exiting[0] = True
    for s in (signal.SIGINT, signal.SIGTERM):
        # signal.signal runs the handlers of signals already caught before it swaps this one in
        signal.signal(s, signal.SIG_IGN)
    return requested()
