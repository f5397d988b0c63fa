"""What the sampling tests share: the tiny config's sizes, boxes as shapely polygons and the
overlaps among them, slots of batched samples, the ego, the bins of actors and the cache of
validation scenes."""

from __future__ import annotations

import collections

import jax
import jax.numpy as jnp
import numpy as np
from shapely.geometry import Polygon

from scenegen_jax.config import get_config
from scenegen_jax.scene import PEDESTRIAN, VEHICLE, Actors, bin_index
from scenegen_jax.viz.render import box_corners

TINY = get_config("tiny")
H = TINY.grid.grid_size
N_BINS = H * H
K = TINY.model.num_mixtures
NEG = -30.0  # logit of an (effectively) impossible outcome


def box_polygon(position, size, heading) -> Polygon:
    return Polygon(box_corners(np.asarray(position, np.float64), np.asarray(size, np.float64),
                               float(heading)))


def overlapping_pairs(actors: Actors, ego: Actors) -> list[tuple[int, int]]:
    """(i, j) of overlapping vehicle/bicyclist boxes by shapely (j = -1: the ego)."""
    a = jax.tree.map(np.asarray, actors)
    idx = [i for i in np.flatnonzero(a.valid) if a.cls[i] != PEDESTRIAN]
    polys = {i: box_polygon(a.position[i], a.size[i], a.heading[i]) for i in idx}
    polys[-1] = box_polygon(ego.position, ego.size, ego.heading)
    keys = sorted(polys)
    return [(i, j) for n, i in enumerate(keys) for j in keys[n + 1:]
            if polys[i].intersection(polys[j]).area > 1e-4]


def slot(tree, *index):
    return jax.tree.map(lambda x: np.asarray(x)[index], tree)


def broadcast(tree, b: int):
    return jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (b, *np.shape(x))), tree)


def ego_of(cfg) -> Actors:
    return Actors(cls=np.int32(VEHICLE), position=np.zeros(2, np.float32),
                  size=np.asarray(cfg.grid.ego_size_m, np.float32), heading=np.float32(0.0),
                  velocity=np.zeros(2, np.float32), valid=np.bool_(True))


def bins_of(actors: Actors, cfg):
    return np.asarray(bin_index(jnp.asarray(actors.position), cfg.grid))


def write_val_cache(out: str, data_root: str):
    """A tiny-config cache of every 20th validation frame (8 scenes) written to `out`."""
    from scenegen_jax.data.cache import load_cache
    from scenegen_jax.data.cache_write import write_cache
    from scenegen_jax.data.sources import read_frames, source_spec

    drops = collections.Counter()
    write_cache(read_frames(source_spec("av2", data_root, "val", 20), drops), out, TINY, drops)
    return load_cache(out)
