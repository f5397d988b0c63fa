"""Pure, per-example log-likelihoods and samplers of SceneGen's actor attributes.

Units: positions and sizes in m, angles in rad, velocities in m/s; log-likelihoods in nats
(densities per m^2, rad or (m/s)^2 as documented per function). Samplers take the key first.
Raw head-output layouts are documented in `scenegen_jax.distributions.params`.
"""

from scenegen_jax.distributions.actor import (
    TERMS,
    HeadOutputs,
    actor_log_likelihood,
    is_relative_direction,
    term_masks,
)
from scenegen_jax.distributions.best_of_m import best_of_m
from scenegen_jax.distributions.categorical import (
    class_log_prob,
    hard_negative_log_prob,
    location_log_prob,
    masked_location_log_prob,
    masked_log_softmax,
    offsets_in_bin,
    ordering_mask,
    sample_bins,
    sample_class,
    sample_location,
    uniforms,
)
from scenegen_jax.distributions.mixtures import (
    box_log_prob,
    heading_log_prob,
    log_i0,
    sample_box,
    sample_heading,
    sample_velocity,
    velocity_log_prob,
    velocity_proposal_score,
    vonmises_log_prob,
)
from scenegen_jax.distributions.params import (
    BoxParams,
    VelocityParams,
    VonMisesParams,
    box_params_size,
    heading_params_size,
    num_mixtures,
    split_box,
    split_heading,
    split_velocity,
    velocity_params_size,
)

__all__ = [
    "TERMS",
    "BoxParams",
    "HeadOutputs",
    "VelocityParams",
    "VonMisesParams",
    "actor_log_likelihood",
    "best_of_m",
    "box_log_prob",
    "box_params_size",
    "class_log_prob",
    "hard_negative_log_prob",
    "heading_log_prob",
    "heading_params_size",
    "is_relative_direction",
    "location_log_prob",
    "log_i0",
    "masked_location_log_prob",
    "masked_log_softmax",
    "num_mixtures",
    "offsets_in_bin",
    "ordering_mask",
    "sample_bins",
    "sample_box",
    "sample_class",
    "sample_heading",
    "sample_location",
    "sample_velocity",
    "split_box",
    "split_heading",
    "split_velocity",
    "term_masks",
    "uniforms",
    "velocity_log_prob",
    "velocity_proposal_score",
    "velocity_params_size",
    "vonmises_log_prob",
]
