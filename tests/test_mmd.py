"""MMD with the Gaussian-TV kernel (supplementary sec. 2.2) against known answers and numpy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scenegen_jax.config import get_config
from scenegen_jax.eval import mmd as M
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE, Actors, Scene, make_ego

MAX_BIASED = 2.0 - 2.0 * math.exp(-0.5)  # TV = 1 between sets, sigma = 1


def random_scene(rng: np.random.Generator, n_slots: int = 12, p_vehicle: float = 0.6) -> dict:
    n = int(rng.integers(0, n_slots + 1))
    cls = rng.choice(
        [VEHICLE, PEDESTRIAN, BICYCLIST],
        size=n_slots,
        p=[p_vehicle, (1 - p_vehicle) / 2, (1 - p_vehicle) / 2],
    )
    return {
        "cls": cls.astype(np.int32),
        "position": rng.uniform(-50, 50, (n_slots, 2)),
        "size": np.exp(rng.normal([0.6, 1.5], [0.3, 0.5], (n_slots, 2))),
        "heading": rng.uniform(0, 2 * np.pi, n_slots),
        "velocity": rng.normal(0, 8, (n_slots, 2)),
        "valid": np.arange(n_slots) < n,
    }


def random_histograms(rng: np.random.Generator, n: int, bins: int, alpha: float = 1.0):
    return rng.dirichlet(np.full(bins, alpha), size=n)


# ---------------------------------------------------------------- an independent reference
def ref_histogram(values, edges):
    clipped = np.clip(values, edges[0], np.nextafter(edges[-1], -np.inf))
    counts, _ = np.histogram(clipped, bins=edges)
    return counts / counts.sum()


def ref_stats(scene: dict, subset: str, region_m: float | None) -> dict:
    keep = np.asarray(scene["valid"], bool).copy()
    if region_m is not None:
        for i, (x, y) in enumerate(scene["position"]):
            keep[i] &= (-region_m / 2 <= x < region_m / 2) and (-region_m / 2 <= y < region_m / 2)
    if subset == "vehicle":
        keep &= scene["cls"] == VEHICLE
    cls = scene["cls"][keep]
    boxed = cls != PEDESTRIAN
    speeds = np.hypot(scene["velocity"][keep, 0], scene["velocity"][keep, 1])
    areas = scene["size"][keep, 0] * scene["size"][keep, 1]
    w = 2 * np.pi / 16
    rel = np.array(
        [(h - scene.get("ego_heading", 0.0)) % (2 * np.pi) for h in scene["heading"][keep]]
    )
    rel = np.where(rel >= 2 * np.pi - w / 2, rel - 2 * np.pi, rel)  # bin 0 centred on 0
    out = {}
    out["class"] = np.bincount(cls, minlength=3) / len(cls) if len(cls) else None
    out["speed"] = ref_histogram(speeds, np.linspace(0, 30, 21)) if len(cls) else None
    if boxed.any():
        out["area"] = ref_histogram(areas[boxed], np.linspace(0, 40, 21))
        out["heading"] = ref_histogram(rel[boxed], (np.arange(17) - 0.5) * w)
    else:
        out["area"] = out["heading"] = None
    return out


def ref_mmd(xs: list, ys: list, sigma: float = 1.0) -> float:
    def k(p, q):
        tv = 0.5 * sum(abs(a - b) for a, b in zip(p, q, strict=True))
        return math.exp(-tv * tv / (2 * sigma * sigma))

    xx = sum(k(a, b) for a in xs for b in xs) / len(xs) ** 2
    yy = sum(k(a, b) for a in ys for b in ys) / len(ys) ** 2
    xy = sum(k(a, b) for a in xs for b in ys) / (len(xs) * len(ys))
    return xx + yy - 2 * xy


def ref_table(real: list, gen: list, region_m=None) -> dict:
    out = {}
    for subset in ("all", "vehicle"):
        for stat in ("class", "area", "speed", "heading"):
            if subset == "vehicle" and stat == "class":
                continue
            xs = [h for s in real if (h := ref_stats(s, subset, region_m)[stat]) is not None]
            ys = [h for s in gen if (h := ref_stats(s, subset, region_m)[stat]) is not None]
            out[f"{stat}/{subset}"] = ref_mmd(xs, ys)
    return out


# ---------------------------------------------------------------- estimator
def test_identical_sets_biased_is_exactly_zero():
    h = random_histograms(np.random.default_rng(0), 40, 8)
    assert M.mmd(h, h.copy()) == 0.0


def test_identical_sets_unbiased_matches_closed_form_and_is_small():
    h = random_histograms(np.random.default_rng(1), 200, 8)
    k = M.tv_kernel(h, h)
    m = len(h)
    mu_off = (k.sum() - m) / (m * (m - 1))
    # Within-set terms drop the diagonal, the cross term keeps it: 2 (mu_off - 1) / m.
    assert M.mmd(h, h, unbiased=True) == pytest.approx(2 * (mu_off - 1) / m, rel=1e-9)
    assert abs(M.mmd(h, h, unbiased=True)) < 0.01


def test_same_distribution_unbiased_near_zero_biased_positive():
    rng = np.random.default_rng(2)
    a, b = random_histograms(rng, 300, 6), random_histograms(rng, 300, 6)
    unbiased, biased = M.mmd(a, b, unbiased=True), M.mmd(a, b)
    assert abs(unbiased) < 5e-3
    assert biased > unbiased  # the V-statistic carries a positive O(1/m) bias


def test_different_distributions_are_farther_than_same():
    rng = np.random.default_rng(3)
    a, b = random_histograms(rng, 100, 6), random_histograms(rng, 100, 6)
    c = random_histograms(rng, 100, 6, alpha=0.1)  # peaked histograms
    assert M.mmd(a, c) > 10 * M.mmd(a, b)


def test_disjoint_supports_give_the_maximum():
    a = np.tile([1.0, 0.0, 0.0], (5, 1))
    b = np.tile([0.0, 0.0, 1.0], (7, 1))
    assert M.mmd(a, b) == pytest.approx(MAX_BIASED, abs=1e-12)
    assert M.mmd(a, b, unbiased=True) == pytest.approx(MAX_BIASED, abs=1e-12)
    # No pair of sets exceeds it.
    rng = np.random.default_rng(4)
    for _ in range(20):
        x, y = random_histograms(rng, 5, 3, 0.2), random_histograms(rng, 6, 3, 0.2)
        assert M.mmd(x, y) <= MAX_BIASED + 1e-12


def test_disjoint_scenes_class_row_is_the_maximum():
    def scene(cls):
        return {
            "cls": np.array([cls, cls]),
            "position": np.zeros((2, 2)),
            "size": np.ones((2, 2)),
            "heading": np.zeros(2),
            "velocity": np.zeros((2, 2)),
        }

    table = M.mmd_table([scene(VEHICLE)] * 3, [scene(BICYCLIST)] * 4)
    assert table["class/all"] == pytest.approx(MAX_BIASED, abs=1e-12)
    assert table["area/all"] == 0.0  # same boxes, speeds and headings
    assert math.isnan(table["area/vehicle"])  # no generated scene has a vehicle


def test_hand_computed_small_case():
    e1, e2 = math.exp(-0.125), math.exp(-0.5)  # k at TV = 0.5 and TV = 1
    a = np.array([[1.0, 0.0], [0.5, 0.5]])
    b = np.array([[0.0, 1.0]])
    # xx = (1 + 1 + 2 e1) / 4, yy = 1, xy = (e2 + e1) / 2.
    assert M.mmd(a, b) == pytest.approx((1 + e1) / 2 + 1 - (e2 + e1), rel=1e-12)
    assert math.isnan(M.mmd(a, b, unbiased=True))  # one generated scene: no U-statistic
    b2 = np.array([[0.0, 1.0], [0.0, 1.0]])
    assert M.mmd(a, b2, unbiased=True) == pytest.approx(e1 + 1 - (e2 + e1), rel=1e-12)
    # sigma enters as TV^2 / (2 sigma^2).
    s = 0.5
    k1, k2 = math.exp(-0.25 / (2 * s * s)), math.exp(-1 / (2 * s * s))
    assert M.mmd(a, b, sigma=s) == pytest.approx((1 + k1) / 2 + 1 - (k2 + k1), rel=1e-12)


def test_symmetry_and_chunking():
    rng = np.random.default_rng(5)
    a, b = random_histograms(rng, 30, 5), random_histograms(rng, 17, 5, 0.3)
    for unbiased in (False, True):
        assert M.mmd(a, b, unbiased=unbiased) == pytest.approx(
            M.mmd(b, a, unbiased=unbiased), abs=1e-14
        )
    np.testing.assert_allclose(M.tv_kernel(a, b, chunk=7), M.tv_kernel(a, b), rtol=0, atol=0)


def test_shape_errors():
    with pytest.raises(ValueError, match="histograms"):
        M.mmd(np.ones((3, 4)), np.ones((3, 5)))
    with pytest.raises(ValueError, match="one scene"):
        M.scene_arrays(
            {"cls": np.zeros((2, 3)), "position": 0, "size": 0, "heading": 0, "velocity": 0}
        )


# ---------------------------------------------------------------- scene statistics
def test_hand_computed_scene_histograms():
    scene = {
        "cls": np.array([VEHICLE, VEHICLE, PEDESTRIAN, BICYCLIST]),
        "position": np.zeros((4, 2)),
        "size": np.array([[2.0, 5.0], [3.0, 20.0], [0.6, 0.6], [0.5, 1.0]]),  # 10, 60, -, 0.5 m^2
        "heading": np.array([0.0, np.pi, 1.0, 2 * np.pi - 0.1]),
        "velocity": np.array([[0.0, 0.0], [3.0, 0.0], [0.0, -1.0], [30.0, 40.0]]),  # 0 3 1 50
    }
    st = M.scene_statistics(scene)
    np.testing.assert_allclose(st["class"], [0.5, 0.25, 0.25])
    area = np.zeros(20)
    area[[5, 19, 0]] = 1 / 3  # [10, 12), beyond 40 -> last, [0, 2)
    np.testing.assert_allclose(st["area"], area)
    speed = np.zeros(20)
    speed[[0, 2, 19]] = [0.5, 0.25, 0.25]  # 0 and 1 m/s in [0, 1.5), 3 in [3, 4.5), 50 -> last
    np.testing.assert_allclose(st["speed"], speed)
    heading = np.zeros(16)
    heading[[0, 8]] = [2 / 3, 1 / 3]  # 0 and -0.1 rad (wrapped) in the bin centred on 0; pi
    np.testing.assert_allclose(st["heading"], heading)
    veh = M.scene_statistics(scene, "vehicle")
    np.testing.assert_allclose(veh["class"], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(veh["speed"][[0, 2]], [0.5, 0.5])


def test_heading_is_relative_to_the_ego():
    cfg = get_config("tiny")
    actors = Actors(
        cls=np.array([VEHICLE]),
        position=np.zeros((1, 2)),
        size=np.ones((1, 2)),
        heading=np.array([0.5 * np.pi]),
        velocity=np.zeros((1, 2)),
        valid=np.array([True]),
    )
    scene = Scene(actors=actors, ego=make_ego(cfg.grid.ego_size_m, heading=0.5 * np.pi))
    assert M.scene_statistics(scene)["heading"][0] == 1.0
    assert M.scene_statistics(actors)["heading"][4] == 1.0  # 90 degrees, ego heading 0


def test_empty_scenes_are_discarded():
    rng = np.random.default_rng(6)
    real = [random_scene(rng) for _ in range(20)]
    gen = [random_scene(rng, p_vehicle=0.3) for _ in range(15)]
    empty = dict(random_scene(rng), valid=np.zeros(12, bool))
    peds = {
        "cls": np.array([PEDESTRIAN]),
        "position": np.zeros((1, 2)),
        "size": np.ones((1, 2)),
        "heading": np.zeros(1),
        "velocity": np.array([[1.0, 0.0]]),
    }
    base = M.mmd_table(real, gen)
    assert M.mmd_table(real + [empty] * 5, gen + [empty]) == base
    h = M.scene_histograms([peds, empty, peds])
    assert {k: len(v) for k, v in h.items()} == {"class": 2, "speed": 2, "area": 0, "heading": 0}
    h = M.scene_histograms([peds, empty, real[0]], "vehicle")
    n_veh = int(((real[0]["cls"] == VEHICLE) & real[0]["valid"]).any())
    assert {k: len(v) for k, v in h.items()} == {s: n_veh for s in M.STATISTICS}
    # A pedestrian-only scene changes class and speed rows only.
    with_peds = M.mmd_table(real + [peds], gen)
    for key in ("area/all", "heading/all", "area/vehicle", "speed/vehicle", "heading/vehicle"):
        assert with_peds[key] == base[key]
    assert with_peds["class/all"] != base["class/all"]


def test_table_matches_independent_numpy_reference():
    rng = np.random.default_rng(7)
    real = [random_scene(rng) for _ in range(25)]
    gen = [random_scene(rng, p_vehicle=0.8) for _ in range(18)]
    for s in gen[::3]:
        s["ego_heading"] = float(rng.uniform(0, 2 * np.pi))
    got = M.mmd_table(real, gen)
    want = ref_table(real, gen)
    assert (
        set(got)
        == set(want)
        == {
            "class/all",
            "area/all",
            "speed/all",
            "heading/all",
            "area/vehicle",
            "speed/vehicle",
            "heading/vehicle",
        }
    )
    for key in want:
        assert got[key] == pytest.approx(want[key], rel=1e-9, abs=1e-12), key
    assert all(0 < v < MAX_BIASED for v in got.values())
    # Restricting to the region drops the far actors, as the reference does.
    got_r = M.mmd_table(real, gen, region_m=80.0)
    want_r = ref_table(real, gen, region_m=80.0)
    for key in want_r:
        assert got_r[key] == pytest.approx(want_r[key], rel=1e-9, abs=1e-12), key
    assert got_r != got


def test_actors_with_valid_mask_equal_dicts():
    rng = np.random.default_rng(8)
    dicts = [random_scene(rng) for _ in range(6)]
    actors = [Actors(**{k: np.asarray(v) for k, v in d.items()}) for d in dicts]
    for stat, h in M.scene_histograms(dicts).items():
        np.testing.assert_array_equal(M.scene_histograms(actors)[stat], h)
