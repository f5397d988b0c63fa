"""The Waymo converter's output (`scenarionet/converter/waymo`), and MetaDrive's older Waymo
pickles."""

from __future__ import annotations

import collections
from typing import Any

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
    Fixture,
    expected,
    line_y,
    motion,
    rectangle,
    true_size,
    world,
    xyz,
)

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
            actors[tid] = expected(actor, true_size(actor))
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
