"""The reference map rasteriser (host side, shapely 2 vectorised predicates): the named map
channels of a vector map. The model's rasters are drawn by `raster.jax_map` where the model
runs; the tests hold the two equal on real maps.

Rasters follow the convention documented in `scenegen_jax.scene`. Polygons are sampled at
pixel centres; polylines (centrelines, painted boundaries) are buffered to at least half a
pixel (`line_half_width`) so they are never missed at coarse resolutions.
"""

from __future__ import annotations

import functools

import numpy as np
import shapely

from scenegen_jax.config import ALL_LAYER_GROUPS, DATASETS, LAYER_GROUPS, GridConfig
from scenegen_jax.scene import pixel_centers
from scenegen_jax.vector_map import VectorMap

ALL_MAP_CHANNELS: tuple[str, ...] = tuple(c for g in ALL_LAYER_GROUPS for c in LAYER_GROUPS[g])
ORIENTATION_CHANNELS = ("lane_orientation_cos", "lane_orientation_sin")
NEAREST_LANE_CHANNELS = ("nearest_lane_cos", "nearest_lane_sin")
# (cos, sin) pairs of directions in the raster's frame: they turn with it (`crop_map`).
VECTOR_CHANNELS = (ORIENTATION_CHANNELS, NEAREST_LANE_CHANNELS)
# The nearest lane channels are zero farther than this from every centreline.
NEAREST_LANE_MAX_M = 30.0
# Side of the pixel blocks of the nearest-centreline search (`_nearest_segments`), m.
NEAREST_BLOCK_M = 1.5
LINE_HALF_WIDTH_M = 0.15  # painted line / centreline half width before pixel padding


def line_half_width(m_per_px: float) -> float:
    """Half width (m) lines are drawn at: at least half a pixel, so none is missed."""
    return max(LINE_HALF_WIDTH_M, 0.5 * m_per_px)


@functools.lru_cache(maxsize=8)
def _grid_points(size: int, m_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    grid = GridConfig(grid_size=size, m_per_px=m_per_px)
    centers = pixel_centers(grid).reshape(-1, 2).astype(np.float64)
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
      `NEAREST_LANE_MAX_M`, 0 farther; the plane of the map's data set (`vmap.dataset`) 1
      everywhere, the other data sets' 0.
    """
    n = size * size
    centers, points = _grid_points(size, m_per_px)  # cached per grid
    half = size * m_per_px / 2 + 1.0
    # Nothing farther than the nearest lane's range from the raster changes it (box test).
    vmap = vmap.crop(np.zeros(2), half + NEAREST_LANE_MAX_M)
    lines = [lane.centerline for lane in vmap.lanes]
    roi = shapely.box(-half, -half, half, half)
    line_buffer = line_half_width(m_per_px)
    channels = {c: np.zeros(n, np.float32) for c in ALL_MAP_CHANNELS}
    tree = shapely.STRtree(points)
    hit_points = functools.partial(_hit_points, tree, roi)
    lane_polys = [_valid(shapely.Polygon(lane.polygon)) for lane in vmap.lanes]
    _draw_lanes(channels, hit_points, vmap, lane_polys, lines, line_buffer)
    _draw_lane_orientation(channels, tree, roi, lane_polys, lines, centers)
    if lines:
        _draw_nearest_lane(channels, centers, size, m_per_px, lines)
    areas = [_valid(shapely.Polygon(p)) for p in vmap.drivable_areas if len(p) >= 3]
    channels["drivable_area"][hit_points(areas)[1]] = 1.0
    walks = [_valid(shapely.Polygon(p)) for p in vmap.crosswalks if len(p) >= 3]
    channels["crosswalk"][hit_points(walks)[1]] = 1.0
    if vmap.dataset in DATASETS:
        channels[LAYER_GROUPS["dataset"][DATASETS.index(vmap.dataset)]][:] = 1.0
    return np.stack([channels[c] for c in ALL_MAP_CHANNELS], -1).reshape(size, size, -1)


def _hit_points(tree: shapely.STRtree, roi, geoms: list) -> np.ndarray:
    """(geometry, pixel) index pairs [2, P] of the pixel centres in `tree` that the geometries
    meeting the region `roi` cover."""
    geoms = [g for g in geoms if not g.is_empty and g.intersects(roi)]
    if not geoms:
        return np.zeros((2, 0), np.int64)
    return tree.query(geoms, predicate="intersects")


def _draw_lanes(channels: dict, hit_points, vmap: VectorMap, lane_polys: list, lines: list,
                line_buffer: float) -> None:
    """The lane type, intersection, centreline and lane boundary channels (`hit_points`: the
    pixels a list of geometries covers; `lines`: the lanes' centrelines; lines buffered by
    `line_buffer` m)."""
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
    centrelines = [shapely.LineString(line) for line in lines]
    channels["lane_centerline"][hit_points([c.buffer(line_buffer) for c in centrelines])[1]] = 1.0
    crossable, uncrossable = [], []
    for line, kind in vmap.marked_lines():
        (crossable if kind else uncrossable).append(shapely.LineString(line).buffer(line_buffer))
    channels["lane_boundary_crossable"][hit_points(crossable)[1]] = 1.0
    channels["lane_boundary_uncrossable"][hit_points(uncrossable)[1]] = 1.0


def _draw_lane_orientation(channels: dict, tree: shapely.STRtree, roi, lane_polys: list,
                           lines: list, centers: np.ndarray) -> None:
    """Lane orientation: the direction of the nearest centreline segment of the lane that
    holds the pixel (`lines`: the lanes' centrelines)."""
    keep = [i for i, g in enumerate(lane_polys) if not g.is_empty and g.intersects(roi)]
    if keep:
        pairs = tree.query([lane_polys[i] for i in keep], predicate="intersects")
        for j in np.unique(pairs[0]):
            idx = pairs[1][pairs[0] == j]
            cos, sin = _segment_direction(lines[keep[j]], centers[idx])
            channels["lane_orientation_cos"][idx] = cos
            channels["lane_orientation_sin"][idx] = sin


def _draw_nearest_lane(channels: dict, centers: np.ndarray, size: int, m_per_px: float,
                       lines: list) -> None:
    """Nearest lane: the direction of the nearest centreline segment, on and off the lanes
    (where the vehicles parked beside a street or in a lot take their heading from its
    aisles), within `NEAREST_LANE_MAX_M`."""
    a = np.concatenate([line[:-1] for line in lines])
    b = np.concatenate([line[1:] for line in lines])
    block = max(2, round(NEAREST_BLOCK_M / m_per_px))
    seg = _nearest_segments(centers, size, a, b, NEAREST_LANE_MAX_M, block)
    hit = seg >= 0
    d = b[seg[hit]] - a[seg[hit]]
    d /= np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)[:, None]
    channels["nearest_lane_cos"][hit] = d[:, 0]
    channels["nearest_lane_sin"][hit] = d[:, 1]


def _point_segment_distance2(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distance from points `p` [..., 2] to segments [a, b] ([..., 2], broadcast)."""
    d = b - a
    t = np.clip(((p - a) * d).sum(-1) / np.maximum((d**2).sum(-1), 1e-12), 0.0, 1.0)
    e = p - (a + t[..., None] * d)
    return (e**2).sum(-1)


def _nearest_segments(centers: np.ndarray, size: int, a: np.ndarray, b: np.ndarray,
                      max_m: float, block: int, chunk: int = 64) -> np.ndarray:
    """Index of the segment [a, b] ([S, 2] each) nearest to each pixel centre ([size * size,
    2], row-major), -1 where every segment is farther than `max_m`; of equally near segments
    the first.

    Block by block (`block` x `block` pixels of centre c and radius r, the farthest pixel
    from c): a pixel p of the block with the nearest segment at d(p) <= d(c) + r has it
    among the segments within d(c) + 2r of c (triangle inequality), so only those are
    measured against the block's pixels. Shapely's nearest-geometry query over every pixel
    would take most of a large raster's time, many times this search's."""
    rows = np.arange(size) // block
    nb = int(rows[-1]) + 1
    blocks = (rows[:, None] * nb + rows[None, :]).ravel()
    order = np.argsort(blocks, kind="stable")  # pixels grouped by block
    counts = np.bincount(blocks, minlength=nb * nb)
    per = counts.max()
    # Pixel indices per block, padded with its last pixel (written twice, the same value).
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.minimum(np.arange(per)[None], counts[:, None] - 1)
    pix = order[starts[:, None] + slot]  # [blocks, per]
    c = centers[pix].mean(1)
    r = np.hypot(*(centers[pix] - c[:, None]).transpose(2, 0, 1)).max(1)

    segs = shapely.linestrings(np.stack([a, b], 1))
    tree = shapely.STRtree(segs)
    cpts = shapely.points(c)
    (bi, _), dist = tree.query_nearest(cpts, max_distance=max_m + r.max(),
                                       return_distance=True, all_matches=False)
    near = np.full(len(c), np.inf)  # each block centre's distance to its nearest segment
    near[bi] = dist
    out = np.full(size * size, -1, np.int64)
    live = np.flatnonzero(near <= max_m + r)
    if not len(live):
        return out
    pairs = tree.query(cpts[live], predicate="dwithin", distance=near[live] + 2 * r[live] + 1e-6)
    pb, ps = live[pairs[0]], pairs[1]
    o = np.lexsort((ps, pb))  # by block, then segment index: ties go to the first segment
    pb, ps = pb[o], ps[o]
    k = np.bincount(pb, minlength=len(c))
    first = np.concatenate([[0], np.cumsum(k)[:-1]])
    live = live[np.argsort(k[live], kind="stable")]  # similar candidate counts in a chunk
    for lo in range(0, len(live), chunk):
        bl = live[lo : lo + chunk]
        j = np.minimum(np.arange(k[bl].max())[None], k[bl, None] - 1)
        cand = ps[first[bl, None] + j]  # [n, kmax], padded with the block's last candidate
        p = centers[pix[bl]][:, :, None]  # [n, per, 1, 2]
        dist2 = _point_segment_distance2(p, a[cand][:, None], b[cand][:, None])
        best = np.argmin(dist2, -1)  # [n, per]
        seg = np.take_along_axis(cand, best.reshape(len(bl), -1), 1)
        within = np.take_along_axis(dist2, best[..., None], -1)[..., 0] <= max_m**2
        out[pix[bl][within]] = seg[within]
    return out


def _segment_direction(line: np.ndarray, pts: np.ndarray,
                       chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """(cos, sin) of the direction of the segment of `line` [P, 2] nearest to each point
    (`chunk` points at a time: a paper-grid canvas has 200,000)."""
    a, b = line[:-1], line[1:]
    nearest = np.empty(len(pts), np.int64)
    for i in range(0, len(pts), chunk):
        dist2 = _point_segment_distance2(pts[i : i + chunk, None, :], a[None], b[None])
        nearest[i : i + chunk] = np.argmin(dist2, axis=1)
    d = (b - a)[nearest]
    u = d / np.sqrt(np.maximum((d**2).sum(-1), 1e-12))[:, None]
    return u[:, 0], u[:, 1]


def select_channels(raster, grid: GridConfig):
    """Map channels of `grid.map_layers` from a raster holding `ALL_MAP_CHANNELS` (last axis)."""
    idx = [ALL_MAP_CHANNELS.index(c) for c in grid.map_channels]
    return raster[..., idx]
