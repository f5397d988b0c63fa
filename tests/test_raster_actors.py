"""Actor rasterization: coverage against shapely, motion channels, masking, jit/vmap, scan."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import shapely

from scenegen_jax.config import get_config
from scenegen_jax.raster.actors import (
    ACTOR_CHANNELS,
    actor_rasters_sequence,
    box_coverage,
    draw_actor,
    empty_actor_raster,
    rasterize_actors,
    window_size,
)
from scenegen_jax.scene import (
    BICYCLIST,
    PEDESTRIAN,
    VEHICLE,
    Actors,
    make_ego,
    pixel_centers,
    pixel_of,
)

CH = {name: i for i, name in enumerate(ACTOR_CHANNELS)}


def _cfg(grid_size: int, m_per_px: float):
    return get_config("tiny").replace(grid_size=grid_size, m_per_px=m_per_px)


def _polygon(center, size, heading) -> shapely.Polygon:
    width, length = size
    rot = np.array([[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]])
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * [length / 2, width / 2]
    return shapely.Polygon(corners @ rot.T + np.asarray(center))


def _pixel_boxes(cfg) -> np.ndarray:
    c = pixel_centers(cfg.grid).astype(np.float64)
    h = cfg.grid.m_per_px / 2
    return shapely.box(c[..., 0] - h, c[..., 1] - h, c[..., 0] + h, c[..., 1] + h)


def _actor(cls, position, size, heading, velocity, valid=True) -> Actors:
    return Actors(
        cls=jnp.int32(cls),
        position=jnp.asarray(position, jnp.float32),
        size=jnp.asarray(size, jnp.float32),
        heading=jnp.float32(heading),
        velocity=jnp.asarray(velocity, jnp.float32),
        valid=jnp.bool_(valid),
    )


def _random_actors(rng: np.random.Generator, n: int, cfg, n_valid: int) -> Actors:
    half = cfg.grid.region_m / 2
    return Actors(
        cls=jnp.asarray(rng.integers(0, 3, n), jnp.int32),
        position=jnp.asarray(rng.uniform(-half, half, (n, 2)), jnp.float32),
        size=jnp.asarray(rng.uniform([1.0, 2.0], [2.5, 8.0], (n, 2)), jnp.float32),
        heading=jnp.asarray(rng.uniform(0, 2 * np.pi, n), jnp.float32),
        velocity=jnp.asarray(rng.normal(0, 5, (n, 2)), jnp.float32),
        valid=jnp.asarray(np.arange(n) < n_valid),
    )


BOXES = [
    # (grid_size, m_per_px, center m, (width, length) m, heading deg)
    (64, 1.0, (3.3, -2.7), (1.9, 4.5), 30.0),
    (64, 1.0, (-7.2, 5.1), (2.5, 12.0), 117.0),
    (128, 0.25, (1.1, 0.4), (2.5, 12.0), 30.0),
    (128, 0.25, (-4.37, 3.81), (1.9, 4.5), 251.0),
    (64, 1.0, (0.3, 0.2), (1.1, 0.9), 37.0),  # about a pixel
    (32, 2.5, (6.0, -11.0), (1.9, 4.5), 300.0),  # under 2 pixels long
    (64, 1.0, (30.5, -29.0), (1.9, 4.5), 45.0),  # crosses the grid edge (clipped window)
]


@pytest.mark.parametrize("grid_size,m_per_px,center,size,heading_deg", BOXES)
def test_box_coverage_matches_shapely(grid_size, m_per_px, center, size, heading_deg):
    cfg = _cfg(grid_size, m_per_px)
    heading = np.deg2rad(heading_deg)
    cov = np.asarray(box_coverage(jnp.asarray(center), jnp.asarray(size), heading, cfg.grid))
    assert cov.shape == (grid_size, grid_size) and cov.dtype == np.float32
    assert cov.min() >= 0.0 and cov.max() <= 1.0 + 1e-6

    poly = _polygon(center, size, heading)
    region = shapely.box(*(2 * [-cfg.grid.region_m / 2]), *(2 * [cfg.grid.region_m / 2]))
    area = shapely.intersection(poly, region).area
    np.testing.assert_allclose(cov.sum() * cfg.grid.bin_area, area, rtol=0.05)

    pixels = _pixel_boxes(cfg)
    inside = shapely.contains_properly(poly, pixels)
    outside = ~shapely.intersects(poly, pixels)
    centers = pixel_centers(cfg.grid)
    centre_in = shapely.contains_xy(poly, centers[..., 0], centers[..., 1])
    assert np.all(centre_in[inside]) and not np.any(centre_in[outside])
    assert np.all(cov[inside] > 0.999)
    assert np.all(cov[outside] < 1e-3)
    # Partially covered pixels: coverage close to the exact area fraction.
    exact = shapely.area(shapely.intersection(pixels, poly)) / cfg.grid.bin_area
    np.testing.assert_allclose(cov, exact, atol=0.03)


def test_window_equals_full_grid():
    cfg = _cfg(128, 0.25)
    for center, size, heading in [((1.0, -2.0), (2.2, 9.0), 0.7), ((-15.9, 15.8), (1.9, 4.5), 2.0)]:
        args = (jnp.asarray(center), jnp.asarray(size), heading, cfg.grid)
        assert window_size(cfg.grid) < cfg.grid.grid_size
        windowed = box_coverage(*args)
        full = box_coverage(*args, max_box_m=1e6)
        np.testing.assert_allclose(windowed, full, atol=1e-6)
        assert float(full.sum()) > 0


@pytest.mark.parametrize("grid_size,m_per_px", [(32, 2.5), (64, 0.25)])
def test_pedestrian_nominal_footprint(grid_size, m_per_px):
    cfg = _cfg(grid_size, m_per_px)
    # Size and heading of a pedestrian are ignored.
    ped = _actor(PEDESTRIAN, (1.3, -0.7), (5.0, 9.0), 1.0, (1.0, 0.5))
    raster = draw_actor(empty_actor_raster(cfg.grid), ped, False, cfg.grid)
    occ = np.asarray(raster[..., CH["occ_pedestrian"]])
    np.testing.assert_allclose(occ.sum() * cfg.grid.bin_area, cfg.grid.pedestrian_size_m**2,
                               rtol=0.05)
    for name in ("occ_ego", "occ_vehicle", "occ_bicyclist", "heading_cos", "heading_sin"):
        assert float(jnp.abs(raster[..., CH[name]]).max()) == 0.0, name


@pytest.mark.parametrize("cls,channel", [(VEHICLE, "occ_vehicle"), (BICYCLIST, "occ_bicyclist")])
def test_motion_channels_at_centre(cls, channel):
    cfg = _cfg(64, 1.0)
    heading, velocity = 2.4, (-3.0, 4.0)
    actor = _actor(cls, (5.5, 8.5), (2.0, 4.0), heading, velocity)
    raster = draw_actor(empty_actor_raster(cfg.grid), actor, False, cfg.grid)
    row, col = (int(i) for i in pixel_of(actor.position, cfg.grid))
    px = np.asarray(raster[row, col])
    assert px[CH[channel]] == pytest.approx(1.0)
    np.testing.assert_allclose(
        px[CH["speed"] :], [5.0, -0.6, 0.8, np.cos(heading), np.sin(heading)], atol=1e-5
    )
    others = [
        c for c in ("occ_ego", "occ_vehicle", "occ_pedestrian", "occ_bicyclist") if c != channel
    ]
    assert float(jnp.abs(raster[..., [CH[c] for c in others]]).max()) == 0.0
    # Outside the box nothing is written.
    assert np.all(np.asarray(raster[0, 0]) == 0.0)


def test_ego_channel_and_stationary_direction():
    cfg = _cfg(32, 2.5)
    ego = make_ego(
        cfg.grid.ego_size_m, velocity=(0.1, 0.0)
    )  # below cfg.grid.zero_speed: direction undefined
    raster = draw_actor(empty_actor_raster(cfg.grid), ego, True, cfg.grid)
    centre = np.asarray(raster[cfg.grid.grid_size // 2, cfg.grid.grid_size // 2])
    assert float(raster[..., CH["occ_ego"]].sum() * cfg.grid.bin_area) == pytest.approx(
        cfg.grid.ego_size_m[0] * cfg.grid.ego_size_m[1], rel=0.05
    )
    assert float(raster[..., CH["occ_vehicle"]].max()) == 0.0
    assert centre[CH["vel_cos"]] == 0.0 and centre[CH["vel_sin"]] == 0.0
    assert centre[CH["heading_cos"]] > 0  # some heading was written where covered


def test_invalid_actor_leaves_raster_unchanged():
    cfg = _cfg(32, 2.5)
    base = rasterize_actors(
        _random_actors(np.random.default_rng(0), 5, cfg, 5),
        make_ego(cfg.grid.ego_size_m),
        cfg.grid,
        5,
    )
    actor = _actor(VEHICLE, (0.0, 0.0), (2.0, 5.0), 0.3, (2.0, 1.0), valid=False)
    np.testing.assert_array_equal(draw_actor(base, actor, False, cfg.grid), base)
    drawn = draw_actor(base, actor.replace(valid=jnp.bool_(True)), False, cfg.grid)
    assert not np.array_equal(drawn, base)  # the same actor, valid, does draw


def test_occupancy_is_max_and_motion_overwrites():
    cfg = _cfg(64, 1.0)
    a = _actor(VEHICLE, (0.5, 0.5), (2.0, 6.0), 0.0, (3.0, 0.0))
    b = _actor(VEHICLE, (0.5, 0.5), (2.0, 6.0), np.pi / 2, (0.0, 7.0))
    raster = draw_actor(
        draw_actor(empty_actor_raster(cfg.grid), a, False, cfg.grid), b, False, cfg.grid
    )
    row, col = (int(i) for i in pixel_of(a.position, cfg.grid))
    assert float(raster[row, col, CH["occ_vehicle"]]) == pytest.approx(1.0)
    assert float(raster[row, col, CH["speed"]]) == pytest.approx(7.0)
    union = _polygon((0.5, 0.5), (2.0, 6.0), 0.0).union(_polygon((0.5, 0.5), (2.0, 6.0), np.pi / 2))
    area = float(raster[..., CH["occ_vehicle"]].sum()) * cfg.grid.bin_area
    assert area == pytest.approx(union.area, rel=0.05)


def test_upto_counts_and_jit_matches_eager():
    cfg = _cfg(32, 2.5)
    actors = _random_actors(np.random.default_rng(1), 6, cfg, 4)
    ego = make_ego(cfg.grid.ego_size_m, velocity=(3.0, 0.0))
    eager = rasterize_actors(actors, ego, cfg.grid, 3)
    jitted = jax.jit(functools.partial(rasterize_actors, grid=cfg.grid))
    np.testing.assert_allclose(jitted(actors, ego, upto=jnp.int32(3)), eager, atol=1e-6)
    # Drawing more actors adds occupancy; invalid slots (index >= 4) add nothing.
    occ = [float(rasterize_actors(actors, ego, cfg.grid, k)[..., 1:4].sum()) for k in range(7)]
    assert occ[0] == 0.0 and all(occ[k + 1] > occ[k] for k in range(3))
    assert occ[4] == occ[5] == occ[6]


def test_vmap_over_batch():
    cfg = _cfg(32, 2.5)
    rng = np.random.default_rng(2)
    batch = [_random_actors(rng, 5, cfg, v) for v in (5, 2, 0)]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *batch)
    egos = jax.tree.map(
        lambda *x: jnp.stack(x), *[make_ego(cfg.grid.ego_size_m, (float(i), 0.0)) for i in range(3)]
    )
    upto = jnp.array([5, 1, 3], jnp.int32)
    fn = jax.jit(jax.vmap(functools.partial(rasterize_actors, grid=cfg.grid)))
    out = fn(stacked, egos, upto=upto)
    assert out.shape == (3, 32, 32, 9)
    for b in range(3):
        ego = jax.tree.map(lambda x, b=b: x[b], egos)
        ref = rasterize_actors(batch[b], ego, cfg.grid, int(upto[b]))
        np.testing.assert_allclose(out[b], ref, atol=1e-6)


def test_sequence_matches_rasterize():
    cfg = _cfg(32, 2.5)
    n = 6
    actors = _random_actors(np.random.default_rng(3), n, cfg, 5)
    ego = make_ego(cfg.grid.ego_size_m, velocity=(2.0, 1.0))
    seq = jax.jit(functools.partial(actor_rasters_sequence, grid=cfg.grid))(actors, ego)
    assert seq.shape == (n + 1, 32, 32, 9)
    for i in range(n + 1):
        np.testing.assert_allclose(seq[i], rasterize_actors(actors, ego, cfg.grid, i), atol=1e-6)
    assert not np.array_equal(seq[0], seq[1])
    np.testing.assert_array_equal(seq[5], seq[6])  # slot 5 is invalid
