"""ScenarioNet / MetaDrive scenario import and export.

A ScenarioNet scenario is a dict with the top-level keys `id`, `version`, `length`, `tracks`,
`map_features`, `metadata` and `dynamic_map_states`, pickled one per file. Coordinates are a
right-handed world frame in metres (x, y, z), headings rad, velocities m/s in that frame.

Import (`frames_from_scenario`, `read_scenarionet`) builds one `Frame` per requested step in
the SDC's ego frame. It accepts what ScenarioNet's converters (Waymo, nuScenes, nuPlan,
Argoverse 2, in their current and older versions) and MetaDrive's older Waymo pickles write,
not only our own exports; every difference is detected from the data:

- per-step arrays stored as [T] or [T, 1] (nuScenes and nuPlan write `length`, `width`,
  `height` as [T, 1]; MetaDrive's old Waymo pickles `heading` and `valid` as [T, 1]);
- box sizes as `length` / `width` or as `size` [T, 3] = (length, width, height);
- `valid` as bool or as 0/1 floats;
- the SDC as `metadata.sdc_id`, else a `sdc_track_index` (top level or in `metadata`) that
  is a track id (int or str) or, failing that, an index into `tracks`;
- time stamps in `metadata.ts` or a top-level `ts` (`scenario_sample_rate_hz`);
- no `metadata` and no `length` at all (old MetaDrive Waymo pickles).

Track types VEHICLE / PEDESTRIAN / CYCLIST map to our classes; every other type (OTHER,
TRAFFIC_CONE, TRAFFIC_BARRIER, UNSET, ...) is dropped and counted in a `Counter` (key:
"type:<TYPE>"), as are actors with NaN/inf in a valid step ("invalid:nan") and vehicles or
cyclists with a non-positive box size ("invalid:size"). Converter quirks are detected and
counted ("quirk:<name>"), never trusted blindly; see `frames_from_scenario`. Map features the
VectorMap cannot hold are counted as "map:<TYPE>". Nothing is dropped silently; structural
problems (missing tracks or SDC, wrong shapes, NaN in the SDC or in map geometry) raise
ValueError naming the file and the field.

Export (`scenario_from_frame`, `write_scenario`, `write_dataset`, `index_dataset`, in
`scenarionet_export`)
writes a one-step scenario in the ego frame, with `scenegen_*` extras that take precedence on
import, so export -> import is lossless up to float32 rounding of tracks. Files from real
converters carry only the standard keys; their maps are read as described in
`map_from_features`.

This module is the reading entry point: frames of a scenario, scenario files, a dataset
directory. It re-exports the public names of its siblings, which import one another one way:
  scenarionet_schema   file names, key and type tables, checked field readers
  scenarionet_map      map_features -> VectorMap (`map_from_features`)
  scenarionet_tracks   tracks, the SDC, time stamps, steps, `velocity_mismatch`
  scenarionet_export   Frame -> scenario dicts and files
  scenarionet          (this module) scenario -> Frames, and the readers of files
"""

from __future__ import annotations

import collections
import os
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from scenegen_jax.data.safe_pickle import load_pickle
from scenegen_jax.data.scenarionet_export import (
    index_dataset,
    map_features_from_vector_map,
    scenario_file_name,
    scenario_from_frame,
    write_dataset,
    write_scenario,
)
from scenegen_jax.data.scenarionet_map import (
    CROSSWALK_FEATURE_TYPES,
    DEFAULT_HALF_WIDTH_M,
    DRIVABLE_OUTLINE_ID_PREFIX,
    DRIVEWAY_FEATURE_TYPES,
    LANE_FEATURE_TYPES,
    MAX_GIVEN_HALF_WIDTH_M,
    MIN_GIVEN_HALF_WIDTH_M,
    ROAD_EDGE_FEATURE_TYPES,
    map_from_features,
)
from scenegen_jax.data.scenarionet_schema import (
    CLASS_FROM_TYPE,
    LINE_TYPE_FROM_MARK,
    MAPPING_FILE,
    MARK_FROM_LINE_TYPE,
    OWN_DATASET,
    SUMMARY_FILE,
    TOP_LEVEL_KEYS,
    TYPE_FROM_CLASS,
    _err,
    _get,
    _int,
)
from scenegen_jax.data.scenarionet_tracks import (
    DEFAULT_STEP_S,
    MIN_MOVING_SAMPLES,
    MOVING_MPS,
    VELOCITY_MISMATCH_REL_ERR,
    _find_sdc,
    _finite_at,
    _read_track,
    _step_times,
    _steps,
    scenario_sample_rate_hz,
    velocity_mismatch,
)
from scenegen_jax.files import files_under
from scenegen_jax.frame import Frame, drop_beyond_limits, future_positions
from scenegen_jax.scene import PEDESTRIAN, VEHICLE, wrap_angle
from scenegen_jax.vector_map import rotation_matrix, se2_pose

__all__ = [
    "CLASS_FROM_TYPE",
    "CROSSWALK_FEATURE_TYPES",
    "DEFAULT_HALF_WIDTH_M",
    "DEFAULT_STEP_S",
    "DRIVABLE_OUTLINE_ID_PREFIX",
    "DRIVEWAY_FEATURE_TYPES",
    "LANE_FEATURE_TYPES",
    "LINE_TYPE_FROM_MARK",
    "MAPPING_FILE",
    "MARK_FROM_LINE_TYPE",
    "MAX_GIVEN_HALF_WIDTH_M",
    "MIN_GIVEN_HALF_WIDTH_M",
    "MIN_MOVING_SAMPLES",
    "MOVING_MPS",
    "ROAD_EDGE_FEATURE_TYPES",
    "SUMMARY_FILE",
    "TOP_LEVEL_KEYS",
    "TYPE_FROM_CLASS",
    "VELOCITY_MISMATCH_REL_ERR",
    "ImportedFrame",
    "frames_from_scenario",
    "index_dataset",
    "map_features_from_vector_map",
    "map_from_features",
    "read_scenario",
    "read_scenarionet",
    "scenario_file_name",
    "scenario_files",
    "scenario_from_frame",
    "scenario_sample_rate_hz",
    "velocity_mismatch",
    "write_dataset",
    "write_scenario",
]


class ImportedFrame(NamedTuple):
    """One imported frame and what was dropped from it, or found odd in it: a Counter of
    "type:<TYPE>", "invalid:<why>", "map:<TYPE>" and "quirk:<name>" keys (see
    `frames_from_scenario`)."""

    frame: Frame
    dropped: collections.Counter


def frames_from_scenario(
    scenario: Mapping,
    source: str,
    time_index: int | Sequence[int] | None = None,
    *,
    all_steps: bool = False,
    stride: int | None = None,
    map_radius_m: float | None = None,
) -> list[ImportedFrame]:
    """Frames (in the SDC's ego frame) of a ScenarioNet scenario, with per-frame drop counts.

    Args:
      scenario: the scenario dict (as loaded from a ScenarioNet pickle).
      source: file it came from, used in error messages and as `Frame.source`.
      time_index: step(s) to import; default `metadata["current_time_index"]` (0 if absent).
      all_steps: import every step at which the SDC is valid (overrides `time_index`).
      stride: import steps 0, stride, 2 * stride, ... at which the SDC is valid (not together
        with `time_index` or `all_steps`).
      map_radius_m: if given, keep only map elements within this box radius (m) of the ego.

    Returns:
      One ImportedFrame(frame, dropped) per step. Every track valid at a frame's step (other
      than the SDC) is an actor of the frame or counted in `dropped`:
      - "type:<TYPE>": a type with no class (OTHER, TRAFFIC_CONE, TRAFFIC_BARRIER, ...);
      - "invalid:nan": NaN/inf in the step's position, heading, velocity or box size;
      - "invalid:size": a vehicle or cyclist box with a non-positive length or width.
      With `stride`, the steps at which the SDC is not valid give no frame, counted as
      "frame:no_ego" in the first frame. Counted but kept:
      - "quirk:length_lt_width": a vehicle or cyclist box (the SDC's included) whose length is
        shorter than its width. Boxes have no preferred axis other than the heading's, and
        converters do write swapped sizes (nuScenes' early converter for every box but the
        ego's, its current one for the ego's); the box is kept with its two sides sorted so
        that length >= width and its heading unchanged.
      - "quirk:velocity_mismatch": the file's velocities (which are used) disagree with its
        positions (`velocity_mismatch`); counted once per file, in the first frame.
      - "quirk:constant_boxes": every vehicle of the file has one box size
        (`constant_boxes`), a converter's constant rather than a measurement: every actor's
        `size_measured` is False; counted once per file, in the first frame.
      Map features the VectorMap cannot hold ("map:<TYPE>", see `map_from_features`) are
      counted once per file, in the first frame.

    Raises:
      ValueError naming `source` and the field for missing keys (tracks, the SDC, map
      features), bad shapes, an SDC that is a pedestrian or cyclist, or is invalid,
      non-finite or without a positive box size at a requested step, with `stride` an SDC
      valid at none of the stride's steps, or NaN/inf map geometry.
    """
    meta, tracks = _scenario_tracks(scenario, source)
    sdc_id = _find_sdc(scenario, meta, tracks, source)
    sdc_field = f"tracks[{sdc_id!r}]"
    length = _scenario_length(scenario, tracks, sdc_id, source)
    read = {tid: _read_track(tid, v, length, source) for tid, v in tracks.items()}
    sdc = read[sdc_id]
    steps, no_ego = _frame_steps(time_index, all_steps, stride, sdc, sdc_field, meta, length,
                                 source)
    world_map, map_dropped = _world_map(scenario, meta, source)
    city_from_world = _city_from_world(meta, source)
    scenario_id = str(scenario.get("id", meta.get("scenario_id", Path(source).stem)))
    own_id = (str(meta["scenegen_scene_id"]) if length == 1 and "scenegen_scene_id" in meta
              else None)  # our own one-step export's scene id
    times_s = _step_times(scenario, length)
    mismatch = bool(steps) and velocity_mismatch(list(read.values()), times_s)
    measured = not constant_boxes(read.values())

    out = []
    for t in steps:
        ego_w, ego_l = _ego_box(sdc, t, source, f"{sdc_field}.state")
        # Map features are the file's, not the frame's: counted once, in the first frame.
        dropped = collections.Counter() if out else collections.Counter(map_dropped)
        if ego_l < ego_w:
            dropped["quirk:length_lt_width"] += 1
            ego_w, ego_l = ego_l, ego_w
        scene_id = own_id if own_id is not None else f"{scenario_id}/{t}"
        frame = _frame_at(t, read, sdc_id, (ego_w, ego_l), world_map, city_from_world, scene_id,
                          source, map_radius_m, dropped, times_s)
        if not measured:
            frame.size_measured = np.zeros(frame.num_actors, bool)
        out.append(ImportedFrame(frame, dropped))
    if mismatch and out:
        out[0].dropped["quirk:velocity_mismatch"] += 1
    if not measured and out:
        out[0].dropped["quirk:constant_boxes"] += 1
    if no_ego:
        out[0].dropped["frame:no_ego"] += no_ego
    return out


def constant_boxes(tracks) -> bool:
    """Whether the boxes of a file's tracks are a converter's constants, not measurements:
    at least two vehicles, and every vehicle at every valid step of one (width, length).
    ScenarioNet's Argoverse 2 converter writes 4.0 x 2.0 m for every vehicle (the forecasting
    data set has no boxes); real boxes of two vehicles never agree to the bit."""
    sizes = set()
    vehicles = 0
    for tr in tracks:
        if CLASS_FROM_TYPE.get(tr.type) != VEHICLE or not tr.valid.any():
            continue
        vehicles += 1
        sizes.update(zip(tr.width[tr.valid].tolist(), tr.length[tr.valid].tolist(), strict=True))
        if len(sizes) > 1:
            return False
    return vehicles >= 2


def _scenario_tracks(scenario: Mapping, source: str) -> tuple[Mapping, dict]:
    """(metadata, tracks by id as a string) of a scenario, their types checked."""
    if not isinstance(scenario, Mapping):
        raise _err(source, "scenario", f"expected a dict, got {type(scenario).__name__}")
    meta = scenario.get("metadata", {})
    if not isinstance(meta, Mapping):
        raise _err(source, "metadata", f"expected a dict, got {type(meta).__name__}")
    tracks = _get(scenario, "tracks", source, "")
    if not isinstance(tracks, Mapping):
        raise _err(source, "tracks", f"expected a dict, got {type(tracks).__name__}")
    keys = [str(k) for k in tracks]  # MetaDrive's old pickles key some files' tracks by int
    if len(set(keys)) != len(keys):
        raise _err(source, "tracks", "two track ids are equal as strings")
    return meta, dict(zip(keys, tracks.values(), strict=True))


def _frame_steps(time_index, all_steps: bool, stride: int | None, sdc, sdc_field: str,
                 meta: Mapping, length: int, source: str) -> tuple[list[int], int]:
    """(steps to import, steps of the stride without a frame because the SDC is not valid at
    them) of a scenario whose SDC is `sdc`, which must be a vehicle (`_steps`)."""
    if CLASS_FROM_TYPE.get(sdc.type, VEHICLE) != VEHICLE:
        raise _err(source, f"{sdc_field}.type", f"the SDC (ego) is a {sdc.type}, not a vehicle")
    steps = _steps(time_index, all_steps, stride, sdc, meta, length, source)
    # Steps of the stride at which the SDC is not valid give no frame: counted.
    no_ego = len(range(0, length, stride)) - len(steps) if stride is not None else 0
    if stride is not None and not steps:
        raise _err(source, f"{sdc_field}.state.valid",
                   f"the SDC (ego) is valid at none of the steps 0, {stride}, ... of {length}")
    return steps, no_ego


def _scenario_length(scenario: Mapping, tracks: dict, sdc_id: str, source: str) -> int:
    """Steps of the scenario: its `length`, else the SDC's positions (MetaDrive's old Waymo
    pickles have no `length`)."""
    if "length" in scenario:
        return _int(scenario["length"], source, "length")
    sdc_field = f"tracks[{sdc_id!r}]"
    sdc_state = _get(tracks[sdc_id], "state", source, sdc_field)
    return len(np.asarray(_get(sdc_state, "position", source, f"{sdc_field}.state")))


def _world_map(scenario: Mapping, meta: Mapping, source: str):
    """(VectorMap in the world frame, counts of unusable map features) of a scenario, for its
    data set (`metadata.dataset`; none for our own exports)."""
    dataset = meta.get("dataset", "")
    if not isinstance(dataset, str):
        raise _err(source, "metadata.dataset", f"expected a string, got {dataset!r}")
    return map_from_features(_get(scenario, "map_features", source, ""), source,
                             "" if dataset == OWN_DATASET else dataset)


def _city_from_world(meta: Mapping, source: str) -> np.ndarray:
    """The [3, 3] pose of the world frame in the city frame our exports record (identity for
    other files)."""
    try:
        city_from_world = np.asarray(meta.get("scenegen_city_from_world", np.eye(3)), np.float64)
    except (TypeError, ValueError) as e:
        raise _err(source, "metadata.scenegen_city_from_world", f"not numbers ({e})") from e
    if city_from_world.shape != (3, 3) or not np.all(np.isfinite(city_from_world)):
        raise _err(source, "metadata.scenegen_city_from_world", "expected a finite 3x3 matrix")
    return city_from_world


def _ego_box(sdc, t: int, source: str, sf: str) -> tuple[float, float]:
    """(width, length) m of the SDC at step t, which must be valid, finite and positive
    (`sf`: the SDC's state field, for errors)."""
    if not sdc.valid[t]:
        raise _err(source, f"{sf}.valid[{t}]", "the SDC (ego) is not valid at this step")
    bad = _finite_at(sdc, t)
    if bad is not None:
        raise _err(source, f"{sf}.{bad}[{t}]", "NaN or inf in a valid step of the SDC")
    ego_w, ego_l = float(sdc.width[t]), float(sdc.length[t])
    if ego_w <= 0 or ego_l <= 0:
        raise _err(
            source,
            f"{sf}.width/length[{t}]",
            f"box size must be positive, got width {ego_w}, length {ego_l}",
        )
    return ego_w, ego_l


def _actors_at(t: int, read: dict, sdc_id: str, ego_from_world: np.ndarray, origin, h0: float,
               dropped: collections.Counter) -> tuple[list, ...]:
    """(classes, positions, sizes, headings, velocities, track ids) in the ego frame (the SDC
    at `origin` in the world, heading h0) of the tracks valid at step t but the SDC; those
    dropped are counted in `dropped` (`frames_from_scenario`)."""
    cls, pos, size, heading, vel, ids = [], [], [], [], [], []
    for tid, tr in read.items():
        if tid == sdc_id or not tr.valid[t]:
            continue
        if tr.type not in CLASS_FROM_TYPE:
            dropped[f"type:{tr.type}"] += 1
            continue
        c = CLASS_FROM_TYPE[tr.type]
        if _finite_at(tr, t) is not None:
            dropped["invalid:nan"] += 1
            continue
        w, length_m = float(tr.width[t]), float(tr.length[t])
        if c != PEDESTRIAN:
            if w <= 0 or length_m <= 0:
                dropped["invalid:size"] += 1
                continue
            if length_m < w:
                dropped["quirk:length_lt_width"] += 1
                w, length_m = length_m, w
        cls.append(c)
        pos.append(ego_from_world @ (tr.position[t] - origin))
        size.append((w, length_m))
        heading.append(tr.heading[t] - h0)
        vel.append(ego_from_world @ tr.velocity[t])
        ids.append(tid)
    return cls, pos, size, heading, vel, ids


def _frame_at(t: int, read: dict, sdc_id: str, ego_size: tuple[float, float], world_map,
              city_from_world: np.ndarray, scene_id: str, source: str,
              map_radius_m: float | None, dropped: collections.Counter,
              times_s: np.ndarray) -> Frame:
    """The Frame of step t in the SDC's ego frame (the ego's box `ego_size` (width, length)
    m, already checked), its map cropped to `map_radius_m` if given, its actors' futures from
    their tracks at the steps' times `times_s` [T] s."""
    sdc = read[sdc_id]
    x0, y0 = sdc.position[t]
    h0 = float(sdc.heading[t])
    ego_from_world = rotation_matrix(-h0)
    cls, pos, size, heading, vel, ids = _actors_at(t, read, sdc_id, ego_from_world, (x0, y0),
                                                   h0, dropped)
    vmap = world_map.transform(ego_from_world, -ego_from_world @ np.array([x0, y0]))
    if map_radius_m is not None:
        vmap = vmap.crop(np.zeros(2), map_radius_m)
    n = len(cls)
    track_xy = np.asarray([read[tid].position for tid in ids], np.float64).reshape(n, -1, 2)
    track_valid = np.asarray([read[tid].valid for tid in ids], bool).reshape(n, -1)
    future = future_positions(track_xy, track_valid, times_s, t, se2_pose(x0, y0, h0))
    return Frame(
        scene_id=scene_id,
        source=source,
        cls=np.asarray(cls, np.int32).reshape(n),
        position=np.asarray(pos, np.float64).reshape(n, 2),
        size=np.asarray(size, np.float64).reshape(n, 2),
        heading=wrap_angle(np.asarray(heading, np.float64).reshape(n)),
        velocity=np.asarray(vel, np.float64).reshape(n, 2),
        track_id=np.asarray(ids, dtype=str).reshape(n),
        ego_velocity=ego_from_world @ sdc.velocity[t],
        ego_size=np.array(ego_size, np.float64),
        map=vmap,
        city_from_ego=city_from_world @ se2_pose(x0, y0, h0),
        future=future,
    )


def scenario_files(root: str | os.PathLike) -> list[Path]:
    """Sorted scenario pickles under `root` (`files.files_under`: recursive, links followed,
    each file once), without the dataset summary/mapping."""
    files = files_under(root, ".pkl", skip=(SUMMARY_FILE, MAPPING_FILE))
    if not files:
        raise FileNotFoundError(f"{root}: no ScenarioNet scenario files (*.pkl)")
    return files


def read_scenario(path: str | os.PathLike) -> dict:
    """One scenario dict from a pickle, loaded with the restricted unpickler."""
    scenario = load_pickle(path)
    if not isinstance(scenario, dict):
        raise ValueError(
            f"{path}: expected a ScenarioNet scenario dict, got {type(scenario).__name__}"
        )
    return scenario


def read_scenarionet(
    root: str | os.PathLike,
    time_index: int | Sequence[int] | None = None,
    *,
    all_steps: bool = False,
    stride: int | None = None,
    map_radius_m: float | None = None,
) -> Iterator[ImportedFrame]:
    """(Frame, dropped Counter) for every scenario file under `root` (`frames_from_scenario`),
    held to the road-user limits of every source (`frame.drop_beyond_limits`)."""
    for path in scenario_files(root):
        for item in frames_from_scenario(read_scenario(path), str(path), time_index,
                                         all_steps=all_steps, stride=stride,
                                         map_radius_m=map_radius_m):
            frame, beyond = drop_beyond_limits(item.frame)
            yield ImportedFrame(frame, item.dropped + beyond)
