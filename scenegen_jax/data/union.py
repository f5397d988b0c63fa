"""Several caches of the same config read as one (`CacheUnion`): scene indices run over the
caches in the order given; map arrays stay memory-mapped per cache."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence

import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.data.cache import (
    Cache,
    check_compatible,
    load_cache,
    stack_caches,
)
from scenegen_jax.data.cache_layout import ACTOR_FIELDS
from scenegen_jax.data.map_store import MapStore, StackedMapStore
from scenegen_jax.scene import Actors, make_ego


def source_labels(caches: Sequence[Cache]) -> list[str]:
    """A name per cache: its source kind and folder name (`av2:train`), or its whole path
    where two would share a name."""
    def kind(c):
        return (c.meta.get("source") or {}).get("kind") or "unknown"

    short = [f"{kind(c)}:{os.path.basename(os.path.normpath(c.path))}" for c in caches]
    return [
        s if short.count(s) == 1 else f"{kind(c)}:{c.path}"
        for s, c in zip(short, caches, strict=True)
    ]


@dataclasses.dataclass
class CacheUnion:
    """Several caches read as one: the fields of a `Cache` over all their scenes (cache 0's
    scenes first), so `gather_batch`, `score_cache` and `cached_scene` take it as they take
    a cache. Map arrays stay memory-mapped per cache (`map_store.frame_map(i)` reads scene
    i's map from its member); actor arrays are padded to the largest slot count and
    concatenated (the members' actors are views into them). One cache is its own union, with
    its arrays as they are."""

    members: list[Cache]
    offsets: np.ndarray  # [N + 1] first scene of each member, then the total
    labels: list[str]  # `source_labels`
    path: str
    meta: dict
    map_store: MapStore | StackedMapStore
    actors: Actors
    ego_velocity: np.ndarray
    ego_size: np.ndarray
    city_from_ego: np.ndarray
    future: np.ndarray | None

    @classmethod
    def of(cls, caches: Sequence[Cache]) -> CacheUnion:
        caches = list(caches)
        if not caches:
            raise ValueError("no caches given")
        sizes = [len(c) for c in caches]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        labels = source_labels(caches)
        if len(caches) == 1:
            c = caches[0]
            return cls(caches, offsets, labels, c.path, c.meta, c.map_store, c.actors,
                       c.ego_velocity, c.ego_size, c.city_from_ego, c.future)
        slots = max(c.actors.cls.shape[1] for c in caches)
        first = caches[0].meta
        meta = {
            **{k: first[k] for k in ("version", "grid_size", "m_per_px", "canvas_size",
                                     "channels") if k in first},
            "slots": slots,
            "scene_ids": [sid for c in caches for sid in c.scene_ids],
            "members": [c.path for c in caches],
            "source": {},
        }
        whole = stack_caches(caches, " + ".join(c.path for c in caches), meta)
        per_scene = {k: getattr(whole, k) for k in ("ego_velocity", "ego_size", "city_from_ego",
                                                    "future")}
        members = []
        for c, a, b in zip(caches, offsets[:-1], offsets[1:], strict=True):
            members.append(dataclasses.replace(
                c,
                actors=Actors(**{k: getattr(whole.actors, k)[a:b] for k in ACTOR_FIELDS}),
                **{k: None if v is None else v[a:b] for k, v in per_scene.items()},
            ))
        return cls(members, offsets, labels, whole.path, meta, whole.map_store, whole.actors,
                   **per_scene)

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def ego(self, index):
        """The ego of scene(s) `index`, as `Cache.ego`."""
        return make_ego(self.ego_size[index], self.ego_velocity[index])

    @property
    def sizes(self) -> list[int]:
        return [len(c) for c in self.members]

    @property
    def scene_ids(self) -> list[str]:
        return self.meta["scene_ids"]

    def member_of(self, indices) -> np.ndarray:
        """Member (cache) number of each union scene index."""
        return np.searchsorted(self.offsets, np.asarray(indices), side="right") - 1

    def scene_name(self, index: int) -> str:
        """The scene's id, after its cache's path when there are several caches."""
        sid = self.scene_ids[index]
        if len(self.members) == 1:
            return sid
        return f"{self.members[int(self.member_of(index))].path}: {sid}"

    def check_config(self, cfg: Config) -> None:
        """Raises naming the cache and field if a member's grid or channels differ from cfg."""
        check_compatible(self.members, cfg)


def load_union(paths: str | Sequence[str], cfg: Config | None = None) -> CacheUnion:
    """Opens one or several cache directories as a `CacheUnion` (checked against `cfg` with
    `check_compatible` when given)."""
    paths = [os.fspath(paths)] if isinstance(paths, str | os.PathLike) else [
        os.fspath(p) for p in paths]
    real = [os.path.realpath(p) for p in paths]
    for i, p in enumerate(real):
        if p in real[:i]:
            raise ValueError(f"{paths[i]}: listed twice (as {paths[real.index(p)]}); give each "
                             "cache once (--weights sets how often one is drawn)")
    caches = [load_cache(p) for p in paths]
    if cfg is not None:
        check_compatible(caches, cfg)
    return CacheUnion.of(caches)
