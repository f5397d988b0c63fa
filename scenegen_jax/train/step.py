"""Optimizer, train state and the jitted (optionally sharded) train step."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from scenegen_jax.backend import DATA_AXIS, release_freed_memory, train_compiler_options
from scenegen_jax.config import Config
from scenegen_jax.likelihood.batch import Batch, crop_batch
from scenegen_jax.likelihood.terms import mean_nll
from scenegen_jax.likelihood.unroll import unroll_terms, unroll_terms_and_grads
from scenegen_jax.model.network import init_params


class TrainState(NamedTuple):
    """Everything a resumed run needs; arrays only, so it goes straight into orbax.

    step: int32 [] steps taken (also the data position: batch i is a pure function of i).
    params: network parameters.
    opt_state: optimizer state.
    key: uint32 [2] raw base key; step keys are fold_in(key, step).
    """

    step: jnp.ndarray
    params: Any
    opt_state: Any
    key: jnp.ndarray


def make_optimizer(cfg: Config) -> optax.GradientTransformation:
    """Adam with global-norm clipping and the learning-rate schedule `learning_rate_at`."""
    adam = optax.adam(learning_rate_at(cfg))
    if cfg.grad_clip > 0:
        return optax.chain(optax.clip_by_global_norm(cfg.grad_clip), adam)
    return adam


def learning_rate_at(cfg: Config) -> float | optax.Schedule:
    """Adam's learning rate: `learning_rate`, after a linear ramp from 0 over `warmup_steps`
    where set, and with `decay_steps` a cosine from `learning_rate` to 0 over that many steps
    after the ramp (0 after them). A constant is a float: its optimizer state has no step
    count, as in checkpoints saved before the schedules existed."""
    peak = cfg.learning_rate
    if cfg.decay_steps == 0:
        return optax.linear_schedule(0.0, peak, cfg.warmup_steps) if cfg.warmup_steps else peak
    decay = optax.cosine_decay_schedule(peak, cfg.decay_steps)
    if cfg.warmup_steps == 0:
        return decay
    ramp = optax.linear_schedule(0.0, peak, cfg.warmup_steps)
    return optax.join_schedules([ramp, decay], [cfg.warmup_steps])


def init_state(cfg: Config, seed: int | None = None) -> TrainState:
    """Fresh train state from `seed` (default cfg.seed)."""
    key = jax.random.key(cfg.seed if seed is None else seed)
    init_key, base = jax.random.split(key)
    params = init_params(cfg, init_key)
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        opt_state=make_optimizer(cfg).init(params),
        key=jax.random.key_data(base),
    )


def loss_fn(params, cfg: Config, maps, scene):
    """Mean scene NLL (nats) with the hard-negative location normaliser, and stats: the
    plain definition. `train_step` computes the same value and its gradient window by window
    (`unroll_terms_and_grads`); a test holds the two equal."""
    return mean_nll(unroll_terms(params, cfg, maps, scene, cfg.hard_negatives))


def _psum_packed(tree, axis: str | None):
    """`lax.psum` of every array of `tree` over `axis` as one all-reduce of one vector (one
    collective per step instead of one per array: each costs a round trip between hosts);
    `tree` as it is without an axis."""
    if axis is None:
        return tree
    flat, unravel = ravel_pytree(jax.tree.map(lambda x: x.astype(jnp.float32), tree))
    summed = unravel(jax.lax.psum(flat, axis))
    return jax.tree.map(lambda x, y: y.astype(x.dtype), tree, summed)


def train_step(
    state: TrainState, batch: Batch, cfg: Config, axis: str | None = None
) -> tuple[TrainState, dict]:
    """One optimizer step on a batch (pure; jit it with `make_train_step`).

    With `axis` (inside `shard_map` over a `data` mesh axis) `batch` is this device's part
    of the global batch: it takes its own slice of the step's rotations, its gradient and
    statistics are summed over the devices in one all-reduce, and every device applies the
    same update.
    """
    key = jax.random.fold_in(jax.random.wrap_key_data(state.key), state.step)
    local = batch.actors.cls.shape[0]
    devices = 1 if axis is None else jax.lax.axis_size(axis)
    first = 0 if axis is None else jax.lax.axis_index(axis) * local
    b = local * devices  # the global batch: draws, and the mean over scenes, are over it
    if cfg.rotate_augment:
        thetas = jax.random.uniform(key, (b,), maxval=2 * jnp.pi)
    else:
        thetas = jnp.zeros((b,))
    maps, scene = crop_batch(batch, jax.lax.dynamic_slice_in_dim(thetas, first, local), cfg)
    if cfg.map_dropout > 0:
        keep = jax.random.uniform(jax.random.fold_in(key, 1), (b, 1, 1, 1)) >= cfg.map_dropout
        maps = maps * jax.lax.dynamic_slice_in_dim(keep, first, local)
    # loss_fn's value, and its gradient taken one window at a time.
    unrolled, grads = unroll_terms_and_grads(state.params, cfg, maps, scene, 1.0 / b)
    loss, stats = mean_nll(unrolled)
    grads, stats, loss = _psum_packed((grads, stats, loss / devices), axis)
    updates, opt_state = make_optimizer(cfg).update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    stats = {**stats, "loss": loss, "grad_norm": optax.global_norm(grads)}
    return TrainState(state.step + 1, params, opt_state, state.key), stats


def make_train_step(cfg: Config, mesh: Mesh | None = None):
    """The jitted train step; with a mesh, the batch is sharded over `data` (each device
    unrolls its own scenes, `shard_map`) and the state replicated. The state argument is
    donated."""
    options = train_compiler_options()
    if mesh is None:
        return jax.jit(lambda state, batch: train_step(state, batch, cfg), donate_argnums=0,
                       compiler_options=options)
    if cfg.batch_size % mesh.size:
        raise ValueError(f"batch_size {cfg.batch_size} is not divisible by {mesh.size} devices")
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
