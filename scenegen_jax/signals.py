"""Stop signals: Ctrl-C (SIGINT) and SIGTERM stop a command the same way, so that every
output it was writing is removed or left whole (`files.written_whole`, the cache writer,
the workdir's lock) and its worker processes end with it.

`install` (the command line) makes both signals raise `Stopped`, a KeyboardInterrupt, in
the main thread. Python runs a signal handler between any two bytecodes, so the exception
can rise inside a garbage-collector callback, where Python prints it and carries on; the
signal is therefore also recorded, and long loops call `raise_pending` between their steps,
so that a stop is never lost.
"""

from __future__ import annotations

import signal

_received: list[int] = []


class Stopped(KeyboardInterrupt):
    """A stop signal arrived; `exit_status` is the shell's for it (130 for SIGINT, 143 for
    SIGTERM)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def exit_status(self) -> int:
        return 128 + self.signum


def _handler(signum, frame) -> None:
    _received.append(signum)
    raise Stopped(signum)


def install() -> None:
    """SIGINT and SIGTERM raise `Stopped` in the main thread from now on."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _handler)


def ignore_in_worker() -> None:
    """For a worker process: leave stop signals to the parent, which ends its workers
    (a Ctrl-C reaches the whole process group; tracebacks of every worker would say
    nothing more)."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, signal.SIG_IGN)


def raise_pending() -> None:
    """Raises `Stopped` if a stop signal arrived whose exception was swallowed."""
    if _received:
        signum = _received[-1]
        _received.clear()
        raise Stopped(signum)
