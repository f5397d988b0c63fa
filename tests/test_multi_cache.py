"""Training and scoring on several caches at once: weighted draws, a data order that is a
function of (seed, step), compatibility checks, per-source NLL (tiny synthetic caches)."""

from __future__ import annotations

import collections
import csv
import dataclasses
import json
import os

import jax
import numpy as np
import pytest
from small import CFG

from scenegen_jax.data.cache import cached_scene, check_compatible, load_cache
from scenegen_jax.data.cache_write import write_cache
from scenegen_jax.data.map_store import MapStore
from scenegen_jax.data.union import CacheUnion, load_union
from scenegen_jax.frame import Frame
from scenegen_jax.likelihood.batch import gather_batch
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE
from scenegen_jax.train import data as D
from scenegen_jax.train.data import (
    batch_indices,
    draw_indices,
    resolve_weights,
    union_indices,
)
from scenegen_jax.vector_map import VectorMap

SIZES = {VEHICLE: (1.9, 4.6), PEDESTRIAN: (0.6, 0.6), BICYCLIST: (0.7, 1.8)}


def _frames(prefix: str, n: int, seed: int):
    """`n` hand-made frames with 0-6 actors each inside the region, on an empty map."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        k = int(rng.integers(0, 7))
        cls = rng.integers(0, 3, k).astype(np.int32)
        yield Frame(
            scene_id=f"{prefix}/{i:03d}",
            source="hand",
            cls=cls,
            position=rng.uniform(-30.0, 30.0, (k, 2)),
            size=np.array([SIZES[int(c)] for c in cls]).reshape(k, 2),
            heading=rng.uniform(0.0, 2 * np.pi, k),
            velocity=rng.normal(0.0, 3.0, (k, 2)),
            track_id=np.array([f"t{j}" for j in range(k)]),
            ego_velocity=np.array([5.0, 0.0]),
            ego_size=np.array([1.95, 4.9]),
            map=VectorMap(),
        )


def _write(path, n, seed, kind, cfg=CFG):
    write_cache(_frames(kind, n, seed), str(path), cfg, collections.Counter(),
                source={"kind": kind, "root": "/nowhere"})
    return str(path)


B_ACTORS = CFG.grid.max_actors - 4  # the second cache's actors; its slots are 2 * B_ACTORS


@pytest.fixture(scope="module")
def caches(tmp_path_factory):
    """Two caches of CFG's grid from two 'sources'; the second with fewer actor slots."""
    root = tmp_path_factory.mktemp("multi")
    a = _write(root / "a", 7, 0, "av2")
    b = _write(root / "b", 5, 1, "womd_json", CFG.replace(max_actors=B_ACTORS))
    return a, b


# ---------------------------------------------------------------------------- data order


def test_draw_frequencies_match_the_weights():
    sizes, weights, steps, b = [7, 13, 5], [5.0, 3.0, 2.0], 3000, 4
    counts = np.zeros(3)
    per_scene = [np.zeros(s) for s in sizes]
    for step in range(steps):
        which, local = draw_indices(sizes, resolve_weights(sizes, weights), b, 11, step)
        assert np.all(local < np.asarray(sizes)[which])
        np.add.at(counts, which, 1)
        for c, i in zip(which, local, strict=True):
            per_scene[c][i] += 1
    expected = np.asarray(weights) / sum(weights) * steps * b
    chi2 = float(np.sum((counts - expected) ** 2 / expected))
    assert chi2 < 13.8, (counts, expected)  # chi-square, 2 dof, p = 0.001
    # Within a cache, every scene is drawn once per pass: counts differ by at most one.
    for c in per_scene:
        assert c.max() - c.min() <= 1, c
    # Default weights: the scene counts, i.e. uniform over all scenes.
    np.testing.assert_allclose(resolve_weights(sizes, None), np.asarray(sizes) / sum(sizes))
    which = np.concatenate([draw_indices(sizes, None, b, 3, s)[0] for s in range(2000)])
    expected = np.asarray(sizes) / sum(sizes) * len(which)
    assert float(np.sum((np.bincount(which, minlength=3) - expected) ** 2 / expected)) < 13.8


def test_bad_weights_are_refused():
    for w in ([1.0], [1.0, -1.0], [0.0, 0.0], [1.0, float("nan")]):
        with pytest.raises(ValueError, match="--weights"):
            resolve_weights([3, 4], w)
    # Weights whose sum overflows float keep their shares.
    np.testing.assert_allclose(resolve_weights([3, 4], [1.5e308, 1e308]), [0.6, 0.4])


def _old_batch_indices(num_scenes, batch_size, seed, step):
    """The single-cache draw order, which older workdirs trained on one cache resume with."""
    pos = step * batch_size + np.arange(batch_size)
    epochs, offsets = np.divmod(pos, num_scenes)
    out = np.empty(batch_size, np.int64)
    for epoch in np.unique(epochs):
        perm = np.random.default_rng([seed, int(epoch)]).permutation(num_scenes)
        out[epochs == epoch] = perm[offsets[epochs == epoch]]
    return out


def test_order_is_a_pure_function_of_seed_and_step(caches):
    sizes, shares = [7, 13, 5], resolve_weights([7, 13, 5], [1.0, 2.0, 1.0])
    forward = [draw_indices(sizes, shares, 4, 5, s) for s in range(1200)]
    D._layout.cache_clear()
    D._pass_permutation.cache_clear()
    for s in np.random.default_rng(0).permutation(1200)[:300]:  # any order, cold caches
        again = draw_indices(sizes, shares, 4, 5, int(s))
        np.testing.assert_array_equal(again[0], forward[s][0])
        np.testing.assert_array_equal(again[1], forward[s][1])
    other = np.concatenate([draw_indices(sizes, shares, 4, 6, s)[1] for s in range(20)])
    assert not np.array_equal(other, np.concatenate([f[1] for f in forward[:20]]))
    # One cache: the order of the single-cache draw (`_old_batch_indices`), so old runs resume.
    for s in range(0, 3000, 7):
        np.testing.assert_array_equal(batch_indices(60, 4, 0, s), _old_batch_indices(60, 4, 0, s))
    # Re-created unions give the same batches.
    a, b = caches
    u1, u2 = load_union([a, b], CFG), load_union([a, b], CFG)
    w = resolve_weights(u1.sizes, [1.0, 3.0])
    for step in (0, 3, 17):
        x = gather_batch(u1, union_indices(u1, w, 4, 0, step), CFG.grid)
        y = gather_batch(u2, union_indices(u2, w, 4, 0, step), CFG.grid)
        for p, q in zip(jax.tree.leaves(x), jax.tree.leaves(y), strict=True):
            np.testing.assert_array_equal(p, q)


# ---------------------------------------------------------------------------- the union


def test_union_reads_each_cache_in_place(caches):
    a, b = caches
    ca, cb = load_cache(a), load_cache(b)
    u = load_union([a, b], CFG)
    assert isinstance(u, CacheUnion) and len(u) == 12 and u.sizes == [7, 5]
    assert u.labels == ["av2:a", "womd_json:b"]
    # Map arrays stay on disk.
    assert all(isinstance(m.map_store.points, np.memmap) for m in u.members)
    assert u.actors.cls.shape == (12, 2 * CFG.grid.max_actors)  # b's fewer slots padded
    vmap, actors, _ = cached_scene(u, 7 + 2, CFG)
    assert vmap == cb.map_store.frame_map(2) == VectorMap()  # the hand-made frames' empty map
    np.testing.assert_array_equal(cached_scene(u, 1, CFG)[1].position, ca.actors.position[1])
    slots = 2 * B_ACTORS
    np.testing.assert_array_equal(actors.position[:slots], cb.actors.position[2])
    assert not actors.valid[slots:].any()
    assert u.scene_name(9) == f"{b}: womd_json/002"
    one = load_union(a, CFG)  # one cache: its own arrays, unchanged
    assert isinstance(one.map_store, MapStore) and len(one.map_store) == len(ca) == 7
    assert one.scene_name(3) == "av2/003"


def test_mismatched_caches_name_the_cache_and_field(caches, tmp_path):
    a, _ = caches
    bad = _write(tmp_path / "coarse", 2, 3, "scenarionet", CFG.replace(grid_size=16))
    with pytest.raises(ValueError, match=f"{bad}: field grid_size: cache has 16"):
        load_union([a, bad], CFG)
    ca = load_cache(a)
    meta = {**ca.meta, "m_per_px": 1.0}
    with pytest.raises(ValueError, match="x: field m_per_px"):
        check_compatible([ca, dataclasses.replace(ca, path="x", meta=meta)], CFG)
    fewer = {**ca.meta, "channels": [c for c in ca.meta["channels"] if c != "crosswalk"]}
    with pytest.raises(ValueError, match=r"y: field channels: no map layer\(s\)"):
        check_compatible([ca, dataclasses.replace(ca, path="y", meta=fewer)], CFG)
    swapped = {**ca.meta, "channels": ca.meta["channels"][::-1]}
    with pytest.raises(ValueError, match=f"z: field channels: .* differ from {a}"):
        check_compatible([ca, dataclasses.replace(ca, path="z", meta=swapped)], CFG)


def test_resume_with_other_caches_or_weights_is_refused(caches, tmp_path):
    from scenegen_jax.train.loop import save_or_check_config, save_or_check_data, train

    a, b = caches
    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, CFG)
    save_or_check_data(workdir, load_union([a, b], CFG), [3.0, 1.0])
    with open(os.path.join(workdir, "data.json")) as f:
        record = json.load(f)
    assert [c["path"] for c in record["caches"]] == [os.path.abspath(a), os.path.abspath(b)]
    assert [c["source"] for c in record["caches"]] == ["av2", "womd_json"]
    assert record["weights"] == [3.0, 1.0] and record["shares"] == [0.75, 0.25]
    os.makedirs(os.path.join(workdir, "checkpoints", "1"))  # a saved step binds the record
    save_or_check_data(workdir, load_union([a, b], CFG), [6.0, 2.0])  # the same shares
    with pytest.raises(ValueError, match="data.json: this workdir was trained on --data"):
        train(CFG, [b, a], workdir, 1, weights=[1.0, 3.0], progress=False)
    with pytest.raises(ValueError, match=r"data.json: .*--weights \[3.0, 1.0\]"):
        train(CFG, [a, b], workdir, 1, progress=False)


# ---------------------------------------------------------------------------- per source


def _combined(parts: list[dict], field: str, count) -> float:
    n = np.array([count(p) for p in parts], np.float64)
    return float(np.sum([p[field] * k for p, k in zip(parts, n, strict=True) if k]) / n.sum())


def test_per_source_summaries_combine_to_the_overall_one(caches, tmp_path, capsys):
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.cli import main
    from scenegen_jax.eval.nll import score_cache, summarize_by_source, summarize_scores
    from scenegen_jax.scene import CLASS_NAMES
    from scenegen_jax.train.loop import save_or_check_config
    from scenegen_jax.train.step import init_state

    a, b = caches
    union = load_union([a, b], CFG)
    state = init_state(CFG)
    scores = score_cache(state.params, union, CFG, batch_size=4, progress=False)
    overall = summarize_scores(scores)
    by_source = summarize_by_source(scores, union)
    assert list(by_source) == ["av2:a", "womd_json:b"]
    parts = list(by_source.values())
    assert sum(p["scenes"] for p in parts) == overall["scenes"] == 12
    assert overall["scene_nll"] == pytest.approx(
        _combined(parts, "scene_nll", lambda p: p["scenes"]), rel=1e-6)
    for name in CLASS_NAMES:
        for field in (f"nll_per_{name}", f"location_nll_per_{name}"):
            if overall[f"actors_{name}"]:
                assert overall[field] == pytest.approx(
                    _combined(parts, field, lambda p, n=name: p[f"actors_{n}"]), rel=1e-6)
    assert overall["nll_per_actor"] == pytest.approx(_combined(
        parts, "nll_per_actor", lambda p: sum(p[f"actors_{n}"] for n in CLASS_NAMES)), rel=1e-6)
    # A source's rows score as that cache does alone (a: the same actor slots, no recompile).
    alone = score_cache(state.params, load_union(a, CFG), CFG, batch_size=4, progress=False)
    for k, v in alone.items():
        np.testing.assert_allclose(scores[k][:7], v, rtol=1e-5, atol=1e-4)

    # The command: a source column, indices per cache, by_source in the summary line.
    workdir = str(tmp_path / "model")
    save_or_check_config(workdir, CFG)
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1)
    ckpt.save(state, force=True)
    ckpt.close()
    out = tmp_path / "scores.csv"
    main(["score", "--workdir", workdir, "--data", a, b, "--out", str(out), "--batch-size", "4"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    with open(out) as f:
        rows = list(csv.DictReader(f))
    assert [r["source"] for r in rows] == ["av2:a"] * 7 + ["womd_json:b"] * 5
    assert [int(r["index"]) for r in rows] == [*range(7), *range(5)]
    assert set(summary["by_source"]) == {"av2:a", "womd_json:b"}
    for name, part in summary["by_source"].items():
        mine = [float(r["scene_nll"]) for r in rows if r["source"] == name]
        assert part["scenes"] == len(mine)
        assert part["scene_nll"] == pytest.approx(np.mean(mine), abs=1e-3)
    assert summary["scene_nll"] == pytest.approx(
        np.mean([float(r["scene_nll"]) for r in rows]), abs=1e-3)


@pytest.mark.slow
def test_train_on_two_caches(caches, tmp_path):
    from scenegen_jax.train.loop import load_trained, train

    a, b = caches
    workdir = str(tmp_path / "wd")
    train(CFG, [a, b], workdir, 2, weights=[1.0, 1.0], progress=False)
    assert int(load_trained(workdir)[1].step) == 2
    with open(os.path.join(workdir, "data.json")) as f:
        assert json.load(f)["shares"] == [0.5, 0.5]


@pytest.mark.slow
def test_four_shards_train_to_the_parameters_of_one_cache(womd_root, tmp_path):
    """`prepare --shard I/4` x 4 (womd_mini GPUDrive JSON val, 14 files, 3 frames of each)
    reads as the unsharded cache and trains to the same parameters, bit for bit."""
    from small import train_args
    from test_map_store import map_differences

    from scenegen_jax import cli
    from scenegen_jax.config import get_config
    from scenegen_jax.data.cache_layout import ACTOR_FIELDS
    from scenegen_jax.data.prepare import prepare
    from scenegen_jax.data.sources import source_spec
    from scenegen_jax.train.loop import load_trained

    spec = source_spec("womd_json", os.path.join(womd_root, "gpudrive_json"), "val", 45)
    whole, sharded = str(tmp_path / "whole"), str(tmp_path / "sharded")
    prepare(spec, whole, get_config("tiny"), workers=1)
    for i in range(4):
        prepare(spec, sharded, get_config("tiny"), workers=1, shard=(i, 4))
    with pytest.raises(ValueError, match=r"--shard 14/15: no files for this shard \(14 files"):
        prepare(spec, sharded, get_config("tiny"), workers=1, shard=(14, 15))
    a, b = load_cache(whole), load_cache(sharded)
    assert a.scene_ids == b.scene_ids and len(b.meta["shards"]) == 4
    for k in ACTOR_FIELDS:
        np.testing.assert_array_equal(getattr(a.actors, k), getattr(b.actors, k))
    for i in range(len(a)):
        assert map_differences(a.map_store.frame_map(i), b.map_store.frame_map(i),
                               atol=0.0) == []

    for cache in (whole, sharded):  # in this process: the second run's programs are traced
        cli.main(train_args(cache, cache + "_run", 3))
    pa, pb = (jax.tree.leaves(load_trained(c + "_run")[1].params) for c in (whole, sharded))
    for x, y in zip(pa, pb, strict=True):
        np.testing.assert_array_equal(x, y)
