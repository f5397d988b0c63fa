"""`scene.wrap_angle` keeps its promise, [0, 2pi), for numpy and jax in float32 and float64."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from scenegen_jax.scene import wrap_angle

TWO_PI = 2 * math.pi  # 6.283185307179586
# (input rad, expected rad, tolerance in float64, tolerance in float32). Expected values by
# hand: x - k * 2pi with k = floor(x / 2pi). The float32 modulus is float32(2pi), 1.75e-7 above
# 2pi, so a float32 result drifts by about k * 1.75e-7 from the float64 one.
CASES = [
    (0.0, 0.0, 0.0, 0.0),
    (math.pi, math.pi, 0.0, 1e-6),
    (-math.pi / 2, 4.71238898038469, 1e-15, 1e-6),  # 2pi - pi/2
    (7.0, 0.7168146928204138, 1e-15, 1e-6),  # 7 - 2pi
    (-1.0, 5.283185307179586, 1e-15, 1e-6),  # 2pi - 1
    (TWO_PI, 0.0, 0.0, 0.0),
    (-TWO_PI, 0.0, 0.0, 0.0),
    (3 * TWO_PI, 0.0, 1e-14, 1e-5),
    (1000.0, 0.9735361584457891, 1e-12, 1e-4),  # 1000 - 159 * 2pi
    (-1000.0, 5.309649148733797, 1e-12, 1e-4),  # 160 * 2pi - 1000
    (1e5, 3.105836236885118, 1e-10, 5e-3),  # 1e5 - 15915 * 2pi
    (1e6, 5.925621140132833, 1e-9, None),  # 1e6 - 159154 * 2pi (float32 too coarse)
]


def _backends():
    """(name, array constructor, wrapper) for every way `wrap_angle` is called."""
    return [
        ("numpy", np.asarray, wrap_angle),
        ("jax", jnp.asarray, wrap_angle),
        ("jax-jit", jnp.asarray, jax.jit(wrap_angle)),
    ]


def _wrap(backend: str, dtype, values):
    for name, make, fn in _backends():
        if name == backend:
            return fn(make(np.asarray(values, dtype)))
    raise AssertionError(backend)


def _in_range(out: np.ndarray, dtype) -> None:
    assert out.dtype == dtype
    assert np.all(out >= 0) and not np.any(np.signbit(out)), out
    # Below 2pi in float64 and below the dtype's own 2pi.
    assert np.all(out.astype(np.float64) < TWO_PI), out
    assert np.all(out < np.asarray(TWO_PI, dtype)), out


@pytest.mark.parametrize("backend", ["numpy", "jax", "jax-jit"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_hand_computed_cases(backend, dtype):
    cases = [c for c in CASES if (c[3] if dtype == np.float32 else c[2]) is not None]
    x = [c[0] for c in cases]
    with jax.enable_x64(dtype == np.float64):
        out = np.asarray(_wrap(backend, dtype, x))
    _in_range(out, dtype)
    for (value, expected, tol64, tol32), got in zip(cases, out, strict=True):
        tol = tol32 if dtype == np.float32 else tol64
        # On the circle: float32(3 * 2pi) is just below 3 * float32(2pi), so it wraps to just
        # below 2pi, the same angle as 0.
        d = abs(float(got) - expected)
        assert min(d, TWO_PI - d) <= tol, (value, float(got), expected)


@pytest.mark.parametrize("backend", ["numpy", "jax", "jax-jit"])
def test_tiny_negative_float32_is_zero_not_two_pi(backend):
    # float32(2pi) - 1e-8 rounds to float32(2pi): a plain modulo returns exactly "2pi".
    assert float(jnp.mod(jnp.float32(-1e-8), 2 * jnp.pi)) == float(np.float32(TWO_PI))
    out = np.asarray(_wrap(backend, np.float32, [-1e-8, -1e-7, -3e-7]))
    _in_range(out, np.float32)
    assert out[0] == 0.0 and out[1] == 0.0  # both round to float32(2pi) after the modulo
    # -3e-7 does not: the largest float32 below 2pi, 6.283185005.
    assert out[2] == np.nextafter(np.float32(TWO_PI), np.float32(0))


@pytest.mark.parametrize("backend", ["numpy", "jax", "jax-jit"])
def test_tiny_negative_float64_stays_below_two_pi(backend):
    with jax.enable_x64(True):
        out = np.asarray(_wrap(backend, np.float64, [-1e-8, -1e-17]))
    _in_range(out, np.float64)
    assert out[0] == 6.283185297179586  # 2pi - 1e-8, representable in float64
    assert out[1] == 0.0  # 2pi - 1e-17 rounds to float64(2pi)


@pytest.mark.parametrize("backend", ["numpy", "jax", "jax-jit"])
def test_nan_stays_nan(backend):
    out = np.asarray(_wrap(backend, np.float32, [np.nan, 1.0]))
    assert np.isnan(out[0]) and out[1] == 1.0


def test_array_type_follows_the_input():
    assert isinstance(wrap_angle(jnp.zeros(3)), jax.Array)
    host = wrap_angle(np.zeros(3))
    assert isinstance(host, np.ndarray) and host.dtype == np.float64
    assert wrap_angle(np.zeros(3, np.float32)).dtype == np.float32
    # Integers and Python numbers become floats.
    assert wrap_angle(7).dtype == np.float64 and float(wrap_angle(7)) == 0.7168146928204138
    assert jnp.issubdtype(wrap_angle(jnp.asarray([7, -1])).dtype, jnp.floating)
