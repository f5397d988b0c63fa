"""SceneGen network (paper supplementary sec. 1.2): a two-layer ConvLSTM over BEV rasters, a
five-layer conv backbone, a class MLP, per-class location CNNs and per-class attribute MLPs.

The network is split into methods so the teacher-forced unroll can be fast (see
`scenegen_jax.likelihood.unroll`): the first ConvLSTM layer's input convolution is linear in its
input, so conv(map ++ actors ++ h1) = conv_map(map) + conv_actors(actors) + conv_rec(h1).
The map part is computed once per scene. The backbone and heads do not feed back into the
recurrence, so the unroll can run them on chunks of steps. Its layers are in `model.layers`,
the cell update in `model.convlstm`, the initial values in `model.initializers`.

All arrays are NHWC; leading axes beyond one batch axis are flattened by the caller.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import errors

from scenegen_jax.backend import compiled_init
from scenegen_jax.config import ModelConfig
from scenegen_jax.distributions import params as P
from scenegen_jax.model.convlstm import lstm_gates
from scenegen_jax.model.initializers import (
    InitialDraws,
    attribute_bias_rows,
    bias_init,
)
from scenegen_jax.model.layers import (
    conv,
    conv_per_example,
    conv_sum,
    group_norm,
    per_class_mlp,
)
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


class SceneGenNet(nn.Module):
    """The network. Parameters are a plain PyTree (Linen), shapes from the config."""

    cfg: ModelConfig

    def setup(self):
        # A key only where the parameters are created (`apply` reads them). The parameters
        # are created in this order, which their initial values depend on (`InitialDraws`).
        draws = InitialDraws(self.make_rng("params") if self.is_initializing() else None)
        self._setup_convlstm(draws)
        self._setup_backbone(draws)
        self._setup_location_heads(draws)
        self._setup_attribute_heads(draws)

    def _setup_convlstm(self, draws: InitialDraws):
        """The two ConvLSTM layers' weights: layer 1's input convolution in shares (map,
        coordinates, canonical order, orientation sectors, actors) and its recurrence."""
        cfg = self.cfg
        h, cm = cfg.hidden, len(cfg.grid.map_channels)
        conv_init = draws.lecun_normal()

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

    def _setup_backbone(self, draws: InitialDraws):
        """The backbone's convolutions and GroupNorms, and the class MLP."""
        h, layers = self.cfg.hidden, range(self.cfg.backbone_layers)
        conv_init = draws.lecun_normal()
        zeros, ones = nn.initializers.zeros, nn.initializers.ones
        self.backbone_w = [self._param(f"backbone{i}_w", conv_init, (3, 3, h, h)) for i in layers]
        self.backbone_b = [self._param(f"backbone{i}_b", zeros, (h,)) for i in layers]
        self.backbone_gs = [self._param(f"backbone{i}_gn_s", ones, (h,)) for i in layers]
        self.backbone_gb = [self._param(f"backbone{i}_gn_b", zeros, (h,)) for i in layers]
        self.class_mlp = [
            nn.Dense(h, kernel_init=conv_init, name="class_mlp0"),
            nn.Dense(h, kernel_init=conv_init, name="class_mlp1"),
            nn.Dense(NUM_CLASSES + 1, kernel_init=conv_init, name="class_mlp2"),
        ]

    def _setup_location_heads(self, draws: InitialDraws):
        """The per-class location CNNs: two 3 x 3 layers with GroupNorm, then a 1 x 1."""
        n, h = NUM_CLASSES, self.cfg.hidden
        stacked_conv_init = draws.lecun_normal(stacked=True)
        zeros, ones = nn.initializers.zeros, nn.initializers.ones
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

    def _setup_attribute_heads(self, draws: InitialDraws):
        """The per-class attribute MLPs and, with the options, their map weights."""
        cfg = self.cfg
        n, h, cm = NUM_CLASSES, cfg.hidden, len(cfg.grid.map_channels)
        sizes = attribute_sizes(cfg.num_mixtures)
        rows = attribute_bias_rows(cfg.num_mixtures)
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
                self._param(f"{name}0_map_w", draws.lecun_normal(stacked=True), (n, cm, h))
                for name in ATTRIBUTES
            ]
        if cfg.attribute_map_skip:
            # The last layer's weights for the same map channels (zero: the MLP's outputs).
            self.attr_map_skip = [
                self._param(f"{name}2_map_w", nn.initializers.zeros, (n, cm, size))
                for name, size in zip(ATTRIBUTES, sizes, strict=True)
            ]

    def _param(self, name: str, init, shape: tuple[int, ...]):
        """`self.param(name, init, shape)`. Outside `init` it reads the stored parameter and
        compares its shape with `shape`: flax's own check traces `init`, and every `apply`
        runs `setup`, so that check would dominate the tracing of a train step."""
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
            self._param(f"{name}2_b", bias_init(last_bias), (n, out)),
        ]
        return ws, bs

    # ------------------------------------------------------------------ recurrence
    def map_gates(self, map_raster):
        """Map share of ConvLSTM layer 1's input gates (with its bias, the lane orientation
        sectors' share with `orientation_bins`, and the pixel coordinates' share with
        `coord_channels`): [B,H,W,Cm] -> [B,H,W,4h]."""
        b, hh, ww, _ = map_raster.shape
        if not self.cfg.grid.map_channels:
            gates = jnp.broadcast_to(self.lstm1_b, (b, hh, ww, 4 * self.cfg.hidden))
        else:
            gates = conv(map_raster, self.lstm1_map, self.lstm1_b)
        if self.cfg.orientation_bins:
            ic, is_ = (self.cfg.grid.map_channels.index(c) for c in ORIENTATION_CHANNELS)
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
        n = self.cfg.grid.grid_size
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
        p = window_size(cfg.grid) + 2 * margin
        if p >= cfg.grid.grid_size:
            return self.actor_gates(after)
        row0, col0 = window_origin(position, p, cfg.grid)

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
        z = jnp.zeros((batch, cfg.grid.grid_size, cfg.grid.grid_size, cfg.hidden), jnp.float32)
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
        weights it removes it partly by silencing backbone channels).
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
                per_class_mlp(x, [jnp.concatenate([ws[0], wm], axis=1), *ws[1:]], bs, cls)
                for (ws, bs), wm in zip(self.attr_mlps, self.attr_map_w, strict=True)
            ]
            if self.cfg.attribute_map_skip:
                outs = [o + jnp.einsum("bi,bio->bo", m, w[cls])
                        for o, w in zip(outs, self.attr_map_skip, strict=True)]
        else:
            outs = [per_class_mlp(feat, ws, bs, cls) for ws, bs in self.attr_mlps]
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


def nearest_lane_direction(map_feat, cfg: ModelConfig):
    """The nearest lane's direction at the bins as a unit (cos, sin), each [...], from the map
    channels there, map_feat [..., Cm] (`nearest_lane` layers); (1, 0), no turn, where no
    centreline is within `raster.map.NEAREST_LANE_MAX_M` (the channels are 0 there; a
    length under 1/2, as where a rotated crop blends a direction with 0, counts as none)."""
    i = cfg.grid.map_channels.index(NEAREST_LANE_CHANNELS[0])
    j = cfg.grid.map_channels.index(NEAREST_LANE_CHANNELS[1])
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


def init_params(cfg: ModelConfig, key):
    """Initial parameters (a plain PyTree) for `cfg`.

    Compiled: flax creates the parameters by running one step of the network, which, run
    eagerly, dispatches its operations one by one; compiled, XLA drops that step (only the
    parameters are returned) and keeps their initialisers (`backend.init_compiler_options`),
    whose random values come from one PRNG call per 2^20 values (`InitialDraws`), so that
    the program compiles few PRNG kernels."""
    net = SceneGenNet(cfg)
    h = cfg.grid.grid_size
    m = jnp.zeros((1, h, h, len(cfg.grid.map_channels)), jnp.float32)
    a = jnp.zeros((1, h, h, NUM_ACTOR_CHANNELS), jnp.float32)
    z = jnp.zeros((1,), jnp.int32)

    def init(k):
        return net.init(k, m, a, z, z)["params"]

    return compiled_init(init, key)
