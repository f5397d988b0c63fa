"""The layout of a preprocessing cache: map canvases and padded actor arrays that training
reads fast.

Layout of a cache directory:
  meta.json     config (grid, resolution), channel names, scene ids, the prepare summary
  .lock         only while `prepare` writes the cache: the writer's pid and host
  maps.npy      float16 [S, C, C, len(ALL_MAP_CHANNELS)] map canvases (C = canvas_size)
  actors.npz    padded actors [S, A] (cls, position, size, heading, velocity, valid,
                size_measured), the ego (velocity, size) per scene, and the ego's city
                pose [S, 3, 3]

A sharded cache (`prepare --shard I/N`, one job per shard, e.g. on N machines) is a directory
of N such caches, `shard-0000I-of-0000N/`; `cache.load_cache` reads it as one cache, the
shards' scenes in shard order and their maps memory-mapped per shard.

The canvas covers every rotation of the grid about the ego, and the actors are those within
the canvas's inscribed circle, so rotation augmentation never reaches outside the cache.
`cache_write` writes caches, `cache` reads them.
"""

from __future__ import annotations

import math
import os
import re

from scenegen_jax.config import Config

# 2: the nearest lane channels; 3: the data set channels; 4: whether each box was measured.
CACHE_VERSION = 4
# Versions this one reads: a version 3 cache predates `size_measured`, and every source it
# could be written from measured its boxes except ScenarioNet's Argoverse 2 converter, whose
# constant boxes only a re-run of prepare marks.
READABLE_VERSIONS = (3, 4)
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

