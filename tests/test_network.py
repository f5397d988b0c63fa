"""The network on its own (small tiny config): its convolutions, GroupNorm and ConvLSTM cell
against references, its initial parameters against flax's initialisers, and the inputs and
outputs its options add (orientation sectors, the map at the bin, the lane frame)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax.traverse_util import flatten_dict
from small import (
    CFG,
    random_params,
)

from scenegen_jax.model.convlstm import lstm_gates, lstm_gates_reference
from scenegen_jax.model.layers import conv, group_norm
from scenegen_jax.model.network import SceneGenNet, orientation_sectors
from scenegen_jax.train.step import (
    init_state,
)


def test_location_head_single_example_path_agrees(tiny_train_cache):
    cfg = CFG
    params = random_params(cfg, jax.random.key(4))
    f = jax.random.normal(
        jax.random.key(5), (3, cfg.grid.grid_size, cfg.grid.grid_size, cfg.model.hidden)
    )
    cls = jnp.array([2, 0, 1])
    net = SceneGenNet(cfg.model)
    batched = net.apply({"params": params}, f, cls, method=SceneGenNet.location_logits)
    for i in range(3):
        one = net.apply(
            {"params": params},
            f[i : i + 1],
            cls[i : i + 1],
            True,
            method=SceneGenNet.location_logits,
        )
        np.testing.assert_allclose(one[0], batched[i], rtol=1e-4, atol=1e-4)


def test_lstm_cell_gradient_equals_autodiff():
    """The hand-written ConvLSTM cell gradient equals autodiff of the plain formula."""
    k1, k2, k3, k4 = jax.random.split(jax.random.key(3), 4)
    gates = 3 * jax.random.normal(k1, (2, 5, 5, 4 * 6))
    c = jax.random.normal(k2, (2, 5, 5, 6))
    wh, wc = jax.random.normal(k3, (2, 5, 5, 6)), jax.random.normal(k4, (2, 5, 5, 6))

    def loss(fn, g, c):
        for _ in range(3):  # a short chain, as in the unroll
            h, c = fn(g, c)
        return jnp.sum(wh * jnp.sin(h)) + jnp.sum(wc * c * c)

    reference = lstm_gates_reference(gates, c)
    with_vjp = jax.vjp(lstm_gates, gates, c)[0]  # the values of the forward rule, as trained
    for outputs in (lstm_gates(gates, c), with_vjp):
        for a, b in zip(outputs, reference, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)
    fast = jax.grad(lambda g, c: loss(lstm_gates, g, c), argnums=(0, 1))(gates, c)
    ref = jax.grad(lambda g, c: loss(lstm_gates_reference, g, c), argnums=(0, 1))(gates, c)
    for a, b in zip(fast, ref, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


def test_banded_weight_gradient_equals_the_convolutions_own(monkeypatch):
    """A convolution whose weight gradient is summed over row bands (with the kernel's halo):
    values and both gradients as XLA's own convolution's, for kernels 5, 3 and 1 and a row
    count the bands do not divide; `conv` bands exactly above the backend's threshold."""
    from scenegen_jax.model import layers

    rows, band_rows = 11, 4  # three bands: 3, 4, 4 rows
    assert layers._band_starts(rows, band_rows) == [0, 3, 7, 11]
    kx, kg = jax.random.split(jax.random.key(9))
    x = jax.random.normal(kx, (2, rows, 7, 3))

    def xla(x, w):
        return jax.lax.conv_general_dilated(
            x, w, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
        )

    for k, kw in zip((5, 3, 1), jax.random.split(jax.random.key(10), 3), strict=True):
        w = jax.random.normal(kw, (k, k, 3, 4))
        g = jax.random.normal(kg, (2, rows, 7, 4))
        ours, vjp_ours = jax.vjp(lambda x, w: layers._banded_conv(x, w, band_rows), x, w)
        theirs, vjp_theirs = jax.vjp(xla, x, w)
        np.testing.assert_array_equal(ours, theirs)
        for a, b in zip(vjp_ours(g), vjp_theirs(g), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)
    calls = []
    monkeypatch.setattr(layers, "weight_gradient_bands", lambda: (10, band_rows))
    monkeypatch.setattr(layers, "_banded_conv", lambda x, w, r: calls.append(r) or xla(x, w))
    w = jnp.ones((3, 3, 3, 4))
    conv(x[:, :10], w)
    assert calls == []  # 10 rows: not above the threshold
    conv(x, w)
    assert calls == [band_rows]


def test_group_norm_matches_flax():
    """Our GroupNorm (statistics reduced over H, W first) against flax.linen.GroupNorm, values
    and gradients, with per-channel and per-example scale and bias (the location heads)."""
    import flax.linen as nn

    kx, ks, kb, kw = jax.random.split(jax.random.key(6), 4)
    x = 3.0 + 2.0 * jax.random.normal(kx, (3, 9, 7, 12))  # a mean far from 0
    scale, bias = jax.random.normal(ks, (3, 12)), jax.random.normal(kb, (3, 12))
    w = jax.random.normal(kw, (1, 9, 7, 12))
    flax_gn = nn.GroupNorm(num_groups=4, epsilon=1e-5)

    def theirs(x, s, b):
        return flax_gn.apply({"params": {"scale": s, "bias": b}}, x)

    def ours(x, s, b):
        return group_norm(x, 4, s, b)

    def grads(fn, *args):
        return jax.grad(lambda *a: jnp.sum(w * jnp.sin(fn(*a))), argnums=(0, 1, 2))(*args)

    for i in range(3):  # per-channel parameters, one example at a time
        args = (x[i : i + 1], scale[i], bias[i])
        np.testing.assert_allclose(ours(*args), theirs(*args), rtol=1e-5, atol=1e-5)
        for g_ours, g_theirs in zip(grads(ours, *args), grads(theirs, *args), strict=True):
            np.testing.assert_allclose(g_ours, g_theirs, rtol=1e-4, atol=1e-4)
    s4, b4 = scale[:, None, None, :], bias[:, None, None, :]
    per_example = group_norm(x, 4, s4, b4)
    g_x, g_s, g_b = grads(ours, x, s4, b4)
    for i in range(3):
        one = (x[i : i + 1], scale[i], bias[i])
        np.testing.assert_allclose(per_example[i : i + 1], theirs(*one), rtol=1e-5, atol=1e-5)
        for g_ours, g_theirs in zip(
            (g_x[i : i + 1], g_s[i, 0, 0], g_b[i, 0, 0]), grads(theirs, *one), strict=True
        ):
            np.testing.assert_allclose(g_ours, g_theirs, rtol=1e-4, atol=1e-4)
    # parameters shared by a batch: their gradient sums the examples'
    shared = grads(ours, x, scale[0], bias[0])
    each = [grads(theirs, x[i : i + 1], scale[0], bias[0]) for i in range(3)]
    for k in (1, 2):
        np.testing.assert_allclose(shared[k], sum(e[k] for e in each), rtol=1e-4, atol=1e-4)


def test_attribute_map_skip_adds_the_map_at_the_bin_linearly_to_each_output():
    """`attribute_map_skip`: each attribute's raw output is the `attribute_map_input` MLP's
    plus map_feat @ W[cls] (W: `{box,heading,velocity}2_map_w` [classes, Cm, out]),
    written out in numpy; zero weights (a fresh model) give the MLP's outputs."""
    skip_cfg = CFG.replace(attribute_map_input=True, attribute_map_skip=True)
    params = init_state(skip_cfg, seed=5).params
    mlp_only = {k: v for k, v in params.items() if not k.endswith("2_map_w")}
    rng = np.random.default_rng(6)
    weights = {
        f"{a}2_map_w": rng.normal(size=params[f"{a}2_map_w"].shape).astype(np.float32)
        for a in ("box", "heading", "velocity")
    }
    feat = jax.random.normal(jax.random.key(3), (4, CFG.model.hidden))
    map_feat = jax.random.uniform(jax.random.key(4), (4, len(CFG.grid.map_channels)))
    cls = jnp.array([0, 2, 1, 0])

    def attrs(cfg, p):
        return SceneGenNet(cfg.model).apply(
            {"params": p}, feat, cls, map_feat, method=SceneGenNet.attributes
        )

    base = attrs(CFG.replace(attribute_map_input=True), mlp_only)
    for got, want in zip(attrs(skip_cfg, params), base, strict=True):
        np.testing.assert_array_equal(got, want)
    got = attrs(skip_cfg, {**params, **weights})
    m, c = np.asarray(map_feat), np.asarray(cls)
    for g, b, name in zip(got, base, ("box", "heading", "velocity"), strict=True):
        w = weights[f"{name}2_map_w"]
        want = np.asarray(b) + np.stack([m[i] @ w[c[i]] for i in range(4)])
        np.testing.assert_allclose(g, want, rtol=1e-5, atol=1e-5)


def test_initial_parameters_are_the_same_compiled_alone_or_inside_a_trace():
    """`init_params` compiles its initialisers on their own (at XLA:CPU's lowest optimisation
    level) unless it is called inside a trace, where it is traced with the caller: both give
    the same parameters, and `jax.eval_shape` of it works (restoring a checkpoint uses it)."""
    from scenegen_jax.model.network import init_params

    alone = init_params(CFG.model, jax.random.key(3))
    traced = jax.jit(lambda k: init_params(CFG.model, k))(jax.random.key(3))
    shapes = jax.eval_shape(lambda: init_params(CFG.model, jax.random.key(3)))
    assert jax.tree.structure(alone) == jax.tree.structure(traced) == jax.tree.structure(shapes)
    for a, t, s in zip(
        jax.tree.leaves(alone), jax.tree.leaves(traced), jax.tree.leaves(shapes), strict=True
    ):
        assert a.shape == s.shape
        np.testing.assert_allclose(a, t, rtol=1e-6, atol=1e-7)


def test_initial_weights_follow_flax_initialisers_and_a_wrong_scale_fails():
    """The weights drawn from `InitialDraws` (one PRNG call for all of them) follow the
    distributions of flax's initialisers, checked against scipy: lecun_normal (a normal
    truncated to two standard deviations, scaled to variance 1 / fan_in; the ConvLSTM,
    backbone, location and class-MLP weights and the first attribute layers, per copy where
    stacked by class) and variance_scaling(0.1, "fan_in", "normal") (the last attribute
    layers). The same draws 10 % wider (lecun) or 50 % wider (the small normal sample) fail;
    the per-class copies differ; zeros, ones and the fixed biases stay as they were."""
    from scipy import stats

    from scenegen_jax.model.initializers import TRUNCATED_STD
    from scenegen_jax.model.network import init_params

    params = flatten_dict(jax.device_get(init_params(CFG.model, jax.random.key(7))), sep="/")
    lecun, normal = [], []
    for name, w in params.items():
        w = np.asarray(w, np.float64)
        if name.endswith(("_b", "bias", "_gn_s", "_gn_b")) or name == "loc2_w":
            continue
        head = name.startswith(("box", "heading", "velocity"))  # the attribute MLPs
        stacked = head or name.startswith("loc")
        one = w.shape[1:] if stacked else w.shape
        fan_in = np.prod(one) // one[-1]
        if stacked:
            assert not np.allclose(w[0], w[1]), name  # independent copies per class
        if head and name.endswith("2_w"):
            normal.append(w.ravel() / np.sqrt(0.1 / fan_in))
        else:
            lecun.append(w.ravel() * np.sqrt(fan_in))
    lecun, normal = np.concatenate(lecun), np.concatenate(normal)
    assert len(lecun) > 29_000 and len(normal) > 1_000
    truncated = stats.truncnorm(-2, 2, scale=1 / TRUNCATED_STD)
    assert np.abs(lecun).max() <= 2 / TRUNCATED_STD + 1e-5
    assert stats.kstest(lecun, truncated.cdf).pvalue > 1e-3
    assert stats.kstest(lecun * 1.1, truncated.cdf).pvalue < 1e-6
    assert abs(np.std(lecun) - 1.0) < 0.02  # variance 1 / fan_in, as flax's
    assert stats.kstest(normal, stats.norm.cdf).pvalue > 1e-3
    assert stats.kstest(normal * 1.5, stats.norm.cdf).pvalue < 1e-6
    assert not np.any(params["loc2_w"]) and not np.any(params["backbone0_b"])
    np.testing.assert_array_equal(params["backbone0_gn_s"], 1.0)


def test_a_parameter_of_the_wrong_shape_is_named_when_the_network_is_applied():
    """The network reads its stored parameters without flax's check (which traces each
    initialiser at every apply) and checks their shapes itself: a parameter of another
    config's shape is an error that names it, with both shapes; a missing one, flax's."""
    from flax.errors import ScopeParamNotFoundError, ScopeParamShapeError

    from scenegen_jax.model.network import SceneGenNet, init_params

    params = dict(init_params(CFG.model, jax.random.key(0)))
    net = SceneGenNet(CFG.model)
    state = net.apply({"params": params}, 1, method=SceneGenNet.initial_state)
    assert state[0][0].shape == (1, CFG.grid.grid_size, CFG.grid.grid_size, CFG.model.hidden)
    params["lstm2_w"] = np.zeros((5, 5, 2 * CFG.model.hidden, 4 * CFG.model.hidden + 1), np.float32)
    with pytest.raises(ScopeParamShapeError, match=r"lstm2_w.*\(5, 5, 16, 32\).*\(5, 5, 16, 33\)"):
        net.apply({"params": params}, 1, method=SceneGenNet.initial_state)
    del params["lstm2_w"]
    with pytest.raises(ScopeParamNotFoundError, match="lstm2_w"):
        net.apply({"params": params}, 1, method=SceneGenNet.initial_state)


def test_orientation_sectors_split_each_direction_between_the_two_nearest_sectors():
    """Hand-computed cases for K = 8 (sector centres every 45 degrees), the wrap at 360
    degrees, lengths below 1 (a lane's blurred edge) and the zero vector (off every lane)."""
    deg = np.radians([0.0, 45.0, 22.5, 350.0, 180.0, 100.0, 0.0])
    length = np.array([1.0, 1.0, 1.0, 1.0, 0.5, 1.0, 0.0])
    got = np.asarray(
        orientation_sectors(jnp.asarray(length * np.cos(deg)), jnp.asarray(length * np.sin(deg)), 8)
    )
    want = np.zeros((7, 8))
    want[0, 0] = 1.0
    want[1, 1] = 1.0
    want[2, [0, 1]] = 0.5
    want[3, [7, 0]] = [2 / 9, 7 / 9]  # 350 deg: 10 deg short of sector 0, 35 past sector 7
    want[4, 4] = 0.5
    want[5, [2, 3]] = [7 / 9, 2 / 9]  # 100 deg: 10 past sector 2 (90 deg)
    np.testing.assert_allclose(got, want, atol=1e-6)
    # Turning every direction by one sector width moves its weights one sector on.
    a = np.random.default_rng(0).uniform(0, 2 * np.pi, 50)
    turned = orientation_sectors(jnp.cos(a + np.pi / 3), jnp.sin(a + np.pi / 3), 6)
    np.testing.assert_allclose(
        turned, np.roll(orientation_sectors(jnp.cos(a), jnp.sin(a), 6), 1, axis=-1), atol=1e-5
    )


def test_heading_lane_frame_turns_the_heading_mixture_by_the_nearest_lane_at_the_bin():
    """`heading_lane_frame`: the heading density at h with the nearest lane at angle a equals
    the density at h - a where no lane is near (scipy's von Mises mixture, weights and
    concentrations from the unturned head); a direction shorter than 1/2 is no lane, a
    longer one counts by its angle alone. The box and velocity do not move."""
    from scipy import stats

    from scenegen_jax.distributions import heading_log_prob
    from scenegen_jax.distributions.params import split_heading

    cfg = CFG.replace(map_layers=("lanes", "nearest_lane"), heading_lane_frame=True)
    params = init_state(cfg, seed=3).params
    params = {**params, "heading2_w": params["heading2_w"] * 30.0}  # a peaked, uneven mixture
    i, j = (cfg.grid.map_channels.index(c) for c in ("nearest_lane_cos", "nearest_lane_sin"))
    a = np.array([0.0, 0.7, 2.5, -1.9, 1.0])
    length = np.array([1.0, 1.0, 0.8, 1.0, 0.3])  # 0.3: no lane (no turn)
    map_feat = np.zeros((5, len(cfg.grid.map_channels)), np.float32)
    map_feat[:, i], map_feat[:, j] = length * np.cos(a), length * np.sin(a)
    feat = jnp.broadcast_to(
        jax.random.normal(jax.random.key(1), (1, cfg.model.hidden)), (5, cfg.model.hidden)
    )
    cls = jnp.zeros((5,), jnp.int32)
    net = SceneGenNet(cfg.model)
    box, heading, velocity = net.apply(
        {"params": params}, feat, cls, jnp.asarray(map_feat), method=SceneGenNet.attributes
    )
    base = net.apply(
        {"params": params}, feat, cls, jnp.zeros_like(map_feat), method=SceneGenNet.attributes
    )
    np.testing.assert_array_equal(box, base[0])
    np.testing.assert_array_equal(velocity, base[2])
    unturned = split_heading(base[1][0])
    w = np.exp(unturned.logits - np.logaddexp.reduce(np.asarray(unturned.logits)))
    mu = np.arctan2(unturned.direction[:, 1], unturned.direction[:, 0])
    kappa = np.exp(np.asarray(unturned.log_kappa))
    h = np.linspace(-np.pi, np.pi, 7)
    for n, turn in enumerate(np.where(length >= 0.5, a, 0.0)):
        want = np.log(
            sum(
                wk * stats.vonmises.pdf(h - turn, kk, loc=mk)
                for wk, kk, mk in zip(w, kappa, mu, strict=True)
            )
        )
        got = [float(heading_log_prob(heading[n], jnp.float32(x))) for x in h]
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
