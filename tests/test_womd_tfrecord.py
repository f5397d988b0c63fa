"""The Waymo Scenario TFRecord reader: framing and CRC32C, the real scenario against an
independent decode (google.protobuf with message classes built here from scenario.proto's
and map.proto's field numbers), records as units of work, damaged files as bad units, and
the same frames as the GPUDrive JSON reader gives for the same scene."""

from __future__ import annotations

import collections
import dataclasses
import json
import os
import struct

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from scenegen_jax.config import get_config
from scenegen_jax.data import womd_json as W
from scenegen_jax.data import womd_scene as S
from scenegen_jax.data import womd_tfrecord as R
from scenegen_jax.data.prepare import prepare
from scenegen_jax.data.sources import source_spec
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE
from scenegen_jax.vector_map import ROAD_EDGE

# ---------------------------------------------------------------- an independent decoder

_F = descriptor_pb2.FieldDescriptorProto
_SCALARS = {"double": _F.TYPE_DOUBLE, "float": _F.TYPE_FLOAT, "int32": _F.TYPE_INT32,
            "int64": _F.TYPE_INT64, "bool": _F.TYPE_BOOL, "string": _F.TYPE_STRING}
_OPT, _REP = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED
# (name, number, type, label) per message, from scenario.proto and map.proto; enums as int32.
_MESSAGES = {
    "MapPoint": [("x", 1, "double", _OPT), ("y", 2, "double", _OPT), ("z", 3, "double", _OPT)],
    "ObjectState": [("center_x", 2, "double", _OPT), ("center_y", 3, "double", _OPT),
                    ("center_z", 4, "double", _OPT), ("length", 5, "float", _OPT),
                    ("width", 6, "float", _OPT), ("height", 7, "float", _OPT),
                    ("heading", 8, "float", _OPT), ("velocity_x", 9, "float", _OPT),
                    ("velocity_y", 10, "float", _OPT), ("valid", 11, "bool", _OPT)],
    "Track": [("id", 1, "int32", _OPT), ("object_type", 2, "int32", _OPT),
              ("states", 3, "ObjectState", _REP)],
    "LaneCenter": [("speed_limit_mph", 1, "double", _OPT), ("type", 2, "int32", _OPT),
                   ("interpolating", 3, "bool", _OPT), ("polyline", 8, "MapPoint", _REP),
                   ("entry_lanes", 9, "int64", _REP), ("exit_lanes", 10, "int64", _REP)],
    "RoadEdge": [("type", 1, "int32", _OPT), ("polyline", 2, "MapPoint", _REP)],
    "RoadLine": [("type", 1, "int32", _OPT), ("polyline", 2, "MapPoint", _REP)],
    "StopSign": [("lane", 1, "int64", _REP), ("position", 2, "MapPoint", _OPT)],
    "Crosswalk": [("polygon", 1, "MapPoint", _REP)],
    "SpeedBump": [("polygon", 1, "MapPoint", _REP)],
    "Driveway": [("polygon", 1, "MapPoint", _REP)],
    "MapFeature": [("id", 1, "int64", _OPT), ("lane", 3, "LaneCenter", _OPT),
                   ("road_line", 4, "RoadLine", _OPT), ("road_edge", 5, "RoadEdge", _OPT),
                   ("stop_sign", 7, "StopSign", _OPT), ("crosswalk", 8, "Crosswalk", _OPT),
                   ("speed_bump", 9, "SpeedBump", _OPT), ("driveway", 10, "Driveway", _OPT)],
    "Scenario": [("timestamps_seconds", 1, "double", _REP), ("tracks", 2, "Track", _REP),
                 ("scenario_id", 5, "string", _OPT), ("sdc_track_index", 6, "int32", _OPT),
                 ("map_features", 8, "MapFeature", _REP),
                 ("current_time_index", 10, "int32", _OPT)],
}
FEATURE_KINDS = ("lane", "road_line", "road_edge", "stop_sign", "crosswalk", "speed_bump",
                 "driveway")
# map.proto's RoadLineType by its Argoverse 2 mark name.
LINE_MARKS = {1: "DASHED_WHITE", 2: "SOLID_WHITE", 3: "DOUBLE_SOLID_WHITE", 4: "DASHED_YELLOW",
              5: "DOUBLE_DASH_YELLOW", 6: "SOLID_YELLOW", 7: "DOUBLE_SOLID_YELLOW",
              8: "SOLID_DASH_YELLOW"}
TYPE_NAMES = {1: "vehicle", 2: "pedestrian", 3: "cyclist"}
CLASSES = {1: VEHICLE, 2: PEDESTRIAN, 3: BICYCLIST}


def _scenario_class():
    """waymo.open_dataset.Scenario (the fields above) as a google.protobuf message class."""
    fd = descriptor_pb2.FileDescriptorProto(name="womd_test.proto", package="womd_test",
                                            syntax="proto2")
    for name, fields in _MESSAGES.items():
        msg = fd.message_type.add(name=name)
        for fname, number, ftype, label in fields:
            field = msg.field.add(name=fname, number=number, label=label)
            if ftype in _SCALARS:
                field.type = _SCALARS[ftype]
            else:
                field.type, field.type_name = _F.TYPE_MESSAGE, f".womd_test.{ftype}"
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("womd_test.Scenario"))


Scenario = _scenario_class()


def _write_records(path, payloads) -> list[int]:
    """A TFRecord file of `payloads`; the byte offset of each record."""
    offsets, out = [], bytearray()
    for data in payloads:
        offsets.append(len(out))
        length = struct.pack("<Q", len(data))
        out += length + struct.pack("<I", R.masked_crc32c(length)) + data
        out += struct.pack("<I", R.masked_crc32c(data))
    path.write_bytes(bytes(out))
    return offsets


def _kind(feature) -> str:
    return next(k for k in FEATURE_KINDS if feature.HasField(k))


# ---------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def real_path(womd_root) -> str:
    return os.path.join(womd_root, "scenario_tfrecord", "motion_data_one_scenario.tfrecord")


@pytest.fixture(scope="module")
def real_bytes(real_path) -> bytes:
    with open(real_path, "rb") as f:
        return f.read()


@pytest.fixture(scope="module")
def real(real_bytes):
    """The real scenario decoded by google.protobuf (the record's data: bytes 12 to -4)."""
    scenario = Scenario()
    scenario.ParseFromString(real_bytes[12:-4])
    return scenario


@pytest.fixture(scope="module")
def real_frames(real_path):
    return R.read_file(R.record_unit(real_path, 0, 0), 10)


# ---------------------------------------------------------------- framing and CRC32C


def _crc32c_bitwise(data: bytes) -> int:
    """CRC32C one bit at a time: the definition, for comparison."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_crc32c_known_vectors():
    assert R.crc32c(b"123456789") == 0xE3069283  # RFC 3720's check value
    assert R.crc32c(b"") == 0
    # RFC 3720, appendix B.4.
    assert R.crc32c(bytes(32)) == 0x8A9136AA
    assert R.crc32c(b"\xff" * 32) == 0x62A8AB43
    assert R.crc32c(bytes(range(32))) == 0x46DD794E
    assert R.crc32c(bytes(range(31, -1, -1))) == 0x113FDB5C
    # Lengths on both sides of the vectorised chunk size, against the bitwise definition.
    rng = np.random.default_rng(0)
    for n in (1, R.CRC_CHUNK - 1, R.CRC_CHUNK, R.CRC_CHUNK + 1, 3 * R.CRC_CHUNK + 17, 5000):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert R.crc32c(data) == _crc32c_bitwise(data), n


def test_real_file_crcs_and_units(real_path, real_bytes):
    """The stored CRCs of the real file are TFRecord's masked CRC32Cs; it is one unit."""
    length, length_crc = struct.unpack_from("<QI", real_bytes, 0)
    assert length + 16 == len(real_bytes)
    assert R.masked_crc32c(real_bytes[:8]) == length_crc
    assert R.masked_crc32c(real_bytes[12:-4]) == struct.unpack("<I", real_bytes[-4:])[0]
    units = R.scenario_files(os.path.dirname(real_path))
    assert units == [f"{real_path}#0@0"]
    assert R.parse_unit(units[0]) == (real_path, 0, 0)
    assert R.parse_unit("a#b/c.tfrecord#12@3456") == ("a#b/c.tfrecord", 12, 3456)
    for bad in ("c.tfrecord", "c.tfrecord#1", "c.tfrecord#x@0", "#1@0"):
        with pytest.raises(ValueError, match="not a TFRecord unit"):
            R.parse_unit(bad)


# ---------------------------------------------------------------- the real scenario


def test_real_scenario_frames_are_the_sdcs(real, real_frames):
    """A frame at every 10th step where the SDC is valid, centred on the SDC's own state;
    its actors are exactly the other vehicles, pedestrians and cyclists valid there."""
    frames, drops = real_frames
    sdc = real.tracks[real.sdc_track_index]
    steps = [t for t in range(0, len(real.timestamps_seconds), 10) if sdc.states[t].valid]
    assert len(frames) == len(steps) >= 9
    assert [f.scene_id for f in frames] == [f"{real.scenario_id}/{t}" for t in steps]
    classes = collections.Counter()
    for f, t in zip(frames, steps, strict=True):
        s = sdc.states[t]
        np.testing.assert_allclose(f.city_from_ego[:2, 2], [s.center_x, s.center_y])
        h0 = np.arctan2(f.city_from_ego[1, 0], f.city_from_ego[0, 0])
        np.testing.assert_allclose(np.cos(h0 - s.heading), 1.0, atol=1e-9)
        np.testing.assert_allclose(f.ego_size, [s.width, s.length])
        np.testing.assert_allclose(np.linalg.norm(f.ego_velocity),
                                   np.hypot(s.velocity_x, s.velocity_y), atol=1e-9)
        want = {str(tr.id): CLASSES[tr.object_type] for i, tr in enumerate(real.tracks)
                if tr.states[t].valid and i != real.sdc_track_index}
        assert dict(zip(f.track_id.tolist(), f.cls.tolist(), strict=True)) == want
        assert f.size_measured is None and f.map.dataset == "waymo"
        classes.update(f.cls.tolist())
    assert classes[VEHICLE] > 0 and classes[PEDESTRIAN] > 0
    assert not any(k.startswith("type:") for k in drops)  # only the three classes here


def test_real_actors_hand_checked(real, real_frames):
    """Position, heading, box, velocity and class of every actor of every frame, computed
    here from the independently decoded states: the world offset from the SDC rotated by
    minus its heading, the heading relative to it in [0, 2 pi)."""
    frames, _ = real_frames
    checked = collections.Counter()
    for frame in frames:
        t = int(frame.scene_id.split("/")[1])
        ego = real.tracks[real.sdc_track_index].states[t]
        c, s = np.cos(ego.heading), np.sin(ego.heading)
        for i, track in enumerate(real.tracks):
            state = track.states[t]
            if not state.valid or i == real.sdc_track_index:
                continue
            where = f"{frame.scene_id} track {track.id}"
            dx, dy = state.center_x - ego.center_x, state.center_y - ego.center_y
            row = frame.track_id.tolist().index(str(track.id))
            np.testing.assert_allclose(frame.position[row],
                                       [c * dx + s * dy, -s * dx + c * dy], atol=1e-9,
                                       err_msg=where)
            np.testing.assert_allclose(np.exp(1j * frame.heading[row]),
                                       np.exp(1j * (state.heading - ego.heading)), atol=1e-9,
                                       err_msg=where)
            assert 0 <= frame.heading[row] < 2 * np.pi
            np.testing.assert_allclose(frame.size[row], [state.width, state.length])
            vx, vy = state.velocity_x, state.velocity_y
            np.testing.assert_allclose(frame.velocity[row],
                                       [c * vx + s * vy, -s * vx + c * vy], atol=1e-9,
                                       err_msg=where)
            assert frame.cls[row] == CLASSES[track.object_type], where
            checked[track.object_type] += 1
    assert set(checked) == {1, 2, 3} and sum(checked.values()) > 200, checked


def test_real_map_features_against_protobuf(real, real_path, real_bytes):
    """Feature counts per kind, lane types and links, and road line marks, as protobuf
    decodes them: every lane, line and edge with two distinct points is in the world map."""
    scenario = R.parse_scenario(real_bytes[12:-4], real_path, "x")
    kinds = collections.Counter(_kind(f) for f in real.map_features)
    assert collections.Counter(f.kind for f in scenario.features) == kinds
    assert kinds["lane"] > 100 and kinds["road_line"] and kinds["road_edge"]
    world, drops = S.build_map(scenario.features, real_path)
    assert drops["map:stop_sign"] == kinds["stop_sign"] > 0
    assert drops["map:speed_bump"] == kinds["speed_bump"] > 0

    def distinct(points) -> int:
        xy = np.array([(p.x, p.y) for p in points])
        return 1 + int(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6))

    lanes = [f for f in real.map_features if f.HasField("lane")
             and distinct(f.lane.polyline) >= 2]
    assert [lane.id for lane in world.lanes] == [f.id for f in lanes]
    for lane, f in zip(world.lanes, lanes, strict=True):
        assert lane.successors == tuple(f.lane.exit_lanes)
        assert lane.predecessors == tuple(f.lane.entry_lanes)
        assert lane.lane_type == ("BIKE" if f.lane.type == 3 else "VEHICLE")
    assert any(lane.lane_type == "BIKE" for lane in world.lanes)
    assert any(lane.successors for lane in world.lanes)
    edges = [f for f in real.map_features if f.HasField("road_edge")
             and distinct(f.road_edge.polyline) >= 2]
    typed = [f for f in real.map_features if f.HasField("road_line")
             and distinct(f.road_line.polyline) >= 2 and f.road_line.type in LINE_MARKS]
    marks = collections.Counter(line.mark for line in world.lines)
    assert marks[ROAD_EDGE] == len(edges)
    assert +collections.Counter(
        {m: marks[m] for m in LINE_MARKS.values()}) == collections.Counter(
        LINE_MARKS[f.road_line.type] for f in typed)
    assert len(world.crosswalks) == kinds["crosswalk"] > 0


# ---------------------------------------------------------------- records as units


def _other_scenario(real):
    """The real scenario with another id and its pedestrians typed TYPE_OTHER."""
    other = Scenario()
    other.CopyFrom(real)
    other.scenario_id = "other"
    for track in other.tracks:
        if track.object_type == 2:
            track.object_type = 4
    return other


def test_records_of_one_file_are_units_and_shards(tmp_path, real, real_bytes, real_frames):
    """A file of three records (the real one twice, then one more) is three units, spread
    over `prepare --shard` parts by record."""
    src = tmp_path / "src"
    src.mkdir()
    other = _other_scenario(real)
    path = src / "training.tfrecord-00000-of-00001"
    offsets = _write_records(path, [real_bytes[12:-4]] * 2 + [other.SerializeToString()])
    units = R.scenario_files(src)
    assert units == [f"{path}#{i}@{o}" for i, o in enumerate(offsets)]
    first, _ = R.read_file(units[1], 10)
    assert [f.scene_id for f in first] == [f.scene_id for f in real_frames[0]]
    frames, drops = R.read_file(units[2], 10)
    assert frames[0].scene_id == "other/0"
    assert all(PEDESTRIAN not in f.cls for f in frames)
    steps = range(0, len(real.timestamps_seconds))
    pedestrian_states = sum(t.states[i].valid for t in real.tracks if t.object_type == 2
                            for i in steps)
    assert drops["type:other"] == pedestrian_states > 0
    cfg = get_config("tiny")
    spec = source_spec("womd", str(src), None, 30)
    parts = [prepare(spec, str(tmp_path / "cache"), cfg, workers=1, shard=(i, 2))[0]
             for i in range(2)]
    assert [p.files for p in parts] == [2, 1]
    assert [p.scenes for p in parts] == [8, 4]  # steps 0, 30, 60, 90 of each record
    assert all(p.bad_files == {} for p in parts)


def _damaged_copies(folder, real_bytes) -> dict[str, bytes]:
    """A bit flipped in the data, a file cut inside the data, a bit flipped in the length,
    and three records whose second has a damaged header."""
    flipped = bytearray(real_bytes)
    flipped[len(real_bytes) // 2] ^= 0x10
    header = bytearray(real_bytes)
    header[2] ^= 0x01
    copies = {"flipped.tfrecord": bytes(flipped), "truncated.tfrecord": real_bytes[:500_000],
              "header.tfrecord": bytes(header)}
    for name, data in copies.items():
        (folder / name).write_bytes(data)
    _write_records(folder / "three.tfrecord", [real_bytes[12:-4]] * 3)
    data = bytearray((folder / "three.tfrecord").read_bytes())
    data[len(real_bytes) + 3] ^= 0x01  # the second record's length
    (folder / "three.tfrecord").write_bytes(bytes(data))
    return copies


def test_damaged_records_are_named(tmp_path, real_bytes):
    _damaged_copies(tmp_path, real_bytes)
    cases = {"flipped": "record 0: data CRC mismatch",
             "truncated": r"record 0: the file ends inside the record \(499988 of",
             "header": "record 0: length CRC mismatch"}
    units = R.scenario_files(tmp_path)
    for name, message in cases.items():
        unit = next(u for u in units if f"{name}.tfrecord#" in u)
        with pytest.raises(ValueError, match=f"{name}\\.tfrecord: {message}"):
            R.read_file(unit, 10)
    three = [u for u in units if "three.tfrecord#" in u]
    assert [R.parse_unit(u)[1:] for u in three] == [(0, 0), (1, len(real_bytes))]
    assert R.read_file(three[0], 10)[0]
    with pytest.raises(ValueError, match=r"three\.tfrecord: record 1: length CRC mismatch"):
        R.read_file(three[1], 10)
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "a.tfrecord").write_bytes(real_bytes[:7])  # the file ends inside the header
    (unit,) = R.scenario_files(cut)
    with pytest.raises(ValueError, match=r"a\.tfrecord: record 0: the file ends inside the "
                       r"record header"):
        R.read_file(unit, 10)


def test_a_record_claiming_an_absurd_length_is_refused_before_reading(tmp_path):
    """A header whose CRC holds but whose length is beyond the file (2^62 bytes) is named,
    without asking for that much memory."""
    length = (2**62).to_bytes(8, "little")
    header = length + R.masked_crc32c(length).to_bytes(4, "little")
    (tmp_path / "big.tfrecord").write_bytes(header + b"\0" * 16)
    (unit,) = R.scenario_files(tmp_path)
    with pytest.raises(ValueError, match=r"big\.tfrecord: record 0: the file ends inside the "
                       r"record \(16 of"):
        R.read_file(unit, 10)


def test_prepare_counts_bad_records_and_keeps_good_ones(tmp_path, real_path, real_bytes,
                                                        real_frames):
    src = tmp_path / "src"
    src.mkdir()
    os.symlink(real_path, src / "good.tfrecord")  # read in place, never copied
    _damaged_copies(src, real_bytes)
    cfg = get_config("tiny")
    spec = source_spec("womd", str(src), None, 10)
    summary, _ = prepare(spec, str(tmp_path / "cache"), cfg, workers=1)
    assert summary.files == 6  # good, flipped, truncated, header, three (2 units)
    assert summary.bad_files == {"ValueError": 4}
    bad = sorted(os.path.basename(b["file"]) for b in summary.bad_file_list)
    assert bad == ["flipped.tfrecord#0@0", "header.tfrecord#0@0", f"three.tfrecord#1@"
                   f"{len(real_bytes)}", "truncated.tfrecord#0@0"]
    assert all(": record " in b["error"] for b in summary.bad_file_list)
    assert summary.scenes == 2 * len(real_frames[0])  # good.tfrecord and three's record 0
    with pytest.raises(ValueError, match=r"flipped\.tfrecord: record 0: data CRC mismatch"):
        prepare(spec, str(tmp_path / "strict"), cfg, workers=1, strict=True)


def test_damaged_messages_are_named(tmp_path, real):
    """Records with valid CRCs but unusable contents: errors name the file, record, field."""
    known = Scenario()
    known.CopyFrom(real)
    known.DiscardUnknownFields()  # (dynamic map states): map features are serialized last
    cut = known.SerializeToString()[:-1000]  # the last map feature runs past the end
    no_sdc, wrong_steps = Scenario(), Scenario()
    no_sdc.CopyFrom(real)
    no_sdc.sdc_track_index = len(real.tracks)
    wrong_steps.CopyFrom(real)
    del wrong_steps.tracks[3].states[-1]
    path = tmp_path / "x.tfrecord"
    _write_records(path, [cut, no_sdc.SerializeToString(), wrong_steps.SerializeToString()])
    units = R.scenario_files(tmp_path)
    messages = [r"record 0: Scenario\.map_features\[\d+\]: length \d+ runs past the end",
                r"record 1: sdc_track_index: not a track index: 83 \(of 83 tracks\)",
                r"record 2: tracks\[3\]\.states: expected 91 states"]
    for unit, message in zip(units, messages, strict=True):
        with pytest.raises(ValueError, match=r"x\.tfrecord: " + message):
            R.read_file(unit, 10)


# ---------------------------------------------------------------- one code path with JSON


def _as_gpudrive_json(scenario) -> dict:
    """The scenario as GPUDrive's converter lays it out (G1: `map_element_id` is the lane
    type, the road line type + 5, the road edge type + 14; 17 stop sign, 18 crosswalk, 19
    speed bump, 20 driveway; -10000 at invalid steps)."""
    objects = []
    for track in scenario.tracks:
        states = track.states
        valid = [s.valid for s in states]
        first = next((s for s in states if s.valid), states[0])

        def at(s, x, y, valid):
            return {"x": x, "y": y} if valid else {"x": -10000.0, "y": -10000.0}

        objects.append({
            "position": [at(s, s.center_x, s.center_y, s.valid) for s in states],
            "velocity": [at(s, s.velocity_x, s.velocity_y, s.valid) for s in states],
            "heading": [s.heading if s.valid else -10000.0 for s in states],
            "valid": valid, "width": first.width, "length": first.length,
            "type": TYPE_NAMES[track.object_type], "id": track.id})
    roads = []
    for f in scenario.map_features:
        kind = _kind(f)
        data = getattr(f, kind)
        points = {"lane": "polyline", "road_line": "polyline", "road_edge": "polyline",
                  "crosswalk": "polygon", "driveway": "polygon", "speed_bump": "polygon"}
        element = {"lane": data.type if kind == "lane" else 0,
                   "road_line": data.type + 5 if kind == "road_line" else 0,
                   "road_edge": data.type + 14 if kind == "road_edge" else 0,
                   "stop_sign": 17, "crosswalk": 18, "speed_bump": 19, "driveway": 20}[kind]
        geometry = ([{"x": data.position.x, "y": data.position.y}] if kind == "stop_sign"
                    else [{"x": p.x, "y": p.y} for p in getattr(data, points[kind])])
        roads.append({"geometry": geometry, "type": kind, "map_element_id": element})
    return {"scenario_id": scenario.scenario_id, "objects": objects, "roads": roads,
            "metadata": {"sdc_track_index": scenario.sdc_track_index}}


def _assert_same_frame(a, b, where):
    for field in dataclasses.fields(a):
        if field.name in ("source", "map"):
            continue
        x, y = getattr(a, field.name), getattr(b, field.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f"{where}.{field.name}")
        else:
            assert x == y, (where, field.name)
    for kind in ("crosswalks", "drivable_areas"):
        for p, q in zip(getattr(a.map, kind), getattr(b.map, kind), strict=True):
            np.testing.assert_array_equal(p, q, err_msg=f"{where}.map.{kind}")
    for p, q in zip(a.map.lines, b.map.lines, strict=True):
        assert p.mark == q.mark, where
        np.testing.assert_array_equal(p.points, q.points, err_msg=f"{where}.map.lines")
    for p, q in zip(a.map.lanes, b.map.lanes, strict=True):  # ids: Waymo's / JSON's indices
        assert (p.lane_type, p.is_intersection) == (q.lane_type, q.is_intersection), where
        np.testing.assert_array_equal(p.left, q.left, err_msg=f"{where}.map.lanes")
        np.testing.assert_array_equal(p.right, q.right, err_msg=f"{where}.map.lanes")


def test_same_scene_as_json_gives_the_same_frames(tmp_path, real):
    """The real scenario as a TFRecord and as GPUDrive JSON (boxes held at each track's first
    valid box, as the JSON layout keeps one box per object) read to the same frames and drop
    counts: both readers end in `womd_scene.scenario_frames`."""
    constant = Scenario()
    constant.CopyFrom(real)
    for track in constant.tracks:
        first = next((s for s in track.states if s.valid), track.states[0])
        for s in track.states:
            if s.valid:
                s.width, s.length = first.width, first.length
    _write_records(tmp_path / "s.tfrecord", [constant.SerializeToString()])
    (tmp_path / "s.json").write_text(json.dumps(_as_gpudrive_json(constant)))
    (unit,) = R.scenario_files(tmp_path)
    from_record, record_drops = R.read_file(unit, 10)
    from_json, json_drops = W.read_file(tmp_path / "s.json", 10)
    assert record_drops == json_drops
    assert len(from_record) == len(from_json) >= 9
    for a, b in zip(from_record, from_json, strict=True):
        _assert_same_frame(a, b, a.scene_id)
        assert len(a.map.lanes) == len(b.map.lanes) and len(a.map.lines) == len(b.map.lines)


# ---------------------------------------------------------------- the wire reader


def test_wire_reader_on_hand_written_bytes():
    """Negative int32s (10-byte varints), repeated numbers packed and unpacked alike,
    unknown fields of every wire type skipped, and damage named by its field path."""
    from scenegen_jax.data.protowire import Field, Message, WireError, decode

    inner = Message({1: Field("x", "double")})
    schema = Message({1: Field("n", "int"), 2: Field("ids", "int", repeated=True),
                      3: Field("inner", inner, repeated=True), 4: Field("name", "string")})
    minus_one = b"\x08" + b"\xff" * 9 + b"\x01"
    unpacked = b"\x10\x05\x10\x07"
    packed = b"\x12\x02\x09\x0b"  # 9, 11
    unknown = b"\x28\x01" + b"\x31" + bytes(8) + b"\x3a\x01z" + b"\x45" + bytes(4)
    point = b"\x1a\x09\x09" + struct.pack("<d", 2.5)
    data = minus_one + unpacked + unknown + packed + point + b"\x22\x02hi"
    assert decode(data, schema) == {"n": -1, "ids": [5, 7, 9, 11], "inner": [{"x": 2.5}],
                                    "name": "hi"}
    assert decode(b"", schema) == {"ids": [], "inner": []}
    with pytest.raises(WireError, match=r"^inner\[1\]\.x: truncated double$"):
        decode(point + b"\x1a\x05\x09" + bytes(4), schema)
    with pytest.raises(WireError, match=r"^inner\[0\]: length 9 runs past the end"):
        decode(point[:-1], schema)
    with pytest.raises(WireError, match="truncated varint"):
        decode(b"\x08\xff", schema)
    with pytest.raises(WireError, match=r"<field 6>: unsupported wire type 3"):
        decode(b"\x33", schema)
