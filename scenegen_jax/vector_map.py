"""A vector HD map (host side, numpy): lanes, lines, crosswalks and drivable areas in one frame.

Argoverse 2 gives lanes with both boundaries and their painted marks, and drivable-area
polygons. Waymo and nuScenes give lane centrelines, painted lines and road edges that belong
to no lane, and no drivable-area polygon; their readers keep the lines as `RoadLine`s and build
lane outlines and the drivable area with `scenegen_jax.data.surface`, so that every source
fills the same raster channels with the same meaning.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

LANE_TYPES = ("VEHICLE", "BIKE", "BUS")
ROAD_EDGE = "ROAD_EDGE"  # the mark of a kerb or road edge: never crossable


def is_crossable(mark_type: str) -> bool | None:
    """Whether a painted lane mark may be crossed; None when there is no painted mark."""
    mark = mark_type.upper()
    if mark in ("NONE", "UNKNOWN", ""):
        return None
    return "DASH" in mark or "BROKEN" in mark


@dataclasses.dataclass(frozen=True)
class Lane:
    """A lane segment.

    Attributes:
      id: lane id.
      lane_type: one of LANE_TYPES.
      left, right: [P, 2] boundary polylines (m), both in the direction of travel.
      left_mark, right_mark: painted mark types (Argoverse 2 names, e.g. "SOLID_WHITE").
      is_intersection: lane lies inside an intersection.
      successors, predecessors: ids of connected lanes.
    """

    id: int
    lane_type: str
    left: np.ndarray
    right: np.ndarray
    left_mark: str = "NONE"
    right_mark: str = "NONE"
    is_intersection: bool = False
    successors: tuple[int, ...] = ()
    predecessors: tuple[int, ...] = ()

    @property
    def centerline(self) -> np.ndarray:
        """[P, 2] centreline: mean of the two boundaries resampled to a common length."""
        n = max(len(self.left), len(self.right), 2)
        return 0.5 * (resample_polyline(self.left, n) + resample_polyline(self.right, n))

    @property
    def polygon(self) -> np.ndarray:
        """[P, 2] closed lane outline: left boundary then the right one reversed."""
        return np.concatenate([self.left, self.right[::-1]], axis=0)


@dataclasses.dataclass(frozen=True)
class RoadLine:
    """A painted line or a road edge that belongs to no single lane.

    Attributes:
      points: [P, 2] polyline, m.
      mark: Argoverse 2 mark name ("SOLID_WHITE", "DASHED_YELLOW", ...), `ROAD_EDGE` for a
        kerb or road edge, or "UNKNOWN" for a painted line of unknown type.
    """

    points: np.ndarray
    mark: str


@dataclasses.dataclass(frozen=True)
class VectorMap:
    """Lanes, standalone lines, crosswalk and drivable-area polygons (all [P, 2] arrays, m),
    and the data set the map comes from, as ScenarioNet names it ("" where its files do not
    say; the `dataset` map layers know those of `config.DATASETS`)."""

    lanes: tuple[Lane, ...] = ()
    crosswalks: tuple[np.ndarray, ...] = ()
    drivable_areas: tuple[np.ndarray, ...] = ()
    lines: tuple[RoadLine, ...] = ()
    dataset: str = ""

    def transform(self, rotation: np.ndarray, translation: np.ndarray) -> VectorMap:
        """Applies p -> rotation @ p + translation to every point."""
        rot = np.asarray(rotation, np.float64)
        trans = np.asarray(translation, np.float64)

        def f(points: np.ndarray) -> np.ndarray:
            return points @ rot.T + trans

        lanes = tuple(
            dataclasses.replace(lane, left=f(lane.left), right=f(lane.right)) for lane in self.lanes
        )
        return dataclasses.replace(  # the fields without points (`dataset`) as they are
            self,
            lanes=lanes,
            crosswalks=tuple(f(p) for p in self.crosswalks),
            drivable_areas=tuple(f(p) for p in self.drivable_areas),
            lines=tuple(dataclasses.replace(line, points=f(line.points)) for line in self.lines),
        )

    @functools.cached_property
    def _boxes(self) -> dict[str, np.ndarray]:
        """Per element kind, the [N, 4] boxes (min x, min y, max x, max y) of its elements,
        computed once per map (readers crop one map for every frame)."""

        def boxes(arrays) -> np.ndarray:
            if not arrays:
                return np.zeros((0, 4))
            return np.array([np.concatenate([a.min(axis=0), a.max(axis=0)]) for a in arrays])

        return {
            "lanes": boxes([np.concatenate([lane.left, lane.right]) for lane in self.lanes]),
            "crosswalks": boxes(self.crosswalks),
            "drivable_areas": boxes(self.drivable_areas),
            "lines": boxes([line.points for line in self.lines]),
        }

    def marked_lines(self) -> list[tuple[np.ndarray, bool]]:
        """(polyline [P, 2], crossable) of every painted line the map draws: the lanes' left
        boundaries, their right ones, then the standalone lines (at least 2 points), each
        with a painted mark (`is_crossable` not None)."""
        marked = [(lane.left, lane.left_mark) for lane in self.lanes]
        marked += [(lane.right, lane.right_mark) for lane in self.lanes]
        marked += [(line.points, line.mark) for line in self.lines if len(line.points) >= 2]
        return [(points, kind) for points, mark in marked
                if (kind := is_crossable(mark)) is not None]

    def crop(self, center: np.ndarray, radius: float) -> VectorMap:
        """Keeps the elements with a point within `radius` m (box test) of `center`."""
        c = np.asarray(center, np.float64)

        def keep(kind: str) -> tuple:
            b = self._boxes[kind]
            near = np.all(b[:, :2] <= c + radius, axis=1) & np.all(b[:, 2:] >= c - radius, axis=1)
            items = getattr(self, kind)
            return tuple(items[i] for i in np.flatnonzero(near))

        return dataclasses.replace(self, **{kind: keep(kind) for kind in self._boxes})


def distinct_points(points: np.ndarray, tol_m: float = 1e-9) -> np.ndarray:
    """bool [P]: the points of a polyline [P, 2] that do not repeat the previous one (within
    `tol_m`); the first point always counts."""
    keep = np.ones(len(points), bool)
    keep[1:] = np.linalg.norm(np.diff(points, axis=0), axis=1) > tol_m
    return keep


def resample_polyline(points: np.ndarray, n: int) -> np.ndarray:
    """n points equally spaced by arc length along a polyline [P, 2]."""
    points = np.asarray(points, np.float64)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return np.repeat(points[:1], n, axis=0)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, points[:, 0]), np.interp(t, s, points[:, 1])], axis=1)


def resample_polylines(lines: list[np.ndarray], counts: np.ndarray) -> list[np.ndarray]:
    """`resample_polyline` of many polylines at once: counts[i] points along lines[i] ([P, 2]
    each), in one interpolation over their arc lengths laid end to end (each line's own
    length range apart from the next by 1 m)."""
    if not lines:
        return []
    pts = [np.asarray(p, np.float64) for p in lines]
    seg = [np.hypot(*np.diff(p, axis=0).T) for p in pts]
    total = np.array([x.sum() for x in seg])
    offset = np.concatenate([[0.0], np.cumsum(total + 1.0)[:-1]])
    s = np.concatenate([np.concatenate([[0.0], np.cumsum(x)]) + o
                        for x, o in zip(seg, offset, strict=True)])
    counts = np.asarray(counts, np.int64)
    which = np.repeat(np.arange(len(pts)), counts)
    first = np.cumsum(counts) - counts
    k = np.arange(len(which)) - first[which]
    frac = k / np.maximum(counts[which] - 1, 1)
    t = offset[which] + frac * total[which]
    xy = np.concatenate(pts)
    out = np.stack([np.interp(t, s, xy[:, 0]), np.interp(t, s, xy[:, 1])], axis=1)
    return np.split(out, np.cumsum(counts)[:-1])


def centerlines(lanes) -> list[np.ndarray]:
    """`Lane.centerline` of every lane, computed together (`resample_polylines`)."""
    counts = np.array([max(len(ln.left), len(ln.right), 2) for ln in lanes], np.int64)
    left = resample_polylines([ln.left for ln in lanes], counts)
    right = resample_polylines([ln.right for ln in lanes], counts)
    return [0.5 * (a + b) for a, b in zip(left, right, strict=True)]


def rotation_matrix(theta: float) -> np.ndarray:
    """2x2 counter-clockwise rotation by theta rad."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def se2_pose(x: float, y: float, theta: float) -> np.ndarray:
    """[3, 3] homogeneous SE(2) pose: rotation by theta rad, then translation (x, y)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])
