"""Synthetic scenarios in the exact layouts ScenarioNet's converters write (for the tests).

Each builder reproduces one converter's output field by field: key names, array shapes and
dtypes, type strings, where the SDC is named, time stamps and map features, as read from
`metadriverse/scenarionet` (`scenarionet/converter/{nuscenes,waymo,nuplan,argoverse2}/utils.py`
and `type.py`) and `metadriverse/metadrive` (`metadrive/scenario/scenario_description.py`,
`metadrive/type.py`). The values are small and synthetic: one road of two lanes, four
modelled actors and one that is not, seen from an ego at a known world pose.

The scene, in the ego frame at the reference step (x forward, y left, m):
- lane A along y = 0 and lane B along y = 3.5, x in [-40, 40], both in the ego's direction;
- a painted divider at y = 1.75, road edges at y = -1.75 and y = 5.25;
- a crosswalk over x in [12, 16];
- actors moving at constant velocity along their headings (see `ACTORS`).
"""

from __future__ import annotations

import collections
import dataclasses
from typing import Any, NamedTuple

import numpy as np

from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE
from scenegen_jax.vector_map import rotation_matrix

# World pose of the ego at the reference step.
X0, Y0, TH = 1250.0, -380.0, 0.6
CLASS = {"VEHICLE": VEHICLE, "PEDESTRIAN": PEDESTRIAN, "CYCLIST": BICYCLIST}


@dataclasses.dataclass(frozen=True)
class Actor:
    """An actor at the reference step, in the ego frame; constant velocity along `heading`."""

    name: str
    kind: str  # VEHICLE / PEDESTRIAN / CYCLIST / OTHER (a type we cannot model)
    xy: tuple[float, float]
    heading: float
    speed: float
    length: float
    width: float
    valid_from: int | None = None  # first valid step, relative to the reference step


EGO = Actor("ego", "VEHICLE", (0.0, 0.0), 0.0, 5.0, 4.6, 1.9)
ACTORS = (
    Actor("car", "VEHICLE", (10.0, 0.0), 0.0, 5.0, 4.5, 1.9),
    Actor("car2", "VEHICLE", (-12.0, 3.5), 0.05, 8.0, 4.8, 2.0),
    Actor("ped", "PEDESTRIAN", (14.0, 6.5), -np.pi / 2, 1.2, 0.7, 0.6),
    Actor("bike", "CYCLIST", (-6.0, -1.0), 0.0, 4.0, 1.8, 0.7),
    Actor("static", "OTHER", (20.0, -2.5), 0.0, 0.0, 0.5, 0.5),
    Actor("late", "VEHICLE", (30.0, 3.5), 0.0, 6.0, 4.2, 1.8, valid_from=3),  # not yet valid
)
LANE_A_Y, LANE_B_Y, DIVIDER_Y, EDGE_RIGHT_Y, EDGE_LEFT_Y = 0.0, 3.5, 1.75, -1.75, 5.25
ROAD_X = np.arange(-40.0, 40.1, 2.0)
CROSSWALK = np.array([[12.0, -1.75], [16.0, -1.75], [16.0, 5.25], [12.0, 5.25]])


def world(points: Any) -> np.ndarray:
    """Ego-frame points [..., 2] at the reference step -> world frame."""
    return np.asarray(points, np.float64) @ rotation_matrix(TH).T + (X0, Y0)


def line_y(y: float, x: np.ndarray = ROAD_X) -> np.ndarray:
    """World [P, 2] of the ego-frame line at constant y."""
    return world(np.stack([x, np.full(len(x), y)], 1))


def rectangle(x0: float, x1: float, y0: float, y1: float, closed: bool = True) -> np.ndarray:
    """World ring of an ego-frame rectangle (closed as shapely writes exteriors)."""
    ring = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]] + ([[x0, y0]] if closed else [])
    return world(ring)


def xyz(points: np.ndarray, z: float = 0.0) -> np.ndarray:
    return np.concatenate([points, np.full((len(points), 1), z)], 1)


class Motion(NamedTuple):
    """World-frame states of one actor at every step (zeros where invalid, as converters do)."""

    position: np.ndarray  # [T, 2]
    heading: np.ndarray  # [T]
    velocity: np.ndarray  # [T, 2]
    valid: np.ndarray  # [T] bool


def motion(actor: Actor, times: np.ndarray, ref: int) -> Motion:
    h = TH + actor.heading
    v = actor.speed * np.array([np.cos(h), np.sin(h)])
    pos = world(actor.xy) + (times - times[ref])[:, None] * v
    first = 0 if actor.valid_from is None else ref + actor.valid_from
    valid = np.arange(len(times)) >= first
    return Motion(
        np.where(valid[:, None], pos, 0.0),
        np.where(valid, h, 0.0),
        np.where(valid[:, None], v, 0.0),
        valid,
    )


class Expected(NamedTuple):
    cls: int
    xy: tuple[float, float]
    heading: float  # ego frame, rad
    velocity: tuple[float, float]  # ego frame, m/s
    size: tuple[float, float]  # (width, length) as imported


class Fixture(NamedTuple):
    """A scenario as a converter writes it and what importing its default step must give."""

    scenario: dict
    ref: int  # the step imported by default
    ego_xy: tuple[float, float]  # the ego's position in the file's frame at `ref`
    actors: dict[str, Expected]  # by track id
    ego_size: tuple[float, float]  # (width, length)
    ego_velocity: tuple[float, float]
    dropped: collections.Counter
    crossable: tuple[tuple[float, float], ...]  # ego-frame points on crossable painted lines
    uncrossable: tuple[tuple[float, float], ...]  # ... on uncrossable lines or road edges
    sample_rate_hz: float


def _expected(actor: Actor, size: tuple[float, float], zero_velocity: bool = False) -> Expected:
    a = actor.heading
    v = (0.0, 0.0) if zero_velocity else (actor.speed * np.cos(a), actor.speed * np.sin(a))
    return Expected(CLASS[actor.kind], actor.xy, a, v, size)


def _true_size(actor: Actor) -> tuple[float, float]:
    return (actor.width, actor.length)


# ----------------------------------------------------------------------------- nuScenes

NUSCENES_TYPE = {  # MetaDrive type and nuScenes category per actor kind
    "VEHICLE": ("VEHICLE", "vehicle.car"),
    "PEDESTRIAN": ("PEDESTRIAN", "human.pedestrian.adult"),
    "CYCLIST": ("CYCLIST", "vehicle.bicycle"),
    "OTHER": ("TRAFFIC_CONE", "movable_object.trafficcone"),
}
NUSCENES_EGO_SIZE = [4.08, 1.73, 1.56]  # the converter's Renault Zoe, as [w, l, h] is read


def _token(i: int) -> str:
    return f"{i:08x}" + "c0ffee" * 4


def nuscenes(n_samples: int = 9) -> Fixture:
    """`convert_nuscenes_scenario` (current): 2 Hz keyframes interpolated to 10 Hz.

    Tracks: float64 position [T, 3], heading [T], velocity [T, 2] (forward differences of
    the positions / 0.1, zero at and before invalid steps and at the last step), valid float
    0/1 [T], length / width / height [T, 1] with length = size[1], width = size[0] of
    nuScenes' [w, l, h], the ego "ego" with size [4.08, 1.73, 1.56] (so its length 1.73 is
    shorter than its width 4.08). `metadata.sdc_id` = "ego", `ts` = np.arange(0, ..., 0.1),
    `sample_rate` 0.1, no `current_time_index`. Map: lanes LANE_SURFACE_STREET with polyline
    [N, 3] = discretize_lane poses (x, y, yaw), polygon [N, 2] (closed), entry/exit tokens;
    lane connectors LANE_SURFACE_UNSTRUCTURE without polygon; the drivable-area outline as
    "boundary_<i>" ROAD_LINE_SOLID_SINGLE_WHITE [N, 2]; lane dividers
    ROAD_LINE_BROKEN_SINGLE_WHITE, road dividers ROAD_LINE_SOLID_SINGLE_YELLOW; CROSSWALK and
    walkway ROAD_EDGE_SIDEWALK polygons [N, 2]. No traffic lights.
    """
    length = (n_samples - 1) * 5 + 1
    times = np.arange(length) * 0.1
    ref = 0
    tracks = {}
    actors = {}
    all_actors = (EGO, *ACTORS)
    for i, actor in enumerate(all_actors):
        tid = "ego" if actor is EGO else _token(i)
        m = motion(actor, times, ref)
        md_type, category = NUSCENES_TYPE[actor.kind]
        if actor is EGO:
            size = NUSCENES_EGO_SIZE
            category = "vehicle.car"
        else:
            size = [actor.width, actor.length, 1.5]
        valid = m.valid.astype(np.float64)
        vel = np.zeros((length, 2))
        vel[:-1] = np.diff(m.position, axis=0) / 0.1
        for k in range(1, length):
            if not m.valid[k]:
                vel[k] = vel[k - 1] = 0.0
        vel[-1] = 0.0
        tracks[tid] = {
            "type": md_type,
            "state": {
                "position": xyz(m.position) * valid[:, None],
                "heading": m.heading * valid,
                "velocity": vel,
                "valid": valid,
                "length": (np.full(length, size[1]) * valid)[:, None],
                "width": (np.full(length, size[0]) * valid)[:, None],
                "height": (np.full(length, size[2]) * valid)[:, None],
            },
            "metadata": {
                "track_length": length,
                "type": category,
                "object_id": tid,
                "original_id": tid,
            },
        }
        if actor is not EGO and actor.kind != "OTHER" and actor.valid_from is None:
            actors[tid] = _expected(actor, _true_size(actor))

    def lane(y: float) -> dict:
        pts = line_y(y)
        yaw = np.full((len(pts), 1), TH)
        return {
            "type": "LANE_SURFACE_STREET",
            "polyline": np.concatenate([pts, yaw], 1),
            "polygon": rectangle(-40.0, 40.0, y - 1.75, y + 1.75),
            "entry_lanes": [],
            "exit_lanes": ["connector_tok"] if y == LANE_A_Y else [],
            "left_neighbor": [],
            "right_neighbor": [],
        }

    arc = np.linspace(0, np.pi / 2, 12)
    connector = world(np.stack([40 + 10 * np.sin(arc), 10 - 10 * np.cos(arc)], 1))
    outline = rectangle(-40.0, 40.0, EDGE_RIGHT_Y, EDGE_LEFT_Y)
    map_features = {
        "boundary_0": {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": outline},
        "lane_divider_tok": {"type": "ROAD_LINE_BROKEN_SINGLE_WHITE", "polyline": line_y(1.75)},
        "road_divider_tok": {
            "type": "ROAD_LINE_SOLID_SINGLE_YELLOW",
            "polyline": line_y(EDGE_LEFT_Y + 7.0),
        },
        "ped_crossing_tok": {"type": "CROSSWALK", "polygon": world(CROSSWALK)},
        "walkway_tok": {"type": "ROAD_EDGE_SIDEWALK", "polygon": rectangle(-40, 40, 5.25, 8.25)},
        "lane_a_tok": lane(LANE_A_Y),
        "lane_b_tok": lane(LANE_B_Y),
        "connector_tok": {
            "type": "LANE_SURFACE_UNSTRUCTURE",
            "polyline": np.concatenate([connector, np.zeros((12, 1))], 1),
            "speed_limit_kmh": 100,
            "entry_lanes": ["lane_a_tok"],
            "exit_lanes": [],
        },
    }
    scenario = {
        "id": "scene-0061",
        "version": "nuscenesv1.0-mini",
        "length": length,
        "metadata": {
            "dataset": "nuscenes",
            "metadrive_processed": False,
            "map": "singapore-onenorth",
            "date": "2018-07-24",
            "coordinate": "right-handed",
            "id": "scene-0061",
            "scenario_id": "scene-0061",
            "sample_rate": 0.1,
            "ts": np.arange(0.0, (n_samples - 1) * 0.5 + 0.1, 0.1),
            "sdc_id": "ego",
        },
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": map_features,
    }
    dropped = collections.Counter(
        {"type:TRAFFIC_CONE": 1, "map:ROAD_EDGE_SIDEWALK": 1, "quirk:length_lt_width": 1}
    )
    return Fixture(
        scenario=scenario,
        ref=ref,
        ego_xy=tuple(world((0.0, 0.0))),
        actors=actors,
        ego_size=(1.73, 4.08),
        ego_velocity=(EGO.speed, 0.0),
        dropped=dropped,
        crossable=((0.0, DIVIDER_Y),),
        uncrossable=((0.0, EDGE_RIGHT_Y), (0.0, EDGE_LEFT_Y), (0.0, EDGE_LEFT_Y + 7.0)),
        sample_rate_hz=10.0,
    )


def nuscenes_keyframes(n_samples: int = 9) -> Fixture:
    """The early nuScenes converter (`convert_one_scene`): keyframes at their 2 Hz rate.

    Tracks as the current converter's, but one step per keyframe, `length = size[0]` and
    `width = size[1]` (nuScenes' width and length: every box but the ego's swapped), velocities
    never filled
    (zeros); `ts` float32 steps of 0.5 s, `sample_rate` 0.5, `metadrive_processed` True. Map:
    lanes and lane connectors both LANE_SURFACE_STREET, polyline = the list of (x, y, yaw)
    poses, polygon = the outline twice ([x, y, 0.1] ..., then [x, y, 0] ...), speed_limit_kmh;
    lane dividers ROAD_LINE_BROKEN_SINGLE_WHITE as lists of [x, y]. No edges, no crosswalks.
    """
    times = np.arange(n_samples) * 0.5
    ref = 0
    tracks, actors = {}, {}
    for i, actor in enumerate((EGO, *ACTORS)):
        tid = "ego" if actor is EGO else _token(i)
        m = motion(actor, times, ref)
        md_type, category = NUSCENES_TYPE[actor.kind]
        size = NUSCENES_EGO_SIZE if actor is EGO else [actor.width, actor.length, 1.5]
        valid = m.valid.astype(np.float64)
        tracks[tid] = {
            "type": md_type,
            "state": {
                "position": xyz(m.position) * valid[:, None],
                "heading": m.heading * valid,
                "velocity": np.zeros((n_samples, 2)),
                "valid": valid,
                "length": (np.full(n_samples, size[0]) * valid)[:, None],
                "width": (np.full(n_samples, size[1]) * valid)[:, None],
                "height": (np.full(n_samples, size[2]) * valid)[:, None],
            },
            "metadata": {
                "track_length": n_samples,
                "type": "vehicle.car" if actor is EGO else category,
                "object_id": tid,
                "original_id": tid,
            },
        }
        if actor is not EGO and actor.kind != "OTHER" and actor.valid_from is None:
            # boxes come back sorted (length >= width), the true ones; pedestrians' sizes are
            # not modelled and stay as written: (width, length) = (its length, its width)
            size = (actor.length, actor.width) if actor.kind == "PEDESTRIAN" else _true_size(actor)
            actors[tid] = _expected(actor, size, zero_velocity=True)

    def lane(y: float) -> dict:
        pts = line_y(y)
        ring = rectangle(-40.0, 40.0, y - 1.75, y + 1.75)
        polygon = [[x, yy, 0.1] for x, yy in ring] + [[x, yy, 0.0] for x, yy in ring]
        return {
            "type": "LANE_SURFACE_STREET",
            "polyline": [(x, yy, TH) for x, yy in pts],
            "polygon": polygon,
            "speed_limit_kmh": 100,
        }

    scenario = {
        "id": "cc8c0bf57f984915a77078b10eb33198",
        "version": "nuscenesv1.0-mini",
        "length": n_samples,
        "metadata": {
            "metadrive_processed": True,
            "dataset": "nuscenes",
            "map": "singapore-onenorth",
            "date": "2018-07-24",
            "coordinate": "right-handed",
            "scenario_id": "cc8c0bf57f984915a77078b10eb33198",
            "sample_rate": 0.5,
            "ts": np.asarray([0.5 * i for i in range(n_samples)], dtype=np.float32),
            "sdc_id": "ego",
        },
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": {
            "divider_tok": {
                "type": "ROAD_LINE_BROKEN_SINGLE_WHITE",
                "polyline": [list(p) for p in line_y(DIVIDER_Y)],
            },
            "lane_a_tok": lane(LANE_A_Y),
            "lane_b_tok": lane(LANE_B_Y),
        },
    }
    boxed = sum(a.kind in ("VEHICLE", "CYCLIST") and a.valid_from is None for a in ACTORS)
    dropped = collections.Counter(
        {
            "type:TRAFFIC_CONE": 1,
            # every vehicle / cyclist box; not the ego, whose [4.08, 1.73] is (length, width)
            "quirk:length_lt_width": boxed,
            "quirk:velocity_mismatch": 1,  # velocities all zero
        }
    )
    return Fixture(
        scenario=scenario,
        ref=ref,
        ego_xy=tuple(world((0.0, 0.0))),
        actors=actors,
        ego_size=(1.73, 4.08),
        ego_velocity=(0.0, 0.0),
        dropped=dropped,
        crossable=((0.0, DIVIDER_Y),),
        uncrossable=(),
        sample_rate_hz=2.0,
    )


# ----------------------------------------------------------------------------- Waymo

WAYMO_TYPE = {"VEHICLE": "VEHICLE", "PEDESTRIAN": "PEDESTRIAN", "CYCLIST": "CYCLIST"}


def waymo(ref: int = 10) -> Fixture:
    """`convert_waymo_scenario`: WOMD at 10 Hz, 91 steps, current_time_index `ref`.

    Tracks keyed by str(track id): float32 position [T, 3], length / width / height / heading
    [T], velocity [T, 2], bool valid [T]; types VEHICLE / PEDESTRIAN / CYCLIST / OTHER; track
    metadata {track_length, type, object_id, dataset}. `metadata.sdc_id` (str) and
    `metadata.sdc_track_index` (the SDC's index in `tracks`), `ts` float32, coordinate
    "waymo". Map (ids str(feature id)): lanes with polyline [N, 3] float32, `width` [N, 2]
    float32 (distances to the left / right boundary line), left/right_boundaries (dicts of
    strings naming the boundary line feature), entry/exit lanes (ints), neighbours, speed
    limits; ROAD_LINE_* and ROAD_EDGE_BOUNDARY / ROAD_EDGE_MEDIAN polylines [N, 3] float32;
    STOP_SIGN {lane, position [3]}; CROSSWALK, SPEED_BUMP and DRIVEWAY polygons [N, 3].
    Traffic lights: {type, state: {object_state: [T] of LANE_STATE_* or None}, lane,
    stop_point [3], metadata}.
    """
    length = 91
    times = (np.arange(length) * 0.1).astype(np.float32).astype(np.float64)
    tracks, actors = {}, {}
    for i, actor in enumerate((*ACTORS, EGO)):
        tid = str(300 + i)
        m = motion(actor, times, ref)
        ttype = WAYMO_TYPE.get(actor.kind, "OTHER")
        f32 = np.float32
        tracks[tid] = {
            "type": ttype,
            "state": {
                "position": xyz(m.position, 0.5).astype(f32) * m.valid[:, None],
                "length": np.where(m.valid, actor.length, 0).astype(f32),
                "width": np.where(m.valid, actor.width, 0).astype(f32),
                "height": np.where(m.valid, 1.5, 0).astype(f32),
                "heading": m.heading.astype(f32),
                "velocity": m.velocity.astype(f32),
                "valid": m.valid.copy(),
            },
            "metadata": {
                "track_length": length,
                "type": ttype,
                "object_id": tid,
                "dataset": "waymo",
            },
        }
        if actor is not EGO and actor.kind != "OTHER" and actor.valid_from is None:
            actors[tid] = _expected(actor, _true_size(actor))
    sdc_id = str(300 + len(ACTORS))

    def boundary(fid: str, line_type: str, n: int) -> list[dict]:
        return [
            {
                "lane_start_index": "0",
                "lane_end_index": str(n - 1),
                "boundary_type": line_type,
                "boundary_feature_id": fid,
            }
        ]

    def lane(y: float, left: tuple[str, str], right: tuple[str, str]) -> dict:
        pts = line_y(y)
        n = len(pts)
        return {
            "speed_limit_mph": 25.0,
            "speed_limit_kmh": 40.2336,
            "type": "LANE_SURFACE_STREET",
            "polyline": xyz(pts, 0.5).astype(np.float32),
            "interpolating": False,
            "entry_lanes": [],
            "exit_lanes": [],
            "left_boundaries": boundary(*left, n),
            "right_boundaries": boundary(*right, n),
            "left_neighbor": [],
            "right_neighbor": [],
            "width": np.full((n, 2), 1.75, np.float32),
        }

    divider = ("200", "ROAD_LINE_BROKEN_SINGLE_WHITE")
    map_features = {
        "100": lane(LANE_A_Y, divider, ("201", "UNKNOWN")),
        "101": lane(LANE_B_Y, ("202", "UNKNOWN"), divider),
        "200": {"type": divider[1], "polyline": xyz(line_y(DIVIDER_Y)).astype(np.float32)},
        "201": {"type": "ROAD_EDGE_BOUNDARY", "polyline": xyz(line_y(EDGE_RIGHT_Y)).astype("f4")},
        "202": {"type": "ROAD_EDGE_MEDIAN", "polyline": xyz(line_y(EDGE_LEFT_Y)).astype("f4")},
        "300": {"type": "CROSSWALK", "polygon": xyz(world(CROSSWALK)).astype(np.float32)},
        "301": {
            "type": "STOP_SIGN",
            "lane": [100],
            "position": np.array([*world((11.0, -1.5)), 0.0], np.float32),
        },
        "302": {"type": "SPEED_BUMP", "polygon": xyz(rectangle(25, 26, -1.75, 5.25, False))},
        "303": {"type": "DRIVEWAY", "polygon": xyz(rectangle(20, 26, 5.25, 12.0, False))},
    }
    for fid in ("300", "302", "303"):
        map_features[fid]["polygon"] = map_features[fid]["polygon"].astype(np.float32)
    lights = {
        "100": {
            "type": "TRAFFIC_LIGHT",
            "state": {"object_state": ["LANE_STATE_GO"] * 50 + [None] * (length - 50)},
            "lane": 100,
            "stop_point": np.array([*world((11.0, 0.0)), 0.0], np.float32),
            "metadata": {
                "track_length": length,
                "type": "TRAFFIC_LIGHT",
                "object_id": "100",
                "dataset": "waymo",
            },
        }
    }
    scenario = {
        "id": "1a2b3c4d5e6f7a8b",
        "version": "v1.2",
        "length": length,
        "tracks": tracks,
        "dynamic_map_states": lights,
        "map_features": map_features,
        "metadata": {
            "id": "1a2b3c4d5e6f7a8b",
            "coordinate": "waymo",
            "ts": times.astype(np.float32),
            "metadrive_processed": False,
            "sdc_id": sdc_id,
            "dataset": "waymo",
            "scenario_id": "1a2b3c4d5e6f7a8b",
            "source_file": "training.tfrecord-00000-of-01000",
            "track_length": length,
            "current_time_index": ref,
            "sdc_track_index": list(tracks).index(sdc_id),
            "objects_of_interest": [],
            "tracks_to_predict": {
                "300": {
                    "track_index": 0,
                    "track_id": "300",
                    "difficulty": 1,
                    "object_type": "VEHICLE",
                }
            },
        },
    }
    dropped = collections.Counter({"type:OTHER": 1, "map:STOP_SIGN": 1, "map:SPEED_BUMP": 1})
    return Fixture(
        scenario=scenario,
        ref=ref,
        ego_xy=tuple(world((0.0, 0.0))),
        actors=actors,
        ego_size=(EGO.width, EGO.length),
        ego_velocity=(EGO.speed, 0.0),
        dropped=dropped,
        crossable=((0.0, DIVIDER_Y),),
        uncrossable=((0.0, EDGE_RIGHT_Y), (0.0, EDGE_LEFT_Y)),
        sample_rate_hz=10.0,
    )


def metadrive_legacy(fixture: Fixture, variant: str) -> Fixture:
    """A Waymo fixture as MetaDrive's older Waymo pickles store it (womd_mini README S3 / S4).

    No `metadata` and no `length`; a top-level `ts` list and `sdc_track_index` (S3: the SDC's
    track id as an int; S4: as a str, version "old format"); `size` [T, 3] = (length, width,
    height) instead of length / width / height; heading and valid [T, 1] (S4: everything
    float64, valid 0/1 floats); lower-case `stop_sign` {lanes, pos} (S4); CROSS_WALK and
    SPEED_BUMP as polylines (S3) or polygons whose `type` is the feature dict itself (S4);
    S4's `dynamic_map_states` is [[{}]].
    """
    s = fixture.scenario
    meta = s["metadata"]
    tracks = {}
    dtype = np.float64 if variant == "S4" else np.float32
    for tid, tr in s["tracks"].items():
        st = tr["state"]
        valid = st["valid"][:, None]
        tracks[tid] = {
            "type": tr["type"],
            "state": {
                "position": st["position"].astype(dtype),
                "size": np.stack([st["length"], st["width"], st["height"]], 1).astype(dtype),
                "heading": st["heading"][:, None].astype(dtype),
                "velocity": st["velocity"].astype(dtype),
                "valid": valid.astype(np.float64) if variant == "S4" else valid,
            },
            "metadata": {
                "track_length": len(valid),
                "type": tr["type"],
                "object_id": int(tid) if variant == "S3" else tid,
            },
        }
    features = dict(s["map_features"])
    stop = features.pop("301")
    crosswalk = features.pop("300")
    bump = features.pop("302")
    features.pop("303")  # no driveways in these files
    dropped = collections.Counter(fixture.dropped)
    del dropped["map:STOP_SIGN"]
    del dropped["map:SPEED_BUMP"]
    if variant == "S3":
        features["301"] = stop
        features["300"] = {"type": "CROSS_WALK", "polyline": crosswalk["polygon"]}
        features["302"] = {"type": "SPEED_BUMP", "polyline": bump["polygon"]}
        dropped.update({"map:STOP_SIGN": 1, "map:SPEED_BUMP": 1})
        sdc_index: Any = int(meta["sdc_id"])
    else:
        features["301"] = {"type": "stop_sign", "lanes": stop["lane"], "pos": stop["position"]}
        for fid, old in (("300", crosswalk), ("302", bump)):
            feature = {"polygon": old["polygon"].astype(np.float64)}
            feature["type"] = feature  # the self-reference these files hold
            features[fid] = feature
        dropped.update({"map:stop_sign": 1, "map:malformed_type": 2})
        sdc_index = meta["sdc_id"]
    for fid in ("100", "101"):
        lane = dict(features[fid])
        lane.pop("speed_limit_kmh")
        if variant == "S4":
            lane["entry"], lane["exit"] = [], []
        features[fid] = lane
    scenario = {
        "id": s["id"],
        "version": "old format" if variant == "S4" else "MetaDrive v0.3.0.1",
        "ts": [float(t) for t in meta["ts"]],
        "sdc_track_index": sdc_index,
        "tracks": tracks,
        "dynamic_map_states": [[{}]] if variant == "S4" else {},
        "map_features": features,
    }
    return fixture._replace(scenario=scenario, dropped=dropped)


# ----------------------------------------------------------------------------- nuPlan

NUPLAN_TYPE = {
    "VEHICLE": ("VEHICLE", 0),
    "PEDESTRIAN": ("PEDESTRIAN", 1),
    "CYCLIST": ("CYCLIST", 2),
    "OTHER": ("TRAFFIC_BARRIER", 4),
}


def nuplan() -> Fixture:
    """`convert_nuplan_scenario`: 10 Hz, everything centred on the ego's first position.

    Tracks keyed by nuPlan track tokens plus "ego": float64 position [T, 3] (z = 0), heading
    [T], velocity [T, 2] (the ego's from position differences / 0.1, the last step repeating
    the one before), valid 0/1 floats [T], length / width / height [T, 1]; types VEHICLE /
    PEDESTRIAN / CYCLIST / TRAFFIC_CONE / TRAFFIC_BARRIER; track metadata {track_length,
    nuplan_type, type, object_id, nuplan_id}. `metadata.sdc_id` = "ego", `ts` = i * 0.1,
    `sample_rate` 0.1, no `current_time_index`. Map: lanes (str(int) ids) LANE_SURFACE_STREET
    with polyline [N, 2] and polygon [N, 2] and no links; each lane's left boundary as
    ROAD_LINE_BROKEN_SINGLE_WHITE [N, 2] (the converter's line type is always broken); the
    outline of roadblocks and intersections as "boundary_<i>" ROAD_LINE_SOLID_SINGLE_WHITE.
    Traffic lights keyed by lane connector id: {type, state: {object_state: [T]},
    stop_point [x, y], lane, metadata}.
    """
    length, ref = 40, 0
    times = np.arange(length) * 0.1
    center = world((0.0, 0.0))
    tracks, actors = {}, {}
    for i, actor in enumerate((*ACTORS, EGO)):
        tid = "ego" if actor is EGO else f"{i:016x}"
        m = motion(actor, times, ref)
        md_type, nuplan_type = NUPLAN_TYPE[actor.kind]
        valid = m.valid.astype(np.float64)
        pos = np.where(m.valid[:, None], m.position - center, 0.0)
        vel = m.velocity.copy()
        if actor is EGO:
            vel[:-1] = np.diff(pos, axis=0) / 0.1
            vel[-1] = vel[-2]
        tracks[tid] = {
            "type": md_type,
            "state": {
                "position": xyz(pos),
                "heading": m.heading,
                "velocity": vel,
                "valid": valid,
                "length": (np.full(length, actor.length) * valid)[:, None],
                "width": (np.full(length, actor.width) * valid)[:, None],
                "height": (np.full(length, 1.6) * valid)[:, None],
            },
            "metadata": {
                "track_length": length,
                "nuplan_type": nuplan_type,
                "type": md_type,
                "object_id": tid,
                "nuplan_id": tid,
            },
        }
        if actor is not EGO and actor.kind != "OTHER" and actor.valid_from is None:
            actors[tid] = _expected(actor, _true_size(actor))

    def lane(y: float) -> dict:
        return {
            "type": "LANE_SURFACE_STREET",
            "polyline": line_y(y) - center,
            "polygon": rectangle(-40.0, 40.0, y - 1.75, y + 1.75) - center,
        }

    map_features = {
        "48001": lane(LANE_A_Y),
        "48102": {"type": "ROAD_LINE_BROKEN_SINGLE_WHITE", "polyline": line_y(DIVIDER_Y) - center},
        "48002": lane(LANE_B_Y),
        "48103": {
            "type": "ROAD_LINE_BROKEN_SINGLE_WHITE",
            "polyline": line_y(EDGE_LEFT_Y) - center,
        },
        "boundary_0": {
            "type": "ROAD_LINE_SOLID_SINGLE_WHITE",
            "polyline": rectangle(-40.0, 40.0, EDGE_RIGHT_Y, EDGE_LEFT_Y) - center,
        },
    }
    lights = {
        "48200": {
            "type": "TRAFFIC_LIGHT",
            "state": {"object_state": ["TRAFFIC_LIGHT_GREEN"] * length},
            "stop_point": list(world((40.0, 0.0)) - center),
            "lane": "48200",
            "metadata": {
                "track_length": length,
                "type": "TRAFFIC_LIGHT",
                "object_id": "48200",
                "lane_id": "48200",
                "dataset": "nuplan",
            },
        }
    }
    scenario = {
        "id": "a1b2c3d4e5f60718",
        "version": "nuplannuplan-maps-v1.0",
        "length": length,
        "metadata": {
            "dataset": "nuplan",
            "map": "us-nv-las-vegas-strip",
            "metadrive_processed": False,
            "map_version": "nuplan-maps-v1.0",
            "log_name": "2021.07.16.20.45.29_veh-35_01095_01486",
            "scenario_extraction_info": {"scenario_name": "x", "scenario_duration": 4.0},
            "ego_vehicle_parameters": {"width": 2.297, "front_length": 4.049},
            "coordinate": "right-handed",
            "scenario_token": "a1b2c3d4e5f60718",
            "scenario_id": "a1b2c3d4e5f60718",
            "scenario_type": "following_lane_with_lead",
            "sample_rate": 0.1,
            "ts": np.asarray([i * 0.1 for i in range(length)]),
            "sdc_id": "ego",
        },
        "tracks": tracks,
        "dynamic_map_states": lights,
        "map_features": map_features,
    }
    return Fixture(
        scenario=scenario,
        ref=ref,
        ego_xy=(0.0, 0.0),  # positions are relative to the ego's first one
        actors=actors,
        ego_size=(EGO.width, EGO.length),
        ego_velocity=(EGO.speed, 0.0),
        dropped=collections.Counter({"type:TRAFFIC_BARRIER": 1}),
        crossable=((0.0, DIVIDER_Y),),
        uncrossable=((0.0, EDGE_RIGHT_Y), (0.0, EDGE_LEFT_Y)),
        sample_rate_hz=10.0,
    )


# ----------------------------------------------------------------------------- Argoverse 2

AV2_SIZE = {"VEHICLE": (4.0, 2.0), "PEDESTRIAN": (0.5, 0.5), "CYCLIST": (2.0, 0.7)}


def argoverse2(current: bool = True) -> Fixture:
    """`convert_av2_scenario`: AV2 motion forecasting, 110 steps at 10 Hz, current index 49.

    Tracks keyed by AV2 track ids ("AV" for the ego): float32 position [T, 3] (z = 0),
    heading [T], velocity [T, 2], the converter's fixed box estimates as length / width [T]
    (vehicle 4.0 x 2.0, pedestrian 0.5 x 0.5, cyclist 2.0 x 0.7, other 1 x 1; height 1),
    bool valid [T]; types VEHICLE (and BUS) / PEDESTRIAN / CYCLIST / OTHER. `metadata.sdc_id`
    "AV"; `metadata.sdc_track_index` is the index of "AV" in `tracks` (current converter) or
    the focal track's id (earlier versions); `ts` = arange(T) / 10. Map: lanes (str(int) ids)
    with polyline [N, 3] float32, `width` all zeros [N, 2], empty boundary and neighbour
    lists, entry/exit lanes as str ids; each lane's two lane marks as features
    str(id + max_id + 1) and str(id + max_id + 2) with the mark's line type (UNKNOWN_LINE for
    no paint; neighbouring lanes' ids collide, the later one wins); CROSSWALK polygons [N, 3]
    float32; the current converter adds the drivable-area outline as "boundary_<i><j>"
    ROAD_LINE_SOLID_SINGLE_WHITE pieces of 20 points [N, 2].
    """
    length, ref = 110, 49
    times = np.arange(length) / 10
    tracks, actors = {}, {}
    for i, actor in enumerate((*ACTORS, EGO)):
        tid = "AV" if actor is EGO else str(52000 + i)
        m = motion(actor, times, ref)
        ttype = actor.kind if actor.kind in AV2_SIZE else "OTHER"
        est_l, est_w = AV2_SIZE.get(ttype, (1.0, 1.0))
        f32 = np.float32
        tracks[tid] = {
            "type": ttype,
            "state": {
                "position": xyz(m.position).astype(f32),
                "length": np.where(m.valid, est_l, 0).astype(f32),
                "width": np.where(m.valid, est_w, 0).astype(f32),
                "height": np.where(m.valid, 1, 0).astype(f32),
                "heading": m.heading.astype(f32),
                "velocity": m.velocity.astype(f32),
                "valid": m.valid.copy(),
            },
            "metadata": {"track_length": length, "type": ttype, "object_id": tid, "dataset": "av2"},
        }
        if actor is not EGO and actor.kind != "OTHER" and actor.valid_from is None:
            actors[tid] = _expected(actor, (est_w, est_l))
    focal = "52000"

    max_id = 2001
    map_features: dict[str, dict] = {}
    broken, no_paint = "ROAD_LINE_BROKEN_SINGLE_WHITE", "UNKNOWN_LINE"
    lanes = {2000: (LANE_A_Y, no_paint, broken), 2001: (LANE_B_Y, broken, no_paint)}
    for seg, (y, right_type, left_type) in lanes.items():
        map_features[str(seg + max_id + 1)] = {
            "type": left_type,
            "polyline": xyz(line_y(y + 1.75)).astype(np.float32),
        }
        map_features[str(seg + max_id + 2)] = {
            "type": right_type,
            "polyline": xyz(line_y(y - 1.75)).astype(np.float32),
        }
        pts = line_y(y)
        map_features[str(seg)] = {
            "speed_limit_mph": 85.0,
            "speed_limit_kmh": 136.7942,
            "type": "LANE_SURFACE_STREET",
            "polyline": xyz(pts).astype(np.float32),
            "interpolating": True,
            "entry_lanes": [],
            "exit_lanes": [],
            "left_boundaries": [],
            "right_boundaries": [],
            "left_neighbor": [],
            "right_neighbor": [],
            "width": np.zeros((len(pts), 2), np.float32),
        }
    map_features["2000"]["exit_lanes"] = ["2002"]  # a lane outside the map's crop
    uncrossable: tuple = ()
    if current:
        x = np.arange(-40.0, 40.1, 1.0)
        ring = np.concatenate(
            [
                np.stack([x, np.full(len(x), EDGE_RIGHT_Y)], 1),
                np.stack([x[::-1], np.full(len(x), EDGE_LEFT_Y)], 1),
                [[-40.0, EDGE_RIGHT_Y]],
            ]
        )
        ring = world(ring)
        for i in range(0, len(ring), 20):
            map_features[f"boundary_0{i}"] = {
                "type": "ROAD_LINE_SOLID_SINGLE_WHITE",
                "polyline": ring[i : i + 20],
            }
        uncrossable = ((0.0, EDGE_RIGHT_Y), (0.0, EDGE_LEFT_Y))
    map_features["9001"] = {"type": "CROSSWALK", "polygon": xyz(world(CROSSWALK)).astype("f4")}
    metadata = {
        "id": "0a1b2c3d-0000-4000-8000-000000000001",
        "coordinate": "waymo",
        "ts": np.array(list(range(length))) / 10,
        "metadrive_processed": False,
        "sdc_id": "AV",
        "dataset": "av2",
        "scenario_id": "0a1b2c3d-0000-4000-8000-000000000001",
        "source_file": "0a1b2c3d-0000-4000-8000-000000000001",
        "track_length": length,
        "current_time_index": 49,
        "objects_of_interest": [],
        "sdc_track_index": list(tracks).index("AV") if current else focal,
        "tracks_to_predict": {
            focal: {"track_index": 0, "track_id": focal, "difficulty": 0, "object_type": "VEHICLE"}
        },
    }
    scenario = {
        "id": metadata["id"],
        "version": "av2",
        "length": length,
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": map_features,
        "metadata": metadata,
    }
    return Fixture(
        scenario=scenario,
        ref=ref,
        ego_xy=tuple(world((0.0, 0.0))),
        actors=actors,
        ego_size=(2.0, 4.0),
        ego_velocity=(EGO.speed, 0.0),
        dropped=collections.Counter({"type:OTHER": 1}),
        crossable=((0.0, DIVIDER_Y),),
        uncrossable=uncrossable,
        sample_rate_hz=10.0,
    )


BUILDERS = {
    "nuscenes": nuscenes,
    "nuscenes_keyframes": nuscenes_keyframes,
    "waymo": waymo,
    # no current_time_index in these: step 0 is imported by default
    "waymo_metadrive_S3": lambda: metadrive_legacy(waymo(ref=0), "S3"),
    "waymo_metadrive_S4": lambda: metadrive_legacy(waymo(ref=0), "S4"),
    "nuplan": nuplan,
    "argoverse2": argoverse2,
    "argoverse2_early": lambda: argoverse2(current=False),
}
