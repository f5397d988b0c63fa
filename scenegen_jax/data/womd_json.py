"""Waymo Open Motion Dataset scenes as GPUDrive / Nocturne JSON -> Frames.

One JSON file holds one scenario: `objects` (tracks of T steps at 10 Hz in the global WOMD
frame, m), `roads` (map features) and, in GPUDrive's newer files, `metadata`. The converters'
layouts differ, and every difference is detected from the data, never from the file name:

- rows (`position: [{x, y}, ...]`) or columns (`position: {x: [T], y: [T]}`);
- headings in radians or in unwrapped degrees: the unit is the one under which moving
  objects' headings agree with their velocity directions (objects at or below 2 m/s leave the
  range as the only clue: degrees when any heading is beyond 2 pi);
- invalid steps hold a sentinel (-10000, 0.0001, ...): every step is masked with `valid`;
- the ego: `metadata.sdc_track_index` where the file has it. Otherwise the recording vehicle
  is estimated (`estimate_sdc`): among vehicles valid at every step, the one whose farthest
  other object is nearest, on average over the steps, because WOMD keeps the objects that
  the SDC's sensors saw around it, so the SDC sits near the centre of the smallest disc that
  holds them. On the 28 WOMD scenes that do mark the SDC (12 GPUDrive JSON files and the
  ScenarioNet pickles) this finds it in 23 (82 %); where it
  picks another vehicle, the frame is still a real scene around a real vehicle, but that
  vehicle's surroundings are seen from a recording car nearby, so near-ego crowding is a
  little lower than for true SDC frames.

Map: roads become `womd_scene.MapFeature`s of their `type` (`map_element_id` 3 is a bike
lane; road lines take their mark from `map_element_id`, which GPUDrive writes with Waymo's
road-line types; Nocturne files have none). Parsing is the only part that knows JSON: it
gives a `womd_scene.ParsedScenario`, and `womd_scene.scenario_frames` turns it into frames,
as for the Waymo Scenario TFRecord reader (`womd_tfrecord`).
"""

from __future__ import annotations

import collections
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from scenegen_jax.data.womd_scene import (
    BIKE_LANE_ELEMENT_ID,
    CLASS_FROM_TYPE,
    DROPPED_ROAD_TYPES,
    MARK_FROM_ELEMENT_ID,
    MOVING_MPS,
    MapFeature,
    ParsedScenario,
    Tracks,
    field_error,
    scenario_frames,
)
from scenegen_jax.files import files_under
from scenegen_jax.frame import Frame
from scenegen_jax.frame import speed as frame_speed
from scenegen_jax.jsonfile import read_json


def _xy(value: Any, n: int | None, source: str, field: str) -> np.ndarray:
    """[T, 2] from rows [{x, y, ...}] or columns {x: [T], y: [T]}."""
    try:
        if isinstance(value, Mapping):
            out = np.stack([np.asarray(value["x"], float), np.asarray(value["y"], float)], -1)
        elif isinstance(value, list):
            out = np.array([(p["x"], p["y"]) for p in value], float).reshape(len(value), 2)
        else:
            raise TypeError(f"expected a list or a dict, got {type(value).__name__}")
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise field_error(source, field, f"expected x/y points ({e})") from e
    if out.ndim != 2 or (n is not None and len(out) != n):
        raise field_error(source, field, f"expected {n} points, got shape {out.shape}")
    return out


def _vector(value: Any, n: int, source: str, field: str) -> np.ndarray:
    try:
        out = np.asarray(value, float)
    except (TypeError, ValueError, OverflowError) as e:
        raise field_error(source, field, f"not a numeric list ({e})") from e
    if out.shape != (n,):
        raise field_error(source, field, f"expected {n} values, got shape {out.shape}")
    return out


def _is_flag(value: Any) -> bool:
    return isinstance(value, bool) or (isinstance(value, int) and value in (0, 1))


def _flags(value: Any, n: int | None, source: str, field: str) -> np.ndarray:
    """bool [n] from a list of JSON booleans (0 and 1 allowed); anything else is named."""
    if not isinstance(value, list):
        raise field_error(source, field, f"expected a list of booleans, got {type(value).__name__}")
    bad = [i for i, v in enumerate(value) if not _is_flag(v)]
    if bad:
        raise field_error(source, field, f"expected booleans, got {value[bad[0]]!r}")
    if n is not None and len(value) != n:
        raise field_error(source, field, f"expected {n} values, got {len(value)}")
    return np.asarray(value, bool)


def _scalar(obj: Mapping, key: str, source: str, field: str) -> float:
    value = obj.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise field_error(source, f"{field}.{key}", f"expected a number, got {value!r}")
    try:
        return float(value)
    except OverflowError as e:  # a JSON integer beyond float range
        raise field_error(source, f"{field}.{key}", "integer out of float range") from e


def heading_unit_is_degrees(heading: np.ndarray, velocity: np.ndarray, valid: np.ndarray) -> bool:
    """Whether headings [O, T] are degrees, from their agreement with velocity directions."""
    speed = frame_speed(velocity)  # inf, not an overflow warning, for speeds near 1e308
    moving = valid & (speed > MOVING_MPS) & np.isfinite(heading)
    if moving.sum() >= 5:
        direction = np.arctan2(velocity[..., 1], velocity[..., 0])[moving]
        h = heading[moving]

        def error(rad: np.ndarray) -> float:
            return float(np.mean(np.abs(np.angle(np.exp(1j * (rad - direction))))))

        return error(np.deg2rad(h)) < error(h)
    h = heading[valid & np.isfinite(heading)]
    return bool(h.size and np.max(np.abs(h)) > 2 * np.pi + 1e-3)


def read_tracks(objects: Any, source: str) -> tuple[Tracks, collections.Counter]:
    """The objects of a scenario; objects never valid or of unknown type are counted."""
    if not isinstance(objects, list) or not objects:
        raise field_error(source, "objects", "expected a non-empty list")
    dropped: collections.Counter = collections.Counter()
    first = objects[0]
    if not isinstance(first, Mapping) or "valid" not in first:
        raise field_error(source, "objects[0].valid", "missing")
    n_steps = len(_flags(first["valid"], None, source, "objects[0].valid"))
    kept = collections.defaultdict(list)
    for i, obj in enumerate(objects):
        field = f"objects[{i}]"
        if not isinstance(obj, Mapping):
            raise field_error(source, field, f"expected a dict, got {type(obj).__name__}")
        valid = _flags(obj.get("valid"), n_steps, source, f"{field}.valid")
        otype = obj.get("type")
        if not isinstance(otype, str):
            raise field_error(source, f"{field}.type", f"expected a string, got {otype!r}")
        if otype not in CLASS_FROM_TYPE:
            dropped[f"type:{otype}"] += int(valid.sum())
            continue
        kept["type"].append(otype)
        kept["valid"].append(valid)
        kept["position"].append(_xy(obj.get("position"), n_steps, source, f"{field}.position"))
        kept["velocity"].append(_xy(obj.get("velocity"), n_steps, source, f"{field}.velocity"))
        kept["heading"].append(_vector(obj.get("heading"), n_steps, source, f"{field}.heading"))
        kept["size"].append(
            (_scalar(obj, "width", source, field), _scalar(obj, "length", source, field))
        )
        kept["ids"].append(str(obj.get("id", i)))
    if not kept["type"]:
        raise field_error(source, "objects", "no vehicle, pedestrian or cyclist")
    arrays = {k: np.stack(v) for k, v in kept.items() if k not in ("type", "ids")}
    arrays["size"] = np.repeat(arrays["size"][:, None], n_steps, axis=1)  # constant in time
    if heading_unit_is_degrees(arrays["heading"], arrays["velocity"], arrays["valid"]):
        arrays["heading"] = np.deg2rad(arrays["heading"])
    tracks = Tracks(type=kept["type"], ids=kept["ids"], **arrays)
    return tracks, dropped


def estimate_sdc(tracks: Tracks) -> int:
    """Index of the likely recording vehicle: see the module docstring. -1 when none."""
    always = np.flatnonzero(
        np.array([t == "vehicle" for t in tracks.type]) & tracks.valid.all(axis=1)
    )
    if len(always) == 0:
        return -1
    reach = []
    for i in always:  # mean over steps of the distance to the farthest other valid object
        dist = np.linalg.norm(tracks.position - tracks.position[i][None], axis=-1)  # [O, T]
        dist = np.where(tracks.valid, dist, -np.inf)
        dist[i] = -np.inf
        farthest = dist.max(axis=0)
        reach.append(
            np.mean(farthest[np.isfinite(farthest)]) if np.isfinite(farthest).any() else 0.0
        )
    return int(always[int(np.argmin(reach))])


def find_sdc(data: Mapping, tracks: Tracks, objects: list, source: str) -> int:
    """Index into `tracks` of the ego: the file's SDC marker, else `estimate_sdc`."""
    meta = data.get("metadata")
    if meta is not None and not isinstance(meta, Mapping):
        raise field_error(source, "metadata", f"expected an object, got {type(meta).__name__}")
    if isinstance(meta, Mapping) and "sdc_track_index" in meta:
        index = meta["sdc_track_index"]
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(objects):
            raise field_error(source, "metadata.sdc_track_index", f"not an object index: {index!r}")
        # Objects of unknown types were left out of `tracks`: count the kept ones before it.
        kept_before = sum(
            1
            for o in objects[:index]
            if isinstance(o, Mapping) and o.get("type") in CLASS_FROM_TYPE
        )
        if objects[index].get("type") != "vehicle":
            raise field_error(source, "metadata.sdc_track_index", "the SDC is not a vehicle")
        return kept_before
    sdc = estimate_sdc(tracks)
    if sdc < 0:
        raise field_error(source, "objects", "no SDC marker and no vehicle valid at every step")
    return sdc


def _mark_of_element(element: Any) -> str | None:
    """The mark of a road line's `map_element_id`; None when it gives none (unhashable
    damaged values included)."""
    return MARK_FROM_ELEMENT_ID.get(element) if isinstance(element, (int, float)) else None


def road_features(roads: Any, source: str) -> list[MapFeature]:
    """The `roads` of a JSON scenario as MapFeatures (kinds are their `type`s)."""
    if not isinstance(roads, list):
        raise field_error(source, "roads", f"expected a list, got {type(roads).__name__}")
    features = []
    for i, road in enumerate(roads):
        field = f"roads[{i}]"
        rtype = road.get("type") if isinstance(road, Mapping) else None
        if not isinstance(rtype, str):
            raise field_error(source, f"{field}.type", f"expected a string, got {rtype!r}")
        if rtype in DROPPED_ROAD_TYPES:
            features.append(MapFeature(rtype, field))
            continue
        points = _xy(road.get("geometry"), None, source, f"{field}.geometry")
        element = road.get("map_element_id")
        features.append(MapFeature(
            rtype, f"{field}.geometry", points,
            lane_type="BIKE" if element == BIKE_LANE_ELEMENT_ID else "VEHICLE",
            mark=_mark_of_element(element)))
    return features


def parse_scenario(data: Any, source: str) -> ParsedScenario:
    """The tracks, ego and map features of a GPUDrive / Nocturne JSON scenario."""
    if not isinstance(data, Mapping):
        raise field_error(source, "scenario", f"expected a JSON object, got {type(data).__name__}")
    objects = data.get("objects")
    tracks, dropped = read_tracks(objects, source)
    sdc = find_sdc(data, tracks, objects, source)
    features = road_features(data.get("roads"), source)
    scenario_id = str(data.get("scenario_id") or Path(source).stem)
    return ParsedScenario(scenario_id, tracks, sdc, features, dropped)


def frames_from_scenario(
    data: Any, source: str, stride: int
) -> tuple[list[Frame], collections.Counter]:
    """Frames and drop counts of a JSON scenario (`parse_scenario`, `scenario_frames`)."""
    return scenario_frames(parse_scenario(data, source), source, stride)


def scenario_files(root: str | os.PathLike) -> list[Path]:
    """Sorted `*.json` scenario files under `root` (`files.files_under`: recursive, links
    followed, each file once)."""
    files = files_under(root, ".json")
    if not files:
        raise FileNotFoundError(f"{root}: no GPUDrive / Nocturne JSON files (*.json)")
    return files


def read_file(path: str | os.PathLike, stride: int) -> tuple[list[Frame], collections.Counter]:
    """Frames and drop counts of one JSON scenario file; errors name the file and field."""
    return frames_from_scenario(read_json(path), str(path), stride)
