"""Realism figures of scenes against their maps: hand-computed cases and real-data properties."""

from __future__ import annotations

import collections

import numpy as np
import pytest

from scenegen_jax.config import get_config
from scenegen_jax.eval.realism import (
    drivable_share,
    lane_alignment,
    lane_offsets,
    overlapping_pairs,
    realism_stats,
    vehicle_cells,
)
from scenegen_jax.raster.map import ALL_MAP_CHANNELS
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE, Actors

CFG = get_config("tiny").replace(m_per_px=1.0)  # 1 m pixels: pixel (row, col) is easy to name
COS, SIN, DRIVABLE, NEAR_COS, NEAR_SIN = (ALL_MAP_CHANNELS.index(c) for c in (
    "lane_orientation_cos", "lane_orientation_sin", "drivable_area", "nearest_lane_cos",
    "nearest_lane_sin"))


def _actors(rows):
    """numpy Actors from (cls, x, y, heading_deg, width, length) rows."""
    rows = np.asarray(rows, np.float64)
    n = len(rows)
    return Actors(
        cls=rows[:, 0].astype(np.int32),
        position=rows[:, 1:3].astype(np.float32),
        size=rows[:, 4:6].astype(np.float32),
        heading=np.radians(rows[:, 3]).astype(np.float32),
        velocity=np.zeros((n, 2), np.float32),
        valid=np.ones(n, bool),
    )


def _canvas():
    """An 8 m x 8 m canvas (rows from y = 4 m down to y = -4 m): an eastbound lane in row 3
    (0 < y <= 1 m), a northbound lane in column 6 (2 <= x < 3 m), drivable area on both; the
    nearest lane points east except in column 6 (north) and at row 1, column 1 (none)."""
    canvas = np.zeros((8, 8, len(ALL_MAP_CHANNELS)), np.float32)
    canvas[3, :, COS] = 1.0
    canvas[:, 6, COS], canvas[:, 6, SIN] = 0.0, 1.0
    canvas[3, :, DRIVABLE] = canvas[:, 6, DRIVABLE] = 1.0
    canvas[:, :, NEAR_COS] = 1.0
    canvas[:, 6, NEAR_COS], canvas[:, 6, NEAR_SIN] = 0.0, 1.0
    canvas[1, 1, NEAR_COS] = 0.0
    return canvas


def test_lane_alignment_and_drivable_share_hand_computed():
    actors = _actors([
        (VEHICLE, -2.5, 0.5, 0.0, 2, 4),  # on the eastbound lane, along it
        (VEHICLE, -0.5, 0.5, -15.0, 2, 4),  # 15 degrees off: aligned
        (VEHICLE, 0.5, 0.5, 30.0, 2, 4),  # 30 degrees off: not aligned
        (VEHICLE, 1.5, 0.5, 180.0, 2, 4),  # against the lane: not aligned
        (VEHICLE, 2.5, -2.5, 95.0, 2, 4),  # on the northbound lane, 5 degrees off: aligned
        (VEHICLE, -2.5, 2.5, 0.0, 2, 4),  # off every lane and off the drivable area
        (PEDESTRIAN, -1.5, 0.5, 0.0, 0.6, 0.6),  # not a vehicle
        (BICYCLIST, 0.5, 0.5, 90.0, 0.7, 1.8),  # not a vehicle
    ])
    assert lane_alignment(_canvas(), actors, CFG) == (3, 5)
    np.testing.assert_allclose(lane_offsets(_canvas(), actors, CFG), [0, 15, 30, 180, 5],
                               atol=1e-4)
    # The median offset of the aligned three (0, 15, 5 degrees): 5.
    stats = realism_stats([_canvas()], [actors], CFG)
    assert stats["lane_offset_median_deg"] == pytest.approx(5.0, abs=1e-4)
    assert lane_alignment(_canvas(), actors, CFG, tolerance_deg=35.0) == (4, 5)
    assert drivable_share(_canvas(), actors, CFG) == (5, 6)
    # Only vehicles within the radius count: the second to fourth (0.71, 0.71, 1.58 m).
    assert drivable_share(_canvas(), actors, CFG, radius_m=2.0) == (3, 3)
    cells = vehicle_cells(_canvas(), actors, CFG)  # the six vehicles, in slot order
    np.testing.assert_array_equal(cells.slots, np.arange(6))
    np.testing.assert_array_equal(cells.on_lane, [1, 1, 1, 1, 1, 0])
    np.testing.assert_allclose(np.degrees(cells.lane_direction[:5]), [0, 0, 0, 0, 90],
                               atol=1e-4)
    np.testing.assert_allclose(np.degrees(cells.nearest_direction),
                               [0, 0, 0, 0, 90, np.nan], atol=1e-4)


def test_overlapping_pairs_hand_computed():
    actors = _actors([
        (VEHICLE, 0.0, 0.0, 0.0, 2, 4),
        (VEHICLE, 1.0, 0.0, 0.0, 2, 4),  # 1 m along: overlaps the first (2 m wide)
        (VEHICLE, 1.0, 2.0, 0.0, 2, 4),  # touches the second along y = 1 (no overlap)...
        (BICYCLIST, -0.5, 2.5, 90.0, 0.7, 1.8),  # ...but overlaps this bicyclist
        (PEDESTRIAN, 0.0, 0.0, 0.0, 0.6, 0.6),  # a point: never counted
        (VEHICLE, 20.0, 20.0, 45.0, 2, 4),
    ])
    # Boxes: (width, length) with length along the heading, so a 0-degree vehicle spans
    # x +- 2 m, y +- 1 m.
    assert overlapping_pairs(actors) == 2
    stats = realism_stats([_canvas()], [actors], CFG)
    assert stats["overlapping_pairs"] == 2 and stats["scenes_with_overlap"] == 1
    assert stats["actors_per_scene"] == 6.0
    assert stats["class_mix"] == pytest.approx(
        {"vehicle": 4 / 6, "pedestrian": 1 / 6, "bicyclist": 1 / 6})


def test_real_argoverse_scenes_are_on_the_road_along_their_lanes(data_root, tmp_path):
    """The real val log, as a user's reference: every vehicle within 40 m stands on the
    drivable area, and most vehicles on a lane point along it (93 % at the `cpu` grid);
    annotated boxes do not overlap."""
    from scenegen_jax.data.cache import load_cache
    from scenegen_jax.data.cache_write import write_cache
    from scenegen_jax.data.sources import read_frames, source_spec
    from scenegen_jax.eval.evaluate import real_scenes
    from scenegen_jax.eval.realism import map_canvases

    cfg = get_config("tiny")
    frames = read_frames(source_spec("av2", data_root, "val", 20), collections.Counter())
    write_cache(frames, str(tmp_path),
                cfg, collections.Counter())
    cache = load_cache(str(tmp_path))
    indices = np.arange(len(cache))
    _, scenes = real_scenes(cache, indices, cfg)
    canvases = list(map_canvases(cache, indices, cfg))
    stats = realism_stats(canvases, [s.actors for s in scenes], cfg)
    assert stats["vehicles_within_40m"] > 50, stats
    assert stats["on_drivable_share"] > 0.95, stats
    assert stats["vehicles_on_lane"] > 30 and stats["lane_aligned_share"] > 0.8, stats
    assert stats["overlapping_pairs"] == 0, stats
    # Turned by 90 degrees, the same vehicles no longer point along their lanes.
    turned = [s.actors.replace(heading=s.actors.heading + np.pi / 2) for s in scenes]
    assert realism_stats(canvases, turned, cfg)["lane_aligned_share"] < 0.2
