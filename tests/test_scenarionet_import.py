"""ScenarioNet import (`data.scenarionet`) of a scenario with the standard keys only: the ego
frame, every step and validity, lane widths, marks and ids; bad input counted as drops or
refused with the file and the field named."""

from __future__ import annotations

import collections

import numpy as np
import pytest
import shapely
from scenarionet_fixtures import hand_frame, standard_scenario

from scenegen_jax.data import scenarionet as sn
from scenegen_jax.data.safe_pickle import (
    dump_pickle,
)
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE


def test_standard_scenario_imports_in_ego_frame():
    scenario = standard_scenario()
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
    np.testing.assert_allclose(frame.size[0], [2.0, 4.6])
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
    scenario = standard_scenario()
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
    scenario = standard_scenario()
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
    scenario = standard_scenario()
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
    scenario = standard_scenario()
    feats = scenario["map_features"]
    feats["tok_a"] = feats.pop("201")
    feats["tok_b"] = feats.pop("202")
    feats["tok_a"]["exit_lanes"] = ["tok_b"]
    feats["tok_b"]["entry_lanes"] = ["tok_a"]
    [(frame, _)] = sn.frames_from_scenario(scenario, "f.pkl")
    a, b = frame.map.lanes
    assert (a.id, b.id) == (0, 1) and a.successors == (1,) and b.predecessors == (0,)


def test_degenerate_lane_is_counted():
    scenario = standard_scenario()
    scenario["map_features"]["201"]["polyline"] = np.array([[1.0, 2.0, 0.0], [1.0, 2.0, 0.0]])
    [(frame, dropped)] = sn.frames_from_scenario(scenario, "f.pkl")
    assert dropped["map:degenerate_lane"] == 1 and len(frame.map.lanes) == 1


def test_unknown_track_type_is_counted_not_silent():
    frame = hand_frame()
    s = sn.scenario_from_frame(frame, "x")
    s["tracks"]["veh_a"]["type"] = "TRAFFIC_CONE"
    s["tracks"]["cyc_b"]["type"] = "TRAFFIC_CONE"
    s["tracks"]["ped_a"]["type"] = "UNSET"
    [(back, dropped)] = sn.frames_from_scenario(s, "x.pkl")
    assert dropped == collections.Counter({"type:TRAFFIC_CONE": 2, "type:UNSET": 1})
    assert back.num_actors == frame.num_actors - 3
    assert "veh_a" not in set(back.track_id)


def test_nan_in_an_actor_is_a_counted_drop_and_in_the_sdc_an_error():
    s = standard_scenario()
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
    s = standard_scenario()
    mutate(s["tracks"])
    [(frame, dropped)] = sn.frames_from_scenario(s, "f.pkl")
    assert dropped[key] == 1 and frame.num_actors == 2


def test_length_shorter_than_width_is_sorted_and_counted():
    s = standard_scenario()
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
    s = standard_scenario()
    mutate(s)
    with pytest.raises(ValueError, match=pattern):
        sn.frames_from_scenario(s, "f.pkl")


def test_pedestrian_size_is_not_checked():
    s = standard_scenario()
    s["tracks"]["12"]["state"]["width"][:] = 0.0
    [(frame, _)] = sn.frames_from_scenario(s, "f.pkl")
    assert frame.num_actors == 3


def test_non_dict_pickle_is_refused(tmp_path):
    dump_pickle([1, 2, 3], tmp_path / "sd_list.pkl")
    with pytest.raises(ValueError, match=r"sd_list\.pkl: expected a ScenarioNet scenario dict"):
        list(sn.read_scenarionet(tmp_path))


def test_headings_wrap_into_range():
    s = standard_scenario()
    s["tracks"]["11"]["state"]["heading"][:] = np.pi / 2 - 1e-9  # equal to the ego's, minus eps
    s["tracks"]["14"]["state"]["heading"][:] = -7.0
    [(frame, _)] = sn.frames_from_scenario(s, "f.pkl")
    assert np.all((frame.heading >= 0) & (frame.heading < 2 * np.pi))
    np.testing.assert_allclose(frame.heading[2], np.mod(-7.0 - np.pi / 2, 2 * np.pi), atol=1e-6)


def test_bad_current_time_index_names_field():
    s = standard_scenario()
    s["metadata"]["current_time_index"] = "soon"
    with pytest.raises(ValueError, match=r"f\.pkl: metadata\.current_time_index: expected an int"):
        sn.frames_from_scenario(s, "f.pkl")
