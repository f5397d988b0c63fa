"""The cache's vector maps: real frames (Argoverse 2 sensor val, womd_mini GPUDrive JSON) read
back as their readers gave them, elements shared by the frames of a scenario, map stores
stacked over shards and unions, damaged map files and old raster caches refused by name."""

from __future__ import annotations

import collections
import json
import os
import shutil

import numpy as np
import pytest

from scenegen_jax.config import get_config
from scenegen_jax.data import map_store as M
from scenegen_jax.data.cache import cached_scene, load_cache, prepare_command
from scenegen_jax.data.cache_layout import CACHE_VERSION
from scenegen_jax.data.cache_write import CacheWriter, encode_frame, write_cache
from scenegen_jax.data.prepare import prepare
from scenegen_jax.data.sources import read_file, source_files, source_spec
from scenegen_jax.data.union import load_union
from scenegen_jax.vector_map import Lane, RoadLine, VectorMap, rotation_matrix, se2_pose

CPU = get_config("cpu")
MAP_FILES = (M.POINTS_FILE, M.INDEX_FILE, M.ELEMENTS_FILE)
CACHE_FILES = ("meta.json", "actors.npz", *MAP_FILES)


def map_differences(a: VectorMap, b: VectorMap, atol: float = 1e-6) -> list[str]:
    """Where two maps differ: element counts and order, lane types, marks, intersection
    flags, the data set, and points beyond `atol` m; [] when they match. Lane ids and links
    are not compared (the cache does not store them)."""
    diffs = []

    def close(p, q) -> bool:
        p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
        return p.shape == q.shape and bool(np.all(np.abs(p - q) <= atol))

    for name in ("lanes", "crosswalks", "drivable_areas", "lines"):
        if len(getattr(a, name)) != len(getattr(b, name)):
            diffs.append(f"{name}: {len(getattr(a, name))} != {len(getattr(b, name))}")
    if diffs:
        return diffs
    for i, (p, q) in enumerate(zip(a.lanes, b.lanes, strict=True)):
        for f in ("lane_type", "left_mark", "right_mark", "is_intersection"):
            if getattr(p, f) != getattr(q, f):
                diffs.append(f"lanes[{i}].{f}: {getattr(p, f)!r} != {getattr(q, f)!r}")
        if not (close(p.left, q.left) and close(p.right, q.right)):
            diffs.append(f"lanes[{i}] boundaries")
    for name in ("crosswalks", "drivable_areas"):
        for i, (p, q) in enumerate(zip(getattr(a, name), getattr(b, name), strict=True)):
            if not close(p, q):
                diffs.append(f"{name}[{i}]")
    for i, (p, q) in enumerate(zip(a.lines, b.lines, strict=True)):
        if p.mark != q.mark or not close(p.points, q.points):
            diffs.append(f"lines[{i}]")
    if a.dataset != b.dataset:
        diffs.append(f"dataset: {a.dataset!r} != {b.dataset!r}")
    return diffs


def _frames(kind: str, root: str, split: str, stride: int, files: int):
    """(frames, frames per file) of the first `files` files of a source."""
    spec = source_spec(kind, root, split, stride)
    frames, per_file = [], []
    for path in source_files(spec)[:files]:
        got = read_file(spec, path)[0]
        frames += got
        per_file.append(len(got))
    return spec, frames, per_file


@pytest.fixture(scope="module")
def real(tmp_path_factory, data_root, womd_root):
    """Caches at the cpu config of the Argoverse 2 sensor val log (every 10th frame) and of 4
    womd_mini GPUDrive JSON val scenes (every 10th step), with the frames written."""
    root = tmp_path_factory.mktemp("real_maps")
    out = {}
    for name, args in (
        ("av2", ("av2", data_root, "val", 10, 1)),
        ("womd", ("womd_json", os.path.join(womd_root, "gpudrive_json"), "val", 10, 4)),
    ):
        spec, frames, per_file = _frames(*args)
        path = str(root / name)
        write_cache(frames, path, CPU, collections.Counter(), source=spec)
        out[name] = (path, frames, per_file)
    return out


@pytest.mark.parametrize("name", ["av2", "womd"])
def test_real_maps_read_back_as_the_reader_gave_them(real, name):
    path, frames, _ = real[name]
    cache = load_cache(path)
    assert len(cache) == len(frames) and cache.meta["version"] == CACHE_VERSION
    assert sum(len(f.map.lanes) for f in frames) > 100  # real maps, not empty ones
    for i, frame in enumerate(frames):
        vmap, actors, ego = cached_scene(cache, i, CPU)
        assert map_differences(vmap, frame.map) == [], (i, frame.scene_id)
        assert vmap.dataset == frame.map.dataset != ""
    for i in (0, -1):  # a negative index counts from the end, as for arrays
        assert map_differences(cache.map_store.frame_map(i), frames[i].map) == []
    with pytest.raises(IndexError, match=f"{path}: scene index {len(frames)} out of range"):
        cache.map_store.frame_map(len(frames))


def test_the_frames_of_a_scenario_share_its_elements(real):
    """Every element is stored once: far fewer elements and points than the frames hold, and
    each file's frames (one scenario) hold its elements. (Argoverse 2 sensor frames share
    none: their reader moves the map into the ego frame by the 3D pose's rotation, not by
    the planar `city_from_ego`, so a lane's world points differ by millimetres from frame to
    frame.)"""
    path, frames, per_file = real["womd"]
    cache = load_cache(path)
    store = cache.map_store
    held = int(store.count.sum())
    assert held == sum(len(M.frame_elements(f.map)) for f in frames)
    assert store.stored_elements() * 3 < held, (store.stored_elements(), held)
    held_points = sum(int(store.elements["count"][store.index[a : a + n]].sum())
                      for a, n in zip(store.start, store.count, strict=True))
    assert len(store.points) * 3 < held_points
    # Frames of one file share; a multi-frame file's frames hold few elements of their own.
    bounds = np.cumsum([0, *per_file])
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b - a < 2:
            continue
        ids = [set(store.index[store.start[i] : store.start[i] + store.count[i]].tolist())
               for i in range(a, b)]
        assert len(set.union(*ids)) < sum(map(len, ids))
    with open(os.path.join(path, "meta.json")) as f:
        vocab = json.load(f)["map_vocab"]
    assert set(vocab) == {"lane_type", "mark", "dataset"}
    assert {lane.lane_type for f in frames for lane in f.map.lanes} == set(vocab["lane_type"])


def test_cache_files_and_bytes_per_frame(real):
    """Map arrays of the layout's dtypes, and the womd cache at most 50 KB per frame (the
    raster canvases of version 4 took 265 KB per frame at this config)."""
    path, frames, _ = real["womd"]
    assert sorted(os.listdir(path)) == sorted(CACHE_FILES)
    points = np.load(os.path.join(path, M.POINTS_FILE), mmap_mode="r", allow_pickle=False)
    index = np.load(os.path.join(path, M.INDEX_FILE), mmap_mode="r", allow_pickle=False)
    assert isinstance(points, np.memmap) and points.dtype == np.int32 and points.shape[1] == 2
    assert index.dtype == np.int32
    total = sum(os.path.getsize(os.path.join(path, n)) for n in CACHE_FILES)
    assert total / len(frames) < 50_000


def test_quantised_points_keep_their_place():
    rng = np.random.default_rng(0)
    world = np.array([4.5e5, 4.1e6]) + rng.uniform(-300.0, 300.0, (50, 2))  # UTM-sized
    anchor, scale, q = M.quantise(world)
    assert scale == M.POINT_QUANTUM_M and q.dtype == np.int32
    assert np.abs(anchor + scale * q - world).max() <= scale / 2 + 1e-9
    far = np.array([[0.0, 0.0], [5e3, -7e3]])  # beyond int32 at the quantum: a coarser scale
    anchor, scale, q = M.quantise(far)
    assert scale > M.POINT_QUANTUM_M and np.abs(anchor + scale * q - far).max() < 1e-5
    anchor, scale, q = M.quantise(np.zeros((0, 2)))
    assert q.shape == (0, 2)


def _lane(xs, y, mark="SOLID_WHITE", lane_type="VEHICLE", inter=False, lane_id=0):
    xs = np.asarray(xs, np.float64)
    return Lane(id=lane_id, lane_type=lane_type, left=np.stack([xs, xs * 0 + y + 1.75], 1),
                right=np.stack([xs, xs * 0 + y - 1.75], 1), left_mark=mark,
                right_mark="DASHED_WHITE", is_intersection=inter)


def _hand_frame(scene_id, pose, world_map):
    """A frame without actors whose map is `world_map` seen from the ego at `pose`."""
    from scenegen_jax.frame import Frame

    inv = np.linalg.inv(pose)
    return Frame(scene_id=scene_id, source="hand", cls=np.zeros(0, np.int32),
                 position=np.zeros((0, 2)), size=np.zeros((0, 2)), heading=np.zeros(0),
                 velocity=np.zeros((0, 2)), track_id=np.zeros(0, str),
                 ego_velocity=np.zeros(2), ego_size=np.array([1.95, 4.9]),
                 map=world_map.transform(inv[:2, :2], inv[:2, 2]), city_from_ego=pose)


def test_elements_are_keyed_by_kind_attributes_and_points(tmp_path):
    """Frames seen from other poses share equal elements; an element that differs in an
    attribute or by more than the key's 1e-4 m is its own; a map listing one element twice
    keeps both places; the elements come back in their order."""
    base = VectorMap(
        lanes=(_lane([0, 10, 20], 0.0), _lane([0, 10, 20], 0.0, inter=True),
               _lane([0, 10, 20], 0.0, mark="DASHED_YELLOW"), _lane([0, 10, 20], 3.5)),
        crosswalks=(np.array([[5.0, -2], [7, -2], [7, 2], [5, 2]]),) * 2,
        drivable_areas=(np.array([[-5.0, -9], [30, -9], [30, 9], [-5, 9]]),),
        lines=(RoadLine(np.array([[0.0, 5.5], [20, 5.5]]), "ROAD_EDGE"),
               RoadLine(np.array([[0.0, 5.5], [20, 5.5]]), "SOLID_YELLOW")),
        dataset="waymo",
    )
    moved = VectorMap(lanes=(_lane([0, 10, 20], 3.5 + 2e-4),), dataset="av2")
    poses = [se2_pose(1234.5, -678.9, 0.3), se2_pose(1240.0, -670.0, 2.9),
             se2_pose(-50.0, 20.0, -1.2)]
    frames = [_hand_frame("s/0", poses[0], base), _hand_frame("s/1", poses[1], base),
              _hand_frame("s/2", poses[2], moved)]
    write_cache(frames, str(tmp_path), CPU, collections.Counter())
    store = load_cache(str(tmp_path)).map_store
    # 4 lanes, 1 crosswalk, 1 area, 2 lines once; the moved lane is new.
    assert store.stored_elements() == 9
    assert store.count.tolist() == [9, 9, 1]
    assert store.index[:9].tolist() == store.index[9:18].tolist() == [0, 1, 2, 3, 4, 4, 5, 6, 7]
    assert store.index[4] == store.index[5]  # the crosswalk listed twice
    for i, frame in enumerate(frames):
        assert map_differences(store.frame_map(i), frame.map) == []
    assert store.frame_map(2).dataset == "av2"


def test_a_frame_rotated_by_its_pose_reads_in_its_ego_frame(tmp_path):
    """The stored world map is the frame's map under `city_from_ego`: a lane ahead of the ego
    stays ahead whatever the ego's heading and place."""
    ahead = VectorMap(lanes=(_lane([5, 15], 0.0),))
    frames = []
    for k, theta in enumerate((0.0, 1.0, -2.5)):
        pose = se2_pose(100.0 * k, -30.0 * k, theta)
        frame = _hand_frame(f"r/{k}", pose, ahead.transform(rotation_matrix(theta),
                                                            pose[:2, 2]))
        np.testing.assert_allclose(frame.map.lanes[0].left, ahead.lanes[0].left, atol=1e-9)
        frames.append(frame)
    write_cache(frames, str(tmp_path), CPU, collections.Counter())
    store = load_cache(str(tmp_path)).map_store
    for i in range(3):
        assert map_differences(store.frame_map(i), ahead) == []
    assert store.stored_elements() == 3  # one place per frame in the world


def test_stacked_stores_read_each_frame_from_its_own_cache(real, womd_root, tmp_path):
    """Shards read as one cache and unions of caches give each frame the map its own cache
    gives it, on both sides of every boundary."""
    spec = source_spec("womd_json", os.path.join(womd_root, "gpudrive_json"), "val", 30)
    out = tmp_path / "sharded"
    for i in range(3):
        prepare(spec, str(out), CPU, workers=1, shard=(i, 3))
    shards = [load_cache(str(out / f"shard-{i:05d}-of-00003")) for i in range(3)]
    sharded = load_cache(str(out))
    pairs = [(s, j) for s in shards for j in range(len(s))]
    assert len(sharded) == len(pairs) > 6
    for i, (shard, j) in enumerate(pairs):
        assert map_differences(sharded.map_store.frame_map(i),
                               shard.map_store.frame_map(j), atol=0.0) == []
        np.testing.assert_array_equal(sharded.city_from_ego[i], shard.city_from_ego[j])
    # A union of the sharded cache and the two real ones: three levels of stacking.
    (a, frames_a, _), (b, frames_b, _) = real["av2"], real["womd"]
    union = load_union([a, str(out), b], CPU)
    assert len(union) == len(frames_a) + len(pairs) + len(frames_b)
    for i, frame in enumerate(frames_a):
        assert map_differences(union.map_store.frame_map(i), frame.map) == []
    for i, (shard, j) in enumerate(pairs):
        got = cached_scene(union, len(frames_a) + i, CPU)[0]
        assert map_differences(got, shard.map_store.frame_map(j), atol=0.0) == []
    for i, frame in enumerate(frames_b):
        k = len(frames_a) + len(pairs) + i
        assert map_differences(union.map_store.frame_map(k), frame.map) == []
    with pytest.raises(IndexError, match="out of range"):
        union.map_store.frame_map(len(union))


# ---------------------------------------------------------------------------- damage


def _copy(src: str, dst) -> str:
    """A copy of cache `src` in `dst`: its map files copied (to be damaged), the rest linked."""
    dst.mkdir()
    for name in CACHE_FILES:
        if name in MAP_FILES:
            shutil.copy(os.path.join(src, name), dst / name)
        else:
            os.symlink(os.path.join(src, name), dst / name)
    return str(dst)


@pytest.mark.parametrize("name, keep", [(M.POINTS_FILE, 0.5), (M.POINTS_FILE, 0.0),
                                        (M.INDEX_FILE, 0.5), (M.ELEMENTS_FILE, 0.5)])
def test_truncated_map_files_are_named(real, tmp_path, name, keep):
    path = _copy(real["womd"][0], tmp_path / "cut")
    with open(os.path.join(path, name), "r+b") as f:
        f.truncate(int(os.path.getsize(os.path.join(path, name)) * keep))
    field = {M.POINTS_FILE: "field map_points: unreadable",
             M.INDEX_FILE: "field map_index: unreadable",
             M.ELEMENTS_FILE: "unreadable map elements"}[name]
    with pytest.raises(ValueError, match=rf"^{os.path.join(path, name)}: {field} .*re-run"):
        load_cache(path)


def _rewrite_npz(path: str, **changes) -> None:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    for k, change in changes.items():
        arrays[k] = change(arrays[k])
    np.savez(path, **arrays)


def _set(i, value):
    def change(a):
        a = a.copy()
        a[i] = value
        return a
    return change


@pytest.mark.parametrize("file, change, says", [
    (M.INDEX_FILE, lambda a, e: _set(7, e)(a), r"field map_index: entry 7 is (\d+), beyond the"),
    (M.INDEX_FILE, lambda a, e: _set(0, -1)(a), r"field map_index: entry 0 is -1"),
    (M.INDEX_FILE, lambda a, e: a.astype(np.float32), r"field map_index: float32"),
    (M.POINTS_FILE, lambda a, e: a.astype(np.float64), r"field map_points: float64 .*int32"),
    (M.POINTS_FILE, lambda a, e: a[:, :1], r"field map_points: int32 \(\d+, 1\)"),
    (M.ELEMENTS_FILE, {"start": lambda a: _set(3, 10**9)(a)},
     r"field start: element 3: outside the \d+ points"),
    (M.ELEMENTS_FILE, {"count": lambda a: _set(-1, 10**9)(a)},
     r"field count: element \d+: reaches beyond"),
    (M.ELEMENTS_FILE, {"kind": lambda a: _set(2, 9)(a)}, r"field kind: element 2: not a kind"),
    (M.ELEMENTS_FILE, {"anchor": lambda a: _set(1, np.nan)(a)},
     r"field anchor: element 1: NaN, inf"),
    (M.ELEMENTS_FILE, {"scale": lambda a: _set(0, 0.0)(a)}, r"field scale: element 0: not"),
    (M.ELEMENTS_FILE, {"lane_type": lambda a: np.where(a >= 0, 99, a).astype(a.dtype)},
     r"field lane_type: element 0: not a code of .*meta.json map_vocab.lane_type"),
    (M.ELEMENTS_FILE, {"mark": lambda a: a[:, 0]}, r"field mark: int32 \(\d+,\), expected "
     r"integer \(\d+, 2\)"),
    (M.ELEMENTS_FILE, {"split": lambda a: a + 10**6}, r"field split: element 0: not a lane"),
    ("actors.npz", {"map_count": lambda a: _set(-1, 10**9)(a)},
     r"field map_count: scene \d+: reaches beyond the \d+ entries of map_index.npy"),
    ("actors.npz", {"dataset": lambda a: a + 1}, r"field dataset: scene 0: not a code"),
    ("actors.npz", {"city_from_ego": lambda a: a * 0}, r"field city_from_ego: scene 0: not an "
     r"SE\(2\) pose"),
    ("actors.npz", {"city_from_ego": _set((2, 0, 2), 1e300)}, r"field city_from_ego: scene 2: "
     r"not an SE\(2\) pose"),
])
def test_damaged_map_arrays_name_the_file_and_field(real, tmp_path, file, change, says):
    path = _copy(real["womd"][0], tmp_path / "bad")
    target = os.path.join(path, file)
    if file == "actors.npz":
        os.remove(target)
        shutil.copy(os.path.join(real["womd"][0], file), target)
    if file.endswith(".npz"):
        _rewrite_npz(target, **change)
    else:
        count = len(load_cache(real["womd"][0]).map_store.elements["kind"])
        np.save(target, change(np.load(target), count), allow_pickle=False)
    with pytest.raises(ValueError, match=rf"^{target}: {says}"):
        load_cache(path)


def test_elements_out_of_order_are_named_when_read(real, tmp_path):
    path = _copy(real["womd"][0], tmp_path / "order")
    target = os.path.join(path, M.INDEX_FILE)
    index = np.load(target)
    index[:2] = index[:2][::-1].copy()
    kinds = load_cache(real["womd"][0]).map_store.elements["kind"]
    first_line = int(np.flatnonzero(kinds[index] == M.LINE)[0])
    index[0], index[first_line] = index[first_line], index[0]
    np.save(target, index)
    cache = load_cache(path)
    with pytest.raises(ValueError, match=rf"^{target}: field map_index: scene 0: elements not "
                       "in the order lanes, crosswalks, drivable areas, lines"):
        cache.map_store.frame_map(0)


def test_a_raster_cache_is_refused_with_the_command_that_rewrites_it(tmp_path):
    old = tmp_path / "old"
    old.mkdir()
    meta = {"version": 4, "scene_ids": ["a"], "config": json.loads(
                get_config("cpu", grid_size=48).to_json()),
            "source": {"kind": "av2", "root": "/data/av 2", "split": "train", "stride": 5}}
    (old / "meta.json").write_text(json.dumps(meta))
    np.save(old / "maps.npy", np.zeros((1, 2, 2, 3), np.float16))
    want = (f"scenegen prepare --source av2 --root '/data/av 2' --split train --stride 5 "
            f"--config cpu --set grid_size=48 --out {old}")
    assert prepare_command(str(old), meta) == want
    with pytest.raises(ValueError, match=rf"^{old / 'meta.json'}: field version: 4: the cache "
                       r"holds raster canvases \(maps.npy\) of an older scenegen") as e:
        load_cache(str(old))
    assert str(e.value).endswith(f"rewrite it with `{want}`")
    # Version 3, a shard, no recorded config: the shard's --shard and its parent as --out.
    shard = tmp_path / "c" / "shard-00001-of-00004"
    shard.mkdir(parents=True)
    (shard / "meta.json").write_text(json.dumps({
        "version": 3, "scene_ids": [], "source": {"kind": "womd_json", "root": "/w",
                                                  "split": None, "stride": 10,
                                                  "shard": [1, 4]}}))
    with pytest.raises(ValueError, match=r"field version: 3: .*`scenegen prepare --source "
                       rf"womd_json --root /w --stride 10 --shard 1/4 --out {tmp_path / 'c'}`"):
        load_cache(str(shard))
    (shard / "meta.json").write_text(json.dumps({"version": 4, "scene_ids": []}))
    with pytest.raises(ValueError, match=r"--source '<source kind>' --root '<data root>'"):
        load_cache(str(shard))
    (shard / "meta.json").write_text(json.dumps({"version": 7, "scene_ids": []}))
    with pytest.raises(ValueError, match=r"field version: 7, this scenegen reads \[5, 6\]"):
        load_cache(str(shard))


# ---------------------------------------------------------------------------- writing


def test_writing_over_a_cache_replaces_it_whole(real, tmp_path):
    """A writer that stops before `close` leaves the cache that was there as it was, and no
    temporary file; a completed one replaces it, and a raster maps.npy of an older cache."""
    path, frames, _ = real["womd"]
    dst = tmp_path / "c"
    shutil.copytree(path, dst)
    np.save(dst / "maps.npy", np.zeros((1, 2, 2, 3), np.float16))
    before = {n: (dst / n).read_bytes() for n in CACHE_FILES}
    with pytest.raises(KeyboardInterrupt), CacheWriter(str(dst), CPU) as writer:
        for frame in frames[:3]:
            writer.add(encode_frame(frame, CPU))
        assert any(n.startswith(M.POINTS_FILE) and n.endswith(".tmp")
                   for n in os.listdir(dst))
        raise KeyboardInterrupt
    assert sorted(os.listdir(dst)) == sorted([*CACHE_FILES, "maps.npy"])
    assert {n: (dst / n).read_bytes() for n in CACHE_FILES} == before
    write_cache(frames[:3], str(dst), CPU, collections.Counter())
    assert sorted(os.listdir(dst)) == sorted(CACHE_FILES)
    cache = load_cache(str(dst))
    assert len(cache) == 3
    for i in range(3):
        assert map_differences(cache.map_store.frame_map(i), frames[i].map) == []


def test_the_element_table_forgets_the_oldest_keys(real, tmp_path, monkeypatch):
    """Memory stays bounded: beyond SHARED_ELEMENTS keys the oldest are forgotten and their
    elements stored again, and every frame still reads back whole."""
    from scenegen_jax.data import cache_write

    path, frames, _ = real["womd"]
    monkeypatch.setattr(cache_write._ElementTable, "SHARED_ELEMENTS", 50)
    write_cache(frames, str(tmp_path), CPU, collections.Counter())
    store = load_cache(str(tmp_path)).map_store
    assert store.stored_elements() > load_cache(path).map_store.stored_elements()
    for i, frame in enumerate(frames):
        assert map_differences(store.frame_map(i), frame.map) == []
