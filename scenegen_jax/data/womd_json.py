"""Waymo Open Motion Dataset scenes as GPUDrive / Nocturne JSON -> Frames.

One JSON file holds one scenario: `objects` (tracks of T steps at 10 Hz in the global WOMD
frame, m), `roads` (map features) and, in GPUDrive's newer files, `metadata`. The converters'
layouts differ, and every difference is detected from the data, never from the file name:

- rows (`position: [{x, y}, ...]`) or columns (`position: {x: [T], y: [T]}`);
- headings in radians or in unwrapped degrees: the unit is the one under which moving
  objects' headings agree with their velocity directions (objects at or below 2 m/s leave the
  range as the only clue: degrees when any heading is beyond 2 pi);
- invalid steps hold a sentinel (-10000, 0.0001, ...): every step is masked with `valid`;
- the ego: `metadata.sdc_track_index` where the file has it. Otherwise the recording vehicle
  is estimated (`estimate_sdc`): among vehicles valid at every step, the one whose farthest
  other object is nearest, on average over the steps, because WOMD keeps the objects that
  the SDC's sensors saw around it, so the SDC sits near the centre of the smallest disc that
  holds them. On the 28 WOMD scenes that do mark the SDC (12 GPUDrive JSON files and the
  ScenarioNet pickles) this finds it in 23 (82 %); where it
  picks another vehicle, the frame is still a real scene around a real vehicle, but that
  vehicle's surroundings are seen from a recording car nearby, so near-ego crowding is a
  little lower than for true SDC frames.

Map: lanes are centrelines (`map_element_id` 3 is a bike lane), road lines and road edges
become `RoadLine`s (mark from `map_element_id`, which GPUDrive writes with Waymo's road-line
types; Nocturne files have none, see `infer_line_marks`), crosswalks stay crosswalks,
driveways join the drivable surface, and lane outlines and the drivable surface come from
`scenegen_jax.data.surface`. Stop signs and speed bumps have no layer and are counted drops.
"""

from __future__ import annotations

import collections
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from scenegen_jax.data.surface import (
    MAX_HALF_WIDTH_M,
    Centerline,
    normals,
    outline_lanes,
    stacked_normals,
)
from scenegen_jax.files import files_under
from scenegen_jax.frame import Frame
from scenegen_jax.jsonfile import read_json
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE, wrap_angle
from scenegen_jax.vector_map import (
    ROAD_EDGE,
    RoadLine,
    VectorMap,
    distinct_points,
    rotation_matrix,
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

    type: list[str]  # [O]
    position: np.ndarray  # [O, T, 2] m
    velocity: np.ndarray  # [O, T, 2] m/s
    heading: np.ndarray  # [O, T] rad (unit already detected)
    valid: np.ndarray  # [O, T] bool
    size: np.ndarray  # [O, 2] (width, length) m
    ids: list[str]  # [O]


def _err(source: str, field: str, msg: str) -> ValueError:
    return ValueError(f"{source}: {field}: {msg}")


def _xy(value: Any, n: int | None, source: str, field: str) -> np.ndarray:
    """[T, 2] from rows [{x, y, ...}] or columns {x: [T], y: [T]}."""
    try:
        if isinstance(value, Mapping):
            out = np.stack([np.asarray(value["x"], float), np.asarray(value["y"], float)], -1)
        elif isinstance(value, list):
            out = np.array([(p["x"], p["y"]) for p in value], float).reshape(len(value), 2)
        else:
            raise TypeError(f"expected a list or a dict, got {type(value).__name__}")
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise _err(source, field, f"expected x/y points ({e})") from e
    if out.ndim != 2 or (n is not None and len(out) != n):
        raise _err(source, field, f"expected {n} points, got shape {out.shape}")
    return out


def _vector(value: Any, n: int, source: str, field: str) -> np.ndarray:
    try:
        out = np.asarray(value, float)
    except (TypeError, ValueError, OverflowError) as e:
        raise _err(source, field, f"not a numeric list ({e})") from e
    if out.shape != (n,):
        raise _err(source, field, f"expected {n} values, got shape {out.shape}")
    return out


def _is_flag(value: Any) -> bool:
    return isinstance(value, bool) or (isinstance(value, int) and value in (0, 1))


def _flags(value: Any, n: int | None, source: str, field: str) -> np.ndarray:
    """bool [n] from a list of JSON booleans (0 and 1 allowed); anything else is named."""
    if not isinstance(value, list):
        raise _err(source, field, f"expected a list of booleans, got {type(value).__name__}")
    bad = [i for i, v in enumerate(value) if not _is_flag(v)]
    if bad:
        raise _err(source, field, f"expected booleans, got {value[bad[0]]!r}")
    if n is not None and len(value) != n:
        raise _err(source, field, f"expected {n} values, got {len(value)}")
    return np.asarray(value, bool)


def _scalar(obj: Mapping, key: str, source: str, field: str) -> float:
    value = obj.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _err(source, f"{field}.{key}", f"expected a number, got {value!r}")
    try:
        return float(value)
    except OverflowError as e:  # a JSON integer beyond float range
        raise _err(source, f"{field}.{key}", "integer out of float range") from e


def heading_unit_is_degrees(heading: np.ndarray, velocity: np.ndarray, valid: np.ndarray) -> bool:
    """Whether headings [O, T] are degrees, from their agreement with velocity directions."""
    speed = np.linalg.norm(velocity, axis=-1)
    moving = valid & (speed > MOVING_MPS) & np.isfinite(heading)
    if moving.sum() >= 5:
        direction = np.arctan2(velocity[..., 1], velocity[..., 0])[moving]
        h = heading[moving]

        def error(rad: np.ndarray) -> float:
            return float(np.mean(np.abs(np.angle(np.exp(1j * (rad - direction))))))

        return error(np.deg2rad(h)) < error(h)
    h = heading[valid & np.isfinite(heading)]
    return bool(h.size and np.max(np.abs(h)) > 2 * np.pi + 1e-3)


def read_tracks(objects: Any, source: str) -> tuple[Tracks, collections.Counter]:
    """The objects of a scenario; objects never valid or of unknown type are counted."""
    if not isinstance(objects, list) or not objects:
        raise _err(source, "objects", "expected a non-empty list")
    dropped: collections.Counter = collections.Counter()
    first = objects[0]
    if not isinstance(first, Mapping) or "valid" not in first:
        raise _err(source, "objects[0].valid", "missing")
    n_steps = len(_flags(first["valid"], None, source, "objects[0].valid"))
    kept = collections.defaultdict(list)
    for i, obj in enumerate(objects):
        field = f"objects[{i}]"
        if not isinstance(obj, Mapping):
            raise _err(source, field, f"expected a dict, got {type(obj).__name__}")
        valid = _flags(obj.get("valid"), n_steps, source, f"{field}.valid")
        otype = obj.get("type")
        if not isinstance(otype, str):
            raise _err(source, f"{field}.type", f"expected a string, got {otype!r}")
        if otype not in CLASS_FROM_TYPE:
            dropped[f"type:{otype}"] += int(valid.sum())
            continue
        kept["type"].append(otype)
        kept["valid"].append(valid)
        kept["position"].append(_xy(obj.get("position"), n_steps, source, f"{field}.position"))
        kept["velocity"].append(_xy(obj.get("velocity"), n_steps, source, f"{field}.velocity"))
        kept["heading"].append(_vector(obj.get("heading"), n_steps, source, f"{field}.heading"))
        kept["size"].append(
            (_scalar(obj, "width", source, field), _scalar(obj, "length", source, field))
        )
        kept["ids"].append(str(obj.get("id", i)))
    if not kept["type"]:
        raise _err(source, "objects", "no vehicle, pedestrian or cyclist")
    arrays = {k: np.stack(v) for k, v in kept.items() if k not in ("type", "ids")}
    if heading_unit_is_degrees(arrays["heading"], arrays["velocity"], arrays["valid"]):
        arrays["heading"] = np.deg2rad(arrays["heading"])
    tracks = Tracks(type=kept["type"], ids=kept["ids"], **arrays)
    return tracks, dropped


def estimate_sdc(tracks: Tracks) -> int:
    """Index of the likely recording vehicle: see the module docstring. -1 when none."""
    always = np.flatnonzero(
        np.array([t == "vehicle" for t in tracks.type]) & tracks.valid.all(axis=1)
    )
    if len(always) == 0:
        return -1
    reach = []
    for i in always:  # mean over steps of the distance to the farthest other valid object
        dist = np.linalg.norm(tracks.position - tracks.position[i][None], axis=-1)  # [O, T]
        dist = np.where(tracks.valid, dist, -np.inf)
        dist[i] = -np.inf
        farthest = dist.max(axis=0)
        reach.append(
            np.mean(farthest[np.isfinite(farthest)]) if np.isfinite(farthest).any() else 0.0
        )
    return int(always[int(np.argmin(reach))])


def find_sdc(data: Mapping, tracks: Tracks, objects: list, source: str) -> int:
    """Index into `tracks` of the ego: the file's SDC marker, else `estimate_sdc`."""
    meta = data.get("metadata")
    if meta is not None and not isinstance(meta, Mapping):
        raise _err(source, "metadata", f"expected an object, got {type(meta).__name__}")
    if isinstance(meta, Mapping) and "sdc_track_index" in meta:
        index = meta["sdc_track_index"]
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(objects):
            raise _err(source, "metadata.sdc_track_index", f"not an object index: {index!r}")
        # Objects of unknown types were left out of `tracks`: count the kept ones before it.
        kept_before = sum(
            1
            for o in objects[:index]
            if isinstance(o, Mapping) and o.get("type") in CLASS_FROM_TYPE
        )
        if objects[index].get("type") != "vehicle":
            raise _err(source, "metadata.sdc_track_index", "the SDC is not a vehicle")
        return kept_before
    sdc = estimate_sdc(tracks)
    if sdc < 0:
        raise _err(source, "objects", "no SDC marker and no vehicle valid at every step")
    return sdc


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


def read_map(roads: Any, source: str) -> tuple[VectorMap, collections.Counter]:
    """The world-frame VectorMap of a scenario's `roads` and counts of unused features."""
    if not isinstance(roads, list):
        raise _err(source, "roads", f"expected a list, got {type(roads).__name__}")
    dropped: collections.Counter = collections.Counter()
    centerlines, lines, untyped, crosswalks, driveways = [], [], [], [], []
    for i, road in enumerate(roads):
        field = f"roads[{i}]"
        rtype = road.get("type") if isinstance(road, Mapping) else None
        if not isinstance(rtype, str):
            raise _err(source, f"{field}.type", f"expected a string, got {rtype!r}")
        if rtype in DROPPED_ROAD_TYPES:
            dropped[f"map:{rtype}"] += 1
            continue
        points = _xy(road.get("geometry"), None, source, f"{field}.geometry")
        if not np.all(np.isfinite(points)):
            raise _err(source, f"{field}.geometry", "NaN or inf coordinate")
        points = points[distinct_points(points, 1e-6)]
        min_points = 3 if rtype in ("crosswalk", "driveway") else 2
        if len(points) < min_points:
            dropped[f"map:degenerate_{rtype}"] += 1
            continue
        element = road.get("map_element_id")
        if rtype == "lane":
            lane_type = "BIKE" if element == BIKE_LANE_ELEMENT_ID else "VEHICLE"
            centerlines.append(Centerline(id=len(centerlines), lane_type=lane_type, points=points))
        elif rtype == "road_edge":
            lines.append(RoadLine(points, ROAD_EDGE))
        elif rtype == "road_line":
            if element in MARK_FROM_ELEMENT_ID:
                lines.append(RoadLine(points, MARK_FROM_ELEMENT_ID[element]))
            else:
                untyped.append(points)
        elif rtype == "crosswalk":
            crosswalks.append(points)
        elif rtype == "driveway":
            driveways.append(points)
        else:
            dropped[f"map:{rtype}"] += 1
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
        dataset="waymo",  # GPUDrive's and Nocturne's JSON scenes are WOMD's
    )
    return vmap, dropped


def velocity_mismatch(tracks: Tracks) -> bool:
    """Whether the file's velocities disagree with finite differences of the positions."""
    pos, valid = tracks.position, tracks.valid
    both = valid[:, 2:] & valid[:, :-2]
    fd = (pos[:, 2:] - pos[:, :-2]) / (2 * STEP_S)
    v = tracks.velocity[:, 1:-1]
    moving = both & (np.linalg.norm(fd, axis=-1) > MOVING_MPS)
    if moving.sum() < 10:
        return False
    rel = np.linalg.norm(v[moving] - fd[moving], axis=-1) / np.linalg.norm(fd[moving], axis=-1)
    return bool(np.median(rel) > 0.3)


def _se2(x: float, y: float, theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def frames_from_scenario(
    data: Any, source: str, stride: int
) -> tuple[list[Frame], collections.Counter]:
    """Frames at steps 0, stride, 2 stride, ... where the ego is valid, and the drop counts
    (the steps where it is not: "frame:no_ego"; none at all raises ValueError).

    Rows valid at a frame's step are either actors of the frame or counted drops (unknown
    types, NaN/inf, non-positive box sizes of vehicles and cyclists). NaN/inf in the ego's
    state at a frame's step, or an ego box size that is not positive, raise ValueError.
    """
    if not isinstance(data, Mapping):
        raise _err(source, "scenario", f"expected a JSON object, got {type(data).__name__}")
    objects = data.get("objects")
    tracks, dropped = read_tracks(objects, source)
    sdc = find_sdc(data, tracks, objects, source)
    world_map, map_dropped = read_map(data.get("roads"), source)
    dropped.update(map_dropped)
    if velocity_mismatch(tracks):
        dropped["quirk:velocity_mismatch_files"] += 1
    scenario_id = str(data.get("scenario_id") or Path(source).stem)
    boxed = np.array([t != "pedestrian" for t in tracks.type])
    sdc_field = f"objects (the SDC, id {tracks.ids[sdc]})"
    if not (np.all(np.isfinite(tracks.size[sdc])) and np.all(tracks.size[sdc] > 0)):
        size = tracks.size[sdc]
        raise _err(source, f"{sdc_field}.width/length", f"not finite and positive: {size}")
    frames = []
    n_steps = tracks.valid.shape[1]
    for t in range(0, n_steps, stride):
        if not tracks.valid[sdc, t]:
            dropped["frame:no_ego"] += 1
            continue
        for name in ("position", "velocity", "heading"):
            if not np.all(np.isfinite(getattr(tracks, name)[sdc, t])):
                raise _err(source, f"{sdc_field}.{name}", f"NaN or inf at step {t}")
        rows = np.flatnonzero(tracks.valid[:, t])
        rows = rows[rows != sdc]
        bad_size = boxed[rows] & np.any(tracks.size[rows] <= 0, axis=1)
        finite = (
            np.all(np.isfinite(tracks.position[rows, t]), axis=1)
            & np.all(np.isfinite(tracks.velocity[rows, t]), axis=1)
            & np.isfinite(tracks.heading[rows, t])
            & np.all(np.isfinite(tracks.size[rows]), axis=1)
        )
        dropped["invalid:size"] += int(np.sum(bad_size & finite))
        dropped["invalid:nan"] += int(np.sum(~finite))
        rows = rows[finite & ~bad_size]
        x0, y0 = tracks.position[sdc, t]
        h0 = float(tracks.heading[sdc, t])
        ego_from_world = rotation_matrix(-h0)
        vmap = world_map.crop(np.array([x0, y0]), MAP_RADIUS_M)
        vmap = vmap.transform(ego_from_world, -ego_from_world @ np.array([x0, y0]))
        frames.append(
            Frame(
                scene_id=f"{scenario_id}/{t}",
                source=source,
                cls=np.array([CLASS_FROM_TYPE[tracks.type[r]] for r in rows], np.int32),
                position=(tracks.position[rows, t] - (x0, y0)) @ ego_from_world.T,
                size=tracks.size[rows].astype(np.float64),
                heading=wrap_angle(tracks.heading[rows, t] - h0),
                velocity=tracks.velocity[rows, t] @ ego_from_world.T,
                track_id=np.asarray([tracks.ids[r] for r in rows], dtype=str),
                ego_velocity=ego_from_world @ tracks.velocity[sdc, t],
                ego_size=tracks.size[sdc].astype(np.float64),
                map=vmap,
                city_from_ego=_se2(x0, y0, h0),
            )
        )
    if not frames:
        raise _err(source, f"{sdc_field}.valid",
                   f"the SDC is valid at none of the steps 0, {stride}, ... of {n_steps}")
    dropped = collections.Counter({k: v for k, v in dropped.items() if v})
    return frames, dropped


def scenario_files(root: str | os.PathLike) -> list[Path]:
    """Sorted `*.json` scenario files under `root` (`files.files_under`: recursive, links
    followed, each file once)."""
    files = files_under(root, ".json")
    if not files:
        raise FileNotFoundError(f"{root}: no GPUDrive / Nocturne JSON files (*.json)")
    return files


def read_file(path: str | os.PathLike, stride: int) -> tuple[list[Frame], collections.Counter]:
    """Frames and drop counts of one JSON scenario file; errors name the file and field."""
    return frames_from_scenario(read_json(path), str(path), stride)
