"""Frame -> ScenarioNet: `scenario_from_frame`, `write_scenario`, `write_dataset`.

A one-step scenario in the ego frame. Standard keys are filled as ScenarioNet's converters fill
them, so simulators can replay it; what the standard keys cannot carry (exact lane boundaries,
BUS lanes, mark types, intersection flags, the ego pose in the city) goes into extra keys
prefixed `scenegen_`, which take precedence on import, so export -> import is lossless up to
float32 rounding of tracks.
"""

from __future__ import annotations

import collections
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from scenegen_jax import __version__
from scenegen_jax.data.safe_pickle import dump_pickle, load_pickle
from scenegen_jax.data.scenarionet_schema import (
    LINE_TYPE_FROM_MARK,
    MAPPING_FILE,
    OWN_DATASET,
    SUMMARY_FILE,
    TOP_LEVEL_KEYS,
    TYPE_FROM_CLASS,
)
from scenegen_jax.frame import Frame
from scenegen_jax.scene import BICYCLIST, NUM_CLASSES, PEDESTRIAN, VEHICLE
from scenegen_jax.vector_map import ROAD_EDGE, Lane, VectorMap, resample_polyline

# Nominal heights (m); our frames carry no height but ScenarioNet tracks do.
_HEIGHT_M = {VEHICLE: 1.6, PEDESTRIAN: 1.75, BICYCLIST: 1.75}


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
    for i, line in enumerate(vmap.lines):
        mark = str(line.mark)
        if mark == ROAD_EDGE:
            line_type = "ROAD_EDGE_BOUNDARY"
        else:
            line_type = LINE_TYPE_FROM_MARK.get(mark.upper(), "UNKNOWN_LINE")
        features[f"line_{i}"] = {
            "type": line_type,
            "polyline": _xyz(line.points),
            "scenegen_kind": "line",
            "scenegen_mark": mark,
            "scenegen_points": np.asarray(line.points, np.float64),
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


def scenario_from_frame(frame: Frame, scenario_id: str, dataset: str | None = None) -> dict:
    """A one-step ScenarioNet scenario of a Frame, in the ego frame (SDC at the origin, heading 0).
    `dataset` (`metadata.dataset`) defaults to the frame's map's, else `OWN_DATASET`.

    The ego is the SDC track (type VEHICLE); actors keep their track ids (empty ids become
    "actor_<i>"). Raises ValueError naming the frame's source for NaN/inf, bad shapes, unknown
    classes, non-positive box sizes or duplicate track ids.
    """
    _check_frame(frame)
    dataset = dataset or frame.map.dataset or OWN_DATASET
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


def write_dataset(scenarios: Sequence[dict], directory: str | os.PathLike,
                  index: bool = True) -> list[Path]:
    """Writes scenarios plus the `dataset_summary.pkl` / `dataset_mapping.pkl` MetaDrive reads
    (with `index`; else `index_dataset` writes them later, e.g. once every process of a
    multi-process run has written its scenarios).

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
    if index:
        _write_index(directory, {n: s["metadata"] for n, s in zip(names, scenarios, strict=True)})
    return paths


def _write_index(directory: Path, metadata: dict[str, Any]) -> None:
    dump_pickle(metadata, directory / SUMMARY_FILE)
    dump_pickle(dict.fromkeys(metadata, ""), directory / MAPPING_FILE)


def index_dataset(directory: str | os.PathLike, names: Sequence[str]) -> None:
    """Writes the summary and mapping of the scenario files `names` (in that order) already
    in `directory`, reading their metadata back (`safe_pickle.load_pickle`)."""
    directory = Path(directory)
    _write_index(directory, {n: load_pickle(directory / n)["metadata"] for n in names})
