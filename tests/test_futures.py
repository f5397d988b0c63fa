"""Each actor's future positions (`Frame.future`) on every real source against the frames
read at those later times: the same track's position there, moved through both ego poses."""

import collections
import json
import os
import shutil

import numpy as np
import pytest
from conftest import DATA_ROOT, FORECAST_ROOT, WOMD_ROOT

from scenegen_jax.config import get_config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.data.cache_write import write_cache
from scenegen_jax.data.sources import read_file, source_files, source_spec
from scenegen_jax.data.union import load_union
from scenegen_jax.frame import FUTURE_HORIZONS_S, future_positions
from scenegen_jax.vector_map import se2_pose

CPU = get_config("cpu")

SOURCES = {
    "av2": lambda: source_spec("av2", DATA_ROOT, "val", stride=1),
    "av2_forecasting": lambda: source_spec("av2_forecasting", FORECAST_ROOT, "val", stride=1),
    "womd_json": lambda: source_spec("womd_json", os.path.join(WOMD_ROOT, "gpudrive_json"),
                                     "val", stride=1),
    "scenarionet": lambda: source_spec("scenarionet", os.path.join(WOMD_ROOT, "scenarionet"),
                                       "val", stride=1),
    "womd": lambda: source_spec("womd", os.path.join(WOMD_ROOT, "scenario_tfrecord"),
                                stride=1),
}


def _time_s(frame) -> float:
    """The frame's time (s) from its scene id: nanoseconds (sensor logs) or 10 Hz steps."""
    stamp = int(frame.scene_id.rsplit("/", 1)[1])
    return stamp * 1e-9 if stamp > 10**12 else stamp * 0.1


def _expected(frames, i: int) -> np.ndarray:
    """[A, H, 2]: frame i's actors at each horizon, from the frame nearest that time (within
    0.04 s) which holds the same track, moved from its ego frame into frame i's."""
    frame, times = frames[i], np.array([_time_s(f) for f in frames])
    out = np.full((frame.num_actors, len(FUTURE_HORIZONS_S), 2), np.nan)
    ego_from_city = np.linalg.inv(frame.city_from_ego)
    for h, ahead in enumerate(FUTURE_HORIZONS_S):
        j = int(np.argmin(np.abs(times - times[i] - ahead)))
        if abs(times[j] - times[i] - ahead) > 0.04:
            continue
        later = frames[j]
        where = {t: a for a, t in enumerate(later.track_id)}
        move = ego_from_city @ later.city_from_ego
        for a, tid in enumerate(frame.track_id):
            if tid in where:
                p = later.position[where[tid]]
                out[a, h] = move[:2, :2] @ p + move[:2, 2]
    return out


@pytest.mark.parametrize("kind", sorted(SOURCES))
def test_futures_match_the_later_frames(kind):
    spec = SOURCES[kind]()
    path = source_files(spec)[0]
    frames, _ = read_file(spec, path)
    checked = 0
    for i in range(0, len(frames), max(len(frames) // 6, 1)):
        got, want = frames[i].future, _expected(frames, i)
        assert got.shape == want.shape
        # A later frame holds a track exactly where the future is known, but for tracks
        # that the later frame drops (a damaged row there) and rows the reader counts out.
        both = np.isfinite(want[..., 0]) & np.isfinite(got[..., 0])
        # The sensor logs' poses are 3D, the frames' `city_from_ego` planar: moving a point
        # with two planar poses, as here, puts it up to ~5e-3 of its distance (the road's
        # slope and roll) and ~0.1 m (its height above the road times the slope) from where
        # the reader's full poses put it.
        error = np.linalg.norm(got[both] - want[both], axis=-1)
        scale = 5e-3 * np.linalg.norm(want[both], axis=-1) + 0.1 if kind == "av2" else 1e-6
        assert np.all(error <= scale), f"{kind}: error up to {error.max():.3g} m"
        assert np.sum(np.isfinite(want[..., 0]) & ~np.isfinite(got[..., 0])) == 0
        checked += int(both.sum())
    assert checked > 50, f"{kind}: only {checked} future positions checked"


def test_future_positions_hand_case():
    # One track moving +1 m/s along world x; the ego at (10, 5) facing +y (heading pi/2):
    # world +x is the ego's -y (to its right).
    times = np.arange(0, 4.01, 0.1)
    xy = np.stack([times, np.zeros_like(times)], -1)[None]
    valid = np.ones((1, len(times)), bool)
    valid[0, 15] = False  # unobserved 1.5 s after step 0
    pose = se2_pose(10.0, 5.0, np.pi / 2)
    got = future_positions(xy, valid, times, 0, pose)
    for h, ahead in enumerate(FUTURE_HORIZONS_S):
        if ahead == 1.5:
            assert np.all(np.isnan(got[0, h]))
        else:
            np.testing.assert_allclose(got[0, h], [-5.0, 10.0 - ahead], atol=1e-9)
    # From step 20 (2.0 s) the samples end at 4.0 s: 2.5 s and 3.0 s ahead are unknown.
    late = future_positions(xy, valid, times, 20, pose)
    assert np.isfinite(late[0, :4]).all() and np.isnan(late[0, 4:]).all()


# ---------------------------------------------------------------------------- caches


@pytest.fixture(scope="module")
def womd_cache(tmp_path_factory):
    """A cpu cache of 3 womd_mini GPUDrive JSON val scenes (every 10th step), and its frames."""
    spec = SOURCES["womd_json"]()
    spec = {**spec, "stride": 10}
    frames = [f for path in source_files(spec)[:3] for f in read_file(spec, path)[0]]
    path = str(tmp_path_factory.mktemp("futures") / "womd")
    write_cache(frames, path, CPU, collections.Counter(), source=spec)
    return path, frames


def test_cached_futures_are_the_frames(womd_cache):
    path, frames = womd_cache
    cache = load_cache(path)
    assert cache.future.shape == (len(frames), cache.actors.cls.shape[1],
                                  len(FUTURE_HORIZONS_S), 2)
    assert np.isnan(cache.future[~cache.actors.valid]).all()
    known = 0
    for i, frame in enumerate(frames):
        for slot in np.flatnonzero(cache.actors.valid[i]):
            # The cache keeps the actors nearest first: find each slot's actor by position.
            a = int(np.argmin(np.linalg.norm(frame.position - cache.actors.position[i, slot],
                                             axis=1)))
            np.testing.assert_allclose(cache.future[i, slot], frame.future[a], atol=1e-4)
            known += int(np.isfinite(frame.future[a, :, 0]).sum())
    assert known > 1000


def test_a_version_5_cache_reads_without_futures(womd_cache, tmp_path):
    old = tmp_path / "v5"
    shutil.copytree(womd_cache[0], old)
    meta = json.loads((old / "meta.json").read_text())
    (old / "meta.json").write_text(json.dumps({**meta, "version": 5}))
    with np.load(old / "actors.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "future"}
    np.savez(old / "actors.npz", **arrays)
    assert load_cache(str(old)).future is None
    assert load_union([str(old), womd_cache[0]]).future is None  # not every member has them
    (old / "meta.json").write_text(json.dumps({**meta, "version": 6}))
    with pytest.raises(ValueError, match=r"actors.npz: missing field\(s\) \['future'\]"):
        load_cache(str(old))


def test_damaged_futures_are_named(womd_cache, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(womd_cache[0], bad)
    with np.load(bad / "actors.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["future"][0, 0, 0, 0] = np.inf
    np.savez(bad / "actors.npz", **arrays)
    with pytest.raises(ValueError, match=r"actors.npz: field future: inf"):
        load_cache(str(bad))
    arrays["future"] = arrays["future"][:, :, :3]
    np.savez(bad / "actors.npz", **arrays)
    with pytest.raises(ValueError, match=r"actors.npz: field future: float32 .*expected float"):
        load_cache(str(bad))


def test_a_union_stacks_the_futures(womd_cache, tmp_path):
    one = load_cache(womd_cache[0])
    shutil.copytree(womd_cache[0], tmp_path / "again")
    union = load_union([womd_cache[0], str(tmp_path / "again")])
    n = len(one)
    np.testing.assert_array_equal(union.future[:n], one.future)
    np.testing.assert_array_equal(union.future[n:], one.future)
    np.testing.assert_array_equal(union.members[1].future, one.future)
