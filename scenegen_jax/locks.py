"""Exclusive locks on folders that one process at a time may write (a training workdir, a
cache being prepared), held by `fcntl.flock` on a lock file inside them.

The OS releases an flock when its holder exits however it ends (`kill -9` included), so a
lock is never stale: a lock file left by a killed holder is locked again at once. The holder
writes its pid, host and start time into the file, and a second process is refused with a
one-line `LockHeld` naming them. The holder removes the file when it lets go; a process that
locked the file just before its removal sees that the path no longer leads to the file it
locked and tries again on the new one, so two processes never both hold a path.

flock is advisory: only processes that take the lock are kept out. It works on local file
systems and on NFS (Linux emulates it with NFS byte-range locks). Child processes forked while
the lock is held share it: it ends when the last of them exits.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import time
from collections.abc import Iterator

LOCK_FILE = ".lock"  # the lock file's name inside a folder it guards


class LockHeld(OSError):
    """Another process holds the lock; the message names the lock file and the holder."""


def holder_record(what: str) -> dict:
    """What a holder writes into its lock file: this process's pid and host, `what` it is
    doing, and since when (local time)."""
    return {"pid": os.getpid(), "host": socket.gethostname(), "what": what,
            "since": time.strftime("%Y-%m-%d %H:%M:%S")}


def describe_holder(text: str) -> str:
    """The holder as a phrase, from a lock file's contents (empty or cut short: the holder
    has locked the file but not written it yet)."""
    try:
        record = json.loads(text)
        return (f"pid {int(record['pid'])} on host {record['host']} ({record['what']}, since "
                f"{record['since']})")
    except (ValueError, TypeError, KeyError):
        return "another process (it has not written its pid yet)"


def _read(fd: int) -> str:
    return os.pread(fd, 4096, 0).decode("utf-8", errors="replace")


def _same_file(fd: int, path: str) -> bool:
    """Whether `path` still names the file open as `fd` (not removed or replaced since)."""
    try:
        here = os.stat(path)
    except FileNotFoundError:
        return False
    there = os.fstat(fd)
    return (here.st_dev, here.st_ino) == (there.st_dev, there.st_ino)


def acquire(path: str, what: str) -> int:
    """Locks the file `path` (made, with its folder, if missing) for this process and writes
    `holder_record(what)` into it; returns the open file descriptor that holds the lock.

    Raises:
      LockHeld: another process holds it (the message names its pid and host).
    """
    while True:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = describe_holder(_read(fd))
            os.close(fd)
            raise LockHeld(f"{path}: locked by {holder}; wait for that process to end or "
                           "stop it") from None
        if _same_file(fd, path):
            break
        os.close(fd)  # its holder removed it as we locked it: lock the path's new file
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(holder_record(what)).encode(), 0)
    return fd


def release(path: str, fd: int) -> None:
    """Removes the lock file `path`, then lets go of the lock held by `fd` (`acquire`)."""
    with contextlib.suppress(FileNotFoundError):
        if _same_file(fd, path):
            os.remove(path)
    os.close(fd)  # closing the last descriptor releases the flock


@contextlib.contextmanager
def exclusive(path: str, what: str) -> Iterator[None]:
    """Holds the lock file `path` for the block (`acquire`, `release`). `what`: what this
    process does, as the refusal of another shows it, e.g. "training of workdir w"."""
    fd = acquire(path, what)
    try:
        yield
    finally:
        release(path, fd)
