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
own stream, which runs through per-pass permutations of that cache drawn from (seed, pass)
for cache 0, (seed, pass, i) for the others. Everything is a function of (seed, step)
alone, so a resumed run draws what an uninterrupted one would. With one cache this is the
plain epoch-permutation order (`batch_indices`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np

from scenegen_jax.data.union import CacheUnion

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
    if not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
        raise ValueError(f"--weights: {w.tolist()}: need finite weights >= 0, not all zero")
    with np.errstate(over="ignore"):
        total = w.sum()
    if not np.isfinite(total):  # weights near float's limit: the same shares, scaled down
        w = w / w.max()
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
def _pass_permutation(seed: int, pass_index: int, cache: int, size: int) -> np.ndarray:
    """Cache `cache`'s scene order in its pass `pass_index` over its scenes (not a virtual
    epoch: a cache drawn more often than its size per epoch passes over its scenes faster;
    cache 0: the single-cache order)."""
    key = [seed, pass_index] if cache == 0 else [seed, pass_index, cache]
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


def union_indices(union: CacheUnion, shares: np.ndarray | None, batch_size: int, seed: int,
                  step: int) -> np.ndarray:
    """Union scene indices of training batch `step` (`draw_indices` over its members)."""
    which, local = draw_indices(union.sizes, shares, batch_size, seed, step)
    return union.offsets[which] + local
