"""Box size, heading and velocity of sampled actors: one draw of the box, best-of-M proposals
of the heading and velocity, then clamped and made finite (`MIN_SIZE_M`, `MAX_SIZE_M`,
`MAX_SPEED_MPS`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from scenegen_jax.config import ModelConfig
from scenegen_jax.distributions import (
    best_of_m,
    heading_log_prob,
    is_relative_direction,
    sample_box,
    sample_heading,
    sample_velocity,
    velocity_proposal_score,
)
from scenegen_jax.raster.actors import DEFAULT_MAX_BOX_M
from scenegen_jax.scene import PEDESTRIAN, wrap_angle

# Sampled boxes are clamped to what the actor raster draws whole, speeds to 50 m/s (tighter
# than the limits data are read with, `frame.MAX_SIZE_M` and `frame.MAX_SPEED_MPS`).
MIN_SIZE_M = 0.2
MAX_SIZE_M = DEFAULT_MAX_BOX_M
MAX_SPEED_MPS = 50.0


def sample_attributes(
    keys: jax.Array,
    box_raw: jnp.ndarray,
    heading_raw: jnp.ndarray,
    velocity_raw: jnp.ndarray,
    cls: jnp.ndarray,
    cfg: ModelConfig,
    proposals: int,
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Box size of R actors, one draw each; heading and velocity, each the most likely of M.

    Best-of-M (paper sec. 3.3; supplementary 3.2 names the attributes: position, heading and
    velocity) keeps the most likely of M proposals under its own mixture (NaN never wins,
    ties keep the first). The box is drawn once, as the paper does: the most likely of M
    boxes is the mode of the largest component, which would make every vehicle car-sized and
    never sample the trucks and buses of the real scenes. The velocity is scored in its
    mixture's own coordinates, (log speed, direction) (`velocity_proposal_score`): the planar
    density carries the Jacobian 1 / s^2, which would make the slowest proposal win.
    Whether an actor stands is drawn once, by its first velocity proposal (probability
    pi_0, a probability that is not compared with densities); a moving actor keeps the best
    of its moving proposals. The velocity is drawn given the chosen heading (its direction
    is relative to it for vehicles and bicyclists).
    Heading and velocity are each one `distributions.best_of_m` call over the R actors. Keys:
    actor r splits keys[r] into 1 + 2M keys: the box's, then M heading and M velocity
    proposal keys. With M = 1 every attribute is one plain draw.

    Pedestrians get the nominal square box (`cfg.grid.pedestrian_size_m`) and the velocity
    direction as heading (0 when standing). Outputs are clamped and made finite (see the
    module docstring).

    Args:
      keys: [R] PRNG keys.
      box_raw, heading_raw, velocity_raw: [R, ...] raw head outputs of each actor's class.
      cls: int32 [R] classes (vehicle, pedestrian or bicyclist).
      cfg: config (zero_speed, pedestrian_size_m).
      proposals: M >= 1 (static).

    Returns:
      (size [R, 2] (width, length) m, heading [R] rad in [0, 2pi), velocity [R, 2] m/s).
    """
    zero = cfg.grid.zero_speed
    m = proposals
    sub = jax.vmap(lambda k: jax.random.split(k, 1 + 2 * m))(keys)  # box, M heading, M velocity
    size = jax.vmap(sample_box)(sub[:, 0], box_raw)
    heading = best_of_m(sub[:, 1 : 1 + m], sample_heading, heading_log_prob, heading_raw, m)
    heading = jnp.nan_to_num(heading, nan=0.0, posinf=0.0, neginf=0.0)

    def standing_first(vels, score):  # the first proposal decides standing or moving
        moving = (jnp.sum(vels * vels, axis=-1) > zero * zero).reshape(score.shape)
        first = jnp.arange(score.shape[1]) == 0
        return jnp.where(moving[:, :1], jnp.where(moving, score, -jnp.inf),
                         jnp.where(first, 0.0, -jnp.inf))

    velocity = best_of_m(
        sub[:, 1 + m :],
        lambda k, p: sample_velocity(k, p[0], p[1], p[2], zero),
        lambda p, v: velocity_proposal_score(p[0], v, p[1], p[2], zero),
        (velocity_raw, heading, is_relative_direction(cls)),
        m,
        adjust=standing_first,
    )
    velocity = jnp.nan_to_num(velocity, nan=0.0, posinf=0.0, neginf=0.0)

    speed = jnp.sqrt(jnp.sum(velocity**2, axis=-1))
    velocity = velocity * jnp.minimum(1.0, MAX_SPEED_MPS / jnp.maximum(speed, 1e-12))[:, None]
    size = jnp.clip(jnp.nan_to_num(size, nan=MIN_SIZE_M), MIN_SIZE_M, MAX_SIZE_M)
    is_ped = cls == PEDESTRIAN
    moving = speed > zero
    walk = jnp.arctan2(velocity[:, 1], jnp.where(moving, velocity[:, 0], 1.0))
    size = jnp.where(is_ped[:, None], jnp.asarray(cfg.grid.pedestrian_size_m, size.dtype), size)
    heading = wrap_angle(jnp.where(is_ped, jnp.where(moving, walk, 0.0), heading))
    return size.astype(jnp.float32), heading.astype(jnp.float32), velocity.astype(jnp.float32)
