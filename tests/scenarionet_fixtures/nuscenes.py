"""The nuScenes converter's output (`scenarionet/converter/nuscenes`), with every sample or
with key frames only."""

from __future__ import annotations

import collections

import numpy as np

from .scene import (
    ACTORS,
    CROSSWALK,
    DIVIDER_Y,
    EDGE_LEFT_Y,
    EDGE_RIGHT_Y,
    EGO,
    LANE_A_Y,
    LANE_B_Y,
    TH,
    Fixture,
    expected,
    line_y,
    motion,
    rectangle,
    true_size,
    world,
    xyz,
)

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
            actors[tid] = expected(actor, true_size(actor))

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
            size = (actor.length, actor.width) if actor.kind == "PEDESTRIAN" else true_size(actor)
            actors[tid] = expected(actor, size, zero_velocity=True)

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
