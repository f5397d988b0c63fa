"""Micro-benchmarks of the training step's hot operations: single operations at the
paper's width (hidden 32) and grid 128, B 1, on XLA:CPU. Run alone on an idle machine:

    .venv/bin/python bench/micro.py            # prints one line per operation (median ms)

- GroupNorm (8 groups), forward and forward + backward: `model.layers.group_norm` against
  the same statistics reduced over the grouped 5-D view (the plain formulation);
- convolutions 3x3 32 -> 32 and 5x5 32 -> 128: forward, input gradient and weight gradient,
  with XLA's default (YNNPACK) and with `scoring_compiler_options()` (Eigen);
- the 5x5 32 -> 128 weight gradient at grids 128 and 320: XLA's, and summed over row bands
  of the size `conv` uses on this CPU (`backend.weight_gradient_bands`).
"""

from __future__ import annotations

import statistics
import time

import jax
import jax.numpy as jnp

from scenegen_jax.backend import scoring_compiler_options, weight_gradient_bands
from scenegen_jax.model.layers import (
    _banded_conv,
    _conv,
    conv,
    group_norm,
)

GRID, HIDDEN, GROUPS = 128, 32, 8


def group_norm_grouped_view(x, groups, scale, bias, eps=1e-5):
    """GroupNorm with its statistics reduced over the [B, H, W, G, C/G] view (before)."""
    b, h, w, c = x.shape
    g = x.reshape(b, h, w, groups, c // groups)
    mean = jnp.mean(g, axis=(1, 2, 4), keepdims=True)
    var = jnp.mean(jnp.square(g - mean), axis=(1, 2, 4), keepdims=True)
    return ((g - mean) * jax.lax.rsqrt(var + eps)).reshape(b, h, w, c) * scale + bias


def median_ms(fn, *args, options=None, runs: int = 20) -> float:
    compiled = jax.jit(fn, compiler_options=options).lower(*args).compile()
    jax.block_until_ready(compiled(*args))
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def main() -> None:
    keys = jax.random.split(jax.random.key(0), 4)
    x = 0.5 + 2.0 * jax.random.normal(keys[0], (1, GRID, GRID, HIDDEN))
    scale, bias = jnp.ones(HIDDEN), jnp.zeros(HIDDEN)
    cot = jax.random.normal(keys[1], x.shape)
    for name, gn in (("grouped 5-D view", group_norm_grouped_view), ("ours", group_norm)):
        fwd = median_ms(lambda x, gn=gn: gn(x, GROUPS, scale, bias), x)
        both = median_ms(lambda x, gn=gn: jax.vjp(lambda y: gn(y, GROUPS, scale, bias), x)[1](cot),
                         x)
        print(f"GroupNorm, {name}: forward {fwd:.2f} ms, forward + backward {both:.2f} ms")
    for k, c_out in ((3, HIDDEN), (5, 4 * HIDDEN)):
        w = 0.1 * jax.random.normal(keys[2], (k, k, HIDDEN, c_out))
        g = jax.random.normal(keys[3], (1, GRID, GRID, c_out))
        ops = {
            "forward": (lambda x, w: conv(x, w), (x, w)),
            "input gradient": (lambda w, g: jax.vjp(lambda y: conv(y, w), x)[1](g)[0], (w, g)),
            "weight gradient": (lambda x, g, w=w: jax.vjp(lambda v: conv(x, v), w)[1](g)[0],
                                (x, g)),
        }
        for op, (fn, args) in ops.items():
            ynn = median_ms(fn, *args)
            eigen = median_ms(fn, *args, options=scoring_compiler_options())
            print(f"conv {k}x{k} {HIDDEN} -> {c_out}, {op}: YNNPACK {ynn:.2f} ms, "
                  f"Eigen (scoring options) {eigen:.2f} ms")
    w = 0.1 * jax.random.normal(keys[2], (5, 5, HIDDEN, 4 * HIDDEN))
    for grid in (128, 320):
        xg = jax.random.normal(keys[0], (1, grid, grid, HIDDEN))
        g = jax.random.normal(keys[3], (1, grid, grid, 4 * HIDDEN))
        band_rows = (weight_gradient_bands() or (0, grid))[1]
        def banded_conv(x, v, band_rows=band_rows):
            return _banded_conv(x, v, band_rows)

        xla, banded = (median_ms(lambda x, g, f=f: jax.vjp(lambda v: f(x, v), w)[1](g)[0], xg, g,
                                 runs=5) for f in (_conv, banded_conv))
        print(f"conv 5x5 {HIDDEN} -> {4 * HIDDEN} at {grid} x {grid}, weight gradient: XLA "
              f"{xla:.1f} ms, in bands of {band_rows} rows {banded:.1f} ms")


if __name__ == "__main__":
    main()
