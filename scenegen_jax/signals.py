"""Stop signals: Ctrl-C (SIGINT) and SIGTERM stop a command the same way, so that every
output it was writing is removed or left whole (`files.written_whole`, the cache writer,
the workdir's lock) and its worker processes end with it.

`install` (the command line) makes both signals raise `Stopped`, a KeyboardInterrupt, in
the main thread. Python runs a signal handler between any two bytecodes, so the exception
could rise inside a garbage-collector callback, where Python prints it and carries on: a
stop that arrives there is delivered again a moment later instead. The signal is also
recorded, and the training loop calls `raise_pending` between its steps, so that a stop is
never lost.
"""

from __future__ import annotations

import _thread
import signal
import threading

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


# Functions whose exceptions Python prints and drops ("Exception ignored in"): garbage
# collector callbacks (JAX's among them) and finalizers. A stop that arrives inside one is
# delivered again a moment later, outside it.
_DROPPING = ("_xla_gc_callback", "__del__")


def _inside_dropping(frame) -> bool:
    while frame is not None:
        if frame.f_code.co_name in _DROPPING:
            return True
        frame = frame.f_back
    return False


def _handler(signum, frame) -> None:
    _received.append(signum)
    if _inside_dropping(frame):
        threading.Timer(0.01, _thread.interrupt_main, (signum,)).start()
        return
    raise Stopped(signum)


def install() -> dict:
    """SIGINT and SIGTERM raise `Stopped` in the main thread from now on; returns the
    handlers they had (for `restore`)."""
    return {signum: signal.signal(signum, _handler) for signum in (signal.SIGINT, signal.SIGTERM)}


def restore(previous: dict) -> None:
    """The handlers `install` replaced, back (a command run inside another program)."""
    for signum, handler in previous.items():
        signal.signal(signum, handler)


def ignore_while_exiting() -> None:
    """Once a command's work is done (its outputs whole): stop signals are ignored while the
    process exits. Python's shutdown sets the handlers it installed back to the default,
    which would end a finished command as killed by the signal; an ignored signal stays
    ignored."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, signal.SIG_IGN)


def ignore_in_worker() -> None:
    """For a worker process: leave stop signals to the parent, which ends its workers
    (a Ctrl-C reaches the whole process group; tracebacks of every worker would say
    nothing more)."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, signal.SIG_IGN)


def pending_stop() -> Stopped | None:
    """The `Stopped` of the last stop signal that arrived, if one did (kept pending)."""
    return Stopped(_received[-1]) if _received else None


def raise_pending() -> None:
    """Raises `Stopped` if a stop signal arrived whose exception was swallowed."""
    if _received:
        signum = _received[-1]
        _received.clear()
        raise Stopped(signum)
