"""Winograd's F(4, r) (`model.winograd`), the forward pass of the 5 x 5 convolutions on CPUs
without AVX-512: its transforms against numpy's correlation, its convolutions against
scipy's, and the network's convolutions and scores through it against the direct ones."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.signal import correlate2d
from small import CFG

from scenegen_jax.model import layers, winograd


@pytest.mark.parametrize("r", [3, 5])
def test_the_transforms_compute_a_correlation_of_four_outputs(r):
    """A^T ((G g) * (B^T d)) is the correlation of d (length r + 3) with g, in float64."""
    at, g, bt = winograd.transforms(winograd.TILE, r)
    rng = np.random.default_rng(r)
    for _ in range(5):
        d, k = rng.normal(size=r + 3), rng.normal(size=r)
        np.testing.assert_allclose(at @ ((g @ k) * (bt @ d)), np.correlate(d, k, "valid"),
                                   rtol=1e-10, atol=1e-10)
    # Fewer products than the direct correlation: (r + 3) against 4 r.
    assert at.shape == (4, r + 3) and bt.shape == (r + 3, r + 3)


def _scipy_conv(x, w):
    """'SAME' convolution (a correlation, as XLA's) of x [B, H, W, Ci] with w [r, r, Ci, Co]."""
    b, h, wd, ci = x.shape
    out = np.zeros((b, h, wd, w.shape[-1]))
    for n in range(b):
        for o in range(w.shape[-1]):
            out[n, :, :, o] = sum(correlate2d(x[n, :, :, i], w[:, :, i, o], mode="same")
                                  for i in range(ci))
    return out


@pytest.mark.parametrize("r, shape", [(5, (2, 13, 10, 3)), (3, (1, 9, 16, 4)),
                                      (5, (1, 4, 4, 2))])
def test_a_sum_of_convolutions_matches_scipy(r, shape):
    """Inputs whose sides are not multiples of the tile, two inputs of different channel
    counts summed: scipy's correlation to float32's precision."""
    rng = np.random.default_rng(0)
    x1 = rng.normal(size=shape).astype(np.float32)
    x2 = rng.normal(size=shape[:3] + (5,)).astype(np.float32)
    w1 = rng.normal(size=(r, r, shape[-1], 6)).astype(np.float32)
    w2 = rng.normal(size=(r, r, 5, 6)).astype(np.float32)
    y = np.asarray(jax.jit(winograd.conv_sum)([x1, x2], [w1, w2]))
    expected = _scipy_conv(x1, w1) + _scipy_conv(x2, w2)
    assert y.shape == expected.shape
    np.testing.assert_allclose(y, expected, rtol=0, atol=2e-5 * np.abs(expected).max())


def test_kernels_of_even_or_mixed_sizes_are_refused():
    x = jnp.zeros((1, 8, 8, 2))
    with pytest.raises(ValueError, match="square kernels of one odd size"):
        winograd.conv_sum([x], [jnp.zeros((4, 4, 2, 3))])
    with pytest.raises(ValueError, match="square kernels of one odd size"):
        winograd.conv_sum([x, x], [jnp.zeros((5, 5, 2, 3)), jnp.zeros((3, 3, 2, 3))])


@pytest.fixture
def winograd_on(monkeypatch):
    """The backend's choice as on a CPU without AVX-512 (whatever this one has)."""
    monkeypatch.setattr(layers, "winograd_convolutions",
                        lambda kernel, tiles: tuple(kernel) == (5, 5))


def test_the_network_convolution_through_winograd_keeps_values_and_direct_gradients(winograd_on):
    """`layers.conv_sum` through Winograd: the direct convolutions' values to float32's
    precision, and their gradients exactly (the backward pass is theirs)."""
    rng = np.random.default_rng(1)
    xs = [jnp.asarray(rng.normal(size=(2, 12, 12, c)), jnp.float32) for c in (3, 4)]
    ws = [jnp.asarray(rng.normal(size=(5, 5, c, 8)), jnp.float32) for c in (3, 4)]
    b = jnp.asarray(rng.normal(size=(8,)), jnp.float32)

    def through(x1, x2, w1, w2):
        return layers.conv_sum([(x1, w1), (x2, w2)], b)

    def direct(x1, x2, w1, w2):
        return layers._direct_conv(x1, w1) + layers._direct_conv(x2, w2) + b

    y, grad = jax.value_and_grad(lambda *a: jnp.sum(jnp.sin(through(*a))), (0, 1, 2, 3))(*xs, *ws)
    y0, grad0 = jax.value_and_grad(lambda *a: jnp.sum(jnp.sin(direct(*a))), (0, 1, 2, 3))(*xs, *ws)
    np.testing.assert_allclose(y, y0, rtol=1e-4)
    yw = through(*xs, *ws)
    yd = direct(*xs, *ws)
    np.testing.assert_allclose(yw, yd, atol=2e-5 * float(jnp.abs(yd).max()))
    # The cotangents differ only by the forward values' rounding (sin' at y).
    for g, g0 in zip(grad, grad0, strict=True):
        np.testing.assert_allclose(g, g0, rtol=1e-3, atol=1e-3 * float(jnp.abs(g0).max()))


def test_scores_through_winograd_match_the_direct_scores(winograd_on, tiny_train_cache):
    """The scorer with the 5 x 5 convolutions through Winograd scores real scenes as the
    direct convolutions do, to float32's rounding over a window of generation steps."""
    from scenegen_jax.eval.nll import score_batch
    from scenegen_jax.likelihood.batch import gather_batch
    from scenegen_jax.model.network import init_params

    params = init_params(CFG.model, jax.random.key(0))
    batch = gather_batch(tiny_train_cache, np.arange(2), CFG.grid)
    # Traced under the fixture's choice: Winograd.
    score = jax.jit(lambda p, b: score_batch(p, b, CFG.model))
    ours = jax.tree.map(np.asarray, score(params, batch))
    with pytest.MonkeyPatch.context() as m:
        m.setattr(layers, "winograd_convolutions", lambda kernel, tiles: False)
        direct = jax.tree.map(
            np.asarray, jax.jit(lambda p, b: score_batch(p, b, CFG.model))(params, batch)
        )
    assert ours.keys() == direct.keys()
    # Two programs: Winograd rounds differently from the direct convolutions.
    assert any(not np.array_equal(ours[k], direct[k]) for k in ours)
    for k in ours:
        np.testing.assert_allclose(ours[k], direct[k], rtol=1e-4, atol=1e-4, err_msg=k)
