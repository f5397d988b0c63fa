"""The Argoverse 2 converter's output (`scenarionet/converter/argoverse2`), in its current
and its early version."""

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
    Fixture,
    expected,
    line_y,
    motion,
    world,
    xyz,
)

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
            actors[tid] = expected(actor, (est_w, est_l))
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
        dropped=collections.Counter({"type:OTHER": 1, "quirk:constant_boxes": 1}),
        crossable=((0.0, DIVIDER_Y),),
        uncrossable=uncrossable,
        sample_rate_hz=10.0,
    )
