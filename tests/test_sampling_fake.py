"""The rollout's mechanics with a fake deterministic model: insertion order, classes and the
stop token, the ordering mask, the location temperature, one box draw, collision rejection,
class caps and given actors. One compile serves every test (one shape of inputs)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sampling_helpers import (
    N_BINS,
    NEG,
    TINY,
    H,
    K,
    bins_of,
    broadcast,
    ego_of,
    overlapping_pairs,
    slot,
)

from scenegen_jax.config import get_config
from scenegen_jax.sampling import (
    SamplerOptions,
    StopReason,
    actors_from_records,
    batch_inputs,
    sample_batch,
    scene_keys,
)
from scenegen_jax.sampling.batch import jitted_sampler
from scenegen_jax.scene import (
    BICYCLIST,
    PEDESTRIAN,
    STOP,
    VEHICLE,
)

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
        return jnp.broadcast_to(h, (1, self.cfg.grid.grid_size, self.cfg.grid.grid_size, 1))

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
    n = FAKE_CFG.grid.max_actors
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
    maps = jnp.zeros((1, H, H, len(FAKE_CFG.grid.map_channels)))
    g, c = batch_inputs(FAKE_CFG, 1, given, caps)
    options = SamplerOptions(heatmap_steps=FAKE_STEPS, location_temperature=location_temperature,
                             proposals=FAKE_CFG.sample.proposals)
    out = sample_batch(scene_keys(jax.random.key(seed), 1, num), params, maps,
                       broadcast(ego_of(FAKE_CFG), 1), g, c, cfg=FAKE_CFG.model, options=options,
                       model=FakeModel(FAKE_CFG))
    return jax.tree.map(lambda x: np.asarray(x[0]), out)


def test_candidates_take_the_map_channels_at_their_own_bins(monkeypatch):
    """The attribute MLPs' map input (`attribute_map_input`) is the map raster at each
    candidate's own bin: a model that echoes it into the box parameters, and a best-of-M
    draw that returns them as the size, give every candidate its bin's map values."""
    import scenegen_jax.sampling.placement as placement

    class MapEcho(FakeModel):
        def attributes(self, params, feat, cls, map_feat):
            return map_feat, map_feat[:, :1], map_feat[:, :2]

    def echo(keys, box, heading, velocity, classes, cfg, proposals):
        return box[:, :2], heading[:, 0], velocity

    monkeypatch.setattr(placement, "sample_attributes", echo)
    n, cm = FAKE_CFG.grid.grid_size, len(FAKE_CFG.grid.map_channels)
    map_raster = jnp.arange(n * n * cm, dtype=jnp.float32).reshape(1, n, n, cm)
    f = jnp.zeros((1, n, n, 1))
    bins, cands = placement.draw_candidates(
        jax.random.key(0),
        {},
        MapEcho(FAKE_CFG),
        f,
        map_raster,
        VEHICLE,
        jnp.zeros((n * n,)),
        FAKE_CFG.model,
        1,
        16,
    )
    bins = np.asarray(bins)
    assert len(set(bins.tolist())) > 8
    want = np.arange(n * n * cm, dtype=np.float32).reshape(n * n, cm)[bins]
    np.testing.assert_array_equal(cands.size, want[:, :2])
    np.testing.assert_array_equal(cands.heading, want[:, 0])


def test_fake_model_insertion_order_classes_and_stop():
    params = fake_params(
        [VEHICLE, PEDESTRIAN, BICYCLIST],
        [peaked((70, 30.0)), peaked((300, 30.0)), peaked((301, 30.0))],
    )
    out = run_fake(params)
    a = out.actors
    np.testing.assert_array_equal(a.valid, np.tile([1, 1, 1, 0, 0, 0, 0, 0], (FAKE_NUM, 1)) > 0)
    np.testing.assert_array_equal(
        a.cls[:, :3], np.tile([VEHICLE, PEDESTRIAN, BICYCLIST], (FAKE_NUM, 1))
    )
    np.testing.assert_array_equal(
        bins_of(a, FAKE_CFG)[:, :3], np.tile([70, 300, 301], (FAKE_NUM, 1))
    )
    np.testing.assert_array_equal(out.stop_reason, StopReason.STOP_TOKEN)
    np.testing.assert_array_equal(out.rejected, 0)
    # Nothing is written after the stop; attributes as the fake heads dictate.
    assert np.all(a.position[:, 3:] == 0) and np.all(a.size[:, 3:] == 0)
    np.testing.assert_allclose(a.size[:, 0], np.tile([1.0, 2.0], (FAKE_NUM, 1)), rtol=0.1)
    np.testing.assert_allclose(a.size[:, 1], TINY.grid.pedestrian_size_m)
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
    params = fake_params(
        [VEHICLE, VEHICLE], [peaked((500, 30.0)), peaked((100, 30.0), (700, 20.0))]
    )
    out = run_fake(params)
    np.testing.assert_array_equal(
        bins_of(out.actors, FAKE_CFG)[:, :2], np.tile([500, 700], (FAKE_NUM, 1))
    )
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
        np.testing.assert_allclose(
            out.heatmaps[:, 1], np.tile(want, (FAKE_NUM, 1)), rtol=1e-4, atol=1e-7
        )
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
    assert np.all(bins_of(a, FAKE_CFG)[:, 0] == 100) and np.all(bins_of(a, FAKE_CFG)[:, 1] != 100)
    assert np.all(out.rejected >= 8)  # at least the first round of step 1
    assert np.all(np.isin(out.stop_reason, [StopReason.FULL, StopReason.COLLISION]))
    ego = ego_of(FAKE_CFG)
    for s in range(FAKE_NUM):
        one = slot(a, s)
        assert overlapping_pairs(one, ego) == [], s
        assert not np.any(bins_of(one, FAKE_CFG)[one.valid] == ego_bin)
    # Pedestrians are never rejected: they land on the peak next to the ego.
    out = run_fake(fake_params([PEDESTRIAN], [peaked((ego_bin, 30.0))]))
    np.testing.assert_array_equal(bins_of(out.actors, FAKE_CFG)[:, 0], ego_bin)
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
        {
            "class": "bicyclist",
            "x": 10.3,
            "y": -14.0,
            "width": 0.7,
            "length": 1.8,
            "heading": 1.0,
            "vx": 2.0,
            "vy": 1.0,
        },
        {
            "class": "vehicle",
            "x": -30.0,
            "y": 30.0,
            "width": 2.0,
            "length": 4.5,
            "heading": 0.5,
            "vx": 0.0,
            "vy": 0.0,
        },
    ]
    given = actors_from_records(records, FAKE_CFG, "test")
    assert given.cls[0] == VEHICLE and int(given.valid.sum()) == 2  # sorted canonically
    out = run_fake(params, given=given, caps=np.array([2, 1, 8]))
    a = out.actors
    for field in ("cls", "position", "size", "heading", "velocity", "valid"):
        np.testing.assert_array_equal(
            getattr(a, field)[:, :2],
            np.broadcast_to(getattr(given, field)[:2], getattr(a, field)[:, :2].shape),
        )
    np.testing.assert_array_equal(out.num_given, 2)
    np.testing.assert_array_equal(a.cls[:, 2:4], np.tile([VEHICLE, PEDESTRIAN], (FAKE_NUM, 1)))
    assert np.all(a.cls[:, 4:][a.valid[:, 4:]] == BICYCLIST)
    b = bins_of(a, FAKE_CFG)
    last_given = bins_of(given, FAKE_CFG)[1]
    assert np.all(b[:, 2:][a.valid[:, 2:]] >= last_given)
