"""Sampling: loop mechanics with a fake deterministic model, collision rejection, best-of-M,
reproducibility and batching, properties of scenes from the real network, and the CLI.

Compile budget (XLA:CPU compiles of the rollout take 10-30 s here): one compile with the
fake model, one of the real network at [B, S] = [2, 2] and one at [1, 1], which the CLI test
reuses (same config, proposals, heatmap steps and shapes).
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import json
import math
import os
import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from shapely.geometry import Polygon

from scenegen_jax.config import get_config
from scenegen_jax.distributions import (
    box_params_size,
    heading_log_prob,
    heading_params_size,
    sample_box,
    sample_heading,
    sample_velocity,
    velocity_params_size,
    velocity_proposal_score,
)
from scenegen_jax.geometry import boxes_overlap
from scenegen_jax.sampling import (
    HEATMAP_STEPS,
    MAX_SIZE_M,
    MAX_SPEED_MPS,
    MIN_SIZE_M,
    NetworkModel,
    SamplerOptions,
    StopReason,
    actor_records,
    actors_from_records,
    batch_inputs,
    sample_attributes,
    sample_batch,
    sample_scenes,
    scene_keys,
)
from scenegen_jax.sampling.batch import jitted_sampler
from scenegen_jax.scene import (
    BICYCLIST,
    PEDESTRIAN,
    STOP,
    VEHICLE,
    Actors,
    Scene,
    bin_index,
    in_region,
)
from scenegen_jax.train.step import init_state
from scenegen_jax.viz.render import box_corners

TINY = get_config("tiny")
H = TINY.grid_size
N_BINS = H * H
K = TINY.num_mixtures
NEG = -30.0  # logit of an (effectively) impossible outcome


# ----------------------------------------------------------------------------- helpers
def _polygon(position, size, heading) -> Polygon:
    return Polygon(box_corners(np.asarray(position, np.float64), np.asarray(size, np.float64),
                               float(heading)))


def overlapping_pairs(actors: Actors, ego: Actors) -> list[tuple[int, int]]:
    """(i, j) of overlapping vehicle/bicyclist boxes by shapely (j = -1: the ego)."""
    a = jax.tree.map(np.asarray, actors)
    idx = [i for i in np.flatnonzero(a.valid) if a.cls[i] != PEDESTRIAN]
    polys = {i: _polygon(a.position[i], a.size[i], a.heading[i]) for i in idx}
    polys[-1] = _polygon(ego.position, ego.size, ego.heading)
    keys = sorted(polys)
    return [(i, j) for n, i in enumerate(keys) for j in keys[n + 1:]
            if polys[i].intersection(polys[j]).area > 1e-4]


def slot(tree, *index):
    return jax.tree.map(lambda x: np.asarray(x)[index], tree)


def broadcast(tree, b: int):
    return jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (b, *np.shape(x))), tree)


def ego_of(cfg) -> Actors:
    return Actors(cls=np.int32(VEHICLE), position=np.zeros(2, np.float32),
                  size=np.asarray(cfg.ego_size_m, np.float32), heading=np.float32(0.0),
                  velocity=np.zeros(2, np.float32), valid=np.bool_(True))


# ----------------------------------------------------------------------------- geometry
def test_boxes_overlap_matches_shapely():
    rng = np.random.default_rng(0)
    n = 3000
    ca, cb = rng.uniform(-4, 4, (n, 2)), rng.uniform(-4, 4, (n, 2))
    sa, sb = rng.uniform(0.3, 5, (n, 2)), rng.uniform(0.3, 5, (n, 2))
    ha, hb = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n)
    got = np.asarray(jax.jit(jax.vmap(boxes_overlap))(ca, sa, ha, cb, sb, hb))
    areas = np.array([_polygon(ca[i], sa[i], ha[i]).intersection(_polygon(cb[i], sb[i], hb[i])).area
                      for i in range(n)])
    clear = (areas > 1e-3) | (areas == 0.0)  # skip near-touching pairs (float rounding)
    assert np.mean(got) > 0.2 and np.mean(~got) > 0.2  # both outcomes exercised
    np.testing.assert_array_equal(got[clear], areas[clear] > 0)
    # Touching along an edge is not an overlap; a hair of overlap is.
    one = dict(size_a=jnp.array([2.0, 4.0]), heading_a=0.0, size_b=jnp.array([2.0, 4.0]),
               heading_b=0.0, center_a=jnp.zeros(2))
    assert not bool(boxes_overlap(center_b=jnp.array([4.0, 0.0]), **one))
    assert bool(boxes_overlap(center_b=jnp.array([3.99, 0.0]), **one))
    # Separated only along a diagonal axis (axis-aligned bounds overlap).
    assert not bool(boxes_overlap(jnp.zeros(2), jnp.array([1.0, 6.0]), math.pi / 4,
                                  jnp.array([2.2, -2.2]), jnp.array([1.0, 6.0]), math.pi / 4))


# ----------------------------------------------------------------------------- best-of-M
def test_sample_attributes_keeps_the_most_likely_of_m_proposals():
    """The flattened best-of-M equals the most likely of M draws written out per actor, for
    the heading and velocity; the box is one draw."""
    rng = np.random.default_rng(1)
    r, m = 3, 7
    cls = jnp.array([VEHICLE, BICYCLIST, PEDESTRIAN], jnp.int32)
    raws = [jnp.asarray(rng.normal(size=(r, n)), jnp.float32)
            for n in (box_params_size(K), heading_params_size(K), velocity_params_size(K))]
    keys = jax.random.split(jax.random.key(0), r)
    fn = jax.jit(sample_attributes, static_argnames=("cfg", "proposals"))
    size, head, vel = map(np.asarray, fn(keys, *raws, cls, cfg=TINY, proposals=m))

    @jax.jit
    def reference(keys, box, heading, velocity, relative):
        def best(ks, sample, score, p):  # the most likely of m draws, written out
            draws = jax.vmap(lambda kk: sample(kk, p))(ks)
            return draws[jnp.argmax(jax.vmap(lambda d: score(p, d))(draws))]

        def one(k, b, h, v, rel):
            ks = jax.random.split(k, 1 + 2 * m)  # the box's, M heading, M velocity keys
            size = sample_box(ks[0], b)  # one draw: the paper's best-of-M skips the box
            head = best(ks[1 : 1 + m], sample_heading, heading_log_prob, h)
            # Velocity: the first proposal decides standing vs moving; a moving actor keeps
            # its best moving proposal.
            zero = TINY.zero_speed
            vels = jax.vmap(lambda kk: sample_velocity(kk, v, head, rel, zero))(ks[1 + m :])
            moving = jnp.hypot(vels[:, 0], vels[:, 1]) > zero
            score = jax.vmap(lambda x: velocity_proposal_score(v, x, head, rel, zero))(vels)
            pick = jnp.where(moving[0], jnp.argmax(jnp.where(moving, score, -jnp.inf)), 0)
            return size, head, vels[pick]

        return jax.vmap(one)(keys, box, heading, velocity, relative)

    want = list(map(np.asarray, reference(keys, *raws, jnp.array([True, True, False]))))
    want[0] = np.clip(want[0], MIN_SIZE_M, MAX_SIZE_M)
    np.testing.assert_allclose(size[:2], want[0][:2], rtol=1e-6)
    np.testing.assert_allclose(head[:2], want[1][:2], rtol=1e-6)
    np.testing.assert_allclose(vel, want[2], rtol=1e-5, atol=1e-6)
    # The pedestrian: nominal footprint, heading = walking direction (0 when standing).
    np.testing.assert_allclose(size[2], [TINY.pedestrian_size_m] * 2)
    walking = np.hypot(*vel[2]) > TINY.zero_speed
    expect = math.atan2(vel[2, 1], vel[2, 0]) % (2 * math.pi) if walking else 0.0
    np.testing.assert_allclose(head[2], expect, atol=1e-5)
    # Extreme raw outputs still give clamped, finite attributes.
    size, head, vel = map(np.asarray, fn(keys, *[jnp.full_like(x, 1e4) for x in raws], cls,
                                         cfg=TINY, proposals=m))
    assert np.all(np.isfinite(size)) and np.all(np.isfinite(head)) and np.all(np.isfinite(vel))
    assert size.min() >= MIN_SIZE_M and size.max() <= MAX_SIZE_M
    assert np.all(np.hypot(*vel.T) <= MAX_SPEED_MPS * (1 + 1e-5))
    assert np.all((head >= 0) & (head < 2 * math.pi))


def test_best_of_m_keeps_standing_share_and_mixture_modes():
    """Best-of-M (M = 10) keeps P(standing) = pi_0 and picks speeds near the mixture's mode in
    its own coordinates: with the planar density the 1 / s^2 Jacobian made the slowest speed
    win. The box, one draw, has the median of its log-normal."""
    k = TINY.num_mixtures
    n, m = 4000, 10
    box = np.full(box_params_size(k), -30.0, np.float32)  # one component (others' logits -30)
    box[0] = 0.0
    box[k : k + 2] = np.log([2.0, 4.5])  # mu of (log w, log l)
    box[3 * k : 3 * k + 2] = np.log(0.3**2)  # log var
    box[5 * k] = 0.0  # rho
    vel = np.zeros(velocity_params_size(k), np.float32)
    vel[:k] = [0.0, 0.0] + [-30.0] * (k - 2)  # pi_0 = pi_1 = 1/2
    vel[k] = np.log(10.0)  # mu of log speed, component 1
    vel[2 * k - 1] = np.log(0.5)  # log sigma
    vel[3 * k - 2 : 3 * k] = [1.0, 0.0]  # direction biternion
    vel[5 * k - 4] = 2.0  # log kappa
    raws = [jnp.broadcast_to(jnp.asarray(x), (n, x.size)) for x in
            (box, np.zeros(heading_params_size(k), np.float32), vel)]
    cls = jnp.full((n,), VEHICLE, jnp.int32)
    fn = jax.jit(sample_attributes, static_argnames=("cfg", "proposals"))
    size, _, v = map(np.asarray, fn(jax.random.split(jax.random.key(3), n), *raws, cls,
                                    cfg=TINY, proposals=m))
    speed = np.hypot(*v.T)
    standing = speed <= TINY.zero_speed
    assert abs(standing.mean() - 0.5) < 0.04
    # Best of 10 draws from LN(log 10, 0.5) lies near the mode of log speed: median ~10 m/s.
    assert abs(np.median(speed[~standing]) / 10.0 - 1.0) < 0.05
    np.testing.assert_allclose(np.median(size, axis=0), [2.0, 4.5], rtol=0.03)


# ----------------------------------------------------------------------------- fake model
FAKE_CFG = get_config("tiny", max_actors=8)
FAKE_STEPS = (0, 1)  # heatmaps recorded by the fake runs


@dataclasses.dataclass(frozen=True)
class FakeModel:
    """A deterministic stand-in for SceneGenNet: its recurrent state counts steps, and the
    class and location logits of step t are rows t of tables in the params; attributes are
    fixed raw vectors. Everything is in `params`, so one compile serves every scenario."""

    cfg: object

    def initial_state(self, params):
        return jnp.int32(0)

    def map_gates(self, params, map_raster):
        return jnp.zeros((1, 1, 1, 1))

    def actor_gates(self, params, actor_raster):
        return jnp.zeros((1, 1, 1, 1))

    def next_actor_gates(self, params, gates, before, after, position):
        return gates

    def order_gates(self, params, prev_bin):
        return jnp.zeros((1, 1, 1, 1))

    def recur(self, params, state, gates):
        state = self.initial_state(params) if state is None else state
        return state + 1, jnp.full((1, 1, 1, 1), state, jnp.float32)

    def features(self, params, h):
        return jnp.broadcast_to(h, (1, self.cfg.grid_size, self.cfg.grid_size, 1))

    def _t(self, f):
        return f[0, 0, 0, 0].astype(jnp.int32)

    def class_logits(self, params, f):
        return params["cls"][self._t(f)][None]

    def location_logits(self, params, f, cls):
        return params["loc"][self._t(f)][None]

    def attributes(self, params, feat, cls, map_feat):
        r = feat.shape[0]
        return tuple(jnp.broadcast_to(params[k], (r, params[k].shape[0]))
                     for k in ("box", "heading", "velocity"))


def box_raw(weights, mu_m, log_var=(-8.0,)):
    """Raw box params: components with `weights`, (width, length) medians `mu_m` (m) and log
    variances `log_var` (per component, both sides); unused components get no weight."""
    c = len(weights)
    w = np.full(K, 1e-12)
    w[:c] = weights
    mu = np.zeros((K, 2))
    mu[:c] = np.log(np.asarray(mu_m, np.float64))
    lv = np.full((K, 2), -8.0)
    lv[:c] = np.asarray(log_var, np.float64)[:, None]
    return np.concatenate([np.log(w), mu.ravel(), lv.ravel(), np.zeros(K)]).astype(np.float32)


def heading_raw(angle=0.0):
    logits = np.array([0.0] + [NEG] * (K - 1))
    direction = np.tile([math.cos(angle), math.sin(angle)], K)
    return np.concatenate([logits, direction, np.full(K, 9.0)]).astype(np.float32)


def velocity_raw_stationary():
    logits = np.array([10.0] + [NEG] * (K - 1))
    return np.concatenate([logits, np.zeros(5 * (K - 1))]).astype(np.float32)


def fake_params(classes, loc_rows, box=None):
    """Class sequence (STOP ends) and per-step location logits [rows, H*W] (padded with 0)."""
    n = FAKE_CFG.max_actors
    cls = np.full((n, 4), NEG, np.float32)
    for t, c in enumerate(classes[:n]):
        if np.ndim(c):
            cls[t] = c
        else:
            cls[t, c] = 30.0
    cls[len(classes):, STOP] = 30.0
    loc = np.zeros((n, N_BINS), np.float32)
    for t, row in enumerate(loc_rows[:n]):
        loc[t] = row
    box = box_raw([1.0], [(1.0, 2.0)]) if box is None else box
    return {"cls": jnp.asarray(cls), "loc": jnp.asarray(loc), "box": jnp.asarray(box),
            "heading": jnp.asarray(heading_raw()),
            "velocity": jnp.asarray(velocity_raw_stationary())}


def peaked(*bins_logits):
    row = np.zeros(N_BINS, np.float32)
    for b, v in bins_logits:
        row[b] = v
    return row


FAKE_NUM = 16  # samples per fake run (one shape: one compile)


def run_fake(params, given=None, caps=None, seed=0, location_temperature=1.0):
    """FAKE_NUM fake scenes on one empty map; returns the Sample with leading axis [FAKE_NUM]."""
    num = FAKE_NUM
    maps = jnp.zeros((1, H, H, len(FAKE_CFG.map_channels)))
    g, c = batch_inputs(FAKE_CFG, 1, given, caps)
    options = SamplerOptions(heatmap_steps=FAKE_STEPS, location_temperature=location_temperature)
    out = sample_batch(scene_keys(jax.random.key(seed), 1, num), params, maps,
                       broadcast(ego_of(FAKE_CFG), 1), g, c, cfg=FAKE_CFG, options=options,
                       model=FakeModel(FAKE_CFG))
    return jax.tree.map(lambda x: np.asarray(x[0]), out)


def bins_of(actors: Actors, cfg=FAKE_CFG):
    return np.asarray(bin_index(jnp.asarray(actors.position), cfg))


def test_candidates_take_the_map_channels_at_their_own_bins(monkeypatch):
    """The attribute MLPs' map input (`attribute_map_input`) is the map raster at each
    candidate's own bin: a model that echoes it into the box parameters, and a best-of-M
    draw that returns them as the size, give every candidate its bin's map values."""
    import scenegen_jax.sampling.rollout as rollout

    class MapEcho(FakeModel):
        def attributes(self, params, feat, cls, map_feat):
            return map_feat, map_feat[:, :1], map_feat[:, :2]

    def echo(keys, box, heading, velocity, classes, cfg, proposals):
        return box[:, :2], heading[:, 0], velocity

    monkeypatch.setattr(rollout, "sample_attributes", echo)
    n, cm = FAKE_CFG.grid_size, len(FAKE_CFG.map_channels)
    map_raster = jnp.arange(n * n * cm, dtype=jnp.float32).reshape(1, n, n, cm)
    f = jnp.zeros((1, n, n, 1))
    bins, cands = rollout._candidates(jax.random.key(0), {}, MapEcho(FAKE_CFG), f, map_raster,
                                      VEHICLE, jnp.zeros((n * n,)), FAKE_CFG, 1, 16)
    bins = np.asarray(bins)
    assert len(set(bins.tolist())) > 8
    want = np.arange(n * n * cm, dtype=np.float32).reshape(n * n, cm)[bins]
    np.testing.assert_array_equal(cands.size, want[:, :2])
    np.testing.assert_array_equal(cands.heading, want[:, 0])


def test_fake_model_insertion_order_classes_and_stop():
    params = fake_params([VEHICLE, PEDESTRIAN, BICYCLIST],
                         [peaked((70, 30.0)), peaked((300, 30.0)), peaked((301, 30.0))])
    out = run_fake(params)
    a = out.actors
    np.testing.assert_array_equal(a.valid, np.tile([1, 1, 1, 0, 0, 0, 0, 0], (FAKE_NUM, 1)) > 0)
    np.testing.assert_array_equal(a.cls[:, :3],
                                  np.tile([VEHICLE, PEDESTRIAN, BICYCLIST], (FAKE_NUM, 1)))
    np.testing.assert_array_equal(bins_of(a)[:, :3], np.tile([70, 300, 301], (FAKE_NUM, 1)))
    np.testing.assert_array_equal(out.stop_reason, StopReason.STOP_TOKEN)
    np.testing.assert_array_equal(out.rejected, 0)
    # Nothing is written after the stop; attributes as the fake heads dictate.
    assert np.all(a.position[:, 3:] == 0) and np.all(a.size[:, 3:] == 0)
    np.testing.assert_allclose(a.size[:, 0], np.tile([1.0, 2.0], (FAKE_NUM, 1)), rtol=0.1)
    np.testing.assert_allclose(a.size[:, 1], TINY.pedestrian_size_m)
    np.testing.assert_array_equal(a.velocity[:, :3], 0.0)
    # Positions are uniform within the bins: different keys give different positions.
    assert len(np.unique(a.position[:, 0, 0])) == 16
    # Heatmap of step 0: the whole mass on bin 70; of step 1: on bin 300, none before 70.
    np.testing.assert_allclose(out.heatmaps[:, 0, 70], 1.0, atol=1e-6)
    np.testing.assert_allclose(out.heatmaps[:, 1].sum(-1), 1.0, atol=1e-5)
    assert np.all(out.heatmaps[:, 1, :70] == 0)
    np.testing.assert_array_equal(out.heatmap_cls, np.tile([VEHICLE, PEDESTRIAN], (FAKE_NUM, 1)))


def test_fake_model_ordering_mask_excludes_earlier_bins_and_no_bin_stops():
    # Step 1 prefers bin 100, which lies before the first actor's bin 500: masked out. Bin
    # 700 then holds all but 1e-6 of the mass (at logit 10 the 523 other allowed bins held
    # 2.3 %: 16 scenes all at 700 only 69 % of the time).
    params = fake_params([VEHICLE, VEHICLE],
                         [peaked((500, 30.0)), peaked((100, 30.0), (700, 20.0))])
    out = run_fake(params)
    np.testing.assert_array_equal(bins_of(out.actors)[:, :2], np.tile([500, 700], (FAKE_NUM, 1)))
    assert np.all(out.heatmaps[:, 1, :500] == 0)
    # Step 1 allows only bins before 1000 (-inf elsewhere): no bin left, the scene stops.
    row = np.zeros(N_BINS, np.float32)
    row[900:] = -np.inf
    out = run_fake(fake_params([VEHICLE, VEHICLE], [peaked((1000, 30.0)), row]))
    np.testing.assert_array_equal(out.actors.valid.sum(-1), 1)
    np.testing.assert_array_equal(out.stop_reason, StopReason.NO_BIN)
    assert np.all(np.isfinite(out.heatmaps))


def test_location_temperature_divides_the_logits_before_the_masked_softmax():
    # Step 1's logits: bin 100 (before step 0's bin 300: masked out), bins 400 and 500 above
    # the 0 of the rest. The recorded distribution against numpy's softmax of logits / T
    # over the allowed bins 300..N-1.
    row = peaked((100, 9.0), (400, 3.0), (500, 2.0))
    params = fake_params([VEHICLE, VEHICLE], [peaked((300, 30.0)), row])
    compiled = None
    for t in (0.5, 2.0):
        out = run_fake(params, location_temperature=t)
        # The temperature is an argument of the compiled sampler: one program for both.
        assert compiled in (None, jitted_sampler()._cache_size())
        compiled = jitted_sampler()._cache_size()
        z = row[300:] / t
        want = np.zeros(N_BINS)
        want[300:] = np.exp(z - z.max()) / np.exp(z - z.max()).sum()
        np.testing.assert_allclose(out.heatmaps[:, 1], np.tile(want, (FAKE_NUM, 1)),
                                   rtol=1e-4, atol=1e-7)
    for bad in (0, -1.0, float("inf"), float("nan"), True, "1"):
        with pytest.raises(ValueError, match="location_temperature"):
            SamplerOptions(location_temperature=bad)


def test_fake_model_boxes_are_one_draw():
    # Box mixture: a sharp component (weight 0.3) and a broad one (0.7), drawn once as in the
    # paper (supplementary 3.2: best-of-M for position, heading and velocity): the sharp size
    # ~30% of the time, where the best of M = 10 boxes would give it ~97% of the time.
    box = box_raw([0.3, 0.7], [(1.5, 4.0), (0.5, 1.0)], log_var=(-8.0, 0.0))
    spread = np.arange(8) * 128  # one vehicle per 4 grid rows
    params = fake_params([VEHICLE] * 8, [peaked((b, 30.0)) for b in spread], box=box)
    out = run_fake(params)
    sizes = out.actors.size[out.actors.valid]
    sharp = np.all(np.abs(sizes / np.array([1.5, 4.0]) - 1) < 0.05, axis=1)
    assert sizes.shape[0] == 128 and 0.15 < sharp.mean() < 0.45, (sizes.shape, sharp.mean())


def test_fake_model_collision_rejection():
    # Vehicles 4 m x 6 m. Step 0 lands on bin 100; step 1 prefers the same bin (an overlap),
    # steps 2.. the bin next to the ego (rows 15/16 and columns 15/16 surround the origin).
    box = box_raw([1.0], [(4.0, 6.0)])
    ego_bin = 15 * H + 15
    loc = [peaked((100, 30.0)), peaked((100, 30.0))] + [peaked((ego_bin, 30.0))] * 6
    out = run_fake(fake_params([VEHICLE] * 8, loc, box=box))
    a = out.actors
    assert np.all(bins_of(a)[:, 0] == 100) and np.all(bins_of(a)[:, 1] != 100)
    assert np.all(out.rejected >= 8)  # at least the first round of step 1
    assert np.all(np.isin(out.stop_reason, [StopReason.FULL, StopReason.COLLISION]))
    ego = ego_of(FAKE_CFG)
    for s in range(FAKE_NUM):
        one = slot(a, s)
        assert overlapping_pairs(one, ego) == [], s
        assert not np.any(bins_of(one)[one.valid] == ego_bin)
    # Pedestrians are never rejected: they land on the peak next to the ego.
    out = run_fake(fake_params([PEDESTRIAN], [peaked((ego_bin, 30.0))]))
    np.testing.assert_array_equal(bins_of(out.actors)[:, 0], ego_bin)
    np.testing.assert_array_equal(out.rejected, 0)


def test_fake_model_class_caps_and_given_actors():
    spread = [peaked((t * 128, 30.0)) for t in range(8)]  # far apart: no collisions
    prefs = np.array([30.0, 10.0, 0.0, NEG], np.float32)  # vehicle > pedestrian > bicyclist
    params = fake_params([prefs] * 8, spread)
    out = run_fake(params, caps=np.array([2, 8, 8]))
    a = out.actors
    np.testing.assert_array_equal(a.cls, np.tile([0, 0, 1, 1, 1, 1, 1, 1], (FAKE_NUM, 1)))
    out = run_fake(params, caps=np.array([2, 0, 3]))
    np.testing.assert_array_equal(out.actors.cls[:, :5], np.tile([0, 0, 2, 2, 2], (FAKE_NUM, 1)))
    np.testing.assert_array_equal(out.actors.valid.sum(-1), 5)
    np.testing.assert_array_equal(out.stop_reason, StopReason.STOP_TOKEN)  # every class at its cap

    # Given actors: inserted first, unchanged; they count towards the caps; sampling goes on
    # after the last given bin.
    records = [
        {"class": "bicyclist", "x": 10.3, "y": -14.0, "width": 0.7, "length": 1.8,
         "heading": 1.0, "vx": 2.0, "vy": 1.0},
        {"class": "vehicle", "x": -30.0, "y": 30.0, "width": 2.0, "length": 4.5,
         "heading": 0.5, "vx": 0.0, "vy": 0.0},
    ]
    given = actors_from_records(records, FAKE_CFG, "test")
    assert given.cls[0] == VEHICLE and int(given.valid.sum()) == 2  # sorted canonically
    out = run_fake(params, given=given, caps=np.array([2, 1, 8]))
    a = out.actors
    for field in ("cls", "position", "size", "heading", "velocity", "valid"):
        np.testing.assert_array_equal(getattr(a, field)[:, :2],
                                      np.broadcast_to(getattr(given, field)[:2],
                                                      getattr(a, field)[:, :2].shape))
    np.testing.assert_array_equal(out.num_given, 2)
    np.testing.assert_array_equal(a.cls[:, 2:4], np.tile([VEHICLE, PEDESTRIAN], (FAKE_NUM, 1)))
    assert np.all(a.cls[:, 4:][a.valid[:, 4:]] == BICYCLIST)
    b = bins_of(a)
    last_given = bins_of(given)[1]
    assert np.all(b[:, 2:][a.valid[:, 2:]] >= last_given)


# ----------------------------------------------------------------------------- real network
@pytest.fixture(scope="module")
def val_cache(tmp_path_factory, data_root):
    """A tiny-config cache of every 20th validation frame (8 scenes)."""
    from scenegen_jax.data.cache import load_cache, write_cache
    from scenegen_jax.data.sources import read_frames, source_spec

    out = str(tmp_path_factory.mktemp("cache_val_tiny"))
    drops = collections.Counter()
    write_cache(read_frames(source_spec("av2", data_root, "val", 20), drops), out, TINY, drops)
    return load_cache(out)


@pytest.fixture(scope="module")
def real_inputs(val_cache):
    """Network params that make long, crowded scenes, and maps/egos of 2 val scenes.

    Randomly initialised, with the class bias set so that stop is rare and the box means set
    to ~2 m x 4.5 m, so collision rejection is exercised."""
    from scenegen_jax.data.cache import cached_scene
    from scenegen_jax.raster.transform import crop_map

    # init_state, as the CLI's checkpoint template uses: its eager op compiles are shared.
    params = jax.tree.map(np.asarray, init_state(TINY).params)
    params["class_mlp2"]["bias"] = np.array([2.0, 0.5, 0.5, -3.0], np.float32)
    bias = params["box2_b"].copy()  # [classes, box parameters]
    mu = np.log(np.array([[2.0, 4.5], [0.6, 0.6], [0.7, 1.8]]))
    bias[:, K:3 * K] = np.repeat(mu, K, axis=0).reshape(3, K, 2).reshape(3, 2 * K)
    params["box2_b"] = bias
    crop = jax.jit(crop_map, static_argnums=2)
    maps, egos = [], []
    for i in (0, 4):
        canvas, _, ego = cached_scene(val_cache, i, TINY)
        maps.append(np.asarray(crop(jnp.asarray(canvas), 0.0, TINY)))
        egos.append(jax.tree.map(np.asarray, ego))
    return params, np.stack(maps), jax.tree.map(lambda *x: np.stack(x), *egos)


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
    Scene(actors=actors, ego=ego).validate(cfg, "sampled")  # region, canonical order, values
    pos = actors.position[:n]
    assert np.all(np.asarray(in_region(jnp.asarray(pos), cfg)))
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
                                                  model=FullGridActorGates(TINY)))
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
    actors = actors.replace(valid=actors.valid & np.asarray(in_region(actors.position, TINY)))
    real = jax.tree.map(np.asarray, canonical_order(actors, TINY))
    g = min(3, int(real.valid.sum()))
    given = jax.tree.map(lambda x: x[: TINY.max_actors].copy(), real)
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
                           cfg=TINY, options=SamplerOptions(heatmap_steps=HEATMAP_STEPS))
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
    bins = np.asarray(bin_index(actors.position[0], cfg))
    no_order = {**params, "lstm1_order": np.zeros_like(params["lstm1_order"])}
    for k in steps:
        first_k = actors.replace(valid=actors.valid & (jnp.arange(cfg.max_actors) < k))
        scene = Scene(actors=first_k, ego=ego)
        cls = jnp.asarray(out.heatmap_cls[0, 0, k])[None]
        allowed = jnp.arange(cfg.grid_size**2) >= (bins[k - 1] if k else 0)
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
    0's scenes), scene numbers outside the cache, an uncropped canvas, an empty request."""
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

    params = init_params(TINY, jax.random.key(0))
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
            jax.random.key(0), params, TINY, val_cache.maps[:2], egos)
    cropped = np.zeros((2, TINY.grid_size, TINY.grid_size, len(TINY.map_channels)), np.float32)
    refused(r"egos: \(2,\) rows for 3 maps", sample_scenes, jax.random.key(0), params, TINY,
            np.concatenate([cropped, cropped[:1]]), egos)
    refused("num_per_map must be >= 1", sample_scenes, jax.random.key(0), params, TINY,
            cropped, egos, num_per_map=0)
    for caps in ([-1, 5, 5], [1, 1], [1.5, 2, 2]):
        refused("caps: integers >= 0 of shape", sample_scenes, jax.random.key(0), params, TINY,
                cropped, egos, caps=caps)
    # A legacy uint32 key (jax.random.PRNGKey) is the same key as jax.random.key's.
    assert np.array_equal(jax.random.key_data(scene_keys(jax.random.PRNGKey(3), 2, 2)),
                          jax.random.key_data(scene_keys(jax.random.key(3), 2, 2)))

    refused("field grid_size", score_cache, params, val_cache, cpu)
    n = len(val_cache)
    for scenes in (range(0, n, 2), range(4, 2), range(0, n + 1), range(-1, 2)):
        refused(r"scenes range", score_cache, params, val_cache, TINY, scenes=scenes)
    refused("batch_size and workers must be >= 1", score_cache, params, val_cache, TINY,
            batch_size=0)
    refused("batch_size and workers must be >= 1", score_cache, params, val_cache, TINY,
            workers=0)
    refused("num_scenes must be >= 1", evaluate, params, TINY, val_cache, val_cache, 0, 0)
    refused("seed", evaluate, params, TINY, val_cache, val_cache, 2, -1)

    options = SamplerOptions(location_temperature=np.float32(0.5), proposals=np.int64(5),
                             heatmap_steps=[0, 5])
    assert (options.location_temperature, options.proposals, options.heatmap_steps) == (
        0.5, 5, (0, 5))
    assert type(options.location_temperature) is float and type(options.proposals) is int
    for steps in ((-1,), 3, (True,)):
        refused("heatmap_steps must be integers >= 0", SamplerOptions, heatmap_steps=steps)

    from scenegen_jax.data.sources import source_spec
    from scenegen_jax.data.union import load_union
    from scenegen_jax.eval.nll import summarize_by_source

    for stride in (2.5, True, 0):
        refused("stride must be an integer >= 1", source_spec, "av2", data_root, "val", stride)
    assert len(load_union(pathlib.Path(val_cache.path))) == len(val_cache)
    refused(f"scores of 2 scenes for a cache of {n}", summarize_by_source,
            {"step_valid": np.zeros((2, 3), bool)}, val_cache)
    refused(r"map_raster: shape \(48, 48, 15\)", render_scene, str(tmp_path / "x.png"),
            val_cache.maps[0], TINY.map_channels, empty_actors(1), tree_take(egos, 0), TINY)


# ----------------------------------------------------------------------------- CLI
def test_cli_sample_end_to_end(tmp_path, val_cache, monkeypatch):
    """A workdir holding an (untrained) checkpoint -> `scenegen sample` outputs."""
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.cli import main
    from scenegen_jax.data.scenarionet import frames_from_scenario, read_scenario
    from scenegen_jax.train.loop import save_or_check_config

    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, TINY)
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1)
    ckpt.save(init_state(TINY), force=True)
    ckpt.close()
    given = tmp_path / "given.jsonl"
    given.write_text(json.dumps({"actors": [
        {"class": "vehicle", "x": 12.0, "y": 3.5, "width": 2.0, "length": 4.6, "heading": 0.1,
         "vx": 5.0, "vy": 0.0},
        {"class": "pedestrian", "x": -20.0, "y": 25.0, "vx": 1.0, "vy": 0.5},
    ]}) + "\n")
    out = tmp_path / "out"
    argv = ["sample", "--workdir", workdir, "--data", val_cache.path, "--num", "2",
            "--out", str(out), "--seed", "3", "--index", "1", "5", "--batch-size", "1",
            "--heatmaps", "--given", str(given)]
    main(argv)
    rows = [json.loads(line) for line in (out / "scenes.jsonl").read_text().splitlines()]
    assert [r["map_index"] for r in rows] == [1, 5]
    for r in rows:
        assert r["num_given"] == 2 and len(r["actors"]) >= 2
        first = r["actors"][:2]
        assert first[0]["class"] == "pedestrian" and first[1]["class"] == "vehicle"
        assert first[1]["x"] == pytest.approx(12.0) and first[1]["heading"] == pytest.approx(0.1)
        for rec in r["actors"]:
            assert all(math.isfinite(rec[k]) for k in ("x", "y", "width", "length", "heading",
                                                        "vx", "vy"))
            assert abs(rec["x"]) < TINY.region_m / 2 and abs(rec["y"]) <= TINY.region_m / 2
    for r in rows:
        assert (out / "png" / f"{r['scene']}.png").stat().st_size > 1000
        assert (out / "heatmaps" / f"{r['scene']}.png").stat().st_size > 1000
        scenario = read_scenario(out / "scenarionet" / f"sd_scenegen_{r['scene']}.pkl")
        (frame, _), = frames_from_scenario(scenario, "test")
        assert frame.num_actors == len(r["actors"])
        got = sorted(map(tuple, frame.position.round(3)))
        want = sorted((round(a["x"], 3), round(a["y"], 3)) for a in r["actors"])
        np.testing.assert_allclose(got, want, atol=2e-3)
    assert (out / "scenarionet" / "dataset_summary.pkl").exists()
    # The same seed reproduces the scenes exactly.
    first = (out / "scenes.jsonl").read_text()
    main(argv[:8] + [str(tmp_path / "again")] + argv[9:])
    assert (tmp_path / "again" / "scenes.jsonl").read_text() == first
    # The records parse back (as --given input) to the same actors.
    rec = actors_from_records(rows[0]["actors"], TINY, "roundtrip")
    assert actor_records(rec) == rows[0]["actors"]
    # Given boxes that overlap the ego of a cache scene exit 2 naming the line and the actor;
    # --allow-overlap keeps them.
    overlapping = tmp_path / "overlapping.jsonl"
    overlapping.write_text("\n" + json.dumps({"actors": [
        {"class": "vehicle", "x": 3.0, "y": 0.5, "width": 2.0, "length": 4.6, "heading": 0.1,
         "vx": 0.0, "vy": 0.0}]}) + "\n")
    bad = argv[:8] + [str(tmp_path / "bad")] + argv[9:-1] + [str(overlapping)]
    with pytest.raises(SystemExit) as exit_info:
        main(bad)
    assert exit_info.value.code == 2
    assert re.match(rf"{re.escape(str(overlapping))}:2: actors\[0\] \(vehicle at x=3 m, y=0.5 m\) "
                    r"overlaps the ego \(width 1.95 m, length 4.88 m",
                    str(exit_info.value.__cause__))
    main(bad + ["--allow-overlap"])
    rows = [json.loads(line) for line in (tmp_path / "bad" / "scenes.jsonl").open()]
    assert [(r["num_given"], r["actors"][0]["x"]) for r in rows] == [(1, pytest.approx(3.0))] * 2
    # Stopped after its first scene (Ctrl-C): exit 130 and no scenes.jsonl, nor a partial one,
    # that would pass for a finished run's.
    import scenegen_jax.cli.sample as sample_cli

    written = []

    def stopped(*a, **k):
        if written:
            raise KeyboardInterrupt
        written.append(1)
        return sample_cli_write(*a, **k)

    sample_cli_write = sample_cli.write_sampled
    monkeypatch.setattr(sample_cli, "write_sampled", stopped)
    with pytest.raises(SystemExit) as exit_info:
        main(argv[:8] + [str(tmp_path / "stopped")] + argv[9:])
    assert exit_info.value.code == 130 and written
    assert len(os.listdir(tmp_path / "stopped" / "png")) == 1
    assert not [n for n in os.listdir(tmp_path / "stopped") if n.startswith("scenes.jsonl")]


def _vehicle(x, y, heading=0.0, width=2.0, length=4.0, cls="vehicle"):
    return {"class": cls, "x": x, "y": y, "width": width, "length": length, "heading": heading,
            "vx": 0.0, "vy": 0.0}


def test_given_values_must_be_finite_numbers():
    for key, value, message in [("x", True, r"not a number \(True\)"),
                                ("y", "5", r"not a number \('5'\)"),
                                ("vx", False, r"not a number \(False\)"),
                                ("width", [2.0], r"not a number"),
                                ("heading", float("inf"), "NaN or inf"),
                                ("vy", float("nan"), "NaN or inf"),
                                ("length", 10**400, "out of range")]:
        with pytest.raises(ValueError, match=rf"^f\.jsonl:3: actors\[1\]\.{key}: {message}"):
            actors_from_records([_vehicle(20.0, 5.0), {**_vehicle(10.0, -5.0), key: value}],
                                TINY, "f.jsonl:3")
    # JSON's NaN and Infinity literals are read by json.loads and refused the same way.
    row = json.loads('{"class": "pedestrian", "x": 1.0, "y": Infinity, "vx": 0, "vy": 0}')
    with pytest.raises(ValueError, match=r"actors\[0\]\.y: NaN or inf"):
        actors_from_records([row], TINY, "f.jsonl:1")


def test_given_overlaps_are_refused_unless_allowed():
    ego = np.array([[2.0, 4.0]])  # width, length m; at the origin, heading 0
    pair = [_vehicle(20.0, 5.0), _vehicle(10.0, 5.0), _vehicle(12.0, 6.5, heading=0.3)]
    with pytest.raises(ValueError, match=r"^f\.jsonl:2: actors\[1\] \(vehicle at x=10 m, "
                       r"y=5 m\) and actors\[2\] \(vehicle at x=12 m, y=6\.5 m\) overlap; "
                       r"pass --allow-overlap"):
        actors_from_records(pair, TINY, "f.jsonl:2", ego)
    on_ego = [_vehicle(-20.0, 5.0), _vehicle(1.5, 1.2, width=0.7, length=1.8, cls="bicyclist")]
    with pytest.raises(ValueError, match=r"^f\.jsonl:2: actors\[1\] \(bicyclist at x=1\.5 m, "
                       r"y=1\.2 m\) overlaps the ego \(width 2 m, length 4 m at the origin\)"):
        actors_from_records(on_ego, TINY, "f.jsonl:2", ego)
    for records in (pair, on_ego):  # allowed: kept unchanged
        kept = actors_from_records(records, TINY, "f.jsonl:2", ego, allow_overlap=True)
        assert sorted(r["x"] for r in actor_records(kept)) == sorted(r["x"] for r in records)
    # Touching is not overlapping; pedestrians are points (as in collision rejection); each
    # ego size given is checked (a longer ego reaches the vehicle ahead).
    ahead = [_vehicle(4.0, 0.0), _vehicle(0.0, 3.5, heading=math.pi / 2),
             {"class": "pedestrian", "x": 0.2, "y": 0.0, "vx": 0.0, "vy": 0.0}]
    assert int(actors_from_records(ahead, TINY, "f", ego).valid.sum()) == 3
    with pytest.raises(ValueError, match=r"actors\[0\] .* overlaps the ego \(width 2 m, "
                       r"length 6 m"):
        actors_from_records(ahead, TINY, "f", np.array([[2.0, 4.0], [2.0, 6.0]]))


def test_given_lines_are_checked_against_the_egos_they_meet():
    from scenegen_jax.cli import build_parser
    from scenegen_jax.sampling.export import given_from_lines

    ahead = json.dumps({"actors": [_vehicle(6.0, 0.0)]})  # x in [4, 8] m
    lines = [ahead, "", ahead]
    egos = np.array([[2.0, 4.0], [2.0, 10.0], [2.0, 4.0]])  # scenes 0, 1, 2: lines 1, 3, 1
    with pytest.raises(ValueError, match=r"^given.jsonl:3: actors\[0\] .* overlaps "
                       r"the ego \(width 2 m, length 10 m"):
        given_from_lines(lines, "given.jsonl", TINY, egos)
    assert len(given_from_lines(lines, "given.jsonl", TINY, egos[[0, 2, 0]])) == 2
    assert len(given_from_lines(lines, "given.jsonl", TINY, egos, allow_overlap=True)) == 2
    args = ["sample", "--workdir", "w", "--data", "d", "--num", "1", "--out", "o"]
    assert build_parser().parse_args(args + ["--allow-overlap"]).allow_overlap
    assert not build_parser().parse_args(args).allow_overlap


def test_given_records_are_validated():
    # Each error names the file and line, then the actor's field.
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors\[0\]\.class: 'truck' is not"):
        actors_from_records([{"class": "truck", "x": 0, "y": 0}], TINY, "f.jsonl:1")
    ok = {"class": "pedestrian", "x": 0, "y": 0, "vx": 0, "vy": 0}
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors\[1\]\.x/y: \(40, 0\) m lies "
                       r"outside the 80 m region"):  # the region is [-40, 40) m
        actors_from_records([ok, {**ok, "x": 40.0}], TINY, "f.jsonl:1")
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors\[0\]\.width/length: box sizes"):
        actors_from_records([{"class": "vehicle", "x": 1, "y": 1, "width": 0, "length": 4,
                              "heading": 0, "vx": 0, "vy": 0}], TINY, "f.jsonl:1")
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors\[0\]\.x: NaN or inf"):
        actors_from_records([{"class": "vehicle", "x": float("nan"), "y": 1, "width": 2,
                              "length": 4, "heading": 0, "vx": 0, "vy": 0}], TINY, "f.jsonl:1")
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors\[0\]\.vx: out of range$"):
        actors_from_records([{**ok, "vx": 10**39}], TINY, "f.jsonl:1")  # float32 tops 3.4e38
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors: 50 actors, more than max_actors"):
        actors_from_records([ok] * 50, TINY, "f.jsonl:1")
