"""Every backend-specific choice, made here and nowhere else.

Between XLA:CPU and accelerators: compiled loops, convolution gradients, how training starts,
each program's compiler options, concurrent calls, vmapped scenes, the device mesh and
multi-process start-up. Between CPUs (`cpu_vendor`, `cpu_has_avx512`, read once): the train
step's convolution library and weight-gradient bands, and Winograd's F(4, 5) forward
convolutions (`model.winograd`). Each is the faster choice on that kind of CPU
(docs/performance.md).

XLA:CPU runs calls from different host threads side by side, so concurrent calls on parts of
a batch fill the cores one call leaves idle during its serial operations; accelerators run
one batched call at a time.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh

# Steps per iteration of the compiled step loop (`lax.scan`'s unroll): on accelerators 4 runs
# about as fast as the fully unrolled window and compiles many times faster.
STEP_LOOP_UNROLL = 4


DATA_AXIS = "data"  # the mesh axis a batch is sharded along


def on_cpu() -> bool:
    """Whether JAX's default backend is XLA:CPU."""
    return jax.default_backend() == "cpu"


def cpu_cores() -> int:
    """CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def free_memory_bytes() -> int:
    """Bytes free for a program's buffers on the first local device: its allocator's limit
    less what it holds (`memory_stats`: accelerators), else the host's available memory
    (MemAvailable in /proc/meminfo, else its physical memory: XLA:CPU)."""
    stats = jax.local_devices()[0].memory_stats() or {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def default_workers() -> int:
    """Concurrent calls by default: one per CPU core on CPU, 1 on accelerators."""
    return cpu_cores() if on_cpu() else 1


def default_parallel() -> int:
    """Scenes the sampler vmaps together by default: 1 on CPU, all on accelerators."""
    return 1 if on_cpu() else 2**31 - 1


def compiled_window_loop() -> bool:
    """Whether the unroll's windows run as a compiled loop (everywhere but XLA:CPU)."""
    return not on_cpu()


def weight_gradient_bands() -> tuple[int, int] | None:
    """(above, rows): convolutions over more than `above` rows take their weight gradient
    summed over bands of at most `rows` rows (`model.layers.conv`); None: never (accelerators
    keep their own).

    XLA:CPU through YNNPACK (AMD with AVX-512): (128, 64), since its weight gradient slows
    down on large rasters but banding costs time at grid 128. Through Eigen
    (`train_eigen_convolutions`): (32, 32), since bands speed its train step up at every grid
    and 32 rows is at or near the fastest height (docs/performance.md)."""
    if not on_cpu():
        return None
    return (32, 32) if train_eigen_convolutions() else (128, 64)


def compiled_step_loop(differentiated: bool = True) -> bool:
    """Whether a window's steps run as a compiled loop (`likelihood.unroll`): everywhere but
    in a differentiated unroll (the train step) on XLA:CPU. On an accelerator an unrolled
    window compiles for minutes. On XLA:CPU the unrolled train step runs faster, while the
    scorer (no gradient) runs as fast as a loop and compiles in about half the time."""
    return not (on_cpu() and differentiated)


def explicit_conv_gradients() -> bool:
    """Whether the model writes its convolutions' gradients in the form XLA:CPU's convolution
    library takes (`model.layers.conv`): on XLA:CPU where a differentiated unroll runs a
    compiled loop (only where tests patch in the accelerators' loops). XLA:CPU canonicalises
    autodiff's convolution forms only outside loops; inside one they become plain loops, an
    order of magnitude slower."""
    return on_cpu() and (compiled_window_loop() or compiled_step_loop())


# XLA:CPU's compile-time preset: fewer LLVM optimisations of its generated kernels. It
# compiles faster for the same step time, since the heavy work (convolutions, dots) runs in
# libraries either way.
FAST_COMPILE = {"xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE"}


def _unless_flagged(option: str, value) -> dict:
    """`{option: value}` as a compiler option, or nothing where XLA_FLAGS sets that option
    (the test suite's level and emitters, or a user's choice), which the option would
    override."""
    if f"--{option}" in os.environ.get("XLA_FLAGS", ""):
        return {}
    return {option: value}


def _backend_level(level: int) -> dict:
    """XLA:CPU's backend optimisation level as a compiler option (`_unless_flagged`)."""
    return _unless_flagged("xla_backend_optimization_level", level)


def _quickest_compile() -> dict:
    """XLA:CPU's quickest compile for programs that run briefly: backend optimisation level
    0 with its loop emitters instead of its fusion emitters (the test suite's pair,
    conftest.py), each `_unless_flagged`."""
    return {**_backend_level(0), **_unless_flagged("xla_cpu_use_fusion_emitters", False)}


def init_compiler_options() -> dict | None:
    """XLA compiler options for drawing initial parameters: on XLA:CPU `_quickest_compile`
    (the initialisers' random-number kernels run once, so at XLA's default level their
    compile takes most of the initialisation), None on other backends."""
    return _quickest_compile() if on_cpu() else None


def compiled_init(init: Callable[[Any], Any], key) -> Any:
    """`init(key)` compiled with `init_compiler_options`, or traced in place where `key` is a
    tracer (`jax.eval_shape`, an enclosing `jax.jit`): JAX accepts compiler options only on
    a top-level jit."""
    if isinstance(key, jax.core.Tracer):
        return init(key)
    return jax.jit(init, compiler_options=init_compiler_options())(key)


# YNNPACK keeps dots and reductions, and the convolutions go to XLA's Eigen path.
EIGEN_CONVOLUTIONS = {
    "xla_cpu_experimental_ynn_fusion_type": (
        "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT,LIBRARY_FUSION_TYPE_REDUCE"
    ),
}


@functools.cache
def cpu_vendor() -> str:
    """The host CPU's vendor id from /proc/cpuinfo ('GenuineIntel', 'AuthenticAMD'), or ''
    where it cannot be read; read once (every convolution asks while it is traced)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("vendor_id"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


@functools.cache
def cpu_has_avx512() -> bool:
    """Whether the CPU runs AVX-512 (AVX512F), as CPUID tells numpy's kernel dispatch: the
    answer every kernel library gets from CPUID at run time (YNNPACK, oneDNN, LLVM), so a CPU
    whose CPUID hides AVX-512 (`bench/avx2_only.c`) counts as AVX2-only, as it does for them.
    /proc/cpuinfo's flags where numpy's table is missing."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__

        return bool(__cpu_features__["AVX512F"])
    except (ImportError, KeyError):
        try:
            with open("/proc/cpuinfo") as f:
                return any(line.startswith("flags") and "avx512f" in line.split() for line in f)
        except OSError:
            return False


def train_eigen_convolutions() -> bool:
    """Whether the train step's convolutions run through XLA's Eigen path, whose matrix
    products are oneDNN's (else YNNPACK's): on Intel CPUs and on every CPU without AVX-512.
    The weight gradients decide it: on Intel CPUs and on AVX2-only CPUs Eigen's are faster;
    on AMD CPUs with AVX-512 the whole steps tie and YNNPACK compiles faster, so those keep
    YNNPACK (docs/performance.md)."""
    return on_cpu() and (cpu_vendor() == "GenuineIntel" or not cpu_has_avx512())


# Most output tiles (4 x 4 pixels each) of a convolution that Winograd's algorithm takes: one
# 128 x 128 scene (the sampler's every call on CPU, one scene each; the scorer's and the train
# step's at grid 128, B 1). Its products are 64 x tiles x Co floats, 32 MB there. Above it the
# train step runs slower through Winograd (its forward runs twice, with remat) while the scorer
# runs faster; this limit does not tell the two programs apart.
WINOGRAD_MAX_TILES = 1024


def winograd_convolutions(kernel: tuple[int, ...], tiles: int) -> bool:
    """Whether a convolution with this kernel size (kh, kw) and this many 4 x 4 output tiles
    runs its forward pass through Winograd's F(4, 5) (`model.winograd`): the 5 x 5 ones of up
    to `WINOGRAD_MAX_TILES` tiles, on CPUs without AVX-512. There the matrix products run at
    half AVX-512's width and the 6.25x fewer products win; with AVX-512 the transforms' memory
    traffic costs more than the products save (docs/performance.md)."""
    return (on_cpu() and tuple(kernel) == (5, 5) and tiles <= WINOGRAD_MAX_TILES
            and not cpu_has_avx512())


# Runs of more steps than this compile the one-program train step in the background while
# they start on the split one (`train.programs.QuickStartTrainStep`); shorter runs keep the split
# step throughout (its compile saved outweighs its slower steps).
QUICK_START_STEPS = 100


# Steps of a window per pair of programs of the split train step (`likelihood.grads.
# chunk_steps`, `train.programs.SplitTrainStep`): chunks of 5 compile several times faster than
# the whole window and run as fast; chunks of 1 compile faster still but run slower.
SPLIT_CHUNK_STEPS = 5


def quick_start_training() -> bool:
    """Whether training starts on the train step split into programs of a few steps
    (`train.programs.QuickStartTrainStep`): on XLA:CPU, whose one-program step unrolls every
    window and compiles for tens of seconds before the first step. On accelerators the
    windows already run as a compiled loop."""
    return on_cpu()


def train_compiler_options() -> dict | None:
    """XLA compiler options for the train step: `FAST_COMPILE` and backend optimisation level
    1 on XLA:CPU, with `EIGEN_CONVOLUTIONS` where `train_eigen_convolutions`; None (XLA's
    defaults) on other backends. Level 1 compiles faster than the default 2 with steps as
    fast; level 0 compiles faster still but runs the step markedly slower."""
    if not on_cpu():
        return None
    eigen = EIGEN_CONVOLUTIONS if train_eigen_convolutions() else {}
    return {**FAST_COMPILE, **_backend_level(1), **eigen}


def quick_train_compiler_options() -> dict | None:
    """XLA compiler options for train-step programs that run for milliseconds, or only until
    a faster program takes over: `train_compiler_options` with `_quickest_compile`; None on
    other backends. The split step's prologue and epilogue (the optimizer's update) always,
    its chunk programs where faster programs take over after the first step
    (`train.programs.QuickStartTrainStep`), since at this level a chunk program compiles several
    times faster but runs its steps about twice as slowly."""
    return {**train_compiler_options(), **_quickest_compile()} if on_cpu() else None


def sampling_compiler_options() -> dict | None:
    """XLA compiler options for the sampler: backend optimisation level 1 on XLA:CPU, None
    (XLA's defaults) on other backends. Level 1 compiles faster than the default 2 and runs
    as fast; level 0, or the loop emitters, compile faster still but run slower."""
    return _backend_level(1) if on_cpu() else None


def scoring_compiler_options() -> dict | None:
    """XLA compiler options for the scorer (no gradients).

    On XLA:CPU `FAST_COMPILE` with the convolutions through XLA's Eigen path, which runs the
    scorer's forward convolutions faster than YNNPACK; YNNPACK keeps the dots and reductions.
    The sampler keeps YNNPACK's convolutions, which run it faster on AMD CPUs. None (XLA's
    defaults) on other backends.
    """
    if not on_cpu():
        return None
    return {**FAST_COMPILE, **EIGEN_CONVOLUTIONS}


def start_distributed(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> None:
    """Joins a multi-process JAX job (`jax.distributed.initialize`): one process per host, or
    several on one machine. Without arguments JAX finds them itself (SLURM, Open MPI, Cloud
    TPU; the coordinator also from JAX_COORDINATOR_ADDRESS); given, they run anywhere.
    Afterwards `jax.devices()` lists every process's devices and `make_mesh` spans them all.
    """
    if (num_processes is None) != (process_id is None):
        raise ValueError("--num-processes and --process-id go together")
    if process_id is not None and not 0 <= process_id < num_processes:
        raise ValueError(f"--process-id {process_id}: need 0 <= id < {num_processes}")
    jax.distributed.initialize(
        coordinator_address=coordinator, num_processes=num_processes, process_id=process_id
    )


def is_main_process() -> bool:
    """Whether this is the process that writes shared files and draws progress bars."""
    return jax.process_index() == 0


def contiguous_part(n: int, index: int, count: int) -> range:
    """Part `index` of `count` of n items in order: equal parts, the first n mod count of
    them one item longer."""
    size, extra = divmod(n, count)
    start = index * size + min(index, extra)
    return range(start, start + size + (index < extra))


def process_share(n: int) -> range:
    """This process's contiguous share of n items (scenes to score or sample); all of them
    with one process."""
    return contiguous_part(n, jax.process_index(), jax.process_count())


def sync_processes(name: str) -> None:
    """Waits until every process reaches the barrier `name` (nothing with one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def make_mesh(devices=None) -> Mesh:
    """A 1-D mesh with a `data` axis over all (or the given) devices; with several
    processes, every process's devices."""
    devices = np.asarray(jax.devices() if devices is None else devices)
    return Mesh(devices, (DATA_AXIS,))


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
