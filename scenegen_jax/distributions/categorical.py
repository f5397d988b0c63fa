"""Class and location categoricals: log-likelihoods, hard negative mining, ordering mask, samplers.

Per example (unbatched); vmap for batches. Location bins are row-major over the H x W
raster (see `scenegen_jax.scene` for the grid convention); the continuous position density
is uniform inside a bin, so log p(x, y) = log pi[bin] - log(bin_area) in nats per m^2.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy import special

from scenegen_jax.config import GridConfig
from scenegen_jax.scene import bin_center

# Sampled positions stay this fraction of a pixel inside their bin, so float32 rounding
# never moves them into a neighbouring bin.
_EDGE = 1e-4


def uniforms(key: jax.Array, shape) -> jnp.ndarray:
    """Uniform draws in (0, 1) (float32, never 0): one PRNG call for everything a sampler
    needs. Each `jax.random` call compiles its own hash loop, and one loop per draw would
    take a large share of the sampler's compile time on XLA:CPU."""
    return jax.random.uniform(key, shape, minval=jnp.finfo(jnp.float32).tiny, maxval=1.0)


def offsets_in_bin(u: jnp.ndarray, grid: GridConfig) -> jnp.ndarray:
    """Offsets (x, y) [..., 2], m, from a bin's centre, uniform inside the bin, made from
    uniforms `u` [..., 2] in (0, 1); `_EDGE` of a pixel away from the bin's sides."""
    return (_EDGE + (1.0 - 2.0 * _EDGE) * u - 0.5) * grid.m_per_px


def gumbel_argmax(u: jnp.ndarray, logits: jnp.ndarray) -> jnp.ndarray:
    """A draw from the categorical `logits` [..., K] (int32 [...]) made from uniforms `u` in
    (0, 1) of the same shape: the Gumbel-max trick, as `jax.random.categorical`."""
    return jnp.argmax(logits - jnp.log(-jnp.log(u)), axis=-1).astype(jnp.int32)


# ----------------------------------------------------------------------------- class
def class_log_prob(logits: jnp.ndarray, cls: jnp.ndarray) -> jnp.ndarray:
    """Log probability of class `cls` under `logits` [4] (vehicle, pedestrian, bicyclist, stop)."""
    return jax.nn.log_softmax(logits)[cls]


def sample_class(key: jax.Array, logits: jnp.ndarray) -> jnp.ndarray:
    """Draws a class id (int32; STOP = 3 ends the scene) from `logits` [4]."""
    return gumbel_argmax(uniforms(key, logits.shape), logits)


# ----------------------------------------------------------------------------- location
def location_log_prob(logits: jnp.ndarray, bin: jnp.ndarray, bin_area: float) -> jnp.ndarray:
    """Log density (log 1/m^2) of a position in `bin` under the full softmax of `logits` [H*W].

    Args:
      logits: [H*W] location logits, row-major bins.
      bin: row-major bin index of the position.
      bin_area: area of one bin, m^2.
    """
    return jax.nn.log_softmax(logits)[bin] - jnp.log(bin_area)


def hard_negative_log_prob(logits: jnp.ndarray, bin: jnp.ndarray, n: int) -> jnp.ndarray:
    """Log probability of `bin` normalised over the `n` highest logits including `bin`.

    Online hard negative mining (supplementary sec. 1.3): the positive is forced into the
    selection, then the top `n` bins (the positive and the n - 1 hardest negatives) are
    normalised with the true logits. With n >= H*W this is the full log softmax. Used for
    training only; evaluation always uses the full softmax.

    Args:
      logits: [H*W] location logits.
      bin: row-major index of the positive bin.
      n: static number of bins in the normaliser.

    Returns:
      Scalar log probability (nats, per bin; subtract log(bin_area) for a density).
    """
    logits = jnp.asarray(logits)
    n_bins = logits.shape[-1]
    if n >= n_bins:
        return jax.nn.log_softmax(logits)[bin]
    forced = logits.at[bin].set(jnp.inf)
    _, idx = jax.lax.top_k(jax.lax.stop_gradient(forced), n)
    return logits[bin] - special.logsumexp(logits[idx])


def ordering_mask(prev_bin: jnp.ndarray, n_bins: int) -> jnp.ndarray:
    """bool [n_bins]: bins allowed after an actor in `prev_bin` (canonical order, ties allowed).

    Bins before `prev_bin` are excluded (they get -inf logits); prev_bin = 0 allows all,
    prev_bin >= n_bins allows none.
    """
    return jnp.arange(n_bins) >= prev_bin


def masked_log_softmax(logits: jnp.ndarray, mask: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Log softmax renormalised over `mask`; -inf outside it.

    Returns:
      (log_probs [n], any_valid). When no bin is allowed every entry is -inf and any_valid
      is False; values and gradients stay free of NaN.
    """
    log_z = special.logsumexp(jnp.where(mask, logits, -jnp.inf))  # -inf (no NaN) if empty
    return jnp.where(mask, logits - log_z, -jnp.inf), jnp.any(mask)


def masked_location_log_prob(
    logits: jnp.ndarray, mask: jnp.ndarray, bin: jnp.ndarray, bin_area: float
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Log density (log 1/m^2) of `bin` under the location categorical restricted to `mask`.

    Returns:
      (log_prob, any_valid); log_prob is -inf for a bin outside the mask or when the mask
      allows no bin (then any_valid is False).
    """
    log_probs, any_valid = masked_log_softmax(logits, mask)
    return log_probs[bin] - jnp.log(bin_area), any_valid


def sample_bins(key: jax.Array, log_probs: jnp.ndarray, count: int, width: int) -> jnp.ndarray:
    """`count` i.i.d. bins [count] int32 from the categorical with log-probabilities
    `log_probs` [H*W] (row-major bins, rows of `width`; -inf: excluded).

    Each bin is drawn as a row, from the rows' total masses, then a column within that row:
    P(r, c) = P(r) P(c | r), the same distribution as `jax.random.categorical(key, log_probs,
    shape=(count,))` with H + W Gumbel draws per bin instead of H * W.
    """
    grid = log_probs.reshape(-1, width)
    h = grid.shape[0]
    u = uniforms(key, (count, h + width))
    rows = gumbel_argmax(u[:, :h], jax.nn.logsumexp(grid, axis=1))
    cols = gumbel_argmax(u[:, h:], grid[rows])
    return rows * width + cols


def sample_location(
    key: jax.Array, logits: jnp.ndarray, grid: GridConfig, mask: jnp.ndarray | None = None
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Draws a location bin from `logits` [H*W] (restricted to `mask`), then a position in it.

    Args:
      key: PRNG key.
      logits: [H*W] location logits, row-major bins.
      grid: the grid (`GridConfig`: grid_size, m_per_px).
      mask: optional bool [H*W] of allowed bins (e.g. `ordering_mask`).

    Returns:
      (bin int32, position [2] (x, y) m uniform inside the bin, any_valid). If the mask
      allows no bin, bin is the last bin H*W - 1 and any_valid is False (callers stop).
    """
    n_bins = logits.shape[-1]
    if mask is None:
        mask = jnp.ones((n_bins,), bool)
    k_bin, k_pos = jax.random.split(key)
    log_probs, any_valid = masked_log_softmax(logits, mask)
    bin_ = sample_bins(k_bin, jnp.where(any_valid, log_probs, 0.0), 1, grid.grid_size)[0]
    bin_ = jnp.where(any_valid, bin_, n_bins - 1)
    offset = offsets_in_bin(uniforms(k_pos, (2,)), grid)
    return bin_, bin_center(bin_, grid) + offset, any_valid
