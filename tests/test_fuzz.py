"""Fuzzed input surface: damaged copies of real inputs end in a clean error or a clean read.

Every reader here gets real inputs (Waymo GPUDrive JSON and ScenarioNet pickles, an
Argoverse 2 map and a log's feather tables, a config, given actors from a real scene, a cache
written from real frames, the checkpoints of a short training run) damaged by hypothesis:
truncated at random offsets, bytes flipped, fields or columns dropped, values replaced by
other types, arrays with other dtypes or shapes, NaN and inf, duplicated rows, files deleted or
emptied. Each read must end either in success or in one of the errors the CLI prints as one
line (`scenegen_jax.cli.main`: ValueError, FileNotFoundError, IndexError) whose message names
the file (or the given source); never another exception type and never a hang. A successful
read must hold only finite values; an Argoverse 2 log's rows are each an actor or a counted
drop, and a checkpoint restores bit for bit what was saved (the newest step or the one
before it).

The default profile (conftest.py) runs a fixed, derandomized set of 25 examples per test (part
of `make test`); HYPOTHESIS_PROFILE=fuzz (`make fuzz`) draws 200 new ones per test on each run.
The counts per reader (clean errors + successful reads) are printed at the end of the module
(`pytest -s`). The damaged copies live in pytest tmp dirs only.
"""

from __future__ import annotations

import collections
import contextlib
import glob
import json
import math
import os
import pickle
import shutil
import signal
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
from conftest import DATA_ROOT, WOMD_ROOT
from hypothesis import given
from hypothesis import strategies as st

from scenegen_jax.checkpoint import CHECKSUM_FILE
from scenegen_jax.config import Config, get_config
from scenegen_jax.data import scenarionet as SN
from scenegen_jax.data import womd_json as W
from scenegen_jax.data.av2 import ANNOTATION_COLUMNS, POSE_COLUMNS
from scenegen_jax.data.av2_map import vector_map_from_json
from scenegen_jax.data.cache import cached_scene, load_cache
from scenegen_jax.data.cache_write import write_cache
from scenegen_jax.data.map_store import ELEMENTS_FILE, INDEX_FILE, POINTS_FILE
from scenegen_jax.data.sources import read_file as read_source_file
from scenegen_jax.data.sources import source_spec
from scenegen_jax.frame import MAX_SIZE_M
from scenegen_jax.sampling.export import actors_from_records
from scenegen_jax.scene import CLASS_NAMES
from scenegen_jax.train.loop import load_trained, train

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
    notes = {t: "".join(f", {n} {kind}" for (u, kind), n in sorted(EXAMPLES.items())
                        if u == t and kind not in ("error", "read")) for t in tests}
    print("\nfuzz examples per reader (clean errors + successful reads): " + ", ".join(
        f"{t}={EXAMPLES[t, 'error'] + EXAMPLES[t, 'read']} ({EXAMPLES[t, 'error']} + "
        f"{EXAMPLES[t, 'read']}{notes[t]})" for t in tests))


def _load_json(path: str) -> Any:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


FRAME_ARRAYS = ("position", "size", "heading", "velocity", "ego_velocity", "ego_size",
                "city_from_ego")


def _assert_frame_finite(frame, where: str) -> None:
    _assert_finite({k: getattr(frame, k) for k in FRAME_ARRAYS}, where)


def _check_frames(result: Any, where: str) -> None:
    """A successful read of (frames, drops): counted drops and finite frame arrays."""
    if result is None:
        return
    frames, dropped = result
    assert isinstance(dropped, collections.Counter)
    for fr in frames:
        _assert_frame_finite(fr, where)


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
    _check_frames(result, str(path))


@given(data=st.data(), which=st.sampled_from([WOMD_JSON, WOMD_JSON_N1]))
def test_womd_json_damaged_fields(scratch, data, which):
    damaged = _mutations(_womd_json(which), data.draw)
    path = scratch / "womd_fields.json"
    path.write_text(json.dumps(damaged))  # NaN / Infinity written as JSON's extensions
    result = _outcome(lambda: W.read_file(path, 30), str(path), "womd_json_fields")
    _check_frames(result, str(path))


# ---------------------------------------------------------------- ScenarioNet pickles


def _read_pickle_frames(path: Path) -> Any:
    scenario = SN.read_scenario(path)
    return SN.frames_from_scenario(scenario, str(path), stride=50)


def _check_imported(result: Any, where: str) -> None:
    if result is None:
        return
    for imported in result:
        fr = imported.frame
        _assert_frame_finite(fr, where)


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


CACHE_FILES = ("meta.json", "actors.npz", POINTS_FILE, INDEX_FILE, ELEMENTS_FILE)


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


# ---------------------------------------------------------------- Argoverse 2 feather tables

ANN_FILE, POSE_FILE = "annotations.feather", "city_SE3_egovehicle.feather"
AV2_SWEEPS = 4  # sweeps kept of the copied log, so that one read takes well under a second
NUMERIC = {"int64", "double", "float", "int32"}


def _table_copy(src: str, dst: Path, sweeps: int) -> dict[str, pa.Table]:
    """Writes the first `sweeps` annotated sweeps of real log `src` (and the ego poses within
    0.5 s of them) into `dst`, with a link to its map (read in place); returns the tables."""
    ann = feather.read_table(os.path.join(src, ANN_FILE))
    t = ann.column("timestamp_ns").to_numpy()
    kept = np.unique(t)[:sweeps]
    ann = ann.filter(pa.array(np.isin(t, kept)))
    poses = feather.read_table(os.path.join(src, POSE_FILE))
    pt = poses.column("timestamp_ns").to_numpy()
    poses = poses.filter(pa.array((pt >= kept[0] - 500_000_000) & (pt <= kept[-1] + 500_000_000)))
    dst.mkdir(parents=True)
    os.symlink(os.path.join(src, "map"), dst / "map")
    tables = {ANN_FILE: ann, POSE_FILE: poses}
    for name, table in tables.items():
        feather.write_feather(table, dst / name)
    return tables


def _read_av2(log_dir: Path) -> tuple[list, collections.Counter]:
    """What `scenegen prepare --source av2` reads of one log (every sweep)."""
    spec = source_spec("av2", str(log_dir.parent.parent), log_dir.parent.name, stride=1)
    return read_source_file(spec, str(log_dir))


class _Quiet(dict):
    """A fixture's dict that hypothesis prints by name only when a test case fails."""

    def __repr__(self) -> str:
        return f"<{', '.join(self)}>"


@pytest.fixture(scope="module")
def av2_log(data_root, tmp_path_factory) -> dict:
    """The real val log cut to AV2_SWEEPS sweeps: its tables, their file bytes (uncompressed
    and lz4), its read, and the folder in which damaged copies are read."""
    src = sorted(glob.glob(os.path.join(data_root, "val", "*")))[0]
    root = tmp_path_factory.mktemp("fuzz_av2")
    pristine = root / "pristine" / "val" / os.path.basename(src)
    tables = _table_copy(src, pristine, AV2_SWEEPS)
    frames, drops = _read_av2(pristine)
    assert len(frames) == AV2_SWEEPS and sum(f.num_actors for f in frames) > 20
    raw = {}
    for name, table in tables.items():
        for compression in ("uncompressed", "lz4"):
            sink = pa.BufferOutputStream()
            feather.write_feather(table, sink, compression=compression)
            raw[name, compression] = sink.getvalue().to_pybytes()
    damaged = root / "damaged" / "val" / os.path.basename(src)
    damaged.mkdir(parents=True)
    os.symlink(os.path.join(src, "map"), damaged / "map")
    return _Quiet(tables=tables, raw=raw, frames=frames, drops=drops, dir=damaged)


def _row_drops(drops: collections.Counter) -> int:
    """Annotation rows dropped (not map elements, not copies of ego poses)."""
    return sum(n for reason, n in drops.items() if not reason.startswith(("map:", "ego_pose:")))


def _check_av2(result: Any, rows: int | None, where: str) -> None:
    """A successful read holds only finite values, and every annotation row (`rows` in the
    file, when known) is either an actor of a frame or a drop counted by reason."""
    if result is None:
        return
    _check_frames(result, where)
    frames, drops = result
    for fr in frames:
        for lane in fr.map.lanes:
            _assert_finite({"left": lane.left, "right": lane.right}, where)
        assert np.all(fr.size > 0) and np.all(fr.size <= MAX_SIZE_M), where
        assert np.all((fr.heading >= 0) & (fr.heading < 2 * np.pi)), where
        assert fr.cls.shape == fr.track_id.shape == fr.position.shape[:1], where
    if rows is not None:
        in_frames = sum(fr.num_actors for fr in frames)
        assert in_frames + _row_drops(drops) == rows, (
            f"{where}: {rows} rows, {in_frames} actors and {_row_drops(drops)} counted drops")


def _same_frames(a: list, b: list) -> bool:
    if len(a) != len(b):
        return False
    fields = ("cls", "position", "size", "heading", "velocity", "track_id", "ego_velocity",
              "city_from_ego")
    return all(x.scene_id == y.scene_id and all(np.array_equal(getattr(x, k), getattr(y, k))
                                                for k in fields) for x, y in zip(a, b, strict=True))


@given(data=st.data(), name=st.sampled_from([ANN_FILE, POSE_FILE]),
       compression=st.sampled_from(["uncompressed", "lz4"]))
def test_av2_feather_damaged_bytes(av2_log, data, name, compression):
    log_dir = av2_log["dir"]
    for other in (ANN_FILE, POSE_FILE):
        raw = av2_log["raw"][other, compression]
        (log_dir / other).write_bytes(_damage_bytes(raw, data.draw) if other == name else raw)
    path = str(log_dir / name)
    result = _outcome(lambda: _read_av2(log_dir), path, "av2_feather_bytes")
    # Flipped bytes in an uncompressed table may change a value and nothing else: the file
    # is then as valid as any, so only the row count is known when the table is intact.
    rows = av2_log["tables"][ANN_FILE].num_rows if name == POSE_FILE else None
    _check_av2(result, rows, path)


# Columns of one type that may replace a column: values no reader can take as numbers.
ODD_COLUMNS: list[Callable[[int], pa.Array]] = [
    lambda n: pa.array(["x"] * n),
    lambda n: pa.array(["1.5"] * n),
    lambda n: pa.nulls(n),
    lambda n: pa.nulls(n, pa.float64()),
    lambda n: pa.array([[1.0, 2.0]] * n),
    lambda n: pa.array([b"\x00\xff"] * n),
    lambda n: pa.array([True] * n),
    lambda n: pa.array([{"x": 1.0}] * n),
    lambda n: pa.array(np.zeros(n, "datetime64[ns]")),
]


def _retype(values: np.ndarray, target: str) -> pa.Array:
    """`values` as another type (strings become their lengths when a number is wanted, values
    that convert to nothing become row numbers)."""
    try:
        if target == "str":
            return pa.array(values.astype(str))
        if values.dtype.kind in "OUS":
            values = np.char.str_len(values.astype(str))
        with np.errstate(all="ignore"):
            return pa.array(values.astype(target))
    except (ValueError, TypeError, UnicodeError):  # lists, bytes, structs, nulls
        return pa.array(np.arange(len(values)).astype(target))


def _mutate_table(table: pa.Table, draw) -> tuple[pa.Table, str]:
    """`table` with a column dropped, retyped or replaced, NaN/inf or nulls in a few rows,
    rows duplicated, or no rows; and the name of the change."""
    n = table.num_rows
    op = draw(st.sampled_from(["drop", "dtype", "other_type", "nonfinite", "null",
                               "duplicate", "empty"]))
    if op == "empty" or (n == 0 and op in ("nonfinite", "null", "duplicate")):
        return table.slice(0, 0), "empty"
    if op == "duplicate":
        rows = draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=5))
        order = np.sort(np.r_[np.arange(n), rows], kind="stable")  # copies follow the original
        return table.take(pa.array(order)), "duplicate"
    numeric = [c for c in table.column_names if str(table.schema.field(c).type) in NUMERIC]
    names = numeric if op == "nonfinite" and numeric else table.column_names
    name = draw(st.sampled_from(names))
    i = table.column_names.index(name)
    if op == "drop":
        return table.remove_column(i), f"drop {name}"
    values = table.column(name).to_numpy(zero_copy_only=False)
    if op == "dtype":
        target = draw(st.sampled_from(["int8", "int32", "int64", "float16", "float32", "bool",
                                       "str"]))
        column = _retype(values, target)
    elif op == "other_type":
        column = draw(st.sampled_from(ODD_COLUMNS))(n)
    else:
        rows = draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=3, unique=True))
        if op == "nonfinite":
            values = values.astype(np.float64)
            values[rows] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
            column = pa.array(values)
        else:
            mask = np.zeros(n, bool)
            mask[rows] = True
            column = pa.array(values, mask=mask)
    return table.set_column(i, name, column), f"{op} {name}"


@given(data=st.data(), name=st.sampled_from([ANN_FILE, POSE_FILE]))
def test_av2_feather_damaged_columns(av2_log, data, name):
    log_dir = av2_log["dir"]
    table, changes = av2_log["tables"][name], []
    for _ in range(data.draw(st.integers(1, 3))):
        table, change = _mutate_table(table, data.draw)
        changes.append(change)
    for other in (ANN_FILE, POSE_FILE):
        feather.write_feather(table if other == name else av2_log["tables"][other],
                              log_dir / other)
    path = str(log_dir / name)
    result = _outcome(lambda: _read_av2(log_dir), path, "av2_feather_columns")
    rows = (table if name == ANN_FILE else av2_log["tables"][ANN_FILE]).num_rows
    _check_av2(result, rows, f"{path} ({', '.join(changes)})")
    used = ANNOTATION_COLUMNS if name == ANN_FILE else POSE_COLUMNS
    if result is not None and all(c == "duplicate" or (c.startswith("drop ") and c[5:] not in
                                                       used) for c in changes):
        # Copies of rows and columns the reader does not use change nothing: the frames are
        # the undamaged log's, and each copied row is a counted drop.
        frames, drops = result
        assert _same_frames(frames, av2_log["frames"]), f"{path}: silent change ({changes})"
        extra = drops - av2_log["drops"]
        assert all(r in ("invalid:duplicate_row", "ego_pose:duplicate_row")
                   or r.startswith("category:") for r in extra), extra


# ---------------------------------------------------------------- checkpoints


def _state_leaves(state: Any) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(jax.device_get(state))]


@pytest.fixture(scope="module")
def trained_workdir(tiny_train_cache, tmp_path_factory) -> dict:
    """A workdir of the small test config trained 2 steps (checkpoints at steps 1 and 2),
    the two saved states, and the files of the newest checkpoint (relative to its folder)."""
    from small import CFG

    workdir = tmp_path_factory.mktemp("fuzz_ckpt") / "wd"
    train(CFG, tiny_train_cache.path, str(workdir), 2, save_every=1, log_every=1,
          progress=False)
    states = {step: _state_leaves(load_trained(str(workdir), step)[1]) for step in (1, 2)}
    newest = workdir / "checkpoints" / "2"
    files = sorted(str(p.relative_to(newest)) for p in newest.rglob("*") if p.is_file())
    assert CHECKSUM_FILE in files and len(files) > 3, files
    # Two steps of training changed the parameters: a fallback to step 1 is visible.
    assert not all(np.array_equal(a, b) for a, b in zip(*states.values(), strict=True))
    return _Quiet(dir=workdir, states=states, files=files)


@given(data=st.data(), alone=st.booleans())
def test_checkpoint_damaged_newest_step(trained_workdir, scratch, data, alone):
    """`alone`: step 1 is deleted first, so that a damaged step 2 has nothing to fall back to:
    the clean error, or step 2 as saved where the damage touched nothing it needs."""
    rel = data.draw(st.sampled_from(trained_workdir["files"]))
    op = data.draw(st.sampled_from(["bytes", "delete", "empty"]))
    copy = Path(tempfile.mkdtemp(dir=scratch)) / "wd"  # a fresh path: no cached file handles
    shutil.copytree(trained_workdir["dir"], copy)
    if alone:
        shutil.rmtree(copy / "checkpoints" / "1")
    target = copy / "checkpoints" / "2" / rel
    raw = target.read_bytes()
    if op == "delete":
        target.unlink()
    elif op == "empty" or not raw:
        target.write_bytes(b"")
    else:
        target.write_bytes(_damage_bytes(raw, data.draw))
    where = str(copy / "checkpoints")
    result = _outcome(lambda: load_trained(str(copy)), where, "checkpoint")
    assert result is not None or alone, f"{rel} ({op}): the good step 1 was not restored"
    if result is not None:
        # The newest step if the damage changed nothing it holds, else the previous good one;
        # bit for bit what was saved either way.
        step = int(result[1].step)
        assert step in ((2,) if alone else (1, 2)), step
        EXAMPLES["checkpoint", "fell back to step 1"] += step == 1
        got = _state_leaves(result[1])
        want = trained_workdir["states"][step]
        assert len(got) == len(want)
        for i, (a, b) in enumerate(zip(got, want, strict=True)):
            assert a.dtype == b.dtype and np.array_equal(a, b), (
                f"{rel} ({op}): leaf {i} of step {step} restored with other values")
    shutil.rmtree(copy.parent)
