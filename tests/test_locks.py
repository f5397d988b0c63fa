"""Exclusive locks (`locks`): a second process is refused naming the holder's pid and host, a
killed holder leaves no stale lock, the lock file goes with its holder, and a holder never
removes a file that another process locked after it."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from scenegen_jax.locks import LockHeld, acquire, describe_holder, exclusive, release

# A second process that takes the lock at argv[1], says so, and holds it until killed.
HOLDER = """
import sys, time
from scenegen_jax.locks import exclusive
with exclusive(sys.argv[1], "holding for a test"):
    print("held", flush=True)
    time.sleep(600)
"""
# A second process that tries the lock at argv[1] once: prints its refusal.
TRIER = """
import sys
from scenegen_jax.locks import LockHeld, exclusive
try:
    with exclusive(sys.argv[1], "trying for a test"):
        print("acquired")
except LockHeld as e:
    print("refused:", e)
"""


def _python(script: str, *args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", script, *args], stdout=subprocess.PIPE,
                            text=True, **kw)


def test_a_second_process_is_refused_naming_the_holder(tmp_path):
    path = str(tmp_path / "w" / ".lock")  # the folder is made for it
    with exclusive(path, "training into w"):
        record = json.loads(open(path).read())
        assert record["pid"] == os.getpid() and record["host"] == socket.gethostname()
        out = _python(TRIER, path).communicate(timeout=60)[0]
    assert out.startswith("refused:"), out
    assert (f"{path}: locked by pid {os.getpid()} on host {socket.gethostname()} "
            "(training into w, since ") in out
    assert len(out.strip().splitlines()) == 1
    assert not os.path.exists(path)  # the holder removed its file
    assert _python(TRIER, path).communicate(timeout=60)[0].strip() == "acquired"


def test_a_killed_holder_leaves_no_stale_lock(tmp_path):
    path = str(tmp_path / ".lock")
    holder = _python(HOLDER, path)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(LockHeld, match=f"locked by pid {holder.pid} "):
            acquire(path, "a second run")
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert os.path.exists(path)  # no cleanup ran, and no matter: the OS let go of the lock
    with exclusive(path, "after the kill"):
        assert json.loads(open(path).read())["pid"] == os.getpid()


def test_the_holder_never_removes_a_file_locked_after_it(tmp_path):
    """A process that locked the path's file as the holder removed it tries again on the new
    file; the holder, letting go, removes only the file it locked."""
    path = str(tmp_path / ".lock")
    fd = acquire(path, "first")
    os.remove(path)  # as `release` does, with another process's file made in its place
    with open(path, "w") as f:
        f.write("another process's lock file")
    release(path, fd)
    assert open(path).read() == "another process's lock file"


def test_one_process_holds_at_a_time(tmp_path):
    """Processes started together on one path: one holds it, every other is refused."""
    path = str(tmp_path / ".lock")
    holder = _python(HOLDER, path)
    try:
        assert holder.stdout.readline().strip() == "held"
        triers = [_python(TRIER, path) for _ in range(4)]
        outs = [t.communicate(timeout=60)[0] for t in triers]
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert all(o.startswith(f"refused: {path}: locked by pid {holder.pid} ") for o in outs), outs


def test_a_holder_that_has_not_written_yet_is_described():
    assert describe_holder("") == "another process (it has not written its pid yet)"
    assert describe_holder('{"pid": 7') == "another process (it has not written its pid yet)"
    text = json.dumps({"pid": 7, "host": "h", "what": "x", "since": time.strftime("%Y")})
    assert describe_holder(text).startswith("pid 7 on host h (x, since ")
