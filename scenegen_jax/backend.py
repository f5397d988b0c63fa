"""Every backend-specific choice, made here and nowhere else.

What differs between XLA:CPU and accelerators: which loops are compiled (on XLA:CPU the
unrolled window's step runs faster), how convolutions take their gradients (on XLA:CPU
large ones in row bands, and in its library's form inside a differentiated compiled loop,
which runs on XLA:CPU only where the tests run the accelerators' loops), how training
starts (on the train step split into programs of a few steps while the one-program step
compiles), the compiler options of the parameter initialisation, the train step, the scorer
and the sampler, how many calls run at once and how many scenes are vmapped together, and the
device mesh. Also where a multi-process job starts and which process writes. (The host's
allocator, and handing the compiler's freed memory back to the OS: `allocator`.)

What differs between CPUs, read once at start-up (`cpu_vendor` from /proc/cpuinfo,
`cpu_has_avx512` from CPUID): which library runs the train step's convolutions and the row
bands of their weight gradients (Intel, and every CPU without AVX-512: Eigen, 32-row bands;
AMD with AVX-512: YNNPACK, 64-row bands above 128 rows), and how the 5 x 5 convolutions of
up to one 128 x 128 scene run forward (without AVX-512: Winograd's F(4, 5), `model.winograd`;
else directly), all measured (bench/README.md).

Concurrent calls: XLA:CPU runs calls made from different host threads side by side. One call
at a time leaves a core idle whenever the program runs a small serial operation between its
multi-threaded convolutions; concurrent calls on parts of a batch fill the cores (on 2 cores:
sampling 1.2x faster, scoring 1.05-1.1x; bench/README.md). Accelerators run one batched call
at a time.
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

# Steps per iteration of the compiled step loop (`lax.scan`'s unroll). On an H100 (paper
# preset, grid 320, T 25) 4 gave a train step within 1.4 % of the unrolled window's, compiled
# in 26 s instead of 202 s; 1 gave 6.5 % slower in 20 s (bench/README.md).
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
    summed over bands of at most `rows` rows (`model.network.conv`); None: never (accelerators
    keep their own).

    XLA:CPU through YNNPACK (AMD with AVX-512): (128, 64). Its weight gradient at 320 x 320
    ran at a quarter of its speed at 128 x 128 (5 x 5, 32 -> 128, one Zen 4 core: 857 ms,
    240 ms in bands of 64 rows); banded at grid 128 the `paper` step compiled 12 s longer and
    ran 4 % slower (session 23). Through Eigen (`train_eigen_convolutions`): (32, 32); on the
    Xeon of session 24, 2 cores, the `paper` step at grid 128, T 25 took 6.84 s unbanded, 4.45
    s in bands of 64 rows, 4.32 in 32, 4.64 in 16; at grid 320, T 5 8.62 s unbanded, 6.08 /
    5.62 / 5.77 s in bands of 64 / 128 / 32; the `cpu` preset 3.01 -> 2.74 s in bands of 32
    (bench/README.md)."""
    if not on_cpu():
        return None
    return (32, 32) if train_eigen_convolutions() else (128, 64)


def compiled_step_loop(differentiated: bool = True) -> bool:
    """Whether a window's steps run as a compiled loop (`likelihood.unroll`): everywhere but
    in a differentiated unroll (the train step) on XLA:CPU. On an accelerator the unrolled
    window compiled for minutes. On XLA:CPU the unrolled train step runs faster: the `paper`
    step at grid 128, T 25 took 4.34 s against 4.71 s as a loop of 4 steps an iteration,
    which compiled in 8.8 s instead of 35 s (session 32, with `explicit_conv_gradients`).
    The scorer (no gradient) runs as fast or faster as a loop there and compiles in half the
    time: `paper` at grid 128, T 25, B 1 1.15-1.17 against 1.21-1.25 s, first call 3.1
    against 6.5-7.0 s; the shipped `cpu` model's first batch of 8 traced in 0.9 against 2.5 s
    and compiled in 3.1 against 4.7 s (session 34; bench/README.md)."""
    return not (on_cpu() and differentiated)


def explicit_conv_gradients() -> bool:
    """Whether the model writes its convolutions' gradients in the form XLA:CPU's convolution
    library takes (`model.network.conv`): on XLA:CPU where a differentiated unroll runs a
    compiled loop, which happens only where tests patch `compiled_step_loop` or
    `compiled_window_loop` to run the accelerators' loops there. XLA:CPU rewrites the other
    forms of a convolution (those autodiff makes of its gradients) into that one only outside
    loops (its ConvCanonicalization pass visits the entry computation alone); inside a loop it
    emits them as plain loops, 10x slower at the test suite's optimisation level (session 32:
    the `tiny` step's gradient with a compiled step loop ran in 10 s, 0.8 s unrolled)."""
    return on_cpu() and (compiled_window_loop() or compiled_step_loop())


# XLA:CPU's compile-time preset: fewer LLVM optimisations of its generated kernels. The `cpu`
# preset's train step compiled in 32 s instead of 40 s for the same step time (3.35 s, Zen 4);
# the heavy work (convolutions, dots) runs in libraries either way (bench/README.md).
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
    (the initialisers' random-number kernels run once, and compiled at XLA's default level
    they took 4.6 of the 5 s `tiny`'s initialisation took; 1.2 s at level 0 on a Zen 4; on
    a slow Xeon, session 43, `init_state`'s program 2.7-3.0 s at level 0, 2.0 s with the
    loop emitters), None on other backends."""
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
    The weight gradients decide it. Intel Xeon with AVX-512 and AMX, 2 cores (session 24):
    5 x 5, 64 -> 128 at 128 x 128, forward + weight gradient 84 ms through Eigen against 136
    through YNNPACK; the `paper` step 7.41 -> 6.58 s at grid 128, T 25 and 8.75 -> 5.56 s at
    grid 320, T 5. AMD EPYC Zen 4 (session 11): Eigen's weight gradients 2-4x slower than
    YNNPACK's (76 against 35.5 ms for 5 x 5, 32 -> 128). With the gradients in the libraries'
    form and the bands of sessions 24-32, the whole steps tie there within the machine's noise
    (session 39: `paper` at grid 128, T 25 and grid 320, T 5 and T 25; the `cpu` preset), and
    YNNPACK compiles faster, so AMD with AVX-512 keeps it. AVX2 only (that Xeon with AVX-512
    and AMX hidden from CPUID, session 38): the `paper` step at grid 128, T 25 took 6.33 s
    through Eigen against 10.61 s through YNNPACK (the reference: 6.79 s). bench/README.md."""
    return on_cpu() and (cpu_vendor() == "GenuineIntel" or not cpu_has_avx512())


# Most output tiles (4 x 4 pixels each) of a convolution that Winograd's algorithm takes: one
# 128 x 128 scene (the sampler's every call on CPU, one scene each; the scorer's and the train
# step's at grid 128, B 1). Its products are 64 x tiles x Co floats, 32 MB there. Above it,
# AVX2 only (session 41): the train step at grid 320, T 5 took 13.6 s against 12.2 s direct
# (Winograd's forward runs twice there, with remat), while the scorer gained (grid 128, B 8:
# 29.7 -> 17.7 s; grid 320: 22.6 -> 14.0 s, means of two runs); this choice cannot yet tell
# the two apart (bench/README.md).
WINOGRAD_MAX_TILES = 1024


def winograd_convolutions(kernel: tuple[int, ...], tiles: int) -> bool:
    """Whether a convolution with this kernel size (kh, kw) and this many 4 x 4 output tiles
    runs its forward pass through Winograd's F(4, 5) (`model.winograd`): the 5 x 5 ones of up
    to `WINOGRAD_MAX_TILES` tiles, on CPUs without AVX-512. There the matrix products run at
    half AVX-512's width and the 6.25x fewer products win; with AVX-512 the transforms' memory
    traffic costs more than the products save. Intel Xeon with AVX-512 and AMX hidden from
    CPUID (`bench/avx2_only.c`), session 40, alternating: the `paper` scorer at grid 128, T 25,
    B 1 1.18-1.19x faster (3.55 -> 2.99 s, 3.86 -> 3.28 s), its train step as fast (13.80
    against 14.02 s); with AVX-512 a lone 5 x 5, 32 -> 128 forward took 30 ms against 16
    direct. Session 41, the output transform as one matrix product: against the reference,
    batched sampling 2.16-2.29x (was 1.11-1.19x), scoring 1.76-1.95x, the train step
    1.27-1.30x; with AVX-512 still slower than direct (32 -> 128: 80 against 69 ms with the
    sampler's options). Session 49, the input transform as two matrix products: the programs
    compile 2-3x faster (the shipped model's first scoring batch 57.7 -> 17.5-22.3 s), the
    scorer at grid 128 runs about 15 % slower (bench/README.md)."""
    return (on_cpu() and tuple(kernel) == (5, 5) and tiles <= WINOGRAD_MAX_TILES
            and not cpu_has_avx512())


# Runs of more steps than this compile the one-program train step in the background while
# they start on the split one (`train.step.QuickStartTrainStep`); shorter runs keep the split
# step throughout (its compile saved outweighs its slower steps).
QUICK_START_STEPS = 100


# Steps of a window per pair of programs of the split train step (`likelihood.unroll.
# chunk_steps`, `train.step.SplitTrainStep`). One Intel Xeon core, the other busy (session 26):
# a window of 25 steps (`tiny`) compiled as one program in 14.8 s; as chunks of 5, forward 5.1
# and backward 3.4 s (side by side on 2 cores), the window as fast (0.92-0.96 against 0.95 s);
# chunks of 1 compiled in 4.1 + 2.3 s but ran 14 % slower. `cpu` (windows of 20): 16.6 s
# against 6.6 + 4.4 s, 2.86 against 2.97 s a window.
SPLIT_CHUNK_STEPS = 5


def quick_start_training() -> bool:
    """Whether training starts on the train step split into programs of a few steps
    (`train.step.QuickStartTrainStep`): on XLA:CPU, whose one-program step unrolls every
    window and compiles for tens of seconds before the first step (bench/README.md). On
    accelerators the windows already run as a compiled loop."""
    return on_cpu()


def train_compiler_options() -> dict | None:
    """XLA compiler options for the train step: `FAST_COMPILE` and backend optimisation level
    1 on XLA:CPU, with `EIGEN_CONVOLUTIONS` where `train_eigen_convolutions`; None (XLA's
    defaults) on other backends. Level 1 against the default 2, one Zen 4 core, the other
    busy: compile 44-45 -> 39-41 s (`tiny`), 47 -> 43 s (`cpu`), 43 -> 38 s (`paper` at grid
    128, T 25), steps as fast (fastest of 7: 1.89-1.90 against 1.88-1.89 s at `tiny`; medians
    5.8 against 6.3 s at `cpu`, 10.9 against 10.8 s at `paper`); level 0 compiled faster
    still but ran `tiny`'s step 1.7x slower (bench/README.md)."""
    if not on_cpu():
        return None
    eigen = EIGEN_CONVOLUTIONS if train_eigen_convolutions() else {}
    return {**FAST_COMPILE, **_backend_level(1), **eigen}


def quick_train_compiler_options() -> dict | None:
    """XLA compiler options for train-step programs that run for milliseconds, or only until
    a faster program takes over: `train_compiler_options` with `_quickest_compile`; None on
    other backends. The split step's prologue and epilogue (the optimizer's update) always,
    its chunk programs where faster programs take over after the first step
    (`train.step.QuickStartTrainStep`). Slow Intel Xeon (family 6
    model 167, AVX-512 and AMX), 2 cores, session 43, each program compiled alone: `tiny`'s
    prologue 2.4 -> 0.5 s and epilogue 3.3 -> 1.2 s, both still running in 10-30 ms; its
    forward and backward chunks 6.7 + 4.8 -> 1.8 + 1.6 s, but a split step of 2.0 s then
    takes 4.1 s (`cpu`: 10.2 + 7.3 -> 2.6 + 2.5 s; 5.9 -> 12.5 s a step). The loop emitters
    at level 1 compiled `tiny`'s chunks a little faster and `cpu`'s slower, and the
    one-program step 1.7x slower, running slower too (bench/README.md)."""
    return {**train_compiler_options(), **_quickest_compile()} if on_cpu() else None


def sampling_compiler_options() -> dict | None:
    """XLA compiler options for the sampler: backend optimisation level 1 on XLA:CPU, None
    (XLA's defaults) on other backends. Against the default level (2), on one Zen 4 core, the
    first batch of 8 scenes compiles in 17 s instead of 26-28 (`cpu` preset), 17 against 22
    (`tiny`), 31 against 35 (`paper` at grid 128), and runs as fast or faster (1.08-1.16 s
    against 1.25 s a batch at `cpu`; 10.4 s both at `paper`); level 0, or XLA:CPU's loop
    emitters instead of its fusion emitters, compiled faster still but ran 20-70 % slower
    (bench/README.md)."""
    return _backend_level(1) if on_cpu() else None


def scoring_compiler_options() -> dict | None:
    """XLA compiler options for the scorer (no gradients).

    On XLA:CPU its convolutions then run through XLA's Eigen path instead of YNNPACK: the
    backbone's 3 x 3, 32 -> 32 convolution takes 1.7 ms there at 128 x 128 against 3.0 ms,
    the 5 x 5 ones the same; YNNPACK keeps what it runs by default besides convolutions (dots
    and reductions). The train step keeps YNNPACK's convolutions on AMD CPUs with AVX-512
    (`train_eigen_convolutions`), and so does the sampler, which ran 7 % slower with Eigen's
    on a Zen 4 (bench/README.md).
    None (XLA's defaults) on other backends.
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
