"""The layers the network is built of: 'SAME' convolutions (direct, with the weight gradient
in row bands, or Winograd's forward pass, as the backend chooses), the per-example
convolution of the location heads, GroupNorm and the per-class MLPs.

All arrays are NHWC; leading axes beyond one batch axis are flattened by the caller.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from scenegen_jax.backend import (
    explicit_conv_gradients,
    weight_gradient_bands,
    winograd_convolutions,
)
from scenegen_jax.model import winograd


def _conv(x, w, padding="SAME"):
    return jax.lax.conv_general_dilated(
        x, w, (1, 1), padding, dimension_numbers=("NHWC", "HWIO", "NHWC")
    )


def _band_starts(rows: int, band_rows: int) -> list[int]:
    """First rows of `ceil(rows / band_rows)` bands whose sizes differ by at most one row,
    then `rows`."""
    n = -(-rows // band_rows)
    return [i * rows // n for i in range(n)] + [rows]


def _same_pads(w) -> list[tuple[int, int]]:
    """'SAME' padding of the two spatial axes for kernel w [kh, kw, Ci, Co]."""
    return [((k - 1) // 2, k // 2) for k in w.shape[:2]]


def _conv_input_grad(g, w):
    """The input gradient of `_conv(x, w)` for the output gradient g [B, H, W, Co]: g
    convolved with the kernel turned by 180 degrees and its features swapped, written in the
    form XLA:CPU hands to its convolution library (NHWC, HWIO)."""
    pads = [(hi, lo) for lo, hi in _same_pads(w)]
    return _conv(g, jnp.flip(w, (0, 1)).swapaxes(2, 3), padding=pads)


def _conv_weight_grad(xp, g):
    """The weight gradient [kh, kw, Ci, Co] of the 'VALID' convolution of the padded input
    xp [B, H + kh - 1, W + kw - 1, Ci] for its output gradient g [B, H, W, Co], in the same
    library form: x's features as the batch, the batch as the features."""
    return _conv(xp.transpose(3, 1, 2, 0), g.transpose(1, 2, 0, 3), padding="VALID").transpose(
        1, 2, 0, 3)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _banded_conv(x, w, band_rows: int):
    """`_conv(x, w)` whose gradients are written in the convolution library's form, the
    weight gradient summed over bands of at most `band_rows` rows of the input (each with the
    kernel's halo)."""
    return _conv(x, w)


def _banded_conv_fwd(x, w, band_rows):
    return _conv(x, w), (x, w)


def _banded_conv_bwd(band_rows, res, g):
    x, w = res
    xp = jnp.pad(x, [(0, 0), *_same_pads(w), (0, 0)])
    kh = w.shape[0]
    starts = _band_starts(x.shape[1], band_rows)
    dw = jnp.zeros_like(w)
    for lo, hi in zip(starts[:-1], starts[1:], strict=True):
        band = jax.lax.slice_in_dim(xp, lo, hi + kh - 1, axis=1)  # the band and its halo
        dw = dw + _conv_weight_grad(band, jax.lax.slice_in_dim(g, lo, hi, axis=1))
    return _conv_input_grad(g, w), dw


_banded_conv.defvjp(_banded_conv_fwd, _banded_conv_bwd)


def _direct_conv(x, w):
    """'SAME' stride-1 convolution, x [B, H, W, Ci], w [kh, kw, Ci, Co]. Where the backend
    bands weight gradients (`backend.weight_gradient_bands`) and x has more rows than its
    threshold, the weight gradient is summed over row bands; where it wants the gradients in
    its library's form (`backend.explicit_conv_gradients`), they are written so (one band)."""
    bands = weight_gradient_bands()
    if bands is not None and x.shape[1] > bands[0]:
        return _banded_conv(x, w, bands[1])
    if explicit_conv_gradients():
        return _banded_conv(x, w, x.shape[1])
    return _conv(x, w)


@jax.custom_vjp
def _winograd_conv_sum(xs, ws):
    return winograd.conv_sum(xs, ws)


def _winograd_conv_sum_fwd(xs, ws):
    return winograd.conv_sum(xs, ws), (xs, ws)


def _winograd_conv_sum_bwd(res, g):
    """The direct convolutions' gradients: Winograd's forward pass only."""
    xs, ws = res
    grads = [jax.vjp(_direct_conv, x, w)[1](g) for x, w in zip(xs, ws, strict=True)]
    return tuple(gx for gx, _ in grads), tuple(gw for _, gw in grads)


_winograd_conv_sum.defvjp(_winograd_conv_sum_fwd, _winograd_conv_sum_bwd)


def conv_sum(terms, b=None):
    """sum of conv(x, w) over terms [(x, w), ...] (see `conv`), plus b. Where the backend
    takes Winograd's algorithm for these kernels (`backend.winograd_convolutions`), the sum is
    one Winograd convolution over the inputs' joined channels (gradients: the direct ones)."""
    xs, ws = (tuple(t) for t in zip(*terms, strict=True))
    if winograd_convolutions(ws[0].shape[:2], winograd.tiles(xs[0].shape)) and all(
            w.shape[:2] == ws[0].shape[:2] for w in ws):
        y = _winograd_conv_sum(xs, ws)
    else:
        y = functools.reduce(jnp.add, [_direct_conv(x, w) for x, w in terms])
    return y if b is None else y + b


def conv(x, w, b=None):
    """'SAME' stride-1 convolution, x [B, H, W, Ci], w [kh, kw, Ci, Co], plus b: direct
    (`_direct_conv`) or, where the backend takes it for this kernel and input size, Winograd's
    F(4, r) forward pass (`conv_sum`)."""
    return conv_sum([(x, w)], b)


def conv_per_example(x, w, b):
    """'SAME' convolution with a different kernel per example: x [M, H, W, Ci],
    w [M, kh, kw, Ci, Co], b [M, Co].

    Written as a sum of shifted batched matmuls: XLA:CPU's vmapped (grouped) convolution has a
    pathologically slow weight gradient, while batched matmuls differentiate efficiently.
    """
    kh, kw = w.shape[1:3]
    h, wd = x.shape[1:3]
    xp = jnp.pad(x, ((0, 0), (kh // 2, kh // 2), (kw // 2, kw // 2), (0, 0)))
    out = b[:, None, None, :]
    for dy in range(kh):
        for dx in range(kw):
            out = out + jnp.einsum("mhwi,mio->mhwo", xp[:, dy : dy + h, dx : dx + wd], w[:, dy, dx])
    return out


def group_norm(x, groups: int, scale, bias, eps: float = 1e-5):
    """GroupNorm over (H, W, channels of a group) of x [B, H, W, C]; scale and bias broadcast
    against [B, 1, 1, C].

    Each statistic is reduced over H and W first, channels staying the contiguous axis, then
    over each group's channels: XLA:CPU reduces the grouped 5-D view [B, H, W, G, C/G]
    several times slower, forward and backward (`bench/micro.py` measures both).
    """
    b, _, _, c = x.shape
    size = c // groups

    def group_mean(y):  # [B, H, W, C] -> each channel's group mean, [B, 1, 1, C]
        m = jnp.mean(y, axis=(1, 2)).reshape(b, groups, size).mean(-1)
        return jnp.repeat(m, size, axis=-1)[:, None, None, :]

    centred = x - group_mean(x)
    return centred * (jax.lax.rsqrt(group_mean(jnp.square(centred)) + eps) * scale) + bias


def per_class_mlp(x, ws, bs, cls):
    """A per-class MLP on x [B, i]: layer l uses ws[l][cls], bs[l][cls]; ReLU between."""
    for i, (w, b) in enumerate(zip(ws, bs, strict=True)):
        x = jnp.einsum("bi,bio->bo", x, w[cls]) + b[cls]
        if i < len(ws) - 1:
            x = jax.nn.relu(x)
    return x

