"""Scoring is honest: deterministic, the scene NLL is the sum of its terms, and a real scene
with an actor moved into a city block scores a higher location NLL (real Argoverse scenes)."""

from __future__ import annotations

import csv
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference_unroll import reference_step_terms
from small import CFG, two_small_scenes

from scenegen_jax.distributions import TERMS
from scenegen_jax.eval.nll import score_batch, score_cache, worst_scenes
from scenegen_jax.likelihood.batch import batch_scenes, gather_batch
from scenegen_jax.scene import VEHICLE, in_region, pixel_centers


def off_road_point(drivable: np.ndarray, cfg) -> np.ndarray:
    """(x, y) m of the bin centre farthest from the drivable area (inside a city block).

    Args:
      drivable: bool [H, W] drivable area on the model's grid (`scenegen_jax.scene` layout).
    Returns:
      float32 [2]; raises if the whole region is drivable.
    """
    from scipy import ndimage

    drivable = np.asarray(drivable, bool)
    if drivable.all():
        raise ValueError("the whole region is drivable: no off-road point")
    distance = ndimage.distance_transform_edt(~drivable)
    row, col = np.unravel_index(np.argmax(distance), distance.shape)
    return pixel_centers(cfg.grid)[row, col]


@pytest.fixture(scope="module")
def scenes(tiny_train_cache):
    return two_small_scenes(tiny_train_cache)


@pytest.fixture(scope="module")
def fitted(overfit_run):
    """Params fitted to the two scenes (100 steps, conftest.py): they have learnt where its
    actors are."""
    return jax.tree.map(jnp.asarray, overfit_run[1])


def test_same_model_scored_twice_is_identical(tiny_train_cache, fitted):
    """The first 11 scenes of the cache (batches of 8: the last one padded)."""
    n = 11
    a = score_cache(fitted, tiny_train_cache, CFG, batch_size=8, progress=False, scenes=range(n))
    b = score_cache(fitted, tiny_train_cache, CFG, batch_size=8, progress=False, scenes=range(n))
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    # Concurrent calls on parts of each batch (3 workers: calls of 2 scenes, the last one
    # padded) score every scene as one call per batch does.
    c = score_cache(fitted, tiny_train_cache, CFG, batch_size=8, progress=False, workers=3,
                    scenes=range(n))
    d = score_cache(fitted, tiny_train_cache, CFG, batch_size=8, progress=False, workers=1,
                    scenes=range(n))
    for k in a:
        assert c[k].shape[0] == d[k].shape[0] == n
        # Other batch shapes round the convolutions differently; the fitted mixtures are
        # sharp (box NLL up to 24 nats) and amplify that to ~5e-4 nats. A scene scored in
        # another's place would differ by nats.
        np.testing.assert_allclose(c[k], d[k], rtol=1e-4, atol=1e-3)


@jax.jit
def _scores(params, batch):
    return score_batch(params, batch, CFG.model)


def _location_nll(params, batch):
    return np.asarray(_scores(params, batch)["location"])


def test_actor_moved_into_a_block_scores_higher_location_nll(tiny_train_cache, scenes, fitted):
    batch = gather_batch(tiny_train_cache, scenes, CFG.grid)
    base = _location_nll(fitted, batch).sum(1)
    full = CFG.replace(map_layers=("lanes", "drivable", "crosswalks"))
    drivable_channel = full.grid.map_channels.index("drivable_area")
    moved_count, higher = 0, 0
    for b in range(len(scenes)):
        grid = np.asarray(gather_batch(tiny_train_cache, scenes[b : b + 1], full.grid).maps[0])
        target = off_road_point(grid[..., drivable_channel] > 0.5, CFG)
        a = batch.actors
        inside = np.asarray(in_region(jnp.asarray(a.position[b]), CFG.grid)) & a.valid[b]
        for j in np.flatnonzero(inside & (a.cls[b] == VEHICLE)):
            position = a.position.copy()
            position[b, j] = target
            moved = batch._replace(actors=a.replace(position=position))
            nll = _location_nll(fitted, moved).sum(1)
            np.testing.assert_array_equal(nll[1 - b], base[1 - b])  # the other scene unchanged
            moved_count += 1
            higher += nll[b] > base[b] + 1.0
    assert moved_count >= 4
    assert higher == moved_count, f"{higher}/{moved_count} moves raised the location NLL"


@pytest.mark.slow
def test_score_cli_terms_sum_and_top_k(tiny_train_cache, tmp_path, capsys):
    from scenegen_jax.cli import main
    from scenegen_jax.train.loop import train
    from scenegen_jax.workdir import load_params

    workdir = str(tmp_path / "model")
    train(CFG, tiny_train_cache.path, workdir, steps=2, progress=False)
    out, renders, per_step = tmp_path / "s.csv", tmp_path / "top", tmp_path / "steps.npz"
    main(["score", "--workdir", workdir, "--data", tiny_train_cache.path, "--out", str(out),
          "--actors-out", str(per_step), "--top-k", "3", "--render", str(renders)])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    with open(out) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(tiny_train_cache)
    steps = np.load(per_step)
    for i, row in enumerate(rows):
        terms = [float(row[f"{k}_nll"]) for k in TERMS]
        assert float(row["scene_nll"]) == pytest.approx(sum(terms), abs=2e-3)
        for k, v in zip(TERMS, terms, strict=True):
            assert steps[k][i].sum() == pytest.approx(v, abs=2e-3)
        per_actor = float(row["scene_nll"]) / max(int(row["actors"]), 1)
        assert float(row["nll_per_actor"]) == pytest.approx(per_actor, abs=2e-3)
    scene_nll = np.array([float(r["scene_nll"]) for r in rows])
    assert summary["scene_nll"] == pytest.approx(scene_nll.mean(), rel=1e-5)
    # Each term of the first two rows against the step-by-step reference of the model
    # (tests/reference_unroll.py) under the checkpoint the command scored with.
    _, params, _ = load_params(workdir)
    maps, scene = batch_scenes(gather_batch(tiny_train_cache, np.arange(2), CFG.grid), CFG.grid)
    ref = reference_step_terms(params, CFG, maps, scene, None)
    for i in range(2):
        for k in TERMS:
            assert float(rows[i][f"{k}_nll"]) == pytest.approx(-float(ref[k][i].sum()), abs=2e-3)
    # Scenes with more actors in the region than CFG's 6 slots (every one of the tiny cache's)
    # are scored on their first 6, without the stop token.
    pos, half = tiny_train_cache.actors.position, CFG.grid.region_m / 2
    in_region = tiny_train_cache.actors.valid & ((pos >= -half) & (pos < half)).all(-1)
    truncated = in_region.sum(1) > CFG.grid.max_actors
    assert truncated.any()
    assert [int(r["complete"]) for r in rows] == list((~truncated).astype(int))
    want = np.minimum(in_region.sum(1), CFG.grid.max_actors)
    assert [int(r["actors"]) for r in rows] == list(want)
    assert summary["scenes_truncated"] == truncated.sum()
    per_actor = np.array([float(r["nll_per_actor"]) for r in rows])
    expected = np.argsort(-per_actor, kind="stable")[:3]
    names = sorted(os.listdir(renders))
    assert names == [f"top{r + 1:02d}_{i:05d}.png" for r, i in enumerate(expected)]
    assert summary["rendered"] == [str(renders / n) for n in names]


def test_worst_scenes_picks_the_least_likely_actor():
    # Two scenes: scene 1 has the higher NLL per actor; its step 1 is the least likely actor.
    z = np.zeros((2, 4), np.float32)
    scores = {k: z.copy() for k in TERMS}
    scores["location"][0] = [5.0, 5.0, 0.0, 0.0]
    scores["location"][1] = [2.0, 30.0, 0.0, 0.0]
    scores["class"][:, 2] = 1.0  # the stop step
    scores["step_valid"] = np.array([[True, True, True, False]] * 2)
    scores["step_cls"] = np.array([[0, 1, 3, 0], [2, 0, 3, 0]])
    ranked = worst_scenes(scores, 5)
    assert [(i, s) for i, s, *_ in ranked] == [(1, 1), (0, 0)]
    assert ranked[0][2] == pytest.approx((2 + 30 + 1) / 2)
    assert ranked[0][3]["location"] == 30.0


def test_a_batch_beyond_the_scenes_is_cut_to_them(tiny_train_cache):
    """`--batch-size 100000` on a few scenes scores them as a batch of those scenes does,
    instead of asking the device for a batch of 100,000."""
    from scenegen_jax.model.network import init_params

    params = init_params(CFG.model, jax.random.key(0))
    some = range(3)
    huge = score_cache(params, tiny_train_cache, CFG, batch_size=100_000, progress=False,
                       workers=2, scenes=some)
    fits = score_cache(params, tiny_train_cache, CFG, batch_size=6, progress=False, workers=2,
                       scenes=some)  # 3 scenes per call
    for k in fits:
        np.testing.assert_array_equal(huge[k], fits[k])


def test_a_batch_beyond_the_free_memory_is_refused_before_scoring(tiny_train_cache,
                                                                  monkeypatch):
    from scenegen_jax.eval import nll
    from scenegen_jax.model.network import init_params

    params = init_params(CFG.model, jax.random.key(0))
    monkeypatch.setattr(nll, "free_memory_bytes", lambda: 2**20)  # 1 MiB free
    gathered = []
    gather = nll.gather_batch
    monkeypatch.setattr(nll, "gather_batch", lambda *a: gathered.append(a) or gather(*a))
    with pytest.raises(ValueError, match=r"^batch size 4 \(--batch-size\): 2 concurrent scoring "
                       r"call\(s\) need about [0-9.]+ GiB, 0\.0 GiB free; use a batch size of "
                       r"at most about 1$"):
        score_cache(params, tiny_train_cache, CFG, batch_size=4, progress=False, workers=2,
                    scenes=range(4))
    assert len(gathered) == 1  # the shape template only: no scene was scored
