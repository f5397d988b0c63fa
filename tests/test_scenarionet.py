"""ScenarioNet import/export and the restricted unpickler."""

from __future__ import annotations

import collections
import os
import pickle

import numpy as np
import pytest

from scenegen_jax.data import scenarionet as sn
from scenegen_jax.data.frame import Frame
from scenegen_jax.data.safe_pickle import (
    CorruptPickleError,
    UnsafePickleError,
    dump_pickle,
    load_pickle,
)
from scenegen_jax.data.vector_map import Lane, VectorMap, rotation_matrix
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE


def _hand_frame() -> Frame:
    """Two actors of each class, a curved lane, a bus lane, a crosswalk and a drivable area."""
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
    assert sn.frame_differences(frame, back, atol=1e-5) == []
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
    assert sn.frame_differences(frame, other) == ["velocity", "heading"]
    # headings 2pi - eps and 0 are the same angle
    other = _hand_frame()
    other.heading = np.where(np.isclose(other.heading, 6.2831), 6.2831 - 2 * np.pi, other.heading)
    assert sn.frame_differences(frame, other) == []


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
    assert sn.frame_differences(frame, back, atol=1e-5) == []


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
        assert sn.frame_differences(f, by_id[f.scene_id].frame, atol=1e-5) == []
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
    assert dropped == collections.Counter({"type:OTHER": 1, "map:ROAD_LINE_SOLID_SINGLE_WHITE": 1})
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
    # centreline x = 100 in the world is ego y = +1; boundaries 1.8 m either side (width was 0)
    np.testing.assert_allclose(lane.centerline[:, 1], 1.0, atol=1e-5)
    np.testing.assert_allclose(lane.left[:, 1] - lane.right[:, 1], 3.6, atol=1e-5)
    # lane runs along world +y = ego +x, so its left is world -x = ego +y
    assert np.all(lane.left[:, 1] > lane.right[:, 1])
    assert lanes[202].lane_type == "BIKE" and lanes[202].predecessors == (201,)
    assert len(frame.map.crosswalks) == 1 and frame.map.drivable_areas == ()
    np.testing.assert_allclose(frame.map.crosswalks[0][0], [5.0, 6.0], atol=1e-5)


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
    # the centreline (world x = 100) is ego y = 1; the zero width entry falls back to 1.8 m
    np.testing.assert_allclose(got.left[:, 1] - 1.0, [1.0, 1.0, 1.8], atol=1e-5)
    np.testing.assert_allclose(1.0 - got.right[:, 1], 2.0, atol=1e-5)
    assert got.left_mark == "SOLID_WHITE" and got.right_mark == "DASHED_YELLOW"


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


def test_nan_position_names_file_and_field():
    s = _standard_scenario()
    s["tracks"]["11"]["state"]["position"][1, 0] = np.nan
    with pytest.raises(ValueError, match=r"sd_bad\.pkl: tracks\['11'\]\.state\.position\[1\]: NaN"):
        sn.frames_from_scenario(s, "sd_bad.pkl")
    # NaN in a step that is not imported is not an error
    assert len(sn.frames_from_scenario(s, "sd_bad.pkl", 0)) == 1


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
            lambda s: s["tracks"]["11"]["state"]["width"].__setitem__(1, 0.0),
            r"\['11'\]\.state\.width/length\[1\]: box size must be positive",
        ),
        (
            lambda s: s["tracks"]["14"]["state"]["length"].__setitem__(1, -1.0),
            r"\['14'\]\.state\.width/length\[1\]",
        ),
        (
            lambda s: s["tracks"]["11"]["state"]["heading"].__setitem__(1, np.inf),
            r"\['11'\]\.state\.heading\[1\]: NaN or inf",
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
        for key in ("scenegen_left", "scenegen_right", "scenegen_polygon"):
            if key in feature:
                feature[key] = feature[key] @ rot.T + shift
    # the world is now city_from_ego_original @ inverse(world_from_ego)
    world_from_ego = np.array([[*rot[0], shift[0]], [*rot[1], shift[1]], [0.0, 0.0, 1.0]])
    s["metadata"]["scenegen_city_from_world"] = frame.city_from_ego @ np.linalg.inv(world_from_ego)
    [(back, _)] = sn.frames_from_scenario(s, "x.pkl")
    assert sn.frame_differences(frame, back, atol=1e-4) == []


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
        assert sn.frame_differences(frame, back) == [] and not dropped
