"""Winograd's minimal filtering F(4, r): 'SAME' stride-1 convolutions with fewer products.

A convolution with an r x r kernel computes each output pixel with r * r products per input
channel. Winograd's algorithm (Lavin and Gray, "Fast Algorithms for Convolutional Neural
Networks", 2016) computes a 4 x 4 tile of outputs from an (r + 3) x (r + 3) tile of inputs:
each input tile is transformed (B^T d B), multiplied element by element with the transformed
kernel (G g G^T), summed over input channels (one matrix product per element of the tile),
and transformed back (A^T m A). For a 5 x 5 kernel that is 64 products per 16 outputs per
input channel instead of 400: 6.25x fewer. The input transform is two small matrix products
(B^T over the tiles' rows, then over their columns, 8 x 8 each), the output transform one
(A^T (x) A^T, 16 x 64) and a transpose: few operations, so that a program with several of
these convolutions compiles quickly.

The matrices come from the Cook-Toom construction on the points 0, 1, -1, 2, -2, 1/2, -1/2 and
infinity: A^T and G are written down from the points and B^T is solved exactly from the
identity the three must satisfy (`transforms`). In float32 the result matches the direct
convolution to about 1e-5 relative (tests/test_winograd.py).

Where it pays is the backend's choice (`backend.winograd_convolutions`): on CPUs without
AVX-512, whose matrix products run at half the width, the product count decides; with
AVX-512 the transforms' memory traffic costs more than the products saved (docs/performance.md).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

TILE = 4  # outputs per tile side (the m of F(m, r))
POINTS = (0.0, 1.0, -1.0, 2.0, -2.0, 0.5, -0.5)  # besides infinity; enough for r <= 5


@functools.cache
def transforms(m: int, r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A^T [m, n], G [n, r], B^T [n, n]) of F(m, r), n = m + r - 1, for which the correlation
    y_i = sum_k d_{i+k} g_k (i < m, k < r) of an input d of length n equals
    A^T ((G g) * (B^T d)). A^T and G are the Cook-Toom matrices on `POINTS` and infinity; B^T
    is the exact solution of sum_j A^T[i, j] G[j, k] B^T[j, l] = [l == i + k]."""
    n = m + r - 1
    if n - 1 > len(POINTS):
        raise ValueError(f"F({m}, {r}) needs {n - 1} finite points; POINTS has {len(POINTS)}")
    points = POINTS[: n - 1]
    at = np.zeros((m, n))
    g = np.zeros((n, r))
    for j, p in enumerate(points):
        scale = np.prod([p - q for q in points if q != p])
        at[:, j] = p ** np.arange(m)
        g[j] = p ** np.arange(r) / scale
    at[m - 1, n - 1] = 1.0  # the point at infinity
    g[n - 1, r - 1] = 1.0
    products = np.stack([at[i] * g[:, k] for i in range(m) for k in range(r)])  # [m r, n]
    shifts = np.zeros((m * r, n))
    for i in range(m):
        for k in range(r):
            shifts[i * r + k, i + k] = 1.0
    bt = np.linalg.solve(products.T @ products, products.T @ shifts)
    bt[np.abs(bt) < 1e-12] = 0.0
    if not np.allclose(products @ bt, shifts, atol=1e-9):
        raise ArithmeticError(f"F({m}, {r}): the points give no exact input transform")
    return at, g, bt


def _strided(x, start: int, count: int, axis: int):
    """count slices of x along axis, TILE apart, from start."""
    return jax.lax.slice_in_dim(x, start, start + TILE * (count - 1) + 1, TILE, axis=axis)


def _input_tiles(xp, r: int):
    """Transformed input tiles of xp [B, TILE * th + n - TILE, TILE * tw + n - TILE, C], an
    input padded for an r x r kernel (n = TILE + r - 1): [n * n, B * th * tw, C], element
    (a, b) of every tile first. B^T d B as two small matrix products, one over the tiles' rows
    and one over their columns, each on the n strided slices of its axis stacked: about 20
    operations, where sums of slices with B^T's weights (up to n slices for each of the n * n
    elements) would make a program of ~1,600 lines a convolution that compiles several times
    slower."""
    _, _, bt = transforms(TILE, r)
    n = bt.shape[0]
    b, hp, wp, c = xp.shape
    th, tw = (hp - n) // TILE + 1, (wp - n) // TILE + 1
    bt = jnp.asarray(bt, xp.dtype)
    rows = jnp.stack([_strided(xp, k, th, 1) for k in range(n)])  # [n, B, th, wp, C]
    v = jnp.einsum("ak,kbhwc->abhwc", bt, rows)
    cols = jnp.stack([_strided(v, k, tw, 3) for k in range(n)])  # [n, n, B, th, tw, C]
    t = jnp.einsum("ek,kabhwc->aebhwc", bt, cols)
    return t.reshape(n * n, b * th * tw, c)


def _kernel(w):
    """Transformed kernel G w G^T of w [r, r, Ci, Co]: [n * n, Ci, Co]."""
    _, g, _ = transforms(TILE, w.shape[0])
    g = jnp.asarray(g, w.dtype)
    t = jnp.einsum("ak,klio,bl->abio", g, w, g)
    return t.reshape(-1, *w.shape[2:])


def _output(m, b: int, th: int, tw: int, r: int):
    """The output tiles [B, TILE * th, TILE * tw, Co] of an r x r kernel's products
    m [n * n, B * th * tw, Co]: A^T m A per tile, as one matrix product of the Kronecker
    product A^T (x) A^T [TILE * TILE, n * n] with m, then one transpose that interleaves the
    tiles' rows and columns. Written as sums of slices stacked into the tiles, it runs slower
    under XLA:CPU's fusion emitters (the sampler's) than the products themselves."""
    at, _, _ = transforms(TILE, r)
    y = jnp.einsum("ka,axo->kxo", jnp.asarray(np.kron(at, at), m.dtype), m)
    y = y.reshape(TILE, TILE, b, th, tw, m.shape[-1]).transpose(2, 3, 0, 4, 1, 5)
    return y.reshape(b, th * TILE, tw * TILE, -1)


def tiles(shape: tuple[int, ...]) -> int:
    """Output tiles of a convolution of an input of shape [B, H, W, C]: B * th * tw."""
    b, h, w, _ = shape
    return b * -(-h // TILE) * -(-w // TILE)


def conv_sum(xs, ws):
    """sum_i conv(xs[i], ws[i]): 'SAME' stride-1 convolutions of x [B, H, W, Ci_i] with
    w [r, r, Ci_i, Co] (every r the same, odd), through F(4, r). The inputs' tiles are joined
    along the channels, so the sum costs one matrix product per tile element and one output
    transform, as one convolution over the joined channels would."""
    r = ws[0].shape[0]
    if any(w.shape[:2] != (r, r) for w in ws) or r % 2 == 0:
        raise ValueError(f"winograd.conv_sum: square kernels of one odd size, got "
                         f"{[w.shape for w in ws]}")
    n = TILE + r - 1
    b, h, w, _ = xs[0].shape
    th, tw = -(-h // TILE), -(-w // TILE)
    pad_h = (r // 2, th * TILE + n - TILE - r // 2 - h)
    pad_w = (r // 2, tw * TILE + n - TILE - r // 2 - w)
    xps = [jnp.pad(x, ((0, 0), pad_h, pad_w, (0, 0))) for x in xs]
    tiled = jnp.concatenate([_input_tiles(x, r) for x in xps], axis=-1)
    kernel = jnp.concatenate([_kernel(w) for w in ws], axis=1).astype(tiled.dtype)
    m = jnp.einsum("tnc,tco->tno", tiled, kernel)
    return _output(m, b, th, tw, r)[:, :h, :w]
