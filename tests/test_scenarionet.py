"""ScenarioNet import/export and the restricted unpickler."""

from __future__ import annotations

import collections
import glob
import os
import pickle

import numpy as np
import pytest
import scenarionet_fixtures as fx
import shapely
from frames import frame_differences

from scenegen_jax.config import DATASETS
from scenegen_jax.data import scenarionet as sn
from scenegen_jax.data.safe_pickle import (
    CorruptPickleError,
    UnsafePickleError,
    dump_pickle,
    load_pickle,
)
from scenegen_jax.frame import Frame
from scenegen_jax.raster.map import ALL_MAP_CHANNELS, rasterize_map
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE
from scenegen_jax.vector_map import ROAD_EDGE, Lane, RoadLine, VectorMap, rotation_matrix

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WOMD_ROOT = os.path.normpath(os.path.join(REPO, "..", "shared", "data", "womd_mini", "scenarionet"))


def _hand_frame() -> Frame:
    """Two actors of each class, a curved lane, a bus lane, a crosswalk, a drivable area, a road
    edge and a painted line."""
    lane = Lane(
        id=7,
        lane_type="VEHICLE",
        left=np.array([[-20.0, 1.9], [0.0, 1.8], [20.0, 2.5], [30.0, 4.0]]),
        right=np.array([[-20.0, -1.7], [0.0, -1.8], [25.0, -1.0]]),
        left_mark="DASHED_WHITE",
        right_mark="SOLID_YELLOW",
        is_intersection=False,
        successors=(8,),
        predecessors=(3, 4),
    )
    bus = Lane(
        id=8,
        lane_type="BUS",
        left=np.array([[30.0, 4.0], [40.0, 9.0]]),
        right=np.array([[25.0, -1.0], [38.0, 5.0]]),
        left_mark="NONE",
        right_mark="DOUBLE_DASH_WHITE",
        is_intersection=True,
        predecessors=(7,),
    )
    vmap = VectorMap(
        lanes=(lane, bus),
        crosswalks=(np.array([[5.0, -6.0], [8.0, -6.0], [8.0, 6.0], [5.0, 6.0]]),),
        drivable_areas=(np.array([[-30.0, -10.0], [40.0, -10.0], [40.0, 12.0], [-30.0, 12.0]]),),
        lines=(
            RoadLine(np.array([[-30.0, -9.5], [40.0, -9.7]]), ROAD_EDGE),
            RoadLine(np.array([[-30.0, 5.4], [0.0, 5.5], [30.0, 5.45]]), "DOUBLE_DASH_YELLOW"),
        ),
    )
    cls = np.array([VEHICLE, PEDESTRIAN, BICYCLIST, VEHICLE, PEDESTRIAN, BICYCLIST], np.int32)
    return Frame(
        scene_id="log_a/315967376859506000",
        source="hand",
        cls=cls,
        position=np.array(
            [[10.0, 3.5], [-4.2, 7.9], [15.5, -2.0], [-18.0, -3.3], [6.0, -7.0], [30.1, 5.5]]
        ),
        size=np.array([[1.9, 4.6], [0.6, 0.5], [0.7, 1.8], [2.1, 5.2], [0.5, 0.5], [0.8, 1.9]]),
        heading=np.array([0.1, 3.0, 6.2831, 4.5, 0.0, 1.2]),
        velocity=np.array([[5.0, 0.5], [0.0, -1.2], [4.0, -0.1], [-3.0, 0.0], [0.3, 0.3], [2, 4]]),
        track_id=np.array(["veh_a", "ped_a", "cyc_a", "veh_b", "ped_b", "cyc_b"]),
        ego_velocity=np.array([7.5, -0.2]),
        ego_size=np.array([1.95, 4.9]),
        map=vmap,
        city_from_ego=np.array([[0.6, -0.8, 1200.0], [0.8, 0.6, -350.5], [0.0, 0.0, 1.0]]),
    )


def _standard_scenario(t_len: int = 3) -> dict:
    """A scenario shaped like ScenarioNet's converters write it: standard keys only, world frame."""

    def track(ttype, xy, heading, velocity, length=4.5, width=2.0, valid=None):
        """Constant per-step values; `xy` may also be a [T, 2] array."""
        positions = np.broadcast_to(np.asarray(xy, np.float32), (t_len, 2))
        return {
            "type": ttype,
            "state": {
                "position": np.concatenate([positions, np.zeros((t_len, 1), np.float32)], 1),
                "length": np.full(t_len, length, np.float32),
                "width": np.full(t_len, width, np.float32),
                "height": np.full(t_len, 1.5, np.float32),
                "heading": np.full(t_len, heading, np.float32),
                "velocity": np.tile(np.asarray(velocity, np.float32), (t_len, 1)),
                "valid": np.ones(t_len, bool) if valid is None else np.asarray(valid),
            },
            "metadata": {"track_length": t_len, "type": ttype, "object_id": "x", "dataset": "av2"},
        }

    ts = np.arange(t_len)
    sdc_xy = np.stack([100.0 + ts, 50.0 + 0 * ts], 1)  # 1 m per step along world +x
    ped_valid = [True] * (t_len - 1) + [False]
    tracks = {
        "AV": track("VEHICLE", sdc_xy, np.pi / 2, [0.0, 10.0]),
        "11": track("VEHICLE", [100.0, 60.0], 0.0, [0.0, 0.0]),
        "12": track("PEDESTRIAN", [95.0, 50.0], 0.0, [1.0, 0.0], 0.5, 0.5, valid=ped_valid),
        "13": track("OTHER", [90.0, 40.0], 0.0, [0.0, 0.0]),
        "14": track("CYCLIST", [101.0, 45.0], 4.0, [0.0, 0.0], 1.8, 0.7),
    }
    center = np.array([[100.0, 20.0, 0.0], [100.0, 40.0, 0.0], [100.0, 80.0, 0.0]], np.float32)
    map_features = {
        "201": {
            "type": "LANE_SURFACE_STREET",
            "polyline": center,
            "interpolating": True,
            "entry_lanes": ["200"],
            "exit_lanes": ["202"],
            "left_boundaries": [],
            "right_boundaries": [],
            "left_neighbor": [],
            "right_neighbor": [],
            "width": np.zeros((3, 2), np.float32),
        },
        "202": {
            "type": "LANE_BIKE_LANE",
            "polyline": np.array([[100.0, 80.0], [100.0, 80.0], [90.0, 90.0]], np.float32),
            "entry_lanes": ["201"],
            "exit_lanes": [],
        },
        "300": {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": center + [2.0, 0.0, 0.0]},
        "400": {
            "type": "CROSSWALK",
            "polygon": np.array([[95, 55, 0], [105, 55, 0], [105, 58, 0], [95, 58, 0]], np.float32),
        },
    }
    metadata = {
        "id": "scn",
        "coordinate": "waymo",
        "ts": ts / 10,
        "metadrive_processed": False,
        "sdc_id": "AV",
        "dataset": "av2",
        "scenario_id": "scn",
        "current_time_index": 1,
    }
    return {
        "id": "scn",
        "version": "v2",
        "length": t_len,
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": map_features,
        "metadata": metadata,
    }


# ----------------------------------------------------------------------------- round trip


def test_round_trip_through_pickle_is_lossless(tmp_path):
    frame = _hand_frame()
    scenario = sn.scenario_from_frame(frame, "scene_0")
    path = tmp_path / "sd_scenegen_scene_0.pkl"
    sn.write_scenario(scenario, path)

    [(back, dropped)] = sn.frames_from_scenario(sn.read_scenario(path), str(path))

    assert dropped == collections.Counter()
    assert back.source == str(path)
    assert frame_differences(frame, back, atol=1e-5) == []
    # float32 tracks: exact up to rounding; lane boundaries travel in float64 extras.
    np.testing.assert_allclose(back.position, frame.position, atol=1e-5)
    np.testing.assert_allclose(back.velocity, frame.velocity, atol=1e-5)
    np.testing.assert_array_equal(back.map.lanes[0].left, frame.map.lanes[0].left)
    assert back.map.lanes[1].lane_type == "BUS" and back.map.lanes[1].is_intersection
    assert back.map.lanes[0].predecessors == (3, 4) and back.map.lanes[0].successors == (8,)
    np.testing.assert_allclose(back.city_from_ego, frame.city_from_ego, atol=1e-12)
    assert np.all((back.heading >= 0) & (back.heading < 2 * np.pi))


def test_frame_differences_detects_changes():
    frame = _hand_frame()
    other = _hand_frame()
    other.heading = other.heading.copy()
    other.heading[2] = 0.5
    other.velocity = other.velocity + 0.01
    assert frame_differences(frame, other) == ["velocity", "heading"]
    # headings 2pi - eps and 0 are the same angle
    other = _hand_frame()
    other.heading = np.where(np.isclose(other.heading, 6.2831), 6.2831 - 2 * np.pi, other.heading)
    assert frame_differences(frame, other) == []


def test_export_has_scenarionet_shape():
    frame = _hand_frame()
    s = sn.scenario_from_frame(frame, "scene_0", dataset="mine")
    assert set(s) == {
        "id", "version", "length", "tracks", "map_features", "metadata", "dynamic_map_states"
    }  # fmt: skip
    assert s["length"] == 1 and s["dynamic_map_states"] == {}
    meta = s["metadata"]
    for key in ("sdc_id", "current_time_index", "ts", "dataset", "scenario_id", "coordinate"):
        assert key in meta
    assert meta["ts"].shape == (1,) and meta["dataset"] == "mine"
    sdc = s["tracks"][meta["sdc_id"]]
    assert sdc["type"] == "VEHICLE"
    np.testing.assert_array_equal(sdc["state"]["position"], [[0.0, 0.0, 0.0]])
    assert sdc["state"]["heading"][0] == 0.0
    assert len(s["tracks"]) == frame.num_actors + 1
    types = collections.Counter(t["type"] for t in s["tracks"].values())
    assert types == {"VEHICLE": 3, "PEDESTRIAN": 2, "CYCLIST": 2}
    for tid, track in s["tracks"].items():
        assert track["metadata"]["object_id"] == tid
        state = track["state"]
        assert state["position"].shape == (1, 3) and state["position"].dtype == np.float32
        assert state["velocity"].shape == (1, 2)
        for key in ("length", "width", "height", "heading", "valid"):
            assert state[key].shape == (1,)
        assert state["valid"].dtype == bool
    car = s["tracks"]["veh_a"]["state"]
    assert car["width"][0] == np.float32(1.9) and car["length"][0] == np.float32(4.6)
    lane = s["map_features"]["7"]
    assert lane["type"] == "LANE_SURFACE_STREET"
    assert lane["polyline"].shape[1] == 3 and lane["polygon"].shape[1] == 3
    assert lane["entry_lanes"] == ["3", "4"] and lane["exit_lanes"] == ["8"]
    left = s["map_features"][lane["left_boundaries"][0]["boundary_feature_id"]]
    assert left["type"] == "ROAD_LINE_BROKEN_SINGLE_WHITE"
    assert s["map_features"]["8"]["type"] == "LANE_SURFACE_UNSTRUCTURE"  # intersection
    # half widths are the centreline-to-boundary distances
    np.testing.assert_allclose(lane["width"][1], [1.8, 1.8], atol=0.2)
    assert s["map_features"]["crosswalk_0"]["type"] == "CROSSWALK"
    assert s["map_features"]["drivable_area_0"]["type"] == "ROAD_EDGE_BOUNDARY"
    # standalone lines: a road edge and a painted line of the closest ScenarioNet type
    assert s["map_features"]["line_0"]["type"] == "ROAD_EDGE_BOUNDARY"
    assert s["map_features"]["line_1"]["type"] == "ROAD_LINE_BROKEN_SINGLE_YELLOW"
    assert s["map_features"]["line_1"]["polyline"].shape == (3, 3)


def test_export_rejects_bad_frames():
    frame = _hand_frame()
    frame.position = frame.position.copy()
    frame.position[1, 0] = np.nan
    with pytest.raises(ValueError, match=r"hand: frame\.position: NaN"):
        sn.scenario_from_frame(frame, "x")
    frame = _hand_frame()
    frame.track_id = np.array(["a", "a", "b", "c", "d", "e"])
    with pytest.raises(ValueError, match="duplicate track id 'a'"):
        sn.scenario_from_frame(frame, "x")
    frame = _hand_frame()
    frame.size = frame.size.copy()
    frame.size[0, 1] = 0.0
    with pytest.raises(ValueError, match=r"frame\.size"):
        sn.scenario_from_frame(frame, "x")


def test_sdc_id_avoids_actor_named_ego():
    frame = _hand_frame()
    frame.track_id = np.array(["ego", "ped_a", "cyc_a", "veh_b", "ped_b", "cyc_b"])
    s = sn.scenario_from_frame(frame, "x")
    assert s["metadata"]["sdc_id"] != "ego"
    [(back, _)] = sn.frames_from_scenario(s, "x.pkl")
    assert frame_differences(frame, back, atol=1e-5) == []


def test_write_dataset_and_read_directory(tmp_path):
    frames = [_hand_frame(), _hand_frame()]
    frames[1].scene_id = "log_a/2"
    frames[1].cls = frames[1].cls.copy()
    frames[1].cls[0] = BICYCLIST
    scenarios = [sn.scenario_from_frame(f, f.scene_id) for f in frames]
    paths = sn.write_dataset(scenarios, tmp_path)
    assert [p.name for p in paths] == [
        "sd_scenegen_log_a_315967376859506000.pkl",
        "sd_scenegen_log_a_2.pkl",
    ]
    summary = load_pickle(tmp_path / sn.SUMMARY_FILE)
    assert set(summary) == {p.name for p in paths}
    assert load_pickle(tmp_path / sn.MAPPING_FILE) == {p.name: "" for p in paths}

    got = list(sn.read_scenarionet(tmp_path))  # the summary and mapping files are skipped
    assert len(got) == 2
    by_id = {g.frame.scene_id: g for g in got}
    for f in frames:
        assert frame_differences(f, by_id[f.scene_id].frame, atol=1e-5) == []
        assert by_id[f.scene_id].dropped == collections.Counter()


def test_read_scenarionet_missing_or_empty_dir(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a directory"):
        list(sn.read_scenarionet(tmp_path / "nope"))
    dump_pickle({}, tmp_path / sn.SUMMARY_FILE)
    with pytest.raises(FileNotFoundError, match="no ScenarioNet scenario files"):
        list(sn.read_scenarionet(tmp_path))


# ----------------------------------------------------------------------------- real-shape input


def test_standard_scenario_imports_in_ego_frame():
    scenario = _standard_scenario()
    [(frame, dropped)] = sn.frames_from_scenario(scenario, "sd_av2_scn.pkl")

    # current_time_index = 1: SDC at (101, 50) heading +y (pi/2), velocity 10 m/s along +y.
    assert frame.scene_id == "scn/1"
    assert dropped == collections.Counter({"type:OTHER": 1})
    np.testing.assert_array_equal(frame.cls, [VEHICLE, PEDESTRIAN, BICYCLIST])
    assert list(frame.track_id) == ["11", "12", "14"]
    # world (100, 60) is 10 m ahead and 1 m to the left of the ego
    np.testing.assert_allclose(frame.position[0], [10.0, 1.0], atol=1e-5)
    np.testing.assert_allclose(frame.position[1], [0.0, 6.0], atol=1e-5)
    np.testing.assert_allclose(frame.heading[0], 1.5 * np.pi, atol=1e-6)  # world 0 -> ego -pi/2
    np.testing.assert_allclose(frame.heading[2], np.mod(4.0 - np.pi / 2, 2 * np.pi), atol=1e-6)
    np.testing.assert_allclose(frame.velocity[1], [0.0, -1.0], atol=1e-6)  # world +x is ego right
    np.testing.assert_allclose(frame.ego_velocity, [10.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(frame.size[0], [2.0, 4.5])
    np.testing.assert_allclose(frame.ego_size, [2.0, 4.5])
    np.testing.assert_allclose(frame.city_from_ego[:2, 2], [101.0, 50.0])
    # pose maps ego-frame points back to the world
    np.testing.assert_allclose(
        frame.city_from_ego @ [10.0, 1.0, 1.0], [100.0, 60.0, 1.0], atol=1e-5
    )

    lanes = {lane.id: lane for lane in frame.map.lanes}
    assert set(lanes) == {201, 202}
    lane = lanes[201]
    assert lane.lane_type == "VEHICLE" and not lane.is_intersection
    assert lane.successors == (202,) and lane.predecessors == (200,)  # integer ids kept
    # centreline x = 100 in the world is ego y = +1. The lane runs along world +y = ego +x, so
    # its left is world -x = ego +y. Width 0 is unknown: the half width is measured from the
    # lines, the painted line at world x = 102 (ego y = -1) on the right, the default 1.8 m
    # on the left where there is none.
    np.testing.assert_allclose(lane.left[:, 1] - 1.0, 1.8, atol=1e-5)
    np.testing.assert_allclose(1.0 - lane.right[:, 1], 2.0, atol=1e-5)
    assert lane.left_mark == lane.right_mark == "NONE"
    assert lanes[202].lane_type == "BIKE" and lanes[202].predecessors == (201,)
    [line] = frame.map.lines
    assert line.mark == "SOLID_WHITE"
    np.testing.assert_allclose(line.points[:, 1], -1.0, atol=1e-5)
    assert len(frame.map.crosswalks) == 1
    np.testing.assert_allclose(frame.map.crosswalks[0][0], [5.0, 6.0], atol=1e-5)
    # one drivable polygon per lane (no road edge: the lane itself)
    assert len(frame.map.drivable_areas) == 2
    assert shapely.Polygon(frame.map.drivable_areas[0]).contains(shapely.Point(0.0, 1.0))


def test_standard_scenario_all_steps_and_validity():
    scenario = _standard_scenario()
    got = sn.frames_from_scenario(scenario, "f.pkl", all_steps=True)
    assert [g.frame.scene_id for g in got] == ["scn/0", "scn/1", "scn/2"]
    # the pedestrian is invalid at the last step: absent, not dropped
    assert [g.frame.num_actors for g in got] == [3, 3, 2]
    assert all(g.dropped["type:OTHER"] == 1 for g in got)
    assert [g.frame.scene_id for g in sn.frames_from_scenario(scenario, "f.pkl", [2, 0])] == [
        "scn/2",
        "scn/0",
    ]
    with pytest.raises(ValueError, match=r"f\.pkl: time_index: 5 outside"):
        sn.frames_from_scenario(scenario, "f.pkl", 5)


def test_standard_lane_width_and_marks_are_used():
    scenario = _standard_scenario()
    lane = scenario["map_features"]["201"]
    lane["width"] = np.array([[1.0, 2.0], [1.0, 2.0], [0.0, 2.0]], np.float32)
    lane["left_boundaries"] = [
        {
            "lane_start_index": 0,
            "lane_end_index": 2,
            "boundary_type": "x",
            "boundary_feature_id": 300,
        }
    ]
    lane["right_boundaries"] = [{"boundary_type": "ROAD_LINE_BROKEN_SINGLE_YELLOW"}]
    [(frame, _)] = sn.frames_from_scenario(scenario, "f.pkl")
    got = {lane.id: lane for lane in frame.map.lanes}[201]
    # the centreline (world x = 100) is ego y = 1; the zero width entry is measured: no line
    # on the left, so the default 1.8 m
    np.testing.assert_allclose(got.left[:, 1] - 1.0, [1.0, 1.0, 1.8], atol=1e-5)
    np.testing.assert_allclose(1.0 - got.right[:, 1], 2.0, atol=1e-5)
    # the left boundary is line 300 of the file, drawn as itself; the right one names only a
    # type, so the lane side carries it
    assert got.left_mark == "NONE" and got.right_mark == "DASHED_YELLOW"
    assert [line.mark for line in frame.map.lines] == ["SOLID_WHITE"]


def test_implausible_lane_widths_are_measured_instead():
    """Waymo's `width` is trusted only in [1, 2.5] m (larger ones are mostly wrong)."""
    scenario = _standard_scenario()
    lane = scenario["map_features"]["201"]
    lane["width"] = np.array([[9.0, 2.0], [0.5, 40.0], [np.nan, 2.2]], np.float32)
    [(frame, dropped)] = sn.frames_from_scenario(scenario, "f.pkl")
    got = {lane.id: lane for lane in frame.map.lanes}[201]
    np.testing.assert_allclose(got.left[:, 1] - 1.0, 1.8, atol=1e-5)  # default: no line left
    np.testing.assert_allclose(1.0 - got.right[:, 1], [2.0, 2.0, 2.2], atol=1e-5)
    assert "quirk:lane_width_unusable" not in dropped
    # A `width` of another shape, or not numbers, is measured too, and counted.
    for width in (np.full(3, 2.0), np.full((2, 2), 2.0), "wide"):
        lane["width"] = width
        [(frame, dropped)] = sn.frames_from_scenario(scenario, "f.pkl")
        got = {lane.id: lane for lane in frame.map.lanes}[201]
        np.testing.assert_allclose(1.0 - got.right[:, 1], 2.0, atol=1e-5)  # to the line
        np.testing.assert_allclose(got.left[:, 1] - 1.0, 1.8, atol=1e-5)
        assert dropped["quirk:lane_width_unusable"] == 1


def test_non_integer_lane_ids_are_enumerated():
    scenario = _standard_scenario()
    feats = scenario["map_features"]
    feats["tok_a"] = feats.pop("201")
    feats["tok_b"] = feats.pop("202")
    feats["tok_a"]["exit_lanes"] = ["tok_b"]
    feats["tok_b"]["entry_lanes"] = ["tok_a"]
    [(frame, _)] = sn.frames_from_scenario(scenario, "f.pkl")
    a, b = frame.map.lanes
    assert (a.id, b.id) == (0, 1) and a.successors == (1,) and b.predecessors == (0,)


def test_degenerate_lane_is_counted():
    scenario = _standard_scenario()
    scenario["map_features"]["201"]["polyline"] = np.array([[1.0, 2.0, 0.0], [1.0, 2.0, 0.0]])
    [(frame, dropped)] = sn.frames_from_scenario(scenario, "f.pkl")
    assert dropped["map:degenerate_lane"] == 1 and len(frame.map.lanes) == 1


# ----------------------------------------------------------------------------- bad input


def test_unknown_track_type_is_counted_not_silent():
    frame = _hand_frame()
    s = sn.scenario_from_frame(frame, "x")
    s["tracks"]["veh_a"]["type"] = "TRAFFIC_CONE"
    s["tracks"]["cyc_b"]["type"] = "TRAFFIC_CONE"
    s["tracks"]["ped_a"]["type"] = "UNSET"
    [(back, dropped)] = sn.frames_from_scenario(s, "x.pkl")
    assert dropped == collections.Counter({"type:TRAFFIC_CONE": 2, "type:UNSET": 1})
    assert back.num_actors == frame.num_actors - 3
    assert "veh_a" not in set(back.track_id)


def test_nan_in_an_actor_is_a_counted_drop_and_in_the_sdc_an_error():
    s = _standard_scenario()
    s["tracks"]["11"]["state"]["position"][1, 0] = np.nan
    [(frame, dropped)] = sn.frames_from_scenario(s, "sd_bad.pkl")
    assert dropped["invalid:nan"] == 1 and "11" not in set(frame.track_id)
    # NaN in a step that is not imported is nothing
    [(frame, dropped)] = sn.frames_from_scenario(s, "sd_bad.pkl", 0)
    assert "invalid:nan" not in dropped and "11" in set(frame.track_id)
    s["tracks"]["AV"]["state"]["position"][1, 0] = np.nan
    with pytest.raises(ValueError, match=r"sd_bad\.pkl: tracks\['AV'\]\.state\.position\[1\]: NaN"):
        sn.frames_from_scenario(s, "sd_bad.pkl")


@pytest.mark.parametrize(
    ("mutate", "key"),
    [
        (lambda st: st["11"]["state"]["width"].__setitem__(1, 0.0), "invalid:size"),
        (lambda st: st["14"]["state"]["length"].__setitem__(1, -1.0), "invalid:size"),
        (lambda st: st["11"]["state"]["heading"].__setitem__(1, np.inf), "invalid:nan"),
        (lambda st: st["12"]["state"]["width"].__setitem__(1, np.nan), "invalid:nan"),
    ],
)
def test_bad_actor_states_are_counted_drops(mutate, key):
    s = _standard_scenario()
    mutate(s["tracks"])
    [(frame, dropped)] = sn.frames_from_scenario(s, "f.pkl")
    assert dropped[key] == 1 and frame.num_actors == 2


def test_length_shorter_than_width_is_sorted_and_counted():
    s = _standard_scenario()
    st = s["tracks"]["11"]["state"]
    st["length"][:], st["width"][:] = 1.9, 4.4
    s["tracks"]["AV"]["state"]["width"][:] = 5.0  # longer than its 4.5 m length
    [(frame, dropped)] = sn.frames_from_scenario(s, "f.pkl")
    assert dropped["quirk:length_lt_width"] == 2
    np.testing.assert_allclose(frame.size[0], [1.9, 4.4])  # (width, length)
    np.testing.assert_allclose(frame.ego_size, [4.5, 5.0])
    np.testing.assert_allclose(frame.heading[0], 1.5 * np.pi, atol=1e-6)  # unchanged


@pytest.mark.parametrize(
    ("mutate", "pattern"),
    [
        (lambda s: s["metadata"].pop("sdc_id"), r"f\.pkl: metadata\.sdc_id: missing"),
        (lambda s: s["metadata"].update(sdc_id="nobody"), r"metadata\.sdc_id: 'nobody' is not"),
        (lambda s: s.pop("tracks"), r"f\.pkl: tracks: missing"),
        (lambda s: s.pop("map_features"), r"map_features: missing"),
        (
            lambda s: s["tracks"]["11"]["state"].pop("velocity"),
            r"\['11'\]\.state\.velocity: missing",
        ),
        (lambda s: s["tracks"]["11"]["state"].pop("valid"), r"\['11'\]\.state\.valid: missing"),
        (
            lambda s: s["tracks"]["11"]["state"].update(heading=np.zeros(2)),
            r"\['11'\]\.state\.heading: has 2 steps, scenario length is 3",
        ),
        (
            lambda s: s["tracks"]["AV"]["state"]["width"].__setitem__(1, 0.0),
            r"\['AV'\]\.state\.width/length\[1\]: box size must be positive",
        ),
        (
            lambda s: s["tracks"]["AV"]["state"]["heading"].__setitem__(1, np.inf),
            r"\['AV'\]\.state\.heading\[1\]: NaN or inf",
        ),
        (
            lambda s: s["tracks"]["11"]["state"].update(length=np.ones((3, 2))),
            r"\['11'\]\.state\.length: expected shape \[N\] or \[N, 1\], got \(3, 2\)",
        ),
        (
            lambda s: s["tracks"]["11"]["state"].update(valid=np.array([1.0, np.nan, 1.0])),
            r"\['11'\]\.state\.valid: NaN",
        ),
        (
            lambda s: (s["metadata"].pop("sdc_id"), s.update(sdc_track_index="nobody")),
            r"f\.pkl: sdc_track_index: 'nobody' names no track",
        ),
        (lambda s: s.update(metadata=[1]), r"f\.pkl: metadata: expected a dict"),
        (
            lambda s: (s["metadata"].pop("sdc_id"), s.update(sdc_track_index=True)),
            r"f\.pkl: sdc_track_index: expected a track id or index, got True",
        ),
        (lambda s: s.update(length=2.5), r"f\.pkl: length: expected an integer, got 2\.5"),
        (lambda s: s.update(length="3"), r"f\.pkl: length: expected an integer, got '3'"),
        (
            lambda s: s["metadata"].update(dataset={"name": "waymo"}),
            r"f\.pkl: metadata\.dataset: expected a string",
        ),
        (
            lambda s: s["metadata"].update(scenegen_city_from_world="abc"),
            r"f\.pkl: metadata\.scenegen_city_from_world: not numbers",
        ),
        (
            lambda s: s["tracks"]["AV"].update(type="PEDESTRIAN"),
            r"f\.pkl: tracks\['AV'\]\.type: the SDC \(ego\) is a PEDESTRIAN, not a vehicle",
        ),
        (
            lambda s: s["tracks"]["AV"]["state"]["valid"].__setitem__(1, False),
            r"\['AV'\]\.state\.valid\[1\]: the SDC",
        ),
        (
            lambda s: s["map_features"]["201"]["polyline"].__setitem__((1, 1), np.nan),
            r"map_features\['201'\]\.polyline: NaN",
        ),
        (lambda s: s["map_features"]["400"].pop("type"), r"map_features\['400'\]\.type: missing"),
    ],
)
def test_bad_input_names_file_and_field(mutate, pattern):
    s = _standard_scenario()
    mutate(s)
    with pytest.raises(ValueError, match=pattern):
        sn.frames_from_scenario(s, "f.pkl")


def test_pedestrian_size_is_not_checked():
    s = _standard_scenario()
    s["tracks"]["12"]["state"]["width"][:] = 0.0
    [(frame, _)] = sn.frames_from_scenario(s, "f.pkl")
    assert frame.num_actors == 3


def test_non_dict_pickle_is_refused(tmp_path):
    dump_pickle([1, 2, 3], tmp_path / "sd_list.pkl")
    with pytest.raises(ValueError, match=r"sd_list\.pkl: expected a ScenarioNet scenario dict"):
        list(sn.read_scenarionet(tmp_path))


# ----------------------------------------------------------------------------- safe pickle


class _Exploit:
    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class _Plain:
    pass


def test_code_running_pickle_is_refused(tmp_path):
    marker = tmp_path / "pwned_marker"
    path = tmp_path / "sd_evil.pkl"
    with open(path, "wb") as f:
        pickle.dump({"tracks": _Exploit(str(marker))}, f)
    with pytest.raises(UnsafePickleError, match=r"sd_evil\.pkl.*(posix|os|nt)\.system"):
        load_pickle(path)
    assert not marker.exists()
    # read_scenarionet refuses it too, and still runs nothing
    with pytest.raises(UnsafePickleError):
        list(sn.read_scenarionet(tmp_path))
    assert not marker.exists()


@pytest.mark.parametrize(
    "payload",
    [
        b"cbuiltins\neval\n(S'1+1'\ntR.",  # protocol 0 GLOBAL builtins.eval
        b"\x80\x04\x95\x00\x00\x00\x00\x00\x00\x00\x00\x8c\x08builtins\x8c\x07getattr\x93.",
        b"cbuiltins\n__import__\n(S'os'\ntR.",
    ],
)
def test_dangerous_builtins_are_refused(tmp_path, payload):
    path = tmp_path / "p.pkl"
    path.write_bytes(payload)
    with pytest.raises(UnsafePickleError, match=r"p\.pkl: refusing to unpickle global builtins\."):
        load_pickle(path)


def test_arbitrary_classes_are_refused(tmp_path):
    path = tmp_path / "obj.pkl"
    with open(path, "wb") as f:
        pickle.dump({"a": _Plain()}, f)
    with pytest.raises(UnsafePickleError, match="_Plain"):
        load_pickle(path)


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_numpy_and_containers_load_at_every_protocol(tmp_path, protocol):
    obj = {
        "f32": np.arange(6, dtype=np.float32).reshape(2, 3),
        "f64_fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        "bool": np.array([True, False]),
        "str": np.array(["a", "bc"]),
        "empty": np.zeros((0, 3)),
        "scalar": np.float32(2.5),
        "int": np.int64(7),
        "nested": [(1, 2.0, "x", None, b"by"), {3, 4}, frozenset({5})],
        "dd": collections.defaultdict(int, {"a": 1}),
    }
    path = tmp_path / "ok.pkl"
    with open(path, "wb") as f:
        pickle.dump(obj, f, protocol=protocol)
    got = load_pickle(path)
    for key in ("f32", "f64_fortran", "bool", "str", "empty"):
        np.testing.assert_array_equal(got[key], obj[key])
        assert got[key].dtype == obj[key].dtype
    assert got["scalar"] == np.float32(2.5) and got["scalar"].dtype == np.float32
    assert got["int"] == 7 and got["nested"] == obj["nested"] and got["dd"] == {"a": 1}


def test_truncated_pickle_names_the_file(tmp_path):
    s = sn.scenario_from_frame(_hand_frame(), "x")
    path = tmp_path / "sd_trunc.pkl"
    sn.write_scenario(s, path)
    data = path.read_bytes()
    for cut in (len(data) // 3, len(data) - 1, 1):
        path.write_bytes(data[:cut])
        with pytest.raises(CorruptPickleError, match=r"sd_trunc\.pkl: truncated or corrupt"):
            load_pickle(path)
    path.write_bytes(b"")
    with pytest.raises(CorruptPickleError, match=r"sd_trunc\.pkl"):
        load_pickle(path)
    path.write_bytes(b"not a pickle at all")
    with pytest.raises(CorruptPickleError, match=r"sd_trunc\.pkl"):
        load_pickle(path)
    with pytest.raises(FileNotFoundError):
        load_pickle(tmp_path / "missing.pkl")


def test_dump_pickle_is_atomic_and_round_trips(tmp_path):
    path = tmp_path / "sub" / "a.pkl"
    dump_pickle({"a": np.arange(3)}, path)
    np.testing.assert_array_equal(load_pickle(path)["a"], np.arange(3))
    assert [p.name for p in path.parent.iterdir()] == ["a.pkl"]  # no temp files left


def test_rotated_ego_frame_round_trip():
    """Export a frame, rotate + translate the whole scenario in the world, import: same frame."""
    frame = _hand_frame()
    s = sn.scenario_from_frame(frame, "x")
    theta, shift = 2.3, np.array([-40.0, 17.0])
    rot = rotation_matrix(theta)
    for track in s["tracks"].values():
        st = track["state"]
        st["position"][:, :2] = (st["position"][:, :2].astype(np.float64) @ rot.T + shift).astype(
            np.float32
        )
        st["velocity"][:] = (st["velocity"].astype(np.float64) @ rot.T).astype(np.float32)
        st["heading"][:] = np.float32(st["heading"][0] + theta)
    for feature in s["map_features"].values():
        for key in ("scenegen_left", "scenegen_right", "scenegen_polygon", "scenegen_points"):
            if key in feature:
                feature[key] = feature[key] @ rot.T + shift
    # the world is now city_from_ego_original @ inverse(world_from_ego)
    world_from_ego = np.array([[*rot[0], shift[0]], [*rot[1], shift[1]], [0.0, 0.0, 1.0]])
    s["metadata"]["scenegen_city_from_world"] = frame.city_from_ego @ np.linalg.inv(world_from_ego)
    [(back, _)] = sn.frames_from_scenario(s, "x.pkl")
    assert frame_differences(frame, back, atol=1e-4) == []


def test_headings_wrap_into_range():
    s = _standard_scenario()
    s["tracks"]["11"]["state"]["heading"][:] = np.pi / 2 - 1e-9  # equal to the ego's, minus eps
    s["tracks"]["14"]["state"]["heading"][:] = -7.0
    [(frame, _)] = sn.frames_from_scenario(s, "f.pkl")
    assert np.all((frame.heading >= 0) & (frame.heading < 2 * np.pi))
    np.testing.assert_allclose(frame.heading[2], np.mod(-7.0 - np.pi / 2, 2 * np.pi), atol=1e-6)


def test_bad_current_time_index_names_field():
    s = _standard_scenario()
    s["metadata"]["current_time_index"] = "soon"
    with pytest.raises(ValueError, match=r"f\.pkl: metadata\.current_time_index: expected an int"):
        sn.frames_from_scenario(s, "f.pkl")


def test_real_argoverse_scene_round_trip(all_frames, tmp_path):
    """A real Argoverse 2 scene exported to ScenarioNet, written, read back: unchanged."""
    from scenegen_jax.data import scenarionet as sn

    for frame in all_frames["val"][0][::50]:
        path = tmp_path / "scene.pkl"
        sn.write_scenario(sn.scenario_from_frame(frame, frame.scene_id), path)
        [(back, dropped)] = sn.frames_from_scenario(sn.read_scenario(path), str(path))
        assert frame_differences(frame, back) == [] and not dropped
        assert back.map.dataset == "av2"


# ----------------------------------------------------------------------------- real converters

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


def test_imported_converter_frame_round_trips_through_export(tmp_path):
    """A frame imported from a converter's file (lines included) exports and imports unchanged."""
    [(frame, _)] = sn.frames_from_scenario(fx.argoverse2().scenario, "a.pkl")
    assert frame.map.lines
    path = tmp_path / "x.pkl"
    sn.write_scenario(sn.scenario_from_frame(frame, frame.scene_id), path)
    [(back, dropped)] = sn.frames_from_scenario(sn.read_scenario(path), str(path))
    assert frame_differences(frame, back, atol=1e-4) == [] and not dropped


# ----------------------------------------------------------------------------- real WOMD pickles

WOMD_STRIDE = 10


def _womd_sdc(scenario: dict):
    """The SDC's key in `tracks`: metadata.sdc_id (S1, S2) or the top-level sdc_track_index
    (S3: an int, and so are S3's track keys; S4: a str)."""
    meta = scenario.get("metadata", {})
    return meta["sdc_id"] if "sdc_id" in meta else scenario["sdc_track_index"]


@pytest.fixture(scope="module")
def womd():
    """{file name: (scenario, stride frames)} of every womd_mini ScenarioNet pickle, read once."""
    paths = sorted(glob.glob(os.path.join(WOMD_ROOT, "*", "*.pkl")))
    if not paths:
        pytest.fail(f"real data missing: {WOMD_ROOT} (../shared must sit beside the repo)")
    out = {}
    for path in paths:
        scenario = sn.read_scenario(path)
        out[os.path.basename(path)] = (
            scenario,
            sn.frames_from_scenario(scenario, path, stride=WOMD_STRIDE),
        )
    return out


def test_womd_every_pickle_imports_every_stride_frame(womd):
    assert len(womd) == 18
    for name, (scenario, frames) in womd.items():
        tracks = scenario["tracks"]
        sdc = tracks[_womd_sdc(scenario)]["state"]
        n = len(sdc["position"])
        valid = np.asarray(sdc["valid"]).reshape(n) != 0
        want = [t for t in range(0, n, WOMD_STRIDE) if valid[t]]
        assert [int(g.frame.scene_id.rsplit("/", 1)[1]) for g in frames] == want, name
        assert sn.scenario_sample_rate_hz(scenario) == pytest.approx(10.0, rel=0.01), name


def test_womd_maps_know_their_data_set_where_the_file_says(womd):
    """S1 and S2 carry metadata.dataset "waymo"; S3 and S4 have no metadata (README)."""
    datasets = collections.Counter()
    for name, (scenario, frames) in womd.items():
        want = scenario.get("metadata", {}).get("dataset", "")
        assert {f.map.dataset for f, _ in frames} == {want}, name
        datasets[want] += 1
    assert datasets == {"waymo": 13, "": 5}


def test_womd_actor_counts_equal_the_files_tracks(womd):
    """Per step and class: actors == tracks valid there with that type (the SDC aside)."""
    cls_of = {"VEHICLE": VEHICLE, "PEDESTRIAN": PEDESTRIAN, "CYCLIST": BICYCLIST}
    for name, (scenario, frames) in womd.items():
        sdc = _womd_sdc(scenario)
        others = [tr for tid, tr in scenario["tracks"].items() if tid != sdc]
        for frame, dropped in frames:
            t = int(frame.scene_id.rsplit("/", 1)[1])
            want = collections.Counter(
                tr["type"] for tr in others if np.asarray(tr["state"]["valid"]).reshape(-1)[t]
            )
            got = collections.Counter(int(c) for c in frame.cls)
            assert got == {cls_of[k]: v for k, v in want.items() if k in cls_of}, (name, t)
            assert not any(k.startswith(("invalid:", "type:")) for k in dropped), (name, dropped)


def test_womd_headings_agree_with_velocities_and_sizes_are_plausible(womd):
    for name, (_, frames) in womd.items():
        angles, lengths = [], []
        for frame, _ in frames:
            veh = frame.cls == VEHICLE
            moving = veh & (np.linalg.norm(frame.velocity, axis=1) > 2.0)
            v = frame.velocity[moving]
            angles.append(
                np.angle(np.exp(1j * (frame.heading[moving] - np.arctan2(v[:, 1], v[:, 0]))))
            )
            lengths.append(frame.size[veh, 1])
            assert np.all(frame.size[veh, 1] >= frame.size[veh, 0])
        assert np.degrees(np.median(np.abs(np.concatenate(angles)))) < 5.0, name
        assert 3.5 < np.median(np.concatenate(lengths)) < 6.0, name
        assert not any(d["quirk:velocity_mismatch"] for _, d in frames), name


def test_womd_maps(womd):
    for name, (scenario, frames) in womd.items():
        frame, dropped = frames[0]
        vmap = frame.map
        assert vmap.lanes and vmap.lines and vmap.drivable_areas, name
        marks = collections.Counter(line.mark for line in vmap.lines)
        assert marks[ROAD_EDGE] > 0 and sum(marks.values()) > marks[ROAD_EDGE], name
        features = scenario["map_features"].values()
        types = collections.Counter(f["type"] for f in features if isinstance(f["type"], str))
        # every crosswalk and driveway is kept; one drivable polygon per lane plus driveways
        assert len(vmap.crosswalks) == types["CROSSWALK"] + types["CROSS_WALK"], name
        assert len(vmap.drivable_areas) == len(vmap.lanes) + types["DRIVEWAY"], name
        assert dropped["map:malformed_type"] == sum(
            not isinstance(f["type"], str) for f in features
        )
        for kind in ("STOP_SIGN", "stop_sign", "SPEED_BUMP"):
            assert dropped[f"map:{kind}"] == types[kind], (name, kind)
        # the ego stands on the drivable surface
        around = [p for p in vmap.drivable_areas if np.all(p.min(0) <= 0) and np.all(p.max(0) >= 0)]
        assert any(shapely.Polygon(p).contains(shapely.Point(0.0, 0.0)) for p in around), name


# ----------------------------------------------------------------------------- MetaDrive classes


_SD_GLOBAL = b"cmetadrive.scenario.scenario_description\nScenarioDescription\n"  # GLOBAL
_SD_ITEMS = b"(X\x02\x00\x00\x00idX\x03\x00\x00\x00abcX\x06\x00\x00\x00tracks}u."


@pytest.mark.parametrize(
    ("payload", "want"),
    [
        # protocol 2: GLOBAL, EMPTY_TUPLE, NEWOBJ (cls.__new__(cls)), MARK, items, SETITEMS
        (b"\x80\x02" + _SD_GLOBAL + b")\x81" + _SD_ITEMS, {"id": "abc", "tracks": {}}),
        # protocol 4: the same class by STACK_GLOBAL (what Python 3 writes)
        (
            b"\x80\x04\x8c'metadrive.scenario.scenario_description\x94"
            b"\x8c\x13ScenarioDescription\x94\x93)\x81" + _SD_ITEMS,
            {"id": "abc", "tracks": {}},
        ),
        # protocol 0: GLOBAL called with no arguments
        (_SD_GLOBAL + b"(tR.", {}),
    ],
)
def test_metadrive_scenario_description_loads_as_a_dict(tmp_path, payload, want):
    """Older ScenarioNet files pickled MetaDrive's ScenarioDescription (a dict subclass)."""
    path = tmp_path / "sd_old.pkl"
    path.write_bytes(payload)
    got = load_pickle(path)
    assert type(got) is dict and got == want


@pytest.mark.parametrize(
    ("payload", "name"),
    [
        (b"\x80\x02c__main__\nFoo\n)\x81.", "__main__.Foo"),
        (b"cmetadrive.scenario.scenario_description\nOther\n(tR.", "scenario_description.Other"),
        (b"cmetadrive.type\nMetaDriveType\n(tR.", "metadrive.type.MetaDriveType"),
    ],
)
def test_other_classes_stay_refused(tmp_path, payload, name):
    path = tmp_path / "p.pkl"
    path.write_bytes(payload)
    with pytest.raises(UnsafePickleError, match=name.replace(".", r"\.")):
        load_pickle(path)


def test_os_system_global_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "ran"
    path = tmp_path / "p.pkl"
    path.write_bytes(b"cos\nsystem\n(S'touch " + str(marker).encode() + b"'\ntR.")
    with pytest.raises(UnsafePickleError, match=r"os\.system"):
        load_pickle(path)
    assert not marker.exists()


def test_complex_numbers_are_refused_not_cast():
    """A complex array where reals belong is an error naming the field; a cast to float would
    drop the imaginary part silently (found by the fuzz tests)."""
    path = os.path.join(WOMD_ROOT, "val", "8799c31b5be1f312.pkl")
    scenario = sn.read_scenario(path)
    tracks = dict(scenario["tracks"])
    tid = next(iter(tracks))
    state = dict(tracks[tid]["state"])
    state["position"] = np.asarray(state["position"]).astype(np.complex128) * (1 + 1e-3j)
    tracks[tid] = {**tracks[tid], "state": state}
    with pytest.raises(ValueError, match="complex numbers") as e:
        sn.frames_from_scenario({**scenario, "tracks": tracks}, path, stride=50)
    assert path in str(e.value) and "position" in str(e.value)
