"""Batch likelihood of real scenes (full softmax over locations, no augmentation)."""

from __future__ import annotations

import functools
import sys

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P
from tqdm import tqdm

from scenegen_jax.backend import (
    concurrent_map,
    default_workers,
    free_memory_bytes,
    make_mesh,
    scoring_compiler_options,
)
from scenegen_jax.config import Config, ModelConfig
from scenegen_jax.data.cache import Cache
from scenegen_jax.distributions import TERMS
from scenegen_jax.likelihood.batch import Batch, batch_scenes, check_batch, gather_batch, to_device
from scenegen_jax.likelihood.terms import step_size_measured
from scenegen_jax.likelihood.unroll import unroll_terms
from scenegen_jax.scene import CLASS_NAMES, PEDESTRIAN, STOP


def score_batch(params, batch: Batch, cfg: ModelConfig) -> dict:
    """Per-step NLL terms of a batch: dict term -> [B, T] (nats), plus step class and mask,
    and whether the step's actor had a measured box size (`Actors.size_measured`)."""
    maps, scene = batch_scenes(batch, cfg.grid)
    terms, step_valid, step_cls = unroll_terms(params, cfg, maps, scene, None,
                                               differentiated=False)
    out = {k: -v for k, v in terms.items()}
    out["step_valid"] = step_valid
    out["step_cls"] = step_cls
    out["step_size_measured"] = step_size_measured(scene.actors, step_cls.shape[1])
    return out


@functools.lru_cache(maxsize=4)
def _jitted_scorer(cfg: ModelConfig, mesh):
    data = NamedSharding(mesh, P("data"))
    return jax.jit(
        lambda p, b: score_batch(p, b, cfg),
        in_shardings=(NamedSharding(mesh, P()), data),
        out_shardings=data,
        compiler_options=scoring_compiler_options(),
    )


def _abstract(tree) -> tuple:
    """A hashable (treedef, shapes and dtypes) of a PyTree of arrays."""
    leaves, treedef = jax.tree.flatten(tree)
    return treedef, tuple(jax.ShapeDtypeStruct(np.shape(x), x.dtype) for x in leaves)


@functools.lru_cache(maxsize=8)
def _compiled_scorer(cfg: ModelConfig, mesh, params_spec: tuple, batch_spec: tuple):
    """`_jitted_scorer` compiled for these shapes: its memory is known before it runs
    (`check_call_memory`), and the calls run this program (a jit call would compile again)."""
    params, batch = (jax.tree.unflatten(*spec) for spec in (params_spec, batch_spec))
    return _jitted_scorer(cfg, mesh).lower(params, batch).compile()


def call_scenes(batch_size: int, workers: int, devices: int, scenes: int) -> int:
    """Scenes per call: `batch_size` per device split over `workers` concurrent calls, on
    every device, but no more calls' worth than `scenes` needs (a multiple of `devices`):
    a batch beyond the scenes would only pad them."""
    per_call = max(batch_size // workers, 1) * devices
    return min(per_call, -(-scenes // devices) * devices)


def check_call_memory(compiled, calls: int, batch_size: int, free: int) -> None:
    """Raises ValueError where `calls` concurrent runs of the compiled scorer need more than
    `free` bytes (`memory_analysis`: its temporaries, arguments and outputs on a device);
    no check where the backend does not say."""
    try:
        m = compiled.memory_analysis()
        need = calls * (m.temp_size_in_bytes + m.argument_size_in_bytes
                        + m.output_size_in_bytes)
    except (AttributeError, NotImplementedError, jax.errors.JaxRuntimeError):
        return
    if need > free:
        fits = max(int(batch_size * free / need), 1)
        raise ValueError(f"batch size {batch_size} (--batch-size): {calls} concurrent scoring "
                         f"call(s) need about {need / 2**30:.1f} GiB, {free / 2**30:.1f} GiB "
                         f"free; use a batch size of at most about {fits}")


def score_cache(params, cache: Cache, cfg: Config, batch_size: int = 8, progress: bool = True,
                workers: int | None = None, scenes: range | None = None):
    """Scores every scene of a cache (or the `scenes` range of them), on every local device.

    Each batch of `batch_size` scenes per local device runs as `workers` concurrent calls
    on equal parts of it (`backend.concurrent_map`; default one per core on CPU, 1 on
    accelerators), each call's scenes split over the devices. Every scene's scores are its
    own; a device computes the same groups of scenes whatever the device count, so the
    scores do not change with it, bit for bit. A batch larger than the scenes is cut to
    them (`call_scenes`), and one whose concurrent calls would need more memory than the
    device has free is refused before any scene is scored (`check_call_memory`).

    Returns:
      dict with per-step arrays over the scenes: term -> [S, T] NLL (nats), "step_valid"
      [S, T], "step_cls" [S, T] (STOP at the stop step), "step_size_measured" [S, T] (the
      step's actor had a measured box size; its box NLL is 0 otherwise).
    """
    cache.check_config(cfg)
    scenes = range(len(cache)) if scenes is None else scenes
    if not isinstance(scenes, range) or scenes.step != 1 or not (
            0 <= scenes.start < scenes.stop <= len(cache)):
        raise ValueError(f"scenes {scenes}: a range of step 1 within range({len(cache)}), "
                         "not empty, is needed")
    if batch_size < 1 or (workers is not None and workers < 1):
        raise ValueError(f"batch_size and workers must be >= 1, got {batch_size} and {workers}")
    mesh = make_mesh(jax.local_devices())  # with several processes: this one's devices
    workers = default_workers() if workers is None else workers
    per_call = call_scenes(batch_size, workers, mesh.size, len(scenes))
    params = jax.device_put(params, NamedSharding(mesh, P()))
    template = gather_batch(cache, np.full(per_call, scenes.start), cfg.grid)
    # One program per model, whatever the training settings.
    fn = _compiled_scorer(cfg.model, mesh, _abstract(params), _abstract(template))
    starts = range(scenes.start, scenes.stop, per_call)
    check_call_memory(fn, min(workers, len(starts)), batch_size, free_memory_bytes())
    n = scenes.stop

    def call(start):
        idx = np.arange(start, start + per_call)
        real = idx < n
        idx = np.where(real, idx, scenes.start)  # pad the last call, dropped below
        host = gather_batch(cache, idx, cfg.grid)
        check_batch(host, [cache.scene_name(int(i)) for i in idx])
        out = jax.device_get(fn(params, to_device(host, NamedSharding(mesh, P("data")))))
        return {k: v[real] for k, v in out.items()}

    chunks = list(tqdm(concurrent_map(call, starts, workers), total=len(starts), desc="score",
                       unit="call", file=sys.stderr, disable=not progress))
    return {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}


def actor_steps(scores: dict) -> np.ndarray:
    """[S, T] mask of the steps that place an actor (valid, not the stop token)."""
    return scores["step_valid"] & (scores["step_cls"] < len(CLASS_NAMES))


def complete_scenes(scores: dict) -> np.ndarray:
    """[S] bool: the scene's stop token was scored. False for a scene with more actors in the
    region than the config's max_actors, scored on the first max_actors in canonical order
    (`Scene.complete`)."""
    return np.any(scores["step_valid"] & (scores["step_cls"] == STOP), axis=1)


def box_scored(scores: dict) -> np.ndarray:
    """[S, T] mask of the steps whose box term was scored: actors of a boxed class whose box
    size the source measured (scores of a version without `step_size_measured`: all)."""
    measured = scores.get("step_size_measured", np.ones_like(scores["step_valid"]))
    boxed = (scores["step_cls"] != PEDESTRIAN) & actor_steps(scores)
    return boxed & measured


def summarize_scores(scores: dict) -> dict:
    """Mean scene NLL and mean per-actor NLL by class and by term (paper Table 2 columns),
    and the number of scenes truncated to max_actors (`complete_scenes`). The box term is
    averaged over the actors whose box size was measured (`box_actors_<class>`); the others'
    count is `box_unmeasured_<class>`."""
    total = sum(scores[k] for k in TERMS)
    valid, cls = scores["step_valid"], scores["step_cls"]
    out = {"scenes": int(total.shape[0]), "scene_nll": float(np.mean(np.sum(total, axis=1))),
           "scenes_truncated": int(np.sum(~complete_scenes(scores)))}
    for c, name in enumerate(CLASS_NAMES):
        m = valid & (cls == c)
        count = int(m.sum())
        out[f"actors_{name}"] = count
        out[f"nll_per_{name}"] = float(total[m].sum() / count) if count else None
        for k in TERMS:
            out[f"{k}_nll_per_{name}"] = float(scores[k][m].sum() / count) if count else None
        if c != PEDESTRIAN:
            boxed = m & box_scored(scores)
            out[f"box_actors_{name}"] = int(boxed.sum())
            out[f"box_unmeasured_{name}"] = count - int(boxed.sum())
            out[f"box_nll_per_{name}"] = (float(scores["box"][boxed].sum() / boxed.sum())
                                          if boxed.any() else None)
    actor = actor_steps(scores)
    out["nll_per_actor"] = float(total[actor].sum() / max(actor.sum(), 1))
    return out


def source_slices(cache) -> list[tuple[str, slice]]:
    """(label, scene slice) of each cache of a `CacheUnion` (one, unlabelled: "all")."""
    labels = getattr(cache, "labels", None) or ["all"]
    offsets = getattr(cache, "offsets", (0, len(cache)))
    return [(name, slice(int(a), int(b)))
            for name, a, b in zip(labels, offsets[:-1], offsets[1:], strict=True)]


def summarize_by_source(scores: dict, cache) -> dict:
    """`summarize_scores` of each source (cache) of a `CacheUnion`, by its label; `scores`
    must hold every scene of `cache` (`score_cache` without `scenes`)."""
    rows = len(scores["step_valid"])
    if rows != len(cache):
        raise ValueError(f"scores of {rows} scenes for a cache of {len(cache)}: every scene's "
                         "are needed to split them by source")
    return {name: summarize_scores({k: v[s] for k, v in scores.items()})
            for name, s in source_slices(cache)}


def worst_scenes(scores: dict, k: int) -> list[tuple[int, int, float, dict]]:
    """The k scenes with the highest NLL per actor, most unlikely first (paper Figure 5).

    Returns (scene index, step of its most unlikely actor, scene NLL per actor, that actor's
    NLL by term) per scene; the step indexes the scene's actors in canonical order. Scenes
    without actors are skipped.
    """
    total = sum(scores[k_] for k_ in TERMS)
    actor = actor_steps(scores)
    counts = actor.sum(1)
    per_actor = np.where(counts > 0, (total * scores["step_valid"]).sum(1) / np.maximum(counts, 1),
                         -np.inf)
    out = []
    for i in np.argsort(-per_actor, kind="stable")[:k]:
        if counts[i] == 0:
            break
        step = int(np.argmax(np.where(actor[i], total[i], -np.inf)))
        terms = {k_: float(scores[k_][i, step]) for k_ in TERMS}
        out.append((int(i), step, float(per_actor[i]), terms))
    return out
