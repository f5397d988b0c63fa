"""Sampling an actor's attributes and testing boxes for overlap: the box test against
shapely, best-of-M against the most likely of M draws written out, and the mixtures' modes
and standing share it keeps."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from sampling_helpers import (
    TINY,
    K,
    box_polygon,
)

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
    MAX_SIZE_M,
    MAX_SPEED_MPS,
    MIN_SIZE_M,
    sample_attributes,
)
from scenegen_jax.scene import (
    BICYCLIST,
    PEDESTRIAN,
    VEHICLE,
)


def test_boxes_overlap_matches_shapely():
    rng = np.random.default_rng(0)
    n = 3000
    ca, cb = rng.uniform(-4, 4, (n, 2)), rng.uniform(-4, 4, (n, 2))
    sa, sb = rng.uniform(0.3, 5, (n, 2)), rng.uniform(0.3, 5, (n, 2))
    ha, hb = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n)
    got = np.asarray(jax.jit(jax.vmap(boxes_overlap))(ca, sa, ha, cb, sb, hb))
    areas = np.array([box_polygon(ca[i], sa[i], ha[i]).intersection(
        box_polygon(cb[i], sb[i], hb[i])).area for i in range(n)])
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
    size, head, vel = map(np.asarray, fn(keys, *raws, cls, cfg=TINY.model, proposals=m))

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
            zero = TINY.grid.zero_speed
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
    np.testing.assert_allclose(size[2], [TINY.grid.pedestrian_size_m] * 2)
    walking = np.hypot(*vel[2]) > TINY.grid.zero_speed
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
    k = TINY.model.num_mixtures
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
                                    cfg=TINY.model, proposals=m))
    speed = np.hypot(*v.T)
    standing = speed <= TINY.grid.zero_speed
    assert abs(standing.mean() - 0.5) < 0.04
    # Best of 10 draws from LN(log 10, 0.5) lies near the mode of log speed: median ~10 m/s.
    assert abs(np.median(speed[~standing]) / 10.0 - 1.0) < 0.05
    np.testing.assert_allclose(np.median(size, axis=0), [2.0, 4.5], rtol=0.03)
