"""Gradients of the teacher-forced unroll (`unroll`) window by window, as the train step takes
them.

No gradient crosses a window boundary (truncated BPTT), so each window's backward pass runs
right after its forward pass (`window_grads`), and the train step holds one window's
activations (`unroll_terms_and_grads`). The map share of layer 1's input gates is computed
once per scene; its gradient is summed over the windows and taken through the map
convolution once. `train.programs.SplitTrainStep` runs the prologue and epilogue as programs of
their own, and each window as chunks (`chunk_forward`, `chunk_backward`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from scenegen_jax import backend
from scenegen_jax.config import ModelConfig
from scenegen_jax.likelihood.unroll import (
    Scenes,
    join_windows,
    num_windows,
    prepare_scenes,
    scan_windows,
    window_terms,
)
from scenegen_jax.model.network import SceneGenNet
from scenegen_jax.scene import Scene


def map_gates_and_vjp(params, cfg: ModelConfig, maps):
    """The map share of layer 1's input gates [B, H, W, 4h] (computed once per scene) and its
    vjp with respect to the parameters."""
    net = SceneGenNet(cfg)
    return jax.vjp(lambda p: net.apply({"params": p}, maps, method=SceneGenNet.map_gates),
                   params)


def grads_prologue(params, cfg: ModelConfig, maps, scene: Scene, map_gates):
    """What every window of `unroll_terms_and_grads` reads, and the first window's
    accumulator: (scenes, ((zero ConvLSTM state, ego-only raster), zero parameter gradients,
    zero map-gate gradient))."""
    scenes = prepare_scenes(params, cfg, maps, scene)
    acc = ((scenes.state0, scenes.raster0), jax.tree.map(jnp.zeros_like, params),
           jnp.zeros_like(map_gates))
    return scenes, acc


def window_grads(params, map_gates, scenes: Scenes, cfg: ModelConfig, scale,
                 hard_negatives: int, remat: bool | str, acc, index):
    """One window of `unroll_terms_and_grads`: (accumulator with this window's carry and
    gradients added, the window's terms). `index` is the window's number, static (a scene's
    first window then skips the zero state's recurrent convolutions) or traced."""
    carry, g_params, g_map = acc

    def loss(p, gates):
        out, terms = window_terms(p, gates, carry, index * cfg.bptt_window, scenes, cfg,
                                  hard_negatives, remat=remat)
        return -scale * sum(jnp.sum(v) for v in terms.values()), (out, terms)

    (_, (carry, terms)), (gp, gm) = jax.value_and_grad(loss, (0, 1), has_aux=True)(
        params, map_gates
    )
    # The next window starts once this one's backward is done (a zero taken from its
    # gradient: XLA does not fold 0 * x for floats), so unrolled windows (CPU) also hold
    # one window's activations at a time. A NaN gradient would make the later windows
    # NaN as well: that step is lost either way.
    zero = 0.0 * gm.ravel()[0]
    carry = jax.tree.map(lambda x: x + zero.astype(x.dtype), carry)
    return (carry, jax.tree.map(jnp.add, g_params, gp), g_map + gm), terms


def chunk_steps(cfg: ModelConfig) -> int:
    """Steps of a window that one call of `chunk_forward` runs when a train step goes chunk by
    chunk (`train.programs.SplitTrainStep`): the largest divisor of `cfg.bptt_window` up to
    `backend.SPLIT_CHUNK_STEPS`."""
    return max(d for d in range(1, backend.SPLIT_CHUNK_STEPS + 1) if cfg.bptt_window % d == 0)


def chunk_forward(params, map_gates, scenes: Scenes, cfg: ModelConfig, scale,
                  hard_negatives: int, remat: bool | str, carry, start):
    """The `chunk_steps(cfg)` steps of a window from step `start` (traced) given the carried
    (ConvLSTM state, actor raster): (carry after them, their terms name -> [B, steps], vjp).
    `vjp(g_carry)` -> (parameter gradient, map-gate gradient, carry cotangent) of
    -scale * (sum of the chunk's terms) plus <g_carry, carry after>: chained from a window's
    last chunk (g_carry zero: no gradient across windows) to its first, the chunks' gradients
    add up to `window_grads`'s (tested). vjp is a `jax.tree_util.Partial` holding the chunk's
    activations, so it leaves one compiled program and enters another (`chunk_backward`)."""
    sub = cfg.replace(bptt_window=chunk_steps(cfg))

    def loss(p, gates, c):
        out, terms = window_terms(p, gates, c, start, scenes, sub, hard_negatives, remat=remat)
        return (out, -scale * sum(jnp.sum(v) for v in terms.values())), terms

    (carry, _), vjp, terms = jax.vjp(loss, params, map_gates, carry, has_aux=True)
    return carry, terms, vjp


def chunk_backward(vjp, g_carry, g_params, g_map):
    """A chunk's backward pass (`chunk_forward`'s vjp): (g_params and g_map with the chunk's
    gradients added, the cotangent of the carry the chunk started from)."""
    gp, gm, g_carry = vjp((g_carry, jnp.ones((), jnp.float32)))
    return jax.tree.map(jnp.add, g_params, gp), g_map + gm, g_carry


def grads_epilogue(map_vjp, scenes: Scenes, acc, terms: dict):
    """(unrolled terms as `unroll_terms`, parameter gradient) from the last window's
    accumulator and every window's terms (name -> [windows, B, W]; or every chunk's, name ->
    [chunks, B, steps], in step order): the map-gate gradient, summed over the windows, taken
    through the map convolution (`map_vjp`) once."""
    _, g_params, g_map = acc
    (g_from_map,) = map_vjp(g_map)
    return join_windows(terms, scenes), jax.tree.map(jnp.add, g_params, g_from_map)


def unroll_terms_and_grads(params, cfg: ModelConfig, maps, scene: Scene, scale,
                           hard_negatives: int, remat: bool | str = False):
    """`unroll_terms` with the training normaliser, and the gradient of
    -scale * (sum of all terms) with respect to params, computed window by window.

    No gradient crosses a window boundary (truncated BPTT), so each window's backward pass
    runs right after its forward pass (`window_grads`), in a `lax.scan` over the windows: on
    an accelerator the train step holds one window's activations and compiles one window,
    whatever `cfg.grid.max_actors` (the `paper` preset has 6 windows; on CPU the windows are
    unrolled, `scan_windows`). The map share of layer 1's input gates is still computed
    once per scene; its gradient is summed over the windows and taken through the map
    convolution once. Equal to `jax.grad` of that sum through `unroll_terms` (tested).
    `train.programs.SplitTrainStep` runs `grads_prologue` and `grads_epilogue` as programs of
    their own, and each window as chunks (`chunk_forward`, `chunk_backward`).
    """
    map_gates, map_vjp = map_gates_and_vjp(params, cfg, maps)
    scenes, acc = grads_prologue(params, cfg, maps, scene, map_gates)
    body = functools.partial(window_grads, params, map_gates, scenes, cfg, scale,
                             hard_negatives, remat)
    acc, terms = scan_windows(body, acc, num_windows(cfg))
    return grads_epilogue(map_vjp, scenes, acc, terms)
