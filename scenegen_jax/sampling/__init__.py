"""Sampling new scenes: a jitted autoregressive rollout with best-of-M proposals, ordering
masks and collision rejection, vmapped across scenes and keys.

Layers, bottom up: `model` (what the sampler needs from a network), `attributes` (box size,
best-of-M heading and velocity), `placement` (candidate actors and collision rejection),
`rollout` (one scene in one traced function; not
re-exported, so that `scenegen_jax.sampling.rollout` stays the module), `batch` (keys per
scene, batched and concurrent calls), `export` (JSON records of sampled and given actors,
and Frames for the ScenarioNet exporter).
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
    given_from_lines,
)
from scenegen_jax.sampling.geometry import collides
from scenegen_jax.sampling.model import Model, NetworkModel
from scenegen_jax.sampling.rollout import (
    HEATMAP_STEPS,
    STOP_REASONS,
    Sample,
    SamplerOptions,
    SamplerState,
    StopReason,
)

__all__ = [
    "HEATMAP_STEPS",
    "MAX_SIZE_M",
    "MAX_SPEED_MPS",
    "MIN_SIZE_M",
    "STOP_REASONS",
    "Model",
    "NetworkModel",
    "Sample",
    "SamplerOptions",
    "SamplerState",
    "StopReason",
    "actor_records",
    "actors_from_records",
    "batch_inputs",
    "collides",
    "frame_from_sample",
    "given_from_lines",
    "sample_attributes",
    "sample_batch",
    "sample_scenes",
    "sample_split",
    "scene_key",
    "scene_keys",
]
