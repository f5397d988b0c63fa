"""The process's C heap: tcmalloc in place of glibc's malloc where it is installed.

XLA:CPU allocates a call's temporaries afresh at every call, gigabytes for the train step
at the paper's grid. glibc's malloc maps each allocation above 32 MiB with `mmap` and unmaps
it on `free`, so every call faults all of those pages in again, in kernel time taken from the
cores that run the step. tcmalloc keeps freed pages for the next call, which makes large steps
faster, the more so the dearer the host's page faults (docs/performance.md).

A process's allocator is fixed when it starts, so the `scenegen` command (and `bench/`'s
timing of ours) starts itself again once, at once, with the library in LD_PRELOAD
(`reexec_with_tcmalloc`): found under its Debian/Ubuntu name (`apt install
libtcmalloc-minimal4`) or given as SCENEGEN_MALLOC=/path/to/libtcmalloc_minimal.so;
SCENEGEN_MALLOC=system keeps glibc's. A Python session that imports scenegen_jax keeps the
allocator it started with: start it as `LD_PRELOAD=libtcmalloc_minimal.so.4 python`.

Only the standard library here: this runs before jax is imported.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from collections.abc import Mapping, Sequence

SWITCH = "SCENEGEN_MALLOC"  # "system": glibc's; a path: that tcmalloc; unset: find one
LIBRARY = "tcmalloc_minimal"  # gperftools' allocator without its profilers
# tcmalloc writes a line to stderr for every allocation above this (default 1 GiB); a big
# batch's temporaries are such allocations, and nothing is wrong with them.
QUIET = {"TCMALLOC_LARGE_ALLOC_REPORT_THRESHOLD": str(2**62)}


def find_tcmalloc(env: Mapping[str, str]) -> str | None:
    """The tcmalloc library to preload: SCENEGEN_MALLOC's path, else the linker's
    libtcmalloc_minimal (its soname, which LD_PRELOAD looks up as the linker does); None
    when SCENEGEN_MALLOC=system, off Linux, or none is installed."""
    choice = env.get(SWITCH, "")
    if choice.lower() in ("system", "glibc", "off"):
        return None
    if choice:
        if not os.path.isfile(choice):
            raise FileNotFoundError(f"{SWITCH}={choice}: no such file (a tcmalloc library, "
                                    "or `system` for glibc's malloc)")
        if any(c in choice for c in " \t:"):  # LD_PRELOAD splits its list at these
            raise ValueError(f"{SWITCH}={choice}: LD_PRELOAD cannot hold a path with a space "
                             "or a colon; link the library from a path without them")
        return choice
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.util.find_library(LIBRARY)
    except OSError:
        # CPython's search runs the compiler and reads ld.so's complaint about a missing
        # LD_PRELOAD library as a path to open (a stale `LD_PRELOAD=.../libtcmalloc_minimal.so.4`
        # on a machine without it): none found, so the system's malloc.
        return None


def preload_env(env: Mapping[str, str]) -> dict[str, str] | None:
    """`env` with tcmalloc first in LD_PRELOAD, or None: nothing to preload, or it is there
    already (so a process started with it never starts itself again)."""
    library = find_tcmalloc(env)
    preloaded = env.get("LD_PRELOAD", "").replace(":", " ").split()
    if library is None or library in preloaded or any(
            os.path.basename(p).startswith("libtcmalloc") for p in preloaded):
        return None
    return {**QUIET, **env, "LD_PRELOAD": " ".join([library, *preloaded])}


def reexec_with_tcmalloc(argv: Sequence[str] | None = None) -> None:
    """Starts this process again with tcmalloc preloaded (`os.execve`: same pid, same
    arguments, nothing of this process kept) when `preload_env` finds one to add; else
    returns. Call it first thing, before any heavy import: it costs one interpreter start."""
    env = preload_env(os.environ)
    if env is not None:
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, list(argv or sys.orig_argv), env)


def active() -> str:
    """'tcmalloc' when it serves this process's malloc, else 'system'."""
    on_tcmalloc = hasattr(ctypes.CDLL(None), "MallocExtension_ReleaseFreeMemory")
    return "tcmalloc" if on_tcmalloc else "system"


def release_freed_memory() -> None:
    """Hands freed heap pages back to the OS: tcmalloc's `ReleaseFreeMemory`, glibc's
    `malloc_trim` (a no-op where neither is found).

    Compiling the train step leaves the compiler's freed memory resident (hundreds of MiB at
    grid 128); returned before the first step, it does not add to the step's peak.
    """
    try:
        if active() == "tcmalloc":
            ctypes.CDLL(None).MallocExtension_ReleaseFreeMemory()
        else:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
