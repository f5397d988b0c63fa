"""Network unroll, train step, checkpoints and sharding on real scenes (tiny config)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax.traverse_util import flatten_dict
from small import (
    CFG,
    assert_same_adam_training,
    metrics_rows,
    random_params,
    train_args,
    train_cmd,
    two_small_scenes,
    with_xla_flags,
)

from scenegen_jax import cli
from scenegen_jax.config import get_config
from scenegen_jax.likelihood.batch import Batch, check_batch, crop_batch, gather_batch
from scenegen_jax.likelihood.unroll import unroll_terms
from scenegen_jax.model.network import (
    SceneGenNet,
    conv,
    group_norm,
    lstm_gates,
    lstm_gates_reference,
    orientation_sectors,
)
from scenegen_jax.raster.map import ALL_MAP_CHANNELS
from scenegen_jax.scene import Actors, make_ego
from scenegen_jax.train.data import batch_indices
from scenegen_jax.train.step import (
    REMAT_FREE_SHARE,
    init_state,
    loss_fn,
    make_optimizer,
    make_train_step,
    resolve_remat,
    step_bytes_without_remat,
    train_step,
)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def small_scenes(tiny_train_cache):
    return two_small_scenes(tiny_train_cache)


def _batch(cache, idx):
    return gather_batch(cache, np.asarray(idx), CFG)


# `train_step` compiled once per config. Run op by op, the module's first step took 25-50 s
# (thousands of small programs compiled), more than compiling the whole step (session 37).
_jitted_train_step = jax.jit(train_step, static_argnums=2)


def test_location_head_single_example_path_agrees(tiny_train_cache):
    cfg = CFG
    params = random_params(cfg, jax.random.key(4))
    f = jax.random.normal(jax.random.key(5), (3, cfg.grid_size, cfg.grid_size, cfg.hidden))
    cls = jnp.array([2, 0, 1])
    net = SceneGenNet(cfg)
    batched = net.apply({"params": params}, f, cls, method=SceneGenNet.location_logits)
    for i in range(3):
        one = net.apply({"params": params}, f[i : i + 1], cls[i : i + 1], True,
                        method=SceneGenNet.location_logits)
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


def test_warmup_ramps_adams_step_linearly():
    """With a constant gradient Adam's bias-corrected step is the learning rate itself, so the
    updates are -lr * t / n for t < n warm-up steps, then -lr (hand-computed)."""
    cfg = CFG.replace(learning_rate=1e-2, warmup_steps=4, grad_clip=0.0)
    params = {"w": jnp.zeros(3)}
    g = {"w": jnp.array([0.5, -2.0, 1e-3])}
    opt = make_optimizer(cfg)
    state = opt.init(params)
    for t in range(6):
        updates, state = opt.update(g, state, params)
        lr = 1e-2 * min(t / 4, 1.0)
        np.testing.assert_allclose(updates["w"], -lr * np.sign(g["w"]), rtol=1e-4, atol=1e-9)


def test_cosine_decay_follows_the_warm_up_to_zero():
    """Adam's step under a constant gradient is the learning rate itself: after a 4-step
    ramp it follows lr * (1 + cos(pi * t / 6)) / 2 over 6 decay steps (hand-computed), then
    stays 0."""
    cfg = CFG.replace(learning_rate=1e-2, warmup_steps=4, decay_steps=6, grad_clip=0.0)
    params = {"w": jnp.zeros(3)}
    g = {"w": jnp.array([0.5, -2.0, 1e-3])}
    opt = make_optimizer(cfg)
    state = opt.init(params)
    expected = [0.0, 2.5e-3, 5e-3, 7.5e-3, 1e-2, 9.330127e-3, 7.5e-3, 5e-3, 2.5e-3, 6.69873e-4,
                0.0, 0.0]
    for lr in expected:
        updates, state = opt.update(g, state, params)
        np.testing.assert_allclose(updates["w"], -lr * np.sign(g["w"]), rtol=1e-4, atol=1e-9)


def test_banded_weight_gradient_equals_the_convolutions_own(monkeypatch):
    """A convolution whose weight gradient is summed over row bands (with the kernel's halo):
    values and both gradients as XLA's own convolution's, for kernels 5, 3 and 1 and a row
    count the bands do not divide; `conv` bands exactly above the backend's threshold."""
    from scenegen_jax.model import network

    rows, band_rows = 11, 4  # three bands: 3, 4, 4 rows
    assert network._band_starts(rows, band_rows) == [0, 3, 7, 11]
    kx, kg = jax.random.split(jax.random.key(9))
    x = jax.random.normal(kx, (2, rows, 7, 3))

    def xla(x, w):
        return jax.lax.conv_general_dilated(x, w, (1, 1), "SAME",
                                            dimension_numbers=("NHWC", "HWIO", "NHWC"))

    for k, kw in zip((5, 3, 1), jax.random.split(jax.random.key(10), 3), strict=True):
        w = jax.random.normal(kw, (k, k, 3, 4))
        g = jax.random.normal(kg, (2, rows, 7, 4))
        ours, vjp_ours = jax.vjp(lambda x, w: network._banded_conv(x, w, band_rows), x, w)
        theirs, vjp_theirs = jax.vjp(xla, x, w)
        np.testing.assert_array_equal(ours, theirs)
        for a, b in zip(vjp_ours(g), vjp_theirs(g), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)
    calls = []
    monkeypatch.setattr(network, "weight_gradient_bands", lambda: (10, band_rows))
    monkeypatch.setattr(network, "_banded_conv", lambda x, w, r: calls.append(r) or xla(x, w))
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
        for g_ours, g_theirs in zip((g_x[i : i + 1], g_s[i, 0, 0], g_b[i, 0, 0]),
                                    grads(theirs, *one), strict=True):
            np.testing.assert_allclose(g_ours, g_theirs, rtol=1e-4, atol=1e-4)
    # parameters shared by a batch: their gradient sums the examples'
    shared = grads(ours, x, scale[0], bias[0])
    each = [grads(theirs, x[i : i + 1], scale[0], bias[0]) for i in range(3)]
    for k in (1, 2):
        np.testing.assert_allclose(shared[k], sum(e[k] for e in each), rtol=1e-4, atol=1e-4)


def test_overfit_two_real_scenes(overfit_run):
    # 80 steps: at 60 the loss was at 0.44 of its start through YNNPACK's convolutions and
    # 0.504 through Eigen's (the train step's on Intel CPUs), a plateau both leave by step 80
    # (0.39 either way; session 24). The run (conftest.py) goes on to 100 for test_scoring.
    losses = overfit_run[0][:80]
    assert np.all(np.isfinite(losses))
    assert losses[-1] < 0.5 * losses[0], losses[::10]


def test_split_train_step_equals_the_one_program_step(tiny_train_cache, small_scenes):
    """The train step as programs called chunk by chunk, each window's chunks' backward passes
    chained through the carry (`SplitTrainStep`; windows of 6 steps here, two chunks of 3 steps
    each, then the last step), against the one-program step over two steps: the same loss,
    statistics and gradient norm (a gradient missing a part, e.g. the map convolution's or a
    chunk's carry, changes it), and the same Adam steps of every parameter array
    (`small.assert_same_adam_training`: Adam's first steps move a parameter by about the
    learning rate whatever its gradient's size, so a few elements whose gradient is ~0 may
    differ). The split step is compiled from shapes alone, as `QuickStartTrainStep` compiles
    it in the background."""
    from scenegen_jax.likelihood.unroll import chunk_steps, num_windows
    from scenegen_jax.train.step import SplitTrainStep

    cfg = CFG.replace(rotate_augment=True, bptt_window=6)
    assert chunk_steps(cfg) == 3 and num_windows(cfg) == 2
    batch = jax.device_put(_batch(tiny_train_cache, small_scenes))
    shapes = jax.eval_shape(lambda: (init_state(cfg), batch))
    split, fused = SplitTrainStep(cfg, *shapes, quick=False), make_train_step(cfg)
    def flat(params):
        return flatten_dict(jax.tree.map(np.array, params), sep="/")

    init = flat(init_state(cfg).params)
    a, b = init_state(cfg), init_state(cfg)  # each step donates its state
    for step in (1, 2):
        a, sa = split(a, batch)
        b, sb = fused(b, batch)
        for k in sb:
            np.testing.assert_allclose(sa[k], sb[k], rtol=2e-5, atol=1e-5, err_msg=k)
        # Every parameter array on its own, so that a small one left without its gradient
        # fails even where the whole tree's norm hardly moves.
        assert_same_adam_training(init, flat(a.params), flat(b.params), cfg.learning_rate, step)
    assert int(a.step) == 2


def test_quick_start_swaps_in_the_one_program_step_once_compiled(monkeypatch):
    """`QuickStartTrainStep` runs the quick split step until the background compiles, started
    after the first step, of the split step with the train step's options and then of the
    one-program step are done, each in turn; runs of at most QUICK_START_STEPS steps keep
    the split step with the train step's options and never compile in the background;
    `close` waits for the background. (Stand-ins for the steps: the logic, not the
    compiler.)"""
    import threading

    from scenegen_jax.backend import QUICK_START_STEPS
    from scenegen_jax.train import step as step_module

    gates = {False: threading.Event(), "fused": threading.Event()}
    background, calls = threading.Event(), []

    def split(cfg, state, batch, quick):
        calls.append(quick)
        if not quick and background.is_set():  # the background's: waits for its gate
            gates[False].wait(timeout=30)
        return lambda state, batch: ("quick" if quick else "split", state)

    def compile_fused(*args):
        calls.append("fused")
        gates["fused"].wait(timeout=30)
        return lambda state, batch: ("fused", state)

    monkeypatch.setattr(step_module, "SplitTrainStep", split)
    monkeypatch.setattr(step_module, "compile_train_step", compile_fused)
    state, batch = (jnp.zeros(2), jnp.ones(3)), jnp.ones(4)
    short = step_module.QuickStartTrainStep(CFG, state, batch, None, QUICK_START_STEPS)
    assert short(state, batch)[0] == "split"
    short.close()
    assert short(state, batch)[0] == "split"  # no background compile at all
    background.set()
    quick = step_module.QuickStartTrainStep(CFG, state, batch, None, QUICK_START_STEPS + 1)
    assert calls == [False, True]  # nothing compiles beside the first step
    assert quick(state, batch)[0] == "quick"
    assert quick(state, batch)[0] == "quick"  # the split step still compiling
    gates[False].set()
    deadline = time.time() + 30
    while quick(state, batch)[0] == "quick" and time.time() < deadline:
        time.sleep(0.01)
    assert quick(state, batch)[0] == "split"  # the one-program step still compiling
    gates["fused"].set()
    quick.close()
    assert quick(state, batch)[0] == "fused"
    assert calls == [False, True, False, "fused"]


def test_train_step_compiles_once(tiny_train_cache):
    traces = []

    def counted(state, batch):
        traces.append(1)
        return train_step(state, batch, CFG)

    step = jax.jit(counted, donate_argnums=0)
    state = init_state(CFG)
    for i in range(3):
        idx = batch_indices(len(tiny_train_cache), CFG.batch_size, CFG.seed, i)
        state, _ = step(state, jax.device_put(_batch(tiny_train_cache, idx)))
    assert len(traces) == 1


def _batch_shapes(cfg, b: int) -> Batch:
    """The shapes and dtypes of a cached batch of `b` scenes of `cfg` (`gather_batch`)."""
    s, m = cfg.canvas_size, cfg.max_actors
    sds = jax.ShapeDtypeStruct
    actors = Actors(cls=sds((b, m), np.int32), position=sds((b, m, 2), np.float32),
                    size=sds((b, m, 2), np.float32), heading=sds((b, m), np.float32),
                    velocity=sds((b, m, 2), np.float32), valid=sds((b, m), np.bool_))
    ego = jax.tree.map(lambda x: sds((b, *x.shape), x.dtype), make_ego(cfg.ego_size_m))
    return Batch(sds((b, s, s, len(ALL_MAP_CHANNELS)), np.float16), actors, ego)


@pytest.mark.parametrize("cfg", [
    get_config("tiny", batch_size=1, bptt_window=10, max_actors=9),  # hidden 16, grid 32
    get_config("paper", grid_size=128, m_per_px=0.625, max_actors=4, bptt_window=5,
               batch_size=1, gn_groups=8, remat=False),  # hidden 32
], ids=["tiny", "paper-grid128"])
def test_step_memory_estimate_follows_xlas_buffer_plan(cfg):
    """`remat` "auto" decides on `step_bytes_without_remat`: within 10 % of the buffers XLA
    plans for the step without remat, at the presets' two hidden widths (its terms' fit)."""
    compiled = make_train_step(cfg).lower(init_state(cfg), _batch_shapes(cfg, 1)).compile()
    planned = compiled.memory_analysis().temp_size_in_bytes
    assert 0.9 < planned / step_bytes_without_remat(cfg, 1) < 1.1


def test_remat_auto_stores_activations_where_they_fit(monkeypatch):
    from scenegen_jax.train import step as step_module

    cfg = get_config("paper", remat="auto")
    need = step_bytes_without_remat(cfg, 1)
    assert need == 25 * 320**2 * (60 * 32 + 2800)  # 11.3 GiB: the paper's T 25, one scene
    assert step_bytes_without_remat(cfg, 16) == 16 * need
    monkeypatch.setattr(step_module, "free_memory_bytes", lambda: int(need / REMAT_FREE_SHARE) + 1)
    assert resolve_remat(cfg, 1).remat is False
    assert resolve_remat(cfg, 2).remat is True
    monkeypatch.setattr(step_module, "free_memory_bytes", lambda: 0)
    assert resolve_remat(cfg.replace(remat=False), 1).remat is False  # set values are kept
    assert resolve_remat(get_config("tiny"), 1) == get_config("tiny")


def test_empty_scene_is_one_stop_step(tiny_train_cache, small_scenes):
    batch = _batch(tiny_train_cache, small_scenes)
    empty = batch.actors.replace(valid=np.zeros_like(batch.actors.valid))
    batch = Batch(batch.canvas, empty, batch.ego)
    params = random_params(CFG, jax.random.key(3))
    maps, scene = crop_batch(batch, jnp.zeros(2), CFG)
    terms, valid, cls = jax.jit(
        lambda p: unroll_terms(p, CFG, maps, scene, CFG.hard_negatives))(params)
    assert np.asarray(valid).sum(1).tolist() == [1, 1]
    assert np.asarray(cls)[:, 0].tolist() == [3, 3]
    for k in ("location", "box", "heading", "velocity"):
        assert np.all(np.asarray(terms[k]) == 0)
    (loss, _), grads = jax.jit(jax.value_and_grad(loss_fn, has_aux=True), static_argnums=1)(
        params, CFG, maps, scene)
    assert np.isfinite(float(loss)) and float(loss) > 0
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))


def test_map_dropout_trains_as_on_a_blank_map(tiny_train_cache, small_scenes):
    batch = jax.device_put(_batch(tiny_train_cache, small_scenes))
    blank = batch._replace(canvas=jnp.zeros_like(batch.canvas))
    state = init_state(CFG)
    _, dropped = _jitted_train_step(state, batch, CFG.replace(map_dropout=1.0))
    _, no_map = _jitted_train_step(state, blank, CFG)
    _, with_map = _jitted_train_step(state, batch, CFG)
    np.testing.assert_allclose(dropped["loss"], no_map["loss"], rtol=1e-6)
    assert abs(float(dropped["loss"]) - float(with_map["loss"])) > 1e-3
    with pytest.raises(ValueError, match="map_dropout"):
        CFG.replace(map_dropout=1.5)


def test_train_layers_trains_only_the_weights_of_those_map_channels(tiny_train_cache,
                                                                    small_scenes):
    cfg = CFG.replace(map_layers=("lanes", "drivable", "crosswalks"), attribute_map_input=True,
                      separate_attribute_mlps=True, train_layers=("drivable",), learning_rate=1e-2)
    batch = jax.device_put(_batch(tiny_train_cache, small_scenes))
    state = init_state(cfg)
    start = flatten_dict(jax.tree.map(np.array, state.params), sep="/")
    new, _ = _jitted_train_step(state, batch, cfg)
    end = flatten_dict(new.params, sep="/")
    drivable = cfg.map_channels.index("drivable_area")
    changed = []
    for name, before in start.items():
        after = np.asarray(end[name])
        if name == "lstm1_map" or name.endswith("0_map_w"):
            axis = 2 if name == "lstm1_map" else 1
            others = np.delete(after, drivable, axis) == np.delete(before, drivable, axis)
            assert np.all(others), name
            if np.any(np.take(after, drivable, axis) != np.take(before, drivable, axis)):
                changed.append(name)
        else:
            assert np.array_equal(after, before), name
    # the drivable channel's weights move in layer 1's input and in each attribute MLP
    assert sorted(changed) == ["box0_map_w", "heading0_map_w", "lstm1_map", "velocity0_map_w"]
    with pytest.raises(ValueError, match="train_layers"):
        cfg.replace(train_layers=("nearest_lane",))


def test_train_params_trains_only_those_parameters():
    """Adam's update is zero on every parameter but the named ones, which move in full."""
    cfg = CFG.replace(train_params=("loc2_w", "class_mlp2"), learning_rate=1e-2)
    params = init_state(cfg).params
    opt = make_optimizer(cfg)
    grads = jax.tree.map(jnp.ones_like, params)
    # One program (eagerly, Adam's update compiled ~340 single operations one by one).
    updates, _ = jax.jit(opt.update)(grads, jax.jit(opt.init)(params), params)
    moved = sorted(
        jax.tree_util.keystr(path)
        for path, u in jax.tree_util.tree_flatten_with_path(updates)[0]
        if np.any(np.asarray(u) != 0)
    )
    assert moved == ["['class_mlp2']['bias']", "['class_mlp2']['kernel']", "['loc2_w']"]
    for path, u in jax.tree_util.tree_flatten_with_path(updates)[0]:
        if "loc2_w" in jax.tree_util.keystr(path):
            assert np.all(np.asarray(u) != 0)  # every entry of a named parameter trains
    with pytest.raises(ValueError, match=r"train_params: no parameter \['lstm9'\]"):
        make_optimizer(cfg.replace(train_params=("lstm9",))).update(
            grads, opt.init(params), params)
    with pytest.raises(ValueError, match="train_params"):
        CFG.replace(train_params=("",))


def test_warm_start_extends_a_model_without_map_layers(tiny_train_cache, small_scenes):
    from scenegen_jax.train.loop import warm_start

    no_map = CFG.replace(map_layers=())
    source = init_state(no_map, seed=1)
    params = warm_start(init_state(CFG).params, source.params, "src")
    flat = dict(jax.tree_util.tree_flatten_with_path(params)[0])
    for path, x in jax.tree_util.tree_flatten_with_path(source.params)[0]:
        np.testing.assert_array_equal(flat.pop(path), x)
    (path, x), = flat.items()  # the only parameter the source lacks: zero
    assert "lstm1_map" in jax.tree_util.keystr(path) and not np.any(np.asarray(x))
    # So the extended model starts as the source model: the same loss on real scenes.
    batch = jax.device_put(_batch(tiny_train_cache, small_scenes))
    state = init_state(CFG)._replace(params=params, opt_state=make_optimizer(CFG).init(params))
    _, extended = _jitted_train_step(state, batch, CFG)
    _, original = _jitted_train_step(source, batch, no_map)
    np.testing.assert_allclose(extended["loss"], original["loss"], rtol=1e-6)

    with pytest.raises(ValueError, match=r"src: parameter .* has shape"):
        warm_start(init_state(CFG).params, init_state(CFG.replace(hidden=4)).params, "src")
    del source.params["class_mlp0"]
    with pytest.raises(ValueError, match="src: no parameter class_mlp0"):
        warm_start(init_state(CFG).params, source.params, "src")


def test_init_from_reads_a_pretrained_model_or_names_what_it_is_not(tmp_path):
    """`--init-from` fine-tunes a pretrained model (directory or installed name) as well as a
    workdir; a path that is neither names both."""
    from scenegen_jax.pretrained import save_pretrained
    from scenegen_jax.train.loop import start_params

    params = init_state(CFG, seed=3).params
    save_pretrained(str(tmp_path / "model"), CFG, params, 7, "test")
    cfg, loaded = start_params(str(tmp_path / "model"))
    assert cfg.map_channels == CFG.map_channels and cfg.hidden == CFG.hidden
    for a, b in zip(jax.tree.leaves(loaded), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(FileNotFoundError, match="neither a workdir with checkpoints/ nor a "
                       "pretrained model .*installed"):
        start_params(str(tmp_path / "nothing"))


def test_a_failed_init_from_leaves_a_new_workdir_empty(tiny_train_cache, tmp_path):
    """`train --init-from` with a source that is not there, or of another shape, fails before
    it writes config.json or data.json, so the same workdir takes the next try's config."""
    from scenegen_jax.pretrained import save_pretrained
    from scenegen_jax.train.loop import train

    workdir = tmp_path / "wd"
    with pytest.raises(FileNotFoundError, match="--init-from: neither a workdir"):
        train(CFG, tiny_train_cache.path, str(workdir), steps=1, progress=False,
              init_from=str(tmp_path / "nothing"))
    save_pretrained(str(tmp_path / "narrow"), CFG.replace(hidden=4),
                    init_state(CFG.replace(hidden=4)).params, 1, "test")
    with pytest.raises(ValueError, match="narrow: parameter .* has shape"):
        train(CFG, tiny_train_cache.path, str(workdir), steps=1, progress=False,
              init_from=str(tmp_path / "narrow"))
    assert not workdir.exists() or not os.listdir(workdir)


def test_coordinate_channels_tell_rows_apart_and_start_at_zero_from_a_warm_start():
    """With `coord_channels` layer 1's gates depend on the pixel's row and column (a map that
    is the same everywhere gives different gates at the top and the bottom); extended from a
    model without them, the coordinates' weights start at zero and change nothing."""
    from scenegen_jax.train.loop import warm_start

    coord = CFG.replace(coord_channels=True)
    net = SceneGenNet(coord)
    flat_map = jnp.ones((1, CFG.grid_size, CFG.grid_size, len(CFG.map_channels)))
    params = init_state(coord, seed=2).params
    gates = net.apply({"params": params}, flat_map, method=SceneGenNet.map_gates)
    mid = CFG.grid_size // 2
    assert float(jnp.abs(gates[0, 3, mid] - gates[0, -4, mid]).max()) > 1e-3  # top vs bottom
    assert float(jnp.abs(gates[0, mid, 3] - gates[0, mid, -4]).max()) > 1e-3  # left vs right

    source = init_state(CFG, seed=1).params
    extended = warm_start(params, source, "src")
    assert not np.any(np.asarray(extended["lstm1_coord"]))
    want = SceneGenNet(CFG).apply({"params": source}, flat_map, method=SceneGenNet.map_gates)
    got = net.apply({"params": extended}, flat_map, method=SceneGenNet.map_gates)
    np.testing.assert_array_equal(got, want)


def test_order_channel_and_attribute_map_input_start_at_zero_from_a_warm_start():
    """`order_channel`'s gates are the convolution of a mask that is 1 from the previous
    actor's bin on (hand-built here, checked against `lax.conv`), every bin at a scene's first
    step. Extended from a model without them, the order channel's and the attribute MLPs' map
    weights (`attribute_map_input`, first and last layer with `attribute_map_skip`) start
    at zero and change nothing."""
    from scenegen_jax.train.loop import warm_start

    order = CFG.replace(order_channel=True, attribute_map_input=True, attribute_map_skip=True)
    net = SceneGenNet(order)
    params = init_state(order, seed=2).params
    n = CFG.grid_size
    prev = jnp.array([0, 5 * n + 7])  # first step; after an actor in row 5, column 7
    gates = net.apply({"params": params}, prev, method=SceneGenNet.order_gates)
    mask = np.ones((2, n, n, 1), np.float32)
    mask[1, :5] = 0.0
    mask[1, 5, :7] = 0.0
    want = jax.lax.conv_general_dilated(jnp.asarray(mask), params["lstm1_order"], (1, 1), "SAME",
                                        dimension_numbers=("NHWC", "HWIO", "NHWC"))
    np.testing.assert_allclose(gates, want, rtol=1e-5, atol=1e-5)
    assert float(jnp.abs(gates[0] - gates[1]).max()) > 1e-3

    source = init_state(CFG, seed=1).params
    params = {**params, "heading2_map_w": params["heading2_map_w"] + 1.0}  # as if trained
    extended = warm_start(params, source, "src")
    assert not np.any(np.asarray(extended["lstm1_order"]))
    assert not np.any(np.asarray(extended["heading2_map_w"]))
    assert not np.any(np.asarray(net.apply({"params": extended}, prev,
                                           method=SceneGenNet.order_gates)))
    feat = jax.random.normal(jax.random.key(3), (5, CFG.hidden))
    map_feat = jax.random.uniform(jax.random.key(4), (5, len(CFG.map_channels)))
    cls = jnp.array([0, 1, 2, 0, 1])
    with_map = net.apply({"params": params}, feat, cls, map_feat, method=SceneGenNet.attributes)
    got = net.apply({"params": extended}, feat, cls, map_feat, method=SceneGenNet.attributes)
    want = SceneGenNet(CFG).apply({"params": source}, feat, cls, method=SceneGenNet.attributes)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6)
    # With its own (non-zero) map weights every attribute depends on the map at the bin.
    no_map = net.apply({"params": params}, feat, cls, 0 * map_feat, method=SceneGenNet.attributes)
    for m, z in zip(with_map, no_map, strict=True):
        assert float(jnp.abs(m - z).max()) > 1e-4


def test_attribute_map_skip_adds_the_map_at_the_bin_linearly_to_each_output():
    """`attribute_map_skip`: each attribute's raw output is the `attribute_map_input` MLP's
    plus map_feat @ W[cls] (W: `{box,heading,velocity}2_map_w` [classes, Cm, out]),
    written out in numpy; zero weights (a fresh model) give the MLP's outputs."""
    skip_cfg = CFG.replace(attribute_map_input=True, attribute_map_skip=True)
    params = init_state(skip_cfg, seed=5).params
    mlp_only = {k: v for k, v in params.items() if not k.endswith("2_map_w")}
    rng = np.random.default_rng(6)
    weights = {f"{a}2_map_w": rng.normal(size=params[f"{a}2_map_w"].shape).astype(np.float32)
               for a in ("box", "heading", "velocity")}
    feat = jax.random.normal(jax.random.key(3), (4, CFG.hidden))
    map_feat = jax.random.uniform(jax.random.key(4), (4, len(CFG.map_channels)))
    cls = jnp.array([0, 2, 1, 0])

    def attrs(cfg, p):
        return SceneGenNet(cfg).apply({"params": p}, feat, cls, map_feat,
                                      method=SceneGenNet.attributes)

    base = attrs(CFG.replace(attribute_map_input=True), mlp_only)
    for got, want in zip(attrs(skip_cfg, params), base, strict=True):
        np.testing.assert_array_equal(got, want)
    got = attrs(skip_cfg, {**params, **weights})
    m, c = np.asarray(map_feat), np.asarray(cls)
    for g, b, name in zip(got, base, ("box", "heading", "velocity"), strict=True):
        w = weights[f"{name}2_map_w"]
        want = np.asarray(b) + np.stack([m[i] @ w[c[i]] for i in range(4)])
        np.testing.assert_allclose(g, want, rtol=1e-5, atol=1e-5)


def test_separate_attribute_mlps_keep_each_attribute_to_its_own_weights_and_warm_start_exactly():
    """With `separate_attribute_mlps` (the paper's MLP_box, MLP_theta, MLP_v) the heading
    parameters depend on the heading MLP only: no gradient reaches the box or velocity MLPs'
    weights from them, while with the shared MLP it does. Split from a shared model, the three
    MLPs give exactly the shared model's outputs."""
    from scenegen_jax.train.loop import warm_start

    sep, shared_cfg = (CFG.replace(separate_attribute_mlps=s) for s in (True, False))
    net, shared_net = SceneGenNet(sep), SceneGenNet(shared_cfg)
    feat = jax.random.normal(jax.random.key(0), (5, CFG.hidden))
    cls = jnp.array([0, 1, 2, 0, 2])

    def heading_grads(model, params):
        def heading_sum(p):
            return jnp.sum(model.apply({"params": p}, feat, cls, method=SceneGenNet.attributes)[1])

        return jax.grad(heading_sum)(params)

    params = init_state(sep, seed=1).params
    grads = heading_grads(net, params)
    for name in ("box", "velocity"):
        for layer in range(3):
            assert not np.any(np.asarray(grads[f"{name}{layer}_w"])), (name, layer)
    assert np.any(np.asarray(grads["heading0_w"]))
    shared = init_state(shared_cfg, seed=1).params
    shared_grads = heading_grads(shared_net, shared)
    assert np.any(np.asarray(shared_grads["attr0_w"]))  # the box and velocity use it too

    split = warm_start(params, shared, "src")
    assert not any(k.startswith("attr") for k in split)
    got = net.apply({"params": split}, feat, cls, method=SceneGenNet.attributes)
    want = shared_net.apply({"params": shared}, feat, cls, method=SceneGenNet.attributes)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    jax.jit(lambda p: p, donate_argnums=0)(split)  # one buffer each, as a train step donates
    with pytest.raises(ValueError, match="src: no parameter attr0_[wb]"):
        warm_start(shared, params, "src")  # separate back to shared: not derived


def test_initial_parameters_are_the_same_compiled_alone_or_inside_a_trace():
    """`init_params` compiles its initialisers on their own (at XLA:CPU's lowest optimisation
    level) unless it is called inside a trace, where it is traced with the caller: both give
    the same parameters, and `jax.eval_shape` of it works (restoring a checkpoint uses it)."""
    from scenegen_jax.model.network import init_params

    alone = init_params(CFG, jax.random.key(3))
    traced = jax.jit(lambda k: init_params(CFG, k))(jax.random.key(3))
    shapes = jax.eval_shape(lambda: init_params(CFG, jax.random.key(3)))
    assert jax.tree.structure(alone) == jax.tree.structure(traced) == jax.tree.structure(shapes)
    for a, t, s in zip(jax.tree.leaves(alone), jax.tree.leaves(traced), jax.tree.leaves(shapes),
                       strict=True):
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

    from scenegen_jax.model.network import TRUNCATED_STD, init_params

    params = flatten_dict(jax.device_get(init_params(CFG, jax.random.key(7))), sep="/")
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


def test_a_fresh_state_holds_the_parameters_of_its_seed_and_zero_optimizer_moments(monkeypatch):
    """`init_state` compiles parameters and optimizer state as one program: its parameters
    are `init_params` of the first half of the seed's key split, its step 0, Adam's moments
    zero, and its key the other half; `jax.eval_shape` of it works (resuming uses it), also
    where the initialisation's compiler options are set (outside this suite, whose XLA_FLAGS
    set the level: nested jits must not take them)."""
    from scenegen_jax.backend import init_compiler_options
    from scenegen_jax.model.network import init_params
    from scenegen_jax.train.step import init_state

    monkeypatch.setenv("XLA_FLAGS", "")
    assert init_compiler_options(), "on CPU the initialisation has compiler options"

    state = init_state(CFG, seed=5)
    init_key, base = jax.random.split(jax.random.key(5))
    expected = init_params(CFG, init_key)
    for a, e in zip(jax.tree.leaves(state.params), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-6, atol=1e-7)
    assert int(state.step) == 0
    np.testing.assert_array_equal(state.key, jax.random.key_data(base))
    moments = [x for x in jax.tree.leaves(state.opt_state) if x.ndim > 0]
    assert len(moments) >= 2 * len(jax.tree.leaves(expected))
    assert all(not np.any(np.asarray(x)) for x in moments)
    shapes = jax.eval_shape(lambda: init_state(CFG))
    assert jax.tree.structure(shapes) == jax.tree.structure(state)


def test_a_parameter_of_the_wrong_shape_is_named_when_the_network_is_applied():
    """The network reads its stored parameters without flax's check (which traces each
    initialiser at every apply) and checks their shapes itself: a parameter of another
    config's shape is an error that names it, with both shapes; a missing one, flax's."""
    from flax.errors import ScopeParamNotFoundError, ScopeParamShapeError

    from scenegen_jax.model.network import SceneGenNet, init_params

    params = dict(init_params(CFG, jax.random.key(0)))
    net = SceneGenNet(CFG)
    state = net.apply({"params": params}, 1, method=SceneGenNet.initial_state)
    assert state[0][0].shape == (1, CFG.grid_size, CFG.grid_size, CFG.hidden)
    params["lstm2_w"] = np.zeros((5, 5, 2 * CFG.hidden, 4 * CFG.hidden + 1), np.float32)
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
    got = np.asarray(orientation_sectors(jnp.asarray(length * np.cos(deg)),
                                         jnp.asarray(length * np.sin(deg)), 8))
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
    np.testing.assert_allclose(turned, np.roll(orientation_sectors(jnp.cos(a), jnp.sin(a), 6),
                                               1, axis=-1), atol=1e-5)


def test_orientation_bins_tell_lane_directions_apart_and_start_at_zero_from_a_warm_start():
    """With `orientation_bins` layer 1's gates on a lane depend on which way the lane points
    (the same lane mask with opposite directions gives different gates); extended from a
    model without them, the sectors' weights start at zero and change nothing."""
    from scenegen_jax.train.loop import warm_start

    binned = CFG.replace(orientation_bins=4)
    net = SceneGenNet(binned)
    ic, is_ = (CFG.map_channels.index(c) for c in ("lane_orientation_cos",
                                                     "lane_orientation_sin"))
    east = np.zeros((1, CFG.grid_size, CFG.grid_size, len(CFG.map_channels)), np.float32)
    east[0, 10:14, :, CFG.map_channels.index("lane_vehicle")] = 1.0
    west = east.copy()
    east[0, 10:14, :, ic], west[0, 10:14, :, ic] = 1.0, -1.0
    assert is_ != ic
    params = init_state(binned, seed=2).params

    def gate_gap(p):  # how far apart the east and west lanes' gates are on the lane
        east_g, west_g = (net.apply({"params": p}, jnp.asarray(m), method=SceneGenNet.map_gates)
                          for m in (east, west))
        return float(jnp.abs(east_g - west_g)[0, 12].max())

    # The raw cos channel differs too (+1 against -1): without the map convolution's weights
    # only the sectors can tell the two apart, and without the sectors' weights nothing can.
    no_map = {**params, "lstm1_map": jnp.zeros_like(params["lstm1_map"])}
    assert gate_gap(no_map) > 1e-3
    assert gate_gap({**no_map, "lstm1_orient": jnp.zeros_like(params["lstm1_orient"])}) == 0.0

    source = init_state(CFG, seed=1).params
    extended = warm_start(params, source, "src")
    assert not np.any(np.asarray(extended["lstm1_orient"]))
    want = SceneGenNet(CFG).apply({"params": source}, jnp.asarray(east),
                                  method=SceneGenNet.map_gates)
    got = net.apply({"params": extended}, jnp.asarray(east), method=SceneGenNet.map_gates)
    np.testing.assert_array_equal(got, want)


def test_a_new_map_layer_group_starts_at_zero_from_a_warm_start():
    """Extended with the `nearest_lane` layers, a model keeps each old map channel's weights
    (layer 1's convolution, the attribute MLPs' map weights) and gives the new channels zero:
    on any map, its gates and attributes are the source's on the old channels. A source
    trained with a channel the config lacks is refused by name."""
    from scenegen_jax.train.loop import warm_start

    old = CFG.replace(map_layers=("lanes", "drivable"), attribute_map_input=True,
                      attribute_map_skip=True)
    wide = old.replace(map_layers=("lanes", "drivable", "nearest_lane"))
    assert wide.map_channels[-2:] == ("nearest_lane_cos", "nearest_lane_sin")
    source = init_state(old, seed=1).params
    params = warm_start(init_state(wide, seed=2).params, source, "src", wide.map_channels,
                        old.map_channels)
    keep = [wide.map_channels.index(c) for c in old.map_channels]
    np.testing.assert_array_equal(np.asarray(params["lstm1_map"])[:, :, keep],
                                  source["lstm1_map"])
    assert not np.any(np.asarray(params["lstm1_map"])[:, :, -2:])
    raster = jax.random.normal(jax.random.key(0), (1, CFG.grid_size, CFG.grid_size,
                                                   len(wide.map_channels)))
    got = SceneGenNet(wide).apply({"params": params}, raster, method=SceneGenNet.map_gates)
    want = SceneGenNet(old).apply({"params": source}, raster[..., keep],
                                  method=SceneGenNet.map_gates)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    feat = jax.random.normal(jax.random.key(3), (5, CFG.hidden))
    cls = jnp.array([0, 1, 2, 0, 1])
    got = SceneGenNet(wide).apply({"params": params}, feat, cls, raster[0, 0, :5],
                                  method=SceneGenNet.attributes)
    want = SceneGenNet(old).apply({"params": source}, feat, cls, raster[0, 0, :5][:, keep],
                                  method=SceneGenNet.attributes)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match=r"src: trained with map channels \['crosswalk'\]"):
        warm_start(params, init_state(CFG, seed=1).params, "src", wide.map_channels,
                   CFG.map_channels)


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
    i, j = (cfg.map_channels.index(c) for c in ("nearest_lane_cos", "nearest_lane_sin"))
    a = np.array([0.0, 0.7, 2.5, -1.9, 1.0])
    length = np.array([1.0, 1.0, 0.8, 1.0, 0.3])  # 0.3: no lane (no turn)
    map_feat = np.zeros((5, len(cfg.map_channels)), np.float32)
    map_feat[:, i], map_feat[:, j] = length * np.cos(a), length * np.sin(a)
    feat = jnp.broadcast_to(jax.random.normal(jax.random.key(1), (1, cfg.hidden)), (5, cfg.hidden))
    cls = jnp.zeros((5,), jnp.int32)
    net = SceneGenNet(cfg)
    box, heading, velocity = net.apply({"params": params}, feat, cls, jnp.asarray(map_feat),
                                       method=SceneGenNet.attributes)
    base = net.apply({"params": params}, feat, cls, jnp.zeros_like(map_feat),
                     method=SceneGenNet.attributes)
    np.testing.assert_array_equal(box, base[0])
    np.testing.assert_array_equal(velocity, base[2])
    unturned = split_heading(base[1][0])
    w = np.exp(unturned.logits - np.logaddexp.reduce(np.asarray(unturned.logits)))
    mu = np.arctan2(unturned.direction[:, 1], unturned.direction[:, 0])
    kappa = np.exp(np.asarray(unturned.log_kappa))
    h = np.linspace(-np.pi, np.pi, 7)
    for n, turn in enumerate(np.where(length >= 0.5, a, 0.0)):
        want = np.log(sum(wk * stats.vonmises.pdf(h - turn, kk, loc=mk)
                          for wk, kk, mk in zip(w, kappa, mu, strict=True)))
        got = [float(heading_log_prob(heading[n], jnp.float32(x))) for x in h]
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def test_a_warm_start_into_the_lane_frame_starts_the_heading_layer_afresh():
    """From a model whose headings are in the grid's frame, `heading_lane_frame` takes every
    parameter but the heading MLP's last layer (`reframed`), which keeps its fresh values; a
    model with one attribute MLP for all three is refused by name."""
    from flax.traverse_util import flatten_dict

    from scenegen_jax.train.loop import HEADING_LAST_LAYER, reframed, warm_start

    old = CFG.replace(map_layers=("lanes", "nearest_lane"), attribute_map_input=True,
                      attribute_map_skip=True)
    new = old.replace(heading_lane_frame=True)
    assert reframed(new, new) == () and reframed(old, old) == ()
    source = init_state(old, seed=1).params
    fresh = init_state(new, seed=2).params
    got = warm_start(fresh, source, "src", fresh=reframed(new, old))
    assert set(HEADING_LAST_LAYER) <= set(got)
    fresh, source = flatten_dict(fresh, sep="/"), flatten_dict(source, sep="/")
    for name, x in flatten_dict(got, sep="/").items():
        want = fresh[name] if name in HEADING_LAST_LAYER else source[name]
        np.testing.assert_array_equal(x, want, err_msg=name)
    with pytest.raises(ValueError, match="heading_lane_frame: .* separate_attribute_mlps"):
        reframed(new.replace(separate_attribute_mlps=False, attribute_map_input=False,
                             attribute_map_skip=False), old)


def test_nan_batch_is_rejected_before_the_optimizer(tiny_train_cache, small_scenes):
    batch = _batch(tiny_train_cache, small_scenes)
    batch.actors.velocity[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"scene b/.*actors\.velocity"):
        check_batch(batch, ["a/1", "b/2"])


# ------------------------------------------------------------ subprocess tests


def _params(workdir, step=None):
    from scenegen_jax.train.loop import load_trained

    cfg, state = load_trained(workdir, step)
    return int(state.step), jax.tree.leaves(state.params)


def test_load_trained_picks_a_saved_step(tmp_path):
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.train.loop import load_trained, save_or_check_config

    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, CFG)
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1, keep=5)
    state = init_state(CFG)
    for step in (1, 2):
        ckpt.save(state._replace(step=jnp.asarray(step, state.step.dtype)), force=True)
    ckpt.close()
    assert int(load_trained(workdir)[1].step) == 2
    assert int(load_trained(workdir, 1)[1].step) == 1
    with pytest.raises(ValueError, match=r"no checkpoint at step 5; saved: \[1, 2\]"):
        load_trained(workdir, 5)


def _saved_entries(folder: str) -> str:
    """The text of orbax's tree metadata of a saved step (its entries' key paths)."""
    paths = [os.path.join(d, "_METADATA") for d, _, files in os.walk(folder)
             if "_METADATA" in files]
    assert paths, f"no orbax metadata under {folder}"
    return "".join(open(p).read() for p in paths)


def test_ema_averages_every_steps_parameters_resumes_and_is_what_the_workdir_gives(
        tiny_train_cache, small_scenes, tmp_path):
    """With `ema_decay` d the state carries a_k = d a_(k-1) + (1 - d) p_k from the starting
    parameters (the recurrence in numpy over the steps' own parameters), in buffers of its
    own (the donating step takes both); a checkpoint keeps it and a resumed step continues
    it; `load_params` (what score, sample, export-model and --init-from read) gives it, and
    without `ema_decay` the last parameters, saved without an `ema` entry."""
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.train.loop import load_trained, save_or_check_config
    from scenegen_jax.workdir import load_params

    cfg = CFG.replace(ema_decay=0.75)
    step = make_train_step(cfg)
    batch = _batch(tiny_train_cache, small_scenes)
    state = init_state(cfg)
    average = [np.asarray(x) for x in jax.tree.leaves(state.params)]
    saved_at_two = None
    for k in range(3):
        state, _ = step(state, batch)
        average = [0.75 * a + 0.25 * np.asarray(p)
                   for a, p in zip(average, jax.tree.leaves(state.params), strict=True)]
        if k == 1:
            workdir = str(tmp_path / "ema")
            save_or_check_config(workdir, cfg)
            ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1)
            ckpt.save(state, force=True)
            ckpt.close()
            saved_at_two = [a.copy() for a in average]
    for a, e in zip(jax.tree.leaves(state.ema), average, strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-6, atol=1e-7)
    moved = [np.abs(np.asarray(e) - np.asarray(p)).max()
             for e, p in zip(jax.tree.leaves(state.ema), jax.tree.leaves(state.params),
                             strict=True)]
    assert max(moved) > 1e-4, "the average lags the parameters"

    cfg_read, params, at = load_params(workdir)
    assert at == 2 and cfg_read.ema_decay == 0.75
    for a, e in zip(jax.tree.leaves(params), saved_at_two, strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-6, atol=1e-7)
    _, resumed = load_trained(workdir)
    resumed, _ = step(resumed, batch)
    for a, e in zip(jax.tree.leaves(resumed.ema), jax.tree.leaves(state.ema), strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-6, atol=1e-7)

    plain = str(tmp_path / "plain")
    save_or_check_config(plain, CFG)
    ckpt = Checkpointer(os.path.join(plain, "checkpoints"), every=1)
    ckpt.save(state._replace(ema=None, step=jnp.asarray(7, jnp.int32)), force=True)
    ckpt.close()
    assert "('ema'," in _saved_entries(os.path.join(workdir, "checkpoints", "2"))
    assert "('ema'," not in _saved_entries(os.path.join(plain, "checkpoints", "7"))
    _, params, _ = load_params(plain)
    for a, e in zip(jax.tree.leaves(params), jax.tree.leaves(state.params), strict=True):
        np.testing.assert_array_equal(a, e)
    assert load_trained(plain)[1].ema is None


def test_compile_cache_is_written_where_configured(tmp_path):
    script = """
import json, os, jax, jax.numpy as jnp
from scenegen_jax.cli import enable_compile_cache
os.environ["SCENEGEN_COMPILE_CACHE"] = "off"
off = enable_compile_cache()
del os.environ["SCENEGEN_COMPILE_CACHE"]
on = enable_compile_cache()
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.jit(lambda x: jnp.cumsum(x) * 3)(jnp.arange(5.0)).block_until_ready()
print(json.dumps({"off": off, "on": on, "files": sorted(os.listdir(on))}))
"""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION", "SCENEGEN"))}
    env.update(XDG_CACHE_HOME=str(tmp_path), JAX_PLATFORMS="cpu")
    res = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.splitlines()[-1])
    assert out["off"] is None
    assert out["on"] == str(tmp_path / "scenegen_jax" / "jax")
    assert any(f.startswith("jit__lambda-") for f in out["files"]), out["files"]


def test_xla_flags_optimisation_level_wins_over_the_packages(monkeypatch):
    """The train step and the sampler compile at XLA:CPU level 1 unless XLA_FLAGS names a
    level (this suite's 0): an explicit compiler option would override it."""
    from scenegen_jax.backend import sampling_compiler_options, train_compiler_options

    level = "xla_backend_optimization_level"
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    assert train_compiler_options()[level] == 1 and sampling_compiler_options()[level] == 1
    monkeypatch.setenv("XLA_FLAGS", f"--{level}=0 --xla_cpu_multi_thread_eigen=false")
    assert level not in train_compiler_options() and level not in sampling_compiler_options()
    assert "xla_cpu_opt_preset" in train_compiler_options()


@pytest.mark.slow
def test_killed_run_resumes_exactly(tiny_train_cache, tmp_path):
    cache = tiny_train_cache.path
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    steps = 10
    full = str(tmp_path / "full")
    cli.main(train_args(cache, full, steps))  # in this process: CFG's programs are traced

    killed = str(tmp_path / "killed")
    proc = subprocess.Popen(
        train_cmd(cache, killed, steps),
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    ckpts = os.path.join(killed, "checkpoints")
    deadline = time.time() + 300
    while time.time() < deadline:
        done = [d for d in os.listdir(ckpts)] if os.path.isdir(ckpts) else []
        if any(d.isdigit() and int(d) >= 4 for d in done):
            break
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    step_at_kill, _ = _params(killed)
    assert 4 <= step_at_kill < steps
    metrics = os.path.join(killed, "metrics.jsonl")
    before = [row for row in metrics_rows(metrics) if json.loads(row)["step"] <= step_at_kill]
    assert len(before) == step_at_kill // 2  # a row every 2 steps, each before its checkpoint
    cli.main(train_args(cache, killed, steps))  # resumes from the killed process's checkpoint
    # The killed process's rows stay as it wrote them, timings included: the run went on from
    # its checkpoint (a run started again from step 0 would rewrite them) ...
    after = metrics_rows(metrics)
    assert after[: len(before)] == before
    assert [json.loads(row)["step"] for row in after] == list(range(2, steps + 1, 2))
    assert not os.path.exists(ckpts + ".damaged")  # ... and set no checkpoint aside

    s_full, p_full = _params(full)
    s_killed, p_killed = _params(killed)
    assert s_full == s_killed == steps
    for a, b in zip(p_full, p_killed, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6, rtol=0)


@pytest.mark.slow
def test_sharded_step_equals_single_device(tiny_train_cache, tmp_path):
    """One train step of a batch of 8 on one device and sharded over 8: the same loss and
    gradient norm, and the same Adam step (`small.assert_same_adam_training`)."""
    out_file = tmp_path / "params.npz"
    script = f"""
import jax, numpy as np
from flax.traverse_util import flatten_dict
from scenegen_jax.config import get_config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.backend import make_mesh
from scenegen_jax.likelihood.batch import gather_batch, to_device
from scenegen_jax.train.step import init_state, make_train_step
from jax.sharding import NamedSharding, PartitionSpec as P
assert jax.device_count() == 8, jax.devices()
# CFG's one window of 7 steps: two programs to compile, each smaller than with two windows.
cfg = get_config("tiny").replace(max_actors={CFG.max_actors}, bptt_window={CFG.bptt_window},
                                 batch_size=8, hidden=8, gn_groups=2)
cache = load_cache({tiny_train_cache.path!r})
host = gather_batch(cache, np.arange(8), cfg)
out, params = [], {{"init": init_state(cfg).params}}
for name, mesh in (("one", make_mesh(jax.devices()[:1])), ("eight", make_mesh())):
    step = make_train_step(cfg, mesh)
    state = jax.device_put(init_state(cfg), NamedSharding(mesh, P()))
    batch = to_device(host, NamedSharding(mesh, P("data")))
    assert len(batch.canvas.sharding.device_set) == mesh.size
    state, stats = step(state, batch)
    out.append((float(stats["loss"]), float(stats["grad_norm"])))
    params[name] = state.params
np.testing.assert_allclose(out[0], out[1], rtol=1e-4)
np.savez({str(out_file)!r}, **{{f"{{run}}|{{k}}": np.asarray(v) for run, p in params.items()
                              for k, v in flatten_dict(jax.device_get(p), sep="/").items()}})
print("OK", out[0][0], out[1][0])
"""
    env = with_xla_flags({**os.environ, "JAX_PLATFORMS": "cpu"},
                         "--xla_force_host_platform_device_count=8")
    res = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, cwd=REPO
    )
    assert res.returncode == 0, res.stderr[-3000:]
    assert "OK" in res.stdout
    runs: dict[str, dict] = {}
    with np.load(out_file) as f:
        for key in f.files:
            run, name = key.split("|")
            runs.setdefault(run, {})[name] = f[key]
    assert_same_adam_training(runs["init"], runs["one"], runs["eight"],
                              get_config("tiny").learning_rate, 1)


def test_logged_metrics_are_means_over_the_logged_steps():
    """`summarize` on hand-made sums of two steps: loss and gradient norm per batch, NLL per
    scene, per actor of each class and per vehicle; None for a class with no actor."""
    from scenegen_jax.train.loop import summarize

    stats = {"batches": 2, "scenes": 8, "loss": 30.0, "grad_norm": 5.0, "nll_sum_stop": 4.0,
             **{f"nll_{k}": 16.0 for k in ("class", "location", "box", "heading", "velocity")},
             "count_vehicle": 10, "nll_sum_vehicle": 25.0, "count_pedestrian": 4,
             "nll_sum_pedestrian": 2.0, "count_bicyclist": 0, "nll_sum_bicyclist": 0.0,
             **{f"nll_{k}_sum_vehicle": 3.0 for k in ("location", "box", "heading", "velocity")}}
    row = summarize(stats)
    assert row["loss"] == 15.0 and row["grad_norm"] == 2.5
    assert row["nll_location"] == 2.0 and row["nll_stop"] == 0.5
    assert row["nll_per_vehicle"] == 2.5 and row["nll_per_pedestrian"] == 0.5
    assert row["nll_per_bicyclist"] is None
    assert row["heading_per_vehicle"] == pytest.approx(0.3)
