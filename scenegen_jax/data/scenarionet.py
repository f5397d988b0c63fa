"""ScenarioNet / MetaDrive scenario import and export.

A ScenarioNet scenario is a dict with the top-level keys `id`, `version`, `length`, `tracks`,
`map_features`, `metadata` and `dynamic_map_states`, pickled one per file. Coordinates are a
right-handed world frame in metres (x, y, z), headings rad, velocities m/s in that frame.

Import (`frames_from_scenario`, `read_scenarionet`) builds one `Frame` per requested step in
the SDC's ego frame. It accepts what ScenarioNet's converters (Waymo, nuScenes, nuPlan,
Argoverse 2, in their current and older versions) and MetaDrive's older Waymo pickles write,
not only our own exports; every difference is detected from the data:

- per-step arrays stored as [T] or [T, 1] (nuScenes and nuPlan write `length`, `width`,
  `height` as [T, 1]; MetaDrive's old Waymo pickles `heading` and `valid` as [T, 1]);
- box sizes as `length` / `width` or as `size` [T, 3] = (length, width, height);
- `valid` as bool or as 0/1 floats;
- the SDC as `metadata.sdc_id`, else a `sdc_track_index` (top level or in `metadata`) that
  is a track id (int or str) or, failing that, an index into `tracks`;
- time stamps in `metadata.ts` or a top-level `ts` (`scenario_sample_rate_hz`);
- no `metadata` and no `length` at all (old MetaDrive Waymo pickles).

Track types VEHICLE / PEDESTRIAN / CYCLIST map to our classes; every other type (OTHER,
TRAFFIC_CONE, TRAFFIC_BARRIER, UNSET, ...) is dropped and counted in a `Counter` (key:
"type:<TYPE>"), as are actors with NaN/inf in a valid step ("invalid:nan") and vehicles or
cyclists with a non-positive box size ("invalid:size"). Converter quirks are detected and
counted ("quirk:<name>"), never trusted blindly; see `frames_from_scenario`. Map features the
VectorMap cannot hold are counted as "map:<TYPE>". Nothing is dropped silently; structural
problems (missing tracks or SDC, wrong shapes, NaN in the SDC or in map geometry) raise
ValueError naming the file and the field.

Export (`scenario_from_frame`, `write_scenario`, `write_dataset`) writes a one-step scenario in
the ego frame. Standard keys are filled as ScenarioNet's converters fill them, so simulators can
replay it; what the standard keys cannot carry (exact lane boundaries, BUS lanes, mark types,
intersection flags, the ego pose in the city) goes into extra keys prefixed `scenegen_`, which
take precedence on import, so export -> import is lossless up to float32 rounding of tracks.
Files from real converters carry only the standard keys; their maps are read as described in
`map_from_features`.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from scenegen_jax import __version__
from scenegen_jax.data import surface
from scenegen_jax.data.frame import Frame
from scenegen_jax.data.safe_pickle import dump_pickle, load_pickle
from scenegen_jax.data.surface import Centerline, normals, outline_lanes, ray_distances
from scenegen_jax.data.vector_map import (
    ROAD_EDGE,
    Lane,
    RoadLine,
    VectorMap,
    resample_polyline,
    rotation_matrix,
)
from scenegen_jax.scene import BICYCLIST, NUM_CLASSES, PEDESTRIAN, VEHICLE

DEFAULT_HALF_WIDTH_M = surface.DEFAULT_HALF_WIDTH_M
# A converter's per-point lane `width` (half widths to the left / right boundary) is used only
# in this range; elsewhere the half width is measured from the map's lines. On the WOMD
# ScenarioNet pickles in ../shared/data/womd_mini, half widths <= 2.5 m agree with the
# perpendicular distance to the nearest line within 2 cm (median); larger ones (about a quarter
# of them, up to 177 m) are off by about 3 m, because the Waymo converter matches boundary
# points by nearest index and copies one side's width to the other.
MIN_GIVEN_HALF_WIDTH_M = surface.MIN_HALF_WIDTH_M
MAX_GIVEN_HALF_WIDTH_M = 2.5
DEFAULT_STEP_S = 0.1  # when a file has no usable `ts`
MOVING_MPS = 2.0
VELOCITY_MISMATCH_REL_ERR = 0.3
MIN_MOVING_SAMPLES = 10
SUMMARY_FILE = "dataset_summary.pkl"
MAPPING_FILE = "dataset_mapping.pkl"
TOP_LEVEL_KEYS = ("id", "version", "length", "tracks", "map_features", "metadata")

CLASS_FROM_TYPE: dict[str, int] = {
    "VEHICLE": VEHICLE,
    "PEDESTRIAN": PEDESTRIAN,
    "CYCLIST": BICYCLIST,
}
TYPE_FROM_CLASS: dict[int, str] = {v: k for k, v in CLASS_FROM_TYPE.items()}
# Nominal heights (m); our frames carry no height but ScenarioNet tracks do.
_HEIGHT_M = {VEHICLE: 1.6, PEDESTRIAN: 1.75, BICYCLIST: 1.75}

LANE_FEATURE_TYPES = frozenset(
    {
        "LANE_SURFACE_STREET",
        "LANE_SURFACE_UNSTRUCTURE",
        "LANE_UNKNOWN",
        "LANE_FREEWAY",
        "LANE_BIKE_LANE",
    }
)
# Keys only a lane has: MetaDrive's old Waymo pickles type lanes of unknown type "UNKNOWN",
# the same string Waymo's unknown road lines and road edges get.
_LANE_ONLY_KEYS = ("entry_lanes", "exit_lanes", "left_boundaries", "right_boundaries")
# Kerbs and road edges (MetaDrive's BOUNDARY_LINE is "ROAD_EDGE_BOUNDARY").
ROAD_EDGE_FEATURE_TYPES = frozenset(
    {"ROAD_EDGE_BOUNDARY", "ROAD_EDGE_MEDIAN", "ROAD_EDGE_UNKNOWN", "BOUNDARY_LINE"}
)
# The nuScenes, nuPlan and Argoverse 2 converters write the outline of the drivable area as
# features "boundary_<n>" typed ROAD_LINE_SOLID_SINGLE_WHITE: they are road edges.
DRIVABLE_OUTLINE_ID_PREFIX = "boundary_"
CROSSWALK_FEATURE_TYPES = frozenset({"CROSSWALK", "CROSS_WALK"})
DRIVEWAY_FEATURE_TYPES = frozenset({"DRIVEWAY"})
# Argoverse 2 mark names (our Lane.left_mark / right_mark) -> ScenarioNet line types, as in
# ScenarioNet's own Argoverse 2 converter.
LINE_TYPE_FROM_MARK: dict[str, str] = {
    "DOUBLE_SOLID_YELLOW": "ROAD_LINE_SOLID_DOUBLE_YELLOW",
    "DOUBLE_SOLID_WHITE": "ROAD_LINE_SOLID_DOUBLE_WHITE",
    "SOLID_YELLOW": "ROAD_LINE_SOLID_SINGLE_YELLOW",
    "SOLID_WHITE": "ROAD_LINE_SOLID_SINGLE_WHITE",
    "DASHED_WHITE": "ROAD_LINE_BROKEN_SINGLE_WHITE",
    "DASHED_YELLOW": "ROAD_LINE_BROKEN_SINGLE_YELLOW",
    "DASH_SOLID_YELLOW": "ROAD_LINE_SOLID_DOUBLE_YELLOW",
    "DASH_SOLID_WHITE": "ROAD_LINE_SOLID_DOUBLE_WHITE",
    "DOUBLE_DASH_YELLOW": "ROAD_LINE_BROKEN_SINGLE_YELLOW",
    "DOUBLE_DASH_WHITE": "ROAD_LINE_BROKEN_SINGLE_WHITE",
    "SOLID_DASH_WHITE": "ROAD_LINE_BROKEN_SINGLE_WHITE",
    "SOLID_DASH_YELLOW": "ROAD_LINE_BROKEN_SINGLE_YELLOW",
}
# ScenarioNet line types -> the closest Argoverse 2 mark name (crossability preserved).
MARK_FROM_LINE_TYPE: dict[str, str] = {
    "ROAD_LINE_BROKEN_SINGLE_WHITE": "DASHED_WHITE",
    "ROAD_LINE_SOLID_SINGLE_WHITE": "SOLID_WHITE",
    "ROAD_LINE_SOLID_DOUBLE_WHITE": "DOUBLE_SOLID_WHITE",
    "ROAD_LINE_BROKEN_SINGLE_YELLOW": "DASHED_YELLOW",
    "ROAD_LINE_BROKEN_DOUBLE_YELLOW": "DOUBLE_DASH_YELLOW",
    "ROAD_LINE_SOLID_SINGLE_YELLOW": "SOLID_YELLOW",
    "ROAD_LINE_SOLID_DOUBLE_YELLOW": "DOUBLE_SOLID_YELLOW",
    "ROAD_LINE_PASSING_DOUBLE_YELLOW": "SOLID_DASH_YELLOW",
    "UNKNOWN_LINE": "UNKNOWN",
}


class ImportedFrame(NamedTuple):
    """One imported frame and what was dropped from it, or found odd in it: a Counter of
    "type:<TYPE>", "invalid:<why>", "map:<TYPE>" and "quirk:<name>" keys (see
    `frames_from_scenario`)."""

    frame: Frame
    dropped: collections.Counter


# ----------------------------------------------------------------------------- import


def _err(source: str, field: str, msg: str) -> ValueError:
    return ValueError(f"{source}: {field}: {msg}")


def _get(d: Any, key: str, source: str, field: str) -> Any:
    if not isinstance(d, Mapping):
        raise _err(source, field, f"expected a dict, got {type(d).__name__}")
    if key not in d:
        raise _err(source, f"{field}.{key}" if field else key, "missing")
    return d[key]


def _array(
    value: Any, source: str, field: str, ndim: int, min_cols: int = 0, dtype=np.float64
) -> np.ndarray:
    """A numeric array of `ndim` dims (at least `min_cols` columns); finiteness checked later."""
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError, OverflowError) as e:
        raise _err(source, field, f"not a numeric array ({e})") from e
    if arr.ndim != ndim or (ndim == 2 and arr.shape[1] < min_cols):
        want = f"[N, >={min_cols}]" if ndim == 2 else "[N]"
        raise _err(source, field, f"expected shape {want}, got {arr.shape}")
    return arr


def _series(value: Any, source: str, field: str) -> np.ndarray:
    """[T] float64 of a per-step scalar stored as [T] or [T, 1]."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as e:
        raise _err(source, field, f"not a numeric array ({e})") from e
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.ndim != 1:
        raise _err(source, field, f"expected shape [N] or [N, 1], got {arr.shape}")
    return arr


def _valid_mask(value: Any, source: str, field: str) -> np.ndarray:
    """[T] bool of a `valid` array stored as bool or 0/1 numbers, [T] or [T, 1]."""
    arr = np.asarray(value)
    if arr.dtype != bool:
        arr = _series(value, source, field)
        if not np.all(np.isfinite(arr)):
            raise _err(source, field, "NaN or inf")
        return arr != 0
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.ndim != 1:
        raise _err(source, field, f"expected shape [N] or [N, 1], got {arr.shape}")
    return arr


def _polyline(value: Any, source: str, field: str, min_points: int = 1) -> np.ndarray:
    """[P, 2] float64 from a [P, 2] or [P, 3] polyline; NaN/inf or too few points raise."""
    pts = _array(value, source, field, 2, min_cols=2)[:, :2]
    if len(pts) < min_points:
        raise _err(source, field, f"needs at least {min_points} points, got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise _err(source, field, "NaN or inf coordinate")
    return pts


def _geometry(feature: Mapping, keys: Sequence[str], source: str, field: str) -> np.ndarray:
    """[P, 2] points of the first of `keys` the feature has (NaN/inf raise; P may be 0)."""
    for key in keys:
        if key in feature:
            pts = _array(feature[key], source, f"{field}.{key}", 2, min_cols=2)[:, :2]
            if not np.all(np.isfinite(pts)):
                raise _err(source, f"{field}.{key}", "NaN or inf coordinate")
            return pts
    raise _err(source, f"{field}.{keys[0]}", "missing")


def _canonical_int(key: Any) -> int | None:
    s = str(key)
    return int(s) if re.fullmatch(r"-?[1-9][0-9]*|0", s) else None


def _keep_mask(points: np.ndarray) -> np.ndarray:
    """[P] bool: drop points that repeat the previous one."""
    if len(points) == 0:
        return np.zeros(0, bool)
    return np.concatenate([[True], np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-9])


def _dedupe(points: np.ndarray) -> np.ndarray:
    return points[_keep_mask(points)]


def _ring(points: np.ndarray) -> np.ndarray:
    """A polygon outline without repeated points. An early nuScenes converter wrote each lane
    outline twice (z = 0.1, then z = 0): such a doubled ring is read once."""
    n = len(points)
    if n >= 6 and n % 2 == 0 and np.allclose(points[: n // 2], points[n // 2 :]):
        points = points[: n // 2]
    return _dedupe(points)


def _distinct_points(ring: np.ndarray) -> int:
    closed = len(ring) > 1 and np.allclose(ring[0], ring[-1])
    return len(ring) - int(closed)


def _feature_kind(fid: Any, ftype: str, feature: Mapping) -> str | None:
    """How a map feature is read: "lane", "line", "edge", "crosswalk", "driveway", our own
    "lane_boundary" / "drivable_area" / "own_line" extras, or None (not representable)."""
    kind = feature.get("scenegen_kind")
    if kind in ("lane_boundary", "drivable_area"):
        return kind
    if kind == "line":
        return "own_line"
    if ftype in LANE_FEATURE_TYPES or (
        ftype == "UNKNOWN" and any(k in feature for k in _LANE_ONLY_KEYS)
    ):
        return "lane"
    if ftype in ROAD_EDGE_FEATURE_TYPES:
        return "edge"
    if ftype in MARK_FROM_LINE_TYPE or ftype.startswith("ROAD_LINE_") or ftype == "UNKNOWN":
        return "edge" if str(fid).startswith(DRIVABLE_OUTLINE_ID_PREFIX) else "line"
    if ftype in CROSSWALK_FEATURE_TYPES:
        return "crosswalk"
    if ftype in DRIVEWAY_FEATURE_TYPES:
        return "driveway"
    return None


def _mark_from_boundaries(entries: Any, features: Mapping, line_ids: set[str]) -> str:
    """The Argoverse 2 mark name of a lane side from ScenarioNet `left/right_boundaries`.

    "NONE" when the side has no boundary entry, or when its boundary feature is a line of this
    file: that line is a `RoadLine` of the map and drawn as itself.
    """
    if not isinstance(entries, (list, tuple)) or not entries:
        return "NONE"
    entry = entries[0]
    if not isinstance(entry, Mapping):
        return "NONE"
    ref_id = str(entry.get("boundary_feature_id", ""))
    if ref_id in line_ids:
        return "NONE"
    line_type = entry.get("boundary_type")
    if not (isinstance(line_type, str) and line_type in MARK_FROM_LINE_TYPE):
        ref = features.get(ref_id)
        line_type = ref.get("type") if isinstance(ref, Mapping) else None
    return MARK_FROM_LINE_TYPE.get(line_type, "NONE") if isinstance(line_type, str) else "NONE"


def _exact_lane(fid: Any, feature: Mapping, lane_id: int, links: tuple, source: str) -> Lane:
    """A Lane from one of our exported lane features (exact boundaries in `scenegen_*`)."""
    field = f"map_features[{fid!r}]"
    ftype = feature["type"]
    left = _polyline(feature["scenegen_left"], source, f"{field}.scenegen_left", 2)
    right = _polyline(feature["scenegen_right"], source, f"{field}.scenegen_right", 2)
    default_type = "BIKE" if ftype == "LANE_BIKE_LANE" else "VEHICLE"
    successors, predecessors = links
    return Lane(
        id=lane_id,
        lane_type=str(feature.get("scenegen_lane_type", default_type)),
        left=left,
        right=right,
        left_mark=str(feature.get("scenegen_left_mark", "NONE")),
        right_mark=str(feature.get("scenegen_right_mark", "NONE")),
        is_intersection=bool(
            feature.get("scenegen_is_intersection", ftype == "LANE_SURFACE_UNSTRUCTURE")
        ),
        successors=successors,
        predecessors=predecessors,
    )


class _RealLane(NamedTuple):
    """A converter's lane: centreline (+ half widths), its outline polygon if any, its marks."""

    centerline: Centerline
    polygon: np.ndarray | None
    left_mark: str
    right_mark: str


def _real_lane(
    fid: Any,
    feature: Mapping,
    lane_id: int,
    links: tuple,
    features: Mapping,
    line_ids: set[str],
    source: str,
) -> _RealLane | None:
    """A converter's lane feature as a Centerline; None for a degenerate (zero-length) one.

    Half widths: the converter's `width` [P, 2] (Waymo: distances to the left / right boundary
    line) where it is aligned with the centreline and within [MIN_GIVEN_HALF_WIDTH_M,
    MAX_GIVEN_HALF_WIDTH_M]; else the distance along the normal to the lane's own `polygon`
    (nuScenes, nuPlan); else unknown (0), which `outline_lanes` measures from the map's lines.
    """
    field = f"map_features[{fid!r}]"
    ftype = feature["type"]
    raw = _polyline(_get(feature, "polyline", source, field), source, f"{field}.polyline")
    keep = _keep_mask(raw)
    center = raw[keep]
    if len(center) < 2:
        return None
    half = np.zeros((len(center), 2))
    try:
        w = np.asarray(feature.get("width", ()), dtype=np.float64)
    except (TypeError, ValueError):  # unusable: measured from the lines instead
        w = np.zeros(0)
    if w.shape == (len(raw), 2):
        w = w[keep]
        ok = np.isfinite(w) & (w >= MIN_GIVEN_HALF_WIDTH_M) & (w <= MAX_GIVEN_HALF_WIDTH_M)
        half = np.where(ok, w, 0.0)
    polygon = None
    if "polygon" in feature:
        ring = _ring(_geometry(feature, ("polygon",), source, field))
        if _distinct_points(ring) >= 3:
            polygon = ring
            closed = (
                np.concatenate([ring, ring[:1]]) if _distinct_points(ring) == len(ring) else ring
            )
            segs = np.stack([closed[:-1], closed[1:]], axis=1)
            n = normals(center)
            max_m = 2 * surface.MAX_HALF_WIDTH_M
            from_polygon = np.stack(
                [ray_distances(center, n, max_m, segs), ray_distances(center, -n, max_m, segs)],
                axis=1,
            )
            use = (half <= 0) & np.isfinite(from_polygon) & (from_polygon > 0)
            half = np.where(use, from_polygon, half)
    successors, predecessors = links
    centerline = Centerline(
        id=lane_id,
        lane_type="BIKE" if ftype == "LANE_BIKE_LANE" else "VEHICLE",
        points=center,
        half_widths=half,
        successors=successors,
        predecessors=predecessors,
        # nuScenes' lane connectors; other converters say nothing: inferred from crossings.
        is_intersection=True if ftype == "LANE_SURFACE_UNSTRUCTURE" else None,
    )
    return _RealLane(
        centerline,
        polygon,
        _mark_from_boundaries(feature.get("left_boundaries"), features, line_ids),
        _mark_from_boundaries(feature.get("right_boundaries"), features, line_ids),
    )


def _outline(real: Sequence[_RealLane], lines: Sequence[RoadLine]) -> tuple[list, list]:
    """(lanes, drivable polygons) of converter lanes, via `surface.outline_lanes`; a lane's
    own polygon, where the converter wrote one, is its drivable polygon."""
    lanes, areas = outline_lanes([r.centerline for r in real], lines)
    lanes = [
        dataclasses.replace(lane, left_mark=r.left_mark, right_mark=r.right_mark)
        for lane, r in zip(lanes, real, strict=True)
    ]
    drivable = [r.polygon if r.polygon is not None else a for r, a in zip(real, areas, strict=True)]
    return lanes, drivable


def map_from_features(map_features: Mapping, source: str) -> tuple[VectorMap, collections.Counter]:
    """The VectorMap (in the scenario's world frame) and counts of unusable features.

    Our own exports: lanes, lines, crosswalks and drivable areas come exactly from their
    `scenegen_*` extras; our lane-boundary features are part of their lanes.

    Real converters' features:
    - lanes (`LANE_*`, and "UNKNOWN" features with lane keys) are centrelines, outlined with
      `surface.outline_lanes` (see `_real_lane` for their half widths); each lane's drivable
      polygon is its own `polygon` where it has one (nuScenes, nuPlan), else the outline's;
    - `ROAD_LINE_*` / `UNKNOWN_LINE` become `RoadLine`s with the mark of `MARK_FROM_LINE_TYPE`
      ("UNKNOWN" for other line types and Waymo's "UNKNOWN" lines); ROAD_EDGE_BOUNDARY,
      ROAD_EDGE_MEDIAN (and BOUNDARY_LINE, ROAD_EDGE_UNKNOWN) and the drivable-area outlines
      "boundary_<n>" of the nuScenes / nuPlan / Argoverse 2 converters become
      `RoadLine(points, ROAD_EDGE)`;
    - CROSSWALK / CROSS_WALK `polygon` or `polyline` with >= 3 distinct points are crosswalks;
    - DRIVEWAY polygons join the drivable areas (driveways are drivable).
    Everything else (STOP_SIGN, lower-case stop_sign, SPEED_BUMP, ROAD_EDGE_SIDEWALK, ...) is
    counted as "map:<TYPE>", a feature whose `type` is not a string (MetaDrive's old pickles
    hold some whose type is the feature dict itself) as "map:malformed_type", and geometry too
    short to use as "map:degenerate_<kind>". NaN/inf coordinates raise ValueError.
    """
    if not isinstance(map_features, Mapping):
        raise _err(source, "map_features", f"expected a dict, got {type(map_features).__name__}")
    dropped: collections.Counter = collections.Counter()
    kinds: dict[Any, str] = {}
    for fid, feature in map_features.items():
        ftype = _get(feature, "type", source, f"map_features[{fid!r}]")
        if not isinstance(ftype, str):
            dropped["map:malformed_type"] += 1  # never str() it: it may contain itself
            continue
        kind = _feature_kind(fid, ftype, feature)
        if kind is None:
            dropped[f"map:{ftype}"] += 1
        else:
            kinds[fid] = kind
    lane_keys = [fid for fid, kind in kinds.items() if kind == "lane"]
    line_ids = {str(fid) for fid, kind in kinds.items() if kind in ("line", "edge")}
    # Integer lane ids when the file's ids are canonical integers (Argoverse, Waymo, ours);
    # otherwise (nuScenes, nuPlan tokens) ids are positions in file order.
    as_int = [_canonical_int(k) for k in lane_keys]
    int_ids = all(i is not None for i in as_int) and len(set(as_int)) == len(as_int)
    if int_ids:
        id_of = {str(k): i for k, i in zip(lane_keys, as_int, strict=True)}
    else:
        id_of = {str(k): n for n, k in enumerate(lane_keys)}

    def link_ids(value: Any) -> tuple[int, ...]:
        # Integer ids keep links to lanes outside this file (as a cropped Argoverse map does);
        # enumerated ids can only name lanes that are in it.
        if not isinstance(value, (list, tuple, np.ndarray)):
            return ()
        if int_ids:
            ints = (_canonical_int(x) for x in value)
            return tuple(i for i in ints if i is not None)
        return tuple(id_of[str(x)] for x in value if str(x) in id_of)

    exact, real, lines, crosswalks, own_drivable, driveways = [], [], [], [], [], []
    for fid, kind in kinds.items():
        feature = map_features[fid]
        field = f"map_features[{fid!r}]"
        ftype = feature["type"]
        if kind == "lane":
            links = (link_ids(feature.get("exit_lanes")), link_ids(feature.get("entry_lanes")))
            lane_id = id_of[str(fid)]
            if "scenegen_left" in feature and "scenegen_right" in feature:
                exact.append(_exact_lane(fid, feature, lane_id, links, source))
                continue
            lane = _real_lane(fid, feature, lane_id, links, map_features, line_ids, source)
            if lane is None:
                dropped["map:degenerate_lane"] += 1
            else:
                real.append(lane)
        elif kind == "lane_boundary":
            continue
        elif kind == "own_line":
            points = _polyline(feature.get("scenegen_points"), source, f"{field}.scenegen_points")
            lines.append(RoadLine(points, str(feature.get("scenegen_mark", "UNKNOWN"))))
        elif kind in ("line", "edge"):
            points = _dedupe(_geometry(feature, ("polyline", "polygon"), source, field))
            if len(points) < 2:
                dropped[f"map:degenerate_{kind}"] += 1
            elif kind == "edge":
                lines.append(RoadLine(points, ROAD_EDGE))
            else:
                lines.append(RoadLine(points, MARK_FROM_LINE_TYPE.get(ftype, "UNKNOWN")))
        elif "scenegen_polygon" in feature:  # our own crosswalks and drivable areas: exact
            poly = _polyline(feature["scenegen_polygon"], source, f"{field}.scenegen_polygon", 3)
            (own_drivable if kind == "drivable_area" else crosswalks).append(poly)
        else:  # a converter's crosswalk or driveway
            ring = _ring(_geometry(feature, ("polygon", "polyline"), source, field))
            if _distinct_points(ring) < 3:
                dropped[f"map:degenerate_{kind}"] += 1
            else:
                (crosswalks if kind == "crosswalk" else driveways).append(ring)
    outlined, lane_areas = _outline(real, lines)
    vmap = VectorMap(
        lanes=tuple(exact) + tuple(outlined),
        crosswalks=tuple(crosswalks),
        drivable_areas=tuple(own_drivable) + tuple(lane_areas) + tuple(driveways),
        lines=tuple(lines),
    )
    return vmap, dropped


class _Track(NamedTuple):
    """One track's state arrays (world frame), validated for shape."""

    type: str
    position: np.ndarray  # [T, 2] m
    width: np.ndarray  # [T] m
    length: np.ndarray  # [T] m
    heading: np.ndarray  # [T] rad
    velocity: np.ndarray  # [T, 2] m/s
    valid: np.ndarray  # [T] bool


def _read_track(tid: str, track: Any, length: int, source: str) -> _Track:
    field = f"tracks[{tid!r}]"
    ttype = track.get("type") if isinstance(track, Mapping) else None
    if not isinstance(ttype, str):
        meta = track.get("metadata") if isinstance(track, Mapping) else None
        ttype = meta.get("type") if isinstance(meta, Mapping) else None
    if not isinstance(ttype, str):
        raise _err(source, f"{field}.type", "missing or not a string")
    state = _get(track, "state", source, field)
    sf = f"{field}.state"
    position = _array(_get(state, "position", source, sf), source, f"{sf}.position", 2, 2)[:, :2]
    if "length" in state and "width" in state:
        lengths = _series(state["length"], source, f"{sf}.length")
        widths = _series(state["width"], source, f"{sf}.width")
    elif "size" in state:  # MetaDrive's older Waymo pickles: size [T, 3] = (length, width, height)
        size = _array(state["size"], source, f"{sf}.size", 2, 2)
        lengths, widths = size[:, 0], size[:, 1]
    else:
        raise _err(source, f"{sf}.length", "missing (and no size)")
    heading = _series(_get(state, "heading", source, sf), source, f"{sf}.heading")
    velocity = _array(_get(state, "velocity", source, sf), source, f"{sf}.velocity", 2, 2)[:, :2]
    valid = _valid_mask(_get(state, "valid", source, sf), source, f"{sf}.valid")
    arrays = dict(
        position=position,
        width=widths,
        length=lengths,
        heading=heading,
        velocity=velocity,
        valid=valid,
    )
    for name, arr in arrays.items():
        if len(arr) != length:
            raise _err(source, f"{sf}.{name}", f"has {len(arr)} steps, scenario length is {length}")
    return _Track(type=ttype, **arrays)


def _finite_at(tr: _Track, t: int) -> str | None:
    """The first state field with NaN/inf at step t, or None."""
    for name in ("position", "heading", "velocity", "width", "length"):
        if not np.all(np.isfinite(getattr(tr, name)[t])):
            return name
    return None


def _int(value: Any, source: str, field: str) -> int:
    try:
        return int(value)
    except (TypeError, ValueError, OverflowError) as e:  # OverflowError: int(inf)
        raise _err(source, field, f"expected an integer, got {value!r}") from e


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles (rad) into [0, 2pi); mod alone can round a tiny negative angle up to 2pi."""
    wrapped = np.mod(angle, 2 * np.pi)
    return np.where(wrapped >= 2 * np.pi, 0.0, wrapped)


def _se2(x: float, y: float, theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _find_sdc(scenario: Mapping, meta: Mapping, tracks: Mapping, source: str) -> str:
    """The SDC's key in `tracks` (as a str): `metadata.sdc_id`, else a `sdc_track_index` (top
    level, then in metadata) that names a track, else one that indexes `tracks` in order."""
    if "sdc_id" in meta:
        sdc_id = str(meta["sdc_id"])
        if sdc_id not in tracks:
            raise _err(source, "metadata.sdc_id", f"{sdc_id!r} is not a key of tracks")
        return sdc_id
    for where, holder in (("sdc_track_index", scenario), ("metadata.sdc_track_index", meta)):
        if "sdc_track_index" not in holder:
            continue
        value = holder["sdc_track_index"]
        if str(value) in tracks:
            return str(value)
        if isinstance(value, (int, np.integer)) and 0 <= int(value) < len(tracks):
            return list(tracks)[int(value)]
        raise _err(source, where, f"{value!r} names no track and is no index into tracks")
    raise _err(source, "metadata.sdc_id", "missing (and no sdc_track_index)")


def _timestamps(scenario: Mapping) -> np.ndarray | None:
    """The file's time stamps (s) from `metadata.ts` or a top-level `ts`, if readable."""
    meta = scenario.get("metadata")
    ts = meta.get("ts") if isinstance(meta, Mapping) else None
    if ts is None:
        ts = scenario.get("ts")
    if ts is None:
        return None
    try:
        arr = np.asarray(ts, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    return arr if len(arr) >= 2 and np.all(np.isfinite(arr)) else None


def scenario_sample_rate_hz(scenario: Mapping) -> float | None:
    """Sample rate (Hz) of a scenario: 1 / the median step of `metadata.ts` or a top-level
    `ts`; None when the file has no usable time stamps."""
    if not isinstance(scenario, Mapping):
        return None
    ts = _timestamps(scenario)
    if ts is None:
        return None
    step = float(np.median(np.diff(ts)))
    return 1.0 / step if step > 0 else None


def _step_times(scenario: Mapping, length: int) -> np.ndarray:
    """[length] time (s) of each step: the file's `ts` when it has one entry per step and
    increases; else steps of its median interval, or of DEFAULT_STEP_S."""
    ts = _timestamps(scenario)
    if ts is not None and len(ts) == length and np.all(np.diff(ts) > 0):
        return ts
    rate = scenario_sample_rate_hz(scenario)
    step = 1.0 / rate if rate else DEFAULT_STEP_S
    return np.arange(length) * step


def velocity_mismatch(tracks: Sequence[_Track], times: np.ndarray) -> bool:
    """Whether a file's velocities disagree with its positions.

    Centred finite differences of the positions over valid steps (with the steps' times) are
    compared with the stored velocities of actors of our classes moving faster than
    MOVING_MPS: a mismatch when the median relative error exceeds VELOCITY_MISMATCH_REL_ERR
    (with at least MIN_MOVING_SAMPLES such samples). nuScenes' early converter writes zero
    velocities, for example.
    """
    rel = []
    dt = (times[2:] - times[:-2])[:, None]
    for tr in tracks:
        if tr.type not in CLASS_FROM_TYPE or len(tr.valid) < 3:
            continue
        both = tr.valid[2:] & tr.valid[:-2] & tr.valid[1:-1]
        if not both.any():
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            fd = (tr.position[2:] - tr.position[:-2]) / dt
        speed = np.linalg.norm(fd, axis=1)
        v = tr.velocity[1:-1]
        ok = both & np.isfinite(speed) & (speed > MOVING_MPS) & np.all(np.isfinite(v), axis=1)
        rel.append(np.linalg.norm(v[ok] - fd[ok], axis=1) / speed[ok])
    err = np.concatenate(rel) if rel else np.zeros(0)
    return len(err) >= MIN_MOVING_SAMPLES and float(np.median(err)) > VELOCITY_MISMATCH_REL_ERR


def _steps(
    time_index: int | Sequence[int] | None,
    all_steps: bool,
    stride: int | None,
    sdc: _Track,
    meta: Mapping,
    length: int,
    source: str,
) -> list[int]:
    if stride is not None:
        if all_steps or time_index is not None:
            raise _err(source, "stride", "give only one of time_index, all_steps and stride")
        if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
            raise _err(source, "stride", f"expected a positive integer, got {stride!r}")
        steps = [t for t in range(0, length, int(stride)) if sdc.valid[t]]
    elif all_steps:
        steps = [int(t) for t in np.flatnonzero(sdc.valid)]
    elif time_index is None:
        steps = [_int(meta.get("current_time_index", 0), source, "metadata.current_time_index")]
    elif isinstance(time_index, (int, np.integer)):
        steps = [int(time_index)]
    else:
        steps = [_int(t, source, "time_index") for t in time_index]
    for t in steps:
        if not 0 <= t < length:
            raise _err(source, "time_index", f"{t} outside [0, {length})")
    return steps


def frames_from_scenario(
    scenario: Mapping,
    source: str,
    time_index: int | Sequence[int] | None = None,
    *,
    all_steps: bool = False,
    stride: int | None = None,
    map_radius_m: float | None = None,
) -> list[ImportedFrame]:
    """Frames (in the SDC's ego frame) of a ScenarioNet scenario, with per-frame drop counts.

    Args:
      scenario: the scenario dict (as loaded from a ScenarioNet pickle).
      source: file it came from, used in error messages and as `Frame.source`.
      time_index: step(s) to import; default `metadata["current_time_index"]` (0 if absent).
      all_steps: import every step at which the SDC is valid (overrides `time_index`).
      stride: import steps 0, stride, 2 * stride, ... at which the SDC is valid (not together
        with `time_index` or `all_steps`).
      map_radius_m: if given, keep only map elements within this box radius (m) of the ego.

    Returns:
      One ImportedFrame(frame, dropped) per step. Every track valid at a frame's step (other
      than the SDC) is an actor of the frame or counted in `dropped`:
      - "type:<TYPE>": a type with no class (OTHER, TRAFFIC_CONE, TRAFFIC_BARRIER, ...);
      - "invalid:nan": NaN/inf in the step's position, heading, velocity or box size;
      - "invalid:size": a vehicle or cyclist box with a non-positive length or width.
      Counted but kept:
      - "quirk:length_lt_width": a vehicle or cyclist box (the SDC's included) whose length is
        shorter than its width. Boxes have no preferred axis other than the heading's, and
        converters do write swapped sizes (nuScenes' early converter for every box but the
        ego's, its current one for the ego's); the box is kept with its two sides sorted so
        that length >= width and its heading unchanged.
      - "quirk:velocity_mismatch": the file's velocities (which are used) disagree with its
        positions (`velocity_mismatch`); counted once per file, in the first frame.
      Map features the VectorMap cannot hold ("map:<TYPE>", see `map_from_features`) are
      counted once per file, in the first frame.

    Raises:
      ValueError naming `source` and the field for missing keys (tracks, the SDC, map
      features), bad shapes, an SDC that is invalid, non-finite or without a positive box
      size at a requested step, or NaN/inf map geometry.
    """
    if not isinstance(scenario, Mapping):
        raise _err(source, "scenario", f"expected a dict, got {type(scenario).__name__}")
    meta = scenario.get("metadata", {})
    if not isinstance(meta, Mapping):
        raise _err(source, "metadata", f"expected a dict, got {type(meta).__name__}")
    tracks = _get(scenario, "tracks", source, "")
    if not isinstance(tracks, Mapping):
        raise _err(source, "tracks", f"expected a dict, got {type(tracks).__name__}")
    keys = [str(k) for k in tracks]  # MetaDrive's old pickles key some files' tracks by int
    if len(set(keys)) != len(keys):
        raise _err(source, "tracks", "two track ids are equal as strings")
    tracks = dict(zip(keys, tracks.values(), strict=True))
    sdc_id = _find_sdc(scenario, meta, tracks, source)
    sdc_field = f"tracks[{sdc_id!r}]"
    if "length" in scenario:
        length = _int(scenario["length"], source, "length")
    else:  # MetaDrive's old Waymo pickles have no `length`
        sdc_state = _get(tracks[sdc_id], "state", source, sdc_field)
        length = len(np.asarray(_get(sdc_state, "position", source, f"{sdc_field}.state")))
    read = {tid: _read_track(tid, v, length, source) for tid, v in tracks.items()}
    sdc = read[sdc_id]
    steps = _steps(time_index, all_steps, stride, sdc, meta, length, source)

    world_map, map_dropped = map_from_features(_get(scenario, "map_features", source, ""), source)
    city_from_world = np.asarray(meta.get("scenegen_city_from_world", np.eye(3)), np.float64)
    if city_from_world.shape != (3, 3) or not np.all(np.isfinite(city_from_world)):
        raise _err(source, "metadata.scenegen_city_from_world", "expected a finite 3x3 matrix")
    scenario_id = str(scenario.get("id", meta.get("scenario_id", Path(source).stem)))
    mismatch = bool(steps) and velocity_mismatch(list(read.values()), _step_times(scenario, length))

    out = []
    for t in steps:
        sf = f"{sdc_field}.state"
        if not sdc.valid[t]:
            raise _err(source, f"{sf}.valid[{t}]", "the SDC (ego) is not valid at this step")
        bad = _finite_at(sdc, t)
        if bad is not None:
            raise _err(source, f"{sf}.{bad}[{t}]", "NaN or inf in a valid step of the SDC")
        ego_w, ego_l = float(sdc.width[t]), float(sdc.length[t])
        if ego_w <= 0 or ego_l <= 0:
            raise _err(
                source,
                f"{sf}.width/length[{t}]",
                f"box size must be positive, got width {ego_w}, length {ego_l}",
            )
        # Map features are the file's, not the frame's: counted once, in the first frame.
        dropped = collections.Counter() if out else collections.Counter(map_dropped)
        if ego_l < ego_w:
            dropped["quirk:length_lt_width"] += 1
            ego_w, ego_l = ego_l, ego_w
        x0, y0 = sdc.position[t]
        h0 = float(sdc.heading[t])
        ego_from_world = rotation_matrix(-h0)

        cls, pos, size, heading, vel, ids = [], [], [], [], [], []
        for tid, tr in read.items():
            if tid == sdc_id or not tr.valid[t]:
                continue
            if tr.type not in CLASS_FROM_TYPE:
                dropped[f"type:{tr.type}"] += 1
                continue
            c = CLASS_FROM_TYPE[tr.type]
            if _finite_at(tr, t) is not None:
                dropped["invalid:nan"] += 1
                continue
            w, length_m = float(tr.width[t]), float(tr.length[t])
            if c != PEDESTRIAN:
                if w <= 0 or length_m <= 0:
                    dropped["invalid:size"] += 1
                    continue
                if length_m < w:
                    dropped["quirk:length_lt_width"] += 1
                    w, length_m = length_m, w
            cls.append(c)
            pos.append(ego_from_world @ (tr.position[t] - (x0, y0)))
            size.append((w, length_m))
            heading.append(tr.heading[t] - h0)
            vel.append(ego_from_world @ tr.velocity[t])
            ids.append(tid)

        vmap = world_map.transform(ego_from_world, -ego_from_world @ np.array([x0, y0]))
        if map_radius_m is not None:
            vmap = vmap.crop(np.zeros(2), map_radius_m)
        n = len(cls)
        single_step = length == 1 and "scenegen_scene_id" in meta
        frame = Frame(
            scene_id=str(meta["scenegen_scene_id"]) if single_step else f"{scenario_id}/{t}",
            source=source,
            cls=np.asarray(cls, np.int32).reshape(n),
            position=np.asarray(pos, np.float64).reshape(n, 2),
            size=np.asarray(size, np.float64).reshape(n, 2),
            heading=_wrap(np.asarray(heading, np.float64).reshape(n)),
            velocity=np.asarray(vel, np.float64).reshape(n, 2),
            track_id=np.asarray(ids, dtype=str).reshape(n),
            ego_velocity=ego_from_world @ sdc.velocity[t],
            ego_size=np.array([ego_w, ego_l], np.float64),
            map=vmap,
            city_from_ego=city_from_world @ _se2(x0, y0, h0),
        )
        out.append(ImportedFrame(frame, dropped))
    if mismatch and out:
        out[0].dropped["quirk:velocity_mismatch"] += 1
    return out


def scenario_files(root: str | os.PathLike) -> list[Path]:
    """Sorted scenario pickles under `root` (recursive), without the dataset summary/mapping."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a directory")
    files = sorted(
        p for p in root.rglob("*.pkl") if p.is_file() and p.name not in (SUMMARY_FILE, MAPPING_FILE)
    )
    if not files:
        raise FileNotFoundError(f"{root}: no ScenarioNet scenario files (*.pkl)")
    return files


def read_scenario(path: str | os.PathLike) -> dict:
    """One scenario dict from a pickle, loaded with the restricted unpickler."""
    scenario = load_pickle(path)
    if not isinstance(scenario, dict):
        raise ValueError(
            f"{path}: expected a ScenarioNet scenario dict, got {type(scenario).__name__}"
        )
    return scenario


def read_scenarionet(
    root: str | os.PathLike,
    time_index: int | Sequence[int] | None = None,
    *,
    all_steps: bool = False,
    stride: int | None = None,
    map_radius_m: float | None = None,
) -> Iterator[ImportedFrame]:
    """(Frame, dropped Counter) for every scenario file under `root`; see frames_from_scenario."""
    for path in scenario_files(root):
        yield from frames_from_scenario(
            read_scenario(path),
            str(path),
            time_index,
            all_steps=all_steps,
            stride=stride,
            map_radius_m=map_radius_m,
        )


# ----------------------------------------------------------------------------- export


def _xyz(points: np.ndarray) -> np.ndarray:
    """[P, 3] float32 with z = 0, as ScenarioNet polylines are."""
    points = np.asarray(points, np.float64)
    return np.concatenate([points, np.zeros((len(points), 1))], axis=1).astype(np.float32)


def _check_frame(frame: Frame) -> None:
    where = f"{frame.source or frame.scene_id}: frame"
    n = frame.num_actors
    shapes = {
        "position": (n, 2),
        "size": (n, 2),
        "heading": (n,),
        "velocity": (n, 2),
        "track_id": (n,),
        "ego_velocity": (2,),
        "ego_size": (2,),
        "city_from_ego": (3, 3),
    }
    for name, shape in shapes.items():
        value = np.asarray(getattr(frame, name))
        if value.shape != shape:
            raise ValueError(f"{where}.{name}: expected shape {shape}, got {value.shape}")
        if name != "track_id" and not np.all(np.isfinite(value)):
            raise ValueError(f"{where}.{name}: NaN or inf")
    cls = np.asarray(frame.cls)
    if np.any((cls < 0) | (cls >= NUM_CLASSES)):
        raise ValueError(f"{where}.cls: class ids must be in [0, {NUM_CLASSES})")
    boxed = cls != PEDESTRIAN
    if np.any(np.asarray(frame.size)[boxed] <= 0) or np.any(np.asarray(frame.ego_size) <= 0):
        raise ValueError(f"{where}.size: box width and length must be positive")


def _track(
    ttype: str,
    tid: str,
    position: Any,
    size: Any,
    height: float,
    heading: float,
    velocity: Any,
    dataset: str,
) -> dict:
    """A one-step ScenarioNet track; position (x, y) m, size (width, length) m."""
    x, y = (float(v) for v in position)
    width, length = (float(v) for v in size)
    return {
        "type": ttype,
        "state": {
            "position": np.array([[x, y, 0.0]], np.float32),
            "length": np.array([length], np.float32),
            "width": np.array([width], np.float32),
            "height": np.array([height], np.float32),
            "heading": np.array([heading], np.float32),
            "velocity": np.asarray(velocity, np.float32).reshape(1, 2),
            "valid": np.array([True]),
        },
        "metadata": {"track_length": 1, "type": ttype, "object_id": tid, "dataset": dataset},
    }


def _lane_features(lane: Lane) -> dict[str, dict]:
    """The lane's centreline feature and its two boundary-line features."""
    lid = str(int(lane.id))
    center = lane.centerline
    n = len(center)
    half = np.stack(
        [
            np.linalg.norm(center - resample_polyline(lane.left, n), axis=1),
            np.linalg.norm(center - resample_polyline(lane.right, n), axis=1),
        ],
        axis=1,
    )
    is_vehicle = lane.lane_type != "BIKE"
    if not is_vehicle:
        ftype = "LANE_BIKE_LANE"
    elif lane.is_intersection:
        ftype = "LANE_SURFACE_UNSTRUCTURE"
    else:
        ftype = "LANE_SURFACE_STREET"
    features: dict[str, dict] = {}
    bounds: dict[str, list] = {}
    for side, line, mark in (
        ("left", lane.left, lane.left_mark),
        ("right", lane.right, lane.right_mark),
    ):
        bid = f"{lid}_{side}_boundary"
        line_type = LINE_TYPE_FROM_MARK.get(mark.upper(), "UNKNOWN_LINE")
        features[bid] = {
            "type": line_type,
            "polyline": _xyz(line),
            "scenegen_kind": "lane_boundary",
        }
        bounds[side] = [
            {
                "lane_start_index": 0,
                "lane_end_index": n - 1,
                "boundary_type": line_type,
                "boundary_feature_id": bid,
            }
        ]
    lane_feature = {
        "type": ftype,
        "polyline": _xyz(center),
        "polygon": _xyz(lane.polygon),
        "width": half.astype(np.float32),
        "entry_lanes": [str(int(i)) for i in lane.predecessors],
        "exit_lanes": [str(int(i)) for i in lane.successors],
        "left_boundaries": bounds["left"],
        "right_boundaries": bounds["right"],
        "left_neighbor": [],
        "right_neighbor": [],
        "scenegen_kind": "lane",
        "scenegen_lane_type": lane.lane_type,
        "scenegen_left": np.asarray(lane.left, np.float64),
        "scenegen_right": np.asarray(lane.right, np.float64),
        "scenegen_left_mark": lane.left_mark,
        "scenegen_right_mark": lane.right_mark,
        "scenegen_is_intersection": bool(lane.is_intersection),
    }
    return {lid: lane_feature, **features}


def map_features_from_vector_map(vmap: VectorMap) -> dict[str, dict]:
    """ScenarioNet map features (plus `scenegen_*` extras) of a VectorMap, same frame."""
    features: dict[str, dict] = {}
    ids = [int(lane.id) for lane in vmap.lanes]
    if len(set(ids)) != len(ids):
        raise ValueError("map.lanes: lane ids must be unique")
    for lane in vmap.lanes:
        features.update(_lane_features(lane))
    for i, poly in enumerate(vmap.crosswalks):
        features[f"crosswalk_{i}"] = {
            "type": "CROSSWALK",
            "polygon": _xyz(poly),
            "scenegen_kind": "crosswalk",
            "scenegen_polygon": np.asarray(poly, np.float64),
        }
    for i, line in enumerate(vmap.lines):
        mark = str(line.mark)
        if mark == ROAD_EDGE:
            line_type = "ROAD_EDGE_BOUNDARY"
        else:
            line_type = LINE_TYPE_FROM_MARK.get(mark.upper(), "UNKNOWN_LINE")
        features[f"line_{i}"] = {
            "type": line_type,
            "polyline": _xyz(line.points),
            "scenegen_kind": "line",
            "scenegen_mark": mark,
            "scenegen_points": np.asarray(line.points, np.float64),
        }
    for i, poly in enumerate(vmap.drivable_areas):
        ring = np.asarray(poly, np.float64)
        if len(ring) and not np.allclose(ring[0], ring[-1]):
            ring = np.concatenate([ring, ring[:1]], axis=0)
        # ScenarioNet has no drivable-area type; its outline is a road edge for simulators.
        features[f"drivable_area_{i}"] = {
            "type": "ROAD_EDGE_BOUNDARY",
            "polyline": _xyz(ring),
            "polygon": _xyz(poly),
            "scenegen_kind": "drivable_area",
            "scenegen_polygon": np.asarray(poly, np.float64),
        }
    return features


def scenario_from_frame(frame: Frame, scenario_id: str, dataset: str = "scenegen") -> dict:
    """A one-step ScenarioNet scenario of a Frame, in the ego frame (SDC at the origin, heading 0).

    The ego is the SDC track (type VEHICLE); actors keep their track ids (empty ids become
    "actor_<i>"). Raises ValueError naming the frame's source for NaN/inf, bad shapes, unknown
    classes, non-positive box sizes or duplicate track ids.
    """
    _check_frame(frame)
    where = f"{frame.source or frame.scene_id}: frame"
    ids = [str(t) if str(t) else f"actor_{i}" for i, t in enumerate(np.asarray(frame.track_id))]
    if len(set(ids)) != len(ids):
        dup = collections.Counter(ids).most_common(1)[0][0]
        raise ValueError(f"{where}.track_id: duplicate track id {dup!r}")
    sdc_id = "ego"
    while sdc_id in ids:
        sdc_id = f"_{sdc_id}"

    height = _HEIGHT_M[VEHICLE]
    tracks = {
        sdc_id: _track(
            "VEHICLE", sdc_id, (0, 0), frame.ego_size, height, 0.0, frame.ego_velocity, dataset
        )
    }
    for i, tid in enumerate(ids):
        c = int(frame.cls[i])
        tracks[tid] = _track(
            TYPE_FROM_CLASS[c],
            tid,
            frame.position[i],
            frame.size[i],
            _HEIGHT_M[c],
            float(frame.heading[i]),
            frame.velocity[i],
            dataset,
        )

    metadata = {
        "id": scenario_id,
        "scenario_id": scenario_id,
        "dataset": dataset,
        "ts": np.array([0.0]),
        "metadrive_processed": False,
        "coordinate": "right-handed",
        "sdc_id": sdc_id,
        "sdc_track_index": 0,
        "current_time_index": 0,
        "track_length": 1,
        "objects_of_interest": [],
        "tracks_to_predict": {},
        "source_file": str(frame.source),
        "scenegen_scene_id": str(frame.scene_id),
        "scenegen_city_from_world": np.asarray(frame.city_from_ego, np.float64),
        "scenegen_version": __version__,
    }
    return {
        "id": scenario_id,
        "version": f"scenegen_jax-{__version__}",
        "length": 1,
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": map_features_from_vector_map(frame.map),
        "metadata": metadata,
    }


def _check_scenario(scenario: Any, where: str) -> None:
    if not isinstance(scenario, dict):
        raise ValueError(f"{where}: expected a scenario dict, got {type(scenario).__name__}")
    missing = [k for k in (*TOP_LEVEL_KEYS, "dynamic_map_states") if k not in scenario]
    if missing:
        raise ValueError(f"{where}: scenario lacks top-level keys {missing}")


def write_scenario(scenario: dict, path: str | os.PathLike) -> None:
    """Pickles one scenario dict to `path` (atomic write)."""
    _check_scenario(scenario, str(path))
    dump_pickle(scenario, path)


def scenario_file_name(scenario: Mapping) -> str:
    """ScenarioNet-style file name "sd_<dataset>_<id>.pkl" (id made filesystem-safe)."""
    dataset = str(scenario.get("metadata", {}).get("dataset", "scenegen"))
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", f"{dataset}_{scenario['id']}")
    return f"sd_{safe}.pkl"


def write_dataset(scenarios: Sequence[dict], directory: str | os.PathLike) -> list[Path]:
    """Writes scenarios plus the `dataset_summary.pkl` / `dataset_mapping.pkl` MetaDrive reads.

    Returns the scenario file paths. Raises ValueError on duplicate file names.
    """
    directory = Path(directory)
    names = [scenario_file_name(s) for s in scenarios]
    if len(set(names)) != len(names):
        dup = collections.Counter(names).most_common(1)[0][0]
        raise ValueError(f"{directory}: two scenarios map to the file name {dup!r}")
    paths = []
    for scenario, name in zip(scenarios, names, strict=True):
        write_scenario(scenario, directory / name)
        paths.append(directory / name)
    dump_pickle(
        {n: s["metadata"] for n, s in zip(names, scenarios, strict=True)}, directory / SUMMARY_FILE
    )
    dump_pickle({n: "" for n in names}, directory / MAPPING_FILE)
    return paths


# ----------------------------------------------------------------------------- comparison


def frame_differences(a: Frame, b: Frame, atol: float = 1e-4) -> list[str]:
    """Fields in which two frames differ beyond `atol` (m, rad, m/s); [] when they match.

    Headings compare as angles; the map compares lane by lane (ids, types, marks, flags, links,
    boundary points), then crosswalk and drivable-area points, then lines (marks and points).
    `source` is not compared.
    """
    diffs: list[str] = []
    if a.scene_id != b.scene_id:
        diffs.append(f"scene_id: {a.scene_id!r} != {b.scene_id!r}")
    if a.num_actors != b.num_actors:
        return [*diffs, f"num_actors: {a.num_actors} != {b.num_actors}"]
    if not np.array_equal(np.asarray(a.cls), np.asarray(b.cls)):
        diffs.append("cls")
    if [str(t) for t in a.track_id] != [str(t) for t in b.track_id]:
        diffs.append("track_id")
    for name in ("position", "size", "velocity", "ego_velocity", "ego_size", "city_from_ego"):
        x, y = np.asarray(getattr(a, name), np.float64), np.asarray(getattr(b, name), np.float64)
        if x.shape != y.shape or not np.allclose(x, y, rtol=0, atol=atol):
            diffs.append(name)
    dh = np.angle(np.exp(1j * (np.asarray(a.heading, np.float64) - np.asarray(b.heading))))
    if np.any(np.abs(dh) > atol):
        diffs.append("heading")

    def close(p: np.ndarray, q: np.ndarray) -> bool:
        return p.shape == q.shape and np.allclose(p, q, rtol=0, atol=atol)

    if len(a.map.lanes) != len(b.map.lanes):
        diffs.append(f"map.lanes: {len(a.map.lanes)} != {len(b.map.lanes)}")
    else:
        for i, (la, lb) in enumerate(zip(a.map.lanes, b.map.lanes, strict=True)):
            fields = ("id", "lane_type", "left_mark", "right_mark", "is_intersection")
            for f in (*fields, "successors", "predecessors"):
                if getattr(la, f) != getattr(lb, f):
                    diffs.append(f"map.lanes[{i}].{f}")
            if not (close(la.left, lb.left) and close(la.right, lb.right)):
                diffs.append(f"map.lanes[{i}] boundaries")
    for name in ("crosswalks", "drivable_areas"):
        pa, pb = getattr(a.map, name), getattr(b.map, name)
        if len(pa) != len(pb) or not all(close(p, q) for p, q in zip(pa, pb, strict=True)):
            diffs.append(f"map.{name}")
    la, lb = a.map.lines, b.map.lines
    if len(la) != len(lb) or not all(
        p.mark == q.mark and close(p.points, q.points) for p, q in zip(la, lb, strict=True)
    ):
        diffs.append("map.lines")
    return diffs
