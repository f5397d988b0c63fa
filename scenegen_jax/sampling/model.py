"""What the sampler needs from a network (`Model`), and its implementation by `SceneGenNet`
(`NetworkModel`)."""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import jax.numpy as jnp

from scenegen_jax.config import ModelConfig
from scenegen_jax.model.network import SceneGenNet


class Model(Protocol):
    """What the sampler needs from a network; every method takes the params first.

    The rollout is unbatched: arrays carry a leading axis of 1, except `attributes`, whose
    features [R, h], classes [R] and map channels [R, Cm] are the R candidates of one step.
    The recurrent state is an opaque PyTree. `NetworkModel` (below) wraps `SceneGenNet`;
    tests substitute a fake with known outputs.
    """

    def initial_state(self, params: Any) -> Any: ...
    def map_gates(self, params: Any, map_raster: jnp.ndarray) -> jnp.ndarray: ...
    def actor_gates(self, params: Any, actor_raster: jnp.ndarray) -> jnp.ndarray: ...
    def next_actor_gates(self, params: Any, gates: jnp.ndarray, before: jnp.ndarray,
                         after: jnp.ndarray, position: jnp.ndarray) -> jnp.ndarray: ...
    def order_gates(self, params: Any, prev_bin: jnp.ndarray) -> jnp.ndarray:
        """The canonical order's share of the input gates, given the previous actor's bin."""
    def recur(self, params: Any, state: Any, gates: jnp.ndarray) -> tuple[Any, jnp.ndarray]:
        """One recurrent step from `state` (`initial_state` at a scene's first step)."""
    def features(self, params: Any, h: jnp.ndarray) -> jnp.ndarray: ...
    def class_logits(self, params: Any, f: jnp.ndarray) -> jnp.ndarray: ...
    def location_logits(self, params: Any, f: jnp.ndarray, cls: jnp.ndarray) -> jnp.ndarray: ...
    def attributes(self, params: Any, feat: jnp.ndarray, cls: jnp.ndarray,
                   map_feat: jnp.ndarray) -> tuple:
        """Raw attribute parameters from features and map channels at the bins."""


@dataclasses.dataclass(frozen=True)
class NetworkModel:
    """`Model` backed by `SceneGenNet` (hashable: usable as a static jit argument).

    single_example: the location head as plain convolutions with the class's kernels
    (XLA:CPU's fastest for one scene; under vmap they become a grouped convolution, slow on
    CPU) instead of `conv_per_example`; the same values either way.
    """

    cfg: ModelConfig
    single_example: bool = True

    def _apply(self, params, method, *args):
        return SceneGenNet(self.cfg).apply({"params": params}, *args, method=method)

    def initial_state(self, params):
        return self._apply(params, SceneGenNet.initial_state, 1)

    def map_gates(self, params, map_raster):
        return self._apply(params, SceneGenNet.map_gates, map_raster)

    def actor_gates(self, params, actor_raster):
        return self._apply(params, SceneGenNet.actor_gates, actor_raster)

    def next_actor_gates(self, params, gates, before, after, position):
        return self._apply(params, SceneGenNet.next_actor_gates, gates, before, after, position)

    def order_gates(self, params, prev_bin):
        return self._apply(params, SceneGenNet.order_gates, prev_bin)

    def recur(self, params, state, gates):
        return self._apply(params, SceneGenNet.recur, state, gates)

    def features(self, params, h):
        return self._apply(params, SceneGenNet.features, h)

    def class_logits(self, params, f):
        return self._apply(params, SceneGenNet.class_logits, f)

    def location_logits(self, params, f, cls):
        return self._apply(params, SceneGenNet.location_logits, f, cls, self.single_example)

    def attributes(self, params, feat, cls, map_feat):
        return self._apply(params, SceneGenNet.attributes, feat, cls, map_feat)
