"""The motion-forecasting model whose features measure scenes (paper supplementary 2.2).

A small CNN reads a scene's bird's-eye raster, its map channels and the 9 actor channels of
SceneGen's input (`raster.actors`). Each actor's displacement `frame.FUTURE_HORIZONS_S` ahead
(3 s at 0.5 s steps) is its constant-velocity extrapolation plus a correction regressed from
the backbone's features at the actor's pixel, at three scales, and its velocity: a stopped
or turning actor is what the map and the other actors explain. A scene's feature is the
backbone's last stage averaged over space: the "Features" MMD of Table 1 compares those
between real and generated scenes.

All arrays are NHWC.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from scenegen_jax.config import GridConfig
from scenegen_jax.frame import FUTURE_HORIZONS_S
from scenegen_jax.raster.actors import NUM_ACTOR_CHANNELS, rasterize_actors
from scenegen_jax.scene import Actors, in_region, pixel_of

# Displacements are regressed in units of this many metres (the 3 s displacement of a car
# at 30 km/h), so the targets are of order one.
DISPLACEMENT_SCALE_M = 25.0


@dataclasses.dataclass(frozen=True)
class ForecasterConfig:
    """The forecaster's architecture; the grid is the SceneGen config's it measures.

    widths: channels of the backbone's three stages (full, half and quarter resolution);
      the scene feature has widths[-1] dimensions.
    hidden: width of the per-actor head's two hidden layers.
    groups: GroupNorm groups of every backbone layer.
    dropout: the head's dropout rate in training.
    """

    grid: GridConfig
    widths: tuple[int, int, int] = (32, 64, 64)
    hidden: int = 128
    groups: int = 8
    dropout: float = 0.3

    def __post_init__(self):
        if len(self.widths) != 3 or any(w < 1 or w % self.groups for w in self.widths):
            raise ValueError(f"widths must be 3 positive multiples of groups={self.groups}, "
                             f"got {self.widths}")

    @property
    def in_channels(self) -> int:
        return len(self.grid.map_channels) + NUM_ACTOR_CHANNELS

    @property
    def feature_size(self) -> int:
        return self.widths[-1]

    def to_dict(self) -> dict:
        return {"widths": list(self.widths), "hidden": self.hidden, "groups": self.groups,
                "dropout": self.dropout}

    @classmethod
    def from_dict(cls, d: dict, grid: GridConfig) -> ForecasterConfig:
        return cls(grid=grid, widths=tuple(d["widths"]), hidden=int(d["hidden"]),
                   groups=int(d["groups"]), dropout=float(d["dropout"]))


class Forecaster(nn.Module):
    cfg: ForecasterConfig

    def _block(self, x, width: int, stride: int):
        x = nn.Conv(width, (3, 3), strides=(stride, stride), padding="SAME")(x)
        return nn.relu(nn.GroupNorm(num_groups=self.cfg.groups)(x))

    @nn.compact
    def __call__(self, raster, rows, cols, velocity, train: bool = False):
        """Scene features [B, D] and displacements [B, A, H, 2] m of the actors at pixels
        (rows, cols) [B, A] of rasters [B, G, G, C], moving at velocity [B, A, 2] m/s; with
        `train`, the head's dropout is on (its "dropout" rng)."""
        w = self.cfg.widths
        full = self._block(self._block(raster, w[0], 1), w[0], 1)
        half = self._block(self._block(full, w[1], 2), w[1], 1)
        quarter = self._block(self._block(half, w[2], 2), w[2], 1)
        features = quarter.mean(axis=(1, 2))
        g = self.cfg.grid.grid_size
        r, c = jnp.clip(rows, 0, g - 1), jnp.clip(cols, 0, g - 1)
        take = jax.vmap(lambda fmap, i, j: fmap[i, j])
        x = jnp.concatenate([take(full, r, c), take(half, r // 2, c // 2),
                             take(quarter, r // 4, c // 4), velocity / 10.0], axis=-1)
        drop = nn.Dropout(self.cfg.dropout, deterministic=not train)
        x = drop(nn.relu(nn.Dense(self.cfg.hidden)(drop(x))))
        x = drop(nn.relu(nn.Dense(self.cfg.hidden)(x)))
        out = nn.Dense(2 * len(FUTURE_HORIZONS_S), kernel_init=nn.initializers.zeros)(x)
        correction = out.reshape(*out.shape[:-1], len(FUTURE_HORIZONS_S), 2)
        return features, constant_velocity(velocity) + correction * DISPLACEMENT_SCALE_M


def init_forecaster(cfg: ForecasterConfig, seed: int = 0):
    g = cfg.grid.grid_size
    raster = jnp.zeros((1, g, g, cfg.in_channels), jnp.float32)
    idx = jnp.zeros((1, 1), jnp.int32)
    velocity = jnp.zeros((1, 1, 2), jnp.float32)
    return Forecaster(cfg).init(jax.random.PRNGKey(seed), raster, idx, idx, velocity)["params"]


def scene_actors(actors: Actors, grid: GridConfig) -> Actors:
    """The actors as the forecaster sees them: the valid ones inside the grid's region."""
    return actors.replace(valid=actors.valid & in_region(actors.position, grid))


def scene_raster(maps, actors: Actors, ego: Actors, grid: GridConfig):
    """The forecaster's input [B, G, G, C] of map rasters [B, G, G, Cm], actors [B, A] (those
    `scene_actors` keeps are drawn) and egos [B]."""
    actors = scene_actors(actors, grid)
    draw = jax.vmap(lambda a, e: rasterize_actors(a, e, grid, a.num_slots))
    return jnp.concatenate([maps, draw(actors, ego)], axis=-1)


def apply_forecaster(params, cfg: ForecasterConfig, raster, positions, velocities,
                     dropout_key=None):
    """(scene features [B, D], displacements [B, A, H, 2] m) of actors at positions
    [B, A, 2] m moving at velocities [B, A, 2] m/s; in training (`dropout_key` given) with
    the head's dropout."""
    rows, cols = pixel_of(positions, cfg.grid)
    if dropout_key is None:
        return Forecaster(cfg).apply({"params": params}, raster, rows, cols, velocities)
    return Forecaster(cfg).apply({"params": params}, raster, rows, cols, velocities, True,
                                 rngs={"dropout": dropout_key})


# Jitted forms for the drivers (training, evaluation), each compiled once per config.
draw_scene_rasters = jax.jit(scene_raster, static_argnames="grid")
forecast = jax.jit(apply_forecaster, static_argnames="cfg")


def constant_velocity(velocity):
    """The constant-velocity forecast [..., H, 2] m of velocities [..., 2] m/s: velocity * t."""
    t = np.asarray(FUTURE_HORIZONS_S, np.float32)
    return velocity[..., None, :] * t[:, None]
