"""Best-of-M proposals: draw M samples and keep the one most likely under its own density."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from scenegen_jax.scene import tree_take


def best_of_m(
    keys: jax.Array,
    sample_fn: Callable[[jax.Array, Any], Any],
    score_fn: Callable[[Any, Any], jnp.ndarray],
    params: Any,
    m: int,
    adjust: Callable[[Any, jnp.ndarray], jnp.ndarray] | None = None,
) -> Any:
    """For each of R examples, the most likely of `m` draws.

    Works for any attribute: `sample_fn(key, params)` returns one example's PyTree draw and
    `score_fn(params, draw)` its scalar score (a log-likelihood; bind extra arguments with a
    lambda, and put per-example ones into `params`). The R x M draws run as ONE flat vmap
    (nesting a vmap over M inside one over R doubled XLA:CPU's compile time of the sampler).
    Example r splits keys[r] into its M proposal keys (or takes keys[r] [M] as they are).
    NaN scores never win; ties keep the first draw; with m = 1 the single draw is returned
    unscored (plain sampling).

    Args:
      keys: [R] PRNG keys, or [R, M] proposal keys (one split for several attributes: each
        `jax.random` call compiles its own hash loop, `distributions.uniforms`).
      sample_fn: per-example sampler.
      score_fn: per-example score of a draw.
      params: PyTree of distribution parameters with leading axis R (e.g. raw head outputs).
      m: static number of proposals M >= 1.
      adjust: optional `(draws [R * M, ...], scores [R, M]) -> scores [R, M]`, for rules
        that look across an example's proposals (e.g. the velocity's standing decision).

    Returns:
      The chosen draws, leading axis R.
    """
    if m < 1:
        raise ValueError(f"best_of_m needs m >= 1, got {m}")
    r = keys.shape[0]
    if keys.ndim == 1:
        keys = jax.vmap(lambda k: jax.random.split(k, m))(keys)
    proposal_keys = keys.reshape(r * m)
    flat = jax.tree.map(lambda x: jnp.repeat(x, m, axis=0), params)  # proposals adjacent
    draws = jax.vmap(sample_fn)(proposal_keys, flat)
    if m == 1:
        return draws
    scores = jax.vmap(score_fn)(flat, draws).reshape(r, m)
    if adjust is not None:
        scores = adjust(draws, scores)
    scores = jnp.where(jnp.isnan(scores), -jnp.inf, scores)
    chosen = jnp.arange(r) * m + jnp.argmax(scores, axis=1)
    return tree_take(draws, chosen)
