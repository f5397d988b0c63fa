"""The vector maps of a cache: map elements stored once, in the world frame, and per frame the
indices of the elements its map holds (layout: `cache_layout`).

A frame's map becomes flat element arrays (`frame_elements`, in a `prepare` worker): its
points in the world frame, quantised against a float64 anchor per element, and a key per
element (kind, attributes and world points rounded to `KEY_QUANTUM_M`) by which the writer
(`cache_write.CacheWriter`) stores each element of a scenario once for all its frames.
`load_map_store` reads and checks the stored arrays (errors name the file and field), and
`MapStore.frame_map` rebuilds a frame's `VectorMap` in its ego frame, its elements in their
original order: lanes, crosswalks, drivable areas, lines.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Sequence

import numpy as np

from scenegen_jax.data.cache_layout import UNREADABLE_ARRAY
from scenegen_jax.frame import within_world
from scenegen_jax.vector_map import Lane, RoadLine, VectorMap

# Element kinds, by code, in the order a frame's map lists them.
KINDS = ("lane", "crosswalk", "drivable_area", "line")
LANE, CROSSWALK, DRIVABLE_AREA, LINE = range(len(KINDS))
# Elements of two frames whose world points agree to this (m), with equal kind and
# attributes, are one stored element.
KEY_QUANTUM_M = 1e-4
# Stored points are int32 multiples of an element's `scale` (this, m, unless the element
# reaches beyond what int32 holds at it, ~1 km from its first point) from its anchor.
POINT_QUANTUM_M = 2.0**-21  # ~4.8e-7 m, a binary fraction: offset * scale is exact
INT32_MAX = 2**31 - 1
NO_CODE = -1  # an attribute the element's kind does not have

POINTS_FILE = "map_points.npy"
INDEX_FILE = "map_index.npy"
ELEMENTS_FILE = "map_elements.npz"
# Per-frame fields of actors.npz that locate a frame's elements in map_index.npy.
FRAME_FIELDS = ("map_start", "map_count", "dataset")
# meta.json's `map_vocab`: the strings that element and frame codes index.
VOCABS = ("lane_type", "mark", "dataset")

# Each array of map_elements.npz: numpy dtype kinds it may have, and its shape after the
# element axis.
ELEMENT_LAYOUT = {
    "kind": ("i", ()), "start": ("iu", ()), "count": ("iu", ()), "split": ("iu", ()),
    "lane_type": ("i", ()), "mark": ("i", (2,)), "is_intersection": ("b", ()),
    "anchor": ("f", (2,)), "scale": ("f", ()),
}
_KIND_NAMES = {"i": "integer", "iu": "integer", "b": "bool", "f": "float"}


@dataclasses.dataclass(frozen=True)
class FrameElements:
    """A frame's map as flat element arrays in the world frame, in its map's order.

    Strings stay strings here (a worker has no vocabulary); the writer codes them.
    `mark` holds a lane's (left, right) marks and a line's (mark, "").
    """

    kind: np.ndarray  # int8 [E] index into KINDS
    count: np.ndarray  # int64 [E] points per element
    split: np.ndarray  # int64 [E] a lane's left-boundary points (0 for other kinds)
    lane_type: tuple[str, ...]  # [E] ("" for other kinds)
    mark: tuple[tuple[str, str], ...]  # [E]
    is_intersection: np.ndarray  # bool [E]
    anchor: np.ndarray  # float64 [E, 2] world m, the element's first point
    scale: np.ndarray  # float64 [E] m per offset unit
    offsets: np.ndarray  # int32 [P, 2] points as multiples of `scale` from `anchor`
    keys: tuple[bytes, ...]  # [E] `element_key`
    dataset: str

    def __len__(self) -> int:
        return len(self.kind)


def quantise(points: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """(anchor [2], scale (m), int32 offsets [P, 2]) of world points [P, 2] (m): each point is
    anchor + scale * offset within scale / 2."""
    points = np.asarray(points, np.float64).reshape(-1, 2)
    if not len(points):
        return np.zeros(2), POINT_QUANTUM_M, np.zeros((0, 2), np.int32)
    anchor = points[0]
    rel = points - anchor
    scale = max(POINT_QUANTUM_M, float(np.max(np.abs(rel))) / (INT32_MAX - 1))
    return anchor, scale, np.rint(rel / scale).astype(np.int32)


def element_key(kind: int, attributes: Sequence, points: np.ndarray) -> bytes:
    """A 16-byte digest of an element's kind, attributes and world points [P, 2] rounded to
    `KEY_QUANTUM_M`: equal for elements that are one element."""
    rounded = np.rint(np.asarray(points, np.float64) / KEY_QUANTUM_M).astype(np.int64)
    h = hashlib.blake2b(digest_size=16)
    h.update(repr((kind, *attributes, rounded.shape)).encode())
    h.update(rounded.tobytes())
    return h.digest()


def frame_elements(world_map: VectorMap, where: str = "map") -> FrameElements:
    """The elements of a map in the world frame, in its order (lanes, crosswalks, drivable
    areas, lines).

    Raises:
      ValueError naming `where` and the element when a point is NaN, inf or beyond the
      world's extent (`frame.within_world`).
    """
    items = [(LANE, (lane.lane_type, lane.left_mark, lane.right_mark,
                     bool(lane.is_intersection)), [lane.left, lane.right])
             for lane in world_map.lanes]
    items += [(CROSSWALK, (), [p]) for p in world_map.crosswalks]
    items += [(DRIVABLE_AREA, (), [p]) for p in world_map.drivable_areas]
    items += [(LINE, (line.mark,), [line.points]) for line in world_map.lines]
    kinds, counts, splits, lane_types, marks, flags = [], [], [], [], [], []
    anchors, scales, offsets, keys = [], [], [], []
    for j, (kind, attrs, parts) in enumerate(items):
        parts = [np.asarray(p, np.float64).reshape(-1, 2) for p in parts]
        points = np.concatenate(parts)
        if not np.all(within_world(points)):
            raise ValueError(f"{where}: {KINDS[kind]} {j}: a point is NaN, inf or beyond the "
                             "world's extent")
        anchor, scale, q = quantise(points)
        kinds.append(kind)
        counts.append(len(points))
        splits.append(len(parts[0]) if kind == LANE else 0)
        lane_types.append(attrs[0] if kind == LANE else "")
        marks.append((attrs[1], attrs[2]) if kind == LANE else
                     (attrs[0], "") if kind == LINE else ("", ""))
        flags.append(attrs[3] if kind == LANE else False)
        anchors.append(anchor)
        scales.append(scale)
        offsets.append(q)
        keys.append(element_key(kind, (*attrs, splits[-1]), points))
    return FrameElements(
        kind=np.asarray(kinds, np.int8),
        count=np.asarray(counts, np.int64),
        split=np.asarray(splits, np.int64),
        lane_type=tuple(lane_types),
        mark=tuple(marks),
        is_intersection=np.asarray(flags, bool),
        anchor=np.asarray(anchors, np.float64).reshape(-1, 2),
        scale=np.asarray(scales, np.float64),
        offsets=np.concatenate(offsets) if offsets else np.zeros((0, 2), np.int32),
        keys=tuple(keys),
        dataset=world_map.dataset,
    )


@dataclasses.dataclass
class MapStore:
    """The map elements of one cache directory and each frame's element indices.

    `points` and `index` stay memory-mapped; `frame_map` reads only a frame's elements.
    """

    path: str  # the cache directory
    elements: dict  # map_elements.npz arrays by ELEMENT_LAYOUT field, [E, ...]
    points: np.ndarray  # int32 [P, 2] (map_points.npy)
    index: np.ndarray  # int [I] (map_index.npy)
    start: np.ndarray  # int64 [S] first entry of each frame in `index`
    count: np.ndarray  # int64 [S] entries of each frame
    dataset: np.ndarray  # int [S] index into vocab["dataset"]
    city_from_ego: np.ndarray  # float64 [S, 3, 3]
    vocab: dict  # VOCABS -> list of strings

    def __len__(self) -> int:
        return len(self.start)

    def frame_map(self, index: int) -> VectorMap:
        """The map of frame `index` in its ego frame (m), its elements in their original
        order; a lane's `id` is its stored element's index, its links are not stored."""
        n = len(self)
        i = int(index) + (n if index < 0 else 0)
        if not 0 <= i < n:
            raise IndexError(f"{self.path}: scene index {index} out of range [0, {n})")
        a = int(self.start[i])
        ids = np.asarray(self.index[a : a + int(self.count[i])], np.int64)
        m = len(ids)
        el = self.elements
        kind = el["kind"][ids]
        if np.any(np.diff(kind) < 0):
            raise ValueError(
                f"{os.path.join(self.path, INDEX_FILE)}: field map_index: scene {i}: elements "
                "not in the order lanes, crosswalks, drivable areas, lines; re-run prepare")
        counts = el["count"][ids].astype(np.int64)
        starts = el["start"][ids].astype(np.int64)
        offsets = [np.asarray(self.points[s : s + c]) for s, c in zip(starts, counts,
                                                                      strict=True)]
        q = np.concatenate(offsets).astype(np.float64) if offsets else np.zeros((0, 2))
        pose = np.asarray(self.city_from_ego[i], np.float64)
        ego_from_city = np.linalg.inv(pose)[:2, :2]
        rows = np.repeat(np.arange(m), counts)
        # Relative to the ego before rotating: world coordinates are large, offsets small.
        rel = (el["anchor"][ids] - pose[:2, 2])[rows] + el["scale"][ids][rows, None] * q
        pts = np.split(rel @ ego_from_city.T, np.cumsum(counts)[:-1]) if m else []
        lane_types, marks = self.vocab["lane_type"], self.vocab["mark"]
        lanes, crosswalks, areas, lines = [], [], [], []
        for j, e in enumerate(ids):
            k = int(kind[j])
            if k == LANE:
                s = int(el["split"][e])
                left, right = el["mark"][e]
                lanes.append(Lane(
                    id=int(e), lane_type=lane_types[el["lane_type"][e]],
                    left=pts[j][:s], right=pts[j][s:], left_mark=marks[left],
                    right_mark=marks[right], is_intersection=bool(el["is_intersection"][e])))
            elif k == CROSSWALK:
                crosswalks.append(pts[j])
            elif k == DRIVABLE_AREA:
                areas.append(pts[j])
            else:
                lines.append(RoadLine(points=pts[j], mark=marks[el["mark"][e][0]]))
        return VectorMap(lanes=tuple(lanes), crosswalks=tuple(crosswalks),
                         drivable_areas=tuple(areas), lines=tuple(lines),
                         dataset=self.vocab["dataset"][int(self.dataset[i])])

    def stored_elements(self) -> int:
        """Elements stored once for all frames."""
        return len(self.elements["kind"])


class StackedMapStore:
    """The map stores of several caches read as one: frame `i` is frame `i - offsets[c]` of
    store `c`, whose arrays stay memory-mapped."""

    def __init__(self, stores: Sequence[MapStore | StackedMapStore], offsets: np.ndarray):
        self.stores, self.offsets = list(stores), np.asarray(offsets, np.int64)

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def frame_map(self, index: int) -> VectorMap:
        """The map of frame `index` in its ego frame (`MapStore.frame_map`)."""
        n = len(self)
        i = int(index) + (n if index < 0 else 0)
        if not 0 <= i < n:
            raise IndexError(f"scene index {index} out of range [0, {n})")
        c = int(np.searchsorted(self.offsets, i, side="right")) - 1
        return self.stores[c].frame_map(i - int(self.offsets[c]))

    def stored_elements(self) -> int:
        """Elements stored by all the stores."""
        return sum(s.stored_elements() for s in self.stores)


# ---------------------------------------------------------------------------- reading


def read_vocab(meta: dict, meta_path: str) -> dict:
    """meta.json's `map_vocab` ({VOCABS name: list of strings}), checked."""
    vocab = meta.get("map_vocab")
    if not isinstance(vocab, dict):
        raise ValueError(f"{meta_path}: field map_vocab: missing or not an object")
    for name in VOCABS:
        words = vocab.get(name)
        if not isinstance(words, list) or not all(isinstance(w, str) for w in words):
            raise ValueError(f"{meta_path}: field map_vocab.{name}: expected a list of strings")
    return {name: list(vocab[name]) for name in VOCABS}


def load_map_store(path: str, meta: dict, meta_path: str, frames: dict, npz_path: str,
                   city_from_ego: np.ndarray) -> MapStore:
    """Reads and checks the map files of cache directory `path`.

    Args:
      frames: actors.npz's FRAME_FIELDS arrays ([S] each, S checked by the caller).
      npz_path: actors.npz, named in errors about `frames`.
      city_from_ego: actors.npz's poses [S, 3, 3] (checked by the caller).

    Raises:
      ValueError naming the file and field where an array is unreadable, of another dtype
      or shape, or an index, a point range or a code is out of range.
    """
    vocab = read_vocab(meta, meta_path)
    points_path, index_path = (os.path.join(path, n) for n in (POINTS_FILE, INDEX_FILE))
    elements_path = os.path.join(path, ELEMENTS_FILE)
    arrays = {}
    for name, file in (("map_points", points_path), ("map_index", index_path)):
        try:
            arrays[name] = np.load(file, mmap_mode="r", allow_pickle=False)
        except UNREADABLE_ARRAY as e:  # truncated or not an .npy file
            raise ValueError(f"{file}: field {name}: unreadable ({e}); re-run prepare") from e
    points, index = arrays["map_points"], arrays["map_index"]
    try:
        with np.load(elements_path, allow_pickle=False) as z:
            el = {k: z[k] for k in z.files}
    except UNREADABLE_ARRAY as e:
        raise ValueError(f"{elements_path}: unreadable map elements ({e}); re-run prepare") from e
    if points.dtype != np.int32 or points.ndim != 2 or points.shape[1:] != (2,):
        raise ValueError(f"{points_path}: field map_points: {points.dtype} {points.shape}, "
                         "expected int32 [P, 2]")
    if index.dtype.kind not in "iu" or index.ndim != 1:
        raise ValueError(f"{index_path}: field map_index: {index.dtype} {index.shape}, "
                         "expected integer [I]")
    _check_elements(el, elements_path, len(points), vocab, meta_path)
    _check_frames(frames, npz_path, len(index), vocab, meta_path)
    if len(index) and (int(index.min()) < 0 or int(index.max()) >= len(el["kind"])):
        bad = int(np.flatnonzero((index < 0) | (index >= len(el["kind"])))[0])
        raise ValueError(f"{index_path}: field map_index: entry {bad} is {int(index[bad])}, "
                         f"beyond the {len(el['kind'])} stored elements; re-run prepare")
    return MapStore(path=path, elements=el, points=points, index=index,
                    start=frames["map_start"].astype(np.int64),
                    count=frames["map_count"].astype(np.int64),
                    dataset=frames["dataset"], city_from_ego=city_from_ego, vocab=vocab)


def _first_bad(bad: np.ndarray) -> int:
    return int(np.flatnonzero(bad)[0])


def _check_elements(el: dict, file: str, num_points: int, vocab: dict, meta_path: str) -> None:
    """Raises ValueError naming `file` and the field where map_elements.npz is not the
    layout's (`ELEMENT_LAYOUT`) or points outside map_points.npy or codes outside the
    vocabularies."""
    missing = [k for k in ELEMENT_LAYOUT if k not in el]
    if missing:
        raise ValueError(f"{file}: missing field(s) {missing}")
    e = el["kind"].shape[0] if el["kind"].ndim else -1
    for k, (kinds, tail) in ELEMENT_LAYOUT.items():
        if el[k].dtype.kind not in kinds or el[k].shape != (e, *tail):
            raise ValueError(f"{file}: field {k}: {el[k].dtype} {el[k].shape}, expected "
                             f"{_KIND_NAMES[kinds]} {(max(e, 0), *tail)}")
    kind, start, count, split = (el[k].astype(np.int64) for k in ("kind", "start", "count",
                                                                 "split"))
    checks = [
        ("kind", (kind < 0) | (kind >= len(KINDS)), f"not a kind code 0-{len(KINDS) - 1}"),
        ("start", (start < 0) | (start > num_points), f"outside the {num_points} points of "
         f"{POINTS_FILE}"),
        ("count", (count < 0) | (count > num_points - start), f"reaches beyond the "
         f"{num_points} points of {POINTS_FILE}"),
        ("split", (split < 0) | (split > count) | ((kind != LANE) & (split != 0)),
         "not a lane's left-boundary point count"),
        ("anchor", ~within_world(el["anchor"]), "NaN, inf or beyond the world's extent"),
        ("scale", ~((el["scale"] > 0) & (el["scale"] < np.inf)), "not finite and positive"),
    ]
    lane, line = kind == LANE, kind == LINE
    codes = [("lane_type", el["lane_type"], lane, "lane_type"),
             ("mark", el["mark"][:, 0], lane | line, "mark"),
             ("mark", el["mark"][:, 1], lane, "mark")]
    for field, code, used, name in codes:
        n = len(vocab[name])
        checks.append((field, np.where(used, (code < 0) | (code >= n), code != NO_CODE),
                       f"not a code of {meta_path} map_vocab.{name} ({n} entries)"))
    for field, bad, what in checks:
        if bad.any():
            raise ValueError(f"{file}: field {field}: element {_first_bad(bad)}: {what}; "
                             "re-run prepare")


def _check_frames(frames: dict, file: str, num_index: int, vocab: dict, meta_path: str) -> None:
    """Raises ValueError naming actors.npz (`file`) and the field where a frame's element
    range lies outside map_index.npy or its dataset code outside the vocabulary."""
    for k in FRAME_FIELDS:
        v = frames[k]
        if v.dtype.kind not in "iu" or v.ndim != 1:
            raise ValueError(f"{file}: field {k}: {v.dtype} {v.shape}, expected integer [S]")
    start, count = frames["map_start"].astype(np.int64), frames["map_count"].astype(np.int64)
    n = len(vocab["dataset"])
    for field, bad, what in (
        ("map_start", (start < 0) | (start > num_index), f"outside the {num_index} entries of "
         f"{INDEX_FILE}"),
        ("map_count", (count < 0) | (count > num_index - start), f"reaches beyond the "
         f"{num_index} entries of {INDEX_FILE}"),
        ("dataset", (frames["dataset"] < 0) | (frames["dataset"] >= n),
         f"not a code of {meta_path} map_vocab.dataset ({n} entries)"),
    ):
        if bad.any():
            raise ValueError(f"{file}: field {field}: scene {_first_bad(bad)}: {what}; "
                             "re-run prepare")
