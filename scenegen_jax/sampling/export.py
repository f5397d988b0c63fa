"""Host-side conversions of sampled scenes: JSON records, given-actor parsing, Frames for the
ScenarioNet exporter. Pure functions over numpy; the CLI does the file I/O.

JSON actor record (units m, rad, m/s; ego frame, x forward, y left):
  {"class": "vehicle" | "pedestrian" | "bicyclist", "x", "y", "width", "length", "heading",
   "vx", "vy"}
Pedestrians carry the nominal footprint (`cfg.pedestrian_size_m`) and their walking
direction as heading; on input their width, length and heading may be omitted.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.data.frame import Frame
from scenegen_jax.data.vector_map import VectorMap
from scenegen_jax.scene import CLASS_NAMES, PEDESTRIAN, Actors, Scene, canonical_order, make_ego

RECORD_FIELDS = ("x", "y", "width", "length", "heading", "vx", "vy")


def actor_records(actors: Actors) -> list[dict]:
    """JSON-ready records of the valid slots of Actors [N] (numpy or jax), in slot order."""
    a = _numpy(actors)
    out = []
    for i in np.flatnonzero(a.valid):
        out.append({
            "class": CLASS_NAMES[int(a.cls[i])],
            "x": float(a.position[i, 0]),
            "y": float(a.position[i, 1]),
            "width": float(a.size[i, 0]),
            "length": float(a.size[i, 1]),
            "heading": float(a.heading[i]),
            "vx": float(a.velocity[i, 0]),
            "vy": float(a.velocity[i, 1]),
        })
    return out


def actors_from_records(records: Sequence[Mapping[str, Any]], cfg: Config, where: str) -> Actors:
    """Actors [N = cfg.max_actors] (numpy, canonical order) from JSON records.

    Raises ValueError naming `where` and the field for unknown classes, missing or non-finite
    values, non-positive box sizes, actors outside the region, or more than N actors.
    """
    n = cfg.max_actors
    if not isinstance(records, Sequence) or isinstance(records, (str, bytes)):
        raise ValueError(f"{where}: actors: expected a list of actor records")
    if len(records) > n:
        raise ValueError(f"{where}: actors: {len(records)} actors, more than max_actors = {n}")
    cls = np.zeros(n, np.int32)
    position = np.zeros((n, 2), np.float32)
    size = np.zeros((n, 2), np.float32)
    heading = np.zeros(n, np.float32)
    velocity = np.zeros((n, 2), np.float32)
    valid = np.zeros(n, bool)
    for i, rec in enumerate(records):
        field = f"{where}: actors[{i}]"
        if not isinstance(rec, Mapping):
            raise ValueError(f"{field}: expected an object")
        name = rec.get("class")
        if name not in CLASS_NAMES:
            raise ValueError(f"{field}.class: {name!r} is not one of {CLASS_NAMES}")
        c = CLASS_NAMES.index(name)
        ped = c == PEDESTRIAN
        values = {}
        for key in RECORD_FIELDS:
            default = {"width": cfg.pedestrian_size_m, "length": cfg.pedestrian_size_m,
                       "heading": 0.0}.get(key) if ped else None
            value = rec.get(key, default)
            if value is None:
                raise ValueError(f"{field}.{key}: missing")
            try:
                value = float(value)
            except (TypeError, ValueError) as e:
                raise ValueError(f"{field}.{key}: not a number ({value!r})") from e
            if not math.isfinite(value):
                raise ValueError(f"{field}.{key}: NaN or inf")
            values[key] = value
        if not ped and (values["width"] <= 0 or values["length"] <= 0):
            raise ValueError(f"{field}.width/length: box sizes must be positive")
        cls[i] = c
        position[i] = (values["x"], values["y"])
        size[i] = (values["width"], values["length"])
        heading[i] = values["heading"] % (2 * math.pi)
        velocity[i] = (values["vx"], values["vy"])
        valid[i] = True
    actors = Actors(cls=cls, position=position, size=size, heading=heading, velocity=velocity,
                    valid=valid)
    actors = _numpy(canonical_order(actors, cfg))
    Scene(actors=actors, ego=make_ego(cfg)).validate(cfg, where)
    return actors


def frame_from_sample(
    actors: Actors,
    ego: Actors,
    scene_id: str,
    source: str = "scenegen sample",
    city_from_ego: np.ndarray | None = None,
) -> Frame:
    """A Frame of a sampled scene for `scenario_from_frame`.

    The map is an empty VectorMap: a cache stores only map rasters, so the exported
    scenario carries no map features. Its metadata keeps `scene_id` (the source scene of the
    map) and the ego pose in the city (`city_from_ego`), which locate the map in the
    original log. Track ids are "actor_<slot>".
    """
    a = _numpy(actors)
    idx = np.flatnonzero(a.valid)
    e = _numpy(ego)
    return Frame(
        scene_id=scene_id,
        source=source,
        cls=a.cls[idx].astype(np.int32),
        position=a.position[idx].astype(np.float64),
        size=a.size[idx].astype(np.float64),
        heading=a.heading[idx].astype(np.float64),
        velocity=a.velocity[idx].astype(np.float64),
        track_id=np.array([f"actor_{i}" for i in idx], dtype=str),
        ego_velocity=np.asarray(e.velocity, np.float64),
        ego_size=np.asarray(e.size, np.float64),
        map=VectorMap(),
        city_from_ego=np.eye(3) if city_from_ego is None else np.asarray(city_from_ego, np.float64),
    )


def _numpy(actors: Actors) -> Actors:
    return Actors(*(np.asarray(getattr(actors, f)) for f in
                    ("cls", "position", "size", "heading", "velocity", "valid")))
