"""Optimizer, train state and the jitted (optionally sharded) train step."""

from __future__ import annotations

import functools
import logging
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from scenegen_jax.allocator import release_freed_memory
from scenegen_jax.backend import (
    DATA_AXIS,
    compiled_init,
    free_memory_bytes,
    train_compiler_options,
)
from scenegen_jax.config import LAYER_GROUPS, Config
from scenegen_jax.likelihood.batch import Batch, batch_scenes
from scenegen_jax.likelihood.grads import (
    unroll_terms_and_grads,
)
from scenegen_jax.likelihood.terms import mean_nll
from scenegen_jax.likelihood.unroll import unroll_terms
from scenegen_jax.model.network import MAP_CHANNEL_AXIS, init_params

log = logging.getLogger(__name__)


class TrainState(NamedTuple):
    """Everything a resumed run needs; arrays only, so it goes straight into orbax.

    step: int32 [] steps taken (also the data position: batch i is a pure function of i).
    params: network parameters.
    opt_state: optimizer state.
    key: uint32 [2] raw base key; step keys are fold_in(key, step).
    ema: the parameters' moving average with `ema_decay` (`update_ema`); None without it
      (nothing saved: `checkpoint.Checkpointer`).
    """

    step: jnp.ndarray
    params: Any
    opt_state: Any
    key: jnp.ndarray
    ema: Any = None


def start_ema(cfg: Config, params):
    """The moving average a run starting from `params` begins with: a copy of them (its own
    buffers: a train step donates both), or None without `ema_decay`."""
    if cfg.train.ema_decay == 0:
        return None
    return jax.tree.map(lambda x: jnp.array(x, copy=True), params)


def update_ema(cfg: Config, ema, params):
    """d * ema + (1 - d) * params with d = `ema_decay`, in the parameters' dtypes; None stays
    None."""
    if ema is None:
        return None
    d = cfg.train.ema_decay
    return jax.tree.map(lambda e, p: (d * e + (1 - d) * p).astype(e.dtype), ema, params)


def make_optimizer(cfg: Config) -> optax.GradientTransformation:
    """Adam with global-norm clipping and the learning-rate schedule `learning_rate_at`; with
    `train_layers` or `train_params`, the gradients first masked to those weights
    (`trainable_mask`)."""
    adam = optax.adam(learning_rate_at(cfg))
    if cfg.train.grad_clip > 0:
        adam = optax.chain(optax.clip_by_global_norm(cfg.train.grad_clip), adam)
    if cfg.train.train_layers or cfg.train.train_params:
        return optax.chain(_masked(functools.partial(trainable_mask, cfg)), adam)
    return adam


def trainable_mask(cfg: Config, params):
    """1 on the weights that read the map channels of `cfg.train.train_layers` (`MAP_CHANNEL_AXIS`)
    and on every entry of the parameters `cfg.train.train_params`, 0 elsewhere: numpy arrays shaped
    as `params`. An unknown parameter name is a ValueError that lists the known ones."""
    unknown = sorted(set(cfg.train.train_params) - set(params))
    if unknown:
        raise ValueError(f"train_params: no parameter {unknown}; parameters: {sorted(params)}")
    channels = [
        cfg.grid.map_channels.index(c) for g in cfg.train.train_layers for c in LAYER_GROUPS[g]
    ]

    def mask(path, x):
        if path[0].key in cfg.train.train_params:
            return np.ones(x.shape, np.float32)
        m = np.zeros(x.shape, np.float32)
        axis = MAP_CHANNEL_AXIS.get(path[0].key)
        if axis is not None:
            m[(slice(None),) * axis + (channels,)] = 1.0
        return m

    return jax.tree_util.tree_map_with_path(mask, params)


def _masked(mask_of) -> optax.GradientTransformation:
    """Multiplies the updates by `mask_of(updates)` (stateless: Adam then sees zero gradients
    outside the mask, and its step there is 0)."""

    def update(updates, state, params=None):
        return jax.tree.map(lambda u, m: u * m, updates, mask_of(updates)), state

    return optax.GradientTransformation(lambda params: optax.EmptyState(), update)


def learning_rate_at(cfg: Config) -> float | optax.Schedule:
    """Adam's learning rate: `learning_rate`, after a linear ramp from 0 over `warmup_steps`
    where set, and with `decay_steps` a cosine from `learning_rate` to 0 over that many steps
    after the ramp (0 after them). A constant is a float: its optimizer state has no step
    count, as in checkpoints saved before the schedules existed."""
    peak = cfg.train.learning_rate
    if cfg.train.decay_steps == 0:
        return (
            optax.linear_schedule(0.0, peak, cfg.train.warmup_steps)
            if cfg.train.warmup_steps
            else peak
        )
    decay = optax.cosine_decay_schedule(peak, cfg.train.decay_steps)
    if cfg.train.warmup_steps == 0:
        return decay
    ramp = optax.linear_schedule(0.0, peak, cfg.train.warmup_steps)
    return optax.join_schedules([ramp, decay], [cfg.train.warmup_steps])


def init_state(cfg: Config, seed: int | None = None) -> TrainState:
    """Fresh train state from `seed` (default cfg.train.seed), compiled as one program with the
    parameters (`init_params`), since the optimizer's zeros dispatched one by one would take
    a noticeable share of the initialisation."""

    def fresh(key):
        init_key, base = jax.random.split(key)
        params = init_params(cfg.model, init_key)
        return TrainState(
            step=jnp.zeros((), jnp.int32),
            params=params,
            opt_state=make_optimizer(cfg).init(params),
            key=jax.random.key_data(base),
            ema=start_ema(cfg, params),
        )

    key = jax.random.key(cfg.train.seed if seed is None else seed)
    return compiled_init(fresh, key)


def loss_fn(params, cfg: Config, maps, scene):
    """Mean scene NLL (nats) with the hard-negative location normaliser, and stats: the
    plain definition. `train_step` computes the same value and its gradient window by window
    (`unroll_terms_and_grads`); a test holds the two equal."""
    return mean_nll(
        unroll_terms(
            params, cfg.model, maps, scene, cfg.train.hard_negatives, remat=cfg.train.remat
        ),
        scene.actors,
    )


def _psum_packed(tree, axis: str | None):
    """`lax.psum` of every array of `tree` over `axis` as one all-reduce of one vector (one
    collective per step instead of one per array: each costs a round trip between hosts);
    `tree` as it is without an axis."""
    if axis is None:
        return tree
    flat, unravel = ravel_pytree(jax.tree.map(lambda x: x.astype(jnp.float32), tree))
    summed = unravel(jax.lax.psum(flat, axis))
    return jax.tree.map(lambda x, y: y.astype(x.dtype), tree, summed)


def step_rotations(key_data, step, batch_size: int, rotate: bool):
    """float32 [batch_size] rotations (rad) of the global batch of step `step`: uniform over
    [0, 2 pi) from the run's key (`TrainState.key`) and the step, 0 without `rotate`. The
    loop draws them to draw the maps (`gather_batch`); a pure function of (key, step), so a
    resumed run draws what an uninterrupted one would."""
    if not rotate:
        return jnp.zeros((batch_size,))
    key = jax.random.fold_in(jax.random.wrap_key_data(key_data), step)
    return jax.random.uniform(key, (batch_size,), maxval=2 * jnp.pi)


def step_inputs(state: TrainState, batch: Batch, cfg: Config, axis: str | None):
    """(maps, scene, global batch size, devices) of a step: the batch's rotated scenes (this
    device's part of them with `axis`) and map dropout."""
    key = jax.random.fold_in(jax.random.wrap_key_data(state.key), state.step)
    local = batch.actors.cls.shape[0]
    devices = 1 if axis is None else jax.lax.axis_size(axis)
    first = 0 if axis is None else jax.lax.axis_index(axis) * local
    b = local * devices  # the global batch: draws, and the mean over scenes, are over it
    maps, scene = batch_scenes(batch, cfg.grid)
    if cfg.train.map_dropout > 0:
        keep = jax.random.uniform(jax.random.fold_in(key, 1), (b, 1, 1, 1)) >= cfg.train.map_dropout
        maps = maps * jax.lax.dynamic_slice_in_dim(keep, first, local)
    return maps, scene, b, devices


def apply_grads(state: TrainState, cfg: Config, unrolled, actors, grads, devices,
                axis: str | None):
    """(next state, stats): the loss and stats of the unrolled terms (of `actors`, canonically
    ordered), summed with the gradient over the devices in one all-reduce (`axis`), the
    optimizer's update and the moving average's (`update_ema`)."""
    loss, stats = mean_nll(unrolled, actors)
    grads, stats, loss = _psum_packed((grads, stats, loss / devices), axis)
    updates, opt_state = make_optimizer(cfg).update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    stats = {**stats, "loss": loss, "grad_norm": optax.tree.norm(grads)}
    ema = update_ema(cfg, state.ema, params)
    return TrainState(state.step + 1, params, opt_state, state.key, ema), stats


def train_step(
    state: TrainState, batch: Batch, cfg: Config, axis: str | None = None
) -> tuple[TrainState, dict]:
    """One optimizer step on a batch (pure; jit it with `make_train_step`).

    With `axis` (inside `shard_map` over a `data` mesh axis) `batch` is this device's part
    of the global batch: it takes its own slice of the step's rotations, its gradient and
    statistics are summed over the devices in one all-reduce, and every device applies the
    same update.
    """
    maps, scene, b, devices = step_inputs(state, batch, cfg, axis)
    # loss_fn's value, and its gradient taken one window at a time.
    unrolled, grads = unroll_terms_and_grads(
        state.params, cfg.model, maps, scene, 1.0 / b, cfg.train.hard_negatives, cfg.train.remat
    )
    return apply_grads(state, cfg, unrolled, scene.actors, grads, devices, axis)


# The train step's buffers without remat, bytes per scene, step of a window and pixel of the
# grid: STEP_BYTES_PER_CHANNEL per hidden channel plus STEP_BYTES_FIXED, fitted to XLA's
# buffer plans (`memory_analysis`) at hidden 16 and 32 and grids 32 to 320; tests/test_train_step.py
# holds the estimate within 10 % of the plan.
STEP_BYTES_PER_CHANNEL = 60
STEP_BYTES_FIXED = 2800
# Share of the free memory a step without remat may take (`resolve_remat`): the rest holds
# the data and the checkpoints, and covers the estimate's error.
REMAT_FREE_SHARE = 0.75


def step_bytes_without_remat(cfg: Config, scenes: int) -> int:
    """Estimated bytes of the train step's buffers without remat on a device that holds
    `scenes` scenes of the batch: about one window's activations (the step takes a window's
    gradient right after its forward pass)."""
    per_pixel = STEP_BYTES_PER_CHANNEL * cfg.model.hidden + STEP_BYTES_FIXED
    return scenes * cfg.model.bptt_window * cfg.grid.grid_size**2 * per_pixel


def resolve_remat(cfg: Config, scenes: int) -> Config:
    """`cfg` with `remat` "auto" made false where the step without remat on a device that
    holds `scenes` scenes of the batch takes at most `REMAT_FREE_SHARE` of the memory free
    now (`step_bytes_without_remat`, `backend.free_memory_bytes`), else true; the choice is
    logged. Other values are kept. Remat costs time wherever the step fits without it, so it
    is taken only where memory requires it (the paper's batch of 16 on one accelerator)."""
    if cfg.train.remat != "auto":
        return cfg
    need, free = step_bytes_without_remat(cfg, scenes), free_memory_bytes()
    remat = need > REMAT_FREE_SHARE * free
    log.info(
        "remat auto: %s (the step without it takes about %.1f GiB; %.1f GiB free)",
        "on" if remat else "off",
        need / 2**30,
        free / 2**30,
    )
    return cfg.replace(remat=remat)


def make_train_step(cfg: Config, mesh: Mesh | None = None):
    """The jitted train step; with a mesh, the batch is sharded over `data` (each device
    unrolls its own scenes, `shard_map`) and the state replicated. The state argument is
    donated. `cfg.train.remat` "auto" is resolved for `cfg.train.batch_size` (`resolve_remat`)."""
    cfg = resolve_remat(cfg, cfg.train.batch_size // (1 if mesh is None else mesh.size))
    options = train_compiler_options()
    if mesh is None:
        return jax.jit(
            lambda state, batch: train_step(state, batch, cfg),
            donate_argnums=0,
            compiler_options=options,
        )
    if cfg.train.batch_size % mesh.size:
        raise ValueError(
            f"batch_size {cfg.train.batch_size} is not divisible by {mesh.size} devices"
        )
    per_device = jax.shard_map(
        lambda state, batch: train_step(state, batch, cfg, DATA_AXIS),
        mesh=mesh,
        in_specs=(P(), P(DATA_AXIS)),
        out_specs=(P(), P()),
        # The network's custom VJPs do not type the manual axis; the packed psum makes every
        # output replicated.
        check_vma=False,
    )
    replicated = NamedSharding(mesh, P())
    data = NamedSharding(mesh, P(DATA_AXIS))
    return jax.jit(
        per_device,
        in_shardings=(replicated, data),
        out_shardings=(replicated, replicated),
        donate_argnums=0,
        compiler_options=options,
    )


def compile_train_step(cfg: Config, state: TrainState, batch: Batch, mesh: Mesh | None = None):
    """`make_train_step` compiled ahead of time for the shapes of (state, batch), with the
    compiler's freed memory returned to the OS before the first step runs."""
    step = make_train_step(cfg, mesh).lower(state, batch).compile()
    release_freed_memory()
    return step
