"""The teacher-forced unroll computed the fast way equals the plain reference: values,
gradients, remat, window-by-window gradients, truncation (real scenes, small tiny config)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference_unroll import reference_step_terms
from small import CFG, random_params, two_small_scenes

from scenegen_jax.likelihood.batch import batch_scenes, gather_batch
from scenegen_jax.likelihood.grads import unroll_terms_and_grads
from scenegen_jax.likelihood.terms import nll_metrics
from scenegen_jax.likelihood.unroll import num_windows, unroll_terms
from scenegen_jax.train.step import loss_fn


@pytest.fixture(scope="module")
def small_scenes(tiny_train_cache):
    return two_small_scenes(tiny_train_cache)


def _batch(cache, idx):
    return gather_batch(cache, np.asarray(idx), CFG.grid)


def _crop(cache, idx, thetas, cfg):
    """`batch_scenes` of the two small scenes at `thetas`, the first read as complete: both
    hold more actors than CFG's 6 slots (so no stop token: `Scene.complete`); the first read
    as if its region held only those 6 gives the tests a stop token's terms too."""
    maps, scene = batch_scenes(gather_batch(cache, np.asarray(idx), cfg.grid, thetas), cfg.grid)
    return maps, scene.replace(complete=jnp.array([True, False]))


@pytest.fixture(scope="module")
def reference_case(tiny_train_cache, small_scenes):
    """Inputs of the fast-against-reference tests, and the reference's terms (full
    normaliser) and gradient (64 hard negatives), computed once for every variant."""
    # One window (CFG's 7 steps and a padding step): the reference has no truncation either.
    # With the canonical order's input channel (`order_channel`), whose gates are the one
    # input that changes at every step, and the map at each actor's bin as an input of the
    # attribute MLPs.
    cfg = CFG.replace(bptt_window=8, order_channel=True, attribute_map_input=True)
    params = random_params(cfg, jax.random.key(1))
    maps, scene = _crop(tiny_train_cache, small_scenes, [0.0, 1.0], cfg)
    ref = reference_step_terms(params, cfg, maps, scene, None)

    def ref_loss(p):
        return -sum(jnp.sum(v) for v in reference_step_terms(p, cfg, maps, scene, 64).values())

    return cfg, params, maps, scene, ref, jax.grad(ref_loss)(params)


@pytest.mark.parametrize(
    "chunk_bytes,step_loop",
    [(None, False), (1, False), (3 * 2 * 32 * 32 * 8 * 4, False), (None, True)],
)
def test_fast_unroll_equals_plain_reference(reference_case, chunk_bytes, step_loop,
                                            monkeypatch):
    """Backbone chunks of the whole window (default here), 1 step, and 3 steps (uneven), all
    unrolled as on CPU; and the steps as the compiled loop of accelerators, one step an
    iteration (the scorer's tests run the loop of `backend.STEP_LOOP_UNROLL` steps, which
    compiles this test's gradient much more slowly)."""
    import scenegen_jax.backend as backend
    import scenegen_jax.likelihood.unroll as unroll

    if chunk_bytes is not None:
        monkeypatch.setattr(unroll, "HEAD_CHUNK_BYTES", chunk_bytes)
    monkeypatch.setattr(backend, "compiled_step_loop", lambda differentiated=True: step_loop)
    monkeypatch.setattr(backend, "STEP_LOOP_UNROLL", 1)
    cfg, params, maps, scene, ref, g_ref = reference_case
    fast, valid, _ = jax.jit(lambda p: unroll_terms(p, cfg.model, maps, scene, None))(params)
    steps = ref["class"].shape[1]
    for k, v in ref.items():
        np.testing.assert_allclose(np.asarray(fast[k])[:, :steps], v, rtol=2e-4, atol=2e-3)
        assert np.all(np.asarray(fast[k])[:, steps:] == 0)

    def fast_loss(p):
        t, _, _ = unroll_terms(p, cfg.model, maps, scene, 64)
        return -sum(jnp.sum(v) for v in t.values())

    # One program: eagerly, ~300-700 single operations would each compile on their own.
    g_fast = jax.jit(jax.grad(fast_loss))(params)
    # float32 sums over hundreds of terms in another order: tolerances relative to the scale
    # of the gradient (the location bias is softmax-invariant: its exact gradient is 0).
    scale = max(float(np.abs(b).max()) for b in jax.tree.leaves(g_ref))
    for a, b in zip(jax.tree.leaves(g_fast), jax.tree.leaves(g_ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-2, atol=1e-4 * scale)


def test_only_a_differentiated_unroll_is_unrolled_on_cpu(reference_case):
    """On XLA:CPU the scorer's steps (no gradient) run as a compiled loop, a program of a few
    steps, and the train step's unrolled, every step traced (`backend.compiled_step_loop`);
    on accelerators both loop."""
    from scenegen_jax import backend

    cfg, params, maps, scene, _, _ = reference_case
    cfg = cfg.replace(bptt_window=16)  # lowered only: a window of 16 steps, 9 of them padding

    def lines(differentiated):  # of the lowered program: 16 steps against a loop body of 4
        return (
            jax.jit(lambda p: unroll_terms(p, cfg.model, maps, scene, None, differentiated))
            .lower(params)
            .as_text()
            .count("\n")
        )

    assert (lines(False) < 0.8 * lines(True)) == backend.on_cpu()


@pytest.mark.parametrize("step_loop", [False, True])
def test_remat_gives_the_same_loss_and_gradients(
    tiny_train_cache, small_scenes, step_loop, monkeypatch
):
    """Recomputing the backbone and heads in the backward pass (chunks of 3 steps and the
    windows unrolled as on CPU, or as on accelerators one step per iteration of the compiled
    step loop inside the compiled window loop; two windows of 4 with the state carried
    between them) changes neither the loss nor its gradients."""
    import scenegen_jax.backend as backend
    import scenegen_jax.likelihood.unroll as unroll

    monkeypatch.setattr(unroll, "HEAD_CHUNK_BYTES", 3 * 2 * 32 * 32 * 8 * 4)
    monkeypatch.setattr(backend, "compiled_window_loop", lambda: step_loop)
    monkeypatch.setattr(backend, "compiled_step_loop", lambda differentiated=True: step_loop)
    monkeypatch.setattr(backend, "STEP_LOOP_UNROLL", 1)  # the same loop, a smaller body
    maps, scene = _crop(tiny_train_cache, small_scenes, [0.0, 1.0], CFG)
    params = random_params(CFG, jax.random.key(2))

    def loss(p, remat):
        cfg = CFG.replace(bptt_window=4, remat=remat)
        t, _, _ = unroll_terms(p, cfg.model, maps, scene, 64)
        return -sum(jnp.sum(v) for v in t.values())

    plain = jax.jit(jax.value_and_grad(lambda p: loss(p, False)))(params)
    remat = jax.jit(jax.value_and_grad(lambda p: loss(p, True)))(params)
    np.testing.assert_allclose(remat[0], plain[0], rtol=1e-6)
    assert float(jnp.abs(plain[1]["backbone0_w"]).max()) > 0  # the recomputed part has gradient
    for a, b in zip(jax.tree.leaves(remat[1]), jax.tree.leaves(plain[1]), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * float(np.abs(b).max()))


# The window-by-window test's hard negatives: the 64 most likely of 1,024 bins. At the grid's
# median (CFG's 512) the last bins taken have near-equal logits, so float noise of another
# summation order swaps some of them for their neighbours and moves the gradient by up to 8 %
# (seen with the compiled loops at XLA's lowest optimisation level; 3e-4 with these 64).
HARD_NEGATIVES = 64


@pytest.fixture(scope="module")
def autodiff_case(tiny_train_cache, small_scenes):
    """Inputs of the window-by-window test, and the mean scene NLL, its stats and its
    gradient by plain autodiff through the whole unroll, computed once for every variant."""
    cfg = CFG.replace(bptt_window=3, hard_negatives=HARD_NEGATIVES)
    maps, scene = _crop(tiny_train_cache, small_scenes, [0.5, 2.0], cfg)
    params = random_params(cfg, jax.random.key(4))
    value = jax.jit(jax.value_and_grad(loss_fn, has_aux=True), static_argnums=1)(
        params, cfg, maps, scene
    )
    return maps, scene, params, value


@pytest.mark.parametrize("remat,compiled_loop", [(False, False), (True, True)])
def test_window_by_window_gradient_equals_autodiff(
    autodiff_case, remat, compiled_loop, monkeypatch
):
    """The train step's gradient, taken one window at a time (windows of 3, three per scene of
    6 actors and the stop, the last of one step; windows and steps in Python loops as on CPU,
    or in the `lax.scan`s of accelerators), equals jax.grad of the mean scene NLL through the
    whole unroll (Python loops)."""
    import scenegen_jax.backend as backend

    cfg = CFG.replace(bptt_window=3, remat=remat, hard_negatives=HARD_NEGATIVES)
    assert num_windows(cfg.model) == 3
    maps, scene, params, ((loss, stats), grads) = autodiff_case
    monkeypatch.setattr(backend, "compiled_window_loop", lambda: compiled_loop)
    monkeypatch.setattr(backend, "compiled_step_loop", lambda differentiated=True: compiled_loop)
    unrolled, windowed = jax.jit(
        lambda p: unroll_terms_and_grads(
            p, cfg.model, maps, scene, 1.0 / 2, cfg.train.hard_negatives, cfg.train.remat
        )
    )(params)
    scene_nll, stats_w = nll_metrics(*unrolled)
    _, stats_fwd = nll_metrics(
        *jax.jit(lambda p: unroll_terms(p, cfg.model, maps, scene, cfg.train.hard_negatives))(
            params
        )
    )
    np.testing.assert_allclose(jnp.mean(scene_nll), loss, rtol=1e-6)
    for k, v in stats.items():
        np.testing.assert_allclose(stats_w[k], v, rtol=1e-6)
        np.testing.assert_allclose(stats_fwd[k], v, rtol=1e-6)
    assert float(jnp.abs(grads["lstm1_map"]).max()) > 0  # the map share's gradient is there
    # The location head's last bias is softmax-invariant: its exact gradient is 0 and what
    # is left is float32 noise, so its tolerance comes from the gradient's overall scale.
    scale = max(float(np.abs(b).max()) for b in jax.tree.leaves(grads))
    for a, b in zip(jax.tree.leaves(windowed), jax.tree.leaves(grads), strict=True):
        atol = max(1e-5 * float(np.abs(b).max()), 1e-6 * scale)
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=atol)


def test_truncation_cuts_gradients_between_windows(tiny_train_cache, small_scenes):
    cfg = CFG.replace(bptt_window=4)  # two windows of the 7 steps
    params = random_params(cfg, jax.random.key(2))
    maps, scene = _crop(tiny_train_cache, small_scenes, [0.0, 0.0], cfg)

    def window_grad(c):  # gradient of the class terms of the steps where `steps` is 1
        def loss(p, steps):
            t, _, _ = unroll_terms(p, c.model, maps, scene, None)
            return -jnp.sum(t["class"] * steps)

        return jax.jit(jax.grad(loss))  # one program for every mask of the steps

    w = cfg.model.bptt_window
    one_window = cfg.replace(bptt_window=2 * w)  # all 8 steps in one window: nothing cut
    first = jnp.asarray(np.arange(2 * w) < w, jnp.float32)
    second = 1.0 - first
    cut, whole = window_grad(cfg), window_grad(one_window)
    # The first window's loss never reaches past the cut: the same gradient either way.
    for a, b in zip(
        jax.tree.leaves(cut(params, first)), jax.tree.leaves(whole(params, first)), strict=True
    ):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    # The second window's loss reaches the first window's steps only through the state, whose
    # gradient is cut: the recurrent weights lose that path's share of their gradient.
    g2, g2_whole = cut(params, second)["lstm1_rec"], whole(params, second)["lstm1_rec"]
    assert np.all(np.isfinite(np.asarray(g2)))
    assert float(jnp.abs(g2).max()) > 0
    assert not np.allclose(g2, g2_whole, rtol=1e-3, atol=1e-6)
    # Every step of both windows contributes: the second window's terms are non-zero.
    t, valid, _ = jax.jit(lambda p: unroll_terms(p, cfg.model, maps, scene, None))(params)
    assert np.all(np.asarray(t["class"])[np.asarray(valid)] != 0)

    # Without a gradient (the scorer) the steps run as one window: the program of a single
    # window of all 8 steps, and the same terms.
    def scorer(c):
        return jax.jit(lambda p: unroll_terms(p, c.model, maps, scene, None, differentiated=False))

    assert scorer(cfg).lower(params).as_text() == scorer(one_window).lower(params).as_text()
    scored, scored_valid, _ = scorer(cfg)(params)
    np.testing.assert_array_equal(scored_valid, valid)
    for k in t:
        np.testing.assert_allclose(scored[k], t[k], rtol=1e-5, atol=1e-5)


def test_a_truncated_scene_has_no_stop_token(tiny_train_cache, small_scenes):
    """The two small scenes hold 13 and 14 actors in the region, more than CFG's 6 slots:
    cropped, they are not complete, and their likelihood is that of the 6 kept actors with no
    stop token (the 7th actor is not the end of the scene). The same 6 actors read as a
    complete scene score the same terms at their 6 steps, plus the stop token's."""
    from scenegen_jax.scene import STOP

    maps, scene = batch_scenes(_batch(tiny_train_cache, small_scenes), CFG.grid)
    assert not np.any(np.asarray(scene.complete))
    assert np.all(np.asarray(scene.actors.valid))  # every slot is taken
    params = random_params(CFG, jax.random.key(5))
    unroll = jax.jit(lambda s: unroll_terms(params, CFG.model, maps, s, None))
    cut, cut_valid, cut_cls = unroll(scene)
    whole, whole_valid, whole_cls = unroll(scene.replace(complete=jnp.ones(2, bool)))
    n = CFG.grid.max_actors
    np.testing.assert_array_equal(np.asarray(cut_valid).sum(1), [n, n])
    np.testing.assert_array_equal(np.asarray(whole_valid).sum(1), [n + 1, n + 1])
    assert not np.any(np.asarray(cut_cls)[np.asarray(cut_valid)] == STOP)
    np.testing.assert_array_equal(np.asarray(whole_cls)[:, n], [STOP, STOP])
    for k in cut:
        np.testing.assert_array_equal(np.asarray(cut[k])[:, :n], np.asarray(whole[k])[:, :n])
        assert np.all(np.asarray(cut[k])[:, n:] == 0)
    assert np.all(np.asarray(whole["class"])[:, n] != 0)  # the stop token's class term
