"""Scene PyTree conventions, validation and the preprocessing cache."""

from __future__ import annotations

import json
import os

import jax
import numpy as np
import pytest

from scenegen_jax.config import get_config
from scenegen_jax.data.cache import cached_scene, load_cache
from scenegen_jax.data.map_store import ELEMENTS_FILE, INDEX_FILE, POINTS_FILE
from scenegen_jax.raster.jax_map import draw_maps
from scenegen_jax.raster.transform import scene_from_cached
from scenegen_jax.scene import (
    PEDESTRIAN,
    Actors,
    Scene,
    bin_center,
    bin_index,
    canonical_order,
    empty_actors,
    make_ego,
)

CFG = get_config("tiny")
CACHE_FILES = ("meta.json", "actors.npz", POINTS_FILE, INDEX_FILE, ELEMENTS_FILE)


def test_bin_convention_row_major_top_left():
    half = CFG.grid.region_m / 2
    assert int(bin_index(np.array([-half + 0.1, half - 0.1]), CFG.grid)) == 0  # top left
    assert int(bin_index(np.array([half - 0.1, half - 0.1]), CFG.grid)) == CFG.grid.grid_size - 1
    assert (
        int(bin_index(np.array([-half + 0.1, half - CFG.grid.m_per_px - 0.1]), CFG.grid))
        == CFG.grid.grid_size
    )
    for b in (0, 17, 500, CFG.grid.grid_size**2 - 1):
        assert int(bin_index(bin_center(b, CFG.grid), CFG.grid)) == b


def _actors(positions, cls=None):
    n = len(positions)
    a = empty_actors(8)
    a.position[:n] = positions
    a.size[:n] = (2.0, 4.5)
    a.valid[:n] = True
    if cls is not None:
        a.cls[:n] = cls
    return a


def test_canonical_order_sorts_left_right_top_bottom():
    a = _actors([[10.0, -10.0], [-10.0, 10.0], [10.0, 10.0], [-10.0, -10.0]])
    ordered = canonical_order(a, CFG.grid)
    pos = np.asarray(ordered.position)[:4]
    np.testing.assert_allclose(pos, [[-10, 10], [10, 10], [-10, -10], [10, -10]])
    assert np.asarray(ordered.valid).tolist() == [True] * 4 + [False] * 4
    jitted = jax.jit(lambda x: canonical_order(x, CFG.grid))(a)
    np.testing.assert_array_equal(np.asarray(jitted.position), np.asarray(ordered.position))


def test_validate_names_the_field():
    actors = canonical_order(_actors([[1.0, 2.0], [3.0, -4.0]]), CFG.grid)
    ok = Scene(actors=actors, ego=make_ego(CFG.grid.ego_size_m))
    jax.tree.map(np.asarray, ok).validate(CFG.grid)
    bad = _actors([[1.0, 2.0]])
    bad.size[0] = (0.0, 4.0)
    with pytest.raises(ValueError, match=r"^s\.actors\.size: box width and length"):
        Scene(actors=bad, ego=make_ego(CFG.grid.ego_size_m)).validate(CFG.grid, "s")
    bad = _actors([[1.0, np.nan]])
    with pytest.raises(ValueError, match=r"^s\.actors\.position: NaN or inf"):
        Scene(actors=bad, ego=make_ego(CFG.grid.ego_size_m)).validate(CFG.grid, "s")
    far = _actors([[500.0, 0.0]])
    with pytest.raises(ValueError, match=r"^s\.actors\.position: actor outside"):
        Scene(actors=far, ego=make_ego(CFG.grid.ego_size_m)).validate(CFG.grid, "s")
    unordered = _actors([[10.0, -10.0], [-10.0, 10.0]])
    with pytest.raises(ValueError, match=r"^scene\.actors: not in canonical"):  # the default
        Scene(actors=unordered, ego=make_ego(CFG.grid.ego_size_m)).validate(CFG.grid)
    ped = _actors([[1.0, 2.0]], cls=[PEDESTRIAN])
    ped.size[0] = 0.0  # pedestrians have no box
    Scene(actors=ped, ego=make_ego(CFG.grid.ego_size_m)).validate(CFG.grid)


def test_cache_scenes_are_valid_and_complete(tiny_train_cache):
    cache = tiny_train_cache
    assert len(cache) == 3 * 20  # every 8th of the 156 frames of each of the 3 train logs
    for index in range(0, len(cache), 5):
        vmap, actors, ego = cached_scene(cache, index, CFG)
        assert len(vmap.lanes) > 0 and vmap.dataset == "av2"
        scene, overflow = jax.jit(lambda a, e, t: scene_from_cached(a, e, t, CFG.grid))(
            actors, ego, 0.3 * index
        )
        scene = jax.tree.map(np.asarray, scene)
        scene.validate(CFG.grid, where=f"scene {index}")
        assert int(overflow) == 0
        m = np.asarray(draw_maps([vmap], [0.3 * index], CFG.grid))
        assert m.shape == (1, CFG.grid.grid_size, CFG.grid.grid_size, len(CFG.grid.map_channels))
        assert np.isfinite(m).all() and m.any()


def test_cache_summary_and_bad_cache(tiny_train_cache, tmp_path):
    meta = tiny_train_cache.meta
    assert meta["summary"]["scenes"] == len(tiny_train_cache)
    with pytest.raises(FileNotFoundError, match="meta.json"):
        load_cache(str(tmp_path))
    # A cache whose actor file disagrees with meta.json is refused, naming the file.
    src = tiny_train_cache.path
    dst = tmp_path / "broken"
    dst.mkdir()
    for name in CACHE_FILES:
        if name != "actors.npz":
            os.symlink(os.path.join(src, name), dst / name)
    with np.load(os.path.join(src, "actors.npz")) as z:
        arrays = {k: z[k][:-1] for k in z.files}
    np.savez(dst / "actors.npz", **arrays)
    with pytest.raises(ValueError, match="actors.npz"):
        load_cache(str(dst))
    with pytest.raises(ValueError, match="re-run prepare"):
        tiny_train_cache.check_config(get_config("cpu"))
    assert json.loads(json.dumps(meta["summary"]))["actors"]["vehicle"] > 0


def _damaged_copy(src: str, dst, actors=None) -> str:
    """A copy of cache `src` in `dst` whose actor arrays (`actors`: field -> function of the
    array) are rewritten; the rest linked. (Damaged map files: test_map_store.)"""
    dst.mkdir()
    for name in CACHE_FILES:
        if name != "actors.npz":
            os.symlink(os.path.join(src, name), dst / name)
    with np.load(os.path.join(src, "actors.npz")) as z:
        arrays = {k: z[k] for k in z.files}
    for field, damage in (actors or {}).items():
        arrays[field] = damage(arrays[field])
    np.savez(dst / "actors.npz", **arrays)
    return str(dst)


@pytest.mark.parametrize(
    "field, damage, says",
    [
        (
            "cls",
            lambda v: v.astype(np.float32) + 0.5,
            r"field cls: float32 \(60, 98\), expected "
            r"integer \(60, 98\)",
        ),
        ("velocity", lambda v: v.astype(str), r"field velocity: <U\d+ \(60, 98, 2\)"),
        (
            "position",
            lambda v: v[..., 0],
            r"field position: float32 \(60, 98\), expected float "
            r"\(60, 98, 2\)",
        ),
        ("valid", lambda v: v[..., None], r"field valid: bool \(60, 98, 1\)"),
        ("ego_size", lambda v: -v, "field ego_size: sizes must be finite and positive"),
        ("ego_velocity", lambda v: np.full_like(v, np.inf), "field ego_velocity: NaN or inf"),
        ("position", lambda v: v + 1e3, "field position: scene 0 slot 0 lies beyond the canvas"),
    ],
)
def test_damaged_actor_arrays_name_the_field(tiny_train_cache, tmp_path, field, damage, says):
    """Arrays of another dtype or shape, egos of impossible sizes and actors beyond the canvas
    (a cache edited or written by something else) are refused naming the file and field."""
    assert len(tiny_train_cache) == 60 and tiny_train_cache.meta["slots"] == 98
    path = _damaged_copy(tiny_train_cache.path, tmp_path / "c", actors={field: damage})
    with pytest.raises(ValueError, match=rf"^{tmp_path / 'c' / 'actors.npz'}: {says}"):
        load_cache(path)


@pytest.mark.parametrize(
    "name, keep", [("actors.npz", 0.5), (POINTS_FILE, 0.5), (POINTS_FILE, 0.0),
                   (INDEX_FILE, 0.5), (ELEMENTS_FILE, 0.5), ("meta.json", 0.5)]
)
def test_truncated_cache_files_are_named(tiny_train_cache, tmp_path, name, keep):
    """A cache file cut short (a full disk, a killed copy) gives one error naming it."""
    src, dst = tiny_train_cache.path, tmp_path / "cut"
    dst.mkdir()
    for n in CACHE_FILES:
        if n != name:
            os.symlink(os.path.join(src, n), dst / n)
    data = open(os.path.join(src, name), "rb").read()
    (dst / name).write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ValueError, match=f"{dst / name}: "):
        load_cache(str(dst))


def test_overflow_is_counted():
    cfg = CFG.replace(max_actors=3)
    a = _actors([[x, 0.0] for x in (-30.0, -10.0, 5.0, 20.0, 30.0)])
    scene, overflow = scene_from_cached(a, make_ego(cfg.grid.ego_size_m), 0.0, cfg.grid)
    assert int(overflow) == 2 and int(np.sum(scene.actors.valid)) == 3
    assert isinstance(scene.actors, Actors)


def test_sharded_prepare_reads_as_the_whole_cache(tiny_train_cache, data_root, tmp_path):
    """Two `prepare --shard I/2` jobs make one cache equal to the unsharded one (the same
    frames: every 8th step of the train logs); a missing or foreign shard is an error."""
    import shutil

    from test_map_store import map_differences

    from scenegen_jax.data.cache_layout import ACTOR_FIELDS
    from scenegen_jax.data.prepare import prepare
    from scenegen_jax.data.sources import source_spec
    from scenegen_jax.data.union import load_union

    spec = source_spec("av2", data_root, "train", 8)
    out = tmp_path / "sharded"
    for i in (1, 0):  # any order, any machine
        prepare(spec, str(out), get_config("tiny"), workers=1, shard=(i, 2))
    assert sorted(os.listdir(out)) == ["shard-00000-of-00002", "shard-00001-of-00002"]
    sharded = load_cache(str(out))
    assert sharded.scene_ids == tiny_train_cache.scene_ids
    assert [s["scenes"] for s in sharded.meta["shards"]] == [40, 20]  # files 2 + 1
    for k in ACTOR_FIELDS:
        want = getattr(tiny_train_cache.actors, k)
        np.testing.assert_array_equal(getattr(sharded.actors, k), want)
    np.testing.assert_array_equal(sharded.ego_size, tiny_train_cache.ego_size)
    for i in (0, 39, 40, 59):  # both sides of the shard boundary
        got = sharded.map_store.frame_map(i)
        assert map_differences(got, tiny_train_cache.map_store.frame_map(i), atol=0.0) == []
    assert len(load_union([str(out), tiny_train_cache.path])) == 120  # a cache like any other

    other = tmp_path / "other"
    prepare(spec, str(other), get_config("tiny", max_actors=20), workers=1, shard=(1, 2))
    shutil.rmtree(out / "shard-00001-of-00002")
    with pytest.raises(FileNotFoundError, match=r"shard\(s\) \[1\] of 2 missing"):
        load_cache(str(out))
    shutil.copytree(other / "shard-00001-of-00002", out / "shard-00001-of-00002")
    with pytest.raises(ValueError, match=r"shard-00001-of-00002/meta.json: field slots differs"):
        load_cache(str(out))


def test_a_whole_cache_beside_shards_is_refused_naming_both(tiny_train_cache, tmp_path):
    """A `prepare --shard` into the folder of a whole cache leaves two caches in one: which
    one is meant is unknown, so neither is read."""
    import shutil

    both = tmp_path / "both"
    shutil.copytree(tiny_train_cache.path, both)
    shutil.copytree(tiny_train_cache.path, both / "shard-00000-of-00002")
    with pytest.raises(ValueError, match=rf"^{both}: holds both a whole cache \({both}/meta\.json"
                       rf"\) and shards \({both}/shard-00000-of-00002, \.\.\.\)"):
        load_cache(str(both))
