"""ScenarioNet `map_features` -> VectorMap (`map_from_features`).

Reads our own exports exactly (their `scenegen_*` extras) and real converters' features
(Waymo, nuScenes, nuPlan, Argoverse 2, MetaDrive's old Waymo pickles): lanes are outlined
from centrelines and half widths, lines and road edges become `RoadLine`s, crosswalks and
driveways are polygons; what a VectorMap cannot hold is counted as "map:<TYPE>".
"""

from __future__ import annotations

import collections
import dataclasses
import re
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from scenegen_jax.data import surface
from scenegen_jax.data.scenarionet_schema import (
    MARK_FROM_LINE_TYPE,
    _err,
    _geometry,
    _get,
    _polyline,
)
from scenegen_jax.data.surface import Centerline, normals, outline_lanes, ray_distances
from scenegen_jax.vector_map import ROAD_EDGE, Lane, RoadLine, VectorMap, distinct_points

DEFAULT_HALF_WIDTH_M = surface.DEFAULT_HALF_WIDTH_M
# A converter's per-point lane `width` (half widths to the left / right boundary) is used only
# in this range; elsewhere the half width is measured from the map's lines. On the WOMD
# ScenarioNet pickles in ../shared/data/womd_mini, half widths <= 2.5 m agree with the
# perpendicular distance to the nearest line within 2 cm (median); larger ones (about a quarter
# of them, up to 177 m) are off by about 3 m, because the Waymo converter matches boundary
# points by nearest index and copies one side's width to the other.
MIN_GIVEN_HALF_WIDTH_M = surface.MIN_HALF_WIDTH_M
MAX_GIVEN_HALF_WIDTH_M = 2.5

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


def _canonical_int(key: Any) -> int | None:
    s = str(key)
    return int(s) if re.fullmatch(r"-?[1-9][0-9]*|0", s) else None


def _dedupe(points: np.ndarray) -> np.ndarray:
    return points[distinct_points(points)]


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
    width_unusable: bool  # a `width` not of [P, 2] numbers: measured instead, counted


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
    A `width` of another shape, or not of numbers, is counted ("quirk:lane_width_unusable").
    """
    field = f"map_features[{fid!r}]"
    ftype = feature["type"]
    raw = _polyline(_get(feature, "polyline", source, field), source, f"{field}.polyline")
    keep = distinct_points(raw)
    center = raw[keep]
    if len(center) < 2:
        return None
    half = np.zeros((len(center), 2))
    try:
        w = np.asarray(feature.get("width", np.zeros((len(raw), 2))), dtype=np.float64)
    except (TypeError, ValueError):  # unusable: measured from the lines instead
        w = np.zeros(0)
    width_unusable = w.shape != (len(raw), 2)
    if not width_unusable:
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
        width_unusable,
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


def map_from_features(map_features: Mapping, source: str,
                      dataset: str = "") -> tuple[VectorMap, collections.Counter]:
    """The VectorMap (in the scenario's world frame) and counts of unusable features.
    `dataset` is the scenario's `metadata.dataset` ("" where it has none).

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
    kinds = _feature_kinds(map_features, source, dropped)
    line_ids = {str(fid) for fid, kind in kinds.items() if kind in ("line", "edge")}
    lane_ids = _lane_ids([fid for fid, kind in kinds.items() if kind == "lane"])
    parts = _Parts()
    for fid, kind in kinds.items():
        if kind == "lane":
            _read_lane(fid, map_features, lane_ids, line_ids, parts, dropped, source)
        elif kind != "lane_boundary":  # our lane-boundary features are part of their lanes
            _read_feature(fid, kind, map_features[fid], parts, dropped, source)
    outlined, lane_areas = _outline(parts.real, parts.lines)
    vmap = VectorMap(
        lanes=tuple(parts.exact) + tuple(outlined),
        crosswalks=tuple(parts.crosswalks),
        drivable_areas=tuple(parts.own_drivable) + tuple(lane_areas) + tuple(parts.driveways),
        lines=tuple(parts.lines),
        dataset=dataset,
    )
    return vmap, dropped


def _feature_kinds(map_features: Mapping, source: str,
                   dropped: collections.Counter) -> dict[Any, str]:
    """How each feature is read (`_feature_kind`), by id in file order; the features a
    VectorMap cannot hold are counted in `dropped`."""
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
    return kinds


class _LaneIds(NamedTuple):
    """Lane ids of a file: integer ids when the file's are canonical integers (Argoverse,
    Waymo, ours), otherwise (nuScenes, nuPlan tokens) positions in file order."""

    int_ids: bool
    id_of: dict[str, int]  # by the feature id as a string

    def links(self, value: Any) -> tuple[int, ...]:
        """The lane ids of a list of linked features (`entry_lanes`, `exit_lanes`)."""
        # Integer ids keep links to lanes outside this file (as a cropped Argoverse map does);
        # enumerated ids can only name lanes that are in it.
        if not isinstance(value, (list, tuple, np.ndarray)):
            return ()
        if self.int_ids:
            ints = (_canonical_int(x) for x in value)
            return tuple(i for i in ints if i is not None)
        return tuple(self.id_of[str(x)] for x in value if str(x) in self.id_of)


def _lane_ids(lane_keys: list) -> _LaneIds:
    as_int = [_canonical_int(k) for k in lane_keys]
    int_ids = all(i is not None for i in as_int) and len(set(as_int)) == len(as_int)
    if int_ids:
        return _LaneIds(True, {str(k): i for k, i in zip(lane_keys, as_int, strict=True)})
    return _LaneIds(False, {str(k): n for n, k in enumerate(lane_keys)})


@dataclasses.dataclass
class _Parts:
    """A map's parts as read, in file order."""

    exact: list = dataclasses.field(default_factory=list)  # Lanes of our own exports
    real: list = dataclasses.field(default_factory=list)  # _RealLanes of converters
    lines: list = dataclasses.field(default_factory=list)  # RoadLines
    crosswalks: list = dataclasses.field(default_factory=list)  # polygons
    own_drivable: list = dataclasses.field(default_factory=list)  # our drivable polygons
    driveways: list = dataclasses.field(default_factory=list)  # converters' polygons


def _read_lane(fid: Any, map_features: Mapping, lane_ids: _LaneIds, line_ids: set[str],
               parts: _Parts, dropped: collections.Counter, source: str) -> None:
    """Adds lane feature `fid` to `parts`: exactly where it is ours, else as a converter's
    centreline; a degenerate one and an unusable `width` are counted in `dropped`."""
    feature = map_features[fid]
    links = (lane_ids.links(feature.get("exit_lanes")), lane_ids.links(feature.get("entry_lanes")))
    lane_id = lane_ids.id_of[str(fid)]
    if "scenegen_left" in feature and "scenegen_right" in feature:
        parts.exact.append(_exact_lane(fid, feature, lane_id, links, source))
        return
    lane = _real_lane(fid, feature, lane_id, links, map_features, line_ids, source)
    if lane is None:
        dropped["map:degenerate_lane"] += 1
    else:
        parts.real.append(lane)
        if lane.width_unusable:
            dropped["quirk:lane_width_unusable"] += 1


def _read_feature(fid: Any, kind: str, feature: Mapping, parts: _Parts,
                  dropped: collections.Counter, source: str) -> None:
    """Adds a feature of any kind but a lane's (`_feature_kind`) to `parts`; geometry too
    short to use is counted in `dropped`."""
    field = f"map_features[{fid!r}]"
    ftype = feature["type"]
    if kind == "own_line":
        points = _polyline(feature.get("scenegen_points"), source, f"{field}.scenegen_points")
        parts.lines.append(RoadLine(points, str(feature.get("scenegen_mark", "UNKNOWN"))))
    elif kind in ("line", "edge"):
        points = _dedupe(_geometry(feature, ("polyline", "polygon"), source, field))
        if len(points) < 2:
            dropped[f"map:degenerate_{kind}"] += 1
        elif kind == "edge":
            parts.lines.append(RoadLine(points, ROAD_EDGE))
        else:
            parts.lines.append(RoadLine(points, MARK_FROM_LINE_TYPE.get(ftype, "UNKNOWN")))
    elif "scenegen_polygon" in feature:  # our own crosswalks and drivable areas: exact
        poly = _polyline(feature["scenegen_polygon"], source, f"{field}.scenegen_polygon", 3)
        (parts.own_drivable if kind == "drivable_area" else parts.crosswalks).append(poly)
    else:  # a converter's crosswalk or driveway
        ring = _ring(_geometry(feature, ("polygon", "polyline"), source, field))
        if _distinct_points(ring) < 3:
            dropped[f"map:degenerate_{kind}"] += 1
        else:
            (parts.crosswalks if kind == "crosswalk" else parts.driveways).append(ring)
