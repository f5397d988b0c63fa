"""Two hand-made inputs: a Frame with every kind of actor and map element (`hand_frame`), and
a scenario with the standard keys only, as ScenarioNet's converters write them
(`standard_scenario`)."""

from __future__ import annotations

import numpy as np

from scenegen_jax.frame import Frame
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE
from scenegen_jax.vector_map import ROAD_EDGE, Lane, RoadLine, VectorMap


def hand_frame() -> Frame:
    """Two actors of each class, a curved lane, a bus lane, a crosswalk, a drivable area, a road
    edge and a painted line."""
    lane = Lane(
        id=7,
        lane_type="VEHICLE",
        left=np.array([[-20.0, 1.9], [0.0, 1.8], [20.0, 2.5], [30.0, 4.0]]),
        right=np.array([[-20.0, -1.7], [0.0, -1.8], [25.0, -1.0]]),
        left_mark="DASHED_WHITE",
        right_mark="SOLID_YELLOW",
        is_intersection=False,
        successors=(8,),
        predecessors=(3, 4),
    )
    bus = Lane(
        id=8,
        lane_type="BUS",
        left=np.array([[30.0, 4.0], [40.0, 9.0]]),
        right=np.array([[25.0, -1.0], [38.0, 5.0]]),
        left_mark="NONE",
        right_mark="DOUBLE_DASH_WHITE",
        is_intersection=True,
        predecessors=(7,),
    )
    vmap = VectorMap(
        lanes=(lane, bus),
        crosswalks=(np.array([[5.0, -6.0], [8.0, -6.0], [8.0, 6.0], [5.0, 6.0]]),),
        drivable_areas=(np.array([[-30.0, -10.0], [40.0, -10.0], [40.0, 12.0], [-30.0, 12.0]]),),
        lines=(
            RoadLine(np.array([[-30.0, -9.5], [40.0, -9.7]]), ROAD_EDGE),
            RoadLine(np.array([[-30.0, 5.4], [0.0, 5.5], [30.0, 5.45]]), "DOUBLE_DASH_YELLOW"),
        ),
    )
    cls = np.array([VEHICLE, PEDESTRIAN, BICYCLIST, VEHICLE, PEDESTRIAN, BICYCLIST], np.int32)
    return Frame(
        scene_id="log_a/315967376859506000",
        source="hand",
        cls=cls,
        position=np.array(
            [[10.0, 3.5], [-4.2, 7.9], [15.5, -2.0], [-18.0, -3.3], [6.0, -7.0], [30.1, 5.5]]
        ),
        size=np.array([[1.9, 4.6], [0.6, 0.5], [0.7, 1.8], [2.1, 5.2], [0.5, 0.5], [0.8, 1.9]]),
        heading=np.array([0.1, 3.0, 6.2831, 4.5, 0.0, 1.2]),
        velocity=np.array([[5.0, 0.5], [0.0, -1.2], [4.0, -0.1], [-3.0, 0.0], [0.3, 0.3], [2, 4]]),
        track_id=np.array(["veh_a", "ped_a", "cyc_a", "veh_b", "ped_b", "cyc_b"]),
        ego_velocity=np.array([7.5, -0.2]),
        ego_size=np.array([1.95, 4.9]),
        map=vmap,
        city_from_ego=np.array([[0.6, -0.8, 1200.0], [0.8, 0.6, -350.5], [0.0, 0.0, 1.0]]),
    )


def standard_scenario(t_len: int = 3) -> dict:
    """A scenario shaped like ScenarioNet's converters write it: standard keys only, world frame."""

    def track(ttype, xy, heading, velocity, length=4.5, width=2.0, valid=None):
        """Constant per-step values; `xy` may also be a [T, 2] array."""
        positions = np.broadcast_to(np.asarray(xy, np.float32), (t_len, 2))
        return {
            "type": ttype,
            "state": {
                "position": np.concatenate([positions, np.zeros((t_len, 1), np.float32)], 1),
                "length": np.full(t_len, length, np.float32),
                "width": np.full(t_len, width, np.float32),
                "height": np.full(t_len, 1.5, np.float32),
                "heading": np.full(t_len, heading, np.float32),
                "velocity": np.tile(np.asarray(velocity, np.float32), (t_len, 1)),
                "valid": np.ones(t_len, bool) if valid is None else np.asarray(valid),
            },
            "metadata": {"track_length": t_len, "type": ttype, "object_id": "x", "dataset": "av2"},
        }

    ts = np.arange(t_len)
    sdc_xy = np.stack([100.0 + ts, 50.0 + 0 * ts], 1)  # 1 m per step along world +x
    ped_valid = [True] * (t_len - 1) + [False]
    tracks = {
        "AV": track("VEHICLE", sdc_xy, np.pi / 2, [0.0, 10.0]),
        "11": track("VEHICLE", [100.0, 60.0], 0.0, [0.0, 0.0], length=4.6),
        "12": track("PEDESTRIAN", [95.0, 50.0], 0.0, [1.0, 0.0], 0.5, 0.5, valid=ped_valid),
        "13": track("OTHER", [90.0, 40.0], 0.0, [0.0, 0.0]),
        "14": track("CYCLIST", [101.0, 45.0], 4.0, [0.0, 0.0], 1.8, 0.7),
    }
    center = np.array([[100.0, 20.0, 0.0], [100.0, 40.0, 0.0], [100.0, 80.0, 0.0]], np.float32)
    map_features = {
        "201": {
            "type": "LANE_SURFACE_STREET",
            "polyline": center,
            "interpolating": True,
            "entry_lanes": ["200"],
            "exit_lanes": ["202"],
            "left_boundaries": [],
            "right_boundaries": [],
            "left_neighbor": [],
            "right_neighbor": [],
            "width": np.zeros((3, 2), np.float32),
        },
        "202": {
            "type": "LANE_BIKE_LANE",
            "polyline": np.array([[100.0, 80.0], [100.0, 80.0], [90.0, 90.0]], np.float32),
            "entry_lanes": ["201"],
            "exit_lanes": [],
        },
        "300": {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": center + [2.0, 0.0, 0.0]},
        "400": {
            "type": "CROSSWALK",
            "polygon": np.array([[95, 55, 0], [105, 55, 0], [105, 58, 0], [95, 58, 0]], np.float32),
        },
    }
    metadata = {
        "id": "scn",
        "coordinate": "waymo",
        "ts": ts / 10,
        "metadrive_processed": False,
        "sdc_id": "AV",
        "dataset": "av2",
        "scenario_id": "scn",
        "current_time_index": 1,
    }
    return {
        "id": "scn",
        "version": "v2",
        "length": t_len,
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": map_features,
        "metadata": metadata,
    }
