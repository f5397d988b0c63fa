"""A training workdir as the other commands read it: `config.json` and a checkpoint
(`restore`), of which scoring, sampling and export read only the parameters (`load_params`),
without the optimizer state or anything of `train/`."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import jax

from scenegen_jax.checkpoint import Checkpointer
from scenegen_jax.config import Config
from scenegen_jax.model.network import init_params

CONFIG_FILE = "config.json"
CHECKPOINTS = "checkpoints"


def load_workdir_config(workdir: str) -> Config:
    """The config a workdir was trained with."""
    path = os.path.join(workdir, CONFIG_FILE)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: not a training workdir (no {CONFIG_FILE})")
    with open(path, "rb") as f:
        return Config.from_json(f.read(), path)


def restore(workdir: str, template_of: Callable[[Config], Any], step: int | None = None):
    """(config, checkpoint) of a training workdir: its newest readable checkpoint, or the one
    saved at `step`, restored into the (abstract) tree `template_of(config)`: the entries of
    the train state to read."""
    cfg = load_workdir_config(workdir)
    directory = os.path.join(workdir, CHECKPOINTS)
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"{directory}: no checkpoints (train this workdir first)")
    ckpt = Checkpointer(directory, every=1)
    try:
        restored = ckpt.restore_latest(template_of(cfg), step)
    finally:
        ckpt.close()
    if restored is None:
        raise FileNotFoundError(f"{directory}: no readable checkpoint")
    return cfg, restored


def load_params(workdir: str, step: int | None = None):
    """(config, parameters, step) of a training workdir: the parameters of its newest readable
    checkpoint, or of the one saved at `step`; only the parameters are read. A run with
    `ema_decay` gives its parameters' moving average (`train.step.TrainState.ema`) instead."""
    cfg, restored = restore(workdir, _params_template, step)
    return cfg, restored[_params_entry(cfg)], int(restored["step"])


def _params_entry(cfg: Config) -> str:
    """The train state's entry that holds the parameters to use."""
    return "ema" if cfg.train.ema_decay > 0 else "params"


def _params_template(cfg: Config) -> dict:
    return {_params_entry(cfg): jax.eval_shape(lambda: init_params(cfg.model, jax.random.key(0)))}
