"""experiments/off_road_distance.py's split of the vehicles by where they stand (`by_place`), on
a hand-drawn canvas: a drivable strip with a lane inside it."""

import importlib.util
import os
from types import SimpleNamespace

import numpy as np

from scenegen_jax.raster.map import ALL_MAP_CHANNELS

_PATH = os.path.join(os.path.dirname(__file__), "..", "experiments", "off_road_distance.py")
_spec = importlib.util.spec_from_file_location("off_road_distance", _PATH)
off_road = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(off_road)


def _cache():
    """One 20 x 20 px canvas at 1 m/px: columns 8-11 drivable, a lane (pointing along +x) in
    columns 9-10; pixel column c covers x in [c - 10, c - 9) m."""
    canvas = np.zeros((20, 20, len(ALL_MAP_CHANNELS)), np.float32)
    canvas[:, 8:12, ALL_MAP_CHANNELS.index("drivable_area")] = 1.0
    canvas[:, 9:11, ALL_MAP_CHANNELS.index("lane_orientation_cos")] = 1.0
    return SimpleNamespace(meta={"m_per_px": 1.0}, maps=[canvas], scene_ids=["log/0"])


def test_each_place_and_its_still_share():
    actors = [(-0.5, 0.5, 5.0),  # column 9: on the lane, moving
              (-1.5, 0.5, 0.0),  # column 8: drivable, off the lane, still
              (-3.5, 0.5, 0.1),  # column 6: 2 m off the drivable area, still
              (-7.5, 0.5, 1.0),  # column 2: 6 m off, moving
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
