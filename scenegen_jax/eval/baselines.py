"""Heuristic baselines of the paper (supplementary sec. 2.1): Prob. Grammar and Procedural.

Both place vehicles and bicyclists on the lanes of the HD map (no pedestrians: the maps have
no sidewalks), conditioned on a Frame-like input: an object with `map` (VectorMap in the ego
frame: x forward, y left, m), `ego_size` ((width, length), m) and `ego_velocity` (m/s; kept
for the common interface, neither heuristic uses it). The ego sits at the origin heading
along +x and is an obstacle like any actor. Randomness comes from an explicit
`numpy.random.Generator`; the output is a numpy `Actors` padded to `cfg.grid.max_actors`, valid
slots first in canonical order, every centre inside the region of interest, no two boxes
(the ego's included) overlapping. Lanes of type VEHICLE and BUS carry vehicles, BIKE lanes
bicyclists.

The Argoverse 2 maps carry no speed limits, so one hand-tuned limit per class stands in for
"the lane segment's speed limit". Every hand-tuned number is a module constant below.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any

import jax
import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.eval.mmd import scene_arrays
from scenegen_jax.geometry import box_corners, boxes_overlap  # noqa: F401  (public here too)
from scenegen_jax.scene import BICYCLIST, VEHICLE, Actors, canonical_order, wrap_angle
from scenegen_jax.vector_map import VectorMap

LANE_CLASS = {"VEHICLE": VEHICLE, "BUS": VEHICLE, "BIKE": BICYCLIST}

# ---- shared hand-tuned numbers
# Hand-tuned: AV2 maps have no speed limits; 25 mph urban limit, ~18 km/h for bicycles.
SPEED_LIMIT_MS = {VEHICLE: 11.2, BICYCLIST: 5.0}
# Hand-tuned: lanes with a centreline point within this of the region are used, so that
# traffic enters the region from outside and leaders just outside it count (Procedural).
LANE_MARGIN_M = 10.0

# ---- Prob. Grammar (hand-tuned prior)
# Hand-tuned: the maximum actor count of a lane segment is uniform on {0, ..., this}.
GRAMMAR_MAX_ACTORS_PER_LANE = 3
# Hand-tuned: mean bumper-to-bumper clearance between successive actors, m (exponential).
GRAMMAR_CLEARANCE_MEAN_M = {VEHICLE: 6.0, BICYCLIST: 3.0}
# Hand-tuned: lateral offset from the centreline, uniform on [-this, this] m.
GRAMMAR_LATERAL_OFFSET_M = 0.3
# Hand-tuned: box (width, length) ranges, m, uniform per dimension.
GRAMMAR_SIZE_RANGE_M = {
    VEHICLE: ((1.7, 2.2), (3.8, 5.6)),
    BICYCLIST: ((0.5, 0.9), (1.5, 2.0)),
}
# Hand-tuned: heading (and velocity direction) noise about the lane direction, uniform, rad.
GRAMMAR_HEADING_NOISE_RAD = 0.1
# Hand-tuned: speed = min(uniform sample on this range, speed limit), m/s.
GRAMMAR_SPEED_RANGE_MS = {VEHICLE: (0.0, 15.0), BICYCLIST: (0.0, 6.0)}

# ---- Procedural (hand-tuned rules)
# Hand-tuned: mean bumper-to-bumper clearance to the actor ahead on a route, m (exponential).
PROCEDURAL_CLEARANCE_MEAN_M = {VEHICLE: 12.0, BICYCLIST: 8.0}
# Hand-tuned: mean time gap to the leader, s (exponential): speed = min(limit, gap / time gap).
PROCEDURAL_TIME_GAP_MEAN_S = 1.5
# Hand-tuned: how far ahead along the lane graph a leader is looked for, m; an actor with no
# leader within it drives at the speed limit.
PROCEDURAL_LEADER_HORIZON_M = 100.0
# Hand-tuned: the ego is a leader on lanes whose centreline passes within this (m) of it and
# whose direction is within EGO_LANE_ANGLE_RAD of the ego's.
EGO_LANE_DISTANCE_M = 1.5
EGO_LANE_ANGLE_RAD = np.pi / 4


@dataclasses.dataclass(frozen=True)
class _Path:
    """A lane centreline with cumulative arc length (zero-length segments removed)."""

    points: np.ndarray  # [P, 2] m
    s: np.ndarray  # [P] m

    @classmethod
    def of(cls, points: np.ndarray) -> _Path:
        points = np.asarray(points, np.float64)
        seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
        keep = np.r_[True, seg > 1e-6]
        points = points[keep]
        s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
        return cls(points, s)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, s: float) -> tuple[np.ndarray, float]:
        """(point [2] m, tangent direction rad) at arc length s."""
        i = int(np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 2))
        d = self.points[i + 1] - self.points[i]
        t = (s - self.s[i]) / max(self.s[i + 1] - self.s[i], 1e-9)
        return self.points[i] + t * d, float(np.arctan2(d[1], d[0]))


@dataclasses.dataclass(frozen=True)
class _LaneGraph:
    """The usable lanes near the region: paths, classes and successor indices."""

    paths: list[_Path]
    cls: list[int]
    successors: list[list[int]]
    predecessors: list[list[int]]


def _lane_graph(vmap: VectorMap, region_m: float) -> _LaneGraph:
    reach = region_m / 2 + LANE_MARGIN_M
    lanes = []
    for lane in vmap.lanes:
        if lane.lane_type not in LANE_CLASS:
            continue
        outline = lane.polygon
        if np.any(outline.min(axis=0) > reach) or np.any(outline.max(axis=0) < -reach):
            continue  # bounding box misses the region (plus margin)
        path = _Path.of(lane.centerline)
        if len(path.points) < 2:
            continue
        lanes.append((lane, path))
    index = {lane.id: i for i, (lane, _) in enumerate(lanes)}
    cls = [LANE_CLASS[lane.lane_type] for lane, _ in lanes]
    succ: list[set[int]] = [set() for _ in lanes]
    for i, (lane, _) in enumerate(lanes):
        for j in (index[x] for x in lane.successors if x in index):
            succ[i].add(j)
        for j in (index[x] for x in lane.predecessors if x in index):
            succ[j].add(i)
    succ = [{j for j in s if cls[j] == cls[i] and j != i} for i, s in enumerate(succ)]
    pred: list[list[int]] = [[] for _ in lanes]
    for i, s in enumerate(succ):
        for j in s:
            pred[j].append(i)
    return _LaneGraph(
        paths=[p for _, p in lanes],
        cls=cls,
        successors=[sorted(s) for s in succ],
        predecessors=[sorted(p) for p in pred],
    )


class _Placement:
    """Accepted boxes (the ego first) and their attributes; rejects overlapping candidates."""

    def __init__(self, ego_size: np.ndarray):
        self.center = [np.zeros(2)]
        self.size = [np.asarray(ego_size, np.float64)]
        self.heading = [0.0]
        self.cls: list[int] = []
        self.speed: list[float] = []
        self.lane: list[int] = []
        self.s: list[float] = []  # arc length of the centre along its lane, m

    def try_add(self, center, size, heading, cls, speed=0.0, lane=-1, s=0.0) -> bool:
        hit = boxes_overlap(
            center,
            size,
            heading,
            np.array(self.center).reshape(-1, 2),
            np.array(self.size).reshape(-1, 2),
            np.array(self.heading),
        )
        if hit.any():
            return False
        self.center.append(np.asarray(center, np.float64))
        self.size.append(np.asarray(size, np.float64))
        self.heading.append(float(heading))
        self.cls.append(int(cls))
        self.speed.append(float(speed))
        self.lane.append(int(lane))
        self.s.append(float(s))
        return True

    def actors(self, rng: np.random.Generator, cfg: Config, velocity_heading=None) -> Actors:
        """The accepted actors inside the region, at most cfg.grid.max_actors (random subset)."""
        center = np.array(self.center[1:]).reshape(-1, 2)
        half = cfg.grid.region_m / 2
        inside = np.flatnonzero(np.all((center >= -half) & (center < half), axis=-1))
        if len(inside) > cfg.grid.max_actors:
            inside = np.sort(rng.choice(inside, cfg.grid.max_actors, replace=False))
        heading = np.array(self.heading[1:])[inside]
        vel_dir = heading if velocity_heading is None else np.asarray(velocity_heading)[inside]
        speed = np.array(self.speed)[inside]
        return pad_actors(
            cls=np.array(self.cls, np.int32)[inside],
            position=center[inside],
            size=np.array(self.size[1:]).reshape(-1, 2)[inside],
            heading=heading,
            velocity=speed[:, None] * np.stack([np.cos(vel_dir), np.sin(vel_dir)], -1),
            cfg=cfg,
        )


def pad_actors(cls, position, size, heading, velocity, cfg: Config) -> Actors:
    """numpy Actors padded to cfg.grid.max_actors, valid first, in canonical order."""
    n, slots = len(cls), cfg.grid.max_actors
    if n > slots:
        raise ValueError(f"{n} actors do not fit in max_actors={slots}")

    def pad(x, shape, dtype):
        out = np.zeros((slots, *shape), dtype)
        out[:n] = np.asarray(x, dtype).reshape((n, *shape))
        return out

    h = pad(wrap_angle(np.asarray(heading, np.float32)), (), np.float32)
    actors = Actors(
        cls=pad(cls, (), np.int32),
        position=pad(position, (2,), np.float32),
        size=pad(size, (2,), np.float32),
        heading=h,
        velocity=pad(velocity, (2,), np.float32),
        valid=np.arange(slots) < n,
    )
    return jax.tree.map(np.asarray, canonical_order(actors, cfg.grid))


# ------------------------------------------------------------------------ Prob. Grammar
def prob_grammar(rng: np.random.Generator, frame: Any, cfg: Config) -> Actors:
    """Prob. Grammar: actors on lane segments with a hand-crafted prior.

    Scene -> Lanes; Lane -> Actors. Per lane segment (in random order): a maximum count
    uniform on {0..GRAMMAR_MAX_ACTORS_PER_LANE}; actors placed along the centreline from its
    start with exponential clearances; class from the lane type; uniform lateral offset, box
    size, heading noise about the lane direction; speed min(uniform, limit).

    Args:
      rng: numpy random generator.
      frame: Frame-like (`map`, `ego_size`, `ego_velocity`), ego frame.
      cfg: config (region_m, max_actors, grid for the canonical order).

    Returns:
      numpy Actors [cfg.grid.max_actors], vehicles and bicyclists only.
    """
    graph = _lane_graph(frame.map, cfg.grid.region_m)
    placed = _Placement(frame.ego_size)
    half = cfg.grid.region_m / 2
    vel_heading: list[float] = []
    for i in rng.permutation(len(graph.paths)):
        path, cls = graph.paths[i], graph.cls[i]
        n_max = int(rng.integers(0, GRAMMAR_MAX_ACTORS_PER_LANE + 1))
        (w_lo, w_hi), (l_lo, l_hi) = GRAMMAR_SIZE_RANGE_M[cls]
        s_front, count = 0.0, 0  # s_front: front of the previous actor's gap, m
        while count < n_max:
            size = np.array([rng.uniform(w_lo, w_hi), rng.uniform(l_lo, l_hi)])
            s = s_front + rng.exponential(GRAMMAR_CLEARANCE_MEAN_M[cls]) + size[1] / 2
            if s > path.length:
                break
            s_front = s + size[1] / 2
            count += 1
            point, direction = path.at(s)
            offset = rng.uniform(-GRAMMAR_LATERAL_OFFSET_M, GRAMMAR_LATERAL_OFFSET_M)
            center = point + offset * np.array([-np.sin(direction), np.cos(direction)])
            heading = direction + rng.uniform(-GRAMMAR_HEADING_NOISE_RAD, GRAMMAR_HEADING_NOISE_RAD)
            speed = min(rng.uniform(*GRAMMAR_SPEED_RANGE_MS[cls]), SPEED_LIMIT_MS[cls])
            if not np.all((center >= -half) & (center < half)):
                continue  # outside the region: not part of the scene
            if placed.try_add(center, size, heading, cls, speed, int(i), s):
                vel_heading.append(heading)
    return placed.actors(rng, cfg, vel_heading)


# ------------------------------------------------------------------------ Procedural
@dataclasses.dataclass(frozen=True)
class SizeKDE:
    """Gaussian KDE of log box sizes per class, as scipy.stats.gaussian_kde (Scott's rule).

    Attributes:
      log_sizes: class -> [n, 2] training log (width, length), log m.
      kernel_cov: class -> [2, 2] kernel covariance: data covariance (ddof 1) * n^(-1/3)
        (Scott's factor n^(-1/(d+4)) squared, d = 2).
    """

    log_sizes: dict
    kernel_cov: dict

    def sample(self, rng: np.random.Generator, cls: int, n: int) -> np.ndarray:
        """[n, 2] box (width, length) m: a training sample plus kernel noise, in log space."""
        if cls not in self.log_sizes:
            raise ValueError(
                f"size KDE has no training boxes of class {cls}; fit it on data with at least two"
            )
        data = self.log_sizes[cls]
        chol = np.linalg.cholesky(self.kernel_cov[cls] + 1e-12 * np.eye(2))
        picks = data[rng.integers(0, len(data), n)]
        return np.exp(picks + rng.standard_normal((n, 2)) @ chol.T)


def _iter_scenes(scenes: Any) -> Iterable[Any]:
    valid = getattr(scenes, "valid", None)
    if valid is not None and np.ndim(valid) == 2:  # batched Actors [S, N]
        for i in range(np.shape(valid)[0]):
            yield jax.tree.map(lambda x, i=i: np.asarray(x)[i], scenes)
    else:
        yield from scenes


def fit_size_kde(train_scenes: Any, region_m: float | None = None) -> SizeKDE:
    """Fits the per-class box-size KDE (vehicles and bicyclists) on training scenes.

    Args:
      train_scenes: iterable of scenes (Frames, Actors, dicts; see `mmd.scene_arrays`) or a
        batched Actors [S, N].
      region_m: if given, only actors inside the region of this side (m) count.

    Returns:
      SizeKDE; a class with fewer than two training boxes is left out. Boxes the source did
      not measure (placeholders) are not fitted.
    """
    sizes: dict[int, list[np.ndarray]] = {VEHICLE: [], BICYCLIST: []}
    for scene in _iter_scenes(train_scenes):
        a = scene_arrays(scene, region_m)
        for c in sizes:
            keep = (a["cls"] == c) & a["size_measured"]
            sizes[c].append(np.asarray(a["size"], np.float64).reshape(-1, 2)[keep])
    log_sizes, kernel_cov = {}, {}
    for c, rows in sizes.items():
        x = np.log(np.concatenate(rows)) if rows else np.zeros((0, 2))
        if len(x) < 2:
            continue
        log_sizes[c] = x
        kernel_cov[c] = np.cov(x, rowvar=False) * len(x) ** (-2.0 / 6.0)
    if VEHICLE not in log_sizes:
        raise ValueError("fit_size_kde: need at least two training vehicles")
    return SizeKDE(log_sizes, kernel_cov)


def _lane_chains(rng: np.random.Generator, graph: _LaneGraph) -> list[list[int]]:
    """Routes covering the lane graph once: chains of successive lanes (random at forks)."""
    free = set(range(len(graph.paths)))
    chains = []
    while free:
        starts = sorted(i for i in free if not any(p in free for p in graph.predecessors[i]))
        chain = [int(rng.choice(starts or sorted(free)))]
        free.discard(chain[0])
        while nxt := [j for j in graph.successors[chain[-1]] if j in free]:
            chain.append(int(rng.choice(nxt)))
            free.discard(chain[-1])
        chains.append(chain)
    return chains


def _ego_on_lanes(graph: _LaneGraph) -> list[tuple[int, float]]:
    """(lane, arc length of the ego's projection) for lanes the ego drives along."""
    out = []
    for i, path in enumerate(graph.paths):
        p, d = path.points[:-1], np.diff(path.points, axis=0)
        t = np.clip(np.einsum("pd,pd->p", -p, d) / np.einsum("pd,pd->p", d, d), 0.0, 1.0)
        dist = np.linalg.norm(p + t[:, None] * d, axis=1)
        k = int(np.argmin(dist))
        angle = abs(np.angle(np.exp(1j * np.arctan2(d[k, 1], d[k, 0]))))
        if dist[k] < EGO_LANE_DISTANCE_M and angle < EGO_LANE_ANGLE_RAD:
            out.append((i, float(path.s[k] + t[k] * (path.s[k + 1] - path.s[k]))))
    return out


def _gap_to_leader(
    graph: _LaneGraph,
    on_lane: list[list[tuple[float, float]]],
    lane: int,
    s: float,
    half_length: float,
) -> float:
    """Bumper gap (m) to the nearest actor ahead along any successor path, or inf."""
    best = np.inf
    stack = [(lane, s, -s)]  # (lane, search from arc length, offset of lane start from actor)
    seen = set()
    while stack:
        i, s_from, offset = stack.pop()
        ahead = [(sj, hj) for sj, hj in on_lane[i] if sj > s_from + 1e-6]
        if ahead:
            sj, hj = min(ahead)
            best = min(best, offset + sj - half_length - hj)
            continue
        end = offset + graph.paths[i].length
        if end >= min(best, PROCEDURAL_LEADER_HORIZON_M):
            continue
        for j in graph.successors[i]:
            if (j, end) not in seen:
                seen.add((j, end))
                stack.append((j, -np.inf, end))
    return max(best, 0.0)


def procedural(rng: np.random.Generator, frame: Any, cfg: Config, size_kde: SizeKDE) -> Actors:
    """Procedural: rules on the lane graph.

    Routes: chains of successive lanes (successors only, so no wrong-way merges) covering every
    lane near the region once. Along each route, actors follow the centreline with exponential
    bumper clearances, boxes from the size KDE, heading the centreline tangent; boxes that
    overlap an earlier actor or the ego are skipped. Speed: min(limit, gap / time gap) with an
    exponential time gap and the gap to the nearest actor (or the ego) ahead along the lane
    graph (nearest over forks); no leader within PROCEDURAL_LEADER_HORIZON_M -> the limit.

    Args:
      rng: numpy random generator.
      frame: Frame-like (`map`, `ego_size`, `ego_velocity`), ego frame.
      cfg: config (region_m, max_actors, grid for the canonical order).
      size_kde: from `fit_size_kde` on training scenes.

    Returns:
      numpy Actors [cfg.grid.max_actors], vehicles and bicyclists only.
    """
    graph = _lane_graph(frame.map, cfg.grid.region_m)
    placed = _Placement(frame.ego_size)
    for chain in _lane_chains(rng, graph):
        cls = graph.cls[chain[0]]
        offsets = np.r_[0.0, np.cumsum([graph.paths[i].length for i in chain])]
        s_front = 0.0  # chain arc length of the front bumper of the previous actor, m
        while True:
            size = size_kde.sample(rng, cls, 1)[0]
            s = s_front + rng.exponential(PROCEDURAL_CLEARANCE_MEAN_M[cls]) + size[1] / 2
            if s > offsets[-1]:
                break
            k = int(np.clip(np.searchsorted(offsets, s, side="right") - 1, 0, len(chain) - 1))
            point, direction = graph.paths[chain[k]].at(s - offsets[k])
            # A rejected (overlapping) actor leaves its slot empty; the next is spaced from it.
            placed.try_add(point, size, direction, cls, 0.0, chain[k], s - offsets[k])
            s_front = s + size[1] / 2
    # Speeds from time gaps to the leader (the ego counts as one on its lanes).
    on_lane: list[list[tuple[float, float]]] = [[] for _ in graph.paths]
    for lane, s, size in zip(placed.lane, placed.s, placed.size[1:], strict=True):
        on_lane[lane].append((s, size[1] / 2))
    for lane, s in _ego_on_lanes(graph):
        on_lane[lane].append((s, float(placed.size[0][1]) / 2))
    for a in range(len(placed.cls)):
        limit = SPEED_LIMIT_MS[placed.cls[a]]
        gap = _gap_to_leader(graph, on_lane, placed.lane[a], placed.s[a], placed.size[a + 1][1] / 2)
        tau = rng.exponential(PROCEDURAL_TIME_GAP_MEAN_S)
        placed.speed[a] = float(min(limit, gap / max(tau, 1e-6)))
    return placed.actors(rng, cfg)
