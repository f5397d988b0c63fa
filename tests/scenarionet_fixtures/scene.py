"""The scene every converter fixture describes, and what importing it must give.

Each builder (`nuscenes`, `waymo`, `nuplan`, `argoverse2`) reproduces one converter's output
field by field: key names, array shapes and dtypes, type strings, where the SDC is named,
time stamps and map features, as read from
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


def expected(actor: Actor, size: tuple[float, float], zero_velocity: bool = False) -> Expected:
    a = actor.heading
    v = (0.0, 0.0) if zero_velocity else (actor.speed * np.cos(a), actor.speed * np.sin(a))
    return Expected(CLASS[actor.kind], actor.xy, a, v, size)


def true_size(actor: Actor) -> tuple[float, float]:
    return (actor.width, actor.length)

