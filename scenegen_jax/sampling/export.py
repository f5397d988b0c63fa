"""Host-side conversions of sampled scenes: JSON records, given-actor parsing, Frames for the
ScenarioNet exporter. Pure functions over numpy; the CLI does the file I/O.

JSON actor record (units m, rad, m/s; ego frame, x forward, y left):
  {"class": "vehicle" | "pedestrian" | "bicyclist", "x", "y", "width", "length", "heading",
   "vx", "vy"}
Pedestrians carry the nominal footprint (`cfg.grid.pedestrian_size_m`) and their walking
direction as heading; on input their width, length and heading may be omitted.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.frame import (
    MAX_SIZE_M,
    MAX_SPEED_MPS,
    Frame,
    size_beyond_limits,
    speed,
    speed_beyond_limits,
)
from scenegen_jax.geometry import boxes_overlap
from scenegen_jax.jsonfile import parse_json
from scenegen_jax.scene import (
    CLASS_NAMES,
    PEDESTRIAN,
    Actors,
    Scene,
    canonical_order,
    in_region,
    make_ego,
    wrap_angle,
)
from scenegen_jax.vector_map import VectorMap

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


def road_user_problem(values: Mapping[str, float]) -> str | None:
    """Why an actor record's numbers (`RECORD_FIELDS`) are no road user, as "FIELDS: reason":
    beyond the limits every reader drops actors at (`frame.MAX_SIZE_M`,
    `frame.MAX_SPEED_MPS`); None if they are one."""
    box = np.array([values["width"], values["length"]])
    if size_beyond_limits(box):
        return f"width/length: ({box[0]:g}, {box[1]:g}) m, beyond {MAX_SIZE_M:g} m"
    velocity = np.array([values["vx"], values["vy"]])
    if speed_beyond_limits(velocity):
        return f"vx/vy: speed {float(speed(velocity)):.4g} m/s, beyond {MAX_SPEED_MPS:g} m/s"
    return None


def actors_from_records(
    records: Sequence[Mapping[str, Any]],
    cfg: Config,
    where: str,
    ego_sizes: np.ndarray | None = None,
    allow_overlap: bool = False,
) -> Actors:
    """Actors [N = cfg.grid.max_actors] (numpy, canonical order) from JSON records.

    Args:
      records: actor records (module docstring); `actors[i]` in errors is records[i].
      cfg: the model's config.
      where: what errors name first, e.g. "given.jsonl:3" (file and line).
      ego_sizes: [E, 2] (width, length) m of the egos the actors will meet, each at the
        origin with heading 0 (default: cfg.grid.ego_size_m).
      allow_overlap: keep boxes that overlap each other or an ego (`check_overlaps`).

    Raises ValueError naming `where` and the field for unknown classes, missing values or
    values that are not finite numbers (true/false and strings are not numbers),
    non-positive box sizes, boxes or speeds beyond the readers' road-user limits
    (`road_user_problem`), actors outside the region, more than N actors, and (unless
    `allow_overlap`) overlapping boxes.
    """
    n = cfg.grid.max_actors
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
        if not isinstance(name, str) or name not in CLASS_NAMES:
            raise ValueError(f"{field}.class: {name!r} is not one of {CLASS_NAMES}")
        c = CLASS_NAMES.index(name)
        ped = c == PEDESTRIAN
        values = {}
        for key in RECORD_FIELDS:
            default = {"width": cfg.grid.pedestrian_size_m, "length": cfg.grid.pedestrian_size_m,
                       "heading": 0.0}.get(key) if ped else None
            value = rec.get(key, default)
            if value is None:
                raise ValueError(f"{field}.{key}: missing")
            values[key] = _number(value, f"{field}.{key}")
        if not ped and (values["width"] <= 0 or values["length"] <= 0):
            raise ValueError(f"{field}.width/length: box sizes must be positive")
        if problem := road_user_problem(values):
            raise ValueError(f"{field}.{problem}")
        if not in_region(np.array([values["x"], values["y"]]), cfg.grid):
            raise ValueError(f"{field}.x/y: ({values['x']:g}, {values['y']:g}) m lies outside "
                             f"the {cfg.grid.region_m:g} m region around the ego")
        cls[i] = c
        position[i] = (values["x"], values["y"])
        size[i] = (values["width"], values["length"])
        heading[i] = wrap_angle(values["heading"])
        velocity[i] = (values["vx"], values["vy"])
        valid[i] = True
    actors = Actors(cls=cls, position=position, size=size, heading=heading, velocity=velocity,
                    valid=valid)
    if not allow_overlap:
        sizes = np.asarray(cfg.grid.ego_size_m if ego_sizes is None else ego_sizes, np.float64)
        check_overlaps(actors, sizes.reshape(-1, 2), where)
    actors = _numpy(canonical_order(actors, cfg.grid))
    Scene(actors=actors, ego=make_ego(cfg.grid.ego_size_m)).validate(cfg.grid, where)
    return actors


FLOAT32_MAX = float(np.finfo(np.float32).max)


def _number(value: Any, field: str) -> float:
    """A finite JSON number as a float; ValueError naming `field` for anything else."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{field}: not a number ({value!r})")
    try:
        value = float(value)
    except OverflowError as e:  # a JSON integer beyond float range
        raise ValueError(f"{field}: out of range") from e
    if not math.isfinite(value):
        raise ValueError(f"{field}: NaN or inf")
    if abs(value) > FLOAT32_MAX:  # the actor arrays are float32: it would become inf there
        raise ValueError(f"{field}: out of range")
    return value


def check_overlaps(actors: Actors, ego_sizes: np.ndarray, where: str) -> None:
    """Raises ValueError naming `where` and the actors if boxes overlap.

    Tests the valid vehicle and bicyclist boxes of `actors` [N] against each other and
    against egos at the origin with heading 0, one per row of `ego_sizes` [E, 2] (width,
    length) m. Pedestrians are points here, as in the sampler's collision rejection; boxes
    that only touch do not overlap. `actors[i]` in errors is slot i.
    """
    a = _numpy(actors)
    boxed = np.flatnonzero(a.valid & (a.cls != PEDESTRIAN))
    pos, size = a.position.astype(np.float64), a.size.astype(np.float64)
    head = a.heading.astype(np.float64)
    hint = "; pass --allow-overlap to keep overlapping given actors"
    for ego_size in ego_sizes:
        hit = boxes_overlap(np.zeros(2), ego_size, 0.0, pos[boxed], size[boxed], head[boxed])
        if hit.any():
            i = boxed[np.argmax(hit)]
            raise ValueError(
                f"{where}: actors[{i}] ({_describe(a, i)}) overlaps the ego (width "
                f"{ego_size[0]:g} m, length {ego_size[1]:g} m at the origin){hint}"
            )
    for k, i in enumerate(boxed[:-1]):
        rest = boxed[k + 1:]
        hit = boxes_overlap(pos[i], size[i], head[i], pos[rest], size[rest], head[rest])
        if hit.any():
            j = rest[np.argmax(hit)]
            raise ValueError(
                f"{where}: actors[{i}] ({_describe(a, i)}) and actors[{j}] "
                f"({_describe(a, j)}) overlap{hint}"
            )


def _describe(a: Actors, i: int) -> str:
    x, y = a.position[i]
    return f"{CLASS_NAMES[int(a.cls[i])]} at x={x:g} m, y={y:g} m"


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


def given_from_lines(lines: Iterable[str | bytes], path: str, cfg: Config, scene_ego_sizes,
                     allow_overlap: bool = False) -> list:
    """Given actors (numpy Actors [N]) of each non-blank line of a `sample --given` file:
    `lines` are its lines, `path` its name for the errors.

    Line j of L lines conditions scenes j, j + L, ...; `scene_ego_sizes` [num scenes, 2]
    (width, length) m are the egos of the scenes to sample, so each line's boxes are checked
    against the egos it meets (and each other) unless `allow_overlap`. Errors name the file,
    the line and the field.
    """
    rows = []
    for line_no, line in enumerate(lines, 1):
        if not line.strip():
            continue
        where = f"{path}:{line_no}"
        row = parse_json(line, where)
        if not isinstance(row, dict) or "actors" not in row:
            raise ValueError(f'{where}: actors: missing (expected {{"actors": [...]}})')
        rows.append((where, row["actors"]))
    if not rows:
        raise ValueError(f"{path}: no given scenes")
    sizes = np.asarray(scene_ego_sizes, np.float64).reshape(-1, 2)
    return [
        actors_from_records(records, cfg, where, np.unique(sizes[j :: len(rows)], axis=0),
                            allow_overlap)
        for j, (where, records) in enumerate(rows)
    ]
