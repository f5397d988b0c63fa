"""Prob. Grammar and Procedural baselines on real Argoverse 2 frames and synthetic maps."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.stats
import shapely

from scenegen_jax.config import get_config
from scenegen_jax.eval import baselines as B
from scenegen_jax.scene import BICYCLIST, VEHICLE, Actors, Scene, bin_index, make_ego
from scenegen_jax.vector_map import Lane, VectorMap

CFG = get_config("cpu")
LANE_CLASSES = {"VEHICLE": VEHICLE, "BUS": VEHICLE, "BIKE": BICYCLIST}


@pytest.fixture(scope="module")
def frames(all_frames):
    # Miami val frames (vehicle lanes only) and Pittsburgh train frames (with bike lanes).
    return all_frames["val"][0][::50] + all_frames["train"][0][::150]


@pytest.fixture(scope="module")
def size_kde(all_frames):
    return B.fit_size_kde(all_frames["train"][0], CFG.grid.region_m)


@pytest.fixture(scope="module")
def generated(frames, size_kde):
    out = {"prob_grammar": [], "procedural": []}
    for i, frame in enumerate(frames):
        out["prob_grammar"].append(B.prob_grammar(np.random.default_rng(i), frame, CFG))
        out["procedural"].append(B.procedural(np.random.default_rng(i), frame, CFG, size_kde))
    return out


def polygon(center, size, heading) -> shapely.Polygon:
    """Box outline built independently of the library (rotation of a local rectangle)."""
    w, length = size
    local = np.array([[length, w], [length, -w], [-length, -w], [-length, w]]) / 2
    rot = np.array([[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]])
    return shapely.Polygon(local @ rot.T + np.asarray(center))


def valid_rows(a: Actors):
    v = a.valid
    return a.cls[v], a.position[v], a.size[v], a.heading[v], a.velocity[v]


def lane_segments(vmap: VectorMap, types=None):
    """(starts [S, 2], directions [S, 2]) of every centreline segment of the given lane types."""
    starts, dirs = [], []
    for lane in vmap.lanes:
        if types is None or lane.lane_type in types:
            c = lane.centerline
            starts.append(c[:-1])
            dirs.append(np.diff(c, axis=0))
    return np.concatenate(starts), np.concatenate(dirs)


def aligned_with_nearby_lane(pos, heading, starts, dirs, radius=1.0, tol_deg=10.0) -> bool:
    """Some centreline segment within `radius` m runs within `tol_deg` of the heading."""
    d2 = np.maximum((dirs**2).sum(1), 1e-12)
    t = np.clip(((pos - starts) * dirs).sum(1) / d2, 0, 1)
    dist = np.linalg.norm(starts + t[:, None] * dirs - pos, axis=1)
    near = (dist < radius) & (d2 > 1e-8)
    diff = np.angle(np.exp(1j * (np.arctan2(dirs[near, 1], dirs[near, 0]) - heading)))
    return bool(np.any(np.abs(np.degrees(diff)) < tol_deg))


@pytest.mark.parametrize("method", ["prob_grammar", "procedural"])
def test_valid_scenes_on_real_frames(method, frames, generated):
    counts = []
    for frame, actors in zip(frames, generated[method], strict=True):
        assert actors.valid.shape == (CFG.grid.max_actors,)
        assert isinstance(actors.position, np.ndarray) and actors.position.dtype == np.float32
        Scene(actors=actors, ego=make_ego(CFG.grid.ego_size_m)).validate(
            CFG.grid
        )  # values, region, order
        cls, pos, size, heading, vel = valid_rows(actors)
        n = len(cls)
        counts.append(n)
        assert np.all(actors.valid[:n]) and not np.any(actors.valid[n:])
        assert set(cls.tolist()) <= {VEHICLE, BICYCLIST}
        assert np.all(np.abs(pos) < CFG.grid.region_m / 2)
        assert np.all(np.diff(np.asarray(bin_index(pos, CFG.grid))) >= 0)  # canonical order
        speed = np.linalg.norm(vel, axis=1)
        limits = np.array([B.SPEED_LIMIT_MS[c] for c in cls])
        assert np.all(speed <= limits + 1e-4)
        # No overlaps among actors or with the ego (shapely, independent of the SAT test).
        boxes = [polygon(p, s, h) for p, s, h in zip(pos, size, heading, strict=True)]
        ego = polygon((0.0, 0.0), frame.ego_size, 0.0)
        for i, bi in enumerate(boxes):
            assert bi.intersection(ego).area < 1e-6, f"{method}: actor {i} overlaps the ego"
            for j in range(i):
                assert bi.intersection(boxes[j]).area < 1e-6, f"{method}: {i} overlaps {j}"
        # Headings follow the lanes; velocities point along the heading.
        starts, dirs = lane_segments(frame.map)
        ok = [
            aligned_with_nearby_lane(p, h, starts, dirs) for p, h in zip(pos, heading, strict=True)
        ]
        assert np.mean(ok) >= 0.95, f"{method}: {np.mean(ok):.2f} of actors follow a lane"
        moving = speed > 0.1
        vel_dir = np.arctan2(vel[moving, 1], vel[moving, 0])
        assert np.all(np.abs(np.angle(np.exp(1j * (vel_dir - heading[moving])))) < 1e-3)
    assert min(counts) >= 5 and np.mean(counts) >= 15  # the maps hold plenty of lanes


@pytest.mark.parametrize("method", ["prob_grammar", "procedural"])
def test_classes_follow_lane_types(method, frames, generated):
    n_bikes = 0
    for frame, actors in zip(frames, generated[method], strict=True):
        cls, pos, _, heading, _ = valid_rows(actors)
        for c, types in ((VEHICLE, ("VEHICLE", "BUS")), (BICYCLIST, ("BIKE",))):
            m = cls == c
            if not m.any():
                continue
            starts, dirs = lane_segments(frame.map, types)
            ok = [
                aligned_with_nearby_lane(p, h, starts, dirs, tol_deg=180)
                for p, h in zip(pos[m], heading[m], strict=True)
            ]
            assert all(ok), f"{method}: class {c} off its lane type"
        n_bikes += int((cls == BICYCLIST).sum())
    assert n_bikes > 0  # the Pittsburgh frames have bike lanes


@pytest.mark.parametrize("method", ["prob_grammar", "procedural"])
def test_reproducible_with_a_seed(method, frames, generated, size_kde):
    frame = frames[0]

    def run(seed):
        rng = np.random.default_rng(seed)
        if method == "prob_grammar":
            return B.prob_grammar(rng, frame, CFG)
        return B.procedural(rng, frame, CFG, size_kde)

    a, b, c = run(0), run(0), run(1)
    for f in dataclasses.fields(Actors):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name))
        np.testing.assert_array_equal(getattr(a, f.name), getattr(generated[method][0], f.name))
    assert not np.array_equal(a.position, c.position)


# ------------------------------------------------------------------------ synthetic maps
def straight_lane(lane_id, y, x0, x1, lane_type="VEHICLE", successors=(), width=3.6):
    xs = np.linspace(x0, x1, 5)
    return Lane(
        id=lane_id,
        lane_type=lane_type,
        left=np.stack([xs, np.full_like(xs, y + width / 2)], 1),
        right=np.stack([xs, np.full_like(xs, y - width / 2)], 1),
        successors=tuple(successors),
    )


@dataclasses.dataclass
class FakeFrame:
    map: VectorMap
    ego_size: np.ndarray = dataclasses.field(default_factory=lambda: np.array([1.95, 4.9]))
    ego_velocity: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(2))


def test_prob_grammar_bike_lane_gets_bicyclists():
    vmap = VectorMap(
        lanes=(
            straight_lane(1, 10.0, -45, 45, "BIKE", width=1.5),
            straight_lane(2, -10.0, 45, -45, "VEHICLE"),
        )
    )
    seen = set()
    for seed in range(10):
        cls, pos, size, heading, _ = valid_rows(
            B.prob_grammar(np.random.default_rng(seed), FakeFrame(vmap), CFG)
        )
        bikes, cars = cls == BICYCLIST, cls == VEHICLE
        assert np.all(np.abs(pos[bikes, 1] - 10.0) <= B.GRAMMAR_LATERAL_OFFSET_M + 1e-5)
        assert np.all(np.abs(pos[cars, 1] + 10.0) <= B.GRAMMAR_LATERAL_OFFSET_M + 1e-5)
        assert np.all(np.abs(np.angle(np.exp(1j * heading[bikes]))) <= 0.1 + 1e-5)
        assert np.all(np.abs(np.angle(np.exp(1j * (heading[cars] - np.pi)))) <= 0.1 + 1e-5)
        for c, m in ((BICYCLIST, bikes), (VEHICLE, cars)):
            lo, hi = np.array(B.GRAMMAR_SIZE_RANGE_M[c]).T  # (width, length) bounds
            assert np.all((size[m] >= lo - 1e-5) & (size[m] <= hi + 1e-5))
        assert len(cls) <= 2 * B.GRAMMAR_MAX_ACTORS_PER_LANE
        seen |= set(cls.tolist())
    assert seen == {VEHICLE, BICYCLIST}


def test_procedural_speeds_from_time_gaps_and_the_ego_as_leader(size_kde):
    # Two routes: lane 1 (x -60..0) -> lane 2 (x 0..60) through the ego, and 3 -> 4 at y = 20.
    vmap = VectorMap(
        lanes=(
            straight_lane(1, 0.0, -60, 0, successors=(2,)),
            straight_lane(2, 0.0, 0, 60),
            straight_lane(3, 20.0, -60, 0, successors=(4,)),
            straight_lane(4, 20.0, 0, 60),
        )
    )
    frame = FakeFrame(vmap)
    limit, mean_t = B.SPEED_LIMIT_MS[VEHICLE], B.PROCEDURAL_TIME_GAP_MEAN_S
    excess, pairs = [], []
    for seed in range(40):
        cls, pos, size, heading, vel = valid_rows(
            B.procedural(np.random.default_rng(seed), frame, CFG, size_kde)
        )
        assert np.all(cls == VEHICLE)
        assert np.allclose(pos[:, 1] % 20.0, 0.0, atol=1e-4)  # on the centrelines
        assert np.allclose(np.sin(heading), 0.0, atol=1e-6) and np.all(np.cos(heading) > 0)
        speed = np.linalg.norm(vel, axis=1)
        assert np.all(speed <= limit + 1e-4)
        for y in (0.0, 20.0):
            on = np.flatnonzero(np.isclose(pos[:, 1], y, atol=1e-3))
            x, length, v = pos[on, 0], size[on, 1], speed[on]
            if y == 0.0:  # the ego is on this route, a leader like any actor
                x, length, v = np.r_[x, 0.0], np.r_[length, frame.ego_size[1]], np.r_[v, np.nan]
            order = np.argsort(x)
            x, length, v = x[order], length[order], v[order]
            gap = np.diff(x) - (length[:-1] + length[1:]) / 2  # to the next actor ahead
            assert np.all(gap > -1e-4)  # no overlaps along the route
            for g, vi, leader_is_ego in zip(gap, v[:-1], np.isnan(v[1:]), strict=True):
                if np.isnan(vi):
                    continue  # the ego follows: its speed is given, not generated
                at_limit = vi >= limit - 1e-4
                # P(speed = limit) = P(tau <= gap / limit) under tau ~ Exp(mean T).
                p = 1.0 - np.exp(-g / (limit * mean_t))
                pairs.append((bool(leader_is_ego), at_limit, p))
                if not at_limit:  # speed = gap / tau with tau > gap / limit
                    excess.append(g / vi - g / limit)
    ego, at_limit, p = np.array(pairs).T
    assert ego.sum() >= 20 and len(excess) >= 50
    # The count at the limit matches its expectation, for all pairs and the ego's followers.
    for m in (ego > 0, ego >= 0):
        sd = np.sqrt(np.sum(p[m] * (1 - p[m])))
        assert abs(at_limit[m].sum() - p[m].sum()) < 3 * sd + 1, (at_limit[m].sum(), p[m].sum())
    # Memoryless: tau - gap / limit given tau > gap / limit is Exp(mean T) again.
    se = mean_t / np.sqrt(len(excess))
    assert abs(np.mean(excess) - mean_t) < 4 * se, (np.mean(excess), len(excess))


def test_procedural_free_leader_drives_at_the_limit(size_kde):
    # A single lane far from the ego, ending inside the region: its front actor has no leader.
    vmap = VectorMap(lanes=(straight_lane(1, 15.0, -45, 30),))
    limit = B.SPEED_LIMIT_MS[VEHICLE]
    for seed in range(5):
        _, pos, _, _, vel = valid_rows(
            B.procedural(np.random.default_rng(seed), FakeFrame(vmap), CFG, size_kde)
        )
        front = np.argmax(pos[:, 0])
        assert np.linalg.norm(vel[front]) == pytest.approx(limit, rel=1e-6)


def test_empty_map_gives_an_empty_scene(size_kde):
    frame = FakeFrame(VectorMap())
    for actors in (
        B.prob_grammar(np.random.default_rng(0), frame, CFG),
        B.procedural(np.random.default_rng(0), frame, CFG, size_kde),
    ):
        assert actors.valid.shape == (CFG.grid.max_actors,) and not actors.valid.any()


def test_max_actors_caps_the_scene(frames, size_kde):
    cfg = CFG.replace(max_actors=5)
    for actors in (
        B.prob_grammar(np.random.default_rng(0), frames[0], cfg),
        B.procedural(np.random.default_rng(0), frames[0], cfg, size_kde),
    ):
        assert actors.valid.shape == (5,) and actors.valid.all()
        Scene(actors=actors, ego=make_ego(cfg.grid.ego_size_m)).validate(cfg.grid)


# ------------------------------------------------------------------------ geometry, KDE
def test_boxes_overlap_matches_shapely():
    rng = np.random.default_rng(0)
    centers = rng.uniform(-4, 4, (400, 2))
    sizes = rng.uniform(0.5, 5, (400, 2))
    headings = rng.uniform(0, 2 * np.pi, 400)
    c0, s0, h0 = np.array([0.3, -0.2]), np.array([1.9, 4.7]), 0.4
    got = B.boxes_overlap(c0, s0, h0, centers, sizes, headings)
    p0 = polygon(c0, s0, h0)
    want = [
        p0.intersection(polygon(c, s, h)).area > 1e-9
        for c, s, h in zip(centers, sizes, headings, strict=True)
    ]
    np.testing.assert_array_equal(got, want)
    assert 0.2 < np.mean(want) < 0.9  # both outcomes exercised
    assert B.boxes_overlap(c0, s0, h0, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)).shape == (
        0,
    )


def test_size_kde_matches_scipy_and_training_median(all_frames, size_kde):
    train = all_frames["train"][0]
    sizes = np.concatenate(
        [f.size[(f.cls == VEHICLE) & np.all(np.abs(f.position) < 40, 1)] for f in train]
    )
    x = np.log(sizes)
    np.testing.assert_allclose(size_kde.log_sizes[VEHICLE], x)
    ref = scipy.stats.gaussian_kde(x.T)  # Scott's rule by default
    np.testing.assert_allclose(size_kde.kernel_cov[VEHICLE], ref.covariance, rtol=1e-10)
    rng = np.random.default_rng(0)
    samples = size_kde.sample(rng, VEHICLE, 20000)
    assert np.median(samples[:, 1]) == pytest.approx(np.median(sizes[:, 1]), rel=0.05)
    assert np.median(samples[:, 0]) == pytest.approx(np.median(sizes[:, 0]), rel=0.05)
    # A KDE's variance is the data variance plus the kernel's.
    want_std = np.sqrt(x.var(0) + np.diag(ref.covariance))
    np.testing.assert_allclose(np.log(samples).std(0), want_std, rtol=0.05)
    bikes = size_kde.sample(rng, BICYCLIST, 5000)
    assert 1.0 < np.median(bikes[:, 1]) < 2.5  # bicycles are shorter than cars
    assert B.fit_size_kde(train[:3]).log_sizes[VEHICLE].shape[1] == 2


def test_size_kde_needs_vehicles():
    scene = {
        "cls": np.array([BICYCLIST]),
        "position": np.zeros((1, 2)),
        "size": np.ones((1, 2)),
        "heading": np.zeros(1),
        "velocity": np.zeros((1, 2)),
    }
    with pytest.raises(ValueError, match="vehicles"):
        B.fit_size_kde([scene])
