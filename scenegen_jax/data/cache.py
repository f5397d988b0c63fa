"""Reading a preprocessing cache (layout: `cache_layout`; written by `cache_write`): one
directory or the shards of one, checked field by field, as a `Cache` whose map arrays are
memory-mapped (`map_store`); several caches stacked as one (`stack_caches`) and checked
against a config (`check_compatible`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shlex
from collections.abc import Iterable, Sequence

import numpy as np

from scenegen_jax.config import PRESETS, Config, GridConfig
from scenegen_jax.data.cache_layout import (
    ACTOR_FIELDS,
    CACHE_VERSION,
    FUTURE_FIELD,
    FUTURE_VERSION,
    RASTER_FILE,
    READABLE_VERSIONS,
    SHARD_RE,
    UNREADABLE_ARRAY,
    canvas_radius,
)
from scenegen_jax.data.map_store import FRAME_FIELDS, MapStore, StackedMapStore, load_map_store
from scenegen_jax.frame import FUTURE_HORIZONS_S, MAX_WORLD_M, within_world
from scenegen_jax.jsonfile import read_json
from scenegen_jax.raster.map import ALL_MAP_CHANNELS
from scenegen_jax.scene import Actors, in_region, make_ego
from scenegen_jax.vector_map import VectorMap

# Each array of actors.npz: numpy dtype kinds it may have, and its shape after the scene axis
# ("A": the actor slots).
ARRAY_LAYOUT = {
    "cls": ("iu", ("A",)), "valid": ("b", ("A",)), "position": ("f", ("A", 2)),
    "size": ("f", ("A", 2)), "heading": ("f", ("A",)), "velocity": ("f", ("A", 2)),
    "size_measured": ("b", ("A",)), "ego_velocity": ("f", (2,)), "ego_size": ("f", (2,)),
}
_KIND_NAMES = {"iu": "integer", "b": "bool", "f": "float"}


def actors_in_region(cache, cfg: Config) -> np.ndarray:
    """[S] actors of each scene of a cache (or `CacheUnion`) inside the region of interest,
    unrotated (a rotation moves a few across its edge)."""
    return np.sum(
        cache.actors.valid & np.asarray(in_region(cache.actors.position, cfg.grid)), axis=1
    )


@dataclasses.dataclass
class Cache:
    """A loaded cache: its vector maps (`map_store.MapStore`, arrays memory-mapped) and actor
    arrays."""

    path: str
    meta: dict
    map_store: MapStore | StackedMapStore  # `frame_map(i)`: scene i's map, ego frame
    actors: Actors  # numpy fields [S, A]
    ego_velocity: np.ndarray  # [S, 2] m/s
    ego_size: np.ndarray  # [S, 2] m
    city_from_ego: np.ndarray  # [S, 3, 3]
    # [S, A, H, 2] m the actors' future positions (`cache_layout`); None in a cache of a
    # version before FUTURE_VERSION.
    future: np.ndarray | None = None

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


def shard_folders(path: str) -> list[str]:
    """Names of the `prepare --shard` folders in `path`, sorted (none if it is no folder)."""
    if not os.path.isdir(path):
        return []
    return sorted(n for n in os.listdir(path) if SHARD_RE.fullmatch(n))


def load_cache(path: str) -> Cache:
    """Opens a cache directory written by `write_cache` or `prepare` (sharded or not);
    errors name the file and field."""
    meta_path = os.path.join(path, "meta.json")
    shards = shard_folders(path)
    if not os.path.isfile(meta_path):
        if shards:
            return _load_sharded(path)
        raise FileNotFoundError(f"{meta_path}: not a scenegen cache (run `scenegen prepare`)")
    if shards:  # two caches in one folder: which one is meant is unknown
        raise ValueError(f"{path}: holds both a whole cache ({meta_path}) and shards "
                         f"({os.path.join(path, shards[0])}, ...); move one of them away")
    meta = read_json(meta_path)
    if not isinstance(meta, dict) or not isinstance(meta.get("scene_ids"), list):
        raise ValueError(f"{meta_path}: field scene_ids: missing or not a list")
    version = meta.get("version")
    if isinstance(version, int) and not isinstance(version, bool) and version < min(
            READABLE_VERSIONS):
        raise ValueError(
            f"{meta_path}: field version: {version}: the cache holds raster canvases "
            f"({RASTER_FILE}) of an older scenegen, which this one (cache version "
            f"{CACHE_VERSION}) does not read; rewrite it with `{prepare_command(path, meta)}`"
        )
    if version not in READABLE_VERSIONS:
        raise ValueError(
            f"{meta_path}: field version: {meta.get('version')}, this scenegen reads "
            f"{list(READABLE_VERSIONS)} (a cache of another version of scenegen: re-run "
            "scenegen prepare)"
        )
    if meta.get("channels") != list(ALL_MAP_CHANNELS):
        raise ValueError(
            f"{meta_path}: field channels: cache channels differ from this "
            "version's (re-run scenegen prepare)"
        )
    npz_path = os.path.join(path, "actors.npz")
    try:
        with np.load(npz_path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except UNREADABLE_ARRAY as e:
        raise ValueError(f"{npz_path}: unreadable actor arrays ({e}); re-run prepare") from e
    has_future = version >= FUTURE_VERSION
    missing = [k for k in (*ACTOR_FIELDS, "ego_velocity", "ego_size", "city_from_ego",
                           *FRAME_FIELDS, *[FUTURE_FIELD] * has_future) if k not in data]
    if missing:
        raise ValueError(f"{npz_path}: missing field(s) {missing}")
    n = len(meta["scene_ids"])
    for k, v in data.items():
        if v.ndim == 0 or v.shape[0] != n:
            raise ValueError(f"{npz_path}: field {k}: {v.shape[:1]} scenes, meta.json has {n}")
    _check_layout(meta, meta_path, data, npz_path)
    if has_future:
        _check_future(data[FUTURE_FIELD], n, meta["slots"], npz_path)
    actors = Actors(**{k: data[k] for k in ACTOR_FIELDS})
    actors.validate(f"{npz_path}: actors")
    _check_places_and_egos(meta, data, npz_path)
    map_store = load_map_store(path, meta, meta_path, {k: data[k] for k in FRAME_FIELDS},
                               npz_path, data["city_from_ego"])
    return Cache(
        path=path,
        meta=meta,
        map_store=map_store,
        actors=actors,
        ego_velocity=data["ego_velocity"],
        ego_size=data["ego_size"],
        city_from_ego=data["city_from_ego"],
        future=data[FUTURE_FIELD] if has_future else None,
    )


def _check_future(future: np.ndarray, n: int, slots: int, npz_path: str) -> None:
    """Raises ValueError naming the file and field unless `future` is float [n, slots, H, 2]
    of finite or NaN (unobserved) positions."""
    want = (n, slots, len(FUTURE_HORIZONS_S), 2)
    if future.dtype.kind != "f" or future.shape != want:
        raise ValueError(f"{npz_path}: field {FUTURE_FIELD}: {future.dtype} {future.shape}, "
                         f"expected float {want}")
    if np.isinf(future).any():
        raise ValueError(f"{npz_path}: field {FUTURE_FIELD}: inf (unobserved positions are NaN)")


def prepare_command(path: str, meta: dict) -> str:
    """The `scenegen prepare` command that rewrites the cache at `path` from the source and
    config its meta.json records (placeholders where it records none)."""
    source = meta.get("source") if isinstance(meta.get("source"), dict) else {}
    out = path
    args = ["scenegen", "prepare", "--source", str(source.get("kind") or "<source kind>"),
            "--root", str(source.get("root") or "<data root>")]
    if source.get("split"):
        args += ["--split", str(source["split"])]
    if source.get("stride"):
        args += ["--stride", str(source["stride"])]
    config = meta.get("config") if isinstance(meta.get("config"), dict) else {}
    name = config.get("name")
    if name in PRESETS:
        args += ["--config", name]
        overrides = _grid_overrides(config, PRESETS[name], f"{path}/meta.json")
        if overrides:
            args += ["--set", *overrides]
    shard = source.get("shard")
    if isinstance(shard, list) and len(shard) == 2:
        args += ["--shard", f"{shard[0]}/{shard[1]}"]
        out = os.path.dirname(os.path.normpath(path))  # prepare writes OUT/shard-I-of-N
    return shlex.join([*args, "--out", out])


def _grid_overrides(config: dict, preset: Config, source: str) -> list[str]:
    """`--set FIELD=VALUE` of the grid fields in which a cache's recorded config differs from
    its preset ([] when it does not, or cannot be read)."""
    try:
        saved = Config.from_json(json.dumps(config), source).flat()
    except ValueError:
        return []
    want = preset.flat()

    def text(value) -> str:
        if isinstance(value, bool):
            return str(value).lower()
        if isinstance(value, tuple):
            return ",".join(map(str, value)) or "none"
        return str(value)

    return [f"{f.name}={text(saved[f.name])}" for f in dataclasses.fields(GridConfig)
            if saved[f.name] != want[f.name]]


def _check_layout(meta, meta_path, data, npz_path) -> None:
    """Raises ValueError naming the file and field where an array's dtype or shape is not the
    cache layout's (module docstring; `ARRAY_LAYOUT`)."""
    slots = meta.get("slots")
    for field in ("slots", "canvas_size", "grid_size"):
        value = meta.get(field)
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ValueError(
                f"{meta_path}: field {field}: expected a positive integer, got {value!r}"
            )
    m = meta.get("m_per_px")
    if isinstance(m, bool) or not isinstance(m, int | float) or not 0 < m < math.inf:
        raise ValueError(f"{meta_path}: field m_per_px: expected a positive number, got {m!r}")
    n = len(meta["scene_ids"])
    for k, (kinds, tail) in ARRAY_LAYOUT.items():
        want = (n, *(slots if d == "A" else d for d in tail))
        if data[k].dtype.kind not in kinds or data[k].shape != want:
            raise ValueError(
                f"{npz_path}: field {k}: {data[k].dtype} {data[k].shape}, expected "
                f"{_KIND_NAMES[kinds]} {want}"
            )
    pose = data["city_from_ego"]
    if pose.dtype.kind != "f" or pose.shape != (n, 3, 3):
        raise ValueError(f"{npz_path}: field city_from_ego: {pose.dtype} {pose.shape}, "
                         f"expected float {(n, 3, 3)}")
    if not np.all(np.isfinite(pose)):
        raise ValueError(f"{npz_path}: field city_from_ego: NaN or inf")
    rot = pose[:, :2, :2]
    with np.errstate(over="ignore", invalid="ignore"):
        skew = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(2)).max(axis=(1, 2), initial=0.0)
    bad = ~(skew <= 1e-6) | ~within_world(pose[:, :2, 2]) | np.any(pose[:, 2] != (0, 0, 1), 1)
    if bad.any():
        raise ValueError(f"{npz_path}: field city_from_ego: scene {int(np.flatnonzero(bad)[0])}: "
                         f"not an SE(2) pose (a rotation, then a translation within "
                         f"{MAX_WORLD_M:g} m)")


def _check_places_and_egos(meta, data, npz_path) -> None:
    """Raises ValueError naming the field where a valid actor stands beyond the canvas's
    inscribed circle (`canvas_radius`: prepare keeps none there), or an ego's size is not
    finite and positive or its velocity not finite."""
    radius = canvas_radius(Config().replace(grid_size=meta["grid_size"], m_per_px=meta["m_per_px"]))
    far = data["valid"] & (np.hypot(*np.moveaxis(data["position"], -1, 0)) > radius + 1e-3)
    if far.any():
        scene, slot = (int(i[0]) for i in np.nonzero(far))
        raise ValueError(
            f"{npz_path}: field position: scene {scene} slot {slot} lies beyond the "
            f"canvas ({radius:.2f} m from the ego); re-run prepare"
        )
    if not (np.all(np.isfinite(data["ego_size"])) and np.all(data["ego_size"] > 0)):
        raise ValueError(f"{npz_path}: field ego_size: sizes must be finite and positive")
    if not np.all(np.isfinite(data["ego_velocity"])):
        raise ValueError(f"{npz_path}: field ego_velocity: NaN or inf")


# Fields every shard of a cache must share (the rest, scene ids and summaries, add up).
SHARD_SHARED_FIELDS = (
    "version",
    "grid_size",
    "m_per_px",
    "canvas_size",
    "slots",
    "channels",
    "config",
)


def _shared_value(cache: Cache, field: str):
    """A meta.json field as shards compare it: the config as the config it reads as (a
    one-level config of an older shard equals the nested one of a newer)."""
    value = cache.meta.get(field)
    if field == "config" and isinstance(value, dict):
        return Config.from_json(json.dumps(value), f"{cache.path}/meta.json")
    return value


def _load_sharded(path: str) -> Cache:
    """The shards `shard-I-of-N` of `path` as one cache; every shard must be there."""
    found = {}
    for name in sorted(os.listdir(path)):
        m = SHARD_RE.fullmatch(name)
        if m:
            found[(int(m[1]), int(m[2]))] = os.path.join(path, name)
    counts = sorted({n for _, n in found})
    if len(counts) != 1:
        raise ValueError(
            f"{path}: shards of different counts {counts}; keep one --shard I/N "
            "set per cache directory"
        )
    count = counts[0]
    missing = [i for i in range(count) if (i, count) not in found]
    if missing:
        raise FileNotFoundError(
            f"{path}: shard(s) {missing} of {count} missing (run `scenegen "
            f"prepare --shard I/{count}` for each)"
        )
    shards = [load_cache(found[(i, count)]) for i in range(count)]
    first = shards[0].meta
    for shard in shards[1:]:
        for field in SHARD_SHARED_FIELDS:
            if _shared_value(shard, field) != _shared_value(shards[0], field):
                raise ValueError(
                    f"{shard.path}/meta.json: field {field} differs from "
                    f"{shards[0].path}'s; prepare every shard with the same "
                    "--config, --set and source"
                )
    meta = {
        **{k: first[k] for k in SHARD_SHARED_FIELDS},
        "scene_ids": [sid for c in shards for sid in c.scene_ids],
        "source": {k: v for k, v in first.get("source", {}).items() if k != "shard"},
        "shards": [
            {"path": c.path, "scenes": len(c), "summary": c.meta.get("summary")} for c in shards
        ],
    }
    return stack_caches(shards, path, meta)


def _pad_slots(x: np.ndarray, slots: int, value=0) -> np.ndarray:
    """x [S, A, ...] padded to `slots` actor slots with `value` (0: invalid, class 0)."""
    if x.shape[1] == slots:
        return x
    pad = [(0, 0), (0, slots - x.shape[1])] + [(0, 0)] * (x.ndim - 2)
    return np.pad(x, pad, constant_values=value)


def stacked_futures(caches: Sequence[Cache], slots: int) -> np.ndarray | None:
    """The caches' `future` arrays padded to `slots` and concatenated; None unless every
    cache has them."""
    if any(c.future is None for c in caches):
        return None
    return np.concatenate([_pad_slots(c.future, slots, np.nan) for c in caches])


def stack_caches(caches: Sequence[Cache], path: str, meta: dict) -> Cache:
    """Several caches read as one `Cache` (called `path`, with `meta`): their scenes in order,
    actor arrays padded to the largest slot count and concatenated, maps memory-mapped per
    cache (`StackedMapStore`). Shards of a cache and a `CacheUnion`'s members both use it."""
    slots = max(c.actors.cls.shape[1] for c in caches)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in caches])]).astype(np.int64)
    cat = lambda get: np.concatenate([get(c) for c in caches])  # noqa: E731
    return Cache(
        path=path,
        meta=meta,
        map_store=StackedMapStore([c.map_store for c in caches], offsets),
        actors=Actors(
            **{k: cat(lambda c, k=k: _pad_slots(getattr(c.actors, k), slots)) for k in ACTOR_FIELDS}
        ),
        ego_velocity=cat(lambda c: c.ego_velocity),
        ego_size=cat(lambda c: c.ego_size),
        city_from_ego=cat(lambda c: c.city_from_ego),
        future=stacked_futures(caches, slots),
    )


def check_compatible(caches: Iterable[Cache], cfg: Config) -> None:
    """Raises ValueError naming the cache and the field unless every cache has `cfg`'s grid
    (grid_size, m_per_px, canvas_size) and the map channels the config reads, and all share
    one channel layout (so that their rasters stack and train together)."""
    caches = list(caches)
    want = {
        "grid_size": cfg.grid.grid_size,
        "m_per_px": cfg.grid.m_per_px,
        "canvas_size": cfg.grid.canvas_size,
    }
    hint = f"re-run prepare with --config {cfg.name} (and the same --set overrides)"
    for cache in caches:
        for field, value in want.items():
            got = cache.meta.get(field)
            if got != value:
                raise ValueError(
                    f"{cache.path}: field {field}: cache has {got}, config "
                    f"{cfg.name!r} wants {value}; {hint}"
                )
        channels = list(cache.meta.get("channels") or [])
        missing = [c for c in cfg.grid.map_channels if c not in channels]
        if missing:
            raise ValueError(
                f"{cache.path}: field channels: no map layer(s) {missing} that "
                f"config {cfg.name!r} reads (map_layers {list(cfg.grid.map_layers)})"
            )
        first = list(caches[0].meta.get("channels") or [])
        if channels != first:
            raise ValueError(
                f"{cache.path}: field channels: {channels} differ from {caches[0].path}'s {first}"
            )


def cached_actors(cache: Cache, index: int) -> Actors:
    """The cached actors [A] of scene `index` (numpy, unrotated)."""
    return Actors(**{k: getattr(cache.actors, k)[index] for k in ACTOR_FIELDS})


def cached_scene(cache: Cache, index: int, cfg: Config) -> tuple[VectorMap, Actors, Actors]:
    """(vector map in the ego frame, cached actors [A], ego) of scene `index`, as numpy."""
    if not 0 <= index < len(cache):
        raise IndexError(f"{cache.path}: scene index {index} out of range [0, {len(cache)})")
    return cache.map_store.frame_map(index), cached_actors(cache, index), cache.ego(index)
