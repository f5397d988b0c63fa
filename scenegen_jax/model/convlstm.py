"""The ConvLSTM cell update with a hand-written gradient (`lstm_gates`) that keeps XLA from
fusing the cell state's chain over the unrolled steps into every step."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def lstm_gates_reference(gates, c):
    """ConvLSTM cell update from pre-activation gates [.., 4h] (order i, f, o, g): (h, c)."""
    i, f, o, g = jnp.split(gates, 4, axis=-1)
    c = jax.nn.sigmoid(f) * c + jax.nn.sigmoid(i) * jnp.tanh(g)
    return jax.nn.sigmoid(o) * jnp.tanh(c), c


def _materialize(x):
    """x through a product with the identity (exact for finite x; a NaN spreads to its
    pixel's channels): XLA:CPU does not fuse elementwise work through a dot, and drops
    optimization barriers before fusion, so this makes it store x."""
    return jnp.einsum("...c,cd->...d", x, jnp.eye(x.shape[-1], dtype=x.dtype))


def _lstm_forward(gates, c):
    i, f, o, g = jnp.split(gates, 4, axis=-1)
    si, sf, so, tg = jax.nn.sigmoid(i), jax.nn.sigmoid(f), jax.nn.sigmoid(o), jnp.tanh(g)
    c_new = sf * c + si * tg
    tc = jnp.tanh(c_new)
    c_new = _materialize(c_new)
    return (so * tc, c_new), (si, sf, so, tg, c, tc)


def _lstm_backward(res, cotangents):
    si, sf, so, tg, c, tc = res
    dh, dc_new = cotangents
    dc = dc_new + dh * so * (1.0 - tc * tc)
    dgates = jnp.concatenate(
        [dc * tg * si * (1.0 - si), dc * c * sf * (1.0 - sf), dh * tc * so * (1.0 - so),
         dc * si * (1.0 - tg * tg)],
        axis=-1,
    )
    # Materialising the cell-state gradient (and the cell state in the forward) keeps XLA from
    # fusing the whole chain over the unrolled steps into every step (quadratic in T).
    return dgates, _materialize(dc * sf)


@jax.custom_vjp
def lstm_gates(gates, c):
    """`lstm_gates_reference` with a hand-written gradient (same values, same gradients).
    Without a gradient (scoring, sampling) it is the plain formula: nothing to materialise."""
    return lstm_gates_reference(gates, c)


lstm_gates.defvjp(_lstm_forward, _lstm_backward)
