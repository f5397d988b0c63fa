"""The GPUDrive / Nocturne JSON reader: synthetic layouts, then every real womd_mini file."""

from __future__ import annotations

import collections
import json
import os

import numpy as np
import pytest

from scenegen_jax.config import get_config
from scenegen_jax.data import womd_json as W
from scenegen_jax.data import womd_scene as S
from scenegen_jax.data.prepare import prepare
from scenegen_jax.data.sources import source_spec
from scenegen_jax.data.surface import DEFAULT_HALF_WIDTH_M, Centerline, outline_lanes
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE
from scenegen_jax.vector_map import ROAD_EDGE, RoadLine

# ---------------------------------------------------------------- synthetic layouts


def _object(xy, heading, vel, valid, otype="vehicle", size=(2.0, 4.5), columns=False):
    xy, vel = np.asarray(xy, float), np.asarray(vel, float)
    if columns:
        pos = {"x": xy[:, 0].tolist(), "y": xy[:, 1].tolist()}
        v = {"x": vel[:, 0].tolist(), "y": vel[:, 1].tolist()}
    else:
        pos = [{"x": float(x), "y": float(y)} for x, y in xy]
        v = [{"x": float(x), "y": float(y)} for x, y in vel]
    return {
        "position": pos,
        "velocity": v,
        "heading": [float(h) for h in heading],
        "valid": [bool(b) for b in valid],
        "width": size[0],
        "length": size[1],
        "type": otype,
        "goalPosition": {"x": float(xy[-1, 0]), "y": float(xy[-1, 1])},
    }


def _scene(degrees: bool, columns: bool = False, sentinel: float = -10000.0, sdc=None):
    """Three moving vehicles along +x (one 1 m/s behind), a pedestrian, a cyclist; T = 21."""
    t = np.arange(21) * 0.1
    objs = []
    for i, (y, speed) in enumerate(((0.0, 10.0), (3.5, 8.0), (-3.5, 12.0))):
        xy = np.stack([100 + speed * t + 5 * i, 50 + y + 0 * t], 1)
        vel = np.tile([speed, 0.0], (21, 1))
        heading = np.zeros(21) + (360.0 if degrees else 2 * np.pi) * (i == 1)  # unwrapped
        objs.append(_object(xy, heading, vel, np.ones(21), columns=columns))
    valid = np.ones(21, bool)
    valid[15:] = False
    xy = np.stack([110 + 0 * t, 58 + 1.2 * t], 1)
    heading = np.full(21, 90.0 if degrees else np.pi / 2)
    vel = np.tile([0.0, 1.2], (21, 1))
    for arr in (xy, vel):
        arr[~valid] = sentinel
    heading[~valid] = sentinel
    objs.append(_object(xy, heading, vel, valid, "pedestrian", (0.6, 0.6), columns))
    xy = np.stack([90 + 5 * t, 45 + 0 * t], 1)
    objs.append(_object(xy, np.zeros(21), np.tile([5.0, 0], (21, 1)), np.ones(21), "cyclist",
                        (0.8, 1.8), columns))
    lane = [{"x": float(x), "y": 50.0} for x in np.linspace(0, 300, 31)]
    roads = [
        {"geometry": lane, "type": "lane"},
        {"geometry": [{"x": float(x), "y": 51.8} for x in np.linspace(0, 300, 31)],
         "type": "road_line"},
        {"geometry": [{"x": float(x), "y": 55.5} for x in np.linspace(0, 300, 31)],
         "type": "road_edge"},
        {"geometry": [{"x": 120.0, "y": 46.0}], "type": "stop_sign"},
    ]
    data = {"name": "synthetic.json", "objects": objs, "roads": roads, "tl_states": {}}
    if sdc is not None:
        data["metadata"] = {"sdc_track_index": sdc}
    return data


@pytest.mark.parametrize("degrees", [False, True])
@pytest.mark.parametrize("columns", [False, True])
def test_layouts_read_alike(degrees, columns):
    frames, drops = W.frames_from_scenario(_scene(degrees, columns, sdc=0), "x.json", 10)
    assert [f.scene_id for f in frames] == ["x/0", "x/10", "x/20"]
    f = frames[1]  # t = 1 s: ego at x = 110, y = 50
    assert sorted(f.cls.tolist()) == sorted([VEHICLE, VEHICLE, PEDESTRIAN, BICYCLIST])
    v = f.cls == VEHICLE
    # Unwrapped 2 pi / 360 degrees read as heading 0 in the ego frame.
    np.testing.assert_allclose(np.cos(f.heading[v]), 1.0, atol=1e-9)
    ped = f.position[f.cls == PEDESTRIAN][0]
    np.testing.assert_allclose(ped, [0.0, 8 + 1.2], atol=1e-9)  # (110, 59.2) - (110, 50)
    np.testing.assert_allclose(f.velocity[f.cls == PEDESTRIAN][0], [0.0, 1.2], atol=1e-9)
    assert len(frames[2].cls) == 3  # the pedestrian is invalid (sentinel) at t = 2 s
    assert drops["map:stop_sign"] == 1


def test_sentinel_steps_never_become_actors():
    """The pedestrian (track 3) is invalid from step 15 on, its states there a sentinel near
    the world origin: it is an actor at steps 0-14 only, and the other three at every step,
    each where its track puts it in the ego frame (hand-computed: the ego, vehicle 0, drives
    from (100, 50) m at 10 m/s along +x, so at time s an object at world (x, y) is at
    (x - 100 - 10 s, y - 50))."""
    frames, _ = W.frames_from_scenario(_scene(False, sentinel=0.0001, sdc=0), "x.json", 1)
    assert [f.scene_id for f in frames] == [f"x/{t}" for t in range(21)]
    for t, f in enumerate(frames):
        s = 0.1 * t
        want = {"1": (5 - 2 * s, 3.5), "2": (10 + 2 * s, -3.5), "4": (-10 - 5 * s, -5.0)}
        if t < 15:
            want["3"] = (10 - 10 * s, 8 + 1.2 * s)
        assert sorted(f.track_id.tolist()) == sorted(want), f.scene_id
        got = dict(zip(f.track_id.tolist(), f.position, strict=True))
        for tid, xy in want.items():
            np.testing.assert_allclose(got[tid], xy, atol=1e-9, err_msg=f"{f.scene_id} {tid}")
        assert np.all(np.abs(f.position) < 100), f.scene_id
    classes = collections.Counter(int(c) for f in frames for c in f.cls)
    assert classes == {VEHICLE: 2 * 21, PEDESTRIAN: 15, BICYCLIST: 21}


def test_degrees_detected_from_velocity_not_from_range():
    heading = np.full((1, 6), 10.0)  # 10 rad or 10 degrees: the velocity decides
    valid = np.ones((1, 6), bool)
    vel = np.array([[[np.cos(np.deg2rad(10)), np.sin(np.deg2rad(10))]] * 6]) * 5
    assert W.heading_unit_is_degrees(heading, vel, valid)
    vel = np.array([[[np.cos(10.0), np.sin(10.0)]] * 6]) * 5
    assert not W.heading_unit_is_degrees(heading, vel, valid)
    # Nothing moving: only the range tells (beyond 2 pi: degrees).
    assert W.heading_unit_is_degrees(heading, vel * 0, valid)
    assert not W.heading_unit_is_degrees(heading / 4, vel * 0, valid)


def test_sdc_marker_and_estimate():
    data = _scene(False, sdc=2)
    frames, _ = W.frames_from_scenario(data, "x.json", 10)
    np.testing.assert_allclose(frames[0].ego_velocity, [12.0, 0.0])
    # No marker: the vehicle whose farthest other object is nearest, on average over the
    # steps, is the ego. At t = 0 vehicle 0 at (100, 50) has the pedestrian at (110, 58)
    # farthest, 12.8 m off; vehicle 1 at (105, 53.5) the cyclist at (90, 45), 17.2 m; vehicle
    # 2 at (110, 46.5) the cyclist, 20.1 m. Over the 21 steps: 15.9, 19.9 and 27.0 m.
    del data["metadata"]
    tracks, _ = W.read_tracks(data["objects"], "x.json")
    assert W.estimate_sdc(tracks) == 0
    # A vehicle nearer the middle than vehicle 0 becomes the ego, but not once it misses a step.
    t = np.arange(21) * 0.1
    middle = np.stack([101 + 8 * t, 48 + 0 * t], 1)  # mean farthest distance 14.5 m, not 15.9
    data["objects"].append(_object(middle, np.zeros(21), np.tile([8.0, 0], (21, 1)),
                                   np.ones(21)))
    assert W.estimate_sdc(W.read_tracks(data["objects"], "x.json")[0]) == 5
    data["objects"][-1]["valid"][7] = False
    assert W.estimate_sdc(W.read_tracks(data["objects"], "x.json")[0]) == 0


def test_bad_input_names_file_and_field():
    data = _scene(False)
    data["objects"][1]["width"] = "wide"
    with pytest.raises(ValueError, match=r"x\.json: objects\[1\]\.width"):
        W.frames_from_scenario(data, "x.json", 10)
    data = _scene(False)
    data["objects"][0]["heading"] = data["objects"][0]["heading"][:5]
    with pytest.raises(ValueError, match=r"x\.json: objects\[0\]\.heading"):
        W.frames_from_scenario(data, "x.json", 10)
    # A damaged metadata field is refused, not read as "no SDC marker" (another ego).
    data = _scene(False, sdc=2)
    data["metadata"] = "x"
    with pytest.raises(ValueError, match=r"^x\.json: metadata: expected an object, got str"):
        W.frames_from_scenario(data, "x.json", 10)


def test_surface_widths_from_lines_and_edges():
    center = Centerline(id=0, lane_type="VEHICLE", points=np.stack(
        [np.linspace(0, 50, 11), np.zeros(11)], 1))
    line = RoadLine(np.array([[-5, 1.6], [55, 1.6]]), "DASHED_WHITE")
    edge = RoadLine(np.array([[-5, -5.0], [55, -5.0]]), ROAD_EDGE)
    (lane,), (drivable,) = outline_lanes([center], [line, edge])
    np.testing.assert_allclose(lane.left[:, 1], 1.6)  # to the painted line
    # The edge is 5 m away, beyond MAX_HALF_WIDTH_M: the lane keeps the default half width
    # on that side, and the drivable surface reaches on to the kerb.
    np.testing.assert_allclose(lane.right[:, 1], -DEFAULT_HALF_WIDTH_M)
    np.testing.assert_allclose(drivable[:, 1].max(), 1.6)
    np.testing.assert_allclose(drivable[:, 1].min(), -5.0)
    assert not lane.is_intersection


def test_crossing_centerlines_are_intersection_lanes():
    straight = np.stack([np.linspace(0, 40, 9), np.zeros(9)], 1)
    across = np.stack([np.full(9, 20.0), np.linspace(-20, 20, 9)], 1)
    merge = np.stack([np.linspace(40, 60, 5), np.linspace(10, 0, 5)], 1)  # meets at an end
    lanes, _ = outline_lanes(
        [Centerline(i, "VEHICLE", p) for i, p in enumerate((straight, across, merge))], []
    )
    assert [lane.is_intersection for lane in lanes] == [True, True, False]


def test_lanes_outlined_together_are_each_outlined_alone():
    """Lanes outlined in one call (their normals and rays stacked): each lane's boundaries
    and surface are those of the lane outlined alone, with `np.gradient`'s tangents; given
    half widths win where positive."""
    rng = np.random.default_rng(0)
    paths = [np.cumsum(rng.uniform(0.3, 1.0, (n, 2)), axis=0) + 30 * i
             for i, n in enumerate((2, 3, 7, 12))]
    given = np.where(rng.uniform(size=(7, 2)) < 0.5, 2.5, 0.0)
    centers = [Centerline(i, "VEHICLE", p, given if len(p) == 7 else None)
               for i, p in enumerate(paths)]
    lines = [RoadLine(p + 1.2 * (j % 2 * 2 - 1), ROAD_EDGE if j % 3 else "SOLID_WHITE")
             for j, p in enumerate(paths * 2)]
    lanes, drivable = outline_lanes(centers, lines)
    for c, lane, area in zip(centers, lanes, drivable, strict=True):
        (alone,), (alone_area,) = outline_lanes([c], lines)
        np.testing.assert_array_equal(lane.left, alone.left)
        np.testing.assert_array_equal(lane.right, alone.right)
        np.testing.assert_array_equal(area, alone_area)
        tangent = np.gradient(c.points, axis=0)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        half = np.linalg.norm(lane.left - c.points, axis=1)
        np.testing.assert_allclose(lane.left - c.points,
                                   half[:, None] * np.stack([-tangent[:, 1], tangent[:, 0]], 1),
                                   atol=1e-12)
        if c.half_widths is not None:
            np.testing.assert_allclose(half[c.half_widths[:, 0] > 0], 2.5)
    assert outline_lanes([], lines) == ((), ())


# ---------------------------------------------------------------- the real files


def test_damaged_fields_are_named_or_counted():
    # `valid` must hold booleans: the strings "false" would all read as true.
    data = _scene(False, sdc=0)
    data["objects"][3]["valid"] = ["false"] * 21
    with pytest.raises(ValueError, match=r"x\.json: objects\[3\]\.valid: expected booleans, "
                       r"got 'false'"):
        W.frames_from_scenario(data, "x.json", 10)
    data["objects"][3]["valid"] = [True] * 20 + [None]
    with pytest.raises(ValueError, match=r"objects\[3\]\.valid: expected booleans, got None"):
        W.frames_from_scenario(data, "x.json", 10)
    data["objects"][3]["valid"] = 5
    with pytest.raises(ValueError, match=r"x\.json: objects\[3\]\.valid: expected a list"):
        W.frames_from_scenario(data, "x.json", 10)
    # A road with no points is a counted degenerate feature, as one with a single point.
    data = _scene(False, sdc=0)
    data["roads"] += [{"geometry": [], "type": "road_line"},
                      {"geometry": [{"x": 1.0, "y": 2.0}], "type": "road_line"}]
    assert W.frames_from_scenario(data, "x.json", 10)[1]["map:degenerate_road_line"] == 2
    # Steps of the stride at which the ego is not valid are counted; none at all is an error.
    data = _scene(False, sdc=0)
    data["objects"][0]["valid"][10] = False
    frames, drops = W.frames_from_scenario(data, "x.json", 10)
    assert [f.scene_id for f in frames] == ["x/0", "x/20"] and drops["frame:no_ego"] == 1
    data["objects"][0]["valid"] = [False] * 21
    with pytest.raises(ValueError, match=r"x\.json: objects \(the SDC, id 0\)\.valid: the SDC "
                       r"is valid at none of the steps 0, 10, \.\.\. of 21"):
        W.frames_from_scenario(data, "x.json", 10)


def test_deeply_nested_json_is_a_counted_bad_file(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    (src / "good.json").write_text(json.dumps(_scene(False, sdc=0)))
    (src / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    spec = source_spec("womd_json", str(src), None, 10)
    summary, _ = prepare(spec, str(tmp_path / "cache"), get_config("tiny"), workers=1)
    assert summary.scenes == 3 and summary.bad_files == {"ValueError": 1}
    assert "deep.json: not valid JSON (nested too deeply)" in summary.bad_file_list[0]["error"]


@pytest.fixture(scope="module")
def womd_files(womd_root):
    return [str(p) for p in W.scenario_files(os.path.join(womd_root, "gpudrive_json"))]


@pytest.fixture(scope="module")
def womd_frames(womd_files):
    return {path: W.read_file(path, 10) for path in womd_files}


def _direct_counts(path: str, stride: int) -> collections.Counter:
    """Per class, objects valid at the frame steps, other than the ego, counted from the file's
    own `valid`, `type`, `width` and `length`. The ego is the file's marker where it has one,
    else the reader's estimate (checked on its own in `test_sdc_marker_and_estimate`)."""
    with open(path) as f:
        data = json.load(f)
    objects = data["objects"]
    assert all(o["type"] in S.CLASS_FROM_TYPE for o in objects)  # object index = track index
    marker = (data.get("metadata") or {}).get("sdc_track_index")
    sdc = marker if marker is not None else W.estimate_sdc(W.read_tracks(objects, path)[0])
    out = collections.Counter()
    for t in range(0, len(objects[0]["valid"]), stride):
        if not objects[sdc]["valid"][t]:
            continue
        for o, obj in enumerate(objects):
            sized = obj["type"] == "pedestrian" or (obj["width"] > 0 and obj["length"] > 0)
            out[S.CLASS_FROM_TYPE[obj["type"]]] += int(obj["valid"][t] and o != sdc and sized)
    return out


def test_every_real_file_reads_with_direct_counts(womd_files, womd_frames):
    assert len(womd_files) == 93
    for path, (frames, _) in womd_frames.items():
        assert frames, path
        got = collections.Counter()
        for f in frames:
            got.update(f.cls.tolist())
        assert +got == +_direct_counts(path, 10), path


def _heading_velocity_degrees(heading, velocity) -> np.ndarray:
    diff = heading - np.arctan2(velocity[..., 1], velocity[..., 0])
    return np.degrees(np.abs(np.angle(np.exp(1j * diff))))


def test_real_vehicles_heading_velocity_length(womd_files, womd_frames):
    """Moving vehicles (> 2 m/s) point where they go, in every scene and at every step.

    The frames (every 10th step) hold too few moving vehicles in some scenes for a median,
    so the per-scene check pools every step of the scenario. The one scene whose moving
    states all belong to a single car is exempt: that car turns 89 degrees at 2.4 m/s, and
    the centre of a car in a tight turn moves up to ~10 degrees off its heading (the file's
    own positions agree with its velocities there; a reader bug would fail by tens of
    degrees, as degrees read as radians do).
    """
    lengths, bad = [], []
    for path in womd_files:
        with open(path) as f:
            tracks, _ = W.read_tracks(json.load(f)["objects"], path)
        vehicle = np.array([t == "vehicle" for t in tracks.type])[:, None]
        moving = tracks.valid & vehicle & (np.linalg.norm(tracks.velocity, axis=-1) > 2.0)
        angles = _heading_velocity_degrees(tracks.heading, tracks.velocity)[moving]
        if moving.any() and np.median(angles) >= 5.0:
            bad.append((os.path.basename(path), int(moving.any(axis=1).sum())))
    assert bad == [("tfrecord-00083-of-01000_451.json", 1)]
    pooled = []
    for frames, _ in womd_frames.values():  # the frames carry the same headings as the file
        for f in frames:
            v = f.cls == VEHICLE
            lengths.extend(f.size[v, 1].tolist())
            m = v & (np.linalg.norm(f.velocity, axis=1) > 2.0)
            pooled.extend(_heading_velocity_degrees(f.heading[m], f.velocity[m]).tolist())
    assert len(pooled) > 1000 and np.median(pooled) < 2.0
    assert 3.5 < np.median(lengths) < 6.0


# Waymo's road line types (GPUDrive's `map_element_id` is the proto's RoadLine type + 5) by
# their Argoverse 2 mark names.
WAYMO_LINE_MARKS = {
    6: "DASHED_WHITE",  # BROKEN_SINGLE_WHITE
    7: "SOLID_WHITE",  # SOLID_SINGLE_WHITE
    8: "DOUBLE_SOLID_WHITE",  # SOLID_DOUBLE_WHITE
    9: "DASHED_YELLOW",  # BROKEN_SINGLE_YELLOW
    10: "DOUBLE_DASH_YELLOW",  # BROKEN_DOUBLE_YELLOW
    11: "SOLID_YELLOW",  # SOLID_SINGLE_YELLOW
    12: "DOUBLE_SOLID_YELLOW",  # SOLID_DOUBLE_YELLOW
    13: "SOLID_DASH_YELLOW",  # PASSING_DOUBLE_YELLOW
}


def _file_lines(path: str, center: np.ndarray, radius: float = S.MAP_RADIUS_M):
    """The road edges and road lines of a file as a map around `center` (world, m) must hold
    them, read from the JSON itself: world polylines without repeated points (fewer than two
    left: none), whose bounding box meets the square of half-side `radius` m around
    `center`; the edges and the typed lines in file order, then the lines without a type
    (their marks inferred) in file order. Returns ([(points, mark or None)], untyped lines
    in the whole file)."""
    with open(path) as f:
        roads = json.load(f)["roads"]
    typed, untyped = [], []
    for road in roads:
        if road["type"] not in ("road_edge", "road_line"):
            continue
        pts = np.array([[p["x"], p["y"]] for p in road["geometry"]], np.float64)
        pts = pts[np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6]]
        if len(pts) < 2:
            continue
        element = road.get("map_element_id")
        if road["type"] == "road_edge":
            typed.append((pts, ROAD_EDGE))
        elif element in WAYMO_LINE_MARKS:
            typed.append((pts, WAYMO_LINE_MARKS[element]))
        else:
            untyped.append((pts, None))
    near = [(p, m) for p, m in typed + untyped
            if np.all(p.min(0) <= center + radius) and np.all(p.max(0) >= center - radius)]
    return near, len(untyped)


def test_real_maps_have_lanes_lines_and_surface(womd_frames):
    """Each file's first frame has lanes and a drivable surface, and exactly the file's road
    edges and road lines near the ego (`_file_lines`), point for point in the ego frame, with
    their marks: road edges ROAD_EDGE, typed lines their Waymo type's, the others one that
    `infer_line_marks` gives."""
    inferred = {"UNKNOWN", "SOLID_WHITE", "DASHED_WHITE", "DOUBLE_SOLID_YELLOW"}
    seen = collections.Counter()
    for path, (frames, drops) in womd_frames.items():
        f = frames[0]
        assert f.map.lanes and f.map.drivable_areas, path
        assert f.map.dataset == "waymo", path
        center = f.city_from_ego[:2, 2]
        h0 = np.arctan2(f.city_from_ego[1, 0], f.city_from_ego[0, 0])
        want, untyped = _file_lines(path, center)
        assert drops["map_info:road_line_mark_inferred"] == untyped, path
        assert len(f.map.lines) == len(want), path
        turn = np.array([[np.cos(h0), -np.sin(h0)], [np.sin(h0), np.cos(h0)]])
        for line, (points, mark) in zip(f.map.lines, want, strict=True):
            np.testing.assert_allclose(line.points, (points - center) @ turn, atol=1e-6,
                                       err_msg=path)
            if mark is None:
                assert line.mark in inferred, (path, line.mark)
                seen["untyped"] += 1
            else:
                assert line.mark == mark, path
                seen["edge" if mark == ROAD_EDGE else "typed"] += 1
    assert min(seen["edge"], seen["typed"], seen["untyped"]) > 100, seen


def test_prepare_counts_and_skips_a_corrupt_file(tmp_path, womd_files):
    """A folder with one corrupt file among real ones: the good ones are prepared, the bad
    one counted with its name; --strict stops at it."""
    import shutil

    src = tmp_path / "src"
    src.mkdir()
    for path in womd_files[:2]:
        os.symlink(path, src / os.path.basename(path))  # read in place, never copied
    (src / "broken.json").write_text('{"objects": [')
    cfg = get_config("tiny")
    spec = source_spec("womd_json", str(src), None, 30)
    summary, _ = prepare(spec, str(tmp_path / "cache"), cfg, workers=2)
    assert summary.files == 3
    assert summary.bad_files == {"ValueError": 1}
    assert "broken.json" in summary.bad_file_list[0]["file"]
    direct = sum(sum(_direct_counts(p, 30).values()) for p in womd_files[:2])
    # actors + outside_region is every row of a modelled class read (overflow is a part).
    assert sum(summary.actors.values()) + sum(summary.outside_region.values()) == direct
    with pytest.raises(ValueError, match="broken.json"):
        prepare(spec, str(tmp_path / "cache2"), cfg, workers=1, strict=True)
    shutil.rmtree(src)


def test_real_vehicles_on_the_drivable_surface(tmp_path, womd_root):
    """The built drivable layer holds the moving vehicles of real Waymo scenes (val split,
    `cpu` raster); parked cars in parking lots, which Waymo maps do not draw, may be off it."""
    from scenegen_jax.data.cache import load_cache
    from scenegen_jax.eval.realism import real_data_check

    cfg = get_config("cpu")
    spec = source_spec("womd_json", os.path.join(womd_root, "gpudrive_json"), "val", 10)
    prepare(spec, str(tmp_path / "c"), cfg, workers=2)
    check = real_data_check(load_cache(str(tmp_path / "c")), cfg)
    assert check["moving_drivable_share"] > 0.95, check
    assert check["drivable_share"] > 0.55, check


def test_strict_names_the_file_of_any_reader_error(monkeypatch):
    """--strict stops at the first unusable file with the CLI's bad-input error (ValueError,
    naming the file), whatever a reader raised: here a KeyError."""
    from scenegen_jax.data import prepare as P

    def broken(spec, path):
        raise KeyError("position")

    monkeypatch.setattr(P, "read_file", broken)
    spec = source_spec("womd_json", "root", None, 10)
    assert P.encode_file(spec, "f.json", get_config("tiny")).error == "KeyError: 'position'"
    with pytest.raises(ValueError, match=r"^f\.json: KeyError: 'position'$"):
        P.encode_file(spec, "f.json", get_config("tiny"), strict=True)


def test_every_source_is_held_to_the_road_user_limits(tmp_path):
    """`sources.read_file` (what `prepare` reads with): a 35 m box and a 150 m/s actor are
    counted drops; a 150 m/s ego makes the file a bad one, named."""
    from scenegen_jax.data.sources import read_file

    data = _scene(False, sdc=0)
    data["objects"][1]["length"] = 35.0
    data["objects"][2]["velocity"] = [{"x": 150.0, "y": 0.0}] * 21
    (tmp_path / "limits.json").write_text(json.dumps(data))
    spec = source_spec("womd_json", str(tmp_path), None, 10)
    frames, drops = read_file(spec, str(tmp_path / "limits.json"))
    assert (drops["invalid:size"], drops["invalid:speed"]) == (3, 3)  # one each per frame
    assert all(len(f.cls) == 2 for f in frames[:2]) and len(frames[2].cls) == 1
    data["objects"][0]["velocity"] = [{"x": 150.0, "y": 0.0}] * 21
    (tmp_path / "limits.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"limits\.json: scene limits/0: ego velocity: speed 150"):
        read_file(spec, str(tmp_path / "limits.json"))


def _set_xy(points, value: float) -> None:
    for p in points:
        p["x"] = p["y"] = value


def test_world_coordinates_beyond_range_are_named_or_counted(tmp_path):
    """Coordinates beyond `frame.MAX_WORLD_M` are damaged, like NaN: all of them at 1e300
    gave scenes of actors at the ego's position. A map feature or the ego there is a file
    error naming the field; another object there is a counted drop; 1e308 warns nothing."""
    import warnings

    from scenegen_jax.data.sources import read_file

    spec = source_spec("womd_json", str(tmp_path), None, 10)
    path = str(tmp_path / "far.json")

    def read(data):
        with open(path, "w") as f:
            json.dump(data, f)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            return read_file(spec, path)

    data = _scene(False, sdc=0)
    for o in data["objects"]:
        _set_xy(o["position"], 1e300)
        _set_xy([o["goalPosition"]], 1e300)
    for road in data["roads"]:
        _set_xy(road["geometry"], 1e300)
    with pytest.raises(ValueError, match=r"far\.json: roads\[0\]\.geometry: a coordinate "
                       r"beyond 1e\+07 m"):
        read(data)
    data = _scene(False, sdc=0)
    _set_xy(data["objects"][0]["position"], 1e300)
    with pytest.raises(ValueError, match=r"far\.json: objects \(the SDC, id 0\)\.position: "
                       r"beyond 1e\+07 m at step 0"):
        read(data)
    data = _scene(False, sdc=0)
    _set_xy(data["objects"][1]["position"], 1e308)
    _set_xy(data["objects"][2]["velocity"], 1e308)
    frames, drops = read(data)
    assert (drops["invalid:world_position"], drops["invalid:speed"]) == (3, 3)  # per frame
    assert [len(f.cls) for f in frames] == [2, 2, 1]  # of 4, 4, 3 besides the ego
    _set_xy(data["objects"][0]["velocity"], 1e308)
    with pytest.raises(ValueError, match=r"far\.json: scene far/0: ego velocity: speed "
                       r"1\.414e\+308 m/s"):
        read(data)
