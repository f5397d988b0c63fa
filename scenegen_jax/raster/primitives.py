"""A vector map as the device rasteriser reads it (host side, numpy): polygon edges, line
pieces and centreline segments in padded arrays (`MapPrimitives`), so that scenes batch and
the rasteriser (`raster.jax_map`) compiles once per size bucket.

Edges and pieces are cut to at most `PIECE_PX` pixels, so each spans a fixed, small window
of rows and columns under any rotation: the rasteriser touches only the pixels near each
piece instead of every pixel for every edge.
"""

from __future__ import annotations

import math

import numpy as np
import shapely
from flax import struct

from scenegen_jax.config import DATASETS
from scenegen_jax.raster.map import NEAREST_LANE_MAX_M, line_half_width
from scenegen_jax.vector_map import VectorMap, centerlines

# Channels filled inside polygons, and drawn along lines, by bit / index.
FILL_CHANNELS = (
    "lane_vehicle", "lane_bike", "lane_bus", "lane_intersection", "drivable_area", "crosswalk",
)
LINE_CHANNELS = ("lane_centerline", "lane_boundary_crossable", "lane_boundary_uncrossable")
_LANE_TYPE_CHANNEL = {"VEHICLE": 0, "BIKE": 1, "BUS": 2}
# Longest polygon edge or line piece, pixels: every piece spans at most PIECE_PX + 1 rows.
PIECE_PX = 4
# Centreline points this close (m) to the line through their kept neighbours are dropped:
# the direction of a segment then differs from that of the points it replaces by at most
# about 2 * CENTRE_TOLERANCE_M / its length (0.002 for a 1 m segment). Waymo's straight
# lanes, sampled every half metre, keep a quarter of their segments.
CENTRE_TOLERANCE_M = 0.001
# Smallest padded length of each array (sizes are rounded up to powers of two from it).
MIN_BUCKET = 64


@struct.dataclass
class MapPrimitives:
    """One map (or a batch of maps, leading axis B) in the ego frame, padded.

    Attributes:
      edges: float32 [E, 4] polygon edges (x0, y0, x1, y1), m; padding: zero length.
      edge_poly: int32 [E] polygon of each edge.
      poly_bits: int32 [N] bitmask over `FILL_CHANNELS` of each polygon; lanes first, in the
        map's lane order (polygon i < number of lanes is lane i).
      poly_lane: bool [N] the polygon is a lane's (lane orientation takes the last lane
        holding a pixel).
      pieces: float32 [Q, 4] line pieces (x0, y0, x1, y1), m.
      piece_channel: int32 [Q] index into `LINE_CHANNELS`; padding: len(LINE_CHANNELS).
      centre: float32 [S, 4] lane centreline segments, lanes in order.
      centre_poly: int32 [S] the lane (polygon index) of each segment; -1 padding.
      lane_segments: int32 [N, K] the indices of each lane's centreline segments in
        `centre`, -1 padding (rows of polygons that are no lanes: all -1).
      dataset: int32 [] index of the map's data set in `config.DATASETS`, -1 none.
    """

    edges: np.ndarray
    edge_poly: np.ndarray
    poly_bits: np.ndarray
    poly_lane: np.ndarray
    pieces: np.ndarray
    piece_channel: np.ndarray
    centre: np.ndarray
    centre_poly: np.ndarray
    lane_segments: np.ndarray
    dataset: np.ndarray


def _split_segments(a: np.ndarray, b: np.ndarray, max_len: float) -> tuple[np.ndarray, ...]:
    """Segments [a, b] ([K, 2] each) cut into pieces no longer than `max_len`: (starts, ends,
    index of the segment each piece comes from)."""
    n = np.maximum(np.ceil(np.hypot(*(b - a).T) / max_len), 1).astype(np.int64)
    src = np.repeat(np.arange(len(a)), n)
    first = np.cumsum(n) - n
    k = np.arange(len(src)) - first[src]
    t0 = (k / n[src])[:, None]
    t1 = ((k + 1) / n[src])[:, None]
    d = b[src] - a[src]
    return a[src] + t0 * d, a[src] + t1 * d, src


def _rings(vmap: VectorMap) -> tuple[list[np.ndarray], list[int], list[bool]]:
    """(outline [P, 2], channel bits, is a lane) of every polygon: lanes in order, then
    crosswalks and drivable areas (those with at least 3 points)."""
    rings, bits, lane = [], [], []
    for ln in vmap.lanes:
        b = 0
        if ln.lane_type in _LANE_TYPE_CHANNEL:
            b |= 1 << _LANE_TYPE_CHANNEL[ln.lane_type]
        if ln.is_intersection:
            b |= 1 << FILL_CHANNELS.index("lane_intersection")
        rings.append(ln.polygon)
        bits.append(b)
        lane.append(True)
    for polys, name in ((vmap.crosswalks, "crosswalk"), (vmap.drivable_areas, "drivable_area")):
        for p in polys:
            if len(p) >= 3:
                rings.append(np.asarray(p, np.float64))
                bits.append(1 << FILL_CHANNELS.index(name))
                lane.append(False)
    return rings, bits, lane


def _lines(vmap: VectorMap, centres: list[np.ndarray]) -> tuple[list[np.ndarray], list[int]]:
    """(polyline [P, 2], `LINE_CHANNELS` index) of every drawn line: the lanes' centrelines
    (`centres`), then their painted boundaries and the standalone lines with a mark."""
    lines, chans = list(centres), [0] * len(centres)
    for pts, crossable in vmap.marked_lines():
        lines.append(np.asarray(pts, np.float64))
        chans.append(1 if crossable else 2)
    return lines, chans


def _segments(polylines: list[np.ndarray], closed: bool) -> tuple[np.ndarray, np.ndarray,
                                                                   np.ndarray]:
    """(starts [K, 2], ends [K, 2], polyline index [K]) of the polylines' segments; `closed`
    adds each ring's closing segment."""
    a, b, owner = [], [], []
    for i, p in enumerate(polylines):
        p = np.asarray(p, np.float64)
        if closed:
            p = np.concatenate([p, p[:1]])
        if len(p) < 2:
            continue
        a.append(p[:-1])
        b.append(p[1:])
        owner.append(np.full(len(p) - 1, i))
    if not a:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64)
    return np.concatenate(a), np.concatenate(b), np.concatenate(owner)


def _simplify(line: np.ndarray) -> np.ndarray:
    """A centreline [P, 2] without its points within CENTRE_TOLERANCE_M of the line through
    their neighbours (Douglas-Peucker): sources sample lanes every half metre, straight ones
    too, and the direction fields measure every pixel against every segment nearby."""
    if len(line) < 3:
        return line
    simple = shapely.simplify(shapely.linestrings(line), CENTRE_TOLERANCE_M,
                              preserve_topology=False)
    out = shapely.get_coordinates(simple)
    return out if len(out) >= 2 else line[[0, -1]]


def reach_m(size: int, m_per_px: float) -> float:
    """Radius (m) of the disc that holds a `size` x `size` raster under every rotation."""
    return size * m_per_px / math.sqrt(2.0) + m_per_px


def map_primitives(vmap: VectorMap, size: int, m_per_px: float) -> MapPrimitives:
    """The unpadded primitives of a map in the ego frame for a `size` x `size` raster at
    `m_per_px` under any rotation about the ego."""
    reach = reach_m(size, m_per_px)
    near = vmap.crop(np.zeros(2), reach + NEAREST_LANE_MAX_M)
    piece_m = PIECE_PX * m_per_px

    rings, bits, lane = _rings(near)
    a, b, ring = _segments(rings, closed=True)
    a, b, src = _split_segments(a, b, piece_m)
    edge_poly = ring[src]
    centres = centerlines(near.lanes)
    lines, chans = _lines(near, centres)
    la, lb, line = _segments(lines, closed=False)
    pa, pb, psrc = _split_segments(la, lb, piece_m)
    w = line_half_width(m_per_px)
    lo, hi = np.minimum(pa, pb), np.maximum(pa, pb)
    keep = np.all(hi >= -reach - w, 1) & np.all(lo <= reach + w, 1)
    pieces = np.concatenate([pa, pb], 1)[keep]
    piece_channel = np.asarray(chans, np.int64)[line[psrc]][keep] if len(psrc) else np.zeros(0)

    ca, cb, cl = _segments([_simplify(c) for c in centres], closed=False)
    return MapPrimitives(
        edges=np.concatenate([a, b], 1).astype(np.float32),
        edge_poly=edge_poly.astype(np.int32),
        poly_bits=np.asarray(bits, np.int32),
        poly_lane=np.asarray(lane, bool),
        pieces=pieces.astype(np.float32),
        piece_channel=piece_channel.astype(np.int32),
        centre=np.concatenate([ca, cb], 1).astype(np.float32),
        centre_poly=cl.astype(np.int32),
        lane_segments=_lane_segments(cl, len(bits)),
        dataset=np.asarray(DATASETS.index(vmap.dataset) if vmap.dataset in DATASETS else -1,
                           np.int32),
    )


def _lane_segments(seg_lane: np.ndarray, num_polys: int) -> np.ndarray:
    """int32 [num_polys, K]: row l lists the segments of lane l (`seg_lane` [S], ascending),
    -1 after them; K = the most segments of a lane (at least 1)."""
    counts = np.bincount(seg_lane, minlength=num_polys)[:num_polys]
    out = np.full((num_polys, max(int(counts.max(initial=0)), 1)), -1, np.int32)
    starts = np.cumsum(counts) - counts
    for lane in np.flatnonzero(counts):
        out[lane, : counts[lane]] = np.arange(starts[lane], starts[lane] + counts[lane])
    return out


def bucket(n: int) -> int:
    """Padded length of an array of n items: a power of two, at least MIN_BUCKET."""
    return max(MIN_BUCKET, 1 << max(int(n) - 1, 0).bit_length())


def _pad(x: np.ndarray, n: int, value) -> np.ndarray:
    out = np.full((n, *x.shape[1:]), value, x.dtype)
    out[: len(x)] = x
    return out


def stack_primitives(prims: list[MapPrimitives]) -> MapPrimitives:
    """A batch [B] of maps' primitives, each array padded to the batch's bucket (`bucket`)."""
    size = {f: bucket(max(len(getattr(p, f)) for p in prims))
            for f in ("edges", "poly_bits", "pieces", "centre")}
    pad_value = {
        "edges": ("edges", 0.0), "edge_poly": ("edges", 0),
        "poly_bits": ("poly_bits", 0), "poly_lane": ("poly_bits", False),
        "pieces": ("pieces", 0.0), "piece_channel": ("pieces", len(LINE_CHANNELS)),
        "centre": ("centre", 0.0), "centre_poly": ("centre", -1),
    }
    fields = {
        f: np.stack([_pad(getattr(p, f), size[k], v) for p in prims])
        for f, (k, v) in pad_value.items()
    }
    width = bucket(max(p.lane_segments.shape[1] for p in prims))
    lane_segments = np.full((len(prims), size["poly_bits"], width), -1, np.int32)
    for i, p in enumerate(prims):
        lane_segments[i, : p.lane_segments.shape[0], : p.lane_segments.shape[1]] = p.lane_segments
    return MapPrimitives(**fields, lane_segments=lane_segments,
                         dataset=np.stack([p.dataset for p in prims]))
