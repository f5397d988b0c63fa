"""Argoverse 2 Motion Forecasting scenarios, as published, -> Frames in the ego frame.

Layout: `<split>/<scenario_id>/scenario_<scenario_id>.parquet` (one row per track and 10 Hz
timestep, 0..109: 11 s; positions m, heading rad and velocity m/s in the city frame) beside
`log_map_archive_<scenario_id>.json` (the sensor logs' map schema, city frame). Two releases
of the parquet schema exist; the older adds `map_id` and `slice_id`, which are not read.

- The ego is the track `AV` (the recording vehicle): each frame's ego is its row at the
  frame's step. A step without a usable `AV` row (none, or NaN/inf in it) is not a frame and
  is counted ("frame:no_ego", "frame:invalid_ego").
- Frames at steps 0, stride, 2 stride, ... Each other row at a frame's step is an actor of
  the frame or a counted drop: "type:<object_type>" (riderless bicycles, static objects,
  background, construction, unknown: no modelled class), "invalid:nan" (NaN/inf position,
  heading or velocity), "invalid:duplicate_row" (a track's second row at a step; the first
  is kept).
- `observed` is not a validity mask. In the av2-api (`data_schema.ObjectState`) a row exists
  only where the track was observed at all, and `observed` marks whether the step lies in
  the scenario's history (the first 5 s) rather than in the future that the forecasting
  challenge asks for. In train and val every row, future or not, is a real observation, so
  every row is read and `observed` is ignored; a test-split file has no future rows, so its
  frames after the history lack the `AV` row and are counted as "frame:no_ego".
- No box sizes: the dataset has none. Every actor is marked `size_measured = False` and
  carries a per-type placeholder (`PLACEHOLDER_SIZE_M`) only to draw it; the ego has the
  sensor fleet's `av2.AV2_EGO_SIZE` (the same vehicles recorded both datasets).
- The map: `av2_map.read_map_file`, the sensor-log reader's code path, cropped to
  `MAP_RADIUS_M` around the ego and moved into its frame.
"""

from __future__ import annotations

import collections
import glob
import logging
import os

import numpy as np

from scenegen_jax.data.av2 import AV2_EGO_SIZE
from scenegen_jax.data.av2_map import read_map_file
from scenegen_jax.files import files_under
from scenegen_jax.frame import Frame, future_positions
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE, wrap_angle
from scenegen_jax.vector_map import VectorMap, rotation_matrix, se2_pose

log = logging.getLogger(__name__)

EGO_TRACK_ID = "AV"
NUM_STEPS = 110  # 11 s at 10 Hz: timesteps 0..109
STEP_S = 0.1
MAP_RADIUS_M = 80.0
COLUMNS = ("track_id", "object_type", "timestep", "position_x", "position_y", "heading",
           "velocity_x", "velocity_y")
# Fields that are not numbers (m, rad, m/s), by the kind they must hold.
FIELD_KINDS = {"track_id": "string", "object_type": "string", "timestep": "integer"}
CLASS_FROM_TYPE = {
    "vehicle": VEHICLE,
    "bus": VEHICLE,
    "pedestrian": PEDESTRIAN,
    "cyclist": BICYCLIST,
    "motorcyclist": BICYCLIST,
}
# Argoverse 2's other object types (its `ObjectType`): dropped and counted by name; a type
# outside both lists is dropped, counted and logged.
DROPPED_TYPES = ("riderless_bicycle", "static", "background", "construction", "unknown")
# PLACEHOLDERS, never learnt nor scored (the actors are marked unmeasured): (width, length) m
# to draw an actor, the median box of its category among the Argoverse 2 sensor-log
# annotations (`av2_sensor_mini`: REGULAR_VEHICLE, BUS, PEDESTRIAN, BICYCLE, MOTORCYCLE).
PLACEHOLDER_SIZE_M = {
    "vehicle": (1.89, 4.17),
    "bus": (2.94, 11.58),
    "pedestrian": (0.72, 0.67),
    "cyclist": (0.55, 1.62),
    "motorcyclist": (0.59, 1.80),
}


def scenario_files(root: str | os.PathLike) -> list[str]:
    """Sorted scenario directories under `root`: the folders of `scenario_*.parquet` files
    (`files.files_under`: recursive, links followed, each file once)."""
    folders = {
        str(p.parent) for p in files_under(root, ".parquet") if p.name.startswith("scenario_")
    }
    if not folders:
        raise FileNotFoundError(
            f"{root}: no Argoverse 2 forecasting scenarios (<id>/scenario_<id>.parquet)"
        )
    return sorted(folders)


def scenario_paths(path: str) -> tuple[str, str, str]:
    """(scenario id, parquet file, map JSON file) of a scenario directory (or its parquet)."""
    folder = os.path.dirname(path) if path.endswith(".parquet") else path
    found = sorted(glob.glob(os.path.join(glob.escape(folder), "scenario_*.parquet")))
    if not found:
        raise FileNotFoundError(f"{folder}: no scenario_*.parquet file")
    if len(found) > 1:
        raise ValueError(f"{folder}: {len(found)} scenario_*.parquet files, expected one")
    scenario_id = os.path.basename(found[0])[len("scenario_") : -len(".parquet")]
    map_path = os.path.join(folder, f"log_map_archive_{scenario_id}.json")
    if not os.path.isfile(map_path):
        raise FileNotFoundError(f"{map_path}: map file not found")
    return scenario_id, found[0], map_path


def _kind_ok(arrow_type, kind: str) -> bool:
    import pyarrow as pa

    if kind == "string":
        return pa.types.is_string(arrow_type) or pa.types.is_large_string(arrow_type)
    if kind == "integer":
        return pa.types.is_integer(arrow_type)
    return pa.types.is_integer(arrow_type) or pa.types.is_floating(arrow_type)


def _column(column, name: str, path: str) -> np.ndarray:
    """[R] numpy values of one pyarrow column: float64 numbers (nulls as NaN), int64
    timesteps or strings; ValueError naming the file and field for the wrong kind or a null
    id or timestep."""
    import pyarrow as pa

    kind = FIELD_KINDS.get(name, "number")
    if pa.types.is_dictionary(column.type):
        column = column.cast(column.type.value_type)
    if not _kind_ok(column.type, kind) and len(column):  # an empty column may have any type
        raise ValueError(f"{path}: field {name}: expected {kind} values, got {column.type}")
    if kind != "number" and column.null_count:
        raise ValueError(f"{path}: field {name}: {column.null_count} missing values")
    values = column.to_numpy(zero_copy_only=False)
    if kind == "string":
        return values
    return values.astype(np.int64 if kind == "integer" else np.float64)


def read_columns(path: str) -> dict[str, np.ndarray]:
    """The `COLUMNS` of a scenario parquet file as numpy arrays [R].

    Strings and timesteps must have no nulls; a null number reads as NaN (the row becomes a
    counted drop). A missing field, a field of the wrong type or a damaged file raises
    ValueError naming the file and the field, never a pyarrow error.
    """
    import pyarrow.parquet as pq

    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: file not found")
    try:
        with open(path, "rb") as f:  # Python opens it: pyarrow refuses non-UTF-8 path bytes
            parquet = pq.ParquetFile(f)
            present = [c for c in COLUMNS if c in parquet.schema_arrow.names]
            table = parquet.read(columns=present)
        table.validate(full=True)  # offsets and UTF-8: a damaged buffer is caught here
    except Exception as e:  # pyarrow raises several types for corrupt files
        raise ValueError(f"{path}: not a readable parquet file ({e})") from e
    missing = [c for c in COLUMNS if c not in present]
    if missing:
        raise ValueError(f"{path}: missing field(s) {missing}")
    out = {name: _column(table.column(name), name, path) for name in COLUMNS}
    steps = out["timestep"]
    if len(steps) and not (steps.min() >= 0 and steps.max() < NUM_STEPS):
        raise ValueError(f"{path}: field timestep: values {steps.min()}..{steps.max()} outside "
                         f"0..{NUM_STEPS - 1}")
    return out


def _finite(table: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
    """bool [n]: the rows' position, heading and velocity are finite."""
    names = ("position_x", "position_y", "heading", "velocity_x", "velocity_y")
    return np.all([np.isfinite(table[n][rows]) for n in names], axis=0)


def _first_of_track(track: np.ndarray) -> np.ndarray:
    """bool [n]: each row is the first (in file order) of its track."""
    first = np.zeros(len(track), bool)
    first[np.unique(track.astype(str), return_index=True)[1]] = True
    return first


def _count(drops: collections.Counter, reason: str, n: int) -> None:
    if n:
        drops[reason] += n


def actor_rows(table: dict[str, np.ndarray], step: int,
               drops: collections.Counter) -> np.ndarray:
    """Rows [n] of the actors at `step` (every track but the ego); the other rows at the
    step are counted into `drops` by reason (see the module docstring)."""
    track, types = table["track_id"], table["object_type"]
    rows = np.flatnonzero((table["timestep"] == step) & (track != EGO_TRACK_ID))
    modelled = np.array([t in CLASS_FROM_TYPE for t in types[rows]], bool)
    for name, n in collections.Counter(types[rows[~modelled]]).items():
        drops[f"type:{name}"] += n
    rows = rows[modelled]
    finite = _finite(table, rows)
    _count(drops, "invalid:nan", int(np.sum(~finite)))
    rows = rows[finite]
    first = _first_of_track(track[rows])
    _count(drops, "invalid:duplicate_row", int(np.sum(~first)))
    return rows[first]


def ego_row(table: dict[str, np.ndarray], step: int) -> int | None:
    """The row of the `AV` track at `step` (its first, in file order), or None."""
    rows = np.flatnonzero((table["timestep"] == step) & (table["track_id"] == EGO_TRACK_ID))
    return int(rows[0]) if len(rows) else None


def track_positions(table: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(track ids [K] sorted, city positions [K, NUM_STEPS, 2] m, observed [K, NUM_STEPS])
    of a scenario's rows: each track's first row (in file order) at each step; NaN and not
    observed where it has none."""
    track = table["track_id"].astype(str)
    ids, k = np.unique(track, return_inverse=True)
    step = table["timestep"].astype(np.int64)
    first = np.unique(k * NUM_STEPS + step, return_index=True)[1]
    xy = np.full((len(ids), NUM_STEPS, 2), np.nan)
    xy[k[first], step[first]] = np.stack(
        [table["position_x"][first], table["position_y"][first]], -1)
    return ids, xy, np.isfinite(xy).all(-1)


def frame_at(table: dict[str, np.ndarray], ego: int, rows: np.ndarray, city_map: VectorMap,
             scene_id: str, source: str, tracks: tuple | None = None) -> Frame:
    """The Frame of actor rows [n] seen from the ego row `ego`, all in the ego's frame; its
    actors' futures from `tracks` (`track_positions` of the table; computed when None)."""
    p0 = np.array([table["position_x"][ego], table["position_y"][ego]])
    h0 = float(table["heading"][ego])
    ego_from_city = rotation_matrix(-h0)
    position = np.stack([table["position_x"][rows], table["position_y"][rows]], -1)
    velocity = np.stack([table["velocity_x"][rows], table["velocity_y"][rows]], -1)
    ego_v = np.array([table["velocity_x"][ego], table["velocity_y"][ego]])
    types = table["object_type"][rows]
    local_map = city_map.crop(p0, MAP_RADIUS_M)
    ids, track_xy, observed = track_positions(table) if tracks is None else tracks
    k = np.searchsorted(ids, table["track_id"][rows].astype(str))
    pose = se2_pose(p0[0], p0[1], h0)
    step = int(table["timestep"][ego])
    future = future_positions(track_xy[k], observed[k], np.arange(NUM_STEPS) * STEP_S, step,
                              pose)
    return Frame(
        scene_id=scene_id,
        source=source,
        cls=np.array([CLASS_FROM_TYPE[t] for t in types], np.int32),
        position=(position - p0) @ ego_from_city.T,
        size=np.array([PLACEHOLDER_SIZE_M[t] for t in types], np.float64).reshape(-1, 2),
        heading=wrap_angle(table["heading"][rows] - h0),
        velocity=velocity @ ego_from_city.T,
        track_id=np.asarray(table["track_id"][rows], dtype=str),
        ego_velocity=ego_from_city @ ego_v,
        ego_size=np.asarray(AV2_EGO_SIZE, np.float64),
        map=local_map.transform(ego_from_city, -ego_from_city @ p0),
        city_from_ego=pose,
        size_measured=np.zeros(len(rows), bool),
        future=future,
    )


def frames_from_table(table: dict[str, np.ndarray], city_map: VectorMap, scenario_id: str,
                      source: str, stride: int) -> tuple[list[Frame], collections.Counter]:
    """Frames at steps 0, stride, ... of a scenario's rows (`read_columns`) and its map in the
    city frame, and the counted drops. No usable `AV` row at any of them raises ValueError
    naming the file and field."""
    drops: collections.Counter = collections.Counter()
    frames = []
    tracks = track_positions(table)
    for step in range(0, NUM_STEPS, stride):
        ego = ego_row(table, step)
        if ego is None:
            drops["frame:no_ego"] += 1
            continue
        if not _finite(table, np.array([ego]))[0]:
            drops["frame:invalid_ego"] += 1
            continue
        rows = actor_rows(table, step, drops)
        frames.append(frame_at(table, ego, rows, city_map, f"{scenario_id}/{step}", source,
                               tracks))
    if not frames:
        raise ValueError(f"{source}: field track_id: no finite row of the track "
                         f"{EGO_TRACK_ID!r} at steps 0, {stride}, ... of {NUM_STEPS}")
    return frames, drops


def _log_drops(source: str, drops: collections.Counter) -> None:
    unknown = [k for k in drops if k.startswith("type:") and k[5:] not in DROPPED_TYPES]
    for reason in unknown:
        log.warning("%s: unknown object type %r in %d rows, dropped", source, reason[5:],
                    drops[reason])
    for reason in ("invalid:nan", "invalid:duplicate_row", "frame:invalid_ego"):
        if drops[reason]:
            log.warning("%s: %d dropped (%s)", source, drops[reason], reason)


def read_file(path: str | os.PathLike, stride: int) -> tuple[list[Frame], collections.Counter]:
    """Frames and drop counts (rows at the frames' steps, frames, map elements) of one
    scenario directory; errors name the file and field."""
    scenario_id, parquet_path, map_path = scenario_paths(str(path))
    table = read_columns(parquet_path)
    city_map, map_drops = read_map_file(map_path)
    frames, drops = frames_from_table(table, city_map, scenario_id, parquet_path, stride)
    drops = +drops
    _log_drops(parquet_path, drops)
    return frames, drops + map_drops
