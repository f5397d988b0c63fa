"""Map rasterisation where the model runs (JAX, jit and vmap): the channels of
`raster.map.ALL_MAP_CHANNELS` drawn from a map's primitives (`raster.primitives`) at any
rotation about the ego, straight onto the grid.

It draws what the shapely rasteriser (`raster.map`, the reference it is tested against)
draws, sampled at pixel centres:
- polygons (lanes by type, intersections, drivable areas, crosswalks) filled by the
  crossing rule: a pixel is inside a polygon when a ray from its centre crosses its edges
  an odd number of times (each edge adds its crossings of the rows it spans, one cumulative
  sum per row counts them);
- lines (centrelines, painted boundaries) as every pixel whose centre lies within the line's
  half width (`primitives.line_half_width`) of a piece;
- the lane orientation: the direction of the nearest centreline segment of the last lane
  (in the map's order) holding the pixel; the nearest lane: the direction of the nearest
  centreline segment within `NEAREST_LANE_MAX_M`, ties to the first;
- the data set planes.
Directions are in the rotated frame. Raster convention: `scenegen_jax.scene`.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from scenegen_jax.config import DATASETS, LAYER_GROUPS, GridConfig
from scenegen_jax.raster.map import NEAREST_LANE_MAX_M, line_half_width
from scenegen_jax.raster.primitives import (
    FILL_CHANNELS,
    LINE_CHANNELS,
    PIECE_PX,
    MapPrimitives,
    map_primitives,
    stack_primitives,
)
from scenegen_jax.raster.transform import rotate_vectors
from scenegen_jax.vector_map import VectorMap

# The direction fields go block by block of about BLOCK_M x BLOCK_M metres of pixels, each
# measured against at most CANDIDATES segments near it (`_block_directions`).
BLOCK_M = 4.0
CANDIDATES = 256


def _to_pixels(xy, size: int, m_per_px: float):
    """Continuous (column, row) coordinates of points [..., 2] (pixel (r, c) spans [c, c+1)
    x [r, r+1), its centre at (c + 0.5, r + 0.5))."""
    half = size * m_per_px / 2
    return jnp.stack([(xy[..., 0] + half) / m_per_px, (half - xy[..., 1]) / m_per_px], -1)


def _fill(a, b, poly, bits, lane_index, size: int, rows_per_edge: int):
    """Polygon fill at the pixel centres from the polygons' edges [a, b] ([E, 2] each, pixel
    coordinates, each edge crossing at most `rows_per_edge` row centres) and their polygon
    [E] (`bits` [N]: each polygon's `FILL_CHANNELS` bitmask; `lane_index` [N]: its lane
    index, -1 for no lane).

    Returns:
      (bitwise or of the bits of the polygons holding each pixel, int32 [size, size]; the
      last lane holding it, int32 [size, size], -1 none).
    """
    v_lo = jnp.minimum(a[:, 1], b[:, 1])
    rows = jnp.ceil(v_lo - 0.5).astype(jnp.int32)[:, None] + jnp.arange(rows_per_edge)[None]
    yc = rows + 0.5  # [E, R] centres of the rows the edge may cross
    v0, v1 = a[:, 1:2], b[:, 1:2]
    cross = ((v0 <= yc) != (v1 <= yc)) & (rows >= 0) & (rows < size)
    dv = jnp.where(v1 == v0, 1.0, v1 - v0)
    u = a[:, 0:1] + (yc - v0) * (b[:, 0:1] - a[:, 0:1]) / dv
    # The crossing lies left of the centres of columns >= k: it flips their parity.
    k = jnp.clip(jnp.floor(u - 0.5).astype(jnp.int32) + 1, 0, size)
    flips = jnp.zeros((size + 1, bits.shape[0], size), jnp.uint8)  # [column, polygon, row]
    flips = flips.at[k, jnp.broadcast_to(poly[:, None], rows.shape),
                     jnp.clip(rows, 0, size - 1)].add(cross.astype(jnp.uint8))

    def column(parity, flip):  # parity [N, size]: inside each polygon, this column's rows
        parity = parity ^ (flip & 1)
        inside = parity.astype(bool)
        held = jnp.bitwise_or.reduce(jnp.where(inside, bits[:, None], 0), axis=0)
        owner = jnp.max(jnp.where(inside, lane_index[:, None], -1), axis=0)
        return parity, (held, owner)

    # Column by column, so that no [N, size, size] array is ever made.
    _, (held, owner) = jax.lax.scan(column, jnp.zeros(flips.shape[1:], jnp.uint8),
                                    flips[:size])
    return held.T, owner.T


def _lines(a, b, channel, size: int, w_px: float):
    """float32 [len(LINE_CHANNELS), size, size]: 1 at the pixel centres within `w_px` of a
    piece [a, b] ([Q, 2] each, pixel coordinates, pieces no longer than PIECE_PX) of each
    channel (`channel` [Q]; len(LINE_CHANNELS) for padding)."""
    n = math.floor(PIECE_PX + 2 * w_px) + 2
    lo = jnp.minimum(a, b) - w_px - 0.5
    c0 = jnp.ceil(lo).astype(jnp.int32)  # first column / row whose centre may be near
    cols = c0[:, 0, None, None] + jnp.arange(n)[None, None, :]  # [Q, 1, n]
    rows = c0[:, 1, None, None] + jnp.arange(n)[None, :, None]  # [Q, n, 1]
    p = jnp.stack(jnp.broadcast_arrays(cols + 0.5, rows + 0.5), -1)  # [Q, n, n, 2]
    d2 = _point_segment_d2(p, a[:, None, None], b[:, None, None])
    inside = (rows >= 0) & (rows < size) & (cols >= 0) & (cols < size)
    hit = (d2 <= w_px * w_px) & inside
    out = jnp.zeros((len(LINE_CHANNELS) + 1, size, size), jnp.float32)
    ch = jnp.broadcast_to(channel[:, None, None], hit.shape)
    out = out.at[ch, jnp.clip(jnp.broadcast_to(rows, hit.shape), 0, size - 1),
                 jnp.clip(jnp.broadcast_to(cols, hit.shape), 0, size - 1)].max(
        hit.astype(jnp.float32))
    return out[: len(LINE_CHANNELS)]


def _point_segment_d2(p, a, b):
    """Squared distance of points p [..., 2] to segments [a, b] (broadcast)."""
    d = b - a
    t = jnp.clip(((p - a) * d).sum(-1) / jnp.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
    e = p - (a + t[..., None] * d)
    return (e * e).sum(-1)


def _argmin(x):
    """First index of the minimum along the last axis and the minimum: two plain reductions
    (XLA's CPU backend runs `argmin`'s (value, index) reduction many times slower)."""
    low = jnp.min(x, -1, keepdims=True)
    iota = jax.lax.broadcasted_iota(jnp.int32, x.shape, x.ndim - 1)
    return jnp.min(jnp.where(x == low, iota, x.shape[-1] - 1), -1), low[..., 0]


def _d2_to(p, a, b, idx):
    """Squared distances [n, K] of points p [n, 2] to the segments idx [n, K] or [K] of
    [a, b] ([S, 2] each), x and y apart (arrays of pairs [n, K, 2] vectorise poorly)."""
    ax, ay = a[idx, 0], a[idx, 1]
    dx, dy = b[idx, 0] - ax, b[idx, 1] - ay
    px, py = p[:, 0:1], p[:, 1:2]
    t = jnp.clip(((px - ax) * dx + (py - ay) * dy) / jnp.maximum(dx * dx + dy * dy, 1e-12),
                 0.0, 1.0)
    ex, ey = px - ax - t * dx, py - ay - t * dy
    return ex * ex + ey * ey


def _block_directions(p, owner, centre, radius, a, b, valid, lane_segments, k: int):
    """(nearest segment [n], its squared distance [n], nearest segment of the owner lane [n])
    of the pixel centres p [n, 2] of one block (centre `centre`, every pixel within `radius`
    of it; `owner` [n] lane holding each pixel, -1 none).

    The nearest segment of a pixel at d(p) <= d(c) + radius from the centre's nearest lies
    within d(c) + 2 radius of the centre (triangle inequality), so measuring the block's
    pixels against the segments of that band is exact while it holds no more than k (a
    band of more is measured against its first k). On the womd_mini and Argoverse 2 val
    maps the largest band holds 177 segments at the `cpu` grid and 244 at the `paper` one.
    The band is gathered by a cumulative count, not `lax.top_k` or a branch between the
    band and every segment: under the test suite's XLA flags (`tests/conftest.py`) both of
    those gave wrong segments on real maps."""
    s = a.shape[0]
    dc = _d2_to(centre[None], a, b, jnp.arange(s))[0]
    dc = jnp.where(valid, dc, jnp.inf)
    band = dc <= jnp.square(jnp.sqrt(jnp.min(dc)) + 2 * radius)
    # The band's segments in index order (of equally near segments, the first), k slots.
    slot = jnp.where(band, jnp.cumsum(band) - 1, k)
    cand = jnp.zeros(k, jnp.int32).at[slot].set(jnp.arange(s, dtype=jnp.int32), mode="drop")
    count = jnp.sum(band)
    d2 = jnp.where((jnp.arange(k) < count) & valid[cand], _d2_to(p, a, b, cand), jnp.inf)
    j, low = _argmin(d2)
    own = lane_segments[jnp.maximum(owner, 0)]  # [n, K2]
    d2 = jnp.where((own >= 0) & (owner >= 0)[:, None], _d2_to(p, a, b, jnp.maximum(own, 0)),
                   jnp.inf)
    jo, _ = _argmin(d2)
    return cand[j], low, jnp.take_along_axis(own, jo[:, None], 1)[:, 0]


def _direction_fields(size: int, m_per_px: float, a, b, valid, lane_segments, owner,
                      max_m: float):
    """(nearest lane, lane orientation) [size, size, 2] (cos, sin) of segments [a, b] ([S, 2]
    m, rotated frame): at each pixel centre the direction of the nearest valid segment within
    `max_m` (0 farther), and of the nearest segment of the lane `owner` [size, size] (-1: 0),
    block by block (`_block_directions`)."""
    block = max(2, round(BLOCK_M / m_per_px))
    nb = -(-size // block)
    half = size * m_per_px / 2
    coords = (jnp.arange(nb * block) + 0.5) * m_per_px - half  # the grid and its padding
    xx, yy = jnp.meshgrid(coords, -coords)
    pix = jnp.stack([xx, yy], -1).reshape(nb, block, nb, block, 2).transpose(0, 2, 1, 3, 4)
    pix = pix.reshape(nb * nb, block * block, 2)
    own = jnp.pad(owner, ((0, nb * block - size),) * 2, constant_values=-1)
    own = own.reshape(nb, block, nb, block).transpose(0, 2, 1, 3).reshape(nb * nb, -1)
    radius = (block - 1) / 2 * m_per_px * math.sqrt(2.0) + 1e-4
    k = min(CANDIDATES, a.shape[0])
    nearest, low, mine = jax.vmap(
        lambda p, o: _block_directions(p, o, p.mean(0), radius, a, b, valid, lane_segments,
                                       k))(pix, own)
    d = b - a
    unit = d / jnp.maximum(jnp.sqrt((d * d).sum(-1, keepdims=True)), 1e-12)
    near = jnp.where((low <= max_m * max_m)[..., None], unit[nearest], 0.0)
    orient = jnp.where((own >= 0)[..., None], unit[mine], 0.0)

    def image(x):
        x = x.reshape(nb, nb, block, block, 2).transpose(0, 2, 1, 3, 4)
        return x.reshape(nb * block, nb * block, 2)[:size, :size]

    return image(near), image(orient)


@functools.partial(jax.jit, static_argnames=("size", "m_per_px", "channels"))
def rasterise(prims: MapPrimitives, theta, size: int, m_per_px: float,
              channels: tuple[str, ...]):
    """The map channels `channels` of one map rotated by theta about the ego.

    Args:
      prims: one map's primitives (`primitives.map_primitives`, padded), ego frame.
      theta: rotation, rad (counter-clockwise; as `raster.transform.rotate_actors`).
      size: raster side, px (centred on the ego).
      m_per_px: resolution.
      channels: names from `raster.map.ALL_MAP_CHANNELS`.
    Returns:
      float32 [size, size, len(channels)], as `raster.map.rasterize_map` of the rotated map.
    """
    if not channels:
        return jnp.zeros((size, size, 0), jnp.float32)
    out = {}
    num_polys = prims.poly_bits.shape[0]
    lane_index = jnp.where(prims.poly_lane, jnp.arange(num_polys), -1)
    edges = _to_pixels(rotate_vectors(prims.edges.reshape(-1, 2, 2), theta), size, m_per_px)
    held, owner = _fill(edges[:, 0], edges[:, 1], prims.edge_poly, prims.poly_bits, lane_index,
                        size, PIECE_PX + 2)
    for i, name in enumerate(FILL_CHANNELS):
        out[name] = ((held >> i) & 1).astype(jnp.float32)

    pieces = _to_pixels(rotate_vectors(prims.pieces.reshape(-1, 2, 2), theta), size, m_per_px)
    lines = _lines(pieces[:, 0], pieces[:, 1], prims.piece_channel, size,
                   line_half_width(m_per_px) / m_per_px)
    for i, name in enumerate(LINE_CHANNELS):
        out[name] = lines[i]

    centre = rotate_vectors(prims.centre.reshape(-1, 2, 2), theta)
    near, orient = _direction_fields(size, m_per_px, centre[:, 0], centre[:, 1],
                                     prims.centre_poly >= 0, prims.lane_segments, owner,
                                     NEAREST_LANE_MAX_M)
    out["nearest_lane_cos"], out["nearest_lane_sin"] = near[..., 0], near[..., 1]
    out["lane_orientation_cos"], out["lane_orientation_sin"] = orient[..., 0], orient[..., 1]
    for name in LAYER_GROUPS["dataset"]:
        plane = prims.dataset == DATASETS.index(name.removeprefix("dataset_"))
        out[name] = jnp.full((size, size), plane, jnp.float32)
    return jnp.stack([out[c] for c in channels], -1)


@functools.partial(jax.jit, static_argnames=("size", "m_per_px", "channels"))
def rasterise_batch(prims: MapPrimitives, thetas, size: int, m_per_px: float,
                    channels: tuple[str, ...]):
    """`rasterise` over a batch: prims [B, ...], thetas [B] -> [B, size, size, channels], one
    scene after the other (`lax.map`: batched, the lines' scatter runs twice as long on
    CPU)."""
    return jax.lax.map(lambda x: rasterise(x[0], x[1], size, m_per_px, channels),
                       (prims, thetas))


def draw_maps(vmaps: list[VectorMap], thetas, grid: GridConfig, size: int | None = None,
              channels: tuple[str, ...] | None = None):
    """The map rasters of several maps (ego frame) rotated by `thetas` [B] rad: float32
    [B, size, size, len(channels)] on the default device (size: the grid's; channels: the
    grid's `map_channels`)."""
    size = grid.grid_size if size is None else size
    channels = grid.map_channels if channels is None else tuple(channels)
    prims = stack_primitives([map_primitives(v, size, grid.m_per_px) for v in vmaps])
    return rasterise_batch(prims, np.asarray(thetas, np.float32), size, grid.m_per_px, channels)
