"""The allocator switch: which library `scenegen` preloads, and that a process started
through `reexec_with_tcmalloc` really runs on it (a child interpreter, as the command starts)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from scenegen_jax import allocator

INSTALLED = allocator.find_tcmalloc({})


@pytest.fixture
def lib(tmp_path):
    """A file standing for a tcmalloc build that SCENEGEN_MALLOC names."""
    path = tmp_path / "libtcmalloc_minimal.so.4"
    path.write_bytes(b"")
    return path


def test_system_keeps_glibc():
    for value in ("system", "SYSTEM", "glibc", "off"):
        assert allocator.find_tcmalloc({allocator.SWITCH: value}) is None
        assert allocator.preload_env({allocator.SWITCH: value}) is None


def test_a_missing_path_names_the_switch(tmp_path):
    with pytest.raises(FileNotFoundError, match=allocator.SWITCH):
        allocator.find_tcmalloc({allocator.SWITCH: str(tmp_path / "libtcmalloc.so")})


def test_a_path_that_ld_preload_would_split_is_refused(tmp_path):
    for name in ("my lib", "my:lib"):
        path = tmp_path / name / "libtcmalloc_minimal.so.4"
        path.parent.mkdir()
        path.write_bytes(b"")
        with pytest.raises(ValueError, match="LD_PRELOAD cannot hold a path with a space or a"):
            allocator.find_tcmalloc({allocator.SWITCH: str(path)})


def test_preload_goes_first_and_keeps_the_rest(lib):
    env = allocator.preload_env({allocator.SWITCH: str(lib), "LD_PRELOAD": "/a/libx.so:/b/liby.so",
                                 "KEEP": "1"})
    assert env["LD_PRELOAD"] == f"{lib} /a/libx.so /b/liby.so"
    assert env["KEEP"] == "1" and env[allocator.SWITCH] == str(lib)
    assert int(env["TCMALLOC_LARGE_ALLOC_REPORT_THRESHOLD"]) > 2**40


def test_never_twice(lib, tmp_path):
    """A process that has a tcmalloc preloaded (ours or the user's own) is not started again,
    whatever SCENEGEN_MALLOC's file is called."""
    for preloaded in (str(lib), "libtcmalloc.so.4", "/x/liba.so /opt/libtcmalloc_minimal.so"):
        assert allocator.preload_env({allocator.SWITCH: str(lib), "LD_PRELOAD": preloaded}) is None
    other = tmp_path / "my_allocator.so"
    other.write_bytes(b"")
    env = allocator.preload_env({allocator.SWITCH: str(other)})
    assert env["LD_PRELOAD"] == str(other)
    assert allocator.preload_env({**env, allocator.SWITCH: str(other)}) is None


def test_a_user_threshold_is_kept(lib):
    env = allocator.preload_env({allocator.SWITCH: str(lib),
                                 "TCMALLOC_LARGE_ALLOC_REPORT_THRESHOLD": "1000"})
    assert env["TCMALLOC_LARGE_ALLOC_REPORT_THRESHOLD"] == "1000"


def _child(env_extra: dict[str, str]) -> list[str]:
    """What a fresh interpreter that calls `reexec_with_tcmalloc` first reports: its pid
    before and after, and the allocator that then hands its freed pages back."""
    code = ("import os; print(os.getpid()); from scenegen_jax import allocator; "
            "allocator.reexec_with_tcmalloc(); allocator.release_freed_memory(); "
            "print(os.getpid(), allocator.active())")
    env = {k: v for k, v in os.environ.items() if k not in ("LD_PRELOAD", allocator.SWITCH)}
    out = subprocess.run([sys.executable, "-c", code], env={**env, **env_extra},
                         capture_output=True, text=True, check=True, timeout=120)
    return out.stdout.split()


@pytest.mark.skipif(INSTALLED is None, reason="no libtcmalloc_minimal installed "
                    "(apt install libtcmalloc-minimal4)")
def test_the_process_starts_again_on_tcmalloc():
    lines = _child({})
    # Printed once before the exec and once after: the same process (pid), now on tcmalloc.
    assert lines[0] == lines[1] == lines[2] and lines[3] == "tcmalloc"
    lines = _child({allocator.SWITCH: "system"})
    assert lines[0] == lines[1] and lines[2] == "system"


def test_the_command_names_a_missing_library(tmp_path):
    missing = str(tmp_path / "libtcmalloc_minimal.so.4")
    env = {**os.environ, allocator.SWITCH: missing}
    out = subprocess.run([sys.executable, "-m", "scenegen_jax.cli", "models"], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert f"{allocator.SWITCH}={missing}: no such file" in out.stderr


def test_a_stale_preload_of_a_missing_tcmalloc_runs_on(tmp_path):
    """`LD_PRELOAD` naming a tcmalloc that is not there (ld.so prints an error and goes on):
    the command runs. CPython's `find_library` raised FileNotFoundError on ld.so's message
    where no tcmalloc is installed, and every command failed with it."""
    stale = str(tmp_path / "libtcmalloc_minimal.so.4")
    env = {k: v for k, v in os.environ.items() if k != allocator.SWITCH}
    out = subprocess.run([sys.executable, "-m", "scenegen_jax.cli", "models"],
                         env={**env, "LD_PRELOAD": stale}, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "cpu-av2-womd" in out.stdout
