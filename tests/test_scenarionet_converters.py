"""ScenarioNet import of each converter's layout (`scenarionet_fixtures`: nuScenes, Waymo and
MetaDrive's old pickles, nuPlan, Argoverse 2): actors, ego, map channels, lane outlines,
strides, the SDC's places, sample rates and unusable map features."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import scenarionet_fixtures as fx

from scenegen_jax.config import DATASETS
from scenegen_jax.data import scenarionet as sn
from scenegen_jax.raster.map import ALL_MAP_CHANNELS, rasterize_map
from scenegen_jax.scene import PEDESTRIAN

RASTER_SIZE, RASTER_M_PER_PX = 80, 1.0


def _raster_at(raster: np.ndarray, channel: str, xy) -> float:
    """The raster's value in `channel` at the pixel holding ego-frame point xy (m)."""
    half = RASTER_SIZE * RASTER_M_PER_PX / 2
    row = int((half - xy[1]) // RASTER_M_PER_PX)
    col = int((xy[0] + half) // RASTER_M_PER_PX)
    return float(raster[row, col, ALL_MAP_CHANNELS.index(channel)])


@pytest.mark.parametrize("name", sorted(fx.BUILDERS))
def test_converter_output_imports(name):
    """Each converter's layout imports: classes, ego-frame states, lines as boundaries, roads."""
    f = fx.BUILDERS[name]()
    source = f"sd_{name}.pkl"
    [(frame, dropped)] = sn.frames_from_scenario(f.scenario, source)

    assert frame.scene_id.endswith(f"/{f.ref}")
    assert dropped == f.dropped
    assert set(frame.track_id) == set(f.actors)
    for i, tid in enumerate(frame.track_id):
        want = f.actors[str(tid)]
        assert frame.cls[i] == want.cls, tid
        np.testing.assert_allclose(frame.position[i], want.xy, atol=2e-3, err_msg=str(tid))
        np.testing.assert_allclose(frame.velocity[i], want.velocity, atol=2e-3, err_msg=str(tid))
        np.testing.assert_allclose(frame.size[i], want.size, atol=1e-5, err_msg=str(tid))
        if want.cls != PEDESTRIAN:
            dh = np.angle(np.exp(1j * (frame.heading[i] - want.heading)))
            assert abs(dh) < 1e-4, tid
    np.testing.assert_allclose(frame.ego_size, f.ego_size, atol=1e-5)
    # Only ScenarioNet's Argoverse 2 converter writes one box for every vehicle.
    assert np.all(frame.measured == (not name.startswith("argoverse2")))
    np.testing.assert_allclose(frame.ego_velocity, f.ego_velocity, atol=2e-3)
    np.testing.assert_allclose(frame.city_from_ego[:2, 2], f.ego_xy, atol=2e-3)

    vmap = frame.map
    assert len(vmap.lanes) >= 2 and vmap.lines and vmap.drivable_areas
    raster = rasterize_map(vmap, RASTER_SIZE, RASTER_M_PER_PX)
    for xy in f.crossable:
        assert _raster_at(raster, "lane_boundary_crossable", xy) == 1.0, xy
    for xy in f.uncrossable:
        assert _raster_at(raster, "lane_boundary_uncrossable", xy) == 1.0, xy
    # the road is drivable (both lanes), the ground beyond its edges is not
    for xy in ((0.0, 0.0), (20.0, 3.5), (-30.0, 1.0)):
        assert _raster_at(raster, "drivable_area", xy) == 1.0, xy
    for xy in ((0.0, -6.0), (-20.0, -4.0)):
        assert _raster_at(raster, "drivable_area", xy) == 0.0, xy
    # lanes follow the ego's direction
    assert _raster_at(raster, "lane_orientation_cos", (0.0, 0.0)) > 0.99
    assert sn.scenario_sample_rate_hz(f.scenario) == pytest.approx(f.sample_rate_hz, rel=1e-4)
    # the data set planes: the converter's metadata.dataset where the model knows it
    dataset = f.scenario.get("metadata", {}).get("dataset", "")
    assert vmap.dataset == dataset
    for known in DATASETS:
        plane = raster[..., ALL_MAP_CHANNELS.index(f"dataset_{known}")]
        assert np.all(plane == float(known == dataset)), (known, dataset)


def test_converter_lane_outlines():
    """Lane outlines from the converters' widths (Waymo) and lane polygons (nuScenes, nuPlan)."""
    for name in ("waymo", "nuscenes", "nuplan"):
        [(frame, _)] = sn.frames_from_scenario(fx.BUILDERS[name]().scenario, name)
        for lane in frame.map.lanes[:2]:
            y = lane.centerline[:, 1].mean()
            assert y == pytest.approx(0.0, abs=1e-3) or y == pytest.approx(3.5, abs=1e-3)
            # (interior points: a ray from a lane's end along its polygon's side finds no edge)
            left, right = lane.left[1:-1, 1] - y, y - lane.right[1:-1, 1]
            np.testing.assert_allclose(left, 1.75, atol=2e-3, err_msg=name)
            np.testing.assert_allclose(right, 1.75, atol=2e-3, err_msg=name)
    # nuScenes' lane connectors are intersection lanes; the straight lanes are not
    [(frame, _)] = sn.frames_from_scenario(fx.nuscenes().scenario, "n")
    assert [lane.is_intersection for lane in frame.map.lanes] == [False, False, True]
    assert frame.map.lanes[0].successors == (2,) and frame.map.lanes[2].predecessors == (0,)
    # Argoverse 2's lane ids are integers; links to lanes outside the map are kept
    [(frame, _)] = sn.frames_from_scenario(fx.argoverse2().scenario, "a")
    assert sorted(lane.id for lane in frame.map.lanes) == [2000, 2001]
    assert {lane.id: lane for lane in frame.map.lanes}[2000].successors == (2002,)


@pytest.mark.parametrize(
    ("name", "stride", "steps"),
    [
        ("waymo", 10, list(range(0, 91, 10))),
        ("nuscenes", 5, list(range(0, 41, 5))),
        ("argoverse2", 25, [0, 25, 50, 75, 100]),
        ("nuscenes_keyframes", 3, [0, 3, 6]),
    ],
)
def test_stride_frames(name, stride, steps):
    f = fx.BUILDERS[name]()
    got = sn.frames_from_scenario(f.scenario, "s.pkl", stride=stride)
    assert [int(g.frame.scene_id.rsplit("/", 1)[1]) for g in got] == steps
    # the velocity quirk is counted once per file, in the first frame
    mismatch = [g.dropped["quirk:velocity_mismatch"] for g in got]
    assert mismatch == [f.dropped["quirk:velocity_mismatch"]] + [0] * (len(got) - 1)
    for g in got:  # the "late" vehicle is an actor from its first valid step on
        late = [t for t in g.frame.track_id if t not in f.actors]
        assert len(late) == int(int(g.frame.scene_id.rsplit("/", 1)[1]) >= f.ref + 3)


def test_stride_skips_steps_where_the_sdc_is_invalid_and_checks_arguments():
    s = fx.waymo().scenario
    sdc = s["tracks"][s["metadata"]["sdc_id"]]["state"]
    sdc["valid"][20] = False
    got = sn.frames_from_scenario(s, "s.pkl", stride=10)
    assert [g.frame.scene_id.rsplit("/", 1)[1] for g in got] == [
        "0", "10", "30", "40", "50", "60", "70", "80", "90"
    ]  # fmt: skip
    # The skipped step is counted, in the first frame.
    assert [g.dropped["frame:no_ego"] for g in got] == [1] + [0] * 8
    sdc["valid"][::10] = False
    with pytest.raises(ValueError, match=r"s\.pkl: tracks\[.*\]\.state\.valid: the SDC \(ego\) "
                       r"is valid at none of the steps 0, 10, \.\.\. of 91"):
        sn.frames_from_scenario(s, "s.pkl", stride=10)
    with pytest.raises(ValueError, match=r"s\.pkl: stride: give only one"):
        sn.frames_from_scenario(s, "s.pkl", 3, stride=10)
    with pytest.raises(ValueError, match=r"s\.pkl: stride: expected a positive integer"):
        sn.frames_from_scenario(s, "s.pkl", stride=0)


def test_a_pickle_nested_too_deeply_is_a_counted_bad_file(tmp_path):
    """A track id that is a tuple nested 100,000 deep: the restricted unpickler builds it
    without recursion, but reading the ids would end `prepare` with a RecursionError."""
    from scenegen_jax.config import get_config
    from scenegen_jax.data.prepare import prepare
    from scenegen_jax.data.sources import source_spec

    sn.write_scenario(fx.waymo().scenario, tmp_path / "sd_good.pkl")
    deep = fx.waymo().scenario
    deep["tracks"]["PLACEHOLDER"] = next(iter(deep["tracks"].values()))
    raw = pickle.dumps(deep, protocol=2)  # no frames: the placeholder can be swapped
    name = b"X" + (11).to_bytes(4, "little") + b"PLACEHOLDER"  # BINUNICODE
    assert raw.count(name) == 1
    (tmp_path / "sd_deep.pkl").write_bytes(raw.replace(name, b")" + b"\x85" * 100_000))
    spec = source_spec("scenarionet", str(tmp_path), None, 10)
    summary, _ = prepare(spec, str(tmp_path / "cache"), get_config("tiny"), workers=1)
    assert summary.files == 2 and summary.bad_files == {"RecursionError": 1}
    assert summary.bad_file_list[0]["file"].endswith("sd_deep.pkl")
    assert summary.scenes == 10  # the good file's steps 0, 10, ..., 90


def test_read_scenarionet_with_stride(tmp_path):
    for name in ("waymo", "nuplan"):
        sn.write_scenario(fx.BUILDERS[name]().scenario, tmp_path / f"sd_{name}.pkl")
    got = list(sn.read_scenarionet(tmp_path, stride=20))
    assert len(got) == 5 + 2  # Waymo: 0..80 of 91 steps; nuPlan: 0, 20 of 40


def test_sdc_locations():
    """metadata.sdc_id wins; else sdc_track_index as a track id (int or str), else an index."""
    s = fx.waymo().scenario
    sdc_id = s["metadata"]["sdc_id"]
    [(want, _)] = sn.frames_from_scenario(s, "w")
    del s["metadata"]["sdc_id"]  # metadata.sdc_track_index: the SDC's index in tracks
    [(frame, _)] = sn.frames_from_scenario(s, "w")
    np.testing.assert_allclose(frame.city_from_ego, want.city_from_ego)
    del s["metadata"]["sdc_track_index"]
    for value in (int(sdc_id), sdc_id):  # top-level, a track id
        s["sdc_track_index"] = value
        [(frame, _)] = sn.frames_from_scenario(s, "w")
        np.testing.assert_allclose(frame.city_from_ego, want.city_from_ego)
    s["sdc_track_index"] = list(s["tracks"]).index(sdc_id)  # top-level, an index
    [(frame, _)] = sn.frames_from_scenario(s, "w")
    np.testing.assert_allclose(frame.city_from_ego, want.city_from_ego)
    del s["sdc_track_index"]
    with pytest.raises(ValueError, match=r"w: metadata\.sdc_id: missing"):
        sn.frames_from_scenario(s, "w")


def test_sample_rate_and_velocity_mismatch():
    assert sn.scenario_sample_rate_hz({"tracks": {}}) is None
    assert sn.scenario_sample_rate_hz({"ts": [0.0, 0.076, 0.176, 0.276]}) == pytest.approx(10.0)
    assert sn.scenario_sample_rate_hz({"metadata": {"ts": np.zeros(5)}}) is None
    # velocities that disagree with the positions: counted once, kept as they are
    f = fx.waymo()
    for track in f.scenario["tracks"].values():
        track["state"]["velocity"] *= -1
    got = sn.frames_from_scenario(f.scenario, "w.pkl", stride=30)
    assert [g.dropped["quirk:velocity_mismatch"] for g in got] == [1, 0, 0, 0]
    np.testing.assert_allclose(got[0].frame.ego_velocity, [-5.0, 0.0], atol=1e-3)


def test_malformed_and_unknown_map_features_are_counted():
    s = fx.waymo().scenario
    features = s["map_features"]
    feature = {"polygon": np.zeros((4, 3))}
    feature["type"] = feature  # a self-reference: never recursed into
    features["900"] = feature
    features["901"] = {"type": 7, "polyline": np.zeros((2, 3))}
    features["902"] = {"type": "ROAD_EDGE_SIDEWALK", "polygon": np.zeros((4, 3))}
    features["903"] = {"type": "CROSSWALK", "polygon": np.ones((2, 3))}  # too few points
    features["904"] = {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": np.ones((3, 3))}
    features["905"] = {"type": "UNKNOWN", "polyline": fx.xyz(fx.line_y(-9.0))}  # a line
    [(frame, dropped)] = sn.frames_from_scenario(s, "w.pkl")
    assert dropped["map:malformed_type"] == 2
    assert dropped["map:ROAD_EDGE_SIDEWALK"] == 1
    assert dropped["map:degenerate_crosswalk"] == 1 and dropped["map:degenerate_line"] == 1
    assert [line.mark for line in frame.map.lines].count("UNKNOWN") == 1


def test_map_geometry_nan_names_the_field():
    s = fx.nuscenes().scenario
    s["map_features"]["lane_divider_tok"]["polyline"][3, 1] = np.nan
    with pytest.raises(ValueError, match=r"map_features\['lane_divider_tok'\]\.polyline: NaN"):
        sn.frames_from_scenario(s, "n.pkl")
