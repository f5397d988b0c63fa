"""The training loop of the small models beside SceneGen (the forecaster of the Features MMD,
the learned baselines): Adam on a loss over batches drawn from host arrays, checkpoints in a
workdir through `checkpoint.Checkpointer` (resumable: a step's batch and random key depend
only on the seed and the step), a progress bar and `metrics.jsonl`.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import sys
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from scenegen_jax.checkpoint import Checkpointer
from scenegen_jax.files import written_whole
from scenegen_jax.jsonfile import read_json

log = logging.getLogger(__name__)
CHECKPOINTS = "checkpoints"
METRICS_FILE = "metrics.jsonl"
RUN_FILE = "run.json"
LOG_EVERY = 50


class FitState(NamedTuple):
    step: jax.Array
    params: Any
    opt_state: optax.OptState


def save_run_config(workdir: str, fields: dict) -> None:
    """Records a run's settings in `workdir`/run.json, or checks them against the ones a
    run there was started with: a resumed run must be the same run.

    Raises ValueError naming the file and the first field that differs."""
    path = os.path.join(workdir, RUN_FILE)
    fields = json.loads(json.dumps(fields))  # tuples as lists, as read back
    if os.path.isfile(path):
        saved = read_json(path)
        for k in sorted(set(saved) | set(fields)):
            if saved.get(k) != fields.get(k):
                raise ValueError(f"{path}: field {k}: the run there has {saved.get(k)!r}, this "
                                 f"one {fields.get(k)!r}; give another --workdir to start "
                                 "another run")
        return
    os.makedirs(workdir, exist_ok=True)
    with written_whole(path) as tmp, open(tmp, "w") as f:
        json.dump(fields, f, indent=1)


def batch_indices(seed: int, step: int, rows: int, batch_size: int) -> np.ndarray:
    """The rows of a training step's batch: a function of the seed and the step alone, so
    that a resumed run draws what the uninterrupted one did."""
    return np.random.default_rng([seed, step]).choice(rows, batch_size,
                                                      replace=rows < batch_size)


def take_rows(data, rows: np.ndarray):
    """The rows of every host array of `data` (a NamedTuple or any pytree of [N, ...])."""
    return jax.tree.map(lambda x: x[rows], data)


def optimizer(lr: float, weight_decay: float = 0.0):
    """Adam, or AdamW with a weight decay."""
    return optax.adamw(lr, weight_decay=weight_decay) if weight_decay else optax.adam(lr)


@functools.partial(jax.jit, static_argnames=("loss", "lr", "weight_decay"), donate_argnums=0)
def _step(state: FitState, batch, key, loss: Callable, lr: float, weight_decay: float):
    value, grads = jax.value_and_grad(loss)(state.params, batch, key)
    updates, opt_state = optimizer(lr, weight_decay).update(grads, state.opt_state,
                                                            state.params)
    return FitState(state.step + 1, optax.apply_updates(state.params, updates), opt_state), value


def fit(loss: Callable, params, data, workdir: str, steps: int, batch_size: int = 32,
        lr: float = 1e-3, seed: int = 0, save_every: int = 250, progress: bool = True,
        desc: str = "train", weight_decay: float = 0.0):
    """Trains `params` on `loss(params, batch, key) -> scalar` (a module-level function, the
    jit's static argument) with `optimizer(lr, weight_decay)` up to `steps`, resuming from
    the newest checkpoint in `workdir`; returns the parameters. `data`: host arrays [N, ...]
    (a NamedTuple or any pytree)."""
    rows = len(jax.tree.leaves(data)[0])
    state = FitState(jnp.zeros((), jnp.int32), params,
                     optimizer(lr, weight_decay).init(params))
    ckpt = Checkpointer(os.path.join(workdir, CHECKPOINTS), save_every, keep=2, heal=True)
    restored = ckpt.restore_latest(state)
    if restored is not None:
        state = restored
        log.info("%s: resumed at step %d", workdir, int(state.step))
    start = int(state.step)
    losses, t0 = [], time.perf_counter()
    bar = tqdm(total=steps, initial=start, desc=desc, unit="step", file=sys.stderr,
               disable=not progress)
    base = jax.random.key(seed)
    for step in range(start, steps):
        batch = take_rows(data, batch_indices(seed, step, rows, batch_size))
        state, value = _step(state, batch, jax.random.fold_in(base, step), loss, lr,
                             weight_decay)
        losses.append(value)
        if (step + 1) % LOG_EVERY == 0 or step + 1 == steps:
            mean = float(np.mean(jax.device_get(losses)))
            with open(os.path.join(workdir, METRICS_FILE), "a") as f:
                f.write(json.dumps({"step": step + 1, "loss": mean,
                                    "seconds": round(time.perf_counter() - t0, 2)}) + "\n")
            bar.set_postfix(loss=f"{mean:.4g}")
            losses = []
        ckpt.save(state, force=step + 1 == steps)
        bar.update(1)
    bar.close()
    ckpt.close()
    return state.params
