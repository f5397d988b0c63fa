"""ScenarioNet export (`data.scenarionet_export`): frames written as scenarios and read back
losslessly (by hand, rotated, from Argoverse 2 and from a converter's file), the scenario's
shape, bad frames refused, datasets written and read as a directory."""

from __future__ import annotations

import collections

import numpy as np
import pytest
import scenarionet_fixtures as fx
from frames import frame_differences
from scenarionet_fixtures import hand_frame

from scenegen_jax.data import scenarionet as sn
from scenegen_jax.data.safe_pickle import (
    dump_pickle,
    load_pickle,
)
from scenegen_jax.scene import BICYCLIST
from scenegen_jax.vector_map import rotation_matrix


def test_round_trip_through_pickle_is_lossless(tmp_path):
    frame = hand_frame()
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
    frame = hand_frame()
    other = hand_frame()
    other.heading = other.heading.copy()
    other.heading[2] = 0.5
    other.velocity = other.velocity + 0.01
    assert frame_differences(frame, other) == ["velocity", "heading"]
    # headings 2pi - eps and 0 are the same angle
    other = hand_frame()
    other.heading = np.where(np.isclose(other.heading, 6.2831), 6.2831 - 2 * np.pi, other.heading)
    assert frame_differences(frame, other) == []


def test_export_has_scenarionet_shape():
    frame = hand_frame()
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
    frame = hand_frame()
    frame.position = frame.position.copy()
    frame.position[1, 0] = np.nan
    with pytest.raises(ValueError, match=r"hand: frame\.position: NaN"):
        sn.scenario_from_frame(frame, "x")
    frame = hand_frame()
    frame.track_id = np.array(["a", "a", "b", "c", "d", "e"])
    with pytest.raises(ValueError, match="duplicate track id 'a'"):
        sn.scenario_from_frame(frame, "x")
    frame = hand_frame()
    frame.size = frame.size.copy()
    frame.size[0, 1] = 0.0
    with pytest.raises(ValueError, match=r"frame\.size"):
        sn.scenario_from_frame(frame, "x")


def test_sdc_id_avoids_actor_named_ego():
    frame = hand_frame()
    frame.track_id = np.array(["ego", "ped_a", "cyc_a", "veh_b", "ped_b", "cyc_b"])
    s = sn.scenario_from_frame(frame, "x")
    assert s["metadata"]["sdc_id"] != "ego"
    [(back, _)] = sn.frames_from_scenario(s, "x.pkl")
    assert frame_differences(frame, back, atol=1e-5) == []


def test_write_dataset_and_read_directory(tmp_path):
    frames = [hand_frame(), hand_frame()]
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


def test_rotated_ego_frame_round_trip():
    """Export a frame, rotate + translate the whole scenario in the world, import: same frame."""
    frame = hand_frame()
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


def test_real_argoverse_scene_round_trip(all_frames, tmp_path):
    """A real Argoverse 2 scene exported to ScenarioNet, written, read back: unchanged."""
    from scenegen_jax.data import scenarionet as sn

    for frame in all_frames["val"][0][::50]:
        path = tmp_path / "scene.pkl"
        sn.write_scenario(sn.scenario_from_frame(frame, frame.scene_id), path)
        [(back, dropped)] = sn.frames_from_scenario(sn.read_scenario(path), str(path))
        assert frame_differences(frame, back) == [] and not dropped
        assert back.map.dataset == "av2"


def test_imported_converter_frame_round_trips_through_export(tmp_path):
    """A frame imported from a converter's file (lines included) exports and imports unchanged."""
    [(frame, _)] = sn.frames_from_scenario(fx.argoverse2().scenario, "a.pkl")
    assert frame.map.lines
    path = tmp_path / "x.pkl"
    sn.write_scenario(sn.scenario_from_frame(frame, frame.scene_id), path)
    [(back, dropped)] = sn.frames_from_scenario(sn.read_scenario(path), str(path))
    assert frame_differences(frame, back, atol=1e-4) == []
    # the converter's constant boxes stay unmeasured through our export
    assert dropped == {"quirk:constant_boxes": 1} and not back.measured.any()
