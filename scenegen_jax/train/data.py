"""Batches from one or several caches, in an order that is a pure function of (seed, step).

Several caches of the same config (e.g. prepared from different sources) are trained on as
one `CacheUnion`: scene indices run over the caches in the order given. Each training scene
is drawn from cache i with probability w_i / sum(w) (default: w_i = its scene count, i.e.
uniform over scenes), and within a cache every scene is drawn once per pass over it.

The order (`draw_indices`): the batch positions p = step * B + b are cut into "virtual
epochs" of L positions (L: the total scene count, times the smallest factor making it at
least `MIN_EPOCH`, so the rounding of the shares stays below 1/L). In epoch e, cache i gets
n_i = round(w_i / sum(w) * L) of the positions, laid out in a random order drawn from
(seed, e); the k-th of cache i's positions in epoch e takes place e * n_i + k of cache i's
own stream, which runs through per-pass permutations of that cache drawn from (seed, pass,
i). Everything is a function of (seed, step) alone, so a resumed run draws what an
uninterrupted one would. With one cache this is the plain epoch-permutation order
(`batch_indices`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from collections.abc import Sequence

import jax
import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.data.cache import ACTOR_FIELDS, Cache, check_compatible, load_cache
from scenegen_jax.scene import Actors
from scenegen_jax.train.step import Batch

MIN_EPOCH = 4096  # positions per virtual epoch at least (share rounding below 1/4096)


# ---------------------------------------------------------------------------- data order


def resolve_weights(sizes: Sequence[int], weights: Sequence[float] | None) -> np.ndarray:
    """Normalised draw probabilities per cache: `weights` / sum, or the scene counts' shares.

    Raises:
      ValueError on a count mismatch, a negative or non-finite weight, or an all-zero sum.
    """
    sizes = np.asarray(sizes, np.float64)
    w = sizes if weights is None else np.asarray(weights, np.float64)
    if w.shape != sizes.shape:
        raise ValueError(f"--weights: {w.size} weight(s) for {sizes.size} cache(s)")
    if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"--weights: {w.tolist()}: need finite weights >= 0, not all zero")
    return w / w.sum()


def epoch_slots(sizes: Sequence[int], shares: np.ndarray) -> np.ndarray:
    """Positions n_i per virtual epoch of each cache (largest-remainder rounding of
    shares * L; with the scene-count shares exactly L / total times each cache's size)."""
    total = int(np.sum(sizes))
    length = total * max(1, math.ceil(MIN_EPOCH / total))
    exact = np.asarray(shares, np.float64) * length
    n = np.floor(exact).astype(np.int64)
    short = length - int(n.sum())
    if short:
        n[np.argsort(-(exact - n), kind="stable")[:short]] += 1
    return n


@functools.lru_cache(maxsize=8)
def _layout(seed: int, epoch: int, slots: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(cache [L], rank among that cache's positions [L]) of virtual epoch `epoch`."""
    n = np.asarray(slots)
    length = int(n.sum())
    if len(n) == 1:  # one cache: nothing to interleave
        which = np.zeros(length, np.int64)
    else:  # its own stream of (seed, epoch): spawn_key keeps it apart from the caches'
        rng = np.random.default_rng(np.random.SeedSequence([seed, epoch], spawn_key=(1,)))
        which = np.repeat(np.arange(len(n)), n)[rng.permutation(length)]
    order = np.argsort(which, kind="stable")
    rank = np.empty(length, np.int64)
    rank[order] = np.arange(length) - np.repeat(np.cumsum(n) - n, n)
    which.flags.writeable = rank.flags.writeable = False
    return which, rank


@functools.lru_cache(maxsize=16)
def _pass_permutation(seed: int, epoch: int, cache: int, size: int) -> np.ndarray:
    """Cache `cache`'s scene order in its pass `epoch` (cache 0: the single-cache order)."""
    key = [seed, epoch] if cache == 0 else [seed, epoch, cache]
    perm = np.random.default_rng(key).permutation(size)
    perm.flags.writeable = False
    return perm


def draw_indices(
    sizes: Sequence[int],
    shares: np.ndarray | None,
    batch_size: int,
    seed: int,
    step: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(cache, scene index within it) [B] each of batch `step`; a pure function of its
    arguments. `shares`: draw probability per cache (`resolve_weights`; None: by size)."""
    sizes = [int(s) for s in sizes]
    if min(sizes) < 1:
        raise ValueError(f"every cache needs at least one scene; sizes {sizes}")
    shares = resolve_weights(sizes, None) if shares is None else np.asarray(shares)
    n = epoch_slots(sizes, shares)
    pos = step * batch_size + np.arange(batch_size)
    epochs, offsets = np.divmod(pos, int(n.sum()))
    which = np.empty(batch_size, np.int64)
    local = np.empty(batch_size, np.int64)
    for epoch in np.unique(epochs):
        sel = epochs == epoch
        layout, rank = _layout(seed, int(epoch), tuple(int(x) for x in n))
        c = layout[offsets[sel]]
        stream = int(epoch) * n[c] + rank[offsets[sel]]
        passes, k = np.divmod(stream, np.asarray(sizes)[c])
        which[sel] = c
        local[sel] = [
            _pass_permutation(seed, int(p), int(ci), sizes[ci])[ki]
            for ci, p, ki in zip(c, passes, k, strict=True)
        ]
    return which, local


def batch_indices(num_scenes: int, batch_size: int, seed: int, step: int) -> np.ndarray:
    """Scene indices of batch `step` of one cache: consecutive slices of per-epoch
    permutations (`draw_indices` with one cache)."""
    return draw_indices([num_scenes], None, batch_size, seed, step)[1]


# ---------------------------------------------------------------------------- several caches


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


def _pad_slots(x: np.ndarray, slots: int) -> np.ndarray:
    if x.shape[1] == slots:
        return x
    pad = [(0, 0), (0, slots - x.shape[1])] + [(0, 0)] * (x.ndim - 2)
    return np.pad(x, pad)  # zeros: invalid, class 0


@dataclasses.dataclass
class CacheUnion:
    """Several caches read as one: the fields of a `Cache` over all their scenes (cache 0's
    scenes first), so `gather_batch`, `score_cache` and `cached_scene` take it as they take
    a cache. Maps stay memory-mapped per cache; actor arrays are padded to the largest slot
    count and concatenated (the members' actors are views into them). One cache is its own
    union, with its arrays as they are."""

    members: list[Cache]
    offsets: np.ndarray  # [N + 1] first scene of each member, then the total
    labels: list[str]  # `source_labels`
    path: str
    meta: dict
    maps: np.ndarray | StackedMaps
    actors: Actors
    ego_velocity: np.ndarray
    ego_size: np.ndarray
    city_from_ego: np.ndarray

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
            return cls(caches, offsets, labels, c.path, c.meta, c.maps, c.actors,
                       c.ego_velocity, c.ego_size, c.city_from_ego)
        slots = max(c.actors.cls.shape[1] for c in caches)
        actors = Actors(**{
            k: np.concatenate([_pad_slots(getattr(c.actors, k), slots) for c in caches])
            for k in ACTOR_FIELDS
        })
        per_scene = {k: np.concatenate([getattr(c, k) for c in caches])
                     for k in ("ego_velocity", "ego_size", "city_from_ego")}
        members = []
        for c, a, b in zip(caches, offsets[:-1], offsets[1:], strict=True):
            members.append(dataclasses.replace(
                c,
                actors=Actors(**{k: getattr(actors, k)[a:b] for k in ACTOR_FIELDS}),
                **{k: v[a:b] for k, v in per_scene.items()},
            ))
        first = caches[0].meta
        meta = {
            **{k: first[k] for k in ("version", "grid_size", "m_per_px", "canvas_size",
                                     "channels") if k in first},
            "slots": slots,
            "scene_ids": [sid for c in caches for sid in c.scene_ids],
            "members": [c.path for c in caches],
            "source": {},
        }
        return cls(members, offsets, labels, " + ".join(c.path for c in caches), meta,
                   StackedMaps([c.maps for c in caches], offsets), actors, **per_scene)

    def __len__(self) -> int:
        return int(self.offsets[-1])

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
    paths = [paths] if isinstance(paths, str) else list(paths)
    caches = [load_cache(p) for p in paths]
    if cfg is not None:
        check_compatible(caches, cfg)
    return CacheUnion.of(caches)


def union_indices(union: CacheUnion, shares: np.ndarray | None, batch_size: int, seed: int,
                  step: int) -> np.ndarray:
    """Union scene indices of training batch `step` (`draw_indices` over its members)."""
    which, local = draw_indices(union.sizes, shares, batch_size, seed, step)
    return union.offsets[which] + local


# ---------------------------------------------------------------------------- batches


def gather_batch(cache: Cache | CacheUnion, indices: np.ndarray, cfg: Config) -> Batch:
    """Host arrays of the scenes `indices` (canvas kept in float16)."""
    indices = np.asarray(indices)
    actors = Actors(**{k: np.asarray(getattr(cache.actors, k)[indices]) for k in ACTOR_FIELDS})
    n = len(indices)
    ego = Actors(
        cls=np.zeros(n, np.int32),
        position=np.zeros((n, 2), np.float32),
        size=cache.ego_size[indices],
        heading=np.zeros(n, np.float32),
        velocity=cache.ego_velocity[indices],
        valid=np.ones(n, bool),
    )
    canvas = np.stack([np.asarray(cache.maps[i]) for i in indices])
    return Batch(canvas=canvas, actors=actors, ego=ego)


def to_device(batch: Batch, sharding=None) -> Batch:
    """Puts a host batch on device(s), sharded along the batch axis if `sharding` is given."""
    return jax.tree.map(lambda x: jax.device_put(x, sharding), batch)
