"""What the training tests share: batches of the small config's real scenes, and the train
step compiled once per config."""

from __future__ import annotations

import jax
import numpy as np
from small import CFG

from scenegen_jax.likelihood.batch import gather_batch
from scenegen_jax.train.step import train_step


def batch_of(cache, idx):
    """The cached batch of scenes `idx` of `cache`, for the small config."""
    return gather_batch(cache, np.asarray(idx), CFG.grid)


# `train_step` compiled once per config. Run op by op, a module's first step compiles
# thousands of small programs, which takes longer than compiling the whole step.
jitted_train_step = jax.jit(train_step, static_argnums=2)
