"""Per-actor log-likelihood (supplementary eq. 8) from the head outputs of one generation step.

log p(a_i | xi_i) = class + location + box size + heading + velocity. The same function
serves training (hard negative mining in the location normaliser) and evaluation (full
softmax), so the box, heading and velocity terms are identical in both.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from scenegen_jax.config import ModelConfig
from scenegen_jax.distributions import categorical, mixtures
from scenegen_jax.distributions import params as P
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, STOP, VEHICLE, Actors, bin_index

TERMS = ("class", "location", "box", "heading", "velocity")


@struct.dataclass
class HeadOutputs:
    """Head outputs of one generation step for one actor (unbatched; vmap outside).

    Attributes:
      class_logits: [4] logits over (vehicle, pedestrian, bicyclist, stop).
      location_logits: [H*W] location logits of the (true or sampled) class, row-major bins.
      box: [6K] raw box params of that class at the actor's bin (see `params`).
      heading: [4K] raw heading params.
      velocity: [velocity_params_size(K)] raw velocity params.
    """

    class_logits: jnp.ndarray
    location_logits: jnp.ndarray
    box: jnp.ndarray
    heading: jnp.ndarray
    velocity: jnp.ndarray

    @property
    def num_mixtures(self) -> int:
        """K, checked against all three attribute layouts."""
        k = P.num_mixtures(self.box)
        sizes = (self.heading.shape[-1], self.velocity.shape[-1])
        if sizes != (P.heading_params_size(k), P.velocity_params_size(k)):
            raise ValueError(
                f"head sizes disagree: box {self.box.shape[-1]} (K={k}) but heading/velocity "
                f"{sizes}, expected {(P.heading_params_size(k), P.velocity_params_size(k))}"
            )
        return k


def is_relative_direction(cls: jnp.ndarray) -> jnp.ndarray:
    """Velocity direction is relative to the heading for vehicles and bicyclists."""
    return (cls == VEHICLE) | (cls == BICYCLIST)


def term_masks(cls: jnp.ndarray, is_stop: jnp.ndarray,
               size_measured: jnp.ndarray | None = None) -> dict[str, jnp.ndarray]:
    """bool per term: which terms of `actor_log_likelihood` this target contributes (the box
    term only where the size was measured: `Actors.size_measured`, None for all)."""
    actor = jnp.logical_not(is_stop) & (cls != STOP)
    boxed = actor & (cls != PEDESTRIAN)
    measured = boxed if size_measured is None else boxed & size_measured
    return {
        "class": jnp.ones_like(actor),
        "location": actor,
        "box": measured,
        "heading": boxed,
        "velocity": actor,
    }


def actor_log_likelihood(
    head: HeadOutputs,
    target: Actors,
    is_stop: jnp.ndarray,
    cfg: ModelConfig,
    hard_negatives: int | None = None,
) -> dict[str, jnp.ndarray]:
    """Per-term log-likelihoods of one target actor (or the stop token).

    Masking: the stop token contributes the class term only; pedestrians get no box or
    heading term, actors whose size the source did not measure no box term. Masked terms
    are exactly 0 with zero (never NaN) gradients, whatever the target's unused fields hold.
    `valid` of the target is ignored (mask padding outside).

    Args:
      head: head outputs at this step; location and attribute params of the target class.
      target: unbatched Actors: cls in {0, 1, 2}, position (m, gives the bin), size (m),
        heading (rad), velocity (m/s).
      is_stop: the target is the stop token (class STOP); a cls of STOP also counts.
      cfg: config (grid, bin area, zero_speed).
      hard_negatives: None for the full location softmax (evaluation); an int n for the
        hard-negative normaliser over n bins (training).

    Returns:
      dict with scalar "class" (nats), "location" (log 1/m^2), "box" (log 1/m^2),
      "heading" (log 1/rad), "velocity" (log 1/(m/s)^2, or log prob of v = 0).
    """
    _ = head.num_mixtures  # validates the layout sizes at trace time
    masks = term_masks(target.cls, is_stop, target.size_measured)
    stop = jnp.logical_not(masks["location"])
    cls = jnp.where(stop, STOP, target.cls)
    out = {"class": categorical.class_log_prob(head.class_logits, cls)}

    bin_ = bin_index(target.position, cfg.grid)
    if hard_negatives is None:
        loc = categorical.location_log_prob(head.location_logits, bin_, cfg.grid.bin_area)
    else:
        loc = categorical.hard_negative_log_prob(head.location_logits, bin_, hard_negatives)
        loc = loc - jnp.log(cfg.grid.bin_area)
    out["location"] = loc

    # Unused target fields may be garbage (zeros for padding); feed safe values instead.
    size = jnp.where(masks["box"], target.size, jnp.ones_like(target.size))
    heading = jnp.where(masks["heading"], target.heading, 0.0)
    velocity = jnp.where(masks["velocity"], target.velocity, jnp.zeros_like(target.velocity))
    out["box"] = mixtures.box_log_prob(head.box, size)
    out["heading"] = mixtures.heading_log_prob(head.heading, heading)
    out["velocity"] = mixtures.velocity_log_prob(
        head.velocity, velocity, heading, is_relative_direction(target.cls), cfg.grid.zero_speed
    )
    return {name: jnp.where(masks[name], out[name], 0.0) for name in TERMS}
