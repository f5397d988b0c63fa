"""Map rasterization (host side, shapely 2 vectorised predicates) into named channels.

Rasters follow the convention documented in `scenegen_jax.scene`. Polygons are sampled at
pixel centres; polylines (centrelines, painted boundaries) are buffered to at least half a
pixel so they are never missed at coarse resolutions.
"""

from __future__ import annotations

import functools

import numpy as np
import shapely

from scenegen_jax.config import ALL_LAYER_GROUPS, LAYER_GROUPS, Config
from scenegen_jax.scene import pixel_centers
from scenegen_jax.vector_map import VectorMap, is_crossable

ALL_MAP_CHANNELS: tuple[str, ...] = tuple(c for g in ALL_LAYER_GROUPS for c in LAYER_GROUPS[g])
ORIENTATION_CHANNELS = ("lane_orientation_cos", "lane_orientation_sin")
NEAREST_LANE_CHANNELS = ("nearest_lane_cos", "nearest_lane_sin")
# (cos, sin) pairs of directions in the raster's frame: they turn with it (`crop_map`).
VECTOR_CHANNELS = (ORIENTATION_CHANNELS, NEAREST_LANE_CHANNELS)
# The nearest lane channels are zero farther than this from every centreline.
NEAREST_LANE_MAX_M = 30.0
LINE_HALF_WIDTH_M = 0.15  # painted line / centreline half width before pixel padding


@functools.lru_cache(maxsize=8)
def _grid_points(size: int, m_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    cfg = Config(grid_size=size, m_per_px=m_per_px)
    centers = pixel_centers(cfg).reshape(-1, 2).astype(np.float64)
    return centers, shapely.points(centers)


def _valid(geom):
    return geom if geom.is_valid else shapely.make_valid(geom)


def rasterize_map(vmap: VectorMap, size: int, m_per_px: float) -> np.ndarray:
    """All map channels (`ALL_MAP_CHANNELS`) of a map in the ego frame.

    Args:
      vmap: map in the raster's frame (ego at the origin), m.
      size: raster side, px (the grid is centred on the origin).
      m_per_px: resolution.
    Returns:
      float32 [size, size, len(ALL_MAP_CHANNELS)]; binary channels in {0, 1}, lane
      orientation (cos, sin) of the lane direction inside lane polygons, 0 elsewhere;
      nearest lane (cos, sin) of the nearest centreline's direction within
      `NEAREST_LANE_MAX_M`, 0 farther.
    """
    n = size * size
    centers, points = _grid_points(size, m_per_px)  # cached per grid
    half = size * m_per_px / 2 + 1.0
    roi = shapely.box(-half, -half, half, half)
    line_buffer = max(LINE_HALF_WIDTH_M, 0.5 * m_per_px)
    channels = {c: np.zeros(n, np.float32) for c in ALL_MAP_CHANNELS}
    tree = shapely.STRtree(points)

    def hit_points(geoms: list) -> np.ndarray:
        geoms = [g for g in geoms if not g.is_empty and g.intersects(roi)]
        if not geoms:
            return np.zeros((2, 0), np.int64)
        return tree.query(geoms, predicate="intersects")

    lane_polys = [_valid(shapely.Polygon(lane.polygon)) for lane in vmap.lanes]
    for name, lane_type in (
        ("lane_vehicle", "VEHICLE"),
        ("lane_bike", "BIKE"),
        ("lane_bus", "BUS"),
    ):
        sel = [
            p for p, lane in zip(lane_polys, vmap.lanes, strict=True) if lane.lane_type == lane_type
        ]
        channels[name][hit_points(sel)[1]] = 1.0
    sel = [p for p, lane in zip(lane_polys, vmap.lanes, strict=True) if lane.is_intersection]
    channels["lane_intersection"][hit_points(sel)[1]] = 1.0
    centrelines = [shapely.LineString(lane.centerline) for lane in vmap.lanes]
    channels["lane_centerline"][hit_points([c.buffer(line_buffer) for c in centrelines])[1]] = 1.0
    crossable, uncrossable = [], []
    marked = [(lane.left, lane.left_mark) for lane in vmap.lanes]
    marked += [(lane.right, lane.right_mark) for lane in vmap.lanes]
    marked += [(line.points, line.mark) for line in vmap.lines if len(line.points) >= 2]
    for line, mark in marked:
        kind = is_crossable(mark)
        if kind is not None:
            (crossable if kind else uncrossable).append(
                shapely.LineString(line).buffer(line_buffer)
            )
    channels["lane_boundary_crossable"][hit_points(crossable)[1]] = 1.0
    channels["lane_boundary_uncrossable"][hit_points(uncrossable)[1]] = 1.0

    # Lane orientation: direction of the nearest centreline segment of the containing lane.
    keep = [i for i, g in enumerate(lane_polys) if not g.is_empty and g.intersects(roi)]
    if keep:
        pairs = tree.query([lane_polys[i] for i in keep], predicate="intersects")
        for j in np.unique(pairs[0]):
            idx = pairs[1][pairs[0] == j]
            cos, sin = _segment_direction(vmap.lanes[keep[j]].centerline, centers[idx])
            channels["lane_orientation_cos"][idx] = cos
            channels["lane_orientation_sin"][idx] = sin
    # Nearest lane: direction of the nearest centreline segment, on and off the lanes (where
    # the vehicles parked beside a street or in a lot take their heading from its aisles).
    if centrelines:
        pix, nearest = shapely.STRtree(centrelines).query_nearest(
            points, max_distance=NEAREST_LANE_MAX_M, all_matches=False)
        for j in np.unique(nearest):
            idx = pix[nearest == j]
            cos, sin = _segment_direction(vmap.lanes[j].centerline, centers[idx])
            channels["nearest_lane_cos"][idx] = cos
            channels["nearest_lane_sin"][idx] = sin

    areas = [_valid(shapely.Polygon(p)) for p in vmap.drivable_areas if len(p) >= 3]
    channels["drivable_area"][hit_points(areas)[1]] = 1.0
    walks = [_valid(shapely.Polygon(p)) for p in vmap.crosswalks if len(p) >= 3]
    channels["crosswalk"][hit_points(walks)[1]] = 1.0
    return np.stack([channels[c] for c in ALL_MAP_CHANNELS], -1).reshape(size, size, -1)


def _segment_direction(line: np.ndarray, pts: np.ndarray,
                       chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """(cos, sin) of the direction of the segment of `line` [P, 2] nearest to each point
    (`chunk` points at a time: a paper-grid canvas has 200,000)."""
    a, b = line[:-1], line[1:]
    d = b - a
    length2 = np.maximum((d**2).sum(-1), 1e-12)
    nearest = np.empty(len(pts), np.int64)
    for i in range(0, len(pts), chunk):
        p = pts[i : i + chunk, None, :]
        t = np.clip(((p - a[None]) * d[None]).sum(-1) / length2, 0.0, 1.0)
        proj = a[None] + t[..., None] * d[None]
        nearest[i : i + chunk] = np.argmin(((p - proj) ** 2).sum(-1), axis=1)
    u = d[nearest] / np.sqrt(length2[nearest])[:, None]
    return u[:, 0], u[:, 1]


def select_channels(raster, cfg: Config):
    """Map channels of `cfg.map_layers` from a raster holding `ALL_MAP_CHANNELS` (last axis)."""
    idx = [ALL_MAP_CHANNELS.index(c) for c in cfg.map_channels]
    return raster[..., idx]
