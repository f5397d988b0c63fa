"""experiments/off_road_distance.py's split of the vehicles by where they stand (`by_place`), on
a hand-drawn map: a drivable strip with a lane inside it."""

import importlib.util
import os
from types import SimpleNamespace

import numpy as np

from scenegen_jax.vector_map import Lane, VectorMap

_PATH = os.path.join(os.path.dirname(__file__), "..", "experiments", "off_road_distance.py")
_spec = importlib.util.spec_from_file_location("off_road_distance", _PATH)
off_road = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(off_road)


def _cache():
    """One map at 1 m/px on a 14 px grid (a 22 px canvas: pixel column c covers x in
    [c - 11, c - 10) m): the drivable strip |x| <= 2 m (columns 9-12) and a northbound lane
    |x| <= 1 m (columns 10-11) along it."""
    ys = np.linspace(-30.0, 30.0, 7)
    lane = Lane(id=1, lane_type="VEHICLE", left=np.stack([np.full(7, -1.0), ys], 1),
                right=np.stack([np.full(7, 1.0), ys], 1))
    strip = np.array([[-2.0, -30.0], [2.0, -30.0], [2.0, 30.0], [-2.0, 30.0]])
    vmap = VectorMap(lanes=(lane,), drivable_areas=(strip,))
    return SimpleNamespace(meta={"m_per_px": 1.0, "grid_size": 14}, scene_ids=["log/0"],
                           map_store=SimpleNamespace(frame_map=lambda i: vmap))


def test_each_place_and_its_still_share():
    actors = [(-0.5, 0.5, 5.0),  # column 10: on the lane, moving
              (-1.5, 0.5, 0.0),  # column 9: drivable, off the lane, still
              (-3.5, 0.5, 0.1),  # column 7: 2 m off the drivable area, still
              (-7.5, 0.5, 1.0),  # column 3: 6 m off, moving
              (15.0, 0.5, 0.0)]  # beyond the canvas: not counted
    got = off_road.by_place(_cache(), [(0, actors)], still_mps=0.2)
    assert {k: v["share"] for k, v in got.items()} == {
        "on_lane": 0.25, "on_drivable_off_lanes": 0.25, "off_drivable_near": 0.25,
        "off_drivable_far": 0.25}
    assert {k: v["still_share"] for k, v in got.items()} == {
        "on_lane": 0.0, "on_drivable_off_lanes": 1.0, "off_drivable_near": 1.0,
        "off_drivable_far": 0.0}
    # the distances behind the split, in metres
    assert off_road.scene_distances(_cache(), 0, actors) == [0.0, 0.0, 2.0, 6.0, None]


def test_a_place_without_actors_has_no_still_share():
    got = off_road.by_place(_cache(), [(0, [(-0.5, 0.5, 0.0)])], still_mps=0.2)
    assert got["on_lane"] == {"share": 1.0, "still_share": 1.0}
    assert got["off_drivable_far"] == {"share": 0.0, "still_share": None}
