"""Writing a preprocessing cache (layout: `cache_layout`): each frame's map moved into the
world frame and its actors padded (`encode_frame`), appended by a `CacheWriter`, which stores
each map element once for all the frames that share it and whose `close` writes the arrays
and meta.json; `write_cache` does it all in this process."""

from __future__ import annotations

import collections
import dataclasses
import functools
import json
import logging
import os
from collections.abc import Iterable

import numpy as np

from scenegen_jax import locks
from scenegen_jax.config import Config
from scenegen_jax.data.cache_layout import (
    ACTOR_FIELDS,
    CACHE_VERSION,
    FUTURE_FIELD,
    RASTER_FILE,
    cache_slots,
    canvas_radius,
)
from scenegen_jax.data.map_store import (
    ELEMENTS_FILE,
    INDEX_FILE,
    INT32_MAX,
    LANE,
    LINE,
    NO_CODE,
    POINTS_FILE,
    VOCABS,
    FrameElements,
    frame_elements,
)
from scenegen_jax.files import written_whole
from scenegen_jax.frame import FUTURE_HORIZONS_S, Frame
from scenegen_jax.raster.map import ALL_MAP_CHANNELS
from scenegen_jax.scene import CLASS_NAMES, in_region

log = logging.getLogger(__name__)


@dataclasses.dataclass
class Summary:
    """What `prepare` wrote and dropped (printed as one JSON line).

    `actors` counts actors inside the region of interest per class, `outside_region` the rows
    of modelled classes outside it (kept in the cache only as far as rotations can reach), so
    actors + outside_region is every row of a modelled class that was read. `bad_files`
    counts files that could not be read, by reason (their names are in the log and in
    `bad_file_list`). `size_unmeasured` counts, per class, the in-region actors whose box
    size the source did not measure (`Frame.size_measured`): their box term is never
    learnt or scored.
    """

    scenes: int = 0
    actors: dict = dataclasses.field(default_factory=lambda: {c: 0 for c in CLASS_NAMES})
    dropped: dict = dataclasses.field(default_factory=dict)
    outside_region: dict = dataclasses.field(default_factory=lambda: {c: 0 for c in CLASS_NAMES})
    size_unmeasured: dict = dataclasses.field(default_factory=lambda: {c: 0 for c in CLASS_NAMES})
    overflow: int = 0
    empty_scenes: int = 0
    files: int = 0
    bad_files: dict = dataclasses.field(default_factory=dict)
    bad_file_list: list = dataclasses.field(default_factory=list)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass
class EncodedFrame:
    """A frame as the cache stores it: its map's elements in the world frame and padded
    actors, with counts."""

    scene_id: str
    map: FrameElements
    actors: dict  # padded arrays by ACTOR_FIELDS
    ego_velocity: np.ndarray  # [2] m/s
    ego_size: np.ndarray  # [2] m
    city_from_ego: np.ndarray  # [3, 3]
    inside: dict  # in-region actors per class name
    outside: dict  # disc actors outside the region per class name
    unmeasured: dict  # in-region actors without a measured box size per class name
    overflow: int


def encode_frame(frame: Frame, cfg: Config) -> EncodedFrame:
    """Pads one frame's actors and moves its map into the world frame (`city_from_ego`), where
    the frames of one scenario share its elements (runs in `prepare`'s workers)."""
    padded, inside, overflow = pad_frame_actors(frame, cfg, cache_slots(cfg))
    pose = np.asarray(frame.city_from_ego, np.float64)
    world_map = frame.map.transform(pose[:2, :2], pose[:2, 2])
    return EncodedFrame(
        scene_id=frame.scene_id,
        map=frame_elements(world_map, f"{frame.source}: scene {frame.scene_id}: map"),
        actors=padded,
        ego_velocity=np.asarray(frame.ego_velocity, np.float32),
        ego_size=np.asarray(frame.ego_size, np.float32),
        city_from_ego=pose,
        inside={n: int(np.sum(inside & (frame.cls == c))) for c, n in enumerate(CLASS_NAMES)},
        outside={n: int(np.sum(~inside & (frame.cls == c))) for c, n in enumerate(CLASS_NAMES)},
        unmeasured={n: int(np.sum(inside & ~frame.measured & (frame.cls == c)))
                    for c, n in enumerate(CLASS_NAMES)},
        overflow=overflow,
    )


class _NpyAppender:
    """Writes a .npy array a few leading-axis items at a time, so the map arrays never sit
    in memory.

    The header is written first with room for any count and rewritten with the real one at
    `close` (same length, padded with spaces, as the .npy format allows).
    """

    HEADER_BYTES = 256

    def __init__(self, path: str, item_shape: tuple[int, ...], dtype) -> None:
        self.path, self.item_shape, self.dtype = path, item_shape, np.dtype(dtype)
        self.count = 0
        self.tmp = f"{path}.{os.getpid()}.tmp"  # this process's own, whoever else writes
        self.file = open(self.tmp, "wb")  # noqa: SIM115 (closed in close())
        self.file.write(self._header(0))

    def _header(self, count: int) -> bytes:
        shape = (count, *self.item_shape)
        text = repr({"descr": self.dtype.str, "fortran_order": False, "shape": shape})
        body = self.HEADER_BYTES - 10  # magic (6) + version (2) + length (2)
        text = text.ljust(body - 1) + "\n"
        return b"\x93NUMPY\x01\x00" + body.to_bytes(2, "little") + text.encode("latin1")

    def extend(self, items: np.ndarray) -> None:
        """Appends items [n, *item_shape]."""
        items = np.ascontiguousarray(items, self.dtype).reshape(-1, *self.item_shape)
        self.file.write(items.tobytes())
        self.count += len(items)

    def close(self) -> None:
        self.file.seek(0)
        self.file.write(self._header(self.count))
        self.file.close()
        os.replace(self.tmp, self.path)

    def discard(self) -> None:
        """Closes and removes the unfinished file (any earlier `path` stays as it was)."""
        self.file.close()
        if os.path.exists(self.tmp):
            os.remove(self.tmp)


class _Vocab:
    """Strings coded by their order of first appearance (stored in meta.json)."""

    def __init__(self) -> None:
        self.words: list[str] = []
        self._codes: dict[str, int] = {}

    def code(self, word: str) -> int:
        if word not in self._codes:
            self._codes[word] = len(self.words)
            self.words.append(word)
        return self._codes[word]


class _ElementTable:
    """The map elements a `CacheWriter` stores: each element key once, its points streamed
    into `points` (map_points.npy), its other fields kept until `arrays`.

    Keys of the last SHARED_ELEMENTS elements seen are remembered (memory stays bounded on
    any cache; a scenario's or log's frames arrive together, in file order, so its elements
    are stored once).
    """

    SHARED_ELEMENTS = 1 << 20

    def __init__(self, points: _NpyAppender) -> None:
        self.points = points
        self.seen: collections.OrderedDict[bytes, int] = collections.OrderedDict()
        self.vocab = {name: _Vocab() for name in VOCABS}
        self.parts: dict = collections.defaultdict(list)
        self.count = 0

    def add(self, fe: FrameElements) -> np.ndarray:
        """Stores the frame's elements not yet stored; returns its element indices [E]."""
        ids = np.empty(len(fe), np.int64)
        new = []
        for j, key in enumerate(fe.keys):
            if key in self.seen:
                self.seen.move_to_end(key)
                ids[j] = self.seen[key]
                continue
            if self.count >= INT32_MAX:
                raise ValueError(f"{os.path.dirname(self.points.path)}: more than {INT32_MAX} "
                                 "map elements in one cache; prepare it in shards (--shard I/N)")
            ids[j] = self.seen[key] = self.count
            self.count += 1
            new.append(j)
            if len(self.seen) > self.SHARED_ELEMENTS:
                self.seen.popitem(last=False)
        if new:
            self._store(fe, np.asarray(new))
        return ids

    def _store(self, fe: FrameElements, new: np.ndarray) -> None:
        self.parts["start"].append(self.points.count + np.cumsum(fe.count[new]) - fe.count[new])
        is_new = np.zeros(len(fe), bool)
        is_new[new] = True
        self.points.extend(fe.offsets[np.repeat(is_new, fe.count)])
        kinds = fe.kind[new]
        lane_type, mark = self.vocab["lane_type"], self.vocab["mark"]
        self.parts["kind"].append(kinds)
        self.parts["count"].append(fe.count[new])
        self.parts["split"].append(fe.split[new])
        self.parts["lane_type"].append(np.array(
            [lane_type.code(fe.lane_type[j]) if k == LANE else NO_CODE
             for j, k in zip(new, kinds, strict=True)], np.int32))
        self.parts["mark"].append(np.array(
            [[mark.code(fe.mark[j][0]), mark.code(fe.mark[j][1])] if k == LANE else
             [mark.code(fe.mark[j][0]), NO_CODE] if k == LINE else [NO_CODE, NO_CODE]
             for j, k in zip(new, kinds, strict=True)], np.int32).reshape(-1, 2))
        self.parts["is_intersection"].append(fe.is_intersection[new])
        self.parts["anchor"].append(fe.anchor[new])
        self.parts["scale"].append(fe.scale[new])

    def arrays(self) -> dict:
        """The map_elements.npz arrays of every stored element ([E, ...])."""
        empty = {"kind": np.zeros(0, np.int8), "start": np.zeros(0, np.int64),
                 "count": np.zeros(0, np.int64), "split": np.zeros(0, np.int64),
                 "lane_type": np.zeros(0, np.int32), "mark": np.zeros((0, 2), np.int32),
                 "is_intersection": np.zeros(0, bool), "anchor": np.zeros((0, 2)),
                 "scale": np.zeros(0)}
        return {k: np.concatenate([v, *self.parts[k]]).astype(v.dtype)
                for k, v in empty.items()}


class CacheWriter:
    """Appends encoded frames to a cache directory; `close` writes the arrays and meta.json.

    Used as a context manager, which holds the directory's lock (`locks.exclusive` on
    OUT/.lock: a second writer is refused, naming this one's pid and host): when the block
    raises (a bad file under `--strict`, no scenes, an interrupt) or ends without `close`,
    the unfinished map files are removed and a cache already in the directory is left whole.
    """

    def __init__(self, out_dir: str, cfg: Config, source: dict | None = None) -> None:
        os.makedirs(out_dir, exist_ok=True)
        self.out_dir, self.cfg, self.source = out_dir, cfg, source or {}
        self._lock = locks.acquire(self._lock_path, f"writing the cache {out_dir}")
        self.summary = Summary()
        self.streams: list[_NpyAppender] = []
        try:
            self.points = self._stream(POINTS_FILE, (2,), np.int32)
            self.index = self._stream(INDEX_FILE, (), np.int32)
        except BaseException:
            self._discard()
            locks.release(self._lock_path, self._lock)
            raise
        self.elements = _ElementTable(self.points)
        self.arrays: dict = collections.defaultdict(list)
        self.ids: list[str] = []

    def _stream(self, name: str, item_shape: tuple[int, ...], dtype) -> _NpyAppender:
        self.streams.append(_NpyAppender(os.path.join(self.out_dir, name), item_shape, dtype))
        return self.streams[-1]

    def _discard(self) -> None:
        for stream in self.streams:
            stream.discard()

    @property
    def _lock_path(self) -> str:
        return os.path.join(self.out_dir, locks.LOCK_FILE)

    def __enter__(self) -> CacheWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self._discard()  # a no-op after `close`; else the unfinished files go
        finally:
            locks.release(self._lock_path, self._lock)

    def add(self, enc: EncodedFrame) -> None:
        self.arrays["map_start"].append(self.index.count)
        self.arrays["map_count"].append(len(enc.map))
        self.arrays["dataset"].append(self.elements.vocab["dataset"].code(enc.map.dataset))
        self.index.extend(self.elements.add(enc.map))
        for k in (*ACTOR_FIELDS, FUTURE_FIELD):
            self.arrays[k].append(enc.actors[k])
        for k in ("ego_velocity", "ego_size", "city_from_ego"):
            self.arrays[k].append(getattr(enc, k))
        self.ids.append(enc.scene_id)
        s = self.summary
        s.scenes += 1
        for name in CLASS_NAMES:
            s.actors[name] += enc.inside[name]
            s.outside_region[name] += enc.outside[name]
            s.size_unmeasured[name] += enc.unmeasured[name]
        s.overflow += enc.overflow
        s.empty_scenes += int(not any(enc.inside.values()))

    def close(self, drops: collections.Counter) -> Summary:
        """Writes map_elements.npz, actors.npz and meta.json (with `drops` as the summary's
        dropped rows). Every file is written in full before any is renamed into place (the
        map points and indices, map elements, actors, meta.json last), so a cache already in
        the directory is replaced only by a whole one; a raster maps.npy of an older
        scenegen's cache there is removed once the new one is in place."""
        if not self.ids:
            raise ValueError(f"{self.out_dir}: no scenes to write")
        self.summary.dropped = dict(sorted(drops.items()))
        meta = {
            "version": CACHE_VERSION,
            "grid_size": self.cfg.grid.grid_size,
            "m_per_px": self.cfg.grid.m_per_px,
            "canvas_size": self.cfg.grid.canvas_size,
            "slots": cache_slots(self.cfg),
            "channels": list(ALL_MAP_CHANNELS),
            "config": json.loads(self.cfg.to_json()),
            "map_vocab": {k: v.words for k, v in self.elements.vocab.items()},
            "scene_ids": self.ids,
            "summary": self.summary.to_dict(),
            "source": self.source,
        }
        path = functools.partial(os.path.join, self.out_dir)
        with (written_whole(path("meta.json")) as meta_tmp,
              written_whole(path("actors.npz")) as actors_tmp,
              written_whole(path(ELEMENTS_FILE)) as elements_tmp):
            with open(elements_tmp, "wb") as f:
                np.savez(f, **self.elements.arrays())
            with open(actors_tmp, "wb") as f:
                np.savez(f, **{k: np.stack(v) for k, v in self.arrays.items()})
            with open(meta_tmp, "w") as f:
                json.dump(meta, f, indent=1)
            for stream in self.streams:
                stream.close()
        if os.path.exists(path(RASTER_FILE)):
            os.remove(path(RASTER_FILE))
        return self.summary


def write_cache(
    frames: Iterable[Frame],
    out_dir: str,
    cfg: Config,
    drops: collections.Counter,
    progress=None,
    source: dict | None = None,
) -> Summary:
    """Rasterizes and pads every frame into `out_dir` in this process; returns the summary.

    `drops` is the reader's counter of dropped rows; it is read after the frames are consumed.
    `source` (e.g. {"kind": "av2", "root": ..., "split": ..., "stride": ...}) is recorded so
    that the vector maps can be read again (the baselines need them). `scenegen_jax.data.
    prepare` does the same over a source's files in parallel.
    """
    with CacheWriter(out_dir, cfg, source) as writer:
        for frame in frames:
            writer.add(encode_frame(frame, cfg))
            if progress is not None:
                progress.update(1)
        return writer.close(drops)


def pad_frame_actors(frame: Frame, cfg: Config, slots: int) -> tuple[dict, np.ndarray, int]:
    """Actors within the canvas disc, nearest first, padded to `slots`.

    Returns:
      (padded arrays by field, in-region flag per frame actor, count of disc actors beyond
      `slots` that were dropped).
    """
    pos = np.asarray(frame.position, np.float64)
    inside = np.asarray(in_region(pos, cfg.grid))
    dist = np.linalg.norm(pos, axis=1)
    near = np.flatnonzero(dist <= canvas_radius(cfg))
    near = near[np.argsort(dist[near], kind="stable")]
    overflow = max(len(near) - slots, 0)
    if overflow:
        log.warning("%s: %d actors beyond %d cache slots dropped", frame.scene_id, overflow, slots)
    near = near[:slots]
    n = len(near)
    out = {
        "cls": np.zeros(slots, np.int32),
        "position": np.zeros((slots, 2), np.float32),
        "size": np.zeros((slots, 2), np.float32),
        "heading": np.zeros(slots, np.float32),
        "velocity": np.zeros((slots, 2), np.float32),
        "valid": np.zeros(slots, bool),
        "size_measured": np.zeros(slots, bool),
        FUTURE_FIELD: np.full((slots, len(FUTURE_HORIZONS_S), 2), np.nan, np.float32),
    }
    out["cls"][:n] = frame.cls[near]
    out["position"][:n] = pos[near]
    out["size"][:n] = frame.size[near]
    out["heading"][:n] = frame.heading[near]
    out["velocity"][:n] = frame.velocity[near]
    out["valid"][:n] = True
    out["size_measured"][:n] = frame.measured[near]
    if frame.future is not None:
        out[FUTURE_FIELD][:n] = frame.future[near]
    return out, inside, overflow

