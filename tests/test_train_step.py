"""The train step on real scenes (small tiny config): the optimizer's schedule, the loss
falling, the split step against the one-program step, one compile, the memory estimate and
remat, empty scenes, map dropout, training a subset of the parameters, sharding."""

from __future__ import annotations

import os
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
    random_params,
    two_small_scenes,
    with_xla_flags,
)
from train_batches import batch_of, jitted_train_step

from scenegen_jax.config import get_config
from scenegen_jax.likelihood.batch import Batch, batch_scenes, check_batch, gather_batch
from scenegen_jax.likelihood.unroll import unroll_terms
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


def test_overfit_two_real_scenes(overfit_run):
    # 80 steps: at 60 the loss is near half its start through YNNPACK's convolutions and just
    # above it through Eigen's (the train step's on Intel CPUs), a plateau both leave by step
    # 80. The run (conftest.py) goes on to 100 for test_scoring.
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
    from scenegen_jax.likelihood.grads import chunk_steps
    from scenegen_jax.likelihood.unroll import num_windows
    from scenegen_jax.train.programs import SplitTrainStep

    cfg = CFG.replace(rotate_augment=True, bptt_window=6)
    assert chunk_steps(cfg.model) == 3 and num_windows(cfg.model) == 2
    batch = jax.device_put(gather_batch(tiny_train_cache, small_scenes, cfg.grid, [0.5, 2.0]))
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
        assert_same_adam_training(init, flat(a.params), flat(b.params), cfg.train.learning_rate,
                                  step)
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
    from scenegen_jax.train import programs

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

    monkeypatch.setattr(programs, "SplitTrainStep", split)
    monkeypatch.setattr(programs, "compile_train_step", compile_fused)
    state, batch = (jnp.zeros(2), jnp.ones(3)), jnp.ones(4)
    short = programs.QuickStartTrainStep(CFG, state, batch, None, QUICK_START_STEPS)
    assert short(state, batch)[0] == "split"
    short.close()
    assert short(state, batch)[0] == "split"  # no background compile at all
    background.set()
    quick = programs.QuickStartTrainStep(CFG, state, batch, None, QUICK_START_STEPS + 1)
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
        idx = batch_indices(len(tiny_train_cache), CFG.train.batch_size, CFG.train.seed, i)
        state, _ = step(state, jax.device_put(batch_of(tiny_train_cache, idx)))
    assert len(traces) == 1


def _batch_shapes(cfg, b: int) -> Batch:
    """The shapes and dtypes of a cached batch of `b` scenes of `cfg` (`gather_batch`)."""
    h, m = cfg.grid.grid_size, cfg.grid.max_actors
    sds = jax.ShapeDtypeStruct
    actors = Actors(
        cls=sds((b, m), np.int32),
        position=sds((b, m, 2), np.float32),
        size=sds((b, m, 2), np.float32),
        heading=sds((b, m), np.float32),
        velocity=sds((b, m, 2), np.float32),
        valid=sds((b, m), np.bool_),
    )
    ego = jax.tree.map(lambda x: sds((b, *x.shape), x.dtype), make_ego(cfg.grid.ego_size_m))
    return Batch(sds((b, h, h, len(cfg.grid.map_channels)), np.float32), sds((b,), np.float32),
                 actors, ego)


@pytest.mark.parametrize(
    "cfg",
    [
        get_config("tiny", batch_size=1, bptt_window=10, max_actors=9),  # hidden 16, grid 32
        get_config(
            "paper",
            grid_size=128,
            m_per_px=0.625,
            max_actors=4,
            bptt_window=5,
            batch_size=1,
            gn_groups=8,
            remat=False,
        ),  # hidden 32
    ],
    ids=["tiny", "paper-grid128"],
)
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
    assert resolve_remat(cfg, 1).train.remat is False
    assert resolve_remat(cfg, 2).train.remat is True
    monkeypatch.setattr(step_module, "free_memory_bytes", lambda: 0)
    assert resolve_remat(cfg.replace(remat=False), 1).train.remat is False  # set values are kept
    assert resolve_remat(get_config("tiny"), 1) == get_config("tiny")


def test_empty_scene_is_one_stop_step(tiny_train_cache, small_scenes):
    batch = batch_of(tiny_train_cache, small_scenes)
    empty = batch.actors.replace(valid=np.zeros_like(batch.actors.valid))
    batch = batch._replace(actors=empty)
    params = random_params(CFG, jax.random.key(3))
    maps, scene = batch_scenes(batch, CFG.grid)
    terms, valid, cls = jax.jit(
        lambda p: unroll_terms(p, CFG.model, maps, scene, CFG.train.hard_negatives)
    )(params)
    assert np.asarray(valid).sum(1).tolist() == [1, 1]
    assert np.asarray(cls)[:, 0].tolist() == [3, 3]
    for k in ("location", "box", "heading", "velocity"):
        assert np.all(np.asarray(terms[k]) == 0)
    (loss, _), grads = jax.jit(jax.value_and_grad(loss_fn, has_aux=True), static_argnums=1)(
        params, CFG, maps, scene
    )
    assert np.isfinite(float(loss)) and float(loss) > 0
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))


def test_map_dropout_trains_as_on_a_blank_map(tiny_train_cache, small_scenes):
    batch = jax.device_put(batch_of(tiny_train_cache, small_scenes))
    blank = batch._replace(maps=jnp.zeros_like(batch.maps))
    state = init_state(CFG)
    _, dropped = jitted_train_step(state, batch, CFG.replace(map_dropout=1.0))
    _, no_map = jitted_train_step(state, blank, CFG)
    _, with_map = jitted_train_step(state, batch, CFG)
    np.testing.assert_allclose(dropped["loss"], no_map["loss"], rtol=1e-6)
    assert abs(float(dropped["loss"]) - float(with_map["loss"])) > 1e-3
    with pytest.raises(ValueError, match="map_dropout"):
        CFG.replace(map_dropout=1.5)


def test_train_layers_trains_only_the_weights_of_those_map_channels(tiny_train_cache, small_scenes):
    cfg = CFG.replace(
        map_layers=("lanes", "drivable", "crosswalks"),
        attribute_map_input=True,
        separate_attribute_mlps=True,
        train_layers=("drivable",),
        learning_rate=1e-2,
    )
    batch = jax.device_put(batch_of(tiny_train_cache, small_scenes))
    state = init_state(cfg)
    start = flatten_dict(jax.tree.map(np.array, state.params), sep="/")
    new, _ = jitted_train_step(state, batch, cfg)
    end = flatten_dict(new.params, sep="/")
    drivable = cfg.grid.map_channels.index("drivable_area")
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
        make_optimizer(cfg.replace(train_params=("lstm9",))).update(grads, opt.init(params), params)
    with pytest.raises(ValueError, match="train_params"):
        CFG.replace(train_params=("",))


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
    expected = init_params(CFG.model, init_key)
    for a, e in zip(jax.tree.leaves(state.params), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-6, atol=1e-7)
    assert int(state.step) == 0
    np.testing.assert_array_equal(state.key, jax.random.key_data(base))
    moments = [x for x in jax.tree.leaves(state.opt_state) if x.ndim > 0]
    assert len(moments) >= 2 * len(jax.tree.leaves(expected))
    assert all(not np.any(np.asarray(x)) for x in moments)
    shapes = jax.eval_shape(lambda: init_state(CFG))
    assert jax.tree.structure(shapes) == jax.tree.structure(state)


def test_nan_batch_is_rejected_before_the_optimizer(tiny_train_cache, small_scenes):
    batch = batch_of(tiny_train_cache, small_scenes)
    batch.actors.velocity[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"scene b/.*actors\.velocity"):
        check_batch(batch, ["a/1", "b/2"])


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
cfg = get_config("tiny").replace(max_actors={CFG.grid.max_actors},
                                 bptt_window={CFG.model.bptt_window},
                                 batch_size=8, hidden=8, gn_groups=2)
cache = load_cache({tiny_train_cache.path!r})
host = gather_batch(cache, np.arange(8), cfg.grid)
out, params = [], {{"init": init_state(cfg).params}}
for name, mesh in (("one", make_mesh(jax.devices()[:1])), ("eight", make_mesh())):
    step = make_train_step(cfg, mesh)
    state = jax.device_put(init_state(cfg), NamedSharding(mesh, P()))
    batch = to_device(host, NamedSharding(mesh, P("data")))
    assert len(batch.maps.sharding.device_set) == mesh.size
    state, stats = step(state, batch)
    out.append((float(stats["loss"]), float(stats["grad_norm"])))
    params[name] = state.params
np.testing.assert_allclose(out[0], out[1], rtol=1e-4)
np.savez({str(out_file)!r}, **{{f"{{run}}|{{k}}": np.asarray(v) for run, p in params.items()
                              for k, v in flatten_dict(jax.device_get(p), sep="/").items()}})
print("OK", out[0][0], out[1][0])
"""
    env = with_xla_flags(
        {**os.environ, "JAX_PLATFORMS": "cpu"}, "--xla_force_host_platform_device_count=8"
    )
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
    assert_same_adam_training(
        runs["init"], runs["one"], runs["eight"], get_config("tiny").train.learning_rate, 1
    )
