"""Preprocessing cache: map canvases and padded actor arrays that training reads fast.

Layout of a cache directory:
  meta.json     config (grid, resolution), channel names, scene ids, the prepare summary
  maps.npy      float16 [S, C, C, len(ALL_MAP_CHANNELS)] map canvases (C = canvas_size)
  actors.npz    padded actors [S, A] (cls, position, size, heading, velocity, valid), the
                ego (velocity, size) per scene, and the ego's city pose [S, 3, 3]

A sharded cache (`prepare --shard I/N`, one job per shard, e.g. on N machines) is a directory
of N such caches, `shard-0000I-of-0000N/`; `load_cache` reads it as one cache, the shards'
scenes in shard order and their maps memory-mapped per shard.

The canvas covers every rotation of the grid about the ego, and the actors are those within
the canvas's inscribed circle, so rotation augmentation never reaches outside the cache.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import math
import os
import re
import tokenize
import zipfile
from collections.abc import Iterable, Sequence

import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.files import written_whole
from scenegen_jax.frame import Frame
from scenegen_jax.jsonfile import read_json
from scenegen_jax.raster.map import ALL_MAP_CHANNELS, rasterize_map
from scenegen_jax.scene import CLASS_NAMES, Actors, in_region, make_ego

log = logging.getLogger(__name__)
CACHE_VERSION = 3  # 2: the nearest lane channels; 3: the data set channels
ACTOR_FIELDS = ("cls", "position", "size", "heading", "velocity", "valid")
# Each array of actors.npz: numpy dtype kinds it may have, and its shape after the scene axis
# ("A": the actor slots).
ARRAY_LAYOUT = {
    "cls": ("iu", ("A",)), "valid": ("b", ("A",)), "position": ("f", ("A", 2)),
    "size": ("f", ("A", 2)), "heading": ("f", ("A",)), "velocity": ("f", ("A", 2)),
    "ego_velocity": ("f", (2,)), "ego_size": ("f", (2,)),
}
_KIND_NAMES = {"iu": "integer", "b": "bool", "f": "float"}


def cache_slots(cfg: Config) -> int:
    """Actor slots stored per scene: room for the in-region maximum under any rotation."""
    return 2 * cfg.max_actors


def actors_in_region(cache, cfg: Config) -> np.ndarray:
    """[S] actors of each scene of a cache (or `CacheUnion`) inside the region of interest,
    unrotated (a rotation moves a few across its edge)."""
    return np.sum(cache.actors.valid & np.asarray(in_region(cache.actors.position, cfg)), axis=1)


def canvas_radius(cfg: Config) -> float:
    """Radius (m) of the disc that holds the grid under every rotation (its half diagonal)."""
    return cfg.region_m / math.sqrt(2.0)


@dataclasses.dataclass
class Summary:
    """What `prepare` wrote and dropped (printed as one JSON line).

    `actors` counts actors inside the region of interest per class, `outside_region` the rows
    of modelled classes outside it (kept in the cache only as far as rotations can reach), so
    actors + outside_region is every row of a modelled class that was read. `bad_files`
    counts files that could not be read, by reason (their names are in the log and in
    `bad_file_list`).
    """

    scenes: int = 0
    actors: dict = dataclasses.field(default_factory=lambda: {c: 0 for c in CLASS_NAMES})
    dropped: dict = dataclasses.field(default_factory=dict)
    outside_region: dict = dataclasses.field(default_factory=lambda: {c: 0 for c in CLASS_NAMES})
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
    overflow: int


def encode_frame(frame: Frame, cfg: Config) -> EncodedFrame:
    """Rasterizes and pads one frame (the expensive part of `prepare`; runs in workers)."""
    padded, inside, overflow = pad_frame_actors(frame, cfg, cache_slots(cfg))
    return EncodedFrame(
        scene_id=frame.scene_id,
        map=rasterize_map(frame.map, cfg.canvas_size, cfg.m_per_px).astype(np.float16),
        actors=padded,
        ego_velocity=np.asarray(frame.ego_velocity, np.float32),
        ego_size=np.asarray(frame.ego_size, np.float32),
        city_from_ego=np.asarray(frame.city_from_ego, np.float64),
        inside={n: int(np.sum(inside & (frame.cls == c))) for c, n in enumerate(CLASS_NAMES)},
        outside={n: int(np.sum(~inside & (frame.cls == c))) for c, n in enumerate(CLASS_NAMES)},
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
        self.file = open(path + ".tmp", "wb")  # noqa: SIM115 (closed in close())
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
        os.replace(self.path + ".tmp", self.path)

    def discard(self) -> None:
        """Closes and removes the unfinished file (any earlier `path` stays as it was)."""
        self.file.close()
        if os.path.exists(self.path + ".tmp"):
            os.remove(self.path + ".tmp")


class CacheWriter:
    """Appends encoded frames to a cache directory; `close` writes the arrays and meta.json.

    Used as a context manager: when the block raises (a bad file under `--strict`, no scenes,
    an interrupt), the unfinished maps file is removed and a cache already in the directory
    is left whole.
    """

    def __init__(self, out_dir: str, cfg: Config, source: dict | None = None) -> None:
        os.makedirs(out_dir, exist_ok=True)
        self.out_dir, self.cfg, self.source = out_dir, cfg, source or {}
        self.summary = Summary()
        size = cfg.canvas_size
        self.maps = _NpyAppender(
            os.path.join(out_dir, "maps.npy"), (size, size, len(ALL_MAP_CHANNELS)), np.float16
        )
        self.arrays: dict = collections.defaultdict(list)
        self.ids: list[str] = []

    def __enter__(self) -> CacheWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.maps.discard()

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
            "grid_size": self.cfg.grid_size,
            "m_per_px": self.cfg.m_per_px,
            "canvas_size": self.cfg.canvas_size,
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
    inside = np.asarray(in_region(pos, cfg))
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
    }
    out["cls"][:n] = frame.cls[near]
    out["position"][:n] = pos[near]
    out["size"][:n] = frame.size[near]
    out["heading"][:n] = frame.heading[near]
    out["velocity"][:n] = frame.velocity[near]
    out["valid"][:n] = True
    return out, inside, overflow


class StackedMaps:
    """The memory-mapped `maps.npy` of several caches read as one [S, C, C, channels] array:
    indexing reads only the scenes asked for."""

    def __init__(self, maps: Sequence[np.ndarray], offsets: np.ndarray):
        self._maps, self._offsets = list(maps), offsets
        self.shape = (int(offsets[-1]), *maps[0].shape[1:])
        self.dtype = maps[0].dtype

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index):
        if isinstance(index, (int, np.integer)):
            i = int(index) + (self.shape[0] if index < 0 else 0)
            if not 0 <= i < self.shape[0]:
                raise IndexError(f"scene {index} out of range [0, {self.shape[0]})")
            c = int(np.searchsorted(self._offsets, i, side="right")) - 1
            return self._maps[c][i - self._offsets[c]]
        rows = np.arange(self.shape[0])[index]
        return np.stack([self[int(i)] for i in np.atleast_1d(rows)])


SHARD_NAME = "shard-{:05d}-of-{:05d}"
SHARD_RE = re.compile(r"shard-(\d{5})-of-(\d{5})")


def shard_dir(out_dir: str, index: int, count: int) -> str:
    """The folder of shard `index` of `count` inside the cache directory `out_dir`."""
    if not 0 <= index < count:
        raise ValueError(f"--shard {index}/{count}: need 0 <= I < N")
    return os.path.join(out_dir, SHARD_NAME.format(index, count))


@dataclasses.dataclass
class Cache:
    """A loaded cache: map canvases (memory-mapped) and actor arrays."""

    path: str
    meta: dict
    maps: np.ndarray | StackedMaps  # float16 [S, C, C, len(ALL_MAP_CHANNELS)]
    actors: Actors  # numpy fields [S, A]
    ego_velocity: np.ndarray  # [S, 2] m/s
    ego_size: np.ndarray  # [S, 2] m
    city_from_ego: np.ndarray  # [S, 3, 3]

    def ego(self, index):
        """The ego of scene(s) `index` (an int or an index array): `scene.make_ego` with the
        cached size and velocity."""
        return make_ego(self.ego_size[index], self.ego_velocity[index])

    def __len__(self) -> int:
        return len(self.meta["scene_ids"])

    @property
    def scene_ids(self) -> list[str]:
        return self.meta["scene_ids"]

    def scene_name(self, index: int) -> str:
        """The scene's id after the cache's path, for errors."""
        return f"{self.path}: {self.scene_ids[index]}"

    def check_config(self, cfg: Config) -> None:
        """Raises naming the field if `cfg`'s grid or map channels are not the cache's
        (`check_compatible`)."""
        check_compatible([self], cfg)


# What np.load raises on a truncated or damaged .npy / .npz: a header that is cut or no
# Python literal fails in numpy's header parser with SyntaxError or tokenize.TokenError.
_UNREADABLE_ARRAY = (
    ValueError, OSError, EOFError, SyntaxError, TypeError, tokenize.TokenError,
    zipfile.BadZipFile,
)


def load_cache(path: str) -> Cache:
    """Opens a cache directory written by `write_cache` or `prepare` (sharded or not);
    errors name the file and field."""
    meta_path = os.path.join(path, "meta.json")
    if not os.path.isfile(meta_path):
        if os.path.isdir(path) and any(SHARD_RE.fullmatch(n) for n in os.listdir(path)):
            return _load_sharded(path)
        raise FileNotFoundError(f"{meta_path}: not a scenegen cache (run `scenegen prepare`)")
    meta = read_json(meta_path)
    if not isinstance(meta, dict) or not isinstance(meta.get("scene_ids"), list):
        raise ValueError(f"{meta_path}: field scene_ids: missing or not a list")
    if meta.get("version") != CACHE_VERSION:
        raise ValueError(f"{meta_path}: field version: {meta.get('version')} != {CACHE_VERSION}"
                         " (a cache of another version of scenegen: re-run scenegen prepare)")
    if meta.get("channels") != list(ALL_MAP_CHANNELS):
        raise ValueError(f"{meta_path}: field channels: cache channels differ from this "
                         "version's (re-run scenegen prepare)")
    maps_path = os.path.join(path, "maps.npy")
    try:
        maps = np.load(maps_path, mmap_mode="r", allow_pickle=False)
    except _UNREADABLE_ARRAY as e:  # truncated or not an .npy file
        raise ValueError(f"{maps_path}: unreadable map canvases ({e}); re-run prepare") from e
    npz_path = os.path.join(path, "actors.npz")
    try:
        with np.load(npz_path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except _UNREADABLE_ARRAY as e:
        raise ValueError(f"{npz_path}: unreadable actor arrays ({e}); re-run prepare") from e
    missing = [k for k in (*ACTOR_FIELDS, "ego_velocity", "ego_size") if k not in data]
    if missing:
        raise ValueError(f"{npz_path}: missing field(s) {missing}")
    n = len(meta["scene_ids"])
    for k, v in data.items():
        if v.ndim == 0 or v.shape[0] != n:
            raise ValueError(f"{npz_path}: field {k}: {v.shape[:1]} scenes, meta.json has {n}")
    _check_layout(meta, meta_path, maps, maps_path, data, npz_path)
    actors = Actors(**{k: data[k] for k in ACTOR_FIELDS})
    actors.validate(f"{npz_path}: actors")
    _check_places_and_egos(meta, data, npz_path)
    return Cache(
        path=path,
        meta=meta,
        maps=maps,
        actors=actors,
        ego_velocity=data["ego_velocity"],
        ego_size=data["ego_size"],
        city_from_ego=data.get("city_from_ego", np.tile(np.eye(3), (n, 1, 1))),
    )


def _check_layout(meta, meta_path, maps, maps_path, data, npz_path) -> None:
    """Raises ValueError naming the file and field where an array's dtype or shape is not the
    cache layout's (module docstring; `ARRAY_LAYOUT`)."""
    slots, canvas = meta.get("slots"), meta.get("canvas_size")
    for field in ("slots", "canvas_size", "grid_size"):
        value = meta.get(field)
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ValueError(f"{meta_path}: field {field}: expected a positive integer, got "
                             f"{value!r}")
    m = meta.get("m_per_px")
    if isinstance(m, bool) or not isinstance(m, int | float) or not 0 < m < math.inf:
        raise ValueError(f"{meta_path}: field m_per_px: expected a positive number, got {m!r}")
    n = len(meta["scene_ids"])
    for k, (kinds, tail) in ARRAY_LAYOUT.items():
        want = (n, *(slots if d == "A" else d for d in tail))
        if data[k].dtype.kind not in kinds or data[k].shape != want:
            raise ValueError(f"{npz_path}: field {k}: {data[k].dtype} {data[k].shape}, expected "
                             f"{_KIND_NAMES[kinds]} {want}")
    want = (n, canvas, canvas, len(ALL_MAP_CHANNELS))
    if maps.dtype.kind != "f" or maps.shape != want:
        raise ValueError(f"{maps_path}: {maps.dtype} {maps.shape}, expected float {want}")


def _check_places_and_egos(meta, data, npz_path) -> None:
    """Raises ValueError naming the field where a valid actor stands beyond the canvas's
    inscribed circle (`canvas_radius`: prepare keeps none there), or an ego's size is not
    finite and positive or its velocity not finite."""
    radius = canvas_radius(Config(grid_size=meta["grid_size"], m_per_px=meta["m_per_px"]))
    far = data["valid"] & (np.hypot(*np.moveaxis(data["position"], -1, 0)) > radius + 1e-3)
    if far.any():
        scene, slot = (int(i[0]) for i in np.nonzero(far))
        raise ValueError(f"{npz_path}: field position: scene {scene} slot {slot} lies beyond the "
                         f"canvas ({radius:.2f} m from the ego); re-run prepare")
    if not (np.all(np.isfinite(data["ego_size"])) and np.all(data["ego_size"] > 0)):
        raise ValueError(f"{npz_path}: field ego_size: sizes must be finite and positive")
    if not np.all(np.isfinite(data["ego_velocity"])):
        raise ValueError(f"{npz_path}: field ego_velocity: NaN or inf")


# Fields every shard of a cache must share (the rest, scene ids and summaries, add up).
SHARD_SHARED_FIELDS = ("version", "grid_size", "m_per_px", "canvas_size", "slots", "channels",
                       "config")


def _load_sharded(path: str) -> Cache:
    """The shards `shard-I-of-N` of `path` as one cache; every shard must be there."""
    found = {}
    for name in sorted(os.listdir(path)):
        m = SHARD_RE.fullmatch(name)
        if m:
            found[(int(m[1]), int(m[2]))] = os.path.join(path, name)
    counts = sorted({n for _, n in found})
    if len(counts) != 1:
        raise ValueError(f"{path}: shards of different counts {counts}; keep one --shard I/N "
                         "set per cache directory")
    count = counts[0]
    missing = [i for i in range(count) if (i, count) not in found]
    if missing:
        raise FileNotFoundError(f"{path}: shard(s) {missing} of {count} missing (run `scenegen "
                                f"prepare --shard I/{count}` for each)")
    shards = [load_cache(found[(i, count)]) for i in range(count)]
    first = shards[0].meta
    for shard in shards[1:]:
        for field in SHARD_SHARED_FIELDS:
            if shard.meta.get(field) != first.get(field):
                raise ValueError(f"{shard.path}/meta.json: field {field} differs from "
                                 f"{shards[0].path}'s; prepare every shard with the same "
                                 "--config, --set and source")
    meta = {
        **{k: first[k] for k in SHARD_SHARED_FIELDS},
        "scene_ids": [sid for c in shards for sid in c.scene_ids],
        "source": {k: v for k, v in first.get("source", {}).items() if k != "shard"},
        "shards": [{"path": c.path, "scenes": len(c), "summary": c.meta.get("summary")}
                   for c in shards],
    }
    return stack_caches(shards, path, meta)


def _pad_slots(x: np.ndarray, slots: int) -> np.ndarray:
    if x.shape[1] == slots:
        return x
    pad = [(0, 0), (0, slots - x.shape[1])] + [(0, 0)] * (x.ndim - 2)
    return np.pad(x, pad)  # zeros: invalid, class 0


def stack_caches(caches: Sequence[Cache], path: str, meta: dict) -> Cache:
    """Several caches read as one `Cache` (called `path`, with `meta`): their scenes in order,
    actor arrays padded to the largest slot count and concatenated, maps memory-mapped per
    cache (`StackedMaps`). Shards of a cache and a `CacheUnion`'s members both use it."""
    slots = max(c.actors.cls.shape[1] for c in caches)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in caches])]).astype(np.int64)
    cat = lambda get: np.concatenate([get(c) for c in caches])  # noqa: E731
    return Cache(
        path=path,
        meta=meta,
        maps=StackedMaps([c.maps for c in caches], offsets),
        actors=Actors(**{k: cat(lambda c, k=k: _pad_slots(getattr(c.actors, k), slots))
                         for k in ACTOR_FIELDS}),
        ego_velocity=cat(lambda c: c.ego_velocity),
        ego_size=cat(lambda c: c.ego_size),
        city_from_ego=cat(lambda c: c.city_from_ego),
    )


def check_compatible(caches: Iterable[Cache], cfg: Config) -> None:
    """Raises ValueError naming the cache and the field unless every cache has `cfg`'s grid
    (grid_size, m_per_px, canvas_size) and the map channels the config reads, and all share
    one channel layout (so that their canvases stack and train together)."""
    caches = list(caches)
    want = {"grid_size": cfg.grid_size, "m_per_px": cfg.m_per_px, "canvas_size": cfg.canvas_size}
    hint = f"re-run prepare with --config {cfg.name} (and the same --set overrides)"
    for cache in caches:
        for field, value in want.items():
            got = cache.meta.get(field, cache.maps.shape[1] if field == "canvas_size" else None)
            if got != value:
                raise ValueError(f"{cache.path}: field {field}: cache has {got}, config "
                                 f"{cfg.name!r} wants {value}; {hint}")
        channels = list(cache.meta.get("channels") or [])
        missing = [c for c in cfg.map_channels if c not in channels]
        if missing:
            raise ValueError(f"{cache.path}: field channels: no map layer(s) {missing} that "
                             f"config {cfg.name!r} reads (map_layers {list(cfg.map_layers)})")
        first = list(caches[0].meta.get("channels") or [])
        if channels != first:
            raise ValueError(f"{cache.path}: field channels: {channels} differ from "
                             f"{caches[0].path}'s {first}")
        if cache.maps.shape[-1] != len(channels):
            raise ValueError(f"{cache.path}/maps.npy: {cache.maps.shape[-1]} channels, "
                             f"meta.json lists {len(channels)}")


def cached_scene(cache: Cache, index: int, cfg: Config) -> tuple[np.ndarray, Actors, Actors]:
    """(map canvas, cached actors [A], ego) of scene `index`, as numpy."""
    if not 0 <= index < len(cache):
        raise IndexError(f"{cache.path}: scene index {index} out of range [0, {len(cache)})")
    actors = Actors(**{k: getattr(cache.actors, k)[index] for k in ACTOR_FIELDS})
    return np.asarray(cache.maps[index]), actors, cache.ego(index)
