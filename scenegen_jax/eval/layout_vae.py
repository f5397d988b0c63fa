"""LayoutVAE (`model.layout_vae`) as `evaluate` reads it: its scenes' likelihood by Monte
Carlo (1,000 samples of the conditional prior per step, as the paper) and its samples on the
conditioning scenes' maps. Each scene's draws depend only on the seed and the scene's index,
whatever the batch."""

from __future__ import annotations

import functools
import sys

import jax
import numpy as np
from tqdm import tqdm

from scenegen_jax.likelihood.host_data import layout_data
from scenegen_jax.model.layout_vae import LayoutVAEConfig, sample_layouts, step_log_likelihoods
from scenegen_jax.sampling.batch import seed_key

MC_SAMPLES = 1000


@functools.partial(jax.jit, static_argnames=("cfg", "samples"))
def _scene_log_likelihoods(params, cfg: LayoutVAEConfig, batch: dict, keys, samples: int):
    def one(scene, key):
        counts, actors = step_log_likelihoods(
            params, cfg, jax.tree.map(lambda x: x[None], scene), key, samples)
        return counts[0], actors[0]

    return jax.vmap(one)(batch, keys)


def layout_vae_scores(params, cfg: LayoutVAEConfig, cache, seed: int = 0,
                      samples: int = MC_SAMPLES, batch_size: int = 8,
                      progress: bool = True) -> dict:
    """Per scene of a cache (or `CacheUnion`): "scene_nll" [S] nats (counts and actors),
    "count_nll" [S], "actors" [S] (the actors scored: in the region, at most max_actors)."""
    data = layout_data(cache, cfg.grid, progress=progress, desc="LayoutVAE maps")
    base = seed_key(seed)
    counts, actors = [], []
    for start in tqdm(range(0, len(cache), batch_size), desc="LayoutVAE NLL", unit="batch",
                      file=sys.stderr, disable=not progress):
        idx = np.arange(start, min(start + batch_size, len(cache)))
        keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(idx)
        c, a = _scene_log_likelihoods(params, cfg, {k: v[idx] for k, v in data.items()}, keys,
                                      samples)
        counts.append(np.asarray(c).sum(-1))
        actors.append(np.asarray(a).sum(-1))
    count_ll, actor_ll = np.concatenate(counts), np.concatenate(actors)
    return {"scene_nll": -(count_ll + actor_ll), "count_nll": -count_ll,
            "actors": data["valid"].sum(-1)}


def summarize(scores: dict) -> dict:
    n = scores["actors"]
    return {"scenes": len(n), "scene_nll": float(np.mean(scores["scene_nll"])),
            "nll_per_actor": float(np.sum(scores["scene_nll"]) / max(int(np.sum(n)), 1))}


_sample = jax.jit(sample_layouts, static_argnames="cfg")


def sample_layout_vae(params, cfg: LayoutVAEConfig, maps, egos, seed: int) -> list:
    """One LayoutVAE scene per map [n, G, G, C] (numpy Actors each); egos: Actors [n]."""
    base = seed_key(seed)
    out = []
    for i in range(len(maps)):
        scene = _sample(params, cfg, np.asarray(maps[i : i + 1]),
                        np.asarray(egos.velocity[i : i + 1]), jax.random.fold_in(base, i))
        out.append(jax.tree.map(lambda x: np.asarray(x[0]), scene))
    return out
