"""Writing a preprocessing cache (layout: `cache_layout`): each frame rasterized and padded
(`encode_frame`), appended by a `CacheWriter`, whose `close` writes the arrays and meta.json;
`write_cache` does it all in this process."""

from __future__ import annotations

import collections
import dataclasses
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
    cache_slots,
    canvas_radius,
)
from scenegen_jax.files import written_whole
from scenegen_jax.frame import Frame
from scenegen_jax.raster.map import ALL_MAP_CHANNELS, rasterize_map
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
    """A frame as the cache stores it: its map canvas and padded actors, with counts."""

    scene_id: str
    map: np.ndarray  # float16 [C, C, len(ALL_MAP_CHANNELS)]
    actors: dict  # padded arrays by ACTOR_FIELDS
    ego_velocity: np.ndarray  # [2] m/s
    ego_size: np.ndarray  # [2] m
    city_from_ego: np.ndarray  # [3, 3]
    inside: dict  # in-region actors per class name
    outside: dict  # disc actors outside the region per class name
    unmeasured: dict  # in-region actors without a measured box size per class name
    overflow: int


def encode_frame(frame: Frame, cfg: Config) -> EncodedFrame:
    """Rasterizes and pads one frame (the expensive part of `prepare`; runs in workers)."""
    padded, inside, overflow = pad_frame_actors(frame, cfg, cache_slots(cfg))
    return EncodedFrame(
        scene_id=frame.scene_id,
        map=rasterize_map(frame.map, cfg.grid.canvas_size, cfg.grid.m_per_px).astype(np.float16),
        actors=padded,
        ego_velocity=np.asarray(frame.ego_velocity, np.float32),
        ego_size=np.asarray(frame.ego_size, np.float32),
        city_from_ego=np.asarray(frame.city_from_ego, np.float64),
        inside={n: int(np.sum(inside & (frame.cls == c))) for c, n in enumerate(CLASS_NAMES)},
        outside={n: int(np.sum(~inside & (frame.cls == c))) for c, n in enumerate(CLASS_NAMES)},
        unmeasured={n: int(np.sum(inside & ~frame.measured & (frame.cls == c)))
                    for c, n in enumerate(CLASS_NAMES)},
        overflow=overflow,
    )


class _NpyAppender:
    """Writes a .npy array one leading-axis item at a time, so maps never sit in memory.

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

    def append(self, item: np.ndarray) -> None:
        self.file.write(np.ascontiguousarray(item, self.dtype).tobytes())
        self.count += 1

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


class CacheWriter:
    """Appends encoded frames to a cache directory; `close` writes the arrays and meta.json.

    Used as a context manager, which holds the directory's lock (`locks.exclusive` on
    OUT/.lock: a second writer is refused, naming this one's pid and host): when the block
    raises (a bad file under `--strict`, no scenes, an interrupt) or ends without `close`,
    the unfinished maps file is removed and a cache already in the directory is left whole.
    """

    def __init__(self, out_dir: str, cfg: Config, source: dict | None = None) -> None:
        os.makedirs(out_dir, exist_ok=True)
        self.out_dir, self.cfg, self.source = out_dir, cfg, source or {}
        self._lock = locks.acquire(self._lock_path, f"writing the cache {out_dir}")
        self.summary = Summary()
        size = cfg.grid.canvas_size
        try:
            self.maps = _NpyAppender(
                os.path.join(out_dir, "maps.npy"), (size, size, len(ALL_MAP_CHANNELS)),
                np.float16)
        except BaseException:
            locks.release(self._lock_path, self._lock)
            raise
        self.arrays: dict = collections.defaultdict(list)
        self.ids: list[str] = []

    @property
    def _lock_path(self) -> str:
        return os.path.join(self.out_dir, locks.LOCK_FILE)

    def __enter__(self) -> CacheWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self.maps.discard()  # a no-op after `close`; else the unfinished file goes
        finally:
            locks.release(self._lock_path, self._lock)

    def add(self, enc: EncodedFrame) -> None:
        self.maps.append(enc.map)
        for k in ACTOR_FIELDS:
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
        """Writes actors.npz and meta.json (with `drops` as the summary's dropped rows). Every
        file is written in full before any is renamed into place (maps, actors, meta.json
        last), so a cache already in the directory is replaced only by a whole one."""
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
            "scene_ids": self.ids,
            "summary": self.summary.to_dict(),
            "source": self.source,
        }
        with (written_whole(os.path.join(self.out_dir, "meta.json")) as meta_tmp,
              written_whole(os.path.join(self.out_dir, "actors.npz")) as actors_tmp):
            with open(actors_tmp, "wb") as f:
                np.savez(f, **{k: np.stack(v) for k, v in self.arrays.items()})
            with open(meta_tmp, "w") as f:
                json.dump(meta, f, indent=1)
            self.maps.close()
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
    }
    out["cls"][:n] = frame.cls[near]
    out["position"][:n] = pos[near]
    out["size"][:n] = frame.size[near]
    out["heading"][:n] = frame.heading[near]
    out["velocity"][:n] = frame.velocity[near]
    out["valid"][:n] = True
    out["size_measured"][:n] = frame.measured[near]
    return out, inside, overflow

