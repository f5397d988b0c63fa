"""The Features column of the paper's Table 1: MMD^2 between real and generated scenes in the
feature space of a motion forecaster (`model.forecaster`, shipped beside a pretrained model:
`pretrained.load_companion`), with an RBF kernel of bandwidth 1 (supplementary 2.2) and the
estimator of `eval.mmd`.

A scene's feature is the forecaster's backbone averaged over space, read from the scene's map
and its actors drawn as SceneGen's input draws them; every method's scenes are read on the
same maps.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np

from scenegen_jax.eval.mmd import mmd, mmd_interval, rbf_kernel
from scenegen_jax.model.forecaster import ForecasterConfig, draw_scene_rasters, forecast
from scenegen_jax.scene import Actors

BANDWIDTH = 1.0


def stack_actors(actors_list: Sequence[Actors]) -> Actors:
    """Scenes' numpy Actors [N_i] padded with invalid slots to the largest N and stacked."""
    n = max(a.num_slots for a in actors_list)

    def pad(x):
        x = np.asarray(x)
        return np.pad(x, [(0, n - x.shape[0])] + [(0, 0)] * (x.ndim - 1))

    return jax.tree.map(lambda *xs: np.stack([pad(x) for x in xs]), *actors_list)


def scene_features(params, cfg: ForecasterConfig, maps, actors_list: Sequence[Actors], egos,
                   batch_size: int = 32) -> np.ndarray:
    """Features [n, D] of n scenes: map rasters [n, G, G, C] (the forecaster's grid's
    channels), numpy Actors per scene, egos (Actors [n])."""
    out = []
    for start in range(0, len(actors_list), batch_size):
        sl = slice(start, start + batch_size)
        actors = stack_actors(actors_list[sl])
        ego = jax.tree.map(lambda x, sl=sl: np.asarray(x)[sl], egos)
        raster = draw_scene_rasters(np.asarray(maps[sl]), actors, ego, cfg.grid)
        out.append(np.asarray(forecast(params, cfg, raster, actors.position, actors.velocity)[0]))
    return np.concatenate(out) if out else np.zeros((0, cfg.feature_size), np.float32)


def features_mmd(real: np.ndarray, generated: np.ndarray, unbiased: bool = False) -> float:
    """MMD^2 between two sets of scene features [m, D] and [n, D] (RBF, bandwidth 1)."""
    return mmd(real, generated, BANDWIDTH, unbiased, kernel=rbf_kernel)


def features_interval(real: np.ndarray, generated: np.ndarray) -> list[float]:
    """The bootstrap interval of `features_mmd` (`eval.mmd.mmd_interval`)."""
    return mmd_interval(real, generated, BANDWIDTH, kernel=rbf_kernel)
