"""Sampling new scenes: a jitted autoregressive rollout with best-of-M proposals, ordering
masks and collision rejection, vmapped across scenes and keys.

The per-scene function is `scenegen_jax.sampling.rollout.rollout` (not re-exported here, so
that `scenegen_jax.sampling.rollout` stays the module); batches go through `sample_scenes` /
`sample_split` / `sample_batch`.
"""

from scenegen_jax.sampling.export import actor_records, actors_from_records, frame_from_sample
from scenegen_jax.sampling.geometry import box_axes, boxes_overlap, collides
from scenegen_jax.sampling.rollout import (
    COLLISION,
    FULL,
    HEATMAP_STEPS,
    MAX_SIZE_M,
    MAX_SPEED_MPS,
    MIN_SIZE_M,
    NO_BIN,
    STOP_REASONS,
    STOP_TOKEN,
    Model,
    NetworkModel,
    Sample,
    SamplerState,
    batch_inputs,
    sample_attributes,
    sample_batch,
    sample_scenes,
    sample_split,
    scene_keys,
)

__all__ = [
    "COLLISION",
    "FULL",
    "HEATMAP_STEPS",
    "MAX_SIZE_M",
    "MAX_SPEED_MPS",
    "MIN_SIZE_M",
    "NO_BIN",
    "STOP_REASONS",
    "STOP_TOKEN",
    "Model",
    "NetworkModel",
    "Sample",
    "SamplerState",
    "actor_records",
    "actors_from_records",
    "batch_inputs",
    "box_axes",
    "boxes_overlap",
    "collides",
    "frame_from_sample",
    "sample_attributes",
    "sample_batch",
    "sample_scenes",
    "sample_split",
    "scene_keys",
]
