"""The small tiny-config variant shared by the training and scoring tests."""

from __future__ import annotations

import re
import sys

import numpy as np

from scenegen_jax.config import get_config

# Small enough to compile quickly: 6 actor slots, 7 generation steps in one window (two
# windows took twice the compile time of the train step: every window traces its own
# heads; tests of the windows set their own `bptt_window`). On CPU every step of a
# differentiated window is traced and compiled on its own, so the suite's compile time
# grows with the steps.
CFG = get_config("tiny").replace(
    max_actors=6,
    bptt_window=7,
    batch_size=2,
    hidden=8,
    gn_groups=2,
    rotate_augment=False,
    learning_rate=3e-3,
    hard_negatives=512,  # half the grid: the tests cover hard negative mining
)


def two_small_scenes(cache) -> np.ndarray:
    """Indices of the two scenes of `cache` with the fewest actors in the region (13 and 14 in
    the tiny fixture: CFG keeps the first 6 in canonical order, a full scene of 7 steps)."""
    pos = cache.actors.position
    inside = cache.actors.valid & (np.abs(pos) < CFG.grid.region_m / 2).all(-1)
    return np.sort(np.argsort(inside.sum(1), kind="stable")[:2])


def random_params(cfg, key):
    """`init_params` with the location output layer (zero at initialisation: flat logits) drawn
    at random, so that tests comparing two computations of the location logits and their
    gradients compare non-trivial values."""
    import jax

    from scenegen_jax.model.network import init_params

    init_key, loc_key = jax.random.split(key)
    params = dict(init_params(cfg.model, init_key))
    w = params["loc2_w"]
    params["loc2_w"] = jax.random.normal(loc_key, w.shape, w.dtype) / np.sqrt(w.shape[-2])
    return params


def train_args(cache, workdir, steps, *extra) -> list[str]:
    """`scenegen train` of CFG's shapes on `cache` (saving every 2 steps) as the command's
    arguments, with `extra` options: for `cli.main` in this process, where the programs that
    other tests compiled for CFG are already traced, or for `train_cmd`."""
    overrides = [f"{k}={CFG.flat()[k]}"
                 for k in ("max_actors", "bptt_window", "batch_size", "hidden", "gn_groups")]
    return ["train", "--config", "tiny", "--data", cache, "--workdir", workdir,
            "--steps", str(steps), "--save-every", "2", "--log-every", "2", *extra,
            "--set", *overrides]


def train_cmd(cache, workdir, steps, *extra) -> list[str]:
    """`train_args` as a subprocess command line: for runs that are killed, or joined by
    --distributed."""
    return [sys.executable, "-m", "scenegen_jax.cli", *train_args(cache, workdir, steps, *extra)]


def metrics_rows(path: str) -> list[str]:
    """The complete rows of a run's metrics file (a kill may cut its last one short)."""
    with open(path) as f:
        return [line for line in f if line.endswith("\n")]


def with_xla_flags(env, *flags: str) -> dict:
    """`env` with `flags` added to its XLA_FLAGS, keeping the suite's own (conftest.py)."""
    return {**env, "XLA_FLAGS": " ".join([env.get("XLA_FLAGS", ""), *flags]).strip()}


# Conv biases followed by a GroupNorm (which removes them) and the location logits' bias
# (a softmax over the grid ignores it) have a gradient of exactly zero; their float noise
# is turned into steps of up to lr by Adam in any two runs that sum in different orders.
ZERO_GRADIENT = re.compile(r"^(backbone\d+|loc\d+)_b$")


def assert_same_adam_training(init: dict, a: dict, b: dict, lr: float, steps: int) -> None:
    """Two Adam runs of `steps` steps from the parameters `init` (flat dicts name -> array)
    that sum in different orders ended at `a` and `b`: every parameter's change since `init`
    agrees to 1e-3 of its size, but for at most 1 in 200 of its elements, each within two
    runs' Adam steps of at most lr. An element whose gradient is near Adam's epsilon (1e-8)
    turns the float noise of a different summation order into a different step (seen: one
    of 576 location-head weights at step 2, -1.1e-4 against -4.0e-4; one of 6,400 ConvLSTM
    weights after one step on 8 devices against one, 0.0713 against 0.0711, with AVX2's
    Winograd convolutions)."""
    compared = 0
    for name, x0 in init.items():
        if ZERO_GRADIENT.match(name):
            continue
        da, db = np.asarray(a[name]) - x0, np.asarray(b[name]) - x0
        diff = np.abs(da - db).ravel()
        outliers = np.argsort(diff)[len(diff) - len(diff) // 200:]
        assert np.all(diff[outliers] <= 2 * lr * steps), (name, steps)
        rest = np.delete(diff, outliers)
        assert np.linalg.norm(rest) <= 1e-3 * np.linalg.norm(da) + 1e-7, (name, steps)
        compared += 1
    assert compared > 20
