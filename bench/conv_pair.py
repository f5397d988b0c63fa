"""The train step's convolutions one by one, ours against the reference's PyTorch: forward,
input gradient and weight gradient of each shape the `paper` model runs per generation step,
B 1, on the two cores. Run alone on an idle machine, one side after the other:

    .venv/bin/python bench/conv_pair.py ours --grid 320
    bench/.venv-torch/bin/python bench/conv_pair.py torch --grid 320

Ours: `model.layers.conv` (the weight gradient in the backend's row bands) compiled with the
train step's options (`backend.train_compiler_options`); the reference: `conv2d` and
`torch.nn.grad.conv2d_input` / `conv2d_weight` in float32 (oneDNN). Prints one line per shape:
median milliseconds of forward / input gradient / weight gradient, GFLOP/s in brackets.
"""

from __future__ import annotations

import argparse
import statistics
import time

# (kernel, in channels, out channels, per generation step): the ConvLSTM's second layer on
# [h1, h2], its first layer's recurrent half on h1 (the map's and actors' halves run once a
# window or locally), the backbone and location heads' 3 x 3 convolutions.
SHAPES = ((5, 64, 128, 1), (5, 32, 128, 1), (3, 32, 32, 7))


def median_ms(fn, runs: int) -> float:
    fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def ours(grid: int, k: int, ci: int, co: int, runs: int) -> list[float]:
    import jax

    from scenegen_jax.backend import train_compiler_options
    from scenegen_jax.model.layers import conv

    opts = train_compiler_options()
    keys = jax.random.split(jax.random.key(0), 3)
    x = jax.random.normal(keys[0], (1, grid, grid, ci))
    w = 0.05 * jax.random.normal(keys[1], (k, k, ci, co))
    g = jax.random.normal(keys[2], (1, grid, grid, co))
    fwd = jax.jit(conv).lower(x, w).compile(opts)
    dx = jax.jit(lambda x, w, g: jax.vjp(lambda x: conv(x, w), x)[1](g)[0])
    dw = jax.jit(lambda x, w, g: jax.vjp(lambda w: conv(x, w), w)[1](g)[0])
    dx, dw = (f.lower(x, w, g).compile(opts) for f in (dx, dw))
    return [median_ms(lambda f=f, a=a: jax.block_until_ready(f(*a)), runs)
            for f, a in ((fwd, (x, w)), (dx, (x, w, g)), (dw, (x, w, g)))]


def reference(grid: int, k: int, ci: int, co: int, runs: int) -> list[float]:
    import torch

    torch.set_num_threads(2)
    x, g = torch.randn(1, ci, grid, grid), torch.randn(1, co, grid, grid)
    w = 0.05 * torch.randn(co, ci, k, k)
    p = k // 2
    calls = (lambda: torch.nn.functional.conv2d(x, w, padding=p),
             lambda: torch.nn.grad.conv2d_input(x.shape, w, g, padding=p),
             lambda: torch.nn.grad.conv2d_weight(x, w.shape, g, padding=p))
    with torch.no_grad():
        return [median_ms(c, runs) for c in calls]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("side", choices=("ours", "torch"))
    ap.add_argument("--grid", type=int, default=320)
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args()
    measure = ours if args.side == "ours" else reference
    total = 0.0
    for k, ci, co, per_step in SHAPES:
        ms = measure(args.grid, k, ci, co, args.runs)
        gflop = 2 * args.grid**2 * k * k * ci * co / 1e9
        total += per_step * sum(ms)
        cols = " / ".join(f"{t:.1f} ({gflop / t * 1e3:.0f})" for t in ms)
        print(f"{args.side} {k}x{k} {ci}->{co} at {args.grid}: fwd / dx / dw ms {cols}", flush=True)
    print(f"{args.side}: per generation step, these convolutions once each (3 x 3 x7) "
          f"{total:.0f} ms")


if __name__ == "__main__":
    main()
