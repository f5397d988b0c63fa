"""The layout of a preprocessing cache: vector maps and padded actor arrays that training
reads fast.

Layout of a cache directory (S scenes, E stored map elements, P stored map points):
  meta.json         config (grid, resolution), channel names, scene ids, the prepare summary,
                    and `map_vocab`: the lane types, marks and data set names that the codes
                    below index
  .lock             only while `prepare` writes the cache: the writer's pid and host
  actors.npz        padded actors [S, A] (cls, position, size, heading, velocity, valid,
                    size_measured), their `future` positions [S, A, H, 2] float32 in the
                    ego frame (`frame.FUTURE_HORIZONS_S` ahead; NaN where unobserved and in
                    empty slots), the ego (velocity, size) per scene, the ego's world pose
                    `city_from_ego` [S, 3, 3], and per scene `map_start`, `map_count` (its
                    entries of map_index.npy) and `dataset` (a `map_vocab.dataset` code)
  map_index.npy     int32 [I] the element indices of every scene's map, scene after scene,
                    each in its map's order: lanes, crosswalks, drivable areas, lines
  map_elements.npz  per stored element [E]: kind (int8, `map_store.KINDS`), start and count
                    of its points in map_points.npy, split (a lane's left-boundary points,
                    then its right boundary), lane_type and mark [E, 2] codes (a lane's left
                    and right marks, a line's mark; -1 where the kind has none),
                    is_intersection, and the float64 anchor [E, 2] (m, world frame) and
                    scale [E] (m) of its points
  map_points.npy    int32 [P, 2] every stored point as anchor + scale * offset (world frame;
                    scale is 2**-21 m, ~0.5 um, unless an element reaches beyond int32's
                    range at it, ~1 km from its first point)

An element (its kind, attributes and world points to 1e-4 m) is stored once however many
frames hold it: the frames of one scenario or log share most of their map. The map rasters
(the channels of `meta.json`'s `channels`) are drawn where the model runs
(`raster.jax_map`), at the grid and rotation it reads.

A sharded cache (`prepare --shard I/N`, one job per shard, e.g. on N machines) is a directory
of N such caches, `shard-0000I-of-0000N/`; `cache.load_cache` reads it as one cache, the
shards' scenes in shard order and their map arrays memory-mapped per shard.

The actors are those within the disc that holds the grid under every rotation about the
ego (`canvas_radius`), so rotation augmentation never reaches outside the cache.
`cache_write` writes caches, `cache` reads them, `map_store` encodes and decodes the maps.
"""

from __future__ import annotations

import math
import os
import re
import tokenize
import zipfile

from scenegen_jax.config import Config

# 2: the nearest lane channels; 3: the data set channels; 4: whether each box was measured;
# 5: vector maps stored once per cache in place of a raster canvas per scene; 6: the actors'
# future positions (a version 5 cache reads without them).
CACHE_VERSION = 6
READABLE_VERSIONS = (5, 6)
FUTURE_FIELD = "future"
# The first version whose caches hold FUTURE_FIELD.
FUTURE_VERSION = 6
# The raster canvases [S, C, C, channels] of the caches before version 5, which this
# scenegen no longer reads.
RASTER_FILE = "maps.npy"
# What np.load raises on a truncated or damaged .npy / .npz: a header that is cut or no
# Python literal fails in numpy's header parser with SyntaxError or tokenize.TokenError.
UNREADABLE_ARRAY = (
    ValueError,
    OSError,
    EOFError,
    SyntaxError,
    TypeError,
    tokenize.TokenError,
    zipfile.BadZipFile,
)
ACTOR_FIELDS = ("cls", "position", "size", "heading", "velocity", "valid", "size_measured")


def cache_slots(cfg: Config) -> int:
    """Actor slots stored per scene: room for the in-region maximum under any rotation."""
    return 2 * cfg.grid.max_actors


def canvas_radius(cfg: Config) -> float:
    """Radius (m) of the disc that holds the grid under every rotation (its half diagonal)."""
    return cfg.grid.region_m / math.sqrt(2.0)


SHARD_NAME = "shard-{:05d}-of-{:05d}"
SHARD_RE = re.compile(r"shard-(\d{5})-of-(\d{5})")


def shard_dir(out_dir: str, index: int, count: int) -> str:
    """The folder of shard `index` of `count` inside the cache directory `out_dir`."""
    if not 0 <= index < count:
        raise ValueError(f"--shard {index}/{count}: need 0 <= I < N")
    return os.path.join(out_dir, SHARD_NAME.format(index, count))

