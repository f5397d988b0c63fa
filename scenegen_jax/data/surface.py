"""Lane outlines and the drivable surface of maps that give only centrelines and lines.

Waymo (GPUDrive / Nocturne JSON, ScenarioNet) and nuScenes maps have lane centrelines, painted
road lines and road edges, but no lane boundaries tied to a lane and no drivable-area polygon.
So that their rasters mean what Argoverse 2's mean, a lane's half width on each side is the
distance along the centreline's normal to the nearest painted line or road edge
(`MIN_HALF_WIDTH_M`..`MAX_HALF_WIDTH_M`, else `DEFAULT_HALF_WIDTH_M`), and the drivable
surface of a lane side reaches on to the nearest road edge when one lies within
`MAX_EDGE_M` of the centreline (the kerb: parking strips and shoulders are road, as in
Argoverse 2's drivable areas), else it is the lane itself. A lane is an intersection lane when
its centreline crosses another lane's centreline away from both ends (lanes only cross inside
junctions; merges and splits meet at their ends).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import shapely

from scenegen_jax.vector_map import ROAD_EDGE, Lane, RoadLine

DEFAULT_HALF_WIDTH_M = 1.8
MIN_HALF_WIDTH_M = 1.0
MAX_HALF_WIDTH_M = 3.0
MAX_EDGE_M = 8.0
END_MARGIN_M = 2.0  # a crossing this close to a centreline's end is a merge or a split


@dataclasses.dataclass(frozen=True)
class Centerline:
    """A lane as Waymo-like maps give it: a centreline and maybe per-point half widths.

    Attributes:
      id: lane id.
      lane_type: one of `vector_map.LANE_TYPES`.
      points: [P, 2] centreline in the direction of travel, m (P >= 2, no repeated points).
      half_widths: optional [P, 2] (left, right) half widths, m; entries <= 0 are unknown.
      successors, predecessors: ids of connected lanes.
      is_intersection: None to infer it from crossings with other lanes.
    """

    id: int
    lane_type: str
    points: np.ndarray
    half_widths: np.ndarray | None = None
    successors: tuple[int, ...] = ()
    predecessors: tuple[int, ...] = ()
    is_intersection: bool | None = None


def normals(center: np.ndarray) -> np.ndarray:
    """[P, 2] unit normals to the left of travel of a centreline [P, 2] (y left)."""
    tangent = np.gradient(np.asarray(center, np.float64), axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    return np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)


def offset_centerline(
    center: np.ndarray, half_width_left: np.ndarray, half_width_right: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Left and right boundaries [P, 2] at the given per-point distances (m) from a centreline.

    Args:
      center: [P, 2] centreline, P >= 2, no repeated consecutive points.
      half_width_left, half_width_right: [P] distances to the left / right boundary, m.
    """
    normal = normals(center)
    return center + normal * half_width_left[:, None], center - normal * half_width_right[:, None]


def _segments(lines: Sequence[np.ndarray]) -> np.ndarray:
    """[S, 2, 2] segments of polylines (each [P, 2], P >= 2)."""
    segs = [np.stack([p[:-1], p[1:]], axis=1) for p in lines if len(p) >= 2]
    return np.concatenate(segs) if segs else np.zeros((0, 2, 2))


def ray_distances(origins: np.ndarray, dirs: np.ndarray, max_m: float, segs: np.ndarray):
    """Distance (m) along each unit ray to the first segment it crosses; inf when none.

    Args:
      origins, dirs: [R, 2] ray starts and unit directions.
      max_m: ray length, m.
      segs: [S, 2, 2] segments.
    Returns:
      [R] float64 distances in [0, max_m], inf where the ray crosses nothing.
    """
    out = np.full(len(origins), np.inf)
    if len(segs) == 0 or len(origins) == 0:
        return out
    tree = shapely.STRtree(shapely.linestrings(segs))
    rays = shapely.linestrings(np.stack([origins, origins + dirs * max_m], axis=1))
    ri, si = tree.query(rays)  # bounding-box candidates; the exact test is below
    p, r = origins[ri], dirs[ri] * max_m
    q, s = segs[si, 0], segs[si, 1] - segs[si, 0]
    rxs = r[:, 0] * s[:, 1] - r[:, 1] * s[:, 0]
    qp = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[:, 0] * s[:, 1] - qp[:, 1] * s[:, 0]) / rxs
        u = (qp[:, 0] * r[:, 1] - qp[:, 1] * r[:, 0]) / rxs
    hit = (np.abs(rxs) > 1e-12) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    np.minimum.at(out, ri[hit], t[hit] * max_m)
    return out


def _side_distances(centers: Sequence[np.ndarray], max_m: float, segs: np.ndarray) -> list:
    """Per centreline, [P, 2] distances to the nearest segment crossed on its (left, right)."""
    if not centers:
        return []
    points = np.concatenate(centers)
    n = np.concatenate([normals(c) for c in centers])
    # Both sides' rays in one call: one tree of the segments.
    both = ray_distances(np.concatenate([points, points]), np.concatenate([n, -n]), max_m, segs)
    both = both.reshape(2, len(points)).T
    return np.split(both, np.cumsum([len(c) for c in centers])[:-1])


def _crossing_lanes(centers: Sequence[np.ndarray]) -> np.ndarray:
    """[L] bool: centreline crosses another one at a point away from both of their ends."""
    out = np.zeros(len(centers), bool)
    if len(centers) < 2:
        return out
    geoms = np.array([shapely.LineString(c) for c in centers], dtype=object)
    tree = shapely.STRtree(geoms)
    a, b = tree.query(geoms, predicate="crosses")
    for i, j in zip(a, b, strict=True):
        if i >= j or (out[i] and out[j]):
            continue
        crossing = shapely.intersection(geoms[i], geoms[j])
        pts = shapely.get_coordinates(crossing)
        if len(pts) == 0:
            continue
        ends = np.concatenate([centers[i][[0, -1]], centers[j][[0, -1]]])
        far = np.min(np.linalg.norm(pts[:, None] - ends[None], axis=-1), axis=1) > END_MARGIN_M
        if far.any():
            out[i] = out[j] = True
    return out


def outline_lanes(
    centerlines: Sequence[Centerline], lines: Sequence[RoadLine]
) -> tuple[tuple[Lane, ...], tuple[np.ndarray, ...]]:
    """Lanes with boundaries, and the drivable surface polygons, from centrelines and lines.

    Returns:
      (lanes, drivable): one Lane per centreline (its boundaries marked "NONE": the painted
      lines are drawn from `lines` themselves), and one drivable polygon [Q, 2] per lane.
    """
    all_segs = _segments([line.points for line in lines])
    edge_segs = _segments([line.points for line in lines if line.mark == ROAD_EDGE])
    centers = [np.asarray(c.points, np.float64) for c in centerlines]
    crossing = _crossing_lanes(centers)
    to_line = _side_distances(centers, MAX_HALF_WIDTH_M, all_segs)
    to_edge = _side_distances(centers, MAX_EDGE_M, edge_segs)
    lanes, drivable = [], []
    for c, center, crosses, half, edge in zip(
        centerlines, centers, crossing, to_line, to_edge, strict=True
    ):
        half = np.where(np.isfinite(half), np.maximum(half, MIN_HALF_WIDTH_M), DEFAULT_HALF_WIDTH_M)
        if c.half_widths is not None:
            given = np.asarray(c.half_widths, np.float64)
            half = np.where(np.isfinite(given) & (given > 0), given, half)
        left, right = offset_centerline(center, half[:, 0], half[:, 1])
        is_intersection = bool(crosses) if c.is_intersection is None else c.is_intersection
        lanes.append(
            Lane(
                id=c.id,
                lane_type=c.lane_type,
                left=left,
                right=right,
                is_intersection=is_intersection,
                successors=c.successors,
                predecessors=c.predecessors,
            )
        )
        reach = np.where(np.isfinite(edge), np.maximum(edge, half), half)
        outer_left, outer_right = offset_centerline(center, reach[:, 0], reach[:, 1])
        drivable.append(np.concatenate([outer_left, outer_right[::-1]], axis=0))
    return tuple(lanes), tuple(drivable)
