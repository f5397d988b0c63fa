"""Shared fixtures: the real Argoverse 2 mini logs in ../shared, read in place."""

from __future__ import annotations

import collections
import os
import shutil
import tempfile

import pytest
from hypothesis import HealthCheck, settings

# Hypothesis profiles of the fuzz tests. `make test`: the same 25 inputs per test on every run;
# `make fuzz` (HYPOTHESIS_PROFILE=fuzz): 200 new ones per test on each run (a failure prints
# the blob that reproduces it).
_FUZZ_COMMON = dict(
    deadline=None,
    database=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile("default", max_examples=25, derandomize=True, **_FUZZ_COMMON)
settings.register_profile("fuzz", max_examples=200, derandomize=False, **_FUZZ_COMMON)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DATA_ROOT = os.path.normpath(os.path.join(REPO, "..", "shared", "data", "av2_sensor_mini"))
WOMD_ROOT = os.path.normpath(os.path.join(REPO, "..", "shared", "data", "womd_mini"))
FORECAST_ROOT = os.path.normpath(
    os.path.join(REPO, "..", "shared", "data", "av2_forecasting_mini"))


def pytest_configure(config):
    """XLA's lowest backend optimisation level for every program the suite compiles, and
    XLA:CPU's older loop emitters in place of its fusion emitters, unless XLA_FLAGS is set
    (`XLA_FLAGS= make test` runs XLA's defaults): the same HLO, so the same operations in the
    same order, with less LLVM optimisation of the generated kernels. The suite's programs run
    briefly, so the compile time saved outweighs the slower kernels; at this level the loop
    emitters compile the small train step faster than the fusion emitters and run it as fast.

    One persistent compilation cache for this run, shared by the xdist workers and the
    CLI subprocesses (they inherit the environment; JAX reads JAX_COMPILATION_CACHE_DIR when
    it is imported): a program compiled by one test is loaded by the next that builds the
    same one, however short its compile (JAX's default keeps only programs that took 1 s or
    more). The cache
    starts empty and is removed at the end, so the suite times a fresh machine and never
    reads or writes the user's ~/.cache."""
    if "XLA_FLAGS" not in os.environ:
        os.environ["XLA_FLAGS"] = ("--xla_backend_optimization_level=0 "
                                   "--xla_cpu_use_fusion_emitters=false")
    if hasattr(config, "workerinput") or "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return  # an xdist worker (inherits the controller's), or set by the caller
    path = tempfile.mkdtemp(prefix="scenegen-test-jax-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = path
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    config._scenegen_compile_cache = path


# The modules that take longest, slowest first (by `--durations=0` on two workers; the rest
# are short): each xdist worker takes the next whole module when it is nearly done with its last, in
# this order, then the rest in file order, so that the short ones even out the end.
SLOWEST_MODULES = ("test_unroll.py", "test_stress.py", "test_train_step.py",
                   "test_distributed.py",
                   "test_recipe.py", "test_train_loop.py", "test_api.py",
                   "test_warm_start.py", "test_sampling_network.py",
                   "test_womd_json.py", "test_scoring.py", "test_checkpoint.py",
                   "test_multi_cache.py", "test_av2.py", "test_network.py", "test_keys.py",
                   "test_fuzz.py", "test_distributions.py")


def pytest_collection_modifyitems(config, items):
    def rank(item):
        name = item.path.name
        return SLOWEST_MODULES.index(name) if name in SLOWEST_MODULES else len(SLOWEST_MODULES)

    items.sort(key=rank)  # stable: tests keep their order within a module


def pytest_unconfigure(config):
    path = getattr(config, "_scenegen_compile_cache", None)
    if path:
        shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="session")
def data_root() -> str:
    if not os.path.isdir(DATA_ROOT):
        pytest.fail(f"real data missing: {DATA_ROOT} (../shared must sit beside the repo)")
    return DATA_ROOT


@pytest.fixture(scope="session")
def womd_root() -> str:
    """The real Waymo scenes (GPUDrive JSON and ScenarioNet pickles), read in place."""
    if not os.path.isdir(WOMD_ROOT):
        pytest.fail(f"real data missing: {WOMD_ROOT} (../shared must sit beside the repo)")
    return WOMD_ROOT


@pytest.fixture(scope="session")
def forecast_root() -> str:
    """The real Argoverse 2 motion-forecasting scenarios, read in place."""
    if not os.path.isdir(FORECAST_ROOT):
        pytest.fail(f"real data missing: {FORECAST_ROOT} (../shared must sit beside the repo)")
    return FORECAST_ROOT


@pytest.fixture(scope="session")
def all_frames(data_root):
    """Every frame of the four logs, by split, with the drop counters."""
    from scenegen_jax.data.sources import read_frames, source_spec

    out = {}
    for split in ("train", "val"):
        drops = collections.Counter()
        out[split] = (list(read_frames(source_spec("av2", data_root, split, 1), drops)), drops)
    return out


@pytest.fixture(scope="session")
def tiny_train_cache(tmp_path_factory, data_root):
    """A tiny-config cache of every 8th train frame (written once per session)."""
    from scenegen_jax.config import get_config
    from scenegen_jax.data.cache import load_cache
    from scenegen_jax.data.cache_write import write_cache
    from scenegen_jax.data.sources import read_frames, source_spec

    out = str(tmp_path_factory.mktemp("cache_tiny"))
    drops = collections.Counter()
    frames = read_frames(source_spec("av2", data_root, "train", 8), drops)
    write_cache(frames, out, get_config("tiny"), drops)
    return load_cache(out)


def _run_dir(request, tmp_path_factory, name: str):
    """A folder shared by this run's xdist workers (beside their own temporary folders,
    named by the run's id), or this process's own without xdist."""
    worker = getattr(request.config, "workerinput", None)
    if worker is None:
        return tmp_path_factory.mktemp(name)
    path = tmp_path_factory.getbasetemp().parent / f"{name}-{worker['testrunuid']}"
    path.mkdir(exist_ok=True)
    return path


@pytest.fixture(scope="session")
def overfit_run(request, tmp_path_factory, tiny_train_cache):
    """(losses of every step, final parameters) of 100 steps of the small config's
    one-program train step on its two small scenes, from `init_state`: test_train checks
    that the loss falls, test_scoring scores with the parameters. Run once per suite: the
    first worker to ask trains under a lock and writes the result (msgpack and JSON); the
    others read it."""
    import fcntl
    import json

    import jax
    from flax import serialization
    from small import CFG, two_small_scenes

    from scenegen_jax.likelihood.batch import gather_batch
    from scenegen_jax.train.step import init_state, make_train_step

    path = _run_dir(request, tmp_path_factory, "overfit-run")
    with open(path / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (path / "losses.json").exists():
            batch = jax.device_put(
                gather_batch(tiny_train_cache, two_small_scenes(tiny_train_cache), CFG.grid))
            state, step, losses = init_state(CFG), make_train_step(CFG), []
            for _ in range(100):
                state, stats = step(state, batch)
                losses.append(float(stats["loss"]))
            (path / "params.msgpack").write_bytes(
                serialization.msgpack_serialize(jax.device_get(state.params)))
            (path / "losses.json").write_text(json.dumps(losses))  # last: marks it complete
    params = serialization.msgpack_restore((path / "params.msgpack").read_bytes())
    return json.loads((path / "losses.json").read_text()), params
