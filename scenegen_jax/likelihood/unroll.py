"""Teacher-forced unroll of the autoregressive factorisation: per-step log-likelihoods.

Step t of a scene with n actors predicts actor t (t < n) or the stop token (t = n); steps
t > n are padding. Steps run in windows of `cfg.bptt_window`: the ConvLSTM state is carried
from window to window with its gradient cut (truncated backprop through time).

On XLA:CPU the steps of a window that is differentiated (the train step) are unrolled at
trace time (Python loops): it runs convolution gradients inside while loops and conditionals
10-20x slower than at the top level (jax-ml/jax#12868). The scorer's steps there, and every
window's on accelerators, run as a `lax.scan` (`backend.compiled_step_loop`): a few steps are
compiled instead of a window's worth. Windows run through `scan_windows`: a Python loop on
CPU, a `lax.scan` (one window compiled) on accelerators. The train step takes each window's
gradient right after that window (`likelihood.grads`), so it holds one window's activations.
An unroll without a gradient (the scorer) has nothing to truncate: its steps run as one
window, so that one compiled loop serves the whole scene (it compiles faster than a loop
over windows). Every window always runs, so `cfg.grid.max_actors` should fit the data
(overflow is counted).

Inside a window (the fast path; `_unrolled_steps` in the CPU train step, elsewhere
`_scanned_steps`, the same mathematics as a loop over the steps):
  * the map share of layer 1's input convolution is computed once per scene (`map_gates`),
    so its weight gradient is one convolution over the gradients summed over steps;
  * per step: the actor share of layer 1's input gates, updated by a convolution over the
    new actor's drawing window only (`SceneGenNet.next_actor_gates`), the canonical order's
    share with `order_channel` (`SceneGenNet.order_gates`), and the recurrence;
  * the backbone and the conv heads run on chunks of consecutive steps whose activations fit
    in cache (`head_chunk`; one step at the paper's width and grid): batching a whole window
    makes XLA:CPU's convolutions several times slower once the batch leaves the cache;
  * the location head runs only for the class scored at each step;
  * where the first window's start is static (windows in a Python loop: XLA:CPU, or a
    single window), a scene's first step skips the recurrent convolutions of the zero
    initial state;
  * the densities (small) run once, batched over all steps of the window;
  * with `remat` (`TrainConfig.remat`: true; "auto" is made true or false by
    `train.step.resolve_remat`
    before a train step is built, and counts as true unresolved), a chunk's backbone and
    heads are recomputed in the backward pass instead of stored (`recompute_in_backward`),
    each one chunk late so that the recomputation overlaps the next chunk's recurrence: the
    step's temporaries drop to less than half for a few per cent more time
    (docs/performance.md, Remat).
`tests/reference_unroll.py` holds the plain per-step version it is tested against.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from scenegen_jax import backend
from scenegen_jax.config import ModelConfig
from scenegen_jax.distributions import HeadOutputs, actor_log_likelihood
from scenegen_jax.model.network import SceneGenNet, map_at_bins
from scenegen_jax.raster.actors import draw_actor, empty_actor_raster
from scenegen_jax.scene import STOP, Actors, Scene, bin_index


def num_windows(cfg: ModelConfig) -> int:
    """Windows covering the max_actors + 1 steps (the last one the stop token)."""
    return math.ceil((cfg.grid.max_actors + 1) / cfg.bptt_window)


def _pad_slots(actors: Actors, n: int) -> Actors:
    """Pads the slot axis (axis 1 of batched actors) with invalid slots to length n."""
    pad = n - actors.cls.shape[1]
    return jax.tree.map(lambda x: jnp.pad(x, [(0, 0), (0, pad)] + [(0, 0)] * (x.ndim - 2)), actors)


def _stop_and_valid(n_actors, complete, t):
    """(is_stop, step valid) [B, len(t)] of steps t of scenes with n_actors [B] actors: the
    actors' steps, then the stop token's step where the scene is `complete` [B] (a truncated
    scene's next actor is not the end: `Scene.complete`)."""
    is_stop = (t[None, :] == n_actors[:, None]) & complete[:, None]
    return is_stop, (t[None, :] < n_actors[:, None]) | is_stop


def _step_targets(actors: Actors, n_actors, complete, t):
    """Targets of steps t [W] for batched actors [B, W]: (target actors, is_stop, step valid)."""
    is_stop, valid = _stop_and_valid(n_actors, complete, t)
    cls = jnp.where(is_stop, STOP, actors.cls)
    return actors.replace(cls=cls), is_stop, valid


# Bytes of backbone activations per chunk of steps: XLA:CPU's convolutions slow down several
# times (weight gradients most) once a batch no longer fits in cache.
HEAD_CHUNK_BYTES = 2 * 2**20


def head_chunk(cfg: ModelConfig, batch: int) -> int:
    """Steps whose backbone and heads run as one batch (1 at the paper's grid)."""
    per_step = batch * cfg.grid.grid_size * cfg.grid.grid_size * cfg.hidden * 4
    return max(1, min(cfg.bptt_window, HEAD_CHUNK_BYTES // per_step))


def recompute_in_backward(fn):
    """fn(params, x, *static) with its activations recomputed in the backward pass.

    Returns g(params, x, *static, state) -> (fn(params, x, *static), state): `state` (a
    later ConvLSTM state) passes through unchanged, so its cotangent, which only exists
    once the later chunks' backward has run, can order the recomputation: the
    backward recomputes fn from x plus a zero taken from that cotangent. Without that data
    dependency (plain `jax.checkpoint`), XLA:CPU schedules every chunk's recomputation at
    once and keeps them all alive, which saves nothing. Same values and gradients as fn;
    `static` are integer arrays (no gradient).
    """

    @jax.custom_vjp
    def g(params, x, *rest):
        *static, state = rest
        return fn(params, x, *static), state

    def forward(params, x, *rest):
        return g(params, x, *rest), (params, x, rest[:-1])

    def backward(res, cotangent):
        params, x, static = res
        ct_out, ct_state = cotangent
        # XLA does not fold 0 * x for floats (x may be NaN), so the dependency stays.
        zero = 0.0 * jax.tree.leaves(ct_state)[0].ravel()[0]
        _, vjp = jax.vjp(lambda p, y: fn(p, y, *static), params, x + zero)
        return (*vjp(ct_out), *(None for _ in static), ct_state)

    g.defvjp(forward, backward)
    return g


def _bound(net: SceneGenNet, params):
    """net's methods with params bound: apply(method, *args)."""

    def apply(method, *args):
        return net.apply({"params": params}, *args, method=method)

    return apply


def step_heads(net: SceneGenNet, params, f, cls, bins):
    """The convolutional heads of one step: features f [M, H, W, h] -> (class logits [M, 4],
    location logits of class cls [M, H*W], features at the target bins [M, h])."""
    apply = _bound(net, params)
    feat = f.reshape(f.shape[0], -1, f.shape[-1])[jnp.arange(f.shape[0]), bins]
    location = apply(SceneGenNet.location_logits, f, cls, f.shape[0] == 1)
    return apply(SceneGenNet.class_logits, f), location, feat


def head_terms(
    net: SceneGenNet,
    params,
    heads,
    targets: Actors,
    is_stop,
    cfg: ModelConfig,
    hard_negatives,
    map_feat,
):
    """Per-term log-likelihoods of targets [M] from `step_heads` outputs (any leading M) and
    the map channels at the targets' bins, map_feat [M, Cm] (`attribute_map_input`)."""
    class_logits, location_logits, feat = heads
    box, heading, velocity = net.apply(
        {"params": params}, feat, targets.cls, map_feat, method=SceneGenNet.attributes
    )
    head = HeadOutputs(
        class_logits=class_logits,
        location_logits=location_logits,
        box=box,
        heading=heading,
        velocity=velocity,
    )
    ll = functools.partial(actor_log_likelihood, cfg=cfg, hard_negatives=hard_negatives)
    return jax.vmap(ll)(head, targets, is_stop)


def scan_windows(body, init, windows: int):
    """`lax.scan(body, init, jnp.arange(windows))`: a compiled loop on accelerators (one window
    compiled, whatever the count); on XLA:CPU, which runs convolutions inside loops many times
    slower (above; a train step at grid 128 went from 3.6 s to minutes as a one-iteration
    loop), and for a single window, a Python loop over the same body."""
    if backend.compiled_window_loop() and windows > 1:
        return jax.lax.scan(body, init, jnp.arange(windows))
    carry, outs = init, []
    for index in range(windows):
        carry, out = body(carry, index)
        outs.append(out)
    return carry, jax.tree.map(lambda *x: jnp.stack(x), *outs)


class Scenes(NamedTuple):
    """What every window of a batch of scenes reads: actors padded to whole windows [B, T],
    actor counts [B], whether each scene is complete [B] (`Scene.complete`), each step's
    previous actor's bin [B, T] (0 at the first step; the `order_channel` input), the map
    channels at each actor's bin [B, T, Cm] (the `attribute_map_input`), the ego-only raster
    [B, H, W, 9] and the zero ConvLSTM state."""

    actors: Actors
    n_actors: jnp.ndarray
    complete: jnp.ndarray
    prev_bins: jnp.ndarray
    map_feat: jnp.ndarray
    raster0: jnp.ndarray
    state0: Any


def prepare_scenes(params, cfg: ModelConfig, maps, scene: Scene) -> Scenes:
    net = SceneGenNet(cfg)
    b = scene.ego.cls.shape[0]
    raster0 = _draw(cfg)(
        jnp.broadcast_to(empty_actor_raster(cfg.grid), (b, *empty_actor_raster(cfg.grid).shape)),
        scene.ego,
        jnp.ones((b,), bool),
    )
    actors = _pad_slots(scene.actors, num_windows(cfg) * cfg.bptt_window)
    bins = bin_index(actors.position, cfg.grid)
    return Scenes(
        actors=actors,
        n_actors=jnp.sum(scene.actors.valid, axis=1),
        complete=jnp.broadcast_to(jnp.asarray(scene.complete, bool), (b,)),
        prev_bins=jnp.concatenate([jnp.zeros_like(bins[:, :1]), bins[:, :-1]], axis=1),
        map_feat=map_at_bins(maps, bins),
        raster0=raster0,
        state0=net.apply({"params": params}, b, method=SceneGenNet.initial_state),
    )


def window_terms(
    params,
    map_gates,
    carry,
    start,
    scenes: Scenes,
    cfg: ModelConfig,
    hard_negatives: int | None,
    differentiated: bool = True,
    remat: bool | str = False,
):
    """One window: the `cfg.bptt_window` steps from step `start` (may be traced), given the
    carried (ConvLSTM state, actor raster); returns (carry, terms name -> [B, W], zero at
    padding steps). The carry is an input like any other: callers cut its gradient. At a
    static start 0 (a scene's first window) the state is the zero state: its first step skips
    the recurrent convolutions of those zeros (`SceneGenNet.recur`). The steps run unrolled
    where the window is `differentiated` on XLA:CPU and as a compiled loop elsewhere
    (`backend.compiled_step_loop`)."""
    net = SceneGenNet(cfg)
    state, raster = carry
    if isinstance(start, int) and start == 0:
        state = None
    b, w = map_gates.shape[0], cfg.bptt_window
    win = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, start, w, axis=1), scenes.actors)
    prev_bins = jax.lax.dynamic_slice_in_dim(scenes.prev_bins, start, w, axis=1)
    map_feat = jax.lax.dynamic_slice_in_dim(scenes.map_feat, start, w, axis=1)
    targets, is_stop, valid = _step_targets(
        win, scenes.n_actors, scenes.complete, start + jnp.arange(w)
    )
    bins = bin_index(targets.position, cfg.grid)  # [B, W]
    steps = _scanned_steps if backend.compiled_step_loop(differentiated) else _unrolled_steps
    heads, state, raster_end = steps(
        net, params, map_gates, state, raster, win, targets.cls, bins, prev_bins, cfg, remat
    )

    # The densities are cheap and small: one batched call over the window's steps.
    def step_major(x):  # [B, W, ...] -> [W * B, ...]
        return jnp.swapaxes(x, 0, 1).reshape(w * b, *x.shape[2:])

    terms = head_terms(
        net,
        params,
        heads,
        jax.tree.map(step_major, targets),
        step_major(is_stop),
        cfg,
        hard_negatives,
        step_major(map_feat),
    )
    terms = {k: jnp.swapaxes(v.reshape(w, b), 0, 1) * valid for k, v in terms.items()}
    return (state, raster_end), terms


def _chunk_heads(net: SceneGenNet):
    def chunk_heads(params, h2, cls, bins):
        f = net.apply({"params": params}, h2, method=SceneGenNet.features)
        return step_heads(net, params, f, cls, bins)

    return chunk_heads


def _draw(cfg: ModelConfig):
    return jax.vmap(functools.partial(draw_actor, grid=cfg.grid))


def _unrolled_steps(
    net, params, map_gates, state, raster, win: Actors, cls, bins, prev_bins, cfg, remat
):
    """The window's steps unrolled at trace time, backbone and heads on chunks of steps
    (`head_chunk`), with `remat` each chunk recomputed in the backward pass one chunk
    late. Returns (heads [W * B, ...] step-major, state, raster after the window)."""

    apply = _bound(net, params)
    chunk_heads = _chunk_heads(net)
    remat_heads = recompute_in_backward(chunk_heads)
    b, w = map_gates.shape[0], cfg.bptt_window
    draw = _draw(cfg)

    def add(r, a):  # the raster before actor j, then actor j drawn
        return draw(r, a, jnp.zeros((b,), bool)), r

    raster_end, rasters = jax.lax.scan(
        add, raster, jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), win)
    )
    chunk = head_chunk(cfg, b)
    heads, pending = [], []
    actor_gates = apply(SceneGenNet.actor_gates, rasters[0])
    for c0 in range(0, w, chunk):
        h2s = []
        for j in range(c0, min(c0 + chunk, w)):
            if j > 0:
                actor_gates = apply(
                    SceneGenNet.next_actor_gates,
                    actor_gates,
                    rasters[j - 1],
                    rasters[j],
                    win.position[:, j - 1],
                )
            order = apply(SceneGenNet.order_gates, prev_bins[:, j])
            state, h2 = apply(SceneGenNet.recur, state, actor_gates + map_gates + order)
            h2s.append(h2)
        at_cls = jnp.swapaxes(cls[:, c0 : c0 + chunk], 0, 1).reshape(-1)
        at = jnp.swapaxes(bins[:, c0 : c0 + chunk], 0, 1).reshape(-1)
        args = (jnp.concatenate(h2s), at_cls, at)  # [n * B, ...] step-major
        if not remat:
            heads.append(chunk_heads(params, *args))
            continue
        # One chunk late: the state passed through is the one after the next chunk, so
        # the backward recomputes this chunk while the next one's recurrence runs.
        pending.append(args)
        if len(pending) == 2:
            out, state = remat_heads(params, *pending.pop(0), state)
            heads.append(out)
    for args in pending:
        out, state = remat_heads(params, *args, state)
        heads.append(out)
    heads = jax.tree.map(lambda *x: jnp.concatenate(x), *heads)
    return heads, state, raster_end


def _scanned_steps(
    net, params, map_gates, state, raster, win: Actors, cls, bins, prev_bins, cfg, remat
):
    """`_unrolled_steps` as a `lax.scan` over the window's steps 1..W-1 (step 0, which may
    start from the zero state, runs before it): `backend.STEP_LOOP_UNROLL` steps are compiled,
    whatever the window.
    Each iteration draws the previous step's actor, updates the actor gates locally, steps
    the ConvLSTM and runs the backbone and heads of that one step (recomputed in the
    backward pass with `remat`: `jax.checkpoint` inside a loop body holds)."""

    apply = _bound(net, params)
    heads_of = _chunk_heads(net)
    if remat:
        heads_of = jax.checkpoint(heads_of, prevent_cse=False)
    b = map_gates.shape[0]
    draw = _draw(cfg)
    gates = apply(SceneGenNet.actor_gates, raster)
    order = apply(SceneGenNet.order_gates, prev_bins[:, 0])
    state, h2 = apply(SceneGenNet.recur, state, gates + map_gates + order)
    first = heads_of(params, h2, cls[:, 0], bins[:, 0])

    def step(carry, x):
        state, gates, before = carry
        # The previous step's actor; this step's target class and bin, previous actor's bin.
        drawn, at_cls, at, prev = x
        after = draw(before, drawn, jnp.zeros((b,), bool))
        gates = apply(SceneGenNet.next_actor_gates, gates, before, after, drawn.position)
        order = apply(SceneGenNet.order_gates, prev)
        state, h2 = apply(SceneGenNet.recur, state, gates + map_gates + order)
        return (state, gates, after), heads_of(params, h2, at_cls, at)

    steps_major = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), (win, cls, bins, prev_bins))
    drawn = jax.tree.map(lambda x: x[:-1], steps_major[0])
    (state, _, raster), rest = jax.lax.scan(
        step,
        (state, gates, raster),
        (drawn, steps_major[1][1:], steps_major[2][1:], steps_major[3][1:]),
        unroll=backend.STEP_LOOP_UNROLL,
    )
    last = jax.tree.map(lambda x: x[-1], steps_major[0])
    raster_end = draw(raster, last, jnp.zeros((b,), bool))
    heads = jax.tree.map(
        lambda f, r: jnp.concatenate([f, r.reshape(-1, *r.shape[2:])]), first, rest
    )
    return heads, state, raster_end


def join_windows(terms: dict, scenes: Scenes):
    """terms name -> [windows, B, W] as (terms [B, T], step_valid [B, T], step_cls [B, T])."""
    terms = {k: jnp.concatenate(list(v), axis=1) for k, v in terms.items()}
    is_stop, step_valid = _stop_and_valid(
        scenes.n_actors, scenes.complete, jnp.arange(scenes.actors.cls.shape[1])
    )
    return terms, step_valid, jnp.where(is_stop, STOP, scenes.actors.cls)


def unroll_terms(
    params,
    cfg: ModelConfig,
    maps,
    scene: Scene,
    hard_negatives: int | None,
    differentiated: bool = True,
    remat: bool | str = False,
):
    """Log-likelihood terms of every step of a batch of scenes, teacher forced.

    Args:
      params: network parameters.
      cfg: config.
      maps: [B, H, W, Cm] map channels.
      scene: batched Scene (actors [B, N] canonical, ego [B]).
      hard_negatives: location normaliser size for training, None for the full softmax.
      differentiated: whether the caller takes a gradient through it: the steps' loop form
        depends on it (`backend.compiled_step_loop`), and without a gradient every step runs
        in one window; the values do not.
      remat: recompute the backbone and heads in the backward pass (`TrainConfig.remat`).
    Returns:
      (terms: dict name -> [B, T] log-likelihoods, zero at padding steps; step_valid [B, T];
      step_cls [B, T] with STOP at the stop step), T = windows * cfg.bptt_window.
    """
    if not differentiated:  # no gradient to truncate: the same T steps as one window
        cfg = cfg.replace(bptt_window=num_windows(cfg) * cfg.bptt_window)
    scenes = prepare_scenes(params, cfg, maps, scene)
    map_gates = SceneGenNet(cfg).apply({"params": params}, maps, method=SceneGenNet.map_gates)

    def window(carry, index):
        carry = jax.lax.stop_gradient(carry)  # truncated BPTT: no gradient across windows
        return window_terms(
            params,
            map_gates,
            carry,
            index * cfg.bptt_window,
            scenes,
            cfg,
            hard_negatives,
            differentiated,
            remat,
        )

    _, terms = scan_windows(window, (scenes.state0, scenes.raster0), num_windows(cfg))
    return join_windows(terms, scenes)
