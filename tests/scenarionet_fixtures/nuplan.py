"""The nuPlan converter's output (`scenarionet/converter/nuplan`)."""

from __future__ import annotations

import collections

import numpy as np

from .scene import (
    ACTORS,
    DIVIDER_Y,
    EDGE_LEFT_Y,
    EDGE_RIGHT_Y,
    EGO,
    LANE_A_Y,
    LANE_B_Y,
    Fixture,
    expected,
    line_y,
    motion,
    rectangle,
    true_size,
    world,
    xyz,
)

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
            actors[tid] = expected(actor, true_size(actor))

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
