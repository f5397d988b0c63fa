"""Map rasterization: hand-checkable cases and real maps, for the shapely reference
(`raster.map`) and the JAX rasteriser (`raster.jax_map`) alike, and the two against each other
at rotations."""

from __future__ import annotations

import numpy as np
import pytest

from scenegen_jax.config import ALL_LAYER_GROUPS, GridConfig, get_config
from scenegen_jax.likelihood.batch import grid_scene
from scenegen_jax.raster.jax_map import draw_maps
from scenegen_jax.raster.map import (
    ALL_MAP_CHANNELS,
    NEAREST_LANE_CHANNELS,
    NEAREST_LANE_MAX_M,
    rasterize_map,
    select_channels,
)
from scenegen_jax.raster.primitives import CENTRE_TOLERANCE_M
from scenegen_jax.scene import VEHICLE, pixel_centers, pixel_of
from scenegen_jax.vector_map import Lane, VectorMap, rotation_matrix

CH = {name: i for i, name in enumerate(ALL_MAP_CHANNELS)}


def _lane(x0, x1, y, width=3.6, **kw):
    xs = np.linspace(x0, x1, 5)
    return Lane(
        id=1,
        lane_type=kw.pop("lane_type", "VEHICLE"),
        left=np.stack([xs, np.full(5, y + width / 2)], 1),
        right=np.stack([xs, np.full(5, y - width / 2)], 1),
        **kw,
    )


def _jax_raster(vmap: VectorMap, size: int, m_per_px: float) -> np.ndarray:
    grid = GridConfig(grid_size=size, m_per_px=m_per_px)
    return np.asarray(draw_maps([vmap], np.zeros(1), grid, channels=ALL_MAP_CHANNELS)[0])


@pytest.fixture(params=["shapely", "jax"])
def rasterize(request):
    """Each rasteriser as `rasterize_map(vmap, size, m_per_px)` calls it."""
    return rasterize_map if request.param == "shapely" else _jax_raster


def test_square_drivable_area_pixel_count(rasterize):
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    r = rasterize(VectorMap(drivable_areas=(square,)), 40, 0.5)
    assert r[..., CH["drivable_area"]].sum() == 20 * 20
    # Row 0 is the top (+y): the square sits in the upper right quadrant.
    d = r[..., CH["drivable_area"]]
    assert d[:20, 20:].sum() == 400 and d[20:, :].sum() == 0


@pytest.mark.parametrize("dataset", ["av2", "waymo", "", "nuscenes"])
def test_dataset_planes_are_one_on_the_maps_own_data_set(rasterize, dataset):
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    r = rasterize(VectorMap(drivable_areas=(square,), dataset=dataset), 40, 0.5)
    for known in ("av2", "waymo"):
        assert np.array_equal(r[..., CH[f"dataset_{known}"]],
                              np.full((40, 40), float(dataset == known))), known
    # the map's other channels do not depend on it
    other = [i for name, i in CH.items() if not name.startswith("dataset_")]
    plain = rasterize(VectorMap(drivable_areas=(square,)), 40, 0.5)
    assert np.array_equal(r[..., other], plain[..., other])
    # cropping and moving the map keep it
    moved = VectorMap(dataset=dataset).transform(rotation_matrix(0.3), np.ones(2))
    assert moved.crop(np.zeros(2), 5.0).dataset == dataset


def test_lane_channels_orientation_and_marks(rasterize):
    lane = _lane(
        -10, 10, 0.0, left_mark="SOLID_YELLOW", right_mark="DASHED_WHITE", is_intersection=True
    )
    r = rasterize(VectorMap(lanes=(lane,)), 40, 1.0)
    inside = r[..., CH["lane_vehicle"]] > 0
    # Pixel centres lie at x = i - 19.5 m (column i) and y = 19.5 - j m (row j). The lane
    # covers |x| <= 10 m and |y| <= 1.8 m: columns 10-29 (x = -9.5 ... 9.5 m) and rows 18-21
    # (y = 1.5 ... -1.5 m), 20 x 4 = 80 pixels, none of their centres on its outline.
    want = np.zeros((40, 40), bool)
    want[18:22, 10:30] = True
    assert inside.sum() == 80
    np.testing.assert_array_equal(inside, want)
    assert np.allclose(r[inside, CH["lane_orientation_cos"]], 1.0)
    assert np.allclose(r[inside, CH["lane_orientation_sin"]], 0.0)
    assert np.array_equal(inside, r[..., CH["lane_intersection"]] > 0)
    # Uncrossable mark on the left (+y, upper rows), crossable on the right.
    rows_unc = np.flatnonzero(r[..., CH["lane_boundary_uncrossable"]].any(1))
    rows_cr = np.flatnonzero(r[..., CH["lane_boundary_crossable"]].any(1))
    assert rows_unc.max() < rows_cr.min()
    # A lane driven the other way flips the orientation.
    rev = Lane(id=2, lane_type="BIKE", left=lane.right[::-1], right=lane.left[::-1])
    r2 = rasterize(VectorMap(lanes=(rev,)), 40, 1.0)
    assert np.allclose(r2[r2[..., CH["lane_bike"]] > 0, CH["lane_orientation_cos"]], -1.0)


def test_nearest_lane_points_along_the_nearest_centreline_up_to_its_range(rasterize):
    """Two lanes, one driven east at y = 0 and one driven north at x = 20: every pixel takes
    the direction of the nearer centreline, on and off the lanes, and none farther than
    `NEAREST_LANE_MAX_M` from both."""
    east = _lane(-40, 10, 0.0)
    ys = np.linspace(-40, 40, 5)
    north = Lane(id=2, lane_type="VEHICLE", left=np.stack([np.full(5, 18.2), ys], 1),
                 right=np.stack([np.full(5, 21.8), ys], 1))
    size, res = 160, 1.0
    r = rasterize(VectorMap(lanes=(east, north)), size, res)
    xy = pixel_centers(get_config("tiny").replace(grid_size=size, m_per_px=res).grid)
    x, y = xy[..., 0], xy[..., 1]
    # Distance to each centreline (segments from x = -40 to 10 at y = 0; x = 20, |y| <= 40).
    d_east = np.hypot(x - np.clip(x, -40, 10), y)
    d_north = np.hypot(x - 20, y - np.clip(y, -40, 40))
    reach = np.minimum(d_east, d_north) <= NEAREST_LANE_MAX_M
    clear = np.abs(d_east - d_north) > 1.0  # away from the ties between the two
    cos, sin = r[..., CH["nearest_lane_cos"]], r[..., CH["nearest_lane_sin"]]
    pick_east = reach & clear & (d_east < d_north)
    pick_north = reach & clear & (d_north < d_east)
    assert pick_east.sum() > 1000 and pick_north.sum() > 1000
    np.testing.assert_allclose(cos[pick_east], 1.0, atol=1e-6)
    np.testing.assert_allclose(sin[pick_east], 0.0, atol=1e-6)
    np.testing.assert_allclose(sin[pick_north], 1.0, atol=1e-6)
    far = np.minimum(d_east, d_north) > NEAREST_LANE_MAX_M + 1.0
    assert far.sum() > 1000 and not np.any(cos[far]) and not np.any(sin[far])
    # Inside the lanes it agrees with the lane orientation.
    inside = r[..., CH["lane_vehicle"]] > 0
    np.testing.assert_allclose(cos[inside], r[inside, CH["lane_orientation_cos"]], atol=1e-6)


def test_crop_keeps_the_elements_whose_box_reaches_the_square():
    """`VectorMap.crop` keeps an element when its bounding box meets the square of half-side
    `radius` around the centre (edges included), for every kind of element, and crops of one
    map around different centres each see the whole map."""
    from scenegen_jax.vector_map import RoadLine

    def square(x, y, h=1.0):
        return np.array([[x - h, y - h], [x + h, y - h], [x + h, y + h], [x - h, y + h]])

    vmap = VectorMap(
        lanes=(_lane(-30, -12, 0.0), _lane(13, 30, 0.0)),  # boxes x <= -12 and x >= 13
        crosswalks=(square(0, 9),),  # box y in [8, 10]
        drivable_areas=(square(50, 50, 45),),  # box [5, 95] x [5, 95]
        lines=(RoadLine(np.array([[-5.0, -20.0], [5.0, -20.0]]), "SOLID_WHITE"),),
    )
    near = vmap.crop(np.zeros(2), 10.0)
    assert len(near.lanes) == 0 and len(near.crosswalks) == 1
    assert len(near.drivable_areas) == 1 and len(near.lines) == 0
    edge = vmap.crop(np.zeros(2), 12.0)  # the first lane's box ends at x = -12: kept
    assert [lane.right[0, 0] for lane in edge.lanes] == [-30.0]
    far = vmap.crop(np.array([0.0, -20.0]), 1.0)
    assert (len(far.lanes), len(far.crosswalks), len(far.drivable_areas), len(far.lines)) == (
        0, 0, 0, 1)
    assert len(vmap.crop(np.array([200.0, 0.0]), 10.0).lanes) == 0


def _womd_frame(womd_root):
    import os

    from scenegen_jax.data.sources import read_file, source_files, source_spec

    spec = source_spec("womd_json", os.path.join(womd_root, "gpudrive_json"), "val", 10)
    return read_file(spec, source_files(spec)[0])[0][0]


@pytest.mark.parametrize("source,size,res", [("av2", 160, 0.5), ("womd", 64, 1.25),
                                             ("av2", 48, 2.5)])
def test_nearest_lane_is_the_direction_of_a_nearest_segment_on_real_maps(
        rasterize, all_frames, womd_root, source, size, res):
    """On real maps, every pixel within range takes the direction of a centreline segment at
    the least distance from it (brute force over every segment of the map; of equally near
    segments, any), and no pixel farther than the range from every segment takes one. The
    JAX rasteriser measures against centrelines simplified within CENTRE_TOLERANCE_M: at
    least 99 % of its pixels take the direction, within 0.05, of a segment within twice that
    of the least distance."""
    frame = all_frames["val"][0][40] if source == "av2" else _womd_frame(womd_root)
    r = rasterize(frame.map, size, res)
    got = np.stack([r[..., CH[c]].ravel() for c in NEAREST_LANE_CHANNELS], 1)
    lines = [lane.centerline for lane in frame.map.lanes]
    a = np.concatenate([line[:-1] for line in lines])
    b = np.concatenate([line[1:] for line in lines])
    xy = pixel_centers(get_config("tiny").replace(grid_size=size, m_per_px=res).grid)
    xy = xy.reshape(-1, 1, 2).astype(np.float64)
    d = b - a
    length = np.linalg.norm(d, axis=1)
    t = np.clip(((xy - a) * d).sum(-1) / np.maximum(length**2, 1e-12), 0.0, 1.0)
    dist = np.linalg.norm(xy - (a + t[..., None] * d), axis=-1)  # [pixels, segments]
    least = dist.min(1)
    u = d / np.maximum(length, 1e-12)[:, None]
    reach = least <= NEAREST_LANE_MAX_M
    assert reach.mean() > 0.3 and len(a) > 100
    if rasterize is rasterize_map:
        tied = dist <= least[:, None] + 1e-6
        same = (np.abs(got[:, None] - u[None]) < 1e-3).all(-1)
        assert np.all((tied & same).any(1)[reach])
        assert not np.any(got[least > NEAREST_LANE_MAX_M + 1e-6])
    else:
        tied = dist <= least[:, None] + 2 * CENTRE_TOLERANCE_M
        same = (np.abs(got[:, None] - u[None]) < 0.05).all(-1)
        assert (tied & same).any(1)[reach].mean() >= 0.99
        assert not np.any(got[least > NEAREST_LANE_MAX_M + 2 * CENTRE_TOLERANCE_M])


def _val_maps(all_frames, womd_root, source: str) -> list[VectorMap]:
    """Maps of frames spread over a val split: the Argoverse 2 log every 1.5 s, the first
    three womd_mini scenes every 3 s."""
    if source == "av2":
        return [f.map for f in all_frames["val"][0][::15]]
    import os

    from scenegen_jax.data.sources import read_file, source_files, source_spec

    spec = source_spec("womd_json", os.path.join(womd_root, "gpudrive_json"), "val", 30)
    return [f.map for path in source_files(spec)[:3] for f in read_file(spec, path)[0]]


@pytest.mark.parametrize("source", ["av2", "womd"])
@pytest.mark.parametrize("theta_deg", [0.0, 37.0, 200.0])
def test_jax_raster_at_a_rotation_is_the_reference_raster_of_the_rotated_map(
        all_frames, womd_root, source, theta_deg):
    """The JAX rasteriser at theta draws what the shapely reference draws of the map rotated
    by theta: over frames of a val split, at least 99 % of the pixels of every channel agree
    (binary channels equal, directions within 0.05). The rest are pixel centres within float
    rounding of an edge, and nearest-lane directions where centrelines are equally near to
    within float rounding (opposite lanes on one line, lanes meeting at a point), which
    float32 and float64 resolve each their own way."""
    cfg = get_config("cpu", map_layers=ALL_LAYER_GROUPS)
    maps = _val_maps(all_frames, womd_root, source)
    theta = np.deg2rad(theta_deg)
    want = np.stack([rasterize_map(m.transform(rotation_matrix(theta), np.zeros(2)),
                                   cfg.grid.grid_size, cfg.grid.m_per_px) for m in maps])
    got = np.asarray(draw_maps(maps, [theta] * len(maps), cfg.grid, channels=ALL_MAP_CHANNELS))
    agree = (np.abs(got - want) <= 0.05).mean(axis=(0, 1, 2))
    assert agree.min() >= 0.99, dict(zip(ALL_MAP_CHANNELS, agree.round(4), strict=True))
    assert len(maps) >= 6 and want[..., CH["lane_vehicle"]].mean() > 0.05


def test_vehicles_keep_their_map_values_under_rotation(tiny_train_cache):
    cfg = get_config("tiny")
    d = cfg.grid.map_channels.index("drivable_area")
    checked = 0
    for index in range(0, len(tiny_train_cache), 7):
        m0, s0 = grid_scene(tiny_train_cache, index, cfg.grid)
        theta = 1.1
        m1, s1 = grid_scene(tiny_train_cache, index, cfg.grid, theta)
        m0, m1 = m0[..., d], m1[..., d]
        # Match actors through their rotated positions.
        p0 = s0.actors.position[s0.actors.valid]
        c0 = s0.actors.cls[s0.actors.valid]
        p1 = s1.actors.position[s1.actors.valid]
        c, s = np.cos(theta), np.sin(theta)
        for p, k in zip(p0, c0, strict=True):
            if k != VEHICLE:
                continue
            q = np.array([c * p[0] - s * p[1], s * p[0] + c * p[1]])
            if not np.any(np.linalg.norm(p1 - q, axis=1) < 1e-3):
                continue  # rotated out of the region
            r0, col0 = (int(v) for v in pixel_of(p, cfg.grid))
            r1, col1 = (int(v) for v in pixel_of(q, cfg.grid))
            window = m0[max(r0 - 1, 0) : r0 + 2, max(col0 - 1, 0) : col0 + 2]
            assert window.min() - 1e-3 <= m1[r1, col1] <= window.max() + 1e-3
            checked += 1
    assert checked > 50


def test_cached_scene_at_zero_rotation_is_the_reference_raster(tiny_train_cache):
    cfg = get_config("tiny")
    for index in (0, 3, len(tiny_train_cache) - 1):
        got, _ = grid_scene(tiny_train_cache, index, cfg.grid)
        vmap = tiny_train_cache.map_store.frame_map(index)
        want = select_channels(rasterize_map(vmap, cfg.grid.grid_size, cfg.grid.m_per_px),
                               cfg.grid)
        assert (np.abs(got - want) <= 0.05).mean(axis=(0, 1)).min() >= 0.99
