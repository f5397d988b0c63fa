"""Fuzzed input surface: damaged copies of real inputs end in a clean error or a clean read.

Every reader here gets real inputs (Waymo GPUDrive JSON and ScenarioNet pickles, an
Argoverse 2 map, a config, given actors from a real scene, a cache written from real
frames) damaged by hypothesis: truncated at random offsets, bytes flipped, fields dropped,
values replaced by other types, arrays with other dtypes or shapes, NaN and inf. Each read
must end either in success or in one of the errors the CLI prints as one line
(`scenegen_jax.cli.main`: ValueError, FileNotFoundError, IndexError) whose message names the
file (or the given source); never another exception type and never a hang. A successful read
must hold only finite values.

The default profile runs a fixed, derandomized set of 25 examples per test (part of
`make test`); HYPOTHESIS_PROFILE=fuzz (`make fuzz`) draws 200 new ones per test on each run.
The counts per reader (clean errors + successful reads) are printed at the end of the module
(`pytest -s`). The damaged copies live in pytest tmp dirs only.
"""

from __future__ import annotations

import collections
import contextlib
import json
import math
import os
import pickle
import shutil
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import DATA_ROOT, WOMD_ROOT
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scenegen_jax.config import Config, get_config
from scenegen_jax.data import scenarionet as SN
from scenegen_jax.data import womd_json as W
from scenegen_jax.data.av2 import vector_map_from_json
from scenegen_jax.data.cache import cached_scene, load_cache, write_cache
from scenegen_jax.sampling.export import actors_from_records
from scenegen_jax.scene import CLASS_NAMES

_COMMON = dict(
    deadline=None,
    database=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
# `make test`: the same 25 damaged inputs per test on every run.
settings.register_profile("default", max_examples=25, derandomize=True, **_COMMON)
# `make fuzz`: 200 new damaged inputs per test on each run (the failure blob reproduces one).
settings.register_profile("fuzz", max_examples=200, derandomize=False, **_COMMON)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

CLEAN_ERRORS = (ValueError, FileNotFoundError, IndexError)  # what cli.main prints as one line
HANG_S = 60  # one damaged input must be read (or refused) well within this

WOMD_JSON = os.path.join(WOMD_ROOT, "gpudrive_json", "val", "74e892ddfe3b9b8.json")  # G1, SDC
WOMD_JSON_N1 = os.path.join(WOMD_ROOT, "gpudrive_json", "val", "tfrecord-00068-of-01000_277.json")
WOMD_PKLS = [
    os.path.join(WOMD_ROOT, "scenarionet", "val", name)
    for name in ("8799c31b5be1f312.pkl", "6f85f27e0243fc10.pkl")  # S3 and S2 layouts
]

# Examples run per reader in this process, by (test, "error" | "read"), printed at the end.
EXAMPLES: collections.Counter = collections.Counter()


# ---------------------------------------------------------------- harness


class Hang(Exception):
    """A read took longer than HANG_S."""


@contextlib.contextmanager
def _no_hang(seconds: int = HANG_S) -> Iterator[None]:
    def on_alarm(signum, frame):
        raise Hang(f"no result after {seconds} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _outcome(read: Callable[[], Any], name: str, test: str) -> Any:
    """The result of `read()`, or None after a clean error naming `name`; anything else fails."""
    try:
        with _no_hang():
            result = read()
    except CLEAN_ERRORS as e:
        assert name in str(e), f"error does not name {name!r}: {type(e).__name__}: {e}"
        EXAMPLES[test, "error"] += 1
        return None
    EXAMPLES[test, "read"] += 1
    return result


def _assert_finite(arrays: dict[str, Any], where: str) -> None:
    for key, value in arrays.items():
        arr = np.asarray(value, np.float64)
        assert np.all(np.isfinite(arr)), f"{where}: a successful read holds NaN/inf in {key}"


# ---------------------------------------------------------------- mutations

# Values of other types, and the non-finite floats, that a field may be replaced by.
ODD_VALUES = [
    None,
    True,
    0,
    -1,
    10**400,
    1.5,
    math.nan,
    math.inf,
    -math.inf,
    "",
    "x",
    "12",
    [],
    [1, 2],
    [None],
    {},
    {"x": 1},
]


def _children(node: Any) -> list:
    if isinstance(node, dict):
        return list(node.keys())
    if isinstance(node, list | tuple):
        return list(range(len(node)))
    return []


def _replace_at(node: Any, path: list, change: Callable[[Any, Any], Any]) -> Any:
    """A copy of `node` with `change(parent, key)` applied at `path`; only the containers on
    the path are copied (shallow), so the real data is never modified."""
    if isinstance(node, tuple):
        node = list(node)
    else:
        node = node.copy()
    key = path[0]
    if len(path) == 1:
        return change(node, key)
    node[key] = _replace_at(node[key], path[1:], change)
    return node


def _mutate_array(arr: np.ndarray, draw) -> Any:
    """An ndarray with another dtype or shape, NaN/inf, or something that is no array."""
    op = draw(st.sampled_from(["dtype", "shape", "nonfinite", "empty", "other"]))
    if op == "dtype":
        dtype = draw(st.sampled_from(["int8", "int64", "float16", "bool", "complex64", "U3",
                                      "object"]))
        with np.errstate(all="ignore"):
            return arr.astype(dtype)
    if op == "shape":
        kind = draw(st.sampled_from(["flat", "extra_axis", "transpose", "half", "scalar"]))
        if kind == "flat":
            return arr.reshape(-1)
        if kind == "extra_axis":
            return arr[..., None]
        if kind == "transpose":
            return arr.T
        if kind == "half":
            return arr[: len(arr) // 2] if arr.ndim else arr
        return arr.reshape(-1)[:1].reshape(()) if arr.size else np.float64(1.0)
    if op == "nonfinite":
        out = np.array(arr, dtype=np.float64 if arr.dtype.kind not in "fc" else arr.dtype)
        if out.size:
            i = draw(st.integers(0, out.size - 1))
            out.reshape(-1)[i] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
        return out
    if op == "empty":
        return arr[:0] if arr.ndim else np.zeros(0)
    return draw(st.sampled_from(ODD_VALUES))


def _mutate_tree(root: Any, draw) -> Any:
    """`root` (nested dicts/lists/arrays) with one random field dropped, retyped, made
    non-finite, truncated or (arrays) given another dtype or shape."""
    depth = draw(st.integers(1, 7))
    path: list = []
    node = root
    for _ in range(depth):
        keys = _children(node)
        if not keys:
            break
        key = keys[draw(st.integers(0, len(keys) - 1))]
        path.append(key)
        node = node[key]
    if not path:
        return draw(st.sampled_from(ODD_VALUES))
    op = draw(st.sampled_from(["drop", "replace", "nonfinite", "truncate", "wrap", "array"]))

    def change(parent: Any, key: Any) -> Any:
        value = parent[key]
        if op == "drop":
            del parent[key]
        elif op == "nonfinite":
            parent[key] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        elif op == "truncate" and isinstance(value, list | tuple | np.ndarray | str):
            parent[key] = value[: draw(st.integers(0, max(len(value) - 1, 0)))]
        elif op == "wrap":
            parent[key] = [value]
        elif op == "array" and isinstance(value, np.ndarray):
            parent[key] = _mutate_array(value, draw)
        else:
            parent[key] = draw(st.sampled_from(ODD_VALUES))
        return parent

    return _replace_at(root, path, change)


def _mutations(root: Any, draw) -> Any:
    for _ in range(draw(st.integers(1, 3))):
        root = _mutate_tree(root, draw)
    return root


def _damage_bytes(raw: bytes, draw) -> bytes:
    """`raw` truncated at a random offset, or with a few bytes flipped / overwritten."""
    op = draw(st.sampled_from(["truncate", "flip", "overwrite"]))
    if op == "truncate":
        return raw[: draw(st.integers(0, len(raw) - 1))]
    out = bytearray(raw)
    # Damage near the start (headers, opcodes) as often as anywhere else.
    for _ in range(draw(st.integers(1, 4))):
        limit = draw(st.sampled_from([min(len(out), 512), len(out)]))
        i = draw(st.integers(0, limit - 1))
        out[i] = out[i] ^ draw(st.integers(1, 255)) if op == "flip" else draw(st.integers(0, 255))
    return bytes(out)


# ---------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@pytest.fixture(scope="module", autouse=True)
def _report_counts():
    yield
    tests = sorted({t for t, _ in EXAMPLES})
    print("\nfuzz examples per reader (clean errors + successful reads): " + ", ".join(
        f"{t}={EXAMPLES[t, 'error'] + EXAMPLES[t, 'read']} ({EXAMPLES[t, 'error']} + "
        f"{EXAMPLES[t, 'read']})" for t in tests))


def _load_json(path: str) -> Any:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def _check_womd_frames(result: Any, where: str) -> None:
    if result is None:
        return
    frames, dropped = result
    assert isinstance(dropped, collections.Counter)
    for fr in frames:
        _assert_finite(
            {k: getattr(fr, k) for k in ("position", "size", "heading", "velocity",
                                         "ego_velocity", "ego_size", "city_from_ego")},
            where,
        )


# ---------------------------------------------------------------- Waymo GPUDrive JSON


WOMD_JSON_DATA = {p: None for p in (WOMD_JSON, WOMD_JSON_N1)}


def _womd_json(path: str) -> Any:
    if WOMD_JSON_DATA[path] is None:
        WOMD_JSON_DATA[path] = _load_json(path)
    return WOMD_JSON_DATA[path]


@given(data=st.data())
def test_womd_json_damaged_text(scratch, data):
    real = Path(WOMD_JSON_N1).read_bytes()
    path = scratch / "womd_text.json"
    path.write_bytes(_damage_bytes(real, data.draw))
    result = _outcome(lambda: W.read_file(path, 30), str(path), "womd_json_text")
    _check_womd_frames(result, str(path))


@given(data=st.data(), which=st.sampled_from([WOMD_JSON, WOMD_JSON_N1]))
def test_womd_json_damaged_fields(scratch, data, which):
    damaged = _mutations(_womd_json(which), data.draw)
    path = scratch / "womd_fields.json"
    path.write_text(json.dumps(damaged))  # NaN / Infinity written as JSON's extensions
    result = _outcome(lambda: W.read_file(path, 30), str(path), "womd_json_fields")
    _check_womd_frames(result, str(path))


# ---------------------------------------------------------------- ScenarioNet pickles


def _read_pickle_frames(path: Path) -> Any:
    scenario = SN.read_scenario(path)
    return SN.frames_from_scenario(scenario, str(path), stride=50)


def _check_imported(result: Any, where: str) -> None:
    if result is None:
        return
    for imported in result:
        fr = imported.frame
        _assert_finite(
            {k: getattr(fr, k) for k in ("position", "size", "heading", "velocity",
                                         "ego_velocity", "ego_size", "city_from_ego")},
            where,
        )


@given(data=st.data(), which=st.sampled_from(WOMD_PKLS))
def test_scenarionet_damaged_bytes(scratch, data, which):
    path = scratch / "damaged_bytes.pkl"
    path.write_bytes(_damage_bytes(Path(which).read_bytes(), data.draw))
    result = _outcome(lambda: _read_pickle_frames(path), str(path), "scenarionet_bytes")
    _check_imported(result, str(path))


SCENARIOS: dict[str, Any] = {}


@given(data=st.data(), which=st.sampled_from(WOMD_PKLS))
def test_scenarionet_damaged_fields(scratch, data, which):
    if which not in SCENARIOS:
        SCENARIOS[which] = SN.read_scenario(which)
    damaged = _mutations(SCENARIOS[which], data.draw)
    path = scratch / "damaged_fields.pkl"
    with open(path, "wb") as f:  # the standard pickle of plain dicts and numpy arrays
        pickle.dump(damaged, f, protocol=4)
    result = _outcome(lambda: _read_pickle_frames(path), str(path), "scenarionet_fields")
    _check_imported(result, str(path))


# ---------------------------------------------------------------- Argoverse 2 map JSON


def _av2_map_path() -> str:
    split = os.path.join(DATA_ROOT, "val")
    log = sorted(os.listdir(split))[0]
    map_dir = os.path.join(split, log, "map")
    return os.path.join(map_dir, next(n for n in sorted(os.listdir(map_dir))
                                      if n.startswith("log_map_archive_")))


AV2_MAP: dict[str, Any] = {}


@given(data=st.data())
def test_av2_map_damaged_fields(data):
    if not AV2_MAP:
        AV2_MAP["path"] = _av2_map_path()
        AV2_MAP["data"] = _load_json(AV2_MAP["path"])
    path = AV2_MAP["path"]
    # Round trip through JSON text: the reader sees what json.load would give it.
    damaged = json.loads(json.dumps(_mutations(AV2_MAP["data"], data.draw)))
    result = _outcome(lambda: vector_map_from_json(damaged, path), path, "av2_map")
    if result is not None:
        vmap, dropped = result
        assert isinstance(dropped, collections.Counter)
        for lane in vmap.lanes:
            _assert_finite({"left": lane.left, "right": lane.right}, path)
        for poly in (*vmap.crosswalks, *vmap.drivable_areas):
            _assert_finite({"polygon": poly}, path)


# ---------------------------------------------------------------- config JSON

CONFIG_SOURCE = "runs/x/config.json"


def _check_config(result: Any) -> None:
    if result is not None:
        assert isinstance(result, Config)
        # A config that loads is one that could have been constructed: all fields valid.
        assert Config(**{f: getattr(result, f) for f in result.__dataclass_fields__}) == result


@given(data=st.data())
def test_config_damaged_text(data):
    raw = get_config("tiny").to_json().encode()
    text = _damage_bytes(raw, data.draw).decode("utf-8", errors="replace")
    result = _outcome(lambda: Config.from_json(text, CONFIG_SOURCE), CONFIG_SOURCE,
                      "config_text")
    _check_config(result)


@given(data=st.data())
def test_config_damaged_fields(data):
    d = json.loads(get_config("tiny").to_json())
    text = json.dumps(_mutations(d, data.draw))
    result = _outcome(lambda: Config.from_json(text, CONFIG_SOURCE), CONFIG_SOURCE,
                      "config_fields")
    _check_config(result)


# ---------------------------------------------------------------- given actors

GIVEN: dict[str, Any] = {}
GIVEN_WHERE = "given.jsonl:1"


def _given_records() -> list[dict]:
    """Records of real actors of a WOMD frame that `actors_from_records` accepts together."""
    if "records" not in GIVEN:
        cfg = get_config("tiny")
        frames, _ = W.read_file(WOMD_JSON_N1, 1000)
        fr = frames[0]
        kept: list[dict] = []
        for i in range(fr.num_actors):
            rec = {
                "class": CLASS_NAMES[int(fr.cls[i])],
                "x": float(fr.position[i, 0]),
                "y": float(fr.position[i, 1]),
                "width": float(fr.size[i, 0]),
                "length": float(fr.size[i, 1]),
                "heading": float(fr.heading[i]),
                "vx": float(fr.velocity[i, 0]),
                "vy": float(fr.velocity[i, 1]),
            }
            try:
                actors_from_records([*kept, rec], cfg, GIVEN_WHERE)
            except ValueError:
                continue  # outside the region, or overlapping one kept already
            kept.append(rec)
        assert len(kept) >= 3, "too few real actors to fuzz the given-actor reader"
        GIVEN["cfg"], GIVEN["records"] = cfg, kept
    return GIVEN["records"]


@given(data=st.data())
def test_given_actors_damaged_records(data):
    records = _given_records()
    damaged = json.loads(json.dumps(_mutations(records, data.draw)))
    result = _outcome(lambda: actors_from_records(damaged, GIVEN["cfg"], GIVEN_WHERE),
                      GIVEN_WHERE, "given_actors")
    if result is not None:
        result.validate("given")


# ---------------------------------------------------------------- caches


@pytest.fixture(scope="module")
def small_cache(tmp_path_factory) -> str:
    """A tiny-config cache of four frames of a real WOMD scene."""
    out = str(tmp_path_factory.mktemp("fuzz_cache") / "cache")
    frames, drops = W.read_file(WOMD_JSON_N1, 30)
    write_cache(frames[:4], out, get_config("tiny"), collections.Counter(drops))
    load_cache(out)  # the undamaged cache reads
    return out


CACHE_FILES = ("meta.json", "maps.npy", "actors.npz")


def _read_cache(path: str) -> Any:
    cache = load_cache(path)
    cfg = get_config("tiny")
    for i in range(len(cache)):
        cached_scene(cache, i, cfg)
    return cache


def _fresh_copy(src: str, scratch: Path) -> str:
    dst = scratch / "cache_copy"
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    return str(dst)


@given(data=st.data(), name=st.sampled_from(CACHE_FILES))
def test_cache_damaged_bytes(small_cache, scratch, data, name):
    path = _fresh_copy(small_cache, scratch)
    target = Path(path) / name
    target.write_bytes(_damage_bytes(target.read_bytes(), data.draw))
    result = _outcome(lambda: _read_cache(path), path, "cache_bytes")
    if result is not None:
        result.actors.validate("cache")


@given(data=st.data(), name=st.sampled_from(["meta.json", "actors.npz"]))
def test_cache_damaged_fields(small_cache, scratch, data, name):
    path = _fresh_copy(small_cache, scratch)
    target = Path(path) / name
    if name == "meta.json":
        target.write_text(json.dumps(_mutations(_load_json(str(target)), data.draw)))
    else:
        with np.load(target, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        damaged = _mutations(arrays, data.draw)
        if isinstance(damaged, dict):
            arrays = {k: v for k, v in damaged.items()
                      if isinstance(v, np.ndarray) and v.dtype != object}
        np.savez(target, **arrays)
    result = _outcome(lambda: _read_cache(path), path, "cache_fields")
    if result is not None:
        result.actors.validate("cache")
