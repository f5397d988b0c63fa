"""Optimizer, train state and the jitted (optionally sharded) train step."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from scenegen_jax.backend import release_freed_memory
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
    """Adam with an optional linear learning-rate warm-up and global-norm clipping."""
    lr = cfg.learning_rate
    if cfg.warmup_steps > 0:
        lr = optax.linear_schedule(0.0, cfg.learning_rate, cfg.warmup_steps)
    adam = optax.adam(lr)
    if cfg.grad_clip > 0:
        return optax.chain(optax.clip_by_global_norm(cfg.grad_clip), adam)
    return adam


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


def train_step(state: TrainState, batch: Batch, cfg: Config) -> tuple[TrainState, dict]:
    """One optimizer step on a batch (pure; jit it with `make_train_step`)."""
    key = jax.random.fold_in(jax.random.wrap_key_data(state.key), state.step)
    b = batch.actors.cls.shape[0]
    if cfg.rotate_augment:
        thetas = jax.random.uniform(key, (b,), maxval=2 * jnp.pi)
    else:
        thetas = jnp.zeros((b,))
    maps, scene = crop_batch(batch, thetas, cfg)
    if cfg.map_dropout > 0:
        keep = jax.random.uniform(jax.random.fold_in(key, 1), (b, 1, 1, 1)) >= cfg.map_dropout
        maps = maps * keep
    # loss_fn's value, and its gradient taken one window at a time.
    unrolled, grads = unroll_terms_and_grads(state.params, cfg, maps, scene, 1.0 / b)
    loss, stats = mean_nll(unrolled)
    updates, opt_state = make_optimizer(cfg).update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    stats = {**stats, "loss": loss, "grad_norm": optax.global_norm(grads)}
    return TrainState(state.step + 1, params, opt_state, state.key), stats


def make_train_step(cfg: Config, mesh: Mesh | None = None):
    """The jitted train step; with a mesh, the batch is sharded over `data` and the state
    replicated. The state argument is donated."""
    fn = lambda state, batch: train_step(state, batch, cfg)  # noqa: E731
    if mesh is None:
        return jax.jit(fn, donate_argnums=0)
    if cfg.batch_size % mesh.size:
        raise ValueError(f"batch_size {cfg.batch_size} is not divisible by {mesh.size} devices")
    replicated = NamedSharding(mesh, P())
    data = NamedSharding(mesh, P("data"))
    return jax.jit(
        fn,
        in_shardings=(replicated, data),
        out_shardings=(replicated, replicated),
        donate_argnums=0,
    )


def compile_train_step(cfg: Config, state: TrainState, batch: Batch, mesh: Mesh | None = None):
    """`make_train_step` compiled ahead of time for the shapes of (state, batch), with the
    compiler's freed memory returned to the OS before the first step runs."""
    step = make_train_step(cfg, mesh).lower(state, batch).compile()
    release_freed_memory()
    return step
