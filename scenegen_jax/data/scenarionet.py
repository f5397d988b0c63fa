"""ScenarioNet / MetaDrive scenario import and export.

A ScenarioNet scenario is a dict with the top-level keys `id`, `version`, `length`, `tracks`,
`map_features`, `metadata` and `dynamic_map_states`, pickled one per file. Coordinates are a
right-handed world frame in metres (x, y, z), headings rad, velocities m/s in that frame.

Import (`frames_from_scenario`, `read_scenarionet`) builds one `Frame` per requested step in
the SDC's ego frame. Track types VEHICLE / PEDESTRIAN / CYCLIST map to our classes; every other
type is dropped and counted in a `Counter` (key: "type:<TYPE>"), as are map features that the
VectorMap cannot hold (key: "map:<TYPE>"). Nothing is dropped silently; malformed input raises
ValueError naming the file and the field.

Export (`scenario_from_frame`, `write_scenario`, `write_dataset`) writes a one-step scenario in
the ego frame. Standard keys are filled as ScenarioNet's converters fill them, so simulators can
replay it; what the standard keys cannot carry (exact lane boundaries, BUS lanes, mark types,
intersection flags, the ego pose in the city) goes into extra keys prefixed `scenegen_`, which
take precedence on import, so export -> import is lossless up to float32 rounding of tracks.
Files from real converters carry only the standard keys: a lane is then a centreline (plus maybe
a polygon and per-point `width`) and its boundaries are rebuilt by offsetting the centreline by
the `width` entries where positive, else by `DEFAULT_HALF_WIDTH_M`.
"""

from __future__ import annotations

import collections
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from scenegen_jax import __version__
from scenegen_jax.data.frame import Frame
from scenegen_jax.data.safe_pickle import dump_pickle, load_pickle
from scenegen_jax.data.surface import offset_centerline
from scenegen_jax.data.vector_map import Lane, VectorMap, resample_polyline, rotation_matrix
from scenegen_jax.scene import BICYCLIST, NUM_CLASSES, PEDESTRIAN, VEHICLE

DEFAULT_HALF_WIDTH_M = 1.8
SUMMARY_FILE = "dataset_summary.pkl"
MAPPING_FILE = "dataset_mapping.pkl"
TOP_LEVEL_KEYS = ("id", "version", "length", "tracks", "map_features", "metadata")

CLASS_FROM_TYPE: dict[str, int] = {
    "VEHICLE": VEHICLE,
    "PEDESTRIAN": PEDESTRIAN,
    "CYCLIST": BICYCLIST,
}
TYPE_FROM_CLASS: dict[int, str] = {v: k for k, v in CLASS_FROM_TYPE.items()}
# Nominal heights (m); our frames carry no height but ScenarioNet tracks do.
_HEIGHT_M = {VEHICLE: 1.6, PEDESTRIAN: 1.75, BICYCLIST: 1.75}

LANE_FEATURE_TYPES = frozenset(
    {
        "LANE_SURFACE_STREET",
        "LANE_SURFACE_UNSTRUCTURE",
        "LANE_UNKNOWN",
        "LANE_FREEWAY",
        "LANE_BIKE_LANE",
    }
)
# Argoverse 2 mark names (our Lane.left_mark / right_mark) -> ScenarioNet line types, as in
# ScenarioNet's own Argoverse 2 converter.
LINE_TYPE_FROM_MARK: dict[str, str] = {
    "DOUBLE_SOLID_YELLOW": "ROAD_LINE_SOLID_DOUBLE_YELLOW",
    "DOUBLE_SOLID_WHITE": "ROAD_LINE_SOLID_DOUBLE_WHITE",
    "SOLID_YELLOW": "ROAD_LINE_SOLID_SINGLE_YELLOW",
    "SOLID_WHITE": "ROAD_LINE_SOLID_SINGLE_WHITE",
    "DASHED_WHITE": "ROAD_LINE_BROKEN_SINGLE_WHITE",
    "DASHED_YELLOW": "ROAD_LINE_BROKEN_SINGLE_YELLOW",
    "DASH_SOLID_YELLOW": "ROAD_LINE_SOLID_DOUBLE_YELLOW",
    "DASH_SOLID_WHITE": "ROAD_LINE_SOLID_DOUBLE_WHITE",
    "DOUBLE_DASH_YELLOW": "ROAD_LINE_BROKEN_SINGLE_YELLOW",
    "DOUBLE_DASH_WHITE": "ROAD_LINE_BROKEN_SINGLE_WHITE",
    "SOLID_DASH_WHITE": "ROAD_LINE_BROKEN_SINGLE_WHITE",
    "SOLID_DASH_YELLOW": "ROAD_LINE_BROKEN_SINGLE_YELLOW",
}
# ScenarioNet line types -> the closest Argoverse 2 mark name (crossability preserved).
MARK_FROM_LINE_TYPE: dict[str, str] = {
    "ROAD_LINE_BROKEN_SINGLE_WHITE": "DASHED_WHITE",
    "ROAD_LINE_SOLID_SINGLE_WHITE": "SOLID_WHITE",
    "ROAD_LINE_SOLID_DOUBLE_WHITE": "DOUBLE_SOLID_WHITE",
    "ROAD_LINE_BROKEN_SINGLE_YELLOW": "DASHED_YELLOW",
    "ROAD_LINE_BROKEN_DOUBLE_YELLOW": "DOUBLE_DASH_YELLOW",
    "ROAD_LINE_SOLID_SINGLE_YELLOW": "SOLID_YELLOW",
    "ROAD_LINE_SOLID_DOUBLE_YELLOW": "DOUBLE_SOLID_YELLOW",
    "ROAD_LINE_PASSING_DOUBLE_YELLOW": "SOLID_DASH_YELLOW",
    "UNKNOWN_LINE": "UNKNOWN",
}


class ImportedFrame(NamedTuple):
    """One imported frame and what was dropped from it ("type:<TYPE>" / "map:<TYPE>" -> count)."""

    frame: Frame
    dropped: collections.Counter


# ----------------------------------------------------------------------------- import


def _err(source: str, field: str, msg: str) -> ValueError:
    return ValueError(f"{source}: {field}: {msg}")


def _get(d: Any, key: str, source: str, field: str) -> Any:
    if not isinstance(d, Mapping):
        raise _err(source, field, f"expected a dict, got {type(d).__name__}")
    if key not in d:
        raise _err(source, f"{field}.{key}" if field else key, "missing")
    return d[key]


def _array(
    value: Any, source: str, field: str, ndim: int, min_cols: int = 0, dtype=np.float64
) -> np.ndarray:
    """A numeric array of `ndim` dims (at least `min_cols` columns); finiteness checked later."""
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as e:
        raise _err(source, field, f"not a numeric array ({e})") from e
    if arr.ndim != ndim or (ndim == 2 and arr.shape[1] < min_cols):
        want = f"[N, >={min_cols}]" if ndim == 2 else "[N]"
        raise _err(source, field, f"expected shape {want}, got {arr.shape}")
    return arr


def _polyline(value: Any, source: str, field: str, min_points: int = 1) -> np.ndarray:
    """[P, 2] float64 from a [P, 2] or [P, 3] polyline; NaN/inf or too few points raise."""
    pts = _array(value, source, field, 2, min_cols=2)[:, :2]
    if len(pts) < min_points:
        raise _err(source, field, f"needs at least {min_points} points, got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise _err(source, field, "NaN or inf coordinate")
    return pts


def _canonical_int(key: Any) -> int | None:
    s = str(key)
    return int(s) if re.fullmatch(r"-?[1-9][0-9]*|0", s) else None


def _dedupe(points: np.ndarray) -> np.ndarray:
    keep = np.concatenate([[True], np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-9])
    return points[keep]


def _lane_half_widths(feature: Mapping, n: int, source: str, field: str) -> tuple[np.ndarray, ...]:
    """Per-point (left, right) half widths from a standard `width` [P, 2] entry, else default."""
    left = np.full(n, DEFAULT_HALF_WIDTH_M)
    right = np.full(n, DEFAULT_HALF_WIDTH_M)
    width = feature.get("width")
    if width is None:
        return left, right
    w = _array(width, source, f"{field}.width", 2, min_cols=2)
    if len(w) != n:  # not aligned with the (deduplicated) centreline: ignore, use the default
        return left, right
    ok = np.isfinite(w) & (w > 0)
    left[ok[:, 0]] = w[ok[:, 0], 0]
    right[ok[:, 1]] = w[ok[:, 1], 1]
    return left, right


def _mark_from_boundaries(entries: Any, features: Mapping) -> str:
    """The Argoverse 2 mark name of a lane side from ScenarioNet `left/right_boundaries`."""
    if not isinstance(entries, (list, tuple)) or not entries:
        return "NONE"
    entry = entries[0]
    if not isinstance(entry, Mapping):
        return "NONE"
    line_type = entry.get("boundary_type")
    if not (isinstance(line_type, str) and line_type in MARK_FROM_LINE_TYPE):
        ref = features.get(str(entry.get("boundary_feature_id", "")))
        line_type = ref.get("type") if isinstance(ref, Mapping) else None
    return MARK_FROM_LINE_TYPE.get(line_type, "NONE") if isinstance(line_type, str) else "NONE"


def _lane_from_feature(
    fid: str, feature: Mapping, lane_id: int, links: tuple, features: Mapping, source: str
) -> Lane | None:
    """A Lane from a lane map feature; None for a degenerate (zero-length) centreline."""
    field = f"map_features[{fid!r}]"
    ftype = feature["type"]
    if "scenegen_left" in feature and "scenegen_right" in feature:
        left = _polyline(feature["scenegen_left"], source, f"{field}.scenegen_left", 2)
        right = _polyline(feature["scenegen_right"], source, f"{field}.scenegen_right", 2)
    else:
        center = _polyline(_get(feature, "polyline", source, field), source, f"{field}.polyline")
        aligned = len(_dedupe(center)) == len(center)
        center = _dedupe(center)
        if len(center) < 2:
            return None
        if aligned:
            wl, wr = _lane_half_widths(feature, len(center), source, field)
        else:
            wl = wr = np.full(len(center), DEFAULT_HALF_WIDTH_M)
        left, right = offset_centerline(center, wl, wr)
    default_type = "BIKE" if ftype == "LANE_BIKE_LANE" else "VEHICLE"
    successors, predecessors = links
    return Lane(
        id=lane_id,
        lane_type=str(feature.get("scenegen_lane_type", default_type)),
        left=left,
        right=right,
        left_mark=str(
            feature.get("scenegen_left_mark")
            or _mark_from_boundaries(feature.get("left_boundaries"), features)
        ),
        right_mark=str(
            feature.get("scenegen_right_mark")
            or _mark_from_boundaries(feature.get("right_boundaries"), features)
        ),
        is_intersection=bool(
            feature.get("scenegen_is_intersection", ftype == "LANE_SURFACE_UNSTRUCTURE")
        ),
        successors=successors,
        predecessors=predecessors,
    )


def map_from_features(map_features: Mapping, source: str) -> tuple[VectorMap, collections.Counter]:
    """The VectorMap (in the scenario's world frame) and counts of unusable features.

    Lanes come from lane types, crosswalks from CROSSWALK polygons, drivable areas from our own
    `scenegen_kind == "drivable_area"` features. Our exported lane-boundary lines are part of
    their lanes; every other feature (road lines and edges of real converters, stop signs, ...)
    is counted as "map:<TYPE>".
    """
    if not isinstance(map_features, Mapping):
        raise _err(source, "map_features", f"expected a dict, got {type(map_features).__name__}")
    dropped: collections.Counter = collections.Counter()
    lane_keys = []
    for fid, feature in map_features.items():
        ftype = _get(feature, "type", source, f"map_features[{fid!r}]")
        if ftype in LANE_FEATURE_TYPES:
            lane_keys.append(fid)
    # Integer lane ids when the file's ids are canonical integers (Argoverse, Waymo, ours);
    # otherwise (nuScenes tokens) ids are positions in file order.
    as_int = [_canonical_int(k) for k in lane_keys]
    int_ids = all(i is not None for i in as_int) and len(set(as_int)) == len(as_int)
    if int_ids:
        id_of = {str(k): i for k, i in zip(lane_keys, as_int, strict=True)}
    else:
        id_of = {str(k): n for n, k in enumerate(lane_keys)}

    def link_ids(value: Any) -> tuple[int, ...]:
        # Integer ids keep links to lanes outside this file (as a cropped Argoverse map does);
        # enumerated ids can only name lanes that are in it.
        if not isinstance(value, (list, tuple, np.ndarray)):
            return ()
        if int_ids:
            ints = (_canonical_int(x) for x in value)
            return tuple(i for i in ints if i is not None)
        return tuple(id_of[str(x)] for x in value if str(x) in id_of)

    lanes, crosswalks, drivable = [], [], []
    for fid, feature in map_features.items():
        field = f"map_features[{fid!r}]"
        ftype = feature["type"]
        kind = feature.get("scenegen_kind")
        if ftype in LANE_FEATURE_TYPES:
            links = (link_ids(feature.get("exit_lanes")), link_ids(feature.get("entry_lanes")))
            lane = _lane_from_feature(fid, feature, id_of[str(fid)], links, map_features, source)
            if lane is None:
                dropped["map:degenerate_lane"] += 1
            else:
                lanes.append(lane)
        elif kind == "lane_boundary":
            continue
        elif kind == "drivable_area" or ftype == "CROSSWALK":
            if "scenegen_polygon" in feature:
                key = "scenegen_polygon"
            elif "polygon" in feature:
                key = "polygon"
            else:
                key = "polyline"
            poly = _polyline(_get(feature, key, source, field), source, f"{field}.{key}", 3)
            (drivable if kind == "drivable_area" else crosswalks).append(poly)
        else:
            dropped[f"map:{ftype}"] += 1
    vmap = VectorMap(
        lanes=tuple(lanes), crosswalks=tuple(crosswalks), drivable_areas=tuple(drivable)
    )
    return vmap, dropped


class _Track(NamedTuple):
    """One track's state arrays (world frame), validated for shape."""

    type: str
    position: np.ndarray  # [T, 2] m
    width: np.ndarray  # [T] m
    length: np.ndarray  # [T] m
    heading: np.ndarray  # [T] rad
    velocity: np.ndarray  # [T, 2] m/s
    valid: np.ndarray  # [T] bool


def _read_track(tid: str, track: Any, length: int, source: str) -> _Track:
    field = f"tracks[{tid!r}]"
    ttype = track.get("type") if isinstance(track, Mapping) else None
    if not isinstance(ttype, str):
        meta = track.get("metadata") if isinstance(track, Mapping) else None
        ttype = meta.get("type") if isinstance(meta, Mapping) else None
    if not isinstance(ttype, str):
        raise _err(source, f"{field}.type", "missing or not a string")
    state = _get(track, "state", source, field)
    sf = f"{field}.state"
    position = _array(_get(state, "position", source, sf), source, f"{sf}.position", 2, 2)[:, :2]
    if "length" in state and "width" in state:
        lengths = _array(state["length"], source, f"{sf}.length", 1)
        widths = _array(state["width"], source, f"{sf}.width", 1)
    elif "size" in state:  # older exports: size [T, 3] = (length, width, height)
        size = _array(state["size"], source, f"{sf}.size", 2, 2)
        lengths, widths = size[:, 0], size[:, 1]
    else:
        raise _err(source, f"{sf}.length", "missing (and no size)")
    heading = _array(_get(state, "heading", source, sf), source, f"{sf}.heading", 1)
    velocity = _array(_get(state, "velocity", source, sf), source, f"{sf}.velocity", 2, 2)[:, :2]
    valid = _array(_get(state, "valid", source, sf), source, f"{sf}.valid", 1, dtype=bool)
    arrays = dict(
        position=position,
        width=widths,
        length=lengths,
        heading=heading,
        velocity=velocity,
        valid=valid,
    )
    for name, arr in arrays.items():
        if len(arr) != length:
            raise _err(source, f"{sf}.{name}", f"has {len(arr)} steps, scenario length is {length}")
    return _Track(type=ttype, **arrays)


def _check_actor(tr: _Track, t: int, tid: str, boxed: bool, source: str) -> None:
    sf = f"tracks[{tid!r}].state"
    for name in ("position", "heading", "velocity", "width", "length"):
        if not np.all(np.isfinite(getattr(tr, name)[t])):
            raise _err(source, f"{sf}.{name}[{t}]", "NaN or inf in a valid step")
    if boxed and (tr.width[t] <= 0 or tr.length[t] <= 0):
        raise _err(
            source,
            f"{sf}.width/length[{t}]",
            f"box size must be positive, got width {tr.width[t]}, length {tr.length[t]}",
        )


def _int(value: Any, source: str, field: str) -> int:
    try:
        return int(value)
    except (TypeError, ValueError) as e:
        raise _err(source, field, f"expected an integer, got {value!r}") from e


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles (rad) into [0, 2pi); mod alone can round a tiny negative angle up to 2pi."""
    wrapped = np.mod(angle, 2 * np.pi)
    return np.where(wrapped >= 2 * np.pi, 0.0, wrapped)


def _se2(x: float, y: float, theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def frames_from_scenario(
    scenario: Mapping,
    source: str,
    time_index: int | Sequence[int] | None = None,
    *,
    all_steps: bool = False,
    map_radius_m: float | None = None,
) -> list[ImportedFrame]:
    """Frames (in the SDC's ego frame) of a ScenarioNet scenario, with per-frame drop counts.

    Args:
      scenario: the scenario dict (as loaded from a ScenarioNet pickle).
      source: file it came from, used in error messages and as `Frame.source`.
      time_index: step(s) to import; default `metadata["current_time_index"]` (0 if absent).
      all_steps: import every step at which the SDC is valid (overrides `time_index`).
      map_radius_m: if given, keep only map elements within this box radius (m) of the ego.

    Returns:
      One ImportedFrame(frame, dropped) per step. `dropped` counts actors valid at that step
      whose type has no class (key: "type:<TYPE>") and map features the VectorMap cannot
      hold (key: "map:<TYPE>").

    Raises:
      ValueError naming `source` and the field for missing keys, bad shapes, NaN/inf in valid
      steps, non-positive box sizes of vehicles and cyclists, or an invalid SDC step.
    """
    if not isinstance(scenario, Mapping):
        raise _err(source, "scenario", f"expected a dict, got {type(scenario).__name__}")
    meta = _get(scenario, "metadata", source, "")
    tracks = _get(scenario, "tracks", source, "")
    if not isinstance(tracks, Mapping):
        raise _err(source, "tracks", f"expected a dict, got {type(tracks).__name__}")
    sdc_id = str(_get(meta, "sdc_id", source, "metadata"))
    if sdc_id not in tracks:
        raise _err(source, "metadata.sdc_id", f"{sdc_id!r} is not a key of tracks")
    sdc_field = f"tracks[{sdc_id!r}]"
    if "length" in scenario:
        length = _int(scenario["length"], source, "length")
    else:
        sdc_state = _get(tracks[sdc_id], "state", source, sdc_field)
        length = len(np.asarray(_get(sdc_state, "position", source, f"{sdc_field}.state")))
    read = {str(k): _read_track(str(k), v, length, source) for k, v in tracks.items()}
    sdc = read[sdc_id]

    if all_steps:
        steps = [int(t) for t in np.flatnonzero(sdc.valid)]
    elif time_index is None:
        steps = [_int(meta.get("current_time_index", 0), source, "metadata.current_time_index")]
    elif isinstance(time_index, (int, np.integer)):
        steps = [int(time_index)]
    else:
        steps = [_int(t, source, "time_index") for t in time_index]
    for t in steps:
        if not 0 <= t < length:
            raise _err(source, "time_index", f"{t} outside [0, {length})")

    world_map, map_dropped = map_from_features(_get(scenario, "map_features", source, ""), source)
    city_from_world = np.asarray(meta.get("scenegen_city_from_world", np.eye(3)), np.float64)
    if city_from_world.shape != (3, 3) or not np.all(np.isfinite(city_from_world)):
        raise _err(source, "metadata.scenegen_city_from_world", "expected a finite 3x3 matrix")
    scenario_id = str(scenario.get("id", meta.get("scenario_id", Path(source).stem)))

    out = []
    for t in steps:
        sf = f"{sdc_field}.state"
        if not sdc.valid[t]:
            raise _err(source, f"{sf}.valid[{t}]", "the SDC (ego) is not valid at this step")
        _check_actor(sdc, t, sdc_id, True, source)
        x0, y0 = sdc.position[t]
        h0 = float(sdc.heading[t])
        ego_from_world = rotation_matrix(-h0)

        dropped = collections.Counter(map_dropped)
        cls, pos, size, heading, vel, ids = [], [], [], [], [], []
        for tid, tr in read.items():
            if tid == sdc_id or not tr.valid[t]:
                continue
            if tr.type not in CLASS_FROM_TYPE:
                dropped[f"type:{tr.type}"] += 1
                continue
            c = CLASS_FROM_TYPE[tr.type]
            _check_actor(tr, t, tid, c != PEDESTRIAN, source)
            cls.append(c)
            pos.append(ego_from_world @ (tr.position[t] - (x0, y0)))
            size.append((tr.width[t], tr.length[t]))
            heading.append(tr.heading[t] - h0)
            vel.append(ego_from_world @ tr.velocity[t])
            ids.append(tid)

        vmap = world_map.transform(ego_from_world, -ego_from_world @ np.array([x0, y0]))
        if map_radius_m is not None:
            vmap = vmap.crop(np.zeros(2), map_radius_m)
        n = len(cls)
        single_step = length == 1 and "scenegen_scene_id" in meta
        frame = Frame(
            scene_id=str(meta["scenegen_scene_id"]) if single_step else f"{scenario_id}/{t}",
            source=source,
            cls=np.asarray(cls, np.int32).reshape(n),
            position=np.asarray(pos, np.float64).reshape(n, 2),
            size=np.asarray(size, np.float64).reshape(n, 2),
            heading=_wrap(np.asarray(heading, np.float64).reshape(n)),
            velocity=np.asarray(vel, np.float64).reshape(n, 2),
            track_id=np.asarray(ids, dtype=str).reshape(n),
            ego_velocity=ego_from_world @ sdc.velocity[t],
            ego_size=np.array([sdc.width[t], sdc.length[t]], np.float64),
            map=vmap,
            city_from_ego=city_from_world @ _se2(x0, y0, h0),
        )
        out.append(ImportedFrame(frame, dropped))
    return out


def scenario_files(root: str | os.PathLike) -> list[Path]:
    """Sorted scenario pickles under `root` (recursive), without the dataset summary/mapping."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a directory")
    files = sorted(
        p for p in root.rglob("*.pkl") if p.is_file() and p.name not in (SUMMARY_FILE, MAPPING_FILE)
    )
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
    map_radius_m: float | None = None,
) -> Iterator[ImportedFrame]:
    """(Frame, dropped Counter) for every scenario file under `root`; see frames_from_scenario."""
    for path in scenario_files(root):
        yield from frames_from_scenario(
            read_scenario(path),
            str(path),
            time_index,
            all_steps=all_steps,
            map_radius_m=map_radius_m,
        )


# ----------------------------------------------------------------------------- export


def _xyz(points: np.ndarray) -> np.ndarray:
    """[P, 3] float32 with z = 0, as ScenarioNet polylines are."""
    points = np.asarray(points, np.float64)
    return np.concatenate([points, np.zeros((len(points), 1))], axis=1).astype(np.float32)


def _check_frame(frame: Frame) -> None:
    where = f"{frame.source or frame.scene_id}: frame"
    n = frame.num_actors
    shapes = {
        "position": (n, 2),
        "size": (n, 2),
        "heading": (n,),
        "velocity": (n, 2),
        "track_id": (n,),
        "ego_velocity": (2,),
        "ego_size": (2,),
        "city_from_ego": (3, 3),
    }
    for name, shape in shapes.items():
        value = np.asarray(getattr(frame, name))
        if value.shape != shape:
            raise ValueError(f"{where}.{name}: expected shape {shape}, got {value.shape}")
        if name != "track_id" and not np.all(np.isfinite(value)):
            raise ValueError(f"{where}.{name}: NaN or inf")
    cls = np.asarray(frame.cls)
    if np.any((cls < 0) | (cls >= NUM_CLASSES)):
        raise ValueError(f"{where}.cls: class ids must be in [0, {NUM_CLASSES})")
    boxed = cls != PEDESTRIAN
    if np.any(np.asarray(frame.size)[boxed] <= 0) or np.any(np.asarray(frame.ego_size) <= 0):
        raise ValueError(f"{where}.size: box width and length must be positive")


def _track(
    ttype: str,
    tid: str,
    position: Any,
    size: Any,
    height: float,
    heading: float,
    velocity: Any,
    dataset: str,
) -> dict:
    """A one-step ScenarioNet track; position (x, y) m, size (width, length) m."""
    x, y = (float(v) for v in position)
    width, length = (float(v) for v in size)
    return {
        "type": ttype,
        "state": {
            "position": np.array([[x, y, 0.0]], np.float32),
            "length": np.array([length], np.float32),
            "width": np.array([width], np.float32),
            "height": np.array([height], np.float32),
            "heading": np.array([heading], np.float32),
            "velocity": np.asarray(velocity, np.float32).reshape(1, 2),
            "valid": np.array([True]),
        },
        "metadata": {"track_length": 1, "type": ttype, "object_id": tid, "dataset": dataset},
    }


def _lane_features(lane: Lane) -> dict[str, dict]:
    """The lane's centreline feature and its two boundary-line features."""
    lid = str(int(lane.id))
    center = lane.centerline
    n = len(center)
    half = np.stack(
        [
            np.linalg.norm(center - resample_polyline(lane.left, n), axis=1),
            np.linalg.norm(center - resample_polyline(lane.right, n), axis=1),
        ],
        axis=1,
    )
    is_vehicle = lane.lane_type != "BIKE"
    if not is_vehicle:
        ftype = "LANE_BIKE_LANE"
    elif lane.is_intersection:
        ftype = "LANE_SURFACE_UNSTRUCTURE"
    else:
        ftype = "LANE_SURFACE_STREET"
    features: dict[str, dict] = {}
    bounds: dict[str, list] = {}
    for side, line, mark in (
        ("left", lane.left, lane.left_mark),
        ("right", lane.right, lane.right_mark),
    ):
        bid = f"{lid}_{side}_boundary"
        line_type = LINE_TYPE_FROM_MARK.get(mark.upper(), "UNKNOWN_LINE")
        features[bid] = {
            "type": line_type,
            "polyline": _xyz(line),
            "scenegen_kind": "lane_boundary",
        }
        bounds[side] = [
            {
                "lane_start_index": 0,
                "lane_end_index": n - 1,
                "boundary_type": line_type,
                "boundary_feature_id": bid,
            }
        ]
    lane_feature = {
        "type": ftype,
        "polyline": _xyz(center),
        "polygon": _xyz(lane.polygon),
        "width": half.astype(np.float32),
        "entry_lanes": [str(int(i)) for i in lane.predecessors],
        "exit_lanes": [str(int(i)) for i in lane.successors],
        "left_boundaries": bounds["left"],
        "right_boundaries": bounds["right"],
        "left_neighbor": [],
        "right_neighbor": [],
        "scenegen_kind": "lane",
        "scenegen_lane_type": lane.lane_type,
        "scenegen_left": np.asarray(lane.left, np.float64),
        "scenegen_right": np.asarray(lane.right, np.float64),
        "scenegen_left_mark": lane.left_mark,
        "scenegen_right_mark": lane.right_mark,
        "scenegen_is_intersection": bool(lane.is_intersection),
    }
    return {lid: lane_feature, **features}


def map_features_from_vector_map(vmap: VectorMap) -> dict[str, dict]:
    """ScenarioNet map features (plus `scenegen_*` extras) of a VectorMap, same frame."""
    features: dict[str, dict] = {}
    ids = [int(lane.id) for lane in vmap.lanes]
    if len(set(ids)) != len(ids):
        raise ValueError("map.lanes: lane ids must be unique")
    for lane in vmap.lanes:
        features.update(_lane_features(lane))
    for i, poly in enumerate(vmap.crosswalks):
        features[f"crosswalk_{i}"] = {
            "type": "CROSSWALK",
            "polygon": _xyz(poly),
            "scenegen_kind": "crosswalk",
            "scenegen_polygon": np.asarray(poly, np.float64),
        }
    for i, poly in enumerate(vmap.drivable_areas):
        ring = np.asarray(poly, np.float64)
        if len(ring) and not np.allclose(ring[0], ring[-1]):
            ring = np.concatenate([ring, ring[:1]], axis=0)
        # ScenarioNet has no drivable-area type; its outline is a road edge for simulators.
        features[f"drivable_area_{i}"] = {
            "type": "ROAD_EDGE_BOUNDARY",
            "polyline": _xyz(ring),
            "polygon": _xyz(poly),
            "scenegen_kind": "drivable_area",
            "scenegen_polygon": np.asarray(poly, np.float64),
        }
    return features


def scenario_from_frame(frame: Frame, scenario_id: str, dataset: str = "scenegen") -> dict:
    """A one-step ScenarioNet scenario of a Frame, in the ego frame (SDC at the origin, heading 0).

    The ego is the SDC track (type VEHICLE); actors keep their track ids (empty ids become
    "actor_<i>"). Raises ValueError naming the frame's source for NaN/inf, bad shapes, unknown
    classes, non-positive box sizes or duplicate track ids.
    """
    _check_frame(frame)
    where = f"{frame.source or frame.scene_id}: frame"
    ids = [str(t) if str(t) else f"actor_{i}" for i, t in enumerate(np.asarray(frame.track_id))]
    if len(set(ids)) != len(ids):
        dup = collections.Counter(ids).most_common(1)[0][0]
        raise ValueError(f"{where}.track_id: duplicate track id {dup!r}")
    sdc_id = "ego"
    while sdc_id in ids:
        sdc_id = f"_{sdc_id}"

    height = _HEIGHT_M[VEHICLE]
    tracks = {
        sdc_id: _track(
            "VEHICLE", sdc_id, (0, 0), frame.ego_size, height, 0.0, frame.ego_velocity, dataset
        )
    }
    for i, tid in enumerate(ids):
        c = int(frame.cls[i])
        tracks[tid] = _track(
            TYPE_FROM_CLASS[c],
            tid,
            frame.position[i],
            frame.size[i],
            _HEIGHT_M[c],
            float(frame.heading[i]),
            frame.velocity[i],
            dataset,
        )

    metadata = {
        "id": scenario_id,
        "scenario_id": scenario_id,
        "dataset": dataset,
        "ts": np.array([0.0]),
        "metadrive_processed": False,
        "coordinate": "right-handed",
        "sdc_id": sdc_id,
        "sdc_track_index": 0,
        "current_time_index": 0,
        "track_length": 1,
        "objects_of_interest": [],
        "tracks_to_predict": {},
        "source_file": str(frame.source),
        "scenegen_scene_id": str(frame.scene_id),
        "scenegen_city_from_world": np.asarray(frame.city_from_ego, np.float64),
        "scenegen_version": __version__,
    }
    return {
        "id": scenario_id,
        "version": f"scenegen_jax-{__version__}",
        "length": 1,
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": map_features_from_vector_map(frame.map),
        "metadata": metadata,
    }


def _check_scenario(scenario: Any, where: str) -> None:
    if not isinstance(scenario, dict):
        raise ValueError(f"{where}: expected a scenario dict, got {type(scenario).__name__}")
    missing = [k for k in (*TOP_LEVEL_KEYS, "dynamic_map_states") if k not in scenario]
    if missing:
        raise ValueError(f"{where}: scenario lacks top-level keys {missing}")


def write_scenario(scenario: dict, path: str | os.PathLike) -> None:
    """Pickles one scenario dict to `path` (atomic write)."""
    _check_scenario(scenario, str(path))
    dump_pickle(scenario, path)


def scenario_file_name(scenario: Mapping) -> str:
    """ScenarioNet-style file name "sd_<dataset>_<id>.pkl" (id made filesystem-safe)."""
    dataset = str(scenario.get("metadata", {}).get("dataset", "scenegen"))
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", f"{dataset}_{scenario['id']}")
    return f"sd_{safe}.pkl"


def write_dataset(scenarios: Sequence[dict], directory: str | os.PathLike) -> list[Path]:
    """Writes scenarios plus the `dataset_summary.pkl` / `dataset_mapping.pkl` MetaDrive reads.

    Returns the scenario file paths. Raises ValueError on duplicate file names.
    """
    directory = Path(directory)
    names = [scenario_file_name(s) for s in scenarios]
    if len(set(names)) != len(names):
        dup = collections.Counter(names).most_common(1)[0][0]
        raise ValueError(f"{directory}: two scenarios map to the file name {dup!r}")
    paths = []
    for scenario, name in zip(scenarios, names, strict=True):
        write_scenario(scenario, directory / name)
        paths.append(directory / name)
    dump_pickle(
        {n: s["metadata"] for n, s in zip(names, scenarios, strict=True)}, directory / SUMMARY_FILE
    )
    dump_pickle({n: "" for n in names}, directory / MAPPING_FILE)
    return paths


# ----------------------------------------------------------------------------- comparison


def frame_differences(a: Frame, b: Frame, atol: float = 1e-4) -> list[str]:
    """Fields in which two frames differ beyond `atol` (m, rad, m/s); [] when they match.

    Headings compare as angles; the map compares lane by lane (ids, types, marks, flags, links,
    boundary points), then crosswalk and drivable-area points. `source` is not compared.
    """
    diffs: list[str] = []
    if a.scene_id != b.scene_id:
        diffs.append(f"scene_id: {a.scene_id!r} != {b.scene_id!r}")
    if a.num_actors != b.num_actors:
        return [*diffs, f"num_actors: {a.num_actors} != {b.num_actors}"]
    if not np.array_equal(np.asarray(a.cls), np.asarray(b.cls)):
        diffs.append("cls")
    if [str(t) for t in a.track_id] != [str(t) for t in b.track_id]:
        diffs.append("track_id")
    for name in ("position", "size", "velocity", "ego_velocity", "ego_size", "city_from_ego"):
        x, y = np.asarray(getattr(a, name), np.float64), np.asarray(getattr(b, name), np.float64)
        if x.shape != y.shape or not np.allclose(x, y, rtol=0, atol=atol):
            diffs.append(name)
    dh = np.angle(np.exp(1j * (np.asarray(a.heading, np.float64) - np.asarray(b.heading))))
    if np.any(np.abs(dh) > atol):
        diffs.append("heading")

    def close(p: np.ndarray, q: np.ndarray) -> bool:
        return p.shape == q.shape and np.allclose(p, q, rtol=0, atol=atol)

    if len(a.map.lanes) != len(b.map.lanes):
        diffs.append(f"map.lanes: {len(a.map.lanes)} != {len(b.map.lanes)}")
    else:
        for i, (la, lb) in enumerate(zip(a.map.lanes, b.map.lanes, strict=True)):
            fields = ("id", "lane_type", "left_mark", "right_mark", "is_intersection")
            for f in (*fields, "successors", "predecessors"):
                if getattr(la, f) != getattr(lb, f):
                    diffs.append(f"map.lanes[{i}].{f}")
            if not (close(la.left, lb.left) and close(la.right, lb.right)):
                diffs.append(f"map.lanes[{i}] boundaries")
    for name in ("crosswalks", "drivable_areas"):
        pa, pb = getattr(a.map, name), getattr(b.map, name)
        if len(pa) != len(pb) or not all(close(p, q) for p, q in zip(pa, pb, strict=True)):
            diffs.append(f"map.{name}")
    return diffs
