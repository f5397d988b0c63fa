"""SceneGen network (paper supplementary sec. 1.2): a two-layer ConvLSTM over BEV rasters, a
five-layer conv backbone, a class MLP, per-class location CNNs and per-class attribute MLPs.

The network is split into methods so the teacher-forced unroll can be fast (see
`scenegen_jax.likelihood.unroll`): the first ConvLSTM layer's input convolution is linear in its
input, so conv(map ++ actors ++ h1) = conv_map(map) + conv_actors(actors) + conv_rec(h1).
The map part is computed once per scene. The backbone and heads do not feed back into the
recurrence, so the unroll can run them on chunks of steps.

All arrays are NHWC; leading axes beyond one batch axis are flattened by the caller.
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import errors
from jax.scipy import special

from scenegen_jax.backend import (
    compiled_init,
    explicit_conv_gradients,
    weight_gradient_bands,
    winograd_convolutions,
)
from scenegen_jax.config import Config
from scenegen_jax.distributions import params as P
from scenegen_jax.distributions import uniforms
from scenegen_jax.model import winograd
from scenegen_jax.raster.actors import NUM_ACTOR_CHANNELS, window_origin, window_size
from scenegen_jax.raster.map import NEAREST_LANE_CHANNELS, ORIENTATION_CHANNELS
from scenegen_jax.scene import NUM_CLASSES

ATTRIBUTES = ("box", "heading", "velocity")  # the attribute heads, in output order
# The parameters that read the map channels, and the axis of the channels in each.
MAP_CHANNEL_AXIS = {"lstm1_map": 2, **{f"{name}{layer}_map_w": 1
                                       for name in ATTRIBUTES for layer in (0, 2)}}


def attribute_sizes(k: int) -> tuple[int, int, int]:
    """Flat head sizes (box, heading, velocity) for K mixture components."""
    return P.box_params_size(k), P.heading_params_size(k), P.velocity_params_size(k)


def orientation_sectors(cos, sin, k: int):
    """The lane orientation (cos, sin) [...] as K sector weights [..., K]: the direction's
    weight (its length: 1 inside a lane, 0 outside) split linearly between the two of the K
    equal sectors whose centres (0, 2 pi / K, ...) are nearest to it."""
    u = jnp.arctan2(sin, cos)[..., None] * (k / (2 * np.pi))  # in sector widths
    d = jnp.abs(jnp.mod(u - jnp.arange(k) + k / 2, k) - k / 2)  # circular distance to centres
    return jnp.hypot(cos, sin)[..., None] * jnp.maximum(0.0, 1.0 - d)


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
    over each group's channels: XLA:CPU reduced the grouped 5-D view [B, H, W, G, C/G] 4x
    slower, forward and backward (bench/README.md).
    """
    b, _, _, c = x.shape
    size = c // groups

    def group_mean(y):  # [B, H, W, C] -> each channel's group mean, [B, 1, 1, C]
        m = jnp.mean(y, axis=(1, 2)).reshape(b, groups, size).mean(-1)
        return jnp.repeat(m, size, axis=-1)[:, None, None, :]

    centred = x - group_mean(x)
    return centred * (jax.lax.rsqrt(group_mean(jnp.square(centred)) + eps) * scale) + bias


def _bias_init(row):
    """Initialiser of a last layer's bias [n, len(row)]: `row` for every class."""
    row = np.asarray(row)

    def f(key, shape, dtype=jnp.float32):
        del key
        if shape[-1] != row.shape[0]:
            raise ValueError(f"attribute bias: shape {shape} does not end in {row.shape[0]}")
        return jnp.broadcast_to(jnp.asarray(row, dtype), shape)

    return f


def _attribute_bias_rows(k: int):
    """Initial biases of the last attribute layers (box, heading, velocity): box zeros, then
    the heading and velocity starts of `distributions.params` (near-uniform, evenly spread
    mixtures)."""
    return np.zeros(P.box_params_size(k)), P.initial_heading_bias(k), P.initial_velocity_bias(k)


def _mlp(x, ws, bs, cls):
    """A per-class MLP on x [B, i]: layer l uses ws[l][cls], bs[l][cls]; ReLU between."""
    for i, (w, b) in enumerate(zip(ws, bs, strict=True)):
        x = jnp.einsum("bi,bio->bo", x, w[cls]) + b[cls]
        if i < len(ws) - 1:
            x = jax.nn.relu(x)
    return x


# Values per PRNG call of the initial parameters (`InitialDraws`).
INIT_BLOCK = 1 << 20
# The standard deviation of a standard normal truncated to [-2, 2] (jax.nn.initializers).
TRUNCATED_STD = 0.87962566103423978


class InitialDraws:
    """The random initial parameters' values, from one PRNG call per `INIT_BLOCK` values of
    each distribution, handed out in the order the parameters are created. Each `jax.random`
    call compiles its own kernels: a call per parameter (flax's initialisers) made `tiny`'s
    initialisation program compile in 2.7 s on a slow Xeon (bench/README.md, session 45).
    So a parameter's values depend on the seed and on the parameters created before it (the
    config), not on its name alone; their distributions are flax's (`variance_scaling`)."""

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


class SceneGenNet(nn.Module):
    """The network. Parameters are a plain PyTree (Linen), shapes from the config."""

    cfg: Config

    def setup(self):
        cfg = self.cfg
        h = cfg.hidden
        cm = len(cfg.map_channels)
        # A key only where the parameters are created (`apply` reads them).
        draws = InitialDraws(self.make_rng("params") if self.is_initializing() else None)
        conv_init = draws.lecun_normal()
        stacked_conv_init = draws.lecun_normal(stacked=True)
        zeros = nn.initializers.zeros
        ones = nn.initializers.ones

        def lstm_bias(key, shape, dtype=jnp.float32):
            # Forget gate biased open so the state persists at the start of training.
            return jnp.zeros(shape, dtype).at[h : 2 * h].set(1.0)

        if cm:
            self.lstm1_map = self._param("lstm1_map", conv_init, (5, 5, cm, 4 * h))
        if cfg.coord_channels:
            self.lstm1_coord = self._param("lstm1_coord", conv_init, (5, 5, 2, 4 * h))
        if cfg.order_channel:
            self.lstm1_order = self._param("lstm1_order", conv_init, (5, 5, 1, 4 * h))
        if cfg.orientation_bins:
            self.lstm1_orient = self._param(
                "lstm1_orient", conv_init, (5, 5, cfg.orientation_bins, 4 * h))
        self.lstm1_act = self._param("lstm1_act", conv_init, (5, 5, NUM_ACTOR_CHANNELS, 4 * h))
        self.lstm1_rec = self._param("lstm1_rec", conv_init, (5, 5, h, 4 * h))
        self.lstm1_b = self._param("lstm1_b", lstm_bias, (4 * h,))
        self.lstm2_w = self._param("lstm2_w", conv_init, (5, 5, 2 * h, 4 * h))
        self.lstm2_b = self._param("lstm2_b", lstm_bias, (4 * h,))
        self.backbone_w = [
            self._param(f"backbone{i}_w", conv_init, (3, 3, h, h))
            for i in range(cfg.backbone_layers)
        ]
        self.backbone_b = [
            self._param(f"backbone{i}_b", zeros, (h,)) for i in range(cfg.backbone_layers)
        ]
        self.backbone_gs = [
            self._param(f"backbone{i}_gn_s", ones, (h,)) for i in range(cfg.backbone_layers)
        ]
        self.backbone_gb = [
            self._param(f"backbone{i}_gn_b", zeros, (h,)) for i in range(cfg.backbone_layers)
        ]
        self.class_mlp = [
            nn.Dense(h, kernel_init=conv_init, name="class_mlp0"),
            nn.Dense(h, kernel_init=conv_init, name="class_mlp1"),
            nn.Dense(NUM_CLASSES + 1, kernel_init=conv_init, name="class_mlp2"),
        ]
        n = NUM_CLASSES
        self.loc_w = [
            self._param("loc0_w", stacked_conv_init, (n, 3, 3, h, h)),
            self._param("loc1_w", stacked_conv_init, (n, 3, 3, h, h)),
            # Zero: the location logits start flat (see `location_logits`).
            self._param("loc2_w", zeros, (n, 1, 1, h, 1)),
        ]
        self.loc_b = [
            self._param("loc0_b", zeros, (n, h)),
            self._param("loc1_b", zeros, (n, h)),
            self._param("loc2_b", zeros, (n, 1)),
        ]
        self.loc_gs = [self._param(f"loc{i}_gn_s", ones, (n, h)) for i in range(2)]
        self.loc_gb = [self._param(f"loc{i}_gn_b", zeros, (n, h)) for i in range(2)]
        sizes = attribute_sizes(cfg.num_mixtures)
        rows = _attribute_bias_rows(cfg.num_mixtures)
        if cfg.separate_attribute_mlps:
            # The paper's MLP_box, MLP_theta and MLP_v: one three-layer MLP per attribute.
            self.attr_mlps = [
                self._attribute_mlp(draws, name, size, row)
                for name, size, row in zip(ATTRIBUTES, sizes, rows, strict=True)
            ]
        else:
            # One MLP whose last layer outputs all three (box | heading | velocity).
            self.attr_mlps = [
                self._attribute_mlp(draws, "attr", sum(sizes), np.concatenate(rows))]
        if cfg.attribute_map_input:
            # Layer 0's weights for the map channels at the actor's bin, per attribute MLP.
            self.attr_map_w = [
                self._param(f"{name}0_map_w", stacked_conv_init, (n, cm, h))
                for name in ATTRIBUTES
            ]
        if cfg.attribute_map_skip:
            # The last layer's weights for the same map channels (zero: the MLP's outputs).
            self.attr_map_skip = [
                self._param(f"{name}2_map_w", zeros, (n, cm, size))
                for name, size in zip(ATTRIBUTES, sizes, strict=True)
            ]

    def _param(self, name: str, init, shape: tuple[int, ...]):
        """`self.param(name, init, shape)`. Outside `init` it reads the stored parameter and
        compares its shape with `shape`: flax's own check traces `init` (1.4 ms a parameter),
        and every `apply` runs `setup`, which made it 40 % of tracing a train step (~90
        applies of ~60 parameters)."""
        if self.is_initializing() or not self.has_variable("params", name):
            return self.param(name, init, shape)  # creates it, or flax's not-found error
        value = self.get_variable("params", name)
        if np.shape(value) != tuple(shape):
            raise errors.ScopeParamShapeError(name, self.scope.path_text, np.shape(value),
                                              tuple(shape))
        return value

    def _attribute_mlp(self, draws: InitialDraws, name: str, out: int, last_bias):
        """One per-class three-layer MLP's parameters, ([w0, w1, w2], [b0, b1, b2]), with
        `out` outputs whose biases start at `last_bias` and weights small."""
        n, h = NUM_CLASSES, self.cfg.hidden
        dense = draws.lecun_normal(stacked=True)
        last = draws.variance_scaling(0.1, "normal", stacked=True)
        zeros = nn.initializers.zeros
        ws = [
            self._param(f"{name}0_w", dense, (n, h, h)),
            self._param(f"{name}1_w", dense, (n, h, h)),
            self._param(f"{name}2_w", last, (n, h, out)),
        ]
        bs = [
            self._param(f"{name}0_b", zeros, (n, h)),
            self._param(f"{name}1_b", zeros, (n, h)),
            self._param(f"{name}2_b", _bias_init(last_bias), (n, out)),
        ]
        return ws, bs

    # ------------------------------------------------------------------ recurrence
    def map_gates(self, map_raster):
        """Map share of ConvLSTM layer 1's input gates (with its bias, the lane orientation
        sectors' share with `orientation_bins`, and the pixel coordinates' share with
        `coord_channels`): [B,H,W,Cm] -> [B,H,W,4h]."""
        b, hh, ww, _ = map_raster.shape
        if not self.cfg.map_channels:
            gates = jnp.broadcast_to(self.lstm1_b, (b, hh, ww, 4 * self.cfg.hidden))
        else:
            gates = conv(map_raster, self.lstm1_map, self.lstm1_b)
        if self.cfg.orientation_bins:
            ic, is_ = (self.cfg.map_channels.index(c) for c in ORIENTATION_CHANNELS)
            sectors = orientation_sectors(map_raster[..., ic], map_raster[..., is_],
                                          self.cfg.orientation_bins)
            gates = gates + conv(sectors.astype(gates.dtype), self.lstm1_orient)
        if self.cfg.coord_channels:
            rows, cols = jnp.meshgrid(jnp.linspace(-1.0, 1.0, hh), jnp.linspace(-1.0, 1.0, ww),
                                      indexing="ij")
            coords = jnp.stack([rows, cols], axis=-1)[None].astype(gates.dtype)
            gates = gates + conv(coords, self.lstm1_coord)  # the same for every scene
        return gates

    def order_gates(self, prev_bin):
        """Share of layer 1's input gates of the canonical order's channel (`order_channel`):
        1 on the bins at or after `prev_bin` [B] (the previous actor's bin; 0 at a scene's
        first step), 0 before. [B, H, W, 4h], or the scalar 0 without the channel."""
        if not self.cfg.order_channel:
            return jnp.zeros((), jnp.float32)
        n = self.cfg.grid_size
        allowed = jnp.arange(n * n)[None] >= jnp.asarray(prev_bin)[:, None]
        return conv(allowed.reshape(-1, n, n, 1).astype(jnp.float32), self.lstm1_order)

    def actor_gates(self, actor_raster):
        """Actor share of layer 1's input gates: [B,H,W,9] -> [B,H,W,4h] (no bias)."""
        return conv(actor_raster, self.lstm1_act)

    def next_actor_gates(self, gates, before, after, position):
        """Actor share of layer 1's input gates after one more actor is drawn, updated locally.

        The convolution is linear and drawing an actor changes the raster only inside its
        drawing window, so the new gates are the old ones plus the convolution of the change
        over that window with a margin of the kernel's half-width: exact, at a fraction of a
        full-grid convolution. Falls back to the full convolution when the window covers the
        grid.

        Args:
          gates: [B, H, W, 4h] actor gates of `before`.
          before, after: [B, H, W, 9] actor rasters before and after the actor was drawn.
          position: [B, 2] the drawn actor's position (m); an invalid actor leaves the raster
            (and so the gates) as they are.
        """
        cfg = self.cfg
        margin = self.lstm1_act.shape[0] // 2
        p = window_size(cfg) + 2 * margin
        if p >= cfg.grid_size:
            return self.actor_gates(after)
        row0, col0 = window_origin(position, p, cfg)

        def window(x, r, c):
            return jax.lax.dynamic_slice(x, (r, c, 0), (p, p, x.shape[-1]))

        change = jax.vmap(window)(after, row0, col0) - jax.vmap(window)(before, row0, col0)
        delta = self.actor_gates(change)

        def add(g, d, r, c):
            return jax.lax.dynamic_update_slice(g, window(g, r, c) + d, (r, c, 0))

        return jax.vmap(add)(gates, delta, row0, col0)

    def recur(self, state, input_gates):
        """One ConvLSTM step given layer 1's input gates [B,H,W,4h]; returns (state, h2).

        state None is the zero state (`initial_state`, a scene's first step): the same
        result, without the two recurrent convolutions of its zeros (XLA does not fold them).
        """
        zero = state is None
        if zero:
            state = self.initial_state(input_gates.shape[0])
        (h1, c1), (h2, c2) = state
        h1, c1 = lstm_gates(input_gates if zero else input_gates + conv(h1, self.lstm1_rec), c1)
        # A sum of two convolutions instead of one over concat([h1, h2]): the same sum, and
        # XLA:CPU fuses the concatenation's gradient badly in the unrolled backward pass.
        h = self.cfg.hidden
        w2, b2 = self.lstm2_w, self.lstm2_b
        gates2 = conv_sum([(h1, w2[:, :, :h])] + ([] if zero else [(h2, w2[:, :, h:])]), b2)
        h2, c2 = lstm_gates(gates2, c2)
        return ((h1, c1), (h2, c2)), h2

    def initial_state(self, batch: int):
        """Zero ConvLSTM state for `batch` scenes."""
        cfg = self.cfg
        z = jnp.zeros((batch, cfg.grid_size, cfg.grid_size, cfg.hidden), jnp.float32)
        return ((z, z), (z, z))

    # ------------------------------------------------------------------ heads
    def features(self, h2):
        """Backbone: [B,H,W,h] -> [B,H,W,h]."""
        x = h2
        for w, b, s, gb in zip(
            self.backbone_w, self.backbone_b, self.backbone_gs, self.backbone_gb, strict=True
        ):
            x = jax.nn.relu(group_norm(conv(x, w, b), self.cfg.gn_groups, s, gb))
        return x

    def class_logits(self, f):
        """Logits over {vehicle, pedestrian, bicyclist, stop} from pooled features: [B, 4]."""
        x = jnp.mean(f, axis=(1, 2))
        x = jax.nn.relu(self.class_mlp[0](x))
        x = jax.nn.relu(self.class_mlp[1](x))
        return self.class_mlp[2](x)

    def location_logits(self, f, cls, single: bool = False):
        """Logits over the H*W bins from the head of class `cls` [B] only: [B, H*W].

        single=True (static; B must be 1, as in the unrolled training step at B = 1 and in
        the sampler's rollout) runs plain convolutions with that class's kernels, XLA:CPU's
        fastest (under vmap they become a grouped convolution); otherwise
        `conv_per_example`. All give the same values.

        The last layer's weights start at zero, so an untrained model's location distribution
        is uniform and training has no spread of random logits to remove first (with random
        weights it removed it partly by silencing backbone channels;
        experiments/results/README.md, session 13).
        """
        cls = jnp.clip(cls, 0, NUM_CLASSES - 1)

        def layer(x, i):
            if single:
                return conv(x, self.loc_w[i][cls[0]], self.loc_b[i][cls[0]])
            return conv_per_example(x, self.loc_w[i][cls], self.loc_b[i][cls])

        x = f
        for i in range(2):
            x = layer(x, i)
            scale = self.loc_gs[i][cls][:, None, None, :]
            bias = self.loc_gb[i][cls][:, None, None, :]
            x = jax.nn.relu(group_norm(x, self.cfg.gn_groups, scale, bias))
        x = layer(x, 2)
        return x.reshape(x.shape[0], -1)

    def attributes(self, feat, cls, map_feat=None):
        """Raw (box, heading, velocity) parameters from feature vectors [B, h] for class [B];
        with `attribute_map_input`, also from the map channels at the bins, map_feat [B, Cm]
        (ignored otherwise), in layer 0 and, with `attribute_map_skip`, in the last layer.
        With `heading_lane_frame` the heading mixture's directions are turned by the nearest
        lane's direction at the bin (`nearest_lane_direction`): the MLP gives them relative
        to the lane."""
        cls = jnp.clip(cls, 0, NUM_CLASSES - 1)
        for option in ("attribute_map_input", "heading_lane_frame"):
            if getattr(self.cfg, option) and map_feat is None:
                raise ValueError(f"{option}: attributes() needs the map channels at the bins "
                                 "(map_feat)")
        if self.cfg.attribute_map_input:
            m = map_feat.astype(feat.dtype)
            x = jnp.concatenate([feat, m], axis=-1)
            outs = [
                _mlp(x, [jnp.concatenate([ws[0], wm], axis=1), *ws[1:]], bs, cls)
                for (ws, bs), wm in zip(self.attr_mlps, self.attr_map_w, strict=True)
            ]
            if self.cfg.attribute_map_skip:
                outs = [o + jnp.einsum("bi,bio->bo", m, w[cls])
                        for o, w in zip(outs, self.attr_map_skip, strict=True)]
        else:
            outs = [_mlp(feat, ws, bs, cls) for ws, bs in self.attr_mlps]
        if len(outs) == len(ATTRIBUTES):
            box, heading, velocity = outs
        else:
            nb, nh, _ = attribute_sizes(self.cfg.num_mixtures)
            x = outs[0]
            box, heading, velocity = x[:, :nb], x[:, nb : nb + nh], x[:, nb + nh :]
        if self.cfg.heading_lane_frame:
            heading = P.rotate_heading(heading, *nearest_lane_direction(map_feat, self.cfg))
        return box, heading, velocity

    def __call__(self, map_raster, actor_raster, cls, bins):
        """One full step from a zero state (used to initialise every parameter)."""
        state = self.initial_state(map_raster.shape[0])
        gates = self.map_gates(map_raster) + self.actor_gates(actor_raster)
        gates = gates + self.order_gates(jnp.zeros(map_raster.shape[:1], jnp.int32))
        _, h2 = self.recur(state, gates)
        f = self.features(h2)
        feat = f.reshape(f.shape[0], -1, f.shape[-1])[jnp.arange(f.shape[0]), bins]
        map_feat = map_at_bins(map_raster, bins)
        return (self.class_logits(f), self.location_logits(f, cls),
                self.attributes(feat, cls, map_feat))


def nearest_lane_direction(map_feat, cfg: Config):
    """The nearest lane's direction at the bins as a unit (cos, sin), each [...], from the map
    channels there, map_feat [..., Cm] (`nearest_lane` layers); (1, 0), no turn, where no
    centreline is within `raster.map.NEAREST_LANE_MAX_M` (the channels are 0 there; a
    length under 1/2, as where a rotated crop blends a direction with 0, counts as none)."""
    i = cfg.map_channels.index(NEAREST_LANE_CHANNELS[0])
    j = cfg.map_channels.index(NEAREST_LANE_CHANNELS[1])
    c, s = map_feat[..., i], map_feat[..., j]
    n = jnp.hypot(c, s)
    some = n >= 0.5
    n = jnp.where(some, n, 1.0)
    return jnp.where(some, c / n, 1.0), jnp.where(some, s / n, 0.0)


def map_at_bins(map_raster, bins):
    """The map channels at bins [B, ...] of rasters [B, H, W, Cm]: [B, ..., Cm]."""
    b, h, w, cm = map_raster.shape
    flat = map_raster.reshape(b, h * w, cm)  # not -1: a raster may have no channels
    idx = jnp.arange(b).reshape((b,) + (1,) * (jnp.ndim(bins) - 1))
    return flat[idx, bins]


def init_params(cfg: Config, key):
    """Initial parameters (a plain PyTree) for `cfg`.

    Compiled: flax creates the parameters by running one step of the network, which, run
    eagerly, dispatches its operations one by one (8 s for `tiny` on 2 cores); compiled, XLA
    drops that step (only the parameters are returned) and keeps their initialisers
    (`backend.init_compiler_options`), whose random values come from one PRNG call per 2^20
    values (`InitialDraws`: `tiny`'s program compiles in 0.5 s instead of 2.5 s, slow Xeon)."""
    net = SceneGenNet(cfg)
    h = cfg.grid_size
    m = jnp.zeros((1, h, h, len(cfg.map_channels)), jnp.float32)
    a = jnp.zeros((1, h, h, NUM_ACTOR_CHANNELS), jnp.float32)
    z = jnp.zeros((1,), jnp.int32)

    def init(k):
        return net.init(k, m, a, z, z)["params"]

    return compiled_init(init, key)
