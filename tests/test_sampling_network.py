"""Scenes sampled from the real network (tiny config, random parameters biased to crowded
scenes): the sampler's guarantees, reproducibility, the local actor gates, given actors,
batches against single calls, the order channel as training sees it, and the library's
argument checks.

Compile budget (XLA:CPU compiles of the rollout take 10-30 s here): one compile of the real
network at [B, S] = [2, 2] and one at [1, 1], which the CLI test (test_sampling_cli.py)
reuses in the same process (same config, proposals, heatmap steps and shapes).
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sampling_helpers import (
    TINY,
    K,
    bins_of,
    overlapping_pairs,
    slot,
    write_val_cache,
)

from scenegen_jax.config import get_config
from scenegen_jax.sampling import (
    HEATMAP_STEPS,
    MAX_SIZE_M,
    MAX_SPEED_MPS,
    MIN_SIZE_M,
    NetworkModel,
    SamplerOptions,
    batch_inputs,
    sample_batch,
    sample_scenes,
    scene_keys,
)
from scenegen_jax.sampling.batch import jitted_sampler
from scenegen_jax.scene import (
    PEDESTRIAN,
    Actors,
    Scene,
    bin_index,
    in_region,
)
from scenegen_jax.train.step import init_state


@pytest.fixture(scope="module")
def val_cache(tmp_path_factory, data_root):
    """A tiny-config cache of every 20th validation frame (8 scenes)."""
    return write_val_cache(str(tmp_path_factory.mktemp("cache_val_tiny")), data_root)


@pytest.fixture(scope="module")
def real_inputs(val_cache):
    """Network params that make long, crowded scenes, and maps/egos of 2 val scenes.

    Randomly initialised, with the class bias set so that stop is rare and the box means set
    to ~2 m x 4.5 m, so collision rejection is exercised."""
    from scenegen_jax.likelihood.batch import grid_scene

    # init_state, as the CLI's checkpoint template uses: its eager op compiles are shared.
    params = jax.tree.map(np.asarray, init_state(TINY).params)
    params["class_mlp2"]["bias"] = np.array([2.0, 0.5, 0.5, -3.0], np.float32)
    bias = params["box2_b"].copy()  # [classes, box parameters]
    mu = np.log(np.array([[2.0, 4.5], [0.6, 0.6], [0.7, 1.8]]))
    bias[:, K:3 * K] = np.repeat(mu, K, axis=0).reshape(3, K, 2).reshape(3, 2 * K)
    params["box2_b"] = bias
    maps = np.stack([grid_scene(val_cache, i, TINY.grid)[0] for i in (0, 4)])
    return params, maps, val_cache.ego(np.array([0, 4]))


def run_real(params, maps, egos, key, given=None, caps=None, num_per_map=2, parallel=None,
             workers=1):
    options = SamplerOptions(parallel=parallel)
    return jax.tree.map(np.asarray, sample_scenes(key, params, TINY, maps, egos, given,
                                                  num_per_map, caps, options=options,
                                                  workers=workers))


def check_scene(actors: Actors, ego: Actors, cfg, caps=None):
    """The sampler's guarantees for one scene."""
    for name in ("position", "size", "heading", "velocity"):
        assert np.all(np.isfinite(getattr(actors, name))), name
    n = int(actors.valid.sum())
    assert np.all(actors.valid[:n]) and not np.any(actors.valid[n:])
    Scene(actors=actors, ego=ego).validate(cfg.grid, "sampled")  # region, canonical order, values
    pos = actors.position[:n]
    assert np.all(np.asarray(in_region(jnp.asarray(pos), cfg.grid)))
    assert np.all(np.diff(bins_of(actors, cfg)[:n]) >= 0)
    assert overlapping_pairs(actors, ego) == []
    boxed = actors.valid & (actors.cls != PEDESTRIAN)
    assert np.all((actors.size[boxed] >= MIN_SIZE_M) & (actors.size[boxed] <= MAX_SIZE_M))
    assert np.all(np.hypot(*actors.velocity[:n].T) <= MAX_SPEED_MPS * (1 + 1e-5))
    if caps is not None:
        assert np.all(np.bincount(actors.cls[:n], minlength=3) <= caps)
    return n


def test_real_network_scene_properties_and_reproducibility(real_inputs):
    params, maps, egos = real_inputs
    key = jax.random.key(7)
    out = run_real(params, maps, egos, key)
    compiled = jitted_sampler()._cache_size()
    again = run_real(params, maps, egos, key)
    jax.tree.map(np.testing.assert_array_equal, out, again)  # same key: bit for bit
    other = run_real(params, maps, egos, jax.random.key(8))
    assert not np.array_equal(out.actors.position, other.actors.position)
    assert not np.array_equal(out.actors.position[0, 0], out.actors.position[0, 1])  # per key

    caps = np.array([6, 3, 2])
    capped = run_real(params, maps, egos, jax.random.key(9), caps=caps)
    assert jitted_sampler()._cache_size() == compiled  # new keys and caps: no recompile
    counts, reasons, rejected = [], collections.Counter(), 0
    for sample, c in ((out, None), (other, None), (capped, caps)):
        for b in range(2):
            for s in range(2):
                counts.append(check_scene(slot(sample.actors, b, s), slot(egos, b), TINY, c))
                reasons[int(sample.stop_reason[b, s])] += 1
                rejected += int(sample.rejected[b, s])
    # The biased network makes crowded scenes that exercise rejection.
    assert sum(counts) >= 100 and rejected > 0, (counts, rejected, reasons)


@dataclasses.dataclass(frozen=True)
class FullGridActorGates(NetworkModel):
    """The network with the actor gates recomputed over the whole grid at every step."""

    def next_actor_gates(self, params, gates, before, after, position):
        return self.actor_gates(params, after)


def test_real_network_local_actor_gates_equal_full_grid(real_inputs):
    # TINY's drawing window (11 px + 2 x 2 px margins) is smaller than its 32 px grid, so
    # the rollout updates the actor gates locally; recomputing them in full gives the same scenes.
    params, maps, egos = real_inputs
    key = jax.random.key(5)
    local = run_real(params, maps, egos, key)
    full = jax.tree.map(np.asarray, sample_scenes(key, params, TINY, maps, egos, num_per_map=2,
                                                  model=FullGridActorGates(TINY.model)))
    assert local.actors.valid.sum() >= 20
    np.testing.assert_array_equal(local.actors.cls, full.actors.cls)
    np.testing.assert_array_equal(local.actors.valid, full.actors.valid)
    np.testing.assert_array_equal(bins_of(local.actors, TINY), bins_of(full.actors, TINY))
    np.testing.assert_allclose(local.actors.size, full.actors.size, rtol=1e-5, atol=1e-5)


def test_real_network_given_actors_and_batch_equals_single_calls(real_inputs, val_cache):
    params, maps, egos = real_inputs
    from scenegen_jax.data.cache import cached_scene
    from scenegen_jax.scene import canonical_order

    # Condition on the first three real actors (canonical order) of val scene 0.
    _, actors, _ = cached_scene(val_cache, 0, TINY)
    actors = actors.replace(valid=actors.valid & np.asarray(in_region(actors.position, TINY.grid)))
    real = jax.tree.map(np.asarray, canonical_order(actors, TINY.grid))
    g = min(3, int(real.valid.sum()))
    given = jax.tree.map(lambda x: x[: TINY.grid.max_actors].copy(), real)
    given.valid[g:] = False
    given = jax.tree.map(lambda x: x.astype(np.asarray(x).dtype), given)
    given_b = jax.tree.map(lambda x: np.stack([x, x]), given)
    key = jax.random.key(11)
    out = run_real(params, maps, egos, key, given=given_b)
    for b in range(2):
        for s in range(2):
            a = slot(out.actors, b, s)
            check_scene(a, slot(egos, b), TINY)
            assert int(out.num_given[b, s]) == g
            for field in ("cls", "position", "size", "heading", "velocity", "valid"):
                np.testing.assert_array_equal(getattr(a, field)[:g], getattr(given, field)[:g])

    # Each scene of the [2, 2] batch equals a single-scene call with its key, whether the
    # scenes run one by one (the CPU default), three at a time (the last group padded) or all
    # four vmapped, and whether the batch runs as one call or as concurrent calls on parts
    # split along the maps (2 workers) or the samples (3 workers > 2 maps). The
    # discrete outcome is identical; floats may differ in the last bits (XLA vectorises the
    # attribute MLP and mixture math differently at other batch shapes; positions are
    # bin-corner + offset - half region, whose cancellation leaves ~1e-5 m).
    keys = scene_keys(key, 2, 2)
    given_one, caps_one = batch_inputs(TINY, 1, given)
    batches = [out] + [run_real(params, maps, egos, key, given=given_b, parallel=p)
                       for p in (3, 4)]
    batches += [run_real(params, maps, egos, key, given=given_b, workers=w) for w in (2, 3)]
    for b, s in itertools.product(range(2), range(2)):
        one = sample_batch(keys[b:b + 1, s:s + 1], params, maps[b:b + 1],
                           jax.tree.map(lambda x, b=b: x[b:b + 1], egos), given_one, caps_one,
                           cfg=TINY.model,
                           options=SamplerOptions(heatmap_steps=HEATMAP_STEPS,
                                                  proposals=TINY.sample.proposals))
        one = jax.tree.map(lambda x: np.asarray(x)[0, 0], one)
        for batch in batches:
            want = slot(batch, b, s)
            for field in ("cls", "valid"):
                np.testing.assert_array_equal(getattr(one.actors, field),
                                              getattr(want.actors, field))
            np.testing.assert_array_equal(bins_of(one.actors, TINY), bins_of(want.actors, TINY))
            for field in ("position", "size", "heading", "velocity"):
                np.testing.assert_allclose(getattr(one.actors, field),
                                           getattr(want.actors, field), rtol=1e-5, atol=1e-4)
            assert int(one.stop_reason) == int(want.stop_reason)


def test_real_network_order_channel_is_the_one_training_sees(real_inputs):
    """With `order_channel` the sampler gives the network the canonical order's channel of
    the previous actor's bin, as the teacher-forced unroll does: the distribution each step's
    location is drawn from is the plain reference's location softmax after the same actors,
    renormalised over the bins the order allows."""
    from reference_unroll import reference_location_logits

    _, maps, egos = real_inputs
    cfg = TINY.replace(order_channel=True, attribute_map_input=True)
    params = jax.tree.map(np.asarray, init_state(cfg).params)
    params["class_mlp2"]["bias"] = np.array([3.0, 0.0, 0.0, -3.0], np.float32)  # rarely stop
    w = params["loc2_w"]  # zero at initialisation: flat logits
    params["loc2_w"] = np.random.default_rng(0).normal(size=w.shape).astype(w.dtype) / 2.0
    steps = (0, 1, 2, 3)
    out = jax.tree.map(np.asarray, sample_scenes(
        jax.random.key(4), params, cfg, maps[:1], jax.tree.map(lambda x: x[:1], egos),
        num_per_map=1, options=SamplerOptions(heatmap_steps=steps)))
    actors = jax.tree.map(lambda x: jnp.asarray(x[0]), out.actors)  # [1, N]
    ego = jax.tree.map(lambda x: jnp.asarray(x[:1]), egos)
    assert int(actors.valid.sum()) > steps[-1]
    bins = np.asarray(bin_index(actors.position[0], cfg.grid))
    no_order = {**params, "lstm1_order": np.zeros_like(params["lstm1_order"])}
    for k in steps:
        first_k = actors.replace(valid=actors.valid & (jnp.arange(cfg.grid.max_actors) < k))
        scene = Scene(actors=first_k, ego=ego)
        cls = jnp.asarray(out.heatmap_cls[0, 0, k])[None]
        allowed = jnp.arange(cfg.grid.grid_size**2) >= (bins[k - 1] if k else 0)
        want = []
        for p in (params, no_order):
            logits = reference_location_logits(p, cfg, jnp.asarray(maps[:1]), scene, k, cls)[0]
            want.append(np.asarray(jax.nn.softmax(jnp.where(allowed, logits, -jnp.inf))))
        np.testing.assert_allclose(out.heatmaps[0, 0, k], want[0], rtol=1e-4, atol=1e-6)
        if k:  # the channel matters once an actor has been placed
            assert np.abs(want[0] - want[1]).max() > 1e-3


def test_library_calls_check_their_arguments_before_any_work(val_cache, data_root, tmp_path):
    """The Python API refuses what the command line refuses, at the call: a cache of another
    grid (read at the wrong scale before), a seed JAX would fold onto another (2^32 gave seed
    0's scenes), scene numbers outside the cache, maps larger than the grid, an empty
    request."""
    from scenegen_jax.eval.evaluate import evaluate
    from scenegen_jax.eval.nll import score_cache
    from scenegen_jax.model.network import init_params
    from scenegen_jax.sampling.batch import (
        sample_on_cache,
        sample_scenes,
        scene_keys,
        seed_key,
    )
    from scenegen_jax.scene import empty_actors, tree_take
    from scenegen_jax.viz.render import render_scene

    params = init_params(TINY.model, jax.random.key(0))
    cpu = get_config("cpu")
    for bad in (2**32, -1, 1.5, True, "3"):
        with pytest.raises(ValueError, match=r"seed: an integer in \[0, 2\*\*32\)"):
            seed_key(bad)
    assert np.array_equal(jax.random.key_data(seed_key(np.uint32(7))),
                          jax.random.key_data(jax.random.key(7)))

    def refused(match, fn, *args, **kwargs):
        with pytest.raises(ValueError, match=match):
            fn(*args, **kwargs)

    refused("field grid_size: cache has 32, config 'cpu' wants 64", sample_on_cache,
            params, cpu, val_cache, 1, 0)
    refused("seed", sample_on_cache, params, TINY, val_cache, 1, 2**32)
    for indices in ([len(val_cache)], [], [-1]):
        refused("indices", sample_on_cache, params, TINY, val_cache, 1, 0, indices=indices)
    refused("given: a sequence of Actors", sample_on_cache, params, TINY, val_cache, 1, 0,
            given=empty_actors(2))
    egos = val_cache.ego(np.arange(2))
    refused(r"maps: shape \(2, 48, 48, 15\), config .tiny. needs \[B, 32, 32", sample_scenes,
            jax.random.key(0), params, TINY, np.zeros((2, 48, 48, 15), np.float32), egos)
    h = TINY.grid.grid_size
    cropped = np.zeros((2, h, h, len(TINY.grid.map_channels)), np.float32)
    refused(
        r"egos: \(2,\) rows for 3 maps",
        sample_scenes,
        jax.random.key(0),
        params,
        TINY,
        np.concatenate([cropped, cropped[:1]]),
        egos,
    )
    refused(
        "num_per_map must be >= 1",
        sample_scenes,
        jax.random.key(0),
        params,
        TINY,
        cropped,
        egos,
        num_per_map=0,
    )
    for caps in ([-1, 5, 5], [1, 1], [1.5, 2, 2]):
        refused(
            "caps: integers >= 0 of shape",
            sample_scenes,
            jax.random.key(0),
            params,
            TINY,
            cropped,
            egos,
            caps=caps,
        )
    # A legacy uint32 key (jax.random.PRNGKey) is the same key as jax.random.key's.
    assert np.array_equal(
        jax.random.key_data(scene_keys(jax.random.PRNGKey(3), 2, 2)),
        jax.random.key_data(scene_keys(jax.random.key(3), 2, 2)),
    )

    refused("field grid_size", score_cache, params, val_cache, cpu)
    n = len(val_cache)
    for scenes in (range(0, n, 2), range(4, 2), range(0, n + 1), range(-1, 2)):
        refused(r"scenes range", score_cache, params, val_cache, TINY, scenes=scenes)
    refused(
        "batch_size and workers must be >= 1", score_cache, params, val_cache, TINY, batch_size=0
    )
    refused("batch_size and workers must be >= 1", score_cache, params, val_cache, TINY, workers=0)
    refused("num_scenes must be >= 1", evaluate, params, TINY, val_cache, val_cache, 0, 0)
    refused("seed", evaluate, params, TINY, val_cache, val_cache, 2, -1)

    options = SamplerOptions(
        location_temperature=np.float32(0.5), proposals=np.int64(5), heatmap_steps=[0, 5]
    )
    assert (options.location_temperature, options.proposals, options.heatmap_steps) == (
        0.5,
        5,
        (0, 5),
    )
    assert type(options.location_temperature) is float and type(options.proposals) is int
    for steps in ((-1,), 3, (True,)):
        refused("heatmap_steps must be integers >= 0", SamplerOptions, heatmap_steps=steps)

    from scenegen_jax.data.sources import source_spec
    from scenegen_jax.data.union import load_union
    from scenegen_jax.eval.nll import summarize_by_source

    for stride in (2.5, True, 0):
        refused("stride must be an integer >= 1", source_spec, "av2", data_root, "val", stride)
    assert len(load_union(pathlib.Path(val_cache.path))) == len(val_cache)
    refused(
        f"scores of 2 scenes for a cache of {n}",
        summarize_by_source,
        {"step_valid": np.zeros((2, 3), bool)},
        val_cache,
    )
    refused(
        r"map_raster: shape \(48, 48, 15\)",
        render_scene,
        str(tmp_path / "x.png"),
        np.zeros((48, 48, 15), np.float32),
        TINY.grid.map_channels,
        empty_actors(1),
        tree_take(egos, 0),
        TINY,
    )
