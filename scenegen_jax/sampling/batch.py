"""Many scenes at once: keys per scene, batches of `rollout` in one compiled call, and
concurrent calls on parts of a batch.

One key scheme everywhere: scene i of a request with key k uses `scene_key(k, i)`, so a seed
and a scene index give the same scene through `sample_scenes`, `scenegen sample` and
`scenegen evaluate`, whatever the batch size.
"""

from __future__ import annotations

import dataclasses
import functools
import numbers
from collections.abc import Iterator, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from scenegen_jax.backend import (
    concurrent_map,
    default_parallel,
    default_workers,
    make_mesh,
    sampling_compiler_options,
)
from scenegen_jax.config import Config, ModelConfig
from scenegen_jax.raster.jax_map import draw_maps
from scenegen_jax.sampling.model import Model, NetworkModel
from scenegen_jax.sampling.rollout import (
    DEFAULT_OPTIONS,
    Sample,
    SamplerOptions,
    pad_given,
    rollout,
)
from scenegen_jax.scene import NUM_CLASSES, Actors, empty_actors, tree_take


@jax.jit
def _fold_in_each(key: jax.Array, index: jax.Array) -> jax.Array:
    return jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, index.ravel()).reshape(
        index.shape
    )


SEED_LIMIT = 2**32  # jax.random.key keeps a seed's low 32 bits: others repeat a seed below


def seed_key(seed: int) -> jax.Array:
    """`jax.random.key(seed)` of an integer seed in [0, 2^32); any other seed is refused, as
    JAX would give it the key of another seed (2^32 that of 0, -1 that of 2^32 - 1)."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not (
            0 <= seed < SEED_LIMIT):
        raise ValueError(f"seed: an integer in [0, 2**32) is needed, got {seed!r}")
    return jax.random.key(int(seed))


def scene_key(key: jax.Array, index) -> jax.Array:
    """The key of scene `index` (int or int array) of a request made with `key` (a typed key,
    `jax.random.key`; a legacy uint32 [2] key of `jax.random.PRNGKey` is the same key)."""
    if not jax.dtypes.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
        key = jax.random.wrap_key_data(jnp.asarray(key, jnp.uint32))
    return _fold_in_each(key, jnp.asarray(index))


def scene_keys(key: jax.Array, num_maps: int, num_per_map: int, first: int = 0) -> jax.Array:
    """[B, S] keys: scene (b, s) is scene `first + b * S + s` (`scene_key`)."""
    index = first + np.arange(num_maps * num_per_map).reshape(num_maps, num_per_map)
    return scene_key(key, index)


def _sample_batch(keys, params, maps, egos, given, caps, temperature, *, cfg: ModelConfig,
                  options: SamplerOptions, model: Model | None) -> Sample:
    b, s = keys.shape[:2]
    parallel = default_parallel() if options.parallel is None else options.parallel
    if model is None:
        model = NetworkModel(cfg, single_example=parallel == 1)

    def one(key, map_raster, ego, g, c):
        return rollout(key, params, map_raster, ego, cfg, g, c, options, model, temperature)

    if b * s == 1:  # one scene (each call on CPU): no vmap, whose batching of the while loops
        # traces their bodies several times over
        out = one(keys[0, 0], maps[0], tree_take(egos, 0), tree_take(given, 0), caps[0])
        return jax.tree.map(lambda x: x[None, None], out)
    if parallel >= b * s:
        per_map = jax.vmap(one, in_axes=(0, None, None, None, None))
        return jax.vmap(per_map)(keys, maps, egos, given, caps)

    impl = jax.random.key_impl(keys)

    def flat(x):  # scene (b, s) -> index b * S + s
        key, i = x
        key = jax.random.wrap_key_data(key, impl=impl)
        return one(key, maps[i], tree_take(egos, i), tree_take(given, i), caps[i])

    # Groups of `parallel` scenes; the last group is padded with copies of the last scene.
    n = b * s
    groups = -(-n // parallel)
    scene = jnp.minimum(jnp.arange(groups * parallel, dtype=jnp.int32), n - 1)
    data = jax.random.key_data(keys)  # raw key data: typed keys do not pass through lax.map
    data = data.reshape(n, *data.shape[2:])[scene]
    if parallel == 1:
        out, lead = lax.map(flat, (data, scene // s)), 1
    else:
        grouped = (data.reshape(groups, parallel, *data.shape[1:]),
                   (scene // s).reshape(groups, parallel))
        out, lead = lax.map(jax.vmap(flat), grouped), 2

    def unflat(x):  # [groups (, parallel), ...] -> [B, S, ...]
        rest = x.shape[lead:]
        return x.reshape(groups * parallel, *rest)[:n].reshape(b, s, *rest)

    return jax.tree.map(unflat, out)


@functools.cache
def jitted_sampler():
    """`_sample_batch` jitted (cfg, options and model static; the location temperature an
    argument) with the backend's sampling compiler options; made on first use, so that
    importing this module leaves the backend uninitialised (`jax.distributed` must start
    first)."""
    return jax.jit(_sample_batch, static_argnames=("cfg", "options", "model"),
                   compiler_options=sampling_compiler_options())


def sample_batch(
    keys: jax.Array,
    params: Any,
    maps: jnp.ndarray,
    egos: Actors,
    given: Actors,
    caps: jnp.ndarray,
    *,
    cfg: ModelConfig,
    options: SamplerOptions = DEFAULT_OPTIONS,
    model: Model | None = None,
) -> Sample:
    """One compiled call for a batch: scene (b, s) is `rollout(keys[b, s], params, maps[b],
    ...)`. Compiled once per (model config, options, model, shapes); the location
    temperature is passed as an array, so that every temperature runs the same program.

    The B x S scenes run `options.parallel` at a time under vmap (`lax.map` over groups); a
    vmapped group runs until its longest scene is done. With parallel = 1 each scene runs on
    its own (no vmap), which is fastest on CPU: there a vmapped group's activations leave the
    cache and its convolutions slow down more than batching gains.

    Args:
      keys: [B, S] keys; S samples per map share its map, ego, given actors and caps.
      params: network parameters.
      maps: float32 [B, H, W, Cm].
      egos: Actors [B].
      given: Actors [B, N] (all invalid for none).
      caps: int32 [B, 3].
      cfg, options, model: as in `rollout` (static).

    Returns:
      Sample with leading axes [B, S].
    """
    temperature = np.float32(options.location_temperature)
    options = dataclasses.replace(options, location_temperature=1.0)  # the static part
    return jitted_sampler()(keys, params, maps, egos, given, caps, temperature,
                            cfg=cfg, options=options, model=model)


def sample_split(keys: jax.Array, params: Any, maps, egos: Actors, given: Actors, caps, *,
                 cfg: ModelConfig, options: SamplerOptions = DEFAULT_OPTIONS,
                 model: Model | None = None, workers: int | None = None) -> Sample:
    """`sample_batch(keys, params, maps, egos, given, caps, ...)` as `workers` concurrent
    calls on equal parts of the batch (`backend.concurrent_map`); each scene depends only on
    its own key and inputs, so the scenes are those of a single call.

    The batch is split along the maps axis B when B >= workers (or S = 1), else along the
    samples axis S. Where scenes run one at a time (`options.parallel` 1, the CPU default)
    each call takes one map (or sample), so every scene runs the same compiled program
    whatever the batch size and a scene is bit for bit the same in any batch; otherwise the
    parts are equal, the last padded with copies of the last map (or key), so that one
    compilation serves all (the padding's scenes are dropped).

    Every local device works: call c runs on device c mod D, and a batch left whole (one
    call, the accelerator default) has its maps split over the devices (a `data` mesh).
    Scenes run one at a time are never left whole: a batch of one scene on several devices
    would otherwise run, padded, as a sharded program of its own, whose rounding differs
    (a float step in a box size). Each scene is the same on any number of devices with the
    same threads (XLA:CPU splits loops by its thread pool, whose size is the larger of the
    cores and the devices: docs/scaling.md, Determinism).

    Args:
      keys, params, maps, egos, given, caps, cfg, options, model: as in `sample_batch`.
      workers: concurrent calls (threads); default `backend.default_workers()` (one
        per core on CPU, 1 on accelerators).

    Returns:
      Sample with leading axes [B, S].
    """
    kwargs = {"cfg": cfg, "options": options, "model": model}
    devices = jax.local_devices()
    workers = default_workers() if workers is None else workers
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    b, s = keys.shape[:2]
    axis = 0 if b >= workers or s == 1 else 1
    n = (b, s)[axis]
    size = -(-n // min(workers, n))
    one_per_call = (default_parallel() if options.parallel is None else options.parallel) == 1
    if one_per_call:
        size = 1  # one map (or sample) per call: one program for every scene, any batch size
    parts = -(-n // size)
    if parts == 1 and not one_per_call:
        return _sharded_call(keys, params, (maps, egos, given, caps), devices, kwargs)
    index = np.minimum(np.arange(parts * size), n - 1).reshape(parts, size)
    # Parts are cut and joined on the host (numpy): no compiled program per input's shape.
    impl = jax.random.key_impl(keys)
    host = jax.tree.map(np.asarray, (jax.random.key_data(keys), maps, egos, given, caps))

    # Call c runs on local device c mod D, with the parameters put there once.
    on_device = [params] if len(devices) == 1 else [jax.device_put(params, d) for d in devices]

    def call(job):
        c, i = job
        d = c % len(devices)
        part = (jax.tree.map(lambda x: x[i], host) if axis == 0
                else (host[0][:, i], *host[1:]))
        key_data, *per_map = jax.device_put(part, devices[d])
        return sample_batch(jax.random.wrap_key_data(key_data, impl=impl), on_device[d],
                            *per_map, **kwargs)

    outs = list(concurrent_map(call, enumerate(index), workers))
    keep = (slice(0, n),) if axis == 0 else (slice(None), slice(0, n))
    return jax.tree.map(lambda *x: jnp.asarray(np.concatenate(x, axis=axis)[keep]), *outs)


def _sharded_call(keys, params, per_map, devices, kwargs) -> Sample:
    """`sample_batch` of a whole batch in one call, its maps split over `devices` (a `data`
    mesh; the batch padded with copies of its last map to a multiple of their number)."""
    if len(devices) == 1:
        return sample_batch(keys, params, *per_map, **kwargs)
    b = keys.shape[0]
    pad = np.minimum(np.arange(-(-b // len(devices)) * len(devices)), b - 1)
    mesh = make_mesh(devices)
    data, replicated = NamedSharding(mesh, P("data")), NamedSharding(mesh, P())
    keys, per_map = jax.device_put((keys[pad], jax.tree.map(lambda x: x[pad], per_map)), data)
    out = sample_batch(keys, jax.device_put(params, replicated), *per_map, **kwargs)
    return jax.tree.map(lambda x: x[:b], out)


def batch_inputs(cfg: Config, num_maps: int, given: Actors | None = None, caps=None):
    """(given Actors [B, N], caps int32 [B, 3]) for `sample_batch` from optional inputs.

    `given` may be None, Actors [G] (shared by all maps) or Actors [B, G]; `caps` None, [3]
    or [B, 3]. Given actors' `size_measured` is dropped: a sampled scene's boxes are the
    sampler's, whether the given ones were measured or not.
    """
    n = cfg.grid.max_actors
    if given is None:  # numpy: no compiled program
        given = jax.tree.map(lambda x: np.broadcast_to(x, (num_maps, *x.shape)), empty_actors(n))
    else:
        given = jax.tree.map(jnp.asarray, given.replace(size_measured=None))
        if given.cls.ndim == 1:
            given = jax.tree.map(lambda x: jnp.broadcast_to(x, (num_maps, *x.shape)), given)
        given = jax.vmap(lambda g: pad_given(g, n))(given)
    caps = np.full((NUM_CLASSES,), n) if caps is None else np.asarray(caps)
    if caps.shape not in ((NUM_CLASSES,), (num_maps, NUM_CLASSES)) or not (
            np.issubdtype(caps.dtype, np.integer) and (caps >= 0).all()):
        raise ValueError(f"caps: integers >= 0 of shape [{NUM_CLASSES}] or [{num_maps}, "
                         f"{NUM_CLASSES}] (one per class) are needed, got {caps.tolist()}")
    return given, np.broadcast_to(caps.astype(np.int32), (num_maps, NUM_CLASSES))


def sample_scenes(
    key: jax.Array,
    params: Any,
    cfg: Config,
    maps: jnp.ndarray,
    egos: Actors,
    given: Actors | None = None,
    num_per_map: int = 1,
    caps=None,
    *,
    first: int = 0,
    options: SamplerOptions = DEFAULT_OPTIONS,
    model: Model | None = None,
    workers: int | None = None,
) -> Sample:
    """Samples `num_per_map` scenes for each of B maps (`sample_split`).

    Scene (b, s) is scene number `first + b * S + s` of the request: `rollout(scene_key(key,
    first + b * S + s), params, maps[b], egos[b], ...)` bit for bit, so the same key and
    scene number give the same scene in any batch.

    Args:
      key: PRNG key of the request.
      params: network parameters.
      cfg: config.
      maps: float32 [B, H, W, Cm] map channels.
      egos: Actors [B].
      given: optional Actors [G] (shared) or [B, G] to condition on (see `rollout`).
      num_per_map: S, samples per map.
      caps: optional int32 [3] or [B, 3] per-class caps.
      first: number of this call's first scene within the request.
      options, model: see `rollout`.
      workers: concurrent calls, see `sample_split`.

    Returns:
      Sample with leading axes [B, S].
    """
    b = maps.shape[0]
    h = cfg.grid.grid_size
    if maps.ndim != 4 or tuple(maps.shape[1:]) != (h, h, len(cfg.grid.map_channels)):
        raise ValueError(f"maps: shape {tuple(maps.shape)}, config {cfg.name!r} needs [B, {h}, "
                         f"{h}, {len(cfg.grid.map_channels)}] (`raster.jax_map.draw_maps` draws "
                         "them from vector maps)")
    if np.shape(egos.cls)[:1] != (b,):
        raise ValueError(f"egos: {np.shape(egos.cls)[:1]} rows for {b} maps")
    if num_per_map < 1:
        raise ValueError(f"num_per_map must be >= 1, got {num_per_map}")
    given, caps = batch_inputs(cfg, b, given, caps)
    if options.proposals is None:
        options = dataclasses.replace(options, proposals=cfg.sample.proposals)
    return sample_split(scene_keys(key, b, num_per_map, first), params, maps, egos, given, caps,
                        cfg=cfg.model, options=options, model=model, workers=workers)


@dataclasses.dataclass
class CacheScene:
    """One scene sampled on a cache scene's map and ego (numpy arrays).

    index: the scene's number k in the request (its key is `scene_key(key, k)`).
    map_index: the cache scene whose map and ego condition it.
    map_raster: float32 [H, W, Cm] that map, cropped (no rotation).
    ego, actors: Actors (unbatched) and Actors [N].
    num_given, stop_reason, rejected, heatmaps, heatmap_cls: as in `Sample`.
    """

    index: int
    map_index: int
    map_raster: np.ndarray
    ego: Actors
    actors: Actors
    num_given: int
    stop_reason: int
    rejected: int
    heatmaps: np.ndarray
    heatmap_cls: np.ndarray


def sample_on_cache(
    params: Any,
    cfg: Config,
    cache,
    num: int,
    seed: int,
    *,
    indices: Sequence[int] | None = None,
    given: Sequence[Actors] = (),
    caps=None,
    batch_size: int = 8,
    options: SamplerOptions = DEFAULT_OPTIONS,
    scenes: range | None = None,
) -> Iterator[CacheScene]:
    """Samples `num` scenes on the maps and egos of a cache (a `Cache` or `CacheUnion`), in
    batches of `batch_size`, and yields them in order; with `scenes`, only those of the
    `num` (e.g. one process's share).

    Scene k uses cache scene `indices[k % len(indices)]` (default: every scene in order),
    given actors `given[k % len(given)]` (numpy Actors [N] each; none by default) and key
    `scene_key(jax.random.key(seed), k)`: the scenes do not depend on the batch size.
    """
    if num < 1 or batch_size < 1:
        raise ValueError(f"num and batch_size must be >= 1, got {num} and {batch_size}")
    scenes = range(num) if scenes is None else scenes
    if scenes.step != 1 or not 0 <= scenes.start <= scenes.stop <= num:
        raise ValueError(f"scenes {scenes} is not a contiguous part of range({num})")
    cache.check_config(cfg)
    key = seed_key(seed)
    indices = list(range(len(cache))) if indices is None else list(indices)
    if not indices or not all(isinstance(i, numbers.Integral) and not isinstance(i, bool)
                              and 0 <= i < len(cache) for i in indices):
        raise ValueError(f"indices: {len(indices)} scene numbers, each an integer in "
                         f"[0, {len(cache)}) of the cache, are needed")
    indices = [int(i) for i in indices]
    if isinstance(given, Actors):
        raise ValueError("given: a sequence of Actors, one set per scene (e.g. [actors])")
    # Checked above (the caps by each batch's `sample_scenes`), sampled below: a generator's
    # body would run only when first iterated.
    return _sample_on_cache(params, cfg, cache, key, scenes, indices, given, caps, batch_size,
                            options)


def _sample_on_cache(params, cfg: Config, cache, key, scenes: range, indices: list[int], given,
                     caps, batch_size: int, options: SamplerOptions) -> Iterator[CacheScene]:
    maps: dict[int, np.ndarray] = {}

    def map_of(i: int) -> np.ndarray:
        if i not in maps:
            drawn = draw_maps([cache.map_store.frame_map(i)], np.zeros(1), cfg.grid)
            maps[i] = np.asarray(drawn[0])
        return maps[i]

    for start in range(scenes.start, scenes.stop, batch_size):
        ks = np.minimum(np.arange(start, start + batch_size), scenes.stop - 1)  # padded
        map_ids = [indices[k % len(indices)] for k in ks]
        egos = cache.ego(np.asarray(map_ids))
        rows = None
        if given:
            rows = jax.tree.map(lambda *x: np.stack(x), *[given[k % len(given)] for k in ks])
        sample = sample_scenes(key, params, cfg, np.stack([map_of(i) for i in map_ids]), egos,
                               rows, 1, caps, first=start, options=options)
        sample = jax.tree.map(lambda x: x[:, 0], jax.device_get(sample))
        for j in range(min(batch_size, scenes.stop - start)):
            row = jax.tree.map(lambda x, j=j: x[j], sample)
            yield CacheScene(start + j, map_ids[j], map_of(map_ids[j]), tree_take(egos, j),
                             row.actors, int(row.num_given), int(row.stop_reason),
                             int(row.rejected), row.heatmaps, row.heatmap_cls)
