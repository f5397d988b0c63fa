"""Frame: one scene as a reader produces it (unpadded, ego frame), before caching."""

from __future__ import annotations

import collections
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
      size_measured: bool [A], whether each actor's box size was measured by the source;
        None: every box was. An unmeasured size (a placeholder for drawing the actor) is
        never learnt from nor scored.
      future: float64 [A, H, 2] m, each actor's position FUTURE_HORIZONS_S later in this
        frame's ego frame (`future_positions`), NaN where its track is not observed then;
        None: the source gave no tracks (every future unknown).
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
    size_measured: np.ndarray | None = None
    future: np.ndarray | None = None

    @property
    def num_actors(self) -> int:
        return int(self.cls.shape[0])

    @property
    def measured(self) -> np.ndarray:
        """bool [A]: `size_measured`, all True when None."""
        if self.size_measured is None:
            return np.ones(self.num_actors, bool)
        return np.asarray(self.size_measured, bool)


# The times ahead (s) at which a frame records each actor's future position: the paper's
# forecasting model regresses 3 s at 0.5 s steps (supplementary 2.2).
FUTURE_HORIZONS_S = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
# Two samples of a track count as FUTURE_HORIZONS_S apart when they are within this of it:
# the Argoverse 2 sensor logs' annotation times jitter by a few ms around 10 Hz.
FUTURE_TOLERANCE_S = 0.04


def future_positions(world_xy: np.ndarray, valid: np.ndarray, times_s: np.ndarray, step: int,
                     city_from_ego: np.ndarray) -> np.ndarray:
    """Positions [N, H, 2] m of N tracks FUTURE_HORIZONS_S after sample `step`, in the ego
    frame of the pose `city_from_ego` [3, 3]; NaN where a track has no valid, finite sample
    within FUTURE_TOLERANCE_S of that time (or the samples end first).

    Args:
      world_xy: float [N, T, 2] m, the tracks' positions in the world frame at each sample.
      valid: bool [N, T], which samples of each track are observed.
      times_s: float [T] s, the samples' times, increasing.
      step: the frame's sample index into T.
    """
    world_xy = np.asarray(world_xy, np.float64)
    times_s = np.asarray(times_s, np.float64)
    out = np.full((world_xy.shape[0], len(FUTURE_HORIZONS_S), 2), np.nan)
    want = times_s[step] + np.asarray(FUTURE_HORIZONS_S)
    at = np.clip(np.searchsorted(times_s, want), 1, len(times_s) - 1)
    at = np.where(np.abs(times_s[at - 1] - want) < np.abs(times_s[at] - want), at - 1, at)
    found = np.abs(times_s[at] - want) <= FUTURE_TOLERANCE_S
    pose = np.asarray(city_from_ego, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        local = (world_xy[:, at] - pose[:2, 2]) @ pose[:2, :2]  # R^T (x - t)
    seen = np.asarray(valid, bool)[:, at] & found & np.all(np.isfinite(local), axis=-1)
    out[seen] = local[seen]
    return out


# Beyond these a row is damaged, not a road user, in every source: boxes longer or wider
# than MAX_SIZE_M (articulated buses are ~18 m) and speeds above MAX_SPEED_MPS (360 km/h).
MAX_SIZE_M = 30.0
MAX_SPEED_MPS = 100.0
# Beyond this |x| or |y| (m) a world coordinate is damaged, not a place: the data sets' world
# frames (UTM zones, city frames) span at most about 1e6 m, and relative positions taken
# between coordinates near 1e300 round to 0 (every actor at the ego).
MAX_WORLD_M = 1e7


def within_world(points: np.ndarray) -> np.ndarray:
    """bool [...] of points [..., 2] m: finite and within MAX_WORLD_M in x and y."""
    return np.all(np.abs(np.asarray(points, np.float64)) <= MAX_WORLD_M, axis=-1)


def speed(velocity: np.ndarray) -> np.ndarray:
    """[...] m/s of velocities [..., 2] m/s; inf, not an overflow warning, beyond float64."""
    with np.errstate(over="ignore"):
        return np.hypot(*np.moveaxis(np.asarray(velocity, np.float64), -1, 0))


def size_beyond_limits(size: np.ndarray) -> np.ndarray:
    """bool [...] of box sizes [..., 2] (width, length) m: a side beyond MAX_SIZE_M (or NaN)."""
    return ~np.all(np.asarray(size, np.float64) <= MAX_SIZE_M, axis=-1)


def speed_beyond_limits(velocity: np.ndarray) -> np.ndarray:
    """bool [...] of velocities [..., 2] m/s: a speed beyond MAX_SPEED_MPS (or NaN)."""
    return ~(speed(velocity) <= MAX_SPEED_MPS)


def drop_beyond_limits(frame: Frame) -> tuple[Frame, collections.Counter]:
    """The frame without the actors whose box or speed is beyond the limits above, and their
    count by reason ("invalid:size", "invalid:speed").

    Raises:
      ValueError naming the frame's source, scene and field when the ego is beyond them, or
      its world position (`city_from_ego`) beyond MAX_WORLD_M.
    """
    where = f"{frame.source}: scene {frame.scene_id}"
    ego_xy = np.asarray(frame.city_from_ego, np.float64)[:2, 2]
    if not within_world(ego_xy):
        raise ValueError(f"{where}: ego position: ({ego_xy[0]:.4g}, {ego_xy[1]:.4g}) m in the "
                         f"world frame, beyond {MAX_WORLD_M:g} m")
    ego_size = np.asarray(frame.ego_size, np.float64)
    if size_beyond_limits(ego_size):
        raise ValueError(f"{where}: ego width/length: {ego_size.tolist()} m, beyond "
                         f"{MAX_SIZE_M:g} m")
    if speed_beyond_limits(frame.ego_velocity):
        raise ValueError(f"{where}: ego velocity: speed {float(speed(frame.ego_velocity)):.4g} "
                         f"m/s, beyond {MAX_SPEED_MPS:g} m/s")
    too_big = size_beyond_limits(np.reshape(frame.size, (-1, 2)))
    too_fast = ~too_big & speed_beyond_limits(np.reshape(frame.velocity, (-1, 2)))
    drops = +collections.Counter({"invalid:size": int(too_big.sum()),
                                  "invalid:speed": int(too_fast.sum())})
    keep = ~(too_big | too_fast)
    if keep.all():
        return frame, drops
    fields = ("cls", "position", "size", "heading", "velocity", "track_id")
    kept = {f: getattr(frame, f)[keep] for f in fields}
    if frame.size_measured is not None:
        kept["size_measured"] = frame.measured[keep]
    if frame.future is not None:
        kept["future"] = frame.future[keep]
    return dataclasses.replace(frame, **kept), drops
