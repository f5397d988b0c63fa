"""Training the motion forecaster whose features give the Features MMD
(`model.forecaster`): on cached scenes with their actors' futures (cache version 6), each
scene drawn once at rotation 0, the Huber loss of the displacements minimised by `fit.fit`
(resumable), and the held-out error against constant velocity (`forecast_errors`).
"""

from __future__ import annotations

import functools
import logging
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from scenegen_jax.config import GridConfig
from scenegen_jax.data.cache import Cache
from scenegen_jax.data.cache_layout import FUTURE_VERSION
from scenegen_jax.data.union import CacheUnion
from scenegen_jax.likelihood.host_data import DRAW_CHUNK, cache_maps
from scenegen_jax.model.forecaster import (
    DISPLACEMENT_SCALE_M,
    ForecasterConfig,
    apply_forecaster,
    constant_velocity,
    draw_scene_rasters,
    forecast,
    init_forecaster,
    scene_actors,
)
from scenegen_jax.raster.actors import ACTOR_CHANNELS
from scenegen_jax.raster.map import VECTOR_CHANNELS
from scenegen_jax.train.fit import fit, take_rows

log = logging.getLogger(__name__)


class ForecastData(NamedTuple):
    """Host arrays of cached scenes as the forecaster reads them: rasters [S, G, G, C],
    actor positions and velocities [S, A, 2], which actors it sees [S, A] (`scene_actors`),
    and their displacements [S, A, H, 2] m (NaN where unknown)."""

    raster: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    seen: np.ndarray
    target: np.ndarray


def _check_futures(cache: Cache | CacheUnion) -> None:
    members = getattr(cache, "members", [cache])
    for member in members:
        if member.future is None:
            from scenegen_jax.data.cache import prepare_command

            raise ValueError(
                f"{member.path}/meta.json: field version: {member.meta.get('version')}: the "
                f"cache holds no future positions (cache version {FUTURE_VERSION} or later "
                f"does); rewrite it with `{prepare_command(member.path, member.meta)}`")


def forecast_data(cache: Cache | CacheUnion, grid: GridConfig, progress: bool = True,
                  desc: str = "draw scenes") -> ForecastData:
    """Every scene of `cache` drawn at rotation 0, with its actors' displacements.

    Raises ValueError naming the cache when it holds no futures (a version 5 cache)."""
    _check_futures(cache)
    maps = cache_maps(cache, grid, progress=progress, desc=desc)
    rasters = []
    for start in range(0, len(cache), DRAW_CHUNK):
        idx = np.arange(start, min(start + DRAW_CHUNK, len(cache)))
        rasters.append(np.asarray(draw_scene_rasters(maps[idx], take_rows(cache.actors, idx),
                                                     cache.ego(idx), grid)))
    seen = np.asarray(scene_actors(cache.actors, grid).valid)
    target = cache.future - cache.actors.position[:, :, None, :]
    return ForecastData(np.concatenate(rasters), cache.actors.position.astype(np.float32),
                        cache.actors.velocity.astype(np.float32), seen,
                        np.where(seen[..., None, None], target, np.nan).astype(np.float32))


def masked_huber(pred, target, seen):
    """Mean Huber loss (delta 1 m, in DISPLACEMENT_SCALE_M units) over the known targets."""
    known = seen[..., None, None] & jnp.isfinite(target)
    diff = jnp.where(known, pred - jnp.nan_to_num(target), 0.0) / DISPLACEMENT_SCALE_M
    loss = optax.huber_loss(diff, delta=1.0 / DISPLACEMENT_SCALE_M)
    return loss.sum() / jnp.maximum(known.sum(), 1)


# AdamW's decoupled weight decay: with the dropout and the quarter turns, what keeps the
# forecaster from learning the few thousand training scenes by heart.
WEIGHT_DECAY = 1e-4


def vector_channel_pairs(grid: GridConfig) -> list[tuple[int, int]]:
    """The (cos, sin) channel pairs of the forecaster's raster: directions that turn with it
    (the map's `VECTOR_CHANNELS` the grid draws, the actors' velocity and heading)."""
    names = [*grid.map_channels, *ACTOR_CHANNELS]
    pairs = [*VECTOR_CHANNELS, ("vel_cos", "vel_sin"), ("heading_cos", "heading_sin")]
    return [(names.index(c), names.index(s)) for c, s in pairs if c in names]


def _turn(v, k):
    """Vectors [..., 2] turned by k quarter turns (counterclockwise)."""
    c, s = jnp.array([1.0, 0.0, -1.0, 0.0])[k], jnp.array([0.0, 1.0, 0.0, -1.0])[k]
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def quarter_turns(batch: ForecastData, k, grid: GridConfig) -> ForecastData:
    """Each scene of a batch turned about the ego by k [B] quarter turns: exact on the
    raster (the grid is symmetric about the ego), its direction channels and every
    position, velocity and displacement turned alike."""

    def one(raster, position, velocity, target, k):
        raster = jax.lax.switch(k, [functools.partial(jnp.rot90, k=i, axes=(0, 1))
                                    for i in range(4)], raster)
        for c, s in vector_channel_pairs(grid):
            turned = _turn(jnp.stack([raster[..., c], raster[..., s]], -1), k)
            raster = raster.at[..., c].set(turned[..., 0]).at[..., s].set(turned[..., 1])
        return raster, _turn(position, k), _turn(velocity, k), _turn(target, k)

    raster, position, velocity, target = jax.vmap(one)(
        batch.raster, batch.position, batch.velocity, batch.target, k)
    return ForecastData(raster, position, velocity, batch.seen, target)


def forecaster_loss(params, batch: ForecastData, key, cfg: ForecasterConfig):
    """The training loss of a batch, each scene turned by a random number of quarter turns
    (the data hold a few thousand scenes: the forecaster learns the motion, not the maps'
    orientations)."""
    turns, dropout = jax.random.split(key)
    batch = quarter_turns(batch, jax.random.randint(turns, (len(batch.raster),), 0, 4),
                          cfg.grid)
    _, pred = apply_forecaster(params, cfg, batch.raster, batch.position, batch.velocity,
                               dropout)
    return masked_huber(pred, batch.target, batch.seen)


def forecast_errors(params, cfg: ForecasterConfig, data: ForecastData,
                    batch_size: int = 32) -> dict:
    """ADE (mean over the horizons) and FDE (at the last) in m of the forecaster and of
    constant velocity, over the actors whose every future position is known."""
    preds = []
    for start in range(0, len(data.raster), batch_size):
        part = take_rows(data, np.arange(start, min(start + batch_size, len(data.raster))))
        preds.append(np.asarray(
            forecast(params, cfg, part.raster, part.position, part.velocity)[1]))
    pred = np.concatenate(preds)
    full = data.seen & np.isfinite(data.target).all(axis=(-1, -2))
    out = {"actors": int(full.sum())}
    for name, p in (("model", pred), ("constant_velocity", constant_velocity(data.velocity))):
        err = np.linalg.norm(p[full] - data.target[full], axis=-1)  # [N, H]
        out[f"{name}_ade_m"] = float(err.mean()) if len(err) else float("nan")
        out[f"{name}_fde_m"] = float(err[:, -1].mean()) if len(err) else float("nan")
    return out


def train_forecaster(cfg: ForecasterConfig, train: ForecastData, workdir: str, steps: int,
                     batch_size: int = 32, lr: float = 1e-3, seed: int = 0,
                     save_every: int = 250, progress: bool = True):
    """Trains (or resumes, from the newest checkpoint in `workdir`) up to `steps`; returns the
    parameters (`fit.fit`)."""
    return fit(functools.partial(forecaster_loss, cfg=cfg), init_forecaster(cfg, seed), train,
               workdir, steps, batch_size, lr, seed, save_every, progress,
               desc="train forecaster", weight_decay=WEIGHT_DECAY)
