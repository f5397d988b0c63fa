"""Best-of-M proposals: draw M samples and keep the one most likely under its own density."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp


def best_of_m(
    key: jax.Array,
    sample_fn: Callable[[jax.Array, Any], Any],
    log_prob_fn: Callable[[Any, Any], jnp.ndarray],
    params: Any,
    m: int,
) -> tuple[Any, jnp.ndarray]:
    """Draws `m` samples and returns the one with the highest log-likelihood.

    Works for any attribute: `sample_fn(key, params)` returns a PyTree sample and
    `log_prob_fn(params, sample)` its scalar log-likelihood (bind extra arguments such as
    heading or zero_speed with a lambda). The M draws use `vmap` over `split(key, m)`;
    with m = 1 it is exactly `sample_fn(key, params)`. Ties keep the first draw.

    Args:
      key: PRNG key.
      sample_fn: per-example sampler.
      log_prob_fn: per-example log-likelihood of a sample.
      params: distribution parameters (e.g. a raw head output).
      m: static number of proposals M >= 1.

    Returns:
      (sample, log_prob) of the most likely draw.
    """
    if m < 1:
        raise ValueError(f"best_of_m needs m >= 1, got {m}")
    if m == 1:
        sample = sample_fn(key, params)
        return sample, log_prob_fn(params, sample)
    samples = jax.vmap(sample_fn, in_axes=(0, None))(jax.random.split(key, m), params)
    log_probs = jax.vmap(log_prob_fn, in_axes=(None, 0))(params, samples)
    # NaN never wins: it would make argmax pick it.
    best = jnp.argmax(jnp.where(jnp.isnan(log_probs), -jnp.inf, log_probs))
    return jax.tree_util.tree_map(lambda x: x[best], samples), log_probs[best]
