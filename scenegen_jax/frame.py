"""Frame: one scene as a reader produces it (unpadded, ego frame), before caching."""

from __future__ import annotations

import dataclasses

import numpy as np

from scenegen_jax.vector_map import VectorMap


@dataclasses.dataclass
class Frame:
    """One annotated frame in the ego frame (x forward, y left, m), as read from a source.

    Attributes:
      scene_id: unique id, e.g. "<log id>/<timestamp ns>".
      source: file the actors came from (for error messages).
      cls: int32 [A] VEHICLE / PEDESTRIAN / BICYCLIST.
      position: float64 [A, 2] m.
      size: float64 [A, 2] (width, length) m.
      heading: float64 [A] rad in [0, 2pi).
      velocity: float64 [A, 2] m/s over the ground.
      track_id: str [A] track ids (for export and debugging).
      ego_velocity: float64 [2] m/s, ego velocity in its own frame.
      ego_size: float64 [2] (width, length) m.
      map: VectorMap in the ego frame.
      city_from_ego: float64 [3, 3] SE(2) pose of the ego in the map's world frame.
    """

    scene_id: str
    source: str
    cls: np.ndarray
    position: np.ndarray
    size: np.ndarray
    heading: np.ndarray
    velocity: np.ndarray
    track_id: np.ndarray
    ego_velocity: np.ndarray
    ego_size: np.ndarray
    map: VectorMap
    city_from_ego: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))

    @property
    def num_actors(self) -> int:
        return int(self.cls.shape[0])
