"""Two writers of one cache, and stop signals: a second `prepare` into a cache being written
is refused naming the first; SIGTERM stops `prepare` as Ctrl-C does, leaving no partial file,
no lock and no worker process; a stop whose exception Python swallowed still stops."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from processes import alive, children

from scenegen_jax import signals
from scenegen_jax.config import get_config
from scenegen_jax.data.cache_write import CacheWriter
from scenegen_jax.locks import LockHeld


def test_a_second_writer_of_a_cache_is_refused_naming_the_first(tmp_path):
    cfg = get_config("tiny")
    with CacheWriter(str(tmp_path), cfg):
        assert os.path.exists(tmp_path / ".lock")
        assert any(n.startswith("map_points.npy.") and n.endswith(".tmp")
                   for n in os.listdir(tmp_path))
        with pytest.raises(LockHeld, match=rf"\.lock: locked by pid {os.getpid()} "):
            CacheWriter(str(tmp_path), cfg)
    assert os.listdir(tmp_path) == []  # no scenes written: nothing left, the lock released
    with CacheWriter(str(tmp_path), cfg):  # free again
        pass


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="reads /proc")
def test_sigterm_to_prepare_alone_removes_its_outputs_and_ends_its_workers(tmp_path, data_root):
    """SIGTERM to the parent only (not its process group), while its two workers read."""
    out = tmp_path / "cache"
    proc = subprocess.Popen(
        [sys.executable, "-m", "scenegen_jax.cli", "prepare", "--source", "av2", "--root",
         data_root, "--split", "train", "--config", "tiny", "--stride", "1", "--workers", "2",
         "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    workers: set[int] = set()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        workers |= children(proc.pid)
        if len(workers) >= 2 and out.is_dir() and any(".tmp" in n for n in os.listdir(out)):
            break
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()
    time.sleep(1.0)
    workers |= children(proc.pid)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err and "interrupted (SIGTERM)" in err
    assert sorted(os.listdir(out)) == []  # no map_points.npy.<pid>.tmp, no .lock, no cache
    deadline = time.monotonic() + 60
    while any(alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not [w for w in workers if alive(w)]


def test_a_swallowed_stop_is_raised_at_the_next_check(monkeypatch):
    """The handler's exception can rise where Python drops it (a garbage-collector callback);
    the recorded signal is raised again at the next `raise_pending`, once."""
    monkeypatch.setattr(signals, "_received", [])
    with pytest.raises(signals.Stopped):
        signals._handler(signal.SIGTERM, None)  # as if dropped by its caller
    with pytest.raises(signals.Stopped) as e:
        signals.raise_pending()
    assert e.value.exit_status == 143 and isinstance(e.value, KeyboardInterrupt)
    signals.raise_pending()  # nothing pending any more


def test_a_stop_inside_a_garbage_collector_callback_is_delivered_after_it(monkeypatch):
    """Inside `_xla_gc_callback` (where Python would print and drop the exception) the
    handler does not raise; the signal comes again a moment later and raises there."""
    monkeypatch.setattr(signals, "_received", [])
    previous = signals.install()
    try:
        def _xla_gc_callback():  # the name Python's dropping callback has in JAX
            signals._handler(signal.SIGINT, sys._getframe())

        _xla_gc_callback()  # returns: nothing raised inside
        with pytest.raises(signals.Stopped):
            time.sleep(5)  # the redelivered signal interrupts this
    finally:
        signals.restore(previous)


def test_a_stop_turned_into_an_import_error_still_exits_as_the_stop(monkeypatch):
    """A stop that arrives while an extension module initialises comes back as its
    ImportError (tensorstore's "initialization failed"): the command still exits as stopped
    (143 for SIGTERM), not with a traceback; without a stop the error is raised as it is."""
    from scenegen_jax import cli

    def stopped_in_an_import(argv):
        signals._received.append(signal.SIGTERM)
        raise ImportError("initialization failed")

    monkeypatch.setattr(signals, "_received", [])
    monkeypatch.setattr(cli, "_run", stopped_in_an_import)
    with pytest.raises(SystemExit) as e:
        cli.main(["models"])
    assert e.value.code == 143

    def failed_import(argv):
        raise ImportError("no module named x")

    monkeypatch.setattr(signals, "_received", [])
    monkeypatch.setattr(cli, "_run", failed_import)
    with pytest.raises(ImportError, match="no module named x"):
        cli.main(["models"])
