"""Warm starts (`train.warm_start`, `train --init-from`): a model extended with map layers,
coordinates, orientation sectors, the canonical order channel or the map at the bin starts as
its source; split attribute MLPs give the shared one's outputs; the lane frame starts the
heading layer afresh; a bad source fails before the workdir is written."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax.traverse_util import flatten_dict
from small import (
    CFG,
    two_small_scenes,
)
from train_batches import batch_of, jitted_train_step

from scenegen_jax.model.network import SceneGenNet
from scenegen_jax.train.step import (
    init_state,
    make_optimizer,
)


@pytest.fixture(scope="module")
def small_scenes(tiny_train_cache):
    return two_small_scenes(tiny_train_cache)


def test_warm_start_extends_a_model_without_map_layers(tiny_train_cache, small_scenes):
    from scenegen_jax.train.warm_start import warm_start

    no_map = CFG.replace(map_layers=())
    source = init_state(no_map, seed=1)
    params = warm_start(init_state(CFG).params, source.params, "src")
    flat = dict(jax.tree_util.tree_flatten_with_path(params)[0])
    for path, x in jax.tree_util.tree_flatten_with_path(source.params)[0]:
        np.testing.assert_array_equal(flat.pop(path), x)
    (path, x), = flat.items()  # the only parameter the source lacks: zero
    assert "lstm1_map" in jax.tree_util.keystr(path) and not np.any(np.asarray(x))
    # So the extended model starts as the source model: the same loss on real scenes.
    batch = jax.device_put(batch_of(tiny_train_cache, small_scenes))
    state = init_state(CFG)._replace(params=params, opt_state=make_optimizer(CFG).init(params))
    _, extended = jitted_train_step(state, batch, CFG)
    _, original = jitted_train_step(source, batch, no_map)
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
    from scenegen_jax.train.warm_start import start_params

    params = init_state(CFG, seed=3).params
    save_pretrained(str(tmp_path / "model"), CFG, params, 7, "test")
    cfg, loaded = start_params(str(tmp_path / "model"))
    assert cfg.grid.map_channels == CFG.grid.map_channels and cfg.model.hidden == CFG.model.hidden
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
    from scenegen_jax.train.warm_start import warm_start

    coord = CFG.replace(coord_channels=True)
    net = SceneGenNet(coord.model)
    flat_map = jnp.ones((1, CFG.grid.grid_size, CFG.grid.grid_size, len(CFG.grid.map_channels)))
    params = init_state(coord, seed=2).params
    gates = net.apply({"params": params}, flat_map, method=SceneGenNet.map_gates)
    mid = CFG.grid.grid_size // 2
    assert float(jnp.abs(gates[0, 3, mid] - gates[0, -4, mid]).max()) > 1e-3  # top vs bottom
    assert float(jnp.abs(gates[0, mid, 3] - gates[0, mid, -4]).max()) > 1e-3  # left vs right

    source = init_state(CFG, seed=1).params
    extended = warm_start(params, source, "src")
    assert not np.any(np.asarray(extended["lstm1_coord"]))
    want = SceneGenNet(CFG.model).apply({"params": source}, flat_map, method=SceneGenNet.map_gates)
    got = net.apply({"params": extended}, flat_map, method=SceneGenNet.map_gates)
    np.testing.assert_array_equal(got, want)


def test_order_channel_and_attribute_map_input_start_at_zero_from_a_warm_start():
    """`order_channel`'s gates are the convolution of a mask that is 1 from the previous
    actor's bin on (hand-built here, checked against `lax.conv`), every bin at a scene's first
    step. Extended from a model without them, the order channel's and the attribute MLPs' map
    weights (`attribute_map_input`, first and last layer with `attribute_map_skip`) start
    at zero and change nothing."""
    from scenegen_jax.train.warm_start import warm_start

    order = CFG.replace(order_channel=True, attribute_map_input=True, attribute_map_skip=True)
    net = SceneGenNet(order.model)
    params = init_state(order, seed=2).params
    n = CFG.grid.grid_size
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
    feat = jax.random.normal(jax.random.key(3), (5, CFG.model.hidden))
    map_feat = jax.random.uniform(jax.random.key(4), (5, len(CFG.grid.map_channels)))
    cls = jnp.array([0, 1, 2, 0, 1])
    with_map = net.apply({"params": params}, feat, cls, map_feat, method=SceneGenNet.attributes)
    got = net.apply({"params": extended}, feat, cls, map_feat, method=SceneGenNet.attributes)
    want = SceneGenNet(CFG.model).apply({"params": source}, feat, cls,
                                        method=SceneGenNet.attributes)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6)
    # With its own (non-zero) map weights every attribute depends on the map at the bin.
    no_map = net.apply({"params": params}, feat, cls, 0 * map_feat, method=SceneGenNet.attributes)
    for m, z in zip(with_map, no_map, strict=True):
        assert float(jnp.abs(m - z).max()) > 1e-4


def test_separate_attribute_mlps_keep_each_attribute_to_its_own_weights_and_warm_start_exactly():
    """With `separate_attribute_mlps` (the paper's MLP_box, MLP_theta, MLP_v) the heading
    parameters depend on the heading MLP only: no gradient reaches the box or velocity MLPs'
    weights from them, while with the shared MLP it does. Split from a shared model, the three
    MLPs give exactly the shared model's outputs."""
    from scenegen_jax.train.warm_start import warm_start

    sep, shared_cfg = (CFG.replace(separate_attribute_mlps=s) for s in (True, False))
    net, shared_net = SceneGenNet(sep.model), SceneGenNet(shared_cfg.model)
    feat = jax.random.normal(jax.random.key(0), (5, CFG.model.hidden))
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


def test_orientation_bins_tell_lane_directions_apart_and_start_at_zero_from_a_warm_start():
    """With `orientation_bins` layer 1's gates on a lane depend on which way the lane points
    (the same lane mask with opposite directions gives different gates); extended from a
    model without them, the sectors' weights start at zero and change nothing."""
    from scenegen_jax.train.warm_start import warm_start

    binned = CFG.replace(orientation_bins=4)
    net = SceneGenNet(binned.model)
    ic, is_ = (
        CFG.grid.map_channels.index(c) for c in ("lane_orientation_cos", "lane_orientation_sin")
    )
    east = np.zeros(
        (1, CFG.grid.grid_size, CFG.grid.grid_size, len(CFG.grid.map_channels)), np.float32
    )
    east[0, 10:14, :, CFG.grid.map_channels.index("lane_vehicle")] = 1.0
    west = east.copy()
    east[0, 10:14, :, ic], west[0, 10:14, :, ic] = 1.0, -1.0
    assert is_ != ic
    params = init_state(binned, seed=2).params

    def gate_gap(p):  # how far apart the east and west lanes' gates are on the lane
        east_g, west_g = (
            net.apply({"params": p}, jnp.asarray(m), method=SceneGenNet.map_gates)
            for m in (east, west)
        )
        return float(jnp.abs(east_g - west_g)[0, 12].max())

    # The raw cos channel differs too (+1 against -1): without the map convolution's weights
    # only the sectors can tell the two apart, and without the sectors' weights nothing can.
    no_map = {**params, "lstm1_map": jnp.zeros_like(params["lstm1_map"])}
    assert gate_gap(no_map) > 1e-3
    assert gate_gap({**no_map, "lstm1_orient": jnp.zeros_like(params["lstm1_orient"])}) == 0.0

    source = init_state(CFG, seed=1).params
    extended = warm_start(params, source, "src")
    assert not np.any(np.asarray(extended["lstm1_orient"]))
    want = SceneGenNet(CFG.model).apply(
        {"params": source}, jnp.asarray(east), method=SceneGenNet.map_gates
    )
    got = net.apply({"params": extended}, jnp.asarray(east), method=SceneGenNet.map_gates)
    np.testing.assert_array_equal(got, want)


def test_a_new_map_layer_group_starts_at_zero_from_a_warm_start():
    """Extended with the `nearest_lane` layers, a model keeps each old map channel's weights
    (layer 1's convolution, the attribute MLPs' map weights) and gives the new channels zero:
    on any map, its gates and attributes are the source's on the old channels. A source
    trained with a channel the config lacks is refused by name."""
    from scenegen_jax.train.warm_start import warm_start

    old = CFG.replace(
        map_layers=("lanes", "drivable"), attribute_map_input=True, attribute_map_skip=True
    )
    wide = old.replace(map_layers=("lanes", "drivable", "nearest_lane"))
    assert wide.grid.map_channels[-2:] == ("nearest_lane_cos", "nearest_lane_sin")
    source = init_state(old, seed=1).params
    params = warm_start(
        init_state(wide, seed=2).params,
        source,
        "src",
        wide.grid.map_channels,
        old.grid.map_channels,
    )
    keep = [wide.grid.map_channels.index(c) for c in old.grid.map_channels]
    np.testing.assert_array_equal(np.asarray(params["lstm1_map"])[:, :, keep], source["lstm1_map"])
    assert not np.any(np.asarray(params["lstm1_map"])[:, :, -2:])
    raster = jax.random.normal(
        jax.random.key(0), (1, CFG.grid.grid_size, CFG.grid.grid_size, len(wide.grid.map_channels))
    )
    got = SceneGenNet(wide.model).apply({"params": params}, raster, method=SceneGenNet.map_gates)
    want = SceneGenNet(old.model).apply(
        {"params": source}, raster[..., keep], method=SceneGenNet.map_gates
    )
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    feat = jax.random.normal(jax.random.key(3), (5, CFG.model.hidden))
    cls = jnp.array([0, 1, 2, 0, 1])
    got = SceneGenNet(wide.model).apply(
        {"params": params}, feat, cls, raster[0, 0, :5], method=SceneGenNet.attributes
    )
    want = SceneGenNet(old.model).apply(
        {"params": source}, feat, cls, raster[0, 0, :5][:, keep], method=SceneGenNet.attributes
    )
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match=r"src: trained with map channels \['crosswalk'\]"):
        warm_start(
            params,
            init_state(CFG, seed=1).params,
            "src",
            wide.grid.map_channels,
            CFG.grid.map_channels,
        )


def test_a_warm_start_into_the_lane_frame_starts_the_heading_layer_afresh():
    """From a model whose headings are in the grid's frame, `heading_lane_frame` takes every
    parameter but the heading MLP's last layer (`reframed`), which keeps its fresh values; a
    model with one attribute MLP for all three is refused by name."""

    from scenegen_jax.train.warm_start import HEADING_LAST_LAYER, reframed, warm_start

    old = CFG.replace(
        map_layers=("lanes", "nearest_lane"), attribute_map_input=True, attribute_map_skip=True
    )
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
        reframed(
            new.replace(
                separate_attribute_mlps=False, attribute_map_input=False, attribute_map_skip=False
            ),
            old,
        )
