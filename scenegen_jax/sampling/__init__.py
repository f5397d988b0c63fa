"""Sampling new scenes: a jitted autoregressive rollout with best-of-M proposals, ordering
masks and collision rejection, vmapped across scenes and keys.

Layers, bottom up: `model` (what the sampler needs from a network), `attributes` (box size,
best-of-M heading and velocity), `rollout` (one scene in one traced function; not
re-exported, so that `scenegen_jax.sampling.rollout` stays the module), `batch` (keys per
scene, batched and concurrent calls), `export` (records, frames and files of sampled scenes).
"""

from scenegen_jax.sampling.attributes import (
    MAX_SIZE_M,
    MAX_SPEED_MPS,
    MIN_SIZE_M,
    sample_attributes,
)
from scenegen_jax.sampling.batch import (
    batch_inputs,
    sample_batch,
    sample_scenes,
    sample_split,
    scene_key,
    scene_keys,
)
from scenegen_jax.sampling.export import (
    actor_records,
    actors_from_records,
    frame_from_sample,
    read_given,
)
from scenegen_jax.sampling.geometry import collides
from scenegen_jax.sampling.model import Model, NetworkModel
from scenegen_jax.sampling.rollout import (
    COLLISION,
    FULL,
    HEATMAP_STEPS,
    NO_BIN,
    STOP_REASONS,
    STOP_TOKEN,
    Sample,
    SamplerOptions,
    SamplerState,
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
    "SamplerOptions",
    "SamplerState",
    "actor_records",
    "actors_from_records",
    "batch_inputs",
    "collides",
    "frame_from_sample",
    "read_given",
    "sample_attributes",
    "sample_batch",
    "sample_scenes",
    "sample_split",
    "scene_key",
    "scene_keys",
]
