"""Box sizes a source never measured are not learnt or scored: the Argoverse 2 forecasting
scenes (no boxes at all) and ScenarioNet files of one box per vehicle give actors whose box
term is masked in training and scoring, counted in `prepare`'s summary and in `score`'s."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax.traverse_util import flatten_dict
from small import CFG, random_params, two_small_scenes
from train_batches import batch_of

from scenegen_jax.config import get_config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.data.prepare import prepare
from scenegen_jax.data.sources import source_spec
from scenegen_jax.distributions import HeadOutputs, actor_log_likelihood
from scenegen_jax.eval.nll import score_cache, summarize_scores
from scenegen_jax.likelihood.batch import batch_scenes
from scenegen_jax.scene import VEHICLE, Actors
from scenegen_jax.train.step import loss_fn


@pytest.fixture(scope="module")
def forecast_cache(forecast_root, tmp_path_factory):
    """A tiny-config cache of the two forecasting training scenarios, and its summary."""
    out = str(tmp_path_factory.mktemp("forecast"))
    summary, _ = prepare(source_spec("av2_forecasting", forecast_root, "train"), out,
                         get_config("tiny"), workers=1)
    return load_cache(out), summary


def test_prepare_records_and_counts_the_unmeasured_boxes(forecast_cache):
    cache, summary = forecast_cache
    valid = cache.actors.valid
    assert valid.sum() > 0 and not cache.actors.size_measured[valid].any()
    assert summary.size_unmeasured == summary.actors
    assert summary.actors["vehicle"] > 0


def _head(k: int = 2) -> HeadOutputs:
    from scenegen_jax.distributions import params as P

    rng = np.random.default_rng(0)
    return HeadOutputs(
        class_logits=jnp.asarray(rng.normal(size=4), jnp.float32),
        location_logits=jnp.asarray(rng.normal(size=CFG.grid.grid_size ** 2), jnp.float32),
        box=jnp.asarray(rng.normal(size=6 * k), jnp.float32),
        heading=jnp.asarray(rng.normal(size=P.heading_params_size(k)), jnp.float32),
        velocity=jnp.asarray(rng.normal(size=P.velocity_params_size(k)), jnp.float32),
    )


def test_an_unmeasured_box_leaves_only_the_box_term_out():
    """The same vehicle with and without a measured size: every term but the box is equal;
    the box term is exactly 0 with a zero gradient."""
    head = _head()
    vehicle = Actors(cls=jnp.int32(VEHICLE), position=jnp.array([3.0, -2.0]),
                     size=jnp.array([1.9, 4.6]), heading=jnp.float32(0.3),
                     velocity=jnp.array([4.0, 0.5]), valid=jnp.bool_(True))

    def terms(box, measured):
        target = vehicle.replace(size_measured=jnp.bool_(measured))
        return actor_log_likelihood(head.replace(box=box), target, jnp.bool_(False), CFG.model)

    measured, unmeasured = terms(head.box, True), terms(head.box, False)
    assert float(measured["box"]) != 0.0 and float(unmeasured["box"]) == 0.0
    for k in ("class", "location", "heading", "velocity"):
        assert float(measured[k]) == float(unmeasured[k]), k
    grad = jax.grad(lambda b: terms(b, False)["box"])(head.box)
    assert np.all(np.asarray(grad) == 0.0)
    # None (every box measured) is the measured case
    plain = actor_log_likelihood(head, vehicle, jnp.bool_(False), CFG.model)
    assert float(plain["box"]) == float(measured["box"])


def _grads(cache, idx):
    params = random_params(CFG, jax.random.key(0))
    batch = batch_of(cache, idx)
    maps, scene = batch_scenes(batch, CFG.grid)
    grads = jax.jit(jax.grad(lambda p: loss_fn(p, CFG, maps, scene)[0]))(params)
    return {"/".join(k): np.asarray(v) for k, v in flatten_dict(grads).items()}


def _moves(grads, prefix):
    return any(np.any(g != 0) for name, g in grads.items() if name.startswith(prefix))


def test_forecasting_scenes_give_the_box_head_a_zero_gradient(forecast_cache,
                                                              tiny_train_cache):
    """A step on forecasting scenes leaves every box-head parameter unchanged (gradient
    exactly zero) while the other heads move; the same on sensor-log scenes (measured
    boxes) moves the box head too."""
    cache, _ = forecast_cache
    cls, valid = cache.actors.cls, cache.actors.valid
    idx = np.argsort(-(valid & (cls == VEHICLE)).sum(1), kind="stable")[:2]
    grads = _grads(cache, idx)
    box = {n: g for n, g in grads.items() if n.startswith("box")}
    assert box and all(np.all(g == 0) for g in box.values()), sorted(box)
    for head in ("heading", "velocity", "loc", "class"):
        assert _moves(grads, head), head
    assert _moves(_grads(tiny_train_cache, two_small_scenes(tiny_train_cache)), "box")


def test_score_counts_the_masked_boxes(forecast_cache):
    cache, _ = forecast_cache
    params = random_params(CFG, jax.random.key(1))
    scores = score_cache(params, cache, CFG, batch_size=2, progress=False, workers=1)
    summary = summarize_scores(scores)
    assert summary["actors_vehicle"] > 0
    for name in ("vehicle", "bicyclist"):
        assert summary[f"box_actors_{name}"] == 0
        assert summary[f"box_unmeasured_{name}"] == summary[f"actors_{name}"]
        assert summary[f"box_nll_per_{name}"] is None
    assert np.all(scores["box"] == 0.0)
    json.dumps(summary)  # the CLI prints it


def test_placeholder_boxes_stay_out_of_the_area_statistic_and_the_overlaps():
    """Two vehicles on one spot: their boxes overlap and give an area histogram when
    measured; as placeholders they give neither, and are counted instead."""
    from scenegen_jax.eval.mmd import scene_statistics
    from scenegen_jax.eval.realism import overlapping_pairs, unmeasured_boxes

    two = Actors(cls=np.array([VEHICLE, VEHICLE]), position=np.array([[5.0, 0.0], [6.0, 0.5]]),
                 size=np.array([[2.0, 4.5], [2.0, 4.5]]), heading=np.zeros(2),
                 velocity=np.zeros((2, 2)), valid=np.ones(2, bool))
    placeholders = two.replace(size_measured=np.zeros(2, bool))
    assert overlapping_pairs(two) == 1 and unmeasured_boxes(two) == 0
    assert overlapping_pairs(placeholders) == 0 and unmeasured_boxes(placeholders) == 2
    assert scene_statistics(two)["area"] is not None
    assert scene_statistics(placeholders)["area"] is None
    assert scene_statistics(placeholders)["speed"] is not None


def test_baselines_fit_measured_boxes_only_and_give_boxes_that_count():
    """The Procedural baseline's size KDE ignores placeholder boxes, and baseline scenes
    (boxes of their own) enter the area statistic."""
    from scenegen_jax.eval import baselines as B
    from scenegen_jax.eval.mmd import scene_statistics

    sizes = np.array([[1.8, 4.4], [2.0, 4.9], [1.9, 4.6], [9.0, 9.0]])
    train = Actors(cls=np.full((1, 4), VEHICLE), position=np.zeros((1, 4, 2)),
                   size=sizes[None], heading=np.zeros((1, 4)), velocity=np.zeros((1, 4, 2)),
                   valid=np.ones((1, 4), bool),
                   size_measured=np.array([[True, True, True, False]]))
    kde = B.fit_size_kde(train)
    np.testing.assert_allclose(np.exp(kde.log_sizes[VEHICLE]), sizes[:3])
    scene = B.pad_actors([VEHICLE], [[5.0, 0.0]], [[2.0, 4.5]], [0.0], [[0.0, 0.0]], CFG)
    assert scene.size_measured is None
    assert scene_statistics(scene)["area"] is not None
