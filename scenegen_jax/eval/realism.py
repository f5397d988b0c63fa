"""Realism statistics of scenes against their maps, as a user would judge a sample: vehicles
on the drivable area, vehicles on a lane pointing along it, overlapping boxes, actors per scene
and the class mix (`realism_stats`; `scenegen evaluate` reports them for the real scenes, the
SceneGen samples and both baselines on the same maps)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import jax
import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.geometry import boxes_overlap
from scenegen_jax.raster.jax_map import draw_maps
from scenegen_jax.raster.map import ALL_MAP_CHANNELS, NEAREST_LANE_CHANNELS, ORIENTATION_CHANNELS
from scenegen_jax.scene import CLASS_NAMES, PEDESTRIAN, VEHICLE

LANE_TOLERANCE_DEG = 20.0  # a vehicle on a lane is aligned within this of its direction
CANVAS_BATCH = 16  # canvases drawn per call (`map_canvases`)


def map_canvases(cache, indices, cfg: Config) -> Iterator[np.ndarray]:
    """Unrotated canvases [C, C, len(ALL_MAP_CHANNELS)] (C = `GridConfig.canvas_size`: the
    disc of every vehicle within 40 m of the ego on it) of the cached scenes `indices`, one
    after the other (drawn `CANVAS_BATCH` at a time)."""
    indices = [int(i) for i in indices]
    for lo in range(0, len(indices), CANVAS_BATCH):
        chunk = indices[lo : lo + CANVAS_BATCH]
        drawn = draw_maps([cache.map_store.frame_map(i) for i in chunk], np.zeros(len(chunk)),
                          cfg.grid, cfg.grid.canvas_size, ALL_MAP_CHANNELS)
        yield from np.asarray(drawn)


def _vehicle_pixels(canvas: np.ndarray, actors, cfg: Config, radius_m: float):
    """(rows, cols, slots) of the canvas pixels under the valid vehicles within `radius_m` of
    the ego, and the number of such vehicles (some may lie beyond the canvas)."""
    s = canvas.shape[0]
    half = s * cfg.grid.m_per_px / 2
    pos = np.asarray(actors.position)
    sel = np.asarray(actors.valid) & (np.asarray(actors.cls) == VEHICLE)
    sel &= np.linalg.norm(pos, axis=1) < radius_m
    slots = np.flatnonzero(sel)
    col = np.floor((pos[slots, 0] + half) / cfg.grid.m_per_px).astype(int)
    row = np.floor((half - pos[slots, 1]) / cfg.grid.m_per_px).astype(int)
    ok = (row >= 0) & (row < s) & (col >= 0) & (col < s)
    return row[ok], col[ok], slots[ok], len(slots)


class VehicleCells(NamedTuple):
    """The map under the valid vehicles within a radius of the ego whose centre lies on the
    canvas (`vehicle_cells`); arrays [n] over those vehicles."""

    slots: np.ndarray  # int, the vehicles' slots in the scene's Actors
    counted: int  # vehicles within the radius, some maybe beyond the canvas
    on_drivable: np.ndarray  # bool, centre on the drivable area
    on_lane: np.ndarray  # bool, the lane orientation channels there longer than 0.5
    lane_direction: np.ndarray  # rad, the lane's direction in the ego frame (where on_lane)
    nearest_direction: np.ndarray  # rad, the nearest centreline's direction (the
    # `nearest_lane` channels; NaN beyond their range)


def vehicle_cells(canvas: np.ndarray, actors, cfg: Config, radius_m: float = 40.0):
    """`VehicleCells` of one unrotated scene. The lane orientation channels hold the lane's
    (cos, sin) direction in the ego frame, zero off every lane.

    Args:
      canvas: [S, S, len(ALL_MAP_CHANNELS)] unrotated map canvas of the scene
        (`map_canvases`).
      actors: numpy Actors [N] in the ego frame.
      cfg: config of the canvas (resolution).
      radius_m: only vehicles within this distance of the ego count.
    """
    row, col, slots, counted = _vehicle_pixels(canvas, actors, cfg, radius_m)
    drivable = np.asarray(canvas[row, col, ALL_MAP_CHANNELS.index("drivable_area")])
    cos, sin = (np.asarray(canvas[row, col, ALL_MAP_CHANNELS.index(c)], np.float64)
                for c in ORIENTATION_CHANNELS)
    near_cos, near_sin = (np.asarray(canvas[row, col, ALL_MAP_CHANNELS.index(c)], np.float64)
                          for c in NEAREST_LANE_CHANNELS)
    nearest = np.where(np.hypot(near_cos, near_sin) > 0.5, np.arctan2(near_sin, near_cos),
                       np.nan)
    return VehicleCells(slots, counted, drivable > 0.5, np.hypot(cos, sin) > 0.5,
                        np.arctan2(sin, cos), nearest)


def drivable_share(canvas: np.ndarray, actors, cfg: Config, radius_m: float = 40.0):
    """(vehicle centres on the drivable area, vehicle centres counted) for one unrotated scene;
    arguments as `vehicle_cells`."""
    cells = vehicle_cells(canvas, actors, cfg, radius_m)
    return int(cells.on_drivable.sum()), cells.counted


def lane_offsets(canvas: np.ndarray, actors, cfg: Config, radius_m: float = 40.0):
    """Angles (degrees, in [0, 180]) between the heading of each vehicle on a lane and the
    lane's direction, for one unrotated scene; arguments as `vehicle_cells`."""
    cells = vehicle_cells(canvas, actors, cfg, radius_m)
    heading = np.asarray(actors.heading, np.float64)[cells.slots[cells.on_lane]]
    direction = cells.lane_direction[cells.on_lane]
    return np.degrees(np.abs(np.angle(np.exp(1j * (heading - direction)))))


def lane_alignment(canvas: np.ndarray, actors, cfg: Config, radius_m: float = 40.0,
                   tolerance_deg: float = LANE_TOLERANCE_DEG):
    """(vehicles on a lane whose heading is within `tolerance_deg` of the lane's direction,
    vehicles on a lane) for one unrotated scene (`lane_offsets`)."""
    off = lane_offsets(canvas, actors, cfg, radius_m)
    return int((off <= tolerance_deg).sum()), len(off)


def overlapping_pairs(actors) -> int:
    """Pairs of valid vehicle and bicyclist boxes of one scene that overlap with positive area
    (pedestrians are points, as in the sampler's collision rejection; boxes the source did
    not measure are placeholders and left out)."""
    a = jax.tree.map(np.asarray, actors)
    measured = True if a.size_measured is None else a.size_measured.astype(bool)
    boxed = np.flatnonzero(a.valid & (a.cls != PEDESTRIAN) & measured)
    pos, size = a.position.astype(np.float64), a.size.astype(np.float64)
    head = a.heading.astype(np.float64)
    return int(sum(
        boxes_overlap(pos[i], size[i], head[i], pos[boxed[k + 1:]], size[boxed[k + 1:]],
                      head[boxed[k + 1:]]).sum()
        for k, i in enumerate(boxed)
    ))


def realism_stats(canvases, actors_list, cfg: Config) -> dict:
    """Realism figures of a set of scenes (numpy Actors each) on their unrotated map canvases:
    vehicles within 40 m of the ego and the share of them on the drivable area; vehicles on a
    lane, the share of them aligned with it and the median angle between the aligned ones and
    their lane (how closely vehicles that follow a lane follow it); overlapping box pairs
    (total and scenes with any; boxes the source did not measure are placeholders, counted
    in `boxes_unmeasured`); actors per scene; the class mix."""
    on = total = 0
    offsets, overlaps = [], []
    for canvas, actors in zip(canvases, actors_list, strict=True):
        a, b = drivable_share(canvas, actors, cfg)
        on, total = on + a, total + b
        offsets.append(lane_offsets(canvas, actors, cfg))
        overlaps.append(overlapping_pairs(actors))
    offsets = np.concatenate(offsets)
    aligned = offsets[offsets <= LANE_TOLERANCE_DEG]
    return {
        "vehicles_within_40m": total,
        "on_drivable_share": on / total if total else None,
        "vehicles_on_lane": len(offsets),
        "lane_aligned_share": len(aligned) / len(offsets) if len(offsets) else None,
        "lane_offset_median_deg": float(np.median(aligned)) if len(aligned) else None,
        "overlapping_pairs": int(sum(overlaps)),
        "scenes_with_overlap": int(np.count_nonzero(overlaps)),
        "boxes_unmeasured": int(sum(unmeasured_boxes(a) for a in actors_list)),
        "actors_per_scene": float(np.mean([np.sum(a.valid) for a in actors_list])),
        "class_mix": class_mix(actors_list),
    }


def unmeasured_boxes(actors) -> int:
    """Valid vehicles and bicyclists of one scene whose box size the source did not measure
    (`Actors.size_measured`)."""
    if getattr(actors, "size_measured", None) is None:
        return 0
    a = jax.tree.map(np.asarray, actors)
    return int(np.sum(a.valid & (a.cls != PEDESTRIAN) & ~a.size_measured.astype(bool)))


def class_mix(actors_list) -> dict[str, float]:
    """Fraction of actors per class over a list of numpy Actors."""
    counts = np.zeros(len(CLASS_NAMES))
    for a in actors_list:
        cls = np.asarray(a.cls)[np.asarray(a.valid)]
        counts += np.bincount(cls, minlength=len(CLASS_NAMES))[: len(CLASS_NAMES)]
    total = max(counts.sum(), 1)
    return {name: float(c / total) for name, c in zip(CLASS_NAMES, counts, strict=True)}


def real_data_check(cache, cfg: Config, moving_mps: float = 2.0) -> dict:
    """Sanity figures of a prepared cache of real scenes (no model involved).

    Returns a dict with `drivable_share` (vehicle centres within 40 m of the ego on the
    drivable raster, over all scenes), `median_vehicle_length_m`, and
    `heading_velocity_deg`: per scenario (scene ids "<scenario>/<step>"), the median angle
    between heading and velocity direction of vehicles moving faster than `moving_mps`, with
    the number of such vehicle states.
    """
    on = total = moving_on = moving_total = 0
    lengths, per_scenario = [], {}
    a = cache.actors
    canvases = map_canvases(cache, range(len(cache)), cfg)
    for i, canvas in enumerate(canvases):
        sel = np.asarray(a.valid[i]) & (np.asarray(a.cls[i]) == VEHICLE)
        sub = jax.tree.map(lambda x, i=i: np.asarray(x[i]), a)
        o, t = drivable_share(canvas, sub, cfg)
        on, total = on + o, total + t
        moving = sub.valid & (np.linalg.norm(sub.velocity, axis=1) > moving_mps)
        o, t = drivable_share(canvas, sub.replace(valid=moving), cfg)
        moving_on, moving_total = moving_on + o, moving_total + t
        lengths.extend(np.asarray(a.size[i])[sel, 1].tolist())
        vel = np.asarray(a.velocity[i])[sel]
        moving = np.linalg.norm(vel, axis=1) > moving_mps
        diff = np.asarray(a.heading[i])[sel][moving] - np.arctan2(vel[moving, 1], vel[moving, 0])
        scenario = cache.scene_ids[i].rsplit("/", 1)[0]
        per_scenario.setdefault(scenario, []).extend(np.abs(np.angle(np.exp(1j * diff))).tolist())
    return {
        "scenes": len(cache),
        "drivable_share": on / max(total, 1),
        "vehicles_within_40m": total,
        "moving_drivable_share": moving_on / max(moving_total, 1),
        "moving_vehicles_within_40m": moving_total,
        "median_vehicle_length_m": float(np.median(lengths)) if lengths else float("nan"),
        "heading_velocity_deg": {
            k: (float(np.degrees(np.median(v))), len(v)) for k, v in per_scenario.items() if v
        },
    }
