"""Training LayoutVAE (`model.layout_vae`) on the training caches: every scene's map drawn
once at rotation 0, the negative ELBO minimised by `fit.fit` (resumable)."""

from __future__ import annotations

import functools

from scenegen_jax.model.layout_vae import LayoutVAEConfig, elbo_loss, init_layout_vae
from scenegen_jax.train.fit import fit


def train_layout_vae(cfg: LayoutVAEConfig, data: dict, workdir: str, steps: int,
                     batch_size: int = 32, lr: float = 1e-3, seed: int = 0,
                     save_every: int = 250, progress: bool = True):
    """Trains (or resumes) LayoutVAE on `data` (`likelihood.host_data.layout_data`) up to
    `steps`; returns the parameters."""
    return fit(functools.partial(elbo_loss, cfg=cfg), init_layout_vae(cfg, seed), data, workdir,
               steps, batch_size, lr, seed, save_every, progress, desc="train LayoutVAE")
