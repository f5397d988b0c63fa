"""A Waymo Open Motion Dataset scenario after parsing -> a vector map and Frames.

Both WOMD readers parse their format into a `ParsedScenario` (tracks of the modelled
classes, the ego's index, `MapFeature`s): `womd_json` from GPUDrive / Nocturne JSON,
`womd_tfrecord` from Waymo's Scenario protocol buffers. `scenario_frames` turns one into
frames, so both formats of one scene give the same frames.

Map: lanes are centrelines (bike lanes kept apart), road lines and road edges become
`RoadLine`s (the mark from Waymo's road-line type where the file has it, else inferred from
the lanes beside the line: `infer_line_marks`), crosswalks stay crosswalks, driveways join
the drivable surface, and lane outlines and the drivable surface come from
`scenegen_jax.data.surface`. Stop signs and speed bumps have no layer and are counted drops.
"""

from __future__ import annotations

import collections
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from scenegen_jax.data.surface import (
    MAX_HALF_WIDTH_M,
    Centerline,
    normals,
    outline_lanes,
    stacked_normals,
)
from scenegen_jax.frame import MAX_WORLD_M, Frame, future_positions, within_world
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE, wrap_angle
from scenegen_jax.vector_map import (
    ROAD_EDGE,
    RoadLine,
    VectorMap,
    distinct_points,
    rotation_matrix,
    se2_pose,
)

CLASS_FROM_TYPE = {"vehicle": VEHICLE, "pedestrian": PEDESTRIAN, "cyclist": BICYCLIST}
STEP_S = 0.1  # WOMD's 10 Hz
MOVING_MPS = 2.0
MAP_RADIUS_M = 80.0
# GPUDrive's `map_element_id` of road lines: Waymo's RoadLine types, as Argoverse 2 mark names.
MARK_FROM_ELEMENT_ID = {
    6: "DASHED_WHITE",
    7: "SOLID_WHITE",
    8: "DOUBLE_SOLID_WHITE",
    9: "DASHED_YELLOW",
    10: "DOUBLE_DASH_YELLOW",
    11: "SOLID_YELLOW",
    12: "DOUBLE_SOLID_YELLOW",
    13: "SOLID_DASH_YELLOW",
}
BIKE_LANE_ELEMENT_ID = 3
DROPPED_ROAD_TYPES = ("stop_sign", "speed_bump")


class Tracks(NamedTuple):
    """Every object of a scenario in the world frame."""

    type: list[str]  # [O] keys of CLASS_FROM_TYPE
    position: np.ndarray  # [O, T, 2] m
    velocity: np.ndarray  # [O, T, 2] m/s
    heading: np.ndarray  # [O, T] rad (unit already detected)
    valid: np.ndarray  # [O, T] bool
    size: np.ndarray  # [O, T, 2] (width, length) m at each step
    ids: list[str]  # [O]


class MapFeature(NamedTuple):
    """A WOMD map feature as a reader parsed it.

    Attributes:
      kind: "lane", "road_line", "road_edge", "crosswalk", "driveway", or a kind with no
        layer ("stop_sign", "speed_bump", any other name), counted as "map:<kind>".
      field: where its points are in the file, named in errors ("roads[3].geometry").
      points: [P, 2] world m; empty for the kinds in DROPPED_ROAD_TYPES (not read).
      lane_type: lanes: one of `vector_map.LANE_TYPES`.
      mark: road lines: Argoverse 2 mark name; None when the file gives no type (inferred).
      lane_id: lanes: the file's id; None: the lane's index among the lanes.
      successors, predecessors: lanes: ids of the lanes it exits to / is entered from.
    """

    kind: str
    field: str
    points: np.ndarray = np.zeros((0, 2))
    lane_type: str = "VEHICLE"
    mark: str | None = None
    lane_id: int | None = None
    successors: tuple[int, ...] = ()
    predecessors: tuple[int, ...] = ()


class ParsedScenario(NamedTuple):
    """What a reader parsed of one scenario, before it becomes frames (`scenario_frames`)."""

    scenario_id: str
    tracks: Tracks  # objects of a modelled class only
    sdc: int  # index into `tracks` of the ego
    features: list[MapFeature]
    dropped: collections.Counter  # what parsing left out, by reason
    tracks_field: str = "objects"  # the file's name for its tracks, named in errors


def field_error(source: str, field: str, msg: str) -> ValueError:
    return ValueError(f"{source}: {field}: {msg}")


def infer_line_marks(lines: Sequence[np.ndarray], centerlines: Sequence[Centerline]) -> list[str]:
    """Marks of untyped painted lines from the lanes beside them.

    A line with lanes on both sides that run the same way separates lanes of one carriageway
    (a dashed white line: crossable); lanes running opposite ways on its two sides, or a lane
    on one side only, make it a line not to cross (a double yellow or an edge line). Lines
    with no lane within `surface.MAX_HALF_WIDTH_M` stay "UNKNOWN" (not drawn).
    """
    if not centerlines:
        return ["UNKNOWN"] * len(lines)
    pts = np.concatenate([c.points for c in centerlines])
    left = stacked_normals([c.points for c in centerlines])
    dirs = np.stack([left[:, 1], -left[:, 0]], axis=1)  # the unit tangents
    marks = []
    for line in lines:
        mid = line[len(line) // 2] if len(line) > 2 else line.mean(axis=0)
        n = normals(line)[len(line) // 2 if len(line) > 2 else 0]
        tangent = np.array([n[1], -n[0]])
        rel = pts - mid
        dist = np.linalg.norm(rel, axis=1)
        near = dist < MAX_HALF_WIDTH_M
        side = rel[near] @ n
        along = dirs[near] @ tangent
        left, right = along[side > 0.2], along[side < -0.2]
        if not left.size and not right.size:
            marks.append("UNKNOWN")
        elif not left.size or not right.size:
            marks.append("SOLID_WHITE")
        elif np.sign(np.median(left)) == np.sign(np.median(right)):
            marks.append("DASHED_WHITE")
        else:
            marks.append("DOUBLE_SOLID_YELLOW")
    return marks


def build_map(features: Sequence[MapFeature], source: str
              ) -> tuple[VectorMap, collections.Counter]:
    """The world-frame VectorMap of a scenario's map features and counts of unused ones."""
    dropped: collections.Counter = collections.Counter()
    centerlines, lines, untyped, crosswalks, driveways = [], [], [], [], []
    for feature in features:
        kind = feature.kind
        if kind in DROPPED_ROAD_TYPES:
            dropped[f"map:{kind}"] += 1
            continue
        if not np.all(np.isfinite(feature.points)):
            raise field_error(source, feature.field, "NaN or inf coordinate")
        if not np.all(within_world(feature.points)):
            raise field_error(source, feature.field, f"a coordinate beyond {MAX_WORLD_M:g} m")
        points = feature.points[distinct_points(feature.points, 1e-6)]
        if len(points) < (3 if kind in ("crosswalk", "driveway") else 2):
            dropped[f"map:degenerate_{kind}"] += 1
        elif kind == "lane":
            lane_id = len(centerlines) if feature.lane_id is None else feature.lane_id
            centerlines.append(Centerline(
                id=lane_id, lane_type=feature.lane_type, points=points,
                successors=feature.successors, predecessors=feature.predecessors))
        elif kind == "road_edge":
            lines.append(RoadLine(points, ROAD_EDGE))
        elif kind == "road_line" and feature.mark is not None:
            lines.append(RoadLine(points, feature.mark))
        elif kind == "road_line":
            untyped.append(points)
        elif kind in ("crosswalk", "driveway"):
            (crosswalks if kind == "crosswalk" else driveways).append(points)
        else:
            dropped[f"map:{kind}"] += 1
    marks = infer_line_marks(untyped, centerlines)
    lines += [RoadLine(p, m) for p, m in zip(untyped, marks, strict=True)]
    if untyped:
        dropped["map_info:road_line_mark_inferred"] += len(untyped)
    lanes, surface = outline_lanes(centerlines, lines)
    vmap = VectorMap(
        lanes=lanes,
        crosswalks=tuple(crosswalks),
        drivable_areas=surface + tuple(driveways),
        lines=tuple(lines),
        dataset="waymo",  # every reader of this module's features reads WOMD scenes
    )
    return vmap, dropped


def velocity_mismatch(tracks: Tracks) -> bool:
    """Whether the file's velocities disagree with finite differences of the positions (of
    the steps whose position is a place: `frame.within_world`)."""
    pos, valid = tracks.position, tracks.valid & within_world(tracks.position)
    both = valid[:, 2:] & valid[:, :-2]
    fd = (pos[:, 2:] - pos[:, :-2]) / (2 * STEP_S)
    v = tracks.velocity[:, 1:-1]
    moving = both & (np.linalg.norm(fd, axis=-1) > MOVING_MPS)
    if moving.sum() < 10:
        return False
    with np.errstate(over="ignore", invalid="ignore"):  # velocities near 1e308: inf, not warned
        rel = np.linalg.norm(v[moving] - fd[moving], axis=-1) / np.linalg.norm(fd[moving],
                                                                             axis=-1)
    return bool(np.median(rel) > 0.3)


def _ego_state_checked(scenario: ParsedScenario, t: int, source: str) -> None:
    """Raises ValueError naming the field when the ego's state at step `t` is unusable."""
    tracks, sdc = scenario.tracks, scenario.sdc
    sdc_field = f"{scenario.tracks_field} (the SDC, id {tracks.ids[sdc]})"
    for name in ("position", "velocity", "heading"):
        if not np.all(np.isfinite(getattr(tracks, name)[sdc, t])):
            raise field_error(source, f"{sdc_field}.{name}", f"NaN or inf at step {t}")
    if not within_world(tracks.position[sdc, t]):
        raise field_error(source, f"{sdc_field}.position",
                          f"beyond {MAX_WORLD_M:g} m at step {t}: {tracks.position[sdc, t]}")
    size = tracks.size[sdc, t]
    if not (np.all(np.isfinite(size)) and np.all(size > 0)):
        raise field_error(source, f"{sdc_field}.width/length",
                   f"not finite and positive at step {t}: {size}")


def _rotated(velocity: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """velocity [..., 2] m/s @ rotation.T; a speed beyond float64 becomes inf without a
    warning, for the speed limit to drop (`frame.drop_beyond_limits`)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return velocity @ rotation.T


def scenario_frames(
    scenario: ParsedScenario, source: str, stride: int
) -> tuple[list[Frame], collections.Counter]:
    """Frames at steps 0, stride, 2 stride, ... where the ego is valid, and the drop counts
    (the parser's, the map's, and the steps where the ego is not valid: "frame:no_ego"; none
    at all raises ValueError).

    Rows valid at a frame's step are either actors of the frame or counted drops (NaN/inf,
    positions beyond `frame.MAX_WORLD_M`, non-positive box sizes of vehicles and cyclists).
    NaN/inf or a position beyond `frame.MAX_WORLD_M` in the ego's state at a frame's step,
    or an ego box size there that is not positive, raise ValueError; so do map features
    beyond it (`build_map`).
    """
    tracks, sdc = scenario.tracks, scenario.sdc
    world_map, map_dropped = build_map(scenario.features, source)
    dropped = scenario.dropped + map_dropped
    if velocity_mismatch(tracks):
        dropped["quirk:velocity_mismatch_files"] += 1
    boxed = np.array([t != "pedestrian" for t in tracks.type])
    frames = []
    n_steps = tracks.valid.shape[1]
    times_s = np.arange(n_steps) * STEP_S
    for t in range(0, n_steps, stride):
        if not tracks.valid[sdc, t]:
            dropped["frame:no_ego"] += 1
            continue
        _ego_state_checked(scenario, t, source)
        rows = np.flatnonzero(tracks.valid[:, t])
        rows = rows[rows != sdc]
        size = tracks.size[rows, t]
        bad_size = boxed[rows] & np.any(size <= 0, axis=1)
        finite = (
            np.all(np.isfinite(tracks.position[rows, t]), axis=1)
            & np.all(np.isfinite(tracks.velocity[rows, t]), axis=1)
            & np.isfinite(tracks.heading[rows, t])
            & np.all(np.isfinite(size), axis=1)
        )
        far = finite & ~within_world(tracks.position[rows, t])
        dropped["invalid:size"] += int(np.sum(bad_size & finite & ~far))
        dropped["invalid:nan"] += int(np.sum(~finite))
        dropped["invalid:world_position"] += int(np.sum(far))
        rows = rows[finite & ~bad_size & ~far]
        x0, y0 = tracks.position[sdc, t]
        h0 = float(tracks.heading[sdc, t])
        ego_from_world = rotation_matrix(-h0)
        vmap = world_map.crop(np.array([x0, y0]), MAP_RADIUS_M)
        vmap = vmap.transform(ego_from_world, -ego_from_world @ np.array([x0, y0]))
        frames.append(
            Frame(
                scene_id=f"{scenario.scenario_id}/{t}",
                source=source,
                cls=np.array([CLASS_FROM_TYPE[tracks.type[r]] for r in rows], np.int32),
                position=(tracks.position[rows, t] - (x0, y0)) @ ego_from_world.T,
                size=tracks.size[rows, t].astype(np.float64),
                heading=wrap_angle(tracks.heading[rows, t] - h0),
                velocity=_rotated(tracks.velocity[rows, t], ego_from_world),
                track_id=np.asarray([tracks.ids[r] for r in rows], dtype=str),
                ego_velocity=_rotated(tracks.velocity[sdc, t], ego_from_world),
                ego_size=tracks.size[sdc, t].astype(np.float64),
                map=vmap,
                city_from_ego=se2_pose(x0, y0, h0),
                future=future_positions(tracks.position[rows], tracks.valid[rows], times_s, t,
                                        se2_pose(x0, y0, h0)),
            )
        )
    if not frames:
        sdc_field = f"{scenario.tracks_field} (the SDC, id {tracks.ids[sdc]})"
        raise field_error(source, f"{sdc_field}.valid",
                   f"the SDC is valid at none of the steps 0, {stride}, ... of {n_steps}")
    dropped = collections.Counter({k: v for k, v in dropped.items() if v})
    return frames, dropped
