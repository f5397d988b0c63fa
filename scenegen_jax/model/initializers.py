"""Initial parameters: flax's initialiser distributions drawn from one PRNG call per block of
values (`InitialDraws`), and the starting biases of the attribute heads."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy import special

from scenegen_jax.distributions import params as P
from scenegen_jax.distributions import uniforms


def bias_init(row):
    """Initialiser of a last layer's bias [n, len(row)]: `row` for every class."""
    row = np.asarray(row)

    def f(key, shape, dtype=jnp.float32):
        del key
        if shape[-1] != row.shape[0]:
            raise ValueError(f"attribute bias: shape {shape} does not end in {row.shape[0]}")
        return jnp.broadcast_to(jnp.asarray(row, dtype), shape)

    return f


def attribute_bias_rows(k: int):
    """Initial biases of the last attribute layers (box, heading, velocity): box zeros, then
    the heading and velocity starts of `distributions.params` (near-uniform, evenly spread
    mixtures)."""
    return np.zeros(P.box_params_size(k)), P.initial_heading_bias(k), P.initial_velocity_bias(k)


# Values per PRNG call of the initial parameters (`InitialDraws`).
INIT_BLOCK = 1 << 20
# The standard deviation of a standard normal truncated to [-2, 2] (jax.nn.initializers).
TRUNCATED_STD = 0.87962566103423978


class InitialDraws:
    """The random initial parameters' values, from one PRNG call per `INIT_BLOCK` values of
    each distribution, handed out in the order the parameters are created. Each `jax.random`
    call compiles its own kernels, so a call per parameter (flax's initialisers) makes the
    initialisation program slow to compile. So a parameter's values depend on the seed and
    on the parameters created before it (the config), not on its name alone; their
    distributions are flax's (`variance_scaling`)."""

    def __init__(self, key: jax.Array | None):
        self._key = key  # None where the network reads stored parameters (see `_standard`)
        self._blocks = 0
        self._left: dict[str, jnp.ndarray] = {}

    def _standard(self, distribution: str, n: int) -> jnp.ndarray:
        """n standard draws: "normal", or "truncated_normal" (within [-2, 2]). Zeros without
        a key: `apply` runs no initialiser but flax's `nn.Dense`, which traces its kernel's
        for the shape alone (`jax.eval_shape`)."""
        if self._key is None:
            return jnp.zeros((n,))
        left = self._left.get(distribution, jnp.zeros((0,)))
        if n > left.shape[0]:  # a new block (what is left of the last one is dropped)
            u = uniforms(jax.random.fold_in(self._key, self._blocks), (max(n, INIT_BLOCK),))
            self._blocks += 1
            if distribution == "truncated_normal":
                lo = special.ndtr(-2.0)
                left = jnp.clip(special.ndtri(lo + (1.0 - 2.0 * lo) * u), -2.0, 2.0)
            elif distribution == "normal":
                left = special.ndtri(u)
            else:
                raise ValueError(f"initial draws: unknown distribution {distribution!r}")
        self._left[distribution] = left[n:]
        return left[:n]

    def variance_scaling(self, scale: float, distribution: str, stacked: bool = False):
        """`jax.nn.initializers.variance_scaling(scale, "fan_in", distribution)` ("normal" or
        "truncated_normal") drawn from these values; with `stacked`, independent copies along
        the leading axis (fans from the rest)."""

        def init(key, shape, dtype=jnp.float32):
            del key  # every value comes from the draws
            one = shape[1:] if stacked else shape
            fan_in = int(np.prod(one)) // one[-1]  # receptive field x input channels
            std = np.sqrt(scale / fan_in)
            if distribution == "truncated_normal":
                std /= TRUNCATED_STD
            z = self._standard(distribution, int(np.prod(shape)))
            return (z * std).reshape(shape).astype(dtype)

        return init

    def lecun_normal(self, stacked: bool = False):
        """`jax.nn.initializers.lecun_normal()` (flax's default for weights)."""
        return self.variance_scaling(1.0, "truncated_normal", stacked)
