"""Argoverse 2 vector maps: a sensor log's or a forecasting scenario's `log_map_archive_*.json`
read into a `VectorMap` in the city frame, with degenerate elements dropped and counted."""

from __future__ import annotations

import collections
import glob
import logging
import os

import numpy as np

from scenegen_jax.jsonfile import read_json
from scenegen_jax.vector_map import LANE_TYPES, Lane, VectorMap

log = logging.getLogger(__name__)
# Map polygons (lanes, crosswalks, drivable areas) with less area are degenerate, m^2.
MIN_POLYGON_AREA_M2 = 1e-6


def read_map(log_dir: str) -> tuple[VectorMap, collections.Counter]:
    """The log's vector map in the city frame, and counts of degenerate elements dropped."""
    paths = sorted(glob.glob(os.path.join(log_dir, "map", "log_map_archive_*.json")))
    if not paths:
        raise FileNotFoundError(
            f"{os.path.join(log_dir, 'map')}: no log_map_archive_*.json map file"
        )
    return read_map_file(paths[0])


def read_map_file(path: str) -> tuple[VectorMap, collections.Counter]:
    """The vector map of one `log_map_archive_*.json` file (a sensor log's or a forecasting
    scenario's: one schema) in the city frame, and counts of degenerate elements dropped."""
    try:
        data = read_json(path)
    except OSError as e:
        raise ValueError(f"{path}: unreadable map JSON ({e})") from e
    return vector_map_from_json(data, path)


def _points(obj: dict, key: str, path: str, where: str) -> np.ndarray:
    """[P, 2] points (m) of the list `obj[key]`; missing, malformed or NaN/inf raise."""
    field = f"{where}.{key}"
    items = obj.get(key)
    if items is None:
        raise ValueError(f"{path}: field {field}: missing")
    if not isinstance(items, list):
        raise ValueError(f"{path}: field {field}: expected a list of points")
    try:
        pts = np.array([[p["x"], p["y"]] for p in items], np.float64).reshape(-1, 2)
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"{path}: field {field}: malformed point list ({e})") from e
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{path}: field {field}: NaN or inf coordinate")
    return pts


def _integer(value: object, path: str, field: str) -> int:
    """An integer id (an int, an integral float or a decimal string); ValueError naming the
    file and field for anything else (None, lists, booleans, NaN, inf, "abc")."""
    if isinstance(value, bool):
        raise ValueError(f"{path}: field {field}: expected an integer id, got {value!r}")
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, int) or (isinstance(value, str) and value.strip().lstrip("-").isdigit()):
        return int(value)
    raise ValueError(f"{path}: field {field}: expected an integer id, got {value!r}")


def _integers(value: object, path: str, field: str) -> tuple[int, ...]:
    """A tuple of integer ids from a list (missing or null: none)."""
    if value is None:
        return ()
    if not isinstance(value, list):
        raise ValueError(f"{path}: field {field}: expected a list of ids, got {value!r}")
    return tuple(_integer(v, path, f"{field}[{i}]") for i, v in enumerate(value))


def _entries(data: dict, key: str, path: str) -> list[tuple[str, dict]]:
    """(id, element) pairs of a top-level map field; raises naming the field if malformed."""
    if key not in data:
        raise ValueError(f"{path}: missing field {key}")
    if not isinstance(data[key], dict):
        raise ValueError(f"{path}: field {key}: expected an object of elements by id")
    for eid, element in data[key].items():
        if not isinstance(element, dict):
            raise ValueError(f"{path}: field {key}[{eid}]: expected an object")
    return list(data[key].items())


def polygon_area(points: np.ndarray) -> float:
    """Unsigned (shoelace) area of a closed polygon [P, 2] in m, m^2; 0 below 3 points."""
    if len(points) < 3:
        return 0.0
    x, y = (points - points[0]).T  # about a vertex: city coordinates are ~1e4 m
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _lane_ok(left: np.ndarray, right: np.ndarray) -> bool:
    """Whether both boundaries have a length and the lane outline has an area."""

    def has_length(points: np.ndarray) -> bool:
        return len(points) >= 2 and bool(np.any(np.diff(points, axis=0) != 0))

    outline = np.concatenate([left, right[::-1]], axis=0)
    return has_length(left) and has_length(right) and polygon_area(outline) > MIN_POLYGON_AREA_M2


# Argoverse 2's lane mark types (its `LaneMarkType`); another is counted and not drawn.
MARK_TYPES = frozenset({
    "DASH_SOLID_YELLOW", "DASH_SOLID_WHITE", "DASHED_WHITE", "DASHED_YELLOW",
    "DOUBLE_SOLID_YELLOW", "DOUBLE_SOLID_WHITE", "DOUBLE_DASH_YELLOW", "DOUBLE_DASH_WHITE",
    "SOLID_YELLOW", "SOLID_WHITE", "SOLID_DASH_WHITE", "SOLID_DASH_YELLOW", "SOLID_BLUE",
    "NONE", "UNKNOWN",
})


def _mark(seg: dict, key: str, dropped: collections.Counter) -> str:
    """A lane's mark type; one Argoverse 2 does not have is counted and read as UNKNOWN."""
    mark = seg.get(key, "NONE")
    if mark in MARK_TYPES:
        return mark
    dropped["map:unknown_mark_type"] += 1
    return "UNKNOWN"


def _flag(seg: dict, key: str, path: str, field: str) -> bool:
    value = seg.get(key, False)
    if not isinstance(value, bool):
        raise ValueError(f"{path}: field {field}: expected true or false, got {value!r}")
    return value


def vector_map_from_json(data: dict, path: str) -> tuple[VectorMap, collections.Counter]:
    """Parses an Argoverse 2 `log_map_archive` dict.

    Degenerate elements are dropped and counted ("map:degenerate_lane": a boundary without
    length or an outline without area; "map:degenerate_crosswalk" and
    "map:degenerate_drivable_area": a polygon without area, e.g. fewer than 3 points), and
    so are lane mark types Argoverse 2 does not have ("map:unknown_mark_type", not drawn).
    Missing fields, malformed points and NaN/inf raise ValueError naming the file and field.
    """
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object")
    dropped: collections.Counter = collections.Counter()
    lanes = []
    for lid, seg in _entries(data, "lane_segments", path):
        where = f"lane_segments[{lid}]"
        lane_type = str(seg.get("lane_type", "VEHICLE"))
        if lane_type not in LANE_TYPES:
            raise ValueError(f"{path}: field {where}.lane_type: unknown {lane_type!r}")
        left = _points(seg, "left_lane_boundary", path, where)
        right = _points(seg, "right_lane_boundary", path, where)
        if not _lane_ok(left, right):
            dropped["map:degenerate_lane"] += 1
            continue
        lanes.append(
            Lane(
                id=_integer(seg.get("id", lid), path, f"{where}.id"),
                lane_type=lane_type,
                left=left,
                right=right,
                left_mark=_mark(seg, "left_lane_mark_type", dropped),
                right_mark=_mark(seg, "right_lane_mark_type", dropped),
                is_intersection=_flag(seg, "is_intersection", path, f"{where}.is_intersection"),
                successors=_integers(seg.get("successors"), path, f"{where}.successors"),
                predecessors=_integers(seg.get("predecessors"), path, f"{where}.predecessors"),
            )
        )
    crosswalks = []
    for cid, cw in _entries(data, "pedestrian_crossings", path):
        where = f"pedestrian_crossings[{cid}]"
        e1, e2 = (_points(cw, k, path, where) for k in ("edge1", "edge2"))
        polygon = np.concatenate([e1, e2[::-1]], axis=0)
        if polygon_area(polygon) > MIN_POLYGON_AREA_M2:
            crosswalks.append(polygon)
        else:
            dropped["map:degenerate_crosswalk"] += 1
    areas = []
    for did, da in _entries(data, "drivable_areas", path):
        polygon = _points(da, "area_boundary", path, f"drivable_areas[{did}]")
        if polygon_area(polygon) > MIN_POLYGON_AREA_M2:
            areas.append(polygon)
        else:
            dropped["map:degenerate_drivable_area"] += 1
    for reason, n in sorted(dropped.items()):
        log.warning("%s: %d map elements dropped (%s)", path, n, reason)
    vmap = VectorMap(lanes=tuple(lanes), crosswalks=tuple(crosswalks),
                     drivable_areas=tuple(areas), dataset="av2")
    return vmap, dropped
