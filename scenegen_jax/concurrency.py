"""Concurrent calls of compiled functions, for throughput on CPU.

XLA:CPU runs calls made from different host threads side by side. One call at a time leaves
a core idle whenever the program runs a small serial operation between its multi-threaded
convolutions; concurrent calls on parts of a batch fill the cores (on 2 cores: sampling 1.2x
faster, scoring 1.05-1.1x; bench/README.md). Accelerators run one batched call at a time.
"""

from __future__ import annotations

import concurrent.futures
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import jax


def default_workers() -> int:
    """Concurrent calls by default: one per CPU core on CPU, 1 on accelerators."""
    if jax.default_backend() != "cpu":
        return 1
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def concurrent_map(fn: Callable[[Any], Any], items: Iterable, workers: int) -> Iterator:
    """fn(item) for each item, in order, with up to `workers` calls running at once (threads).

    Each result is waited for inside its thread: a call that returned before its computation
    ran would leave the computations to run one after another.
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")

    def call(item):
        return jax.block_until_ready(fn(item))

    items = list(items)
    if workers == 1 or len(items) <= 1:
        yield from map(call, items)
        return
    with concurrent.futures.ThreadPoolExecutor(min(workers, len(items))) as pool:
        yield from pool.map(call, items)
