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


def stacked_normals(lines: Sequence[np.ndarray]) -> np.ndarray:
    """[sum P, 2] unit normals to the left of travel (y left) of the points of several
    polylines (each [P, 2], P >= 2), stacked in order: each point's tangent is `np.gradient`'s
    (central differences inside a line, one-sided at its two ends), the same floats."""
    points = np.concatenate(lines).astype(np.float64)
    sizes = np.array([len(p) for p in lines])
    first = np.repeat(np.cumsum(sizes) - sizes, sizes)
    index = np.arange(len(points))
    before = np.maximum(index - 1, first)
    after = np.minimum(index + 1, first + np.repeat(sizes, sizes) - 1)
    tangent = (points[after] - points[before]) / (after - before)[:, None]
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    return np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)


def normals(center: np.ndarray) -> np.ndarray:
    """[P, 2] unit normals to the left of travel of a centreline [P, 2] (y left)."""
    return stacked_normals([center])


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


def _side_distances(points: np.ndarray, normal: np.ndarray, max_m: float,
                    segs: np.ndarray) -> np.ndarray:
    """[N, 2] distances from points [N, 2] to the nearest segment crossed along their
    normals [N, 2] (left) and against them (right): both sides' rays in one search."""
    both = ray_distances(np.concatenate([points, points]), np.concatenate([normal, -normal]),
                         max_m, segs)
    return both.reshape(2, len(points)).T


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
    if not centers:
        return (), ()
    crossing = _crossing_lanes(centers)
    points, normal = np.concatenate(centers), stacked_normals(centers)
    to_line = _side_distances(points, normal, MAX_HALF_WIDTH_M, all_segs)
    to_edge = _side_distances(points, normal, MAX_EDGE_M, edge_segs)
    half = np.where(np.isfinite(to_line), np.maximum(to_line, MIN_HALF_WIDTH_M),
                    DEFAULT_HALF_WIDTH_M)
    given = np.concatenate([np.full((len(p), 2), np.nan) if c.half_widths is None
                            else np.asarray(c.half_widths, np.float64)
                            for c, p in zip(centerlines, centers, strict=True)])
    half = np.where(np.isfinite(given) & (given > 0), given, half)
    reach = np.where(np.isfinite(to_edge), np.maximum(to_edge, half), half)
    # Boundaries at those distances along the normals: the lane's, and its drivable surface's.
    left, right = points + normal * half[:, :1], points - normal * half[:, 1:]
    outer_left, outer_right = points + normal * reach[:, :1], points - normal * reach[:, 1:]
    split = np.cumsum([len(p) for p in centers])[:-1]
    per_lane = (np.split(x, split) for x in (left, right, outer_left, outer_right))
    lanes, drivable = [], []
    for c, crosses, lane_left, lane_right, out_left, out_right in zip(
        centerlines, crossing, *per_lane, strict=True
    ):
        is_intersection = bool(crosses) if c.is_intersection is None else c.is_intersection
        lanes.append(
            Lane(
                id=c.id,
                lane_type=c.lane_type,
                left=lane_left,
                right=lane_right,
                is_intersection=is_intersection,
                successors=c.successors,
                predecessors=c.predecessors,
            )
        )
        drivable.append(np.concatenate([out_left, out_right[::-1]], axis=0))
    return tuple(lanes), tuple(drivable)
