"""Waymo Open Motion Dataset Scenario TFRecords -> Frames, without TensorFlow.

A TFRecord file is a sequence of records, each: uint64 length (little-endian), uint32 masked
CRC32C of those 8 bytes, the data, uint32 masked CRC32C of the data. Each record of WOMD's
motion files is one serialized `waymo.open_dataset.Scenario` (`scenario.proto`, `map.proto`
in waymo-research/waymo-open-dataset); the field numbers below are theirs. The messages are
decoded by our own wire-format reader (`protowire`), so neither TensorFlow nor protoc nor
generated classes are needed.

Units of work are records, not files: a unit is the string "<path>#<record index>@<byte
offset>" (`record_unit`), so that `prepare --shard I/N` and its worker pool spread the
dataset's ~500 scenarios per file across shards and processes. `scenario_files` lists them
by reading the record headers only. A damaged header (its length CRC fails) or a file that
ends inside a record still gets a unit, so that reading it fails and `prepare` counts it as
a bad unit; the file's later records cannot be located and are not listed.

After decoding, a scenario becomes a `womd_scene.ParsedScenario` and then frames through
`womd_scene.scenario_frames`, the same code the GPUDrive JSON reader uses: tracks of vehicles,
pedestrians and cyclists (others counted as "type:<name>"), the ego at `sdc_track_index`,
lanes (bike lanes typed BIKE, entry/exit lanes kept as predecessors/successors), road lines
with their Waymo type, road edges, crosswalks, driveways; stop signs and speed bumps are
counted drops, and dynamic map states (traffic lights) are not read. Waymo's boxes are
measured at every step, so each frame takes the box of its step.
"""

from __future__ import annotations

import collections
import functools
import os
import struct
from pathlib import Path

import numpy as np

from scenegen_jax.data.protowire import Field, Message, WireError, decode
from scenegen_jax.data.womd_scene import (
    MARK_FROM_ELEMENT_ID,
    MapFeature,
    ParsedScenario,
    Tracks,
    field_error,
    scenario_frames,
)
from scenegen_jax.files import files_under
from scenegen_jax.frame import Frame

# ---------------------------------------------------------------- CRC32C (Castagnoli)

CRC32C_POLY = 0x82F63B78  # bit-reflected Castagnoli polynomial (RFC 3720)
MASK_DELTA = 0xA282EAD8  # TFRecord's mask: ((crc >> 15) | (crc << 17)) + delta, mod 2^32
CRC_CHUNK = 256  # bytes per lane of the vectorised CRC: the fastest on a 1 MB record


@functools.cache
def _crc_table() -> np.ndarray:
    """uint32 [256]: the register update of one byte, for every byte value."""
    t = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        t = np.where(t & 1, (t >> 1) ^ np.uint32(CRC32C_POLY), t >> 1).astype(np.uint32)
    return t


@functools.cache
def _shift_tables(n: int) -> tuple[list[int], ...]:
    """Four [256] tables whose XOR over a register's bytes is the register after `n` zero
    bytes (the update is linear over GF(2), so it acts on each byte of the register alone)."""
    table = _crc_table()
    shifts = np.arange(4, dtype=np.uint32)[:, None] * np.uint32(8)
    v = (np.arange(256, dtype=np.uint32)[None, :] << shifts).ravel()
    for _ in range(n):
        v = table[v & 0xFF] ^ (v >> 8)
    return tuple(v.reshape(4, 256).tolist())


@functools.cache
def _crc_list() -> list[int]:
    return _crc_table().tolist()  # Python ints: faster than numpy scalars one at a time


def _crc_bytes(crc: int, data: bytes | memoryview) -> int:
    """The register after `data`, one byte at a time (short inputs)."""
    table = _crc_list()
    for byte in data:
        crc = table[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc


def crc32c(data: bytes | memoryview) -> int:
    """CRC32C of `data` (RFC 3720; crc32c(b"123456789") == 0xE3069283).

    Long inputs run in numpy: the data is cut into chunks whose CRCs from a zero register are
    computed side by side, one byte position at a time, and then chained (the register after
    a chunk = the incoming register shifted over the chunk's length XOR the chunk's own).
    """
    data = memoryview(data).cast("B")
    n = len(data) // CRC_CHUNK
    head = len(data) - n * CRC_CHUNK
    crc = _crc_bytes(0xFFFFFFFF, data[:head])
    if n:
        table = _crc_table()
        columns = np.frombuffer(data, np.uint8, offset=head).reshape(n, CRC_CHUNK).T.copy()
        regs = np.zeros(n, np.uint32)
        for column in columns:
            regs = table[(regs ^ column) & 0xFF] ^ (regs >> 8)
        s0, s1, s2, s3 = _shift_tables(CRC_CHUNK)
        for reg in regs.tolist():
            crc = s0[crc & 0xFF] ^ s1[(crc >> 8) & 0xFF] ^ s2[(crc >> 16) & 0xFF] ^ s3[crc >> 24]
            crc ^= reg
    return crc ^ 0xFFFFFFFF


def masked_crc32c(data: bytes | memoryview) -> int:
    """The CRC as TFRecord stores it (masked, so that CRCs of CRCs do not look alike)."""
    crc = crc32c(data)
    return ((((crc >> 15) | (crc << 17)) & 0xFFFFFFFF) + MASK_DELTA) & 0xFFFFFFFF


# ---------------------------------------------------------------- records and units

HEADER = struct.Struct("<QI")  # length, masked CRC32C of the length's 8 bytes
FOOTER = struct.Struct("<I")  # masked CRC32C of the data


def record_unit(path: str | os.PathLike, index: int, offset: int) -> str:
    """The unit of work of record `index` (0-based), whose header starts at byte `offset`."""
    return f"{os.fspath(path)}#{index}@{offset}"


def parse_unit(unit: str) -> tuple[str, int, int]:
    """(path, record index, byte offset) of a `record_unit` string."""
    path, _, where = str(unit).rpartition("#")
    index, _, offset = where.partition("@")
    if not (path and index.isdigit() and offset.isdigit()):
        raise ValueError(f"{unit}: not a TFRecord unit (<path>#<record index>@<byte offset>)")
    return path, int(index), int(offset)


def _header_ok(header: bytes) -> bool:
    return masked_crc32c(header[:8]) == HEADER.unpack(header)[1]


def record_offsets(path: str | os.PathLike) -> list[int]:
    """Byte offsets of the records of a TFRecord file, from their headers alone (the data
    is skipped). A damaged header, or a record the file ends inside, is the last offset."""
    offsets: list[int] = []
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        offset = 0
        while offset < size:
            offsets.append(offset)
            f.seek(offset)
            header = f.read(HEADER.size)
            if len(header) < HEADER.size or not _header_ok(header):
                break
            offset += HEADER.size + HEADER.unpack(header)[0] + FOOTER.size
    return offsets


def read_record(path: str, index: int, offset: int) -> bytes:
    """The data of one record, its length and data CRCs checked.

    Raises:
      ValueError("<path>: record <index>: ...") when the record is damaged or cut short.
    """
    where = f"{path}: record {index}"
    with open(path, "rb") as f:
        f.seek(offset)
        header = f.read(HEADER.size)
        if len(header) < HEADER.size:
            raise ValueError(f"{where}: the file ends inside the record header (byte {offset})")
        if not _header_ok(header):
            raise ValueError(f"{where}: length CRC mismatch: damaged header at byte {offset}")
        length = HEADER.unpack(header)[0]
        left = os.fstat(f.fileno()).st_size - offset - HEADER.size
        if length + FOOTER.size > left:  # checked before reading: a length may be absurd
            raise ValueError(f"{where}: the file ends inside the record ({left} of "
                             f"{length + FOOTER.size} bytes of data and CRC)")
        body = f.read(length + FOOTER.size)
    data = memoryview(body)[:length]
    if masked_crc32c(data) != FOOTER.unpack_from(body, length)[0]:
        raise ValueError(f"{where}: data CRC mismatch: damaged record")
    return bytes(data)


def scenario_files(root: str | os.PathLike) -> list[str]:
    """The records of the TFRecord files (names holding ".tfrecord") under `root`, as
    `record_unit` strings in file and record order."""
    files = files_under(root, ".tfrecord", infix=True)
    if not files:
        raise FileNotFoundError(f"{root}: no Waymo Scenario TFRecord files (*.tfrecord*)")
    return [record_unit(p, i, o) for p in files for i, o in enumerate(record_offsets(p))]


# ---------------------------------------------------------------- the Scenario schema

# map.proto: MapPoint; only x and y are read.
POINT = Message({1: Field("x", "double"), 2: Field("y", "double")})
EMPTY = Message({})  # a message whose fields are not read (stop signs, speed bumps: counted)
# scenario.proto: ObjectState, Track.
STATE = Message({
    2: Field("center_x", "double"),
    3: Field("center_y", "double"),
    5: Field("length", "float"),
    6: Field("width", "float"),
    8: Field("heading", "float"),
    9: Field("velocity_x", "float"),
    10: Field("velocity_y", "float"),
    11: Field("valid", "bool"),
})
TRACK = Message({1: Field("id", "int"), 2: Field("object_type", "int"),
                 3: Field("states", STATE, repeated=True)})
# map.proto: LaneCenter, RoadLine / RoadEdge, Crosswalk / Driveway, MapFeature.
LANE = Message({
    2: Field("type", "int"),
    8: Field("polyline", POINT, repeated=True),
    9: Field("entry_lanes", "int", repeated=True),
    10: Field("exit_lanes", "int", repeated=True),
})
TYPED_POLYLINE = Message({1: Field("type", "int"), 2: Field("polyline", POINT, repeated=True)})
POLYGON = Message({1: Field("polygon", POINT, repeated=True)})
MAP_FEATURE = Message({
    1: Field("id", "int"),
    3: Field("lane", LANE),
    4: Field("road_line", TYPED_POLYLINE),
    5: Field("road_edge", TYPED_POLYLINE),
    7: Field("stop_sign", EMPTY),
    8: Field("crosswalk", POLYGON),
    9: Field("speed_bump", EMPTY),
    10: Field("driveway", POLYGON),
})
SCENARIO = Message({
    1: Field("timestamps_seconds", "double", repeated=True),
    2: Field("tracks", TRACK, repeated=True),
    5: Field("scenario_id", "string"),
    6: Field("sdc_track_index", "int"),
    8: Field("map_features", MAP_FEATURE, repeated=True),
})

# Track.ObjectType -> the JSON readers' type names (`womd_scene.CLASS_FROM_TYPE`).
TYPE_FROM_OBJECT_TYPE = {0: "unset", 1: "vehicle", 2: "pedestrian", 3: "cyclist", 4: "other"}
# RoadLine.RoadLineType 1..8 (BROKEN_SINGLE_WHITE .. PASSING_DOUBLE_YELLOW) are GPUDrive's
# `map_element_id`s 6..13; 0 (TYPE_UNKNOWN) has no mark and is inferred from the lanes.
MARK_FROM_LINE_TYPE = {element - 5: mark for element, mark in MARK_FROM_ELEMENT_ID.items()}
BIKE_LANE_TYPE = 3  # LaneCenter.LaneType TYPE_BIKE_LANE (1 freeway, 2 surface street: VEHICLE)
FEATURE_KINDS = ("lane", "road_line", "road_edge", "crosswalk", "driveway", "stop_sign",
                 "speed_bump")
_STATE_FIELDS = ("center_x", "center_y", "velocity_x", "velocity_y", "heading", "width",
                 "length")

# ---------------------------------------------------------------- Scenario -> frames


def _states(states: list[dict], n_steps: int, source: str, field: str) -> dict[str, np.ndarray]:
    """Per-step arrays of one track's states. A field a valid state lacks reads as NaN, so
    that the row is counted as invalid (or the ego named), never placed at the origin."""
    if len(states) != n_steps:
        raise field_error(source, f"{field}.states", f"expected {n_steps} states (one per "
                   f"timestamps_seconds entry), got {len(states)}")
    out = {name: np.array([s.get(name, np.nan) for s in states], np.float64).reshape(n_steps)
           for name in _STATE_FIELDS}
    out["valid"] = np.array([s.get("valid", False) for s in states], bool).reshape(n_steps)
    return out


def read_tracks(tracks: list[dict], n_steps: int, source: str
                ) -> tuple[Tracks, list[int], collections.Counter]:
    """The tracks of the modelled classes, the index of each kept one among all tracks, and
    the valid states of the others by "type:<name>"."""
    dropped: collections.Counter = collections.Counter()
    kept, index, arrays = [], [], collections.defaultdict(list)
    for i, track in enumerate(tracks):
        field = f"tracks[{i}]"
        states = _states(track["states"], n_steps, source, field)
        code = track.get("object_type", 0)
        name = TYPE_FROM_OBJECT_TYPE.get(code, str(code))
        if name not in ("vehicle", "pedestrian", "cyclist"):
            dropped[f"type:{name}"] += int(states["valid"].sum())
            continue
        kept.append((name, str(track.get("id", i))))
        index.append(i)
        for key, value in states.items():
            arrays[key].append(value)
    if not kept:
        raise field_error(source, "tracks", "no vehicle, pedestrian or cyclist")
    a = {k: np.stack(v) for k, v in arrays.items()}
    out = Tracks(
        type=[t for t, _ in kept],
        position=np.stack([a["center_x"], a["center_y"]], -1),
        velocity=np.stack([a["velocity_x"], a["velocity_y"]], -1),
        heading=a["heading"],
        valid=a["valid"],
        size=np.stack([a["width"], a["length"]], -1),
        ids=[i for _, i in kept],
    )
    return out, index, dropped


def _sdc(msg: dict, tracks: Tracks, kept_index: list[int], source: str) -> int:
    """Index into the kept tracks of the ego (`sdc_track_index` indexes all tracks)."""
    index = msg.get("sdc_track_index")
    if index is None:
        raise field_error(source, "sdc_track_index", "missing")
    if index not in kept_index:
        n = len(msg["tracks"])
        what = "not a track index" if not 0 <= index < n else "not a vehicle track"
        raise field_error(source, "sdc_track_index", f"{what}: {index} (of {n} tracks)")
    sdc = kept_index.index(index)
    if tracks.type[sdc] != "vehicle":
        raise field_error(source, "sdc_track_index",
                          f"the SDC is a {tracks.type[sdc]}, not a vehicle")
    return sdc


def _points(points: list[dict]) -> np.ndarray:
    """[P, 2] world m; a coordinate a point lacks is NaN (named by `build_map`)."""
    xy = [(p.get("x", np.nan), p.get("y", np.nan)) for p in points]
    return np.array(xy, np.float64).reshape(len(xy), 2)


def _feature(kind: str, data: dict, feature: dict, field: str) -> MapFeature:
    """One map feature of a known kind as a MapFeature."""
    if kind == "lane":
        return MapFeature(
            kind, f"{field}.lane.polyline", _points(data["polyline"]),
            lane_type="BIKE" if data.get("type") == BIKE_LANE_TYPE else "VEHICLE",
            lane_id=feature.get("id"), successors=tuple(data["exit_lanes"]),
            predecessors=tuple(data["entry_lanes"]))
    if kind == "road_line":
        return MapFeature(kind, f"{field}.road_line.polyline", _points(data["polyline"]),
                          mark=MARK_FROM_LINE_TYPE.get(data.get("type", 0)))
    if kind == "road_edge":
        return MapFeature(kind, f"{field}.road_edge.polyline", _points(data["polyline"]))
    if kind in ("crosswalk", "driveway"):
        return MapFeature(kind, f"{field}.{kind}.polygon", _points(data["polygon"]))
    return MapFeature(kind, f"{field}.{kind}")  # stop signs, speed bumps: counted


def map_features(features: list[dict]) -> tuple[list[MapFeature], collections.Counter]:
    """The map features, and the count of those with no feature data we know
    ("map:unknown_feature": a newer dataset version's kinds)."""
    out, dropped = [], collections.Counter()
    for i, feature in enumerate(features):
        kind = next((k for k in FEATURE_KINDS if k in feature), None)
        if kind is None:
            dropped["map:unknown_feature"] += 1
            continue
        out.append(_feature(kind, feature[kind], feature, f"map_features[{i}]"))
    return out, dropped


def parse_scenario(data: bytes, source: str, default_id: str) -> ParsedScenario:
    """The tracks, ego and map features of a serialized Scenario."""
    try:
        msg = decode(data, SCENARIO)
    except WireError as e:
        field = f"Scenario.{e.field}" if e.field else "Scenario"
        raise field_error(source, field, e.message) from None
    n_steps = len(msg["timestamps_seconds"])
    if n_steps == 0:
        raise field_error(source, "timestamps_seconds", "empty")
    tracks, kept_index, dropped = read_tracks(msg["tracks"], n_steps, source)
    sdc = _sdc(msg, tracks, kept_index, source)
    features, map_dropped = map_features(msg["map_features"])
    scenario_id = msg.get("scenario_id") or default_id
    return ParsedScenario(scenario_id, tracks, sdc, features, dropped + map_dropped,
                          tracks_field="tracks")


def read_file(unit: str, stride: int) -> tuple[list[Frame], collections.Counter]:
    """Frames and drop counts of one record (`record_unit`); errors name the file, the record
    and the field ("<path>: record <i>: tracks[3].states: ...")."""
    path, index, offset = parse_unit(unit)
    data = read_record(path, index, offset)
    source = f"{path}: record {index}"
    scenario = parse_scenario(data, source, default_id=f"{Path(path).name}_{index}")
    return scenario_frames(scenario, source, stride)
