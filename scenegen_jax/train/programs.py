"""The train step as several programs compiled side by side: `SplitTrainStep` (chunks of a
window), `QuickStartTrainStep` (starts on the quickly compiled form, swaps the faster ones in
as they are ready) and `train_step_for_run`, which picks one for a run."""

from __future__ import annotations

import concurrent.futures
import functools

import jax
import jax.numpy as jnp
from jax.sharding import Mesh

from scenegen_jax.allocator import release_freed_memory
from scenegen_jax.backend import (
    QUICK_START_STEPS,
    quick_start_training,
    quick_train_compiler_options,
    train_compiler_options,
)
from scenegen_jax.config import Config
from scenegen_jax.likelihood.batch import Batch
from scenegen_jax.likelihood.grads import (
    chunk_backward,
    chunk_forward,
    chunk_steps,
    grads_epilogue,
    grads_prologue,
    map_gates_and_vjp,
)
from scenegen_jax.likelihood.unroll import num_windows
from scenegen_jax.train.step import (
    TrainState,
    apply_grads,
    compile_train_step,
    resolve_remat,
    step_inputs,
)


class SplitTrainStep:
    """`train_step` on one device as four compiled programs called from Python: the step's
    inputs (`grads_prologue`); a chunk of a window's steps forward, its first step traced, so
    every chunk runs one program (`chunk_forward`); that chunk's backward pass, chained from a
    window's last chunk to its first (`chunk_backward`); the map gradient, the loss and the
    optimizer's update (`grads_epilogue`). The same values as the one-program step up to
    float rounding (tested). The chunk programs hold a few steps instead of every window
    unrolled (XLA:CPU), so they compile in a third of the one-program step's time; a step
    runs a little slower (no zero-state shortcut in the first window, no overlap between
    windows), so `QuickStartTrainStep` swaps the one-program step in once it is compiled.
    The programs compile side by side, the prologue and the epilogue (milliseconds a step)
    with `quick_train_compiler_options`, the chunks with `train_compiler_options`, or with
    the quick options too where `quick` (the chunks then compile several times faster and
    run about 2x slower: for steps until a faster program takes over). The state argument is
    donated."""

    def __init__(self, cfg: Config, state: TrainState, batch: Batch, quick: bool = False):
        scale = 1.0 / batch.actors.cls.shape[0]
        cfg = resolve_remat(cfg, batch.actors.cls.shape[0])
        self._starts = [
            range(
                w * cfg.model.bptt_window, (w + 1) * cfg.model.bptt_window, chunk_steps(cfg.model)
            )
            for w in range(num_windows(cfg.model))
        ]

        def prologue(state, batch):
            maps, scene, _, _ = step_inputs(state, batch, cfg, None)
            map_gates, _ = map_gates_and_vjp(state.params, cfg.model, maps)
            scenes, (carry, g_params, g_map) = grads_prologue(
                state.params, cfg.model, maps, scene, map_gates
            )
            no_grad = jax.tree.map(jnp.zeros_like, carry)  # a window's last chunk's cotangent
            return maps, map_gates, scenes, carry, g_params, g_map, no_grad

        def forward(params, map_gates, scenes, carry, start):
            return chunk_forward(
                params,
                map_gates,
                scenes,
                cfg.model,
                scale,
                cfg.train.hard_negatives,
                cfg.train.remat,
                carry,
                start,
            )

        def epilogue(state, maps, scenes, g_params, g_map, terms):
            _, map_vjp = map_gates_and_vjp(state.params, cfg.model, maps)
            terms = jax.tree.map(lambda *x: jnp.stack(x), *terms)
            unrolled, grads = grads_epilogue(map_vjp, scenes, (None, g_params, g_map), terms)
            return apply_grads(state, cfg, unrolled, scenes.actors, grads, 1, None)

        light = functools.partial(jax.jit, compiler_options=quick_train_compiler_options())
        jit = (
            light
            if quick
            else functools.partial(jax.jit, compiler_options=train_compiler_options())
        )
        with concurrent.futures.ThreadPoolExecutor(4) as pool:
            compiled = []

            def compile_next(lowered):  # compiles while the next is traced (no GIL held)
                compiled.append(pool.submit(lowered.compile))
                return lowered.out_info

            maps, map_gates, scenes, carry, g_params, g_map, _ = compile_next(
                light(prologue).lower(state, batch)
            )
            start = jax.ShapeDtypeStruct((), jnp.int32)
            _, chunk_terms, vjp = compile_next(
                jit(forward).lower(state.params, map_gates, scenes, carry, start)
            )
            compile_next(
                jit(chunk_backward, donate_argnums=(2, 3)).lower(vjp, carry, g_params, g_map)
            )
            terms = [chunk_terms] * sum(map(len, self._starts))
            compile_next(
                light(epilogue, donate_argnums=0).lower(state, maps, scenes, g_params, g_map, terms)
            )
            self._prologue, self._forward, self._backward, self._epilogue = (
                c.result() for c in compiled
            )
        release_freed_memory()

    def __call__(self, state: TrainState, batch: Batch) -> tuple[TrainState, dict]:
        maps, map_gates, scenes, carry, g_params, g_map, no_grad = self._prologue(state, batch)
        terms = []
        for starts in self._starts:
            vjps = []
            for start in starts:
                carry, t, vjp = self._forward(state.params, map_gates, scenes, carry, start)
                terms.append(t)
                vjps.append(vjp)
            g_carry = no_grad  # truncated BPTT: no gradient from the next window
            for vjp in reversed(vjps):
                g_params, g_map, g_carry = self._backward(vjp, g_carry, g_params, g_map)
        return self._epilogue(state, maps, scenes, g_params, g_map, terms)


class QuickStartTrainStep:
    """A train step that starts on `SplitTrainStep` and, for runs of more than
    `backend.QUICK_START_STEPS` steps, starts on its quick form (chunks compiled with the
    quick options, a fraction of the one-program step's compile on XLA:CPU and about 2x
    slower steps), then compiles on a background thread, once the first step is done (a
    compile beside it would slow it), the split step with the train step's options and after
    it the one-program step (`compile_train_step`); each step runs the fastest of them that
    is ready. Shorter runs keep the split step with the train step's options throughout.
    `close` waits for a background compile still running."""

    def __init__(self, cfg: Config, state: TrainState, batch: Batch, mesh: Mesh | None, steps: int):
        # Shapes only: the split step donates the arrays before the background lowering.
        shapes = jax.tree.map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), (state, batch)
        )
        quick = steps > QUICK_START_STEPS
        self._split = SplitTrainStep(cfg, state, batch, quick)
        # Compiled one after the other, each faster than the last.
        self._pending = (
            [
                functools.partial(SplitTrainStep, cfg, *shapes, False),
                functools.partial(compile_train_step, cfg, *shapes, mesh),
            ]
            if quick
            else []
        )
        self._pool, self._compiled = None, []

    def __call__(self, state: TrainState, batch: Batch) -> tuple[TrainState, dict]:
        for step in reversed(self._compiled):
            if step.done():
                return step.result()(state, batch)
        out = self._split(state, batch)
        if self._pending:
            jax.block_until_ready(out)
            self._pool = concurrent.futures.ThreadPoolExecutor(1)
            self._compiled = [self._pool.submit(compile) for compile in self._pending]
            self._pending = []
        return out

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)


def train_step_for_run(cfg: Config, state: TrainState, batch: Batch, mesh: Mesh | None, steps: int):
    """The train step a run of `steps` more steps starts with: `QuickStartTrainStep` where
    `backend.quick_start_training` (XLA:CPU, one device), else `compile_train_step`. Call
    its `close` (if it has one) when the run ends."""
    if quick_start_training() and (mesh is None or mesh.size == 1):
        return QuickStartTrainStep(cfg, state, batch, mesh, steps)
    return compile_train_step(cfg, state, batch, mesh)
