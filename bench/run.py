"""`make bench`: our train step, batched scoring and batched sampling against the PyTorch
reference (`../shared/bench/torch_ref`), on the same shapes, in one run; JSON out.

    .venv/bin/python bench/run.py                      # everything -> bench/results.json
    .venv/bin/python bench/run.py --only ours          # skip the reference
    .venv/bin/python bench/run.py case train --grid 128 --steps 25 --batch 1   # one case
    .venv/bin/python bench/run.py first              # only the time-to-first-result rows
    .venv/bin/python bench/run.py --isa AVX2         # both sides capped to AVX2
    python bench/run.py --suite accel     # on a GPU: paper preset vs the reference on the
                                          # same CUDA device -> bench/results_accel.json

Every row records the CPU model, its vector ISA and the cap put on it (`cpu_fields`). The
time-to-first-result rows (`first_result.py`: process start to the first train step, scoring
batch and sampling batch, no compilation cache) come first. Every case runs in its own
subprocess, so its peak memory (ru_maxrss) is its own, and each
prints one `RESULT {json}` line. Timings: a warm-up call first (its time, compilation
included, is reported as `compile_and_first_s`; the train step is compiled ahead of time as
the training loop does, `compile_s`, so there it is the first call alone), then `--runs`
timed calls; each timed call waits for an idle machine and is kept only if other processes
used < 5 % of the two cores meanwhile (like the reference's harness); median, min, max and
all kept times are reported.

Shapes. The reference model is fixed at the paper's width (hidden 32, GroupNorm 8, K = 10,
10,000 hard negatives); we run our `paper` preset at the same grid, T and B, with our 11 map
channels and the reference given `--map-ch 11`, so both do the same convolutions
(`paper_flops`: the reference README's formula). Our `cpu` preset (hidden 16) has no
reference twin; it is measured alone (train, score and sampling with the trained model on
real validation maps, `--workdir`). The `paper` preset's train step recomputes the backbone
and heads in its backward pass where storing them would not fit in memory (`TrainConfig.remat`
"auto": on a 24 GiB host they fit at B 1, and the step stores them); a row's `remat` says
which ran, `remat_forced` a `--remat` given. Summary keys: `train_...` the preset's setting,
`train_remat_...` and `train_noremat_...` remat forced on or off.

Sampling. The reference times one generation step per scene (16 actors already placed);
our rollout generates whole scenes, so we report ms per scene-step = wall time / the scene
steps generated (each scene's actors, plus its stopping step). Scenes vmapped together run as
many iterations as the longest of them (finished scenes idle: that cost is ours); on CPU
`sample_batch` runs the scenes one by one (`parallel` = 1; a B = 32 row with the whole batch
vmapped is measured too) and `sample_scenes` splits the batch into one concurrent call per
core (`workers`; a B = 32 row with one call is measured too). Batched scoring runs the same
way (`score_cache`). Random weights would stop at once, so the stop logit is lowered by 10
(scenes then end when the ordering mask leaves no bin, or at max_actors).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
TORCH_REF = os.path.normpath(os.path.join(REPO, "..", "shared", "bench", "torch_ref"))
WOMD_JSON = os.path.normpath(os.path.join(REPO, "..", "shared", "data", "womd_mini",
                                          "gpudrive_json"))
TORCH_PY = os.path.join(HERE, ".venv-torch", "bin", "python")
TORCH_VERSION = "2.13.0"
MAP_CHANNELS = 11  # lanes 9 + drivable 1 + crosswalks 1
ACTOR_CHANNELS = 9
FOREIGN_LIMIT = 0.05
# Seconds to wait for an idle machine before each timed call (BENCH_QUIET_TIMEOUT=0 for a
# quick functional check on a busy machine: its timings are then not worth reporting).
QUIET_TIMEOUT = float(os.environ.get("BENCH_QUIET_TIMEOUT", "300"))


# ----------------------------------------------------------------------------- FLOPs
def step_flops(grid: int, c_in: int, hidden: int = 32, with_loc: bool = True) -> float:
    """Forward convolution FLOPs of one generation step (reference README formula, 2 per MAC)."""
    px = grid * grid
    f = 2 * px * 25 * (c_in + hidden) * 4 * hidden  # ConvLSTM layer 1
    f += 2 * px * 25 * 2 * hidden * 4 * hidden  # layer 2
    f += 5 * 2 * px * 9 * hidden * hidden  # backbone
    if with_loc:
        f += 2 * 2 * px * 9 * hidden * hidden + 2 * px * hidden  # one location head
    return float(f)


def paper_flops(grid: int, steps: int, c_in: int, hidden: int = 32) -> tuple[float, float]:
    """(forward, train) FLOPs of a teacher-forced pass over `steps` steps (last = stop)."""
    fwd = (steps - 1) * step_flops(grid, c_in, hidden) + step_flops(grid, c_in, hidden, False)
    layer1 = 2 * grid * grid * 25 * (c_in + hidden) * 4 * hidden
    return fwd, 3 * fwd - layer1


# ----------------------------------------------------------------------------- timing
def _machine_ticks() -> int:
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:9]]
    return v[0] + v[1] + v[2] + v[5] + v[6]  # user nice system irq softirq


def _own_ticks() -> int:
    with open("/proc/self/stat") as f:
        s = f.read()
    fields = s[s.rindex(")") + 2 :].split()
    return int(fields[11]) + int(fields[12])


def wait_quiet(limit: float = 0.1, window: float = 0.5) -> float:
    """Waits until other processes use < `limit` of one core; returns the seconds waited."""
    t0 = time.time()
    hz = os.sysconf("SC_CLK_TCK")
    while time.time() - t0 < QUIET_TIMEOUT:
        m0, s0 = _machine_ticks(), _own_ticks()
        time.sleep(window)
        if (_machine_ticks() - m0) - (_own_ticks() - s0) <= limit * window * hz:
            break
    return time.time() - t0


def timed(fn, runs: int) -> dict:
    """Warm-up call, then `runs` clean timed calls (at most 3 * runs attempts)."""
    import jax

    t = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t
    hz, ncpu = os.sysconf("SC_CLK_TCK"), os.cpu_count()
    clean, every = [], []
    while len(clean) < runs and len(every) < 3 * runs:
        wait_quiet()
        m0, s0 = _machine_ticks(), _own_ticks()
        t = time.perf_counter()
        jax.block_until_ready(fn())
        dt = time.perf_counter() - t
        foreign = max(0, (_machine_ticks() - m0) - (_own_ticks() - s0))
        every.append(dt)
        if foreign <= max(2, FOREIGN_LIMIT * dt * hz * ncpu):
            clean.append(dt)
    kept = clean if len(clean) == runs else every  # too few clean runs: report them all
    return {
        "compile_and_first_s": first,
        "median_s": statistics.median(kept),
        "min_s": min(kept),
        "max_s": max(kept),
        "runs": len(kept),
        "contaminated_runs": len(every) - len(clean),
        "all_s": [round(x, 4) for x in kept],
    }


def peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


# ----------------------------------------------------------------------------- our cases
def case_config(args):
    """Our config for a case: the `paper` preset at the reference's shape, or `cpu` as is."""
    from scenegen_jax.config import get_config

    if args.config == "cpu":
        cfg = get_config("cpu", rotate_augment=False)
        if args.workdir:
            from scenegen_jax.workdir import load_workdir_config

            cfg = load_workdir_config(args.workdir).replace(rotate_augment=False)
        return cfg.replace(max_actors=args.steps - 1) if args.kind != "sample" else cfg
    return get_config(
        "paper",
        grid_size=args.grid,
        m_per_px=80.0 / args.grid,
        max_actors=args.steps - 1,
        bptt_window=args.window or args.steps,
        batch_size=args.batch,
        gn_groups=8,  # the reference's GroupNorm: both sides run the same mathematics
        rotate_augment=False,
        **({} if args.remat is None else {"remat": args.remat == "on"}),
    )


def case_calls(args, batch: int) -> int:
    """Concurrent calls a scoring or sampling case runs its batch as (`--workers`, default one
    per core on CPU), at most one per scene: what its row records as `workers`."""
    from scenegen_jax.backend import default_workers

    return min(default_workers() if args.workers is None else args.workers, batch)


def run_case(args) -> dict:
    import jax
    from synthetic import synthetic_batch

    import scenegen_jax.backend as backend
    from scenegen_jax.allocator import active
    from scenegen_jax.backend import concurrent_map, scoring_compiler_options
    from scenegen_jax.eval.nll import score_batch
    from scenegen_jax.train.step import compile_train_step, init_state, resolve_remat

    cfg = case_config(args)
    if args.step_loop:
        compiled = args.step_loop == "compiled"
        backend.compiled_step_loop = lambda differentiated=True: compiled
    c_in = len(cfg.grid.map_channels) + ACTOR_CHANNELS
    out = {"what": args.kind, "ours": True, "config": cfg.name, "grid": cfg.grid.grid_size,
           "hidden": cfg.model.hidden, "batch": args.batch, "map_ch": len(cfg.grid.map_channels),
           "allocator": active()}
    if args.kind in ("train", "score") and backend.compiled_step_loop(args.kind == "train"):
        out.update(step_loop="compiled", step_loop_unroll=backend.STEP_LOOP_UNROLL)
    elif args.kind in ("train", "score"):
        out["step_loop"] = "unrolled"
    state = init_state(cfg)
    if args.kind == "train":
        # The preset's remat "auto" resolved here, as the training loop does, for the row.
        cfg = resolve_remat(cfg.replace(batch_size=args.batch), args.batch)
        batch = jax.device_put(synthetic_batch(cfg, args.batch, args.steps - 1))
        t = time.perf_counter()
        step = compile_train_step(cfg, state, batch)  # as the training loop does
        out["compile_s"] = time.perf_counter() - t
        holder = {"state": state}

        def fn():
            holder["state"], stats = step(holder["state"], batch)
            return stats["loss"]

        out.update(timed(fn, args.runs), steps=args.steps, window=cfg.model.bptt_window,
                   remat=cfg.train.remat, remat_forced=args.remat)
        flops = paper_flops(cfg.grid.grid_size, args.steps, c_in, cfg.model.hidden)[1]
        out["GFLOP"] = flops * args.batch / 1e9
    elif args.kind == "score":
        # As `score_cache` runs a batch: `workers` concurrent calls on equal parts of it.
        workers = case_calls(args, args.batch)
        if args.batch % workers:
            raise SystemExit(f"--batch {args.batch} is not a multiple of {workers} workers")
        batch = jax.device_put(synthetic_batch(cfg, args.batch, args.steps - 1, seed=1))
        part = args.batch // workers
        parts = [jax.tree.map(lambda x, i=i: x[i * part:(i + 1) * part], batch)
                 for i in range(workers)]
        score = jax.jit(lambda p, b: score_batch(p, b, cfg.model)["class"],
                        compiler_options=scoring_compiler_options())

        def fn():
            return list(concurrent_map(lambda b: score(state.params, b), parts, workers))

        out.update(timed(fn, args.runs), steps=args.steps, window=cfg.model.bptt_window,
                   workers=workers)
        out["scenes_per_s"] = args.batch / out["median_s"]
        flops = paper_flops(cfg.grid.grid_size, args.steps, c_in, cfg.model.hidden)[0]
        out["GFLOP"] = flops * args.batch / 1e9
    elif args.kind == "raster":
        out.update(raster_case(cfg, args))
    else:
        out.update(sample_case(cfg, state.params, args))
        out["GFLOP"] = step_flops(cfg.grid.grid_size, c_in, cfg.model.hidden) * args.batch / 1e9
        out["median_s_per_step"] = out["per_scene_step_ms"] * args.batch / 1e3
        out["GFLOPs_per_s"] = out["GFLOP"] / out["median_s_per_step"]
    if args.kind not in ("sample", "raster"):
        out["GFLOPs_per_s"] = out["GFLOP"] / out["median_s"]
    out["peak_rss_GiB"] = round(peak_rss_gib(), 2)
    out.update(device_fields())
    return out


def raster_case(cfg, args) -> dict:
    """The maps of a training batch drawn from real vector maps (womd_mini val, GPUDrive JSON:
    the densest maps we have) at random rotations: the host's part (`map_primitives`, per
    scene) and the device's (`rasterise_batch`), timed apart; the train step of the same
    batch is the `train` row of the same config, grid and B."""
    import collections
    import itertools

    import numpy as np

    from scenegen_jax.data.sources import read_frames, source_spec
    from scenegen_jax.raster.jax_map import rasterise_batch
    from scenegen_jax.raster.primitives import map_primitives, stack_primitives

    spec = source_spec("womd_json", WOMD_JSON, "val", 10)
    frames = read_frames(spec, collections.Counter())
    maps = [f.map for f in itertools.islice(frames, args.batch)]
    size, m = cfg.grid.grid_size, cfg.grid.m_per_px
    thetas = np.random.default_rng(0).uniform(0, 2 * np.pi, len(maps)).astype(np.float32)

    def host():
        return stack_primitives([map_primitives(v, size, m) for v in maps])

    prims = host()
    host_t = timed(host, args.runs)
    device_t = timed(lambda: rasterise_batch(prims, thetas, size, m, cfg.grid.map_channels),
                     args.runs)
    return {"source": "womd_mini val (GPUDrive JSON)", "steps": args.steps,
            "channels": len(cfg.grid.map_channels),
            "host_median_s": host_t["median_s"], "host": host_t,
            "median_s": host_t["median_s"] + device_t["median_s"],
            "device_median_s": device_t["median_s"], "device": device_t}


def device_fields() -> dict:
    """The backend, and on an accelerator its kind and peak memory (the allocator's high-water
    mark, the figure to set beside `torch.cuda.max_memory_allocated`)."""
    import jax

    d = jax.devices()[0]
    out = {"backend": jax.default_backend()}
    if out["backend"] != "cpu":
        stats = d.memory_stats() or {}
        out["device"] = d.device_kind
        if "peak_bytes_in_use" in stats:
            out["peak_device_GiB"] = round(stats["peak_bytes_in_use"] / 2**30, 3)
    return out


def sample_case(cfg, params, args) -> dict:
    """Sampling throughput: whole scenes, B at once, M = cfg.sample.proposals."""
    import jax
    import numpy as np
    from synthetic import synthetic_batch

    from scenegen_jax.likelihood.batch import batch_scenes
    from scenegen_jax.sampling import SamplerOptions, StopReason, sample_scenes
    from scenegen_jax.scene import STOP

    b = args.batch
    if args.workdir:  # the trained model on real validation maps: realistic scene lengths
        from scenegen_jax.data.cache import load_cache
        from scenegen_jax.likelihood.batch import gather_batch
        from scenegen_jax.train.loop import load_trained

        cfg, state = load_trained(args.workdir)
        cfg = cfg.replace(rotate_augment=False)
        params = jax.device_put(jax.device_get(state.params))
        cache = load_cache(args.data)
        idx = np.arange(b) * max(len(cache) // b, 1) % len(cache)
        host = gather_batch(cache, idx, cfg.grid)
    else:
        params = jax.tree.map(lambda x: x, params)
        bias = params["class_mlp2"]["bias"]
        params["class_mlp2"]["bias"] = bias.at[STOP].add(-10.0)
        host = synthetic_batch(cfg, b, 0, seed=2)
    maps, scenes = batch_scenes(host, cfg.grid)
    counter = iter(range(10**6))
    last = {}

    def fn():
        s = sample_scenes(jax.random.key(next(counter)), params, cfg, maps, scenes.ego,
                          options=SamplerOptions(parallel=args.parallel), workers=args.workers)
        last["s"] = s
        return s.actors.valid

    r = timed(fn, args.runs)
    s = jax.device_get(last["s"])
    count = s.actors.valid.sum(-1).reshape(-1)
    iterations = count + (s.stop_reason.reshape(-1) != StopReason.FULL)
    r.update(
        proposals=cfg.sample.proposals,
        max_actors=cfg.grid.max_actors,
        actors_per_scene=float(count.mean()),
        loop_iterations=int(iterations.max()),
        scene_steps=int(iterations.sum()),
        parallel=args.parallel,
        workers=case_calls(args, b),
        scenes_per_s=b / r["median_s"],
        per_scene_step_ms=1e3 * r["median_s"] / int(iterations.sum()),
        trained_model=bool(args.workdir),
    )
    return r


# ----------------------------------------------------------------------------- orchestration
def _run(cmd: list[str], is_ours: bool, timeout: float = 1800) -> list[dict]:
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=REPO)
    rows = [json.loads(line[7:]) for line in p.stdout.splitlines() if line.startswith("RESULT ")]
    if p.returncode != 0 or not rows:
        tail = (p.stderr or p.stdout)[-2000:]
        return [{"what": "error", "cmd": cmd, "returncode": p.returncode, "stderr_tail": tail}]
    for r in rows:
        r.update(ours=is_ours, **cpu_fields())
        r["cmd"] = " ".join(os.path.relpath(c, REPO) if c.startswith(REPO) else c for c in cmd)
        print(json.dumps({k: v for k, v in r.items() if k not in ("all_s", "cmd")}),
              file=sys.stderr, flush=True)
    return rows


def ours(kind: str, **kw) -> list[dict]:
    cmd = [sys.executable, os.path.join(HERE, "run.py"), "case", kind]
    for k, v in kw.items():
        if v is not None:
            cmd += [f"--{k.replace('_', '-')}", str(v)]
    return _run(cmd, True)


def torch_env() -> str | None:
    """The reference's own environment (created on first use); None if it cannot be made."""
    if not os.path.isdir(TORCH_REF):
        return None
    if not os.path.exists(TORCH_PY):
        subprocess.run([sys.executable, "-m", "venv", os.path.dirname(os.path.dirname(TORCH_PY))],
                       check=True)
        subprocess.run([TORCH_PY, "-m", "pip", "install", "-q", f"torch=={TORCH_VERSION}",
                        "numpy"], check=True)
    return TORCH_PY


def peer(py: str, sub: str, *extra: str, script: str = os.path.join(TORCH_REF, "bench.py")):
    return _run([py, script, sub, *extra], False)


FIRST = os.path.join(HERE, "first_result.py")


def first_results(args) -> list[dict]:
    """Process start to first result, no compilation cache (`first_result.py`): ours for
    `tiny`, `cpu` and `paper` at grid 128 (scoring and sampling load a model directory each
    config's `export` wrote first, untimed), the reference at grid 128; each in a fresh
    process started on an idle machine."""
    rows = []
    py = None if args.only == "ours" else torch_env()
    models = tempfile.mkdtemp(prefix="scenegen-bench-models-")
    try:
        for kind in ("train", "score", "sample"):
            for config in ("tiny", "cpu", "paper") if args.only != "torch" else ():
                model = os.path.join(models, config)
                if kind != "train" and not os.path.isdir(model):
                    subprocess.run([sys.executable, FIRST, "export", "--config", config,
                                    "--model", model], check=True)
                wait_quiet()
                load = ["--model", model] if kind != "train" else []
                rows += _run([sys.executable, FIRST, "ours", kind, "--config", config, *load],
                             True)
            if py:
                wait_quiet()
                rows += _run([py, FIRST, "ref", kind, "--grid", "128"], False)
    finally:
        shutil.rmtree(models, ignore_errors=True)
    return rows


def ceiling_ours(runs: int) -> dict:
    """XLA:CPU convolution ceiling on this machine: 5x5, 65 -> 128 channels at 128 x 128
    (the reference README's probe), float32 and bfloat16, forward and forward + weight grad."""
    import jax
    import jax.numpy as jnp

    out = {"what": "ceiling_xla_conv", "shape": "5x5 65->128 at 128x128, B=1, NHWC"}
    flops = 2 * 128 * 128 * 25 * 65 * 128
    for dtype in ("float32", "bfloat16"):
        x = jnp.ones((1, 128, 128, 65), dtype)
        w = jnp.ones((5, 5, 65, 128), dtype) * 0.01

        def f(x, w):
            return jax.lax.conv_general_dilated(x, w, (1, 1), "SAME",
                                                dimension_numbers=("NHWC", "HWIO", "NHWC"))

        fwd = jax.jit(f)
        wgrad = jax.jit(jax.grad(lambda w, x: jnp.sum(f(x, w).astype(jnp.float32)) ** 2))
        a = timed(functools.partial(fwd, x, w), runs)
        b = timed(functools.partial(wgrad, w, x), runs)
        out[f"{dtype}_fwd_GFLOPs_per_s"] = flops / 1e9 / a["median_s"]
        out[f"{dtype}_fwd_wgrad_GFLOPs_per_s"] = 2 * flops / 1e9 / b["median_s"]
    return out


REF_WHAT = {"train": "train_step", "score": "score_fwd"}  # the reference's names


def summarize(rows: list[dict]) -> dict:
    """Ratios ours / reference (throughput; > 1 means we are faster) on matching shapes: each
    `paper`-preset row of ours against the reference's float32 and fast-mode rows of the same
    grid, T and B (`_Ncalls`: our batch ran as N concurrent calls); sampling per generated
    scene-step against the reference's B = 8 and its row of our own B, if any."""

    def peak(r):
        return r.get("peak_device_GiB", r.get("peak_rss_GiB"))

    refs = [r for r in rows if r.get("ours") is False and r.get("median_s")]
    out = {}
    for r in rows:  # seconds from process start to the first result (`first_results`)
        if r.get("what", "").startswith("first_") and "first_result_s" in r:
            who = f"ours_{r['config']}_grid{r['grid']}" if r["ours"] else f"ref_grid{r['grid']}"
            out.setdefault(f"{r['what']}_s", {})[who] = round(r["first_result_s"], 1)
    for o in rows:
        if not (o.get("ours") and o.get("config") == "paper" and o.get("median_s")):
            continue
        g, b = o["grid"], o["batch"]
        n_calls = o.get("workers", 1)  # concurrent calls on parts of the batch (case_calls)
        calls = f"_{n_calls}calls" if n_calls > 1 else ""
        if o.get("backend", "cpu") != "cpu" and o.get("step_loop") == "unrolled":
            calls += "_unrolled"  # not the accelerator default (`--step-loop unrolled`)
        for p in refs:
            mode = "bf16_cl" if p.get("bf16") else "fp32"
            if p.get("grid") != g:
                continue
            if (p["what"] == REF_WHAT.get(o["what"])
                    and (p["steps"], p["batch"]) == (o["steps"], b)):
                what = o["what"]
                if what == "train" and o.get("remat_forced"):  # else the preset's setting
                    what = {"on": "train_remat", "off": "train_noremat"}[o["remat_forced"]]
                out[f"{what}_grid{g}_T{o['steps']}_B{b}{calls}_vs_{mode}"] = {
                    "ours_s": o["median_s"], "ref_s": p["median_s"],
                    "speedup": p["median_s"] / o["median_s"],
                    "ours_peak_GiB": peak(o), "ref_peak_GiB": peak(p)}
            elif (o["what"] == "sample" and p["what"] == "sample_step" and o.get("parallel") is None
                    and p["batch"] in (8, b)):
                mode = mode.replace("_cl", "")
                out[f"sample_grid{g}_ours_B{b}{calls}_vs_ref_B{p['batch']}_{mode}"] = {
                    "ours_ms_per_scene_step": o["per_scene_step_ms"],
                    "ref_ms_per_scene_step": p["per_scene_ms"],
                    "speedup": p["per_scene_ms"] / o["per_scene_step_ms"]}
    for d in rows:  # the train step with its maps drawn, against the step alone
        if not (d.get("ours") and d.get("what") == "raster" and d.get("median_s")):
            continue
        for t in rows:
            if (t.get("ours") and t.get("what") == "train" and not t.get("remat_forced")
                    and t.get("median_s") and (t["config"], t["grid"], t["batch"], t["steps"])
                    == (d["config"], d["grid"], d["batch"], d["steps"])):
                out[f"train_{d['config']}_grid{d['grid']}_B{d['batch']}_with_maps_drawn"] = {
                    "step_s": t["median_s"], "maps_s": d["median_s"],
                    "ratio": t["median_s"] / (t["median_s"] + d["median_s"])}
    return out


def cpu_ours(args) -> list[dict]:
    r, big, rows = args.runs, max(2, args.runs // 2), []
    for grid in (64, 128):
        rows += ours("train", grid=grid, steps=25, batch=1, runs=r)
        rows += ours("score", grid=grid, steps=25, batch=1, runs=r)
    rows += ours("train", grid=128, steps=25, batch=1, runs=r, remat="on")
    rows += ours("score", grid=128, steps=25, batch=8, runs=big)
    rows += ours("score", grid=128, steps=25, batch=8, runs=big, workers=1)
    for b in (1, 32):
        rows += ours("sample", grid=128, batch=b, runs=r if b == 1 else big)
    # One call at a time, and the whole batch vmapped (the accelerator default), to compare.
    rows += ours("sample", grid=128, batch=32, runs=big, workers=1)
    rows += ours("sample", grid=128, batch=32, runs=big, parallel=32)
    # T 25 is the paper's window. The preset's remat "auto" stores every activation where
    # they fit, as the reference does; the "on" rows recompute them.
    for steps in (5, 25):
        for remat in (None, "on"):
            rows += ours("train", grid=320, steps=steps, batch=1, runs=big, remat=remat)
    rows += ours("score", grid=320, steps=25, batch=1, runs=big)
    for b in (1, 32):
        rows += ours("sample", grid=320, batch=b, runs=big)
    # The maps of the train rows' batches, drawn from vector maps (`raster_case`).
    rows += ours("raster", grid=320, steps=25, batch=1, runs=big)
    cpu = {"config": "cpu"}
    rows += ours("raster", steps=25, batch=4, runs=r, **cpu)
    rows += ours("train", steps=25, batch=4, runs=r, **cpu)
    rows += ours("score", steps=25, batch=8, runs=r, **cpu)
    if args.workdir and not os.path.isdir(os.path.join(args.workdir, "checkpoints")):
        rows.append({"what": "skipped", "reason": f"{args.workdir}: no trained model; give "
                     "--workdir a `scenegen train --config cpu` workdir and --data a cpu-config "
                     "val cache (`scenegen prepare ... --split val --config cpu`) to time its "
                     "sampling on real maps"})
    elif args.workdir:
        for b in (1, 32):
            rows += ours("sample", batch=b, runs=big, workdir=args.workdir, data=args.data,
                         **cpu)
    return rows


def cpu_peer(args) -> list[dict]:
    py = torch_env()
    if py is None:
        return [{"what": "error", "reason": f"{TORCH_REF} not found"}]
    rows = []
    m = ["--map-ch", str(MAP_CHANNELS)]
    for fast in ([], ["--channels-last", "--bf16"]):
        for grid in (64, 128):
            rows += peer(py, "train", "--grid", str(grid), "--steps", "25", *m, *fast)
            rows += peer(py, "score", "--grid", str(grid), "--steps", "25", *m, *fast)
        rows += peer(py, "score", "--grid", "128", "--steps", "25", "--batch", "8", "--runs",
                     "3", *m, *fast)
        for b in ("1", "8"):
            rows += peer(py, "sample", "--grid", "128", "--batch", b, *m, *fast)
        rows += peer(py, "train", "--grid", "320", "--steps", "5", "--runs", "3", *m,
                     *fast)
        if not fast:  # the paper's window, float32 only (its peer), to keep the run short
            rows += peer(py, "train", "--grid", "320", "--steps", "25", "--runs", "3", *m)
        rows += peer(py, "score", "--grid", "320", "--steps", "25", "--runs", "3", *m,
                     *fast)
        rows += peer(py, "sample", "--grid", "320", "--batch", "8", "--runs", "3", *m, *fast)
    return rows + peer(py, "ceiling")


def accel_ours(args) -> list[dict]:
    """The paper preset on an accelerator: its own grid (320, T 25) and 128 at B 1 (the paper
    trains with B 1 per GPU; B 16 on one 80 GB GPU runs out of memory, as the reference's
    does), scoring also at B 16; the whole preset's train step (128 actors: 6 windows of
    25); and the train step and scoring with the window's steps unrolled, to compare."""
    r, big, rows = args.runs, max(2, args.runs // 2), []
    for grid in (320, 128):
        for remat in ("on", "off"):
            rows += ours("train", grid=grid, steps=25, batch=1, runs=r, remat=remat)
        rows += ours("score", grid=grid, steps=25, batch=1, runs=r)
        for b in (1, 32):
            rows += ours("sample", grid=grid, batch=b, runs=big)
    rows += ours("score", grid=320, steps=25, batch=16, runs=big)
    rows += ours("train", grid=320, steps=129, window=25, batch=1, runs=big)
    for kind in ("train", "score"):
        rows += ours(kind, grid=320, steps=25, batch=1, runs=r, step_loop="unrolled")
    return rows


def accel_peer(args) -> list[dict]:
    """The reference on the same CUDA device (bench/torch_ref_cuda.py), float32 and its fast
    mode, on the shapes of `accel_ours`; sampling at B 1, 8 and 32."""
    run = functools.partial(peer, sys.executable, script=os.path.join(HERE, "torch_ref_cuda.py"))
    rows, m = [], ["--ref", args.ref, "--map-ch", str(MAP_CHANNELS)]
    for fast in ([], ["--channels-last", "--bf16"]):
        for grid in ("320", "128"):
            for kind in ("train", "score"):
                rows += run(kind, "--grid", grid, "--steps", "25", *m, *fast)
            for b in ("1", "8", "32"):
                rows += run("sample", "--grid", grid, "--batch", b, *m, *fast)
        rows += run("score", "--grid", "320", "--steps", "25", "--batch", "16", "--runs", "3",
                    *m, *fast)
    return rows


ISA_CAP_OPTION = "--xla_cpu_max_isa="
AVX2_ONLY = "avx2_only"  # bench/avx2_only.c, built into bench/.build/avx2_only.so


def cpu_flags() -> list[str]:
    """The CPU's feature flags as the kernel sees them (/proc/cpuinfo; the CPUID answers that
    `bench/avx2_only.c` changes are the libraries' view, not the kernel's)."""
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].split() for line in f
                         if line.startswith("flags")), [])
    except OSError:
        return []


def cpu_isa() -> str:
    """The widest x86 vector extension of this CPU that the kernels use: AMX, AVX-512 or
    AVX2 (from /proc/cpuinfo's flags)."""
    flags = cpu_flags()
    for flag, name in (("amx_tile", "AMX"), ("avx512f", "AVX-512"), ("avx2", "AVX2")):
        if flag in flags:
            return name
    return platform.machine()


def isa_cap() -> str | None:
    """The vector ISA this run caps both sides to (`cap_isa`), None when uncapped."""
    return "AVX2" if f"{AVX2_ONLY}.so" in os.environ.get("LD_PRELOAD", "") else None


def cpu_fields() -> dict:
    """What every row records about the CPU: its model, its vector ISA and the cap the run
    put on both sides (None when uncapped)."""
    return {"cpu_model": cpu_model(), "isa": cpu_isa(), "isa_cap": isa_cap()}


def build_avx2_only() -> str:
    """Compiles bench/avx2_only.c (`cc`) into bench/.build; returns the library's path."""
    out = os.path.join(HERE, ".build", f"{AVX2_ONLY}.so")
    os.makedirs(os.path.dirname(out), exist_ok=True)
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise SystemExit("--isa AVX2 builds bench/avx2_only.c: install a C compiler (cc)")
    subprocess.run([cc, "-O2", "-shared", "-fPIC", "-o", out,
                    os.path.join(HERE, f"{AVX2_ONLY}.c")], check=True)
    return out


def cap_isa(isa: str) -> None:
    """Makes every case run from here on, ours and the reference's, run on an AVX2-only CPU as
    far as their kernels can tell: CPUID answers without AVX-512, AMX and AVX-VNNI
    (bench/avx2_only.c, preloaded), so YNNPACK, oneDNN, PyTorch's ATen and XLA's code
    generator all pick their AVX2 kernels; XLA's own cap besides (LLVM may also read the CPU's
    model). `--xla_cpu_max_isa` and `ONEDNN_MAX_CPU_ISA` alone leave YNNPACK at the CPU's
    widest ISA (docs/performance.md). Nothing to hide on an AVX2-only CPU."""
    if cpu_isa() == isa:
        return
    if "cpuid_fault" not in cpu_flags():
        raise SystemExit(f"--isa {isa}: this {cpu_isa()} CPU cannot hide its wider extensions "
                         "(no `cpuid_fault` in /proc/cpuinfo); run on an AVX2-only CPU")
    os.environ["LD_PRELOAD"] = build_avx2_only()
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith(ISA_CAP_OPTION)]
    os.environ["XLA_FLAGS"] = " ".join([*flags, ISA_CAP_OPTION + isa])
    check = subprocess.run(
        [sys.executable, "-c", "from numpy._core._multiarray_umath import __cpu_features__ "
         "as f; print(f['AVX2'], f['AVX512F'])"], capture_output=True, text=True)
    if check.stdout.split() != ["True", "False"]:
        raise SystemExit(f"--isa {isa}: bench/avx2_only.c did not hide AVX-512 from CPUID "
                         f"(numpy sees AVX2, AVX512F = {check.stdout.split()}; "
                         f"{check.stderr.strip()[-500:]})")


def cpu_model() -> str:
    """The CPU's model name, family and model (/proc/cpuinfo): timings differ 2x between the
    machines this runs on."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    name = fields.get("model name") or platform.processor() or platform.machine()
    if "cpu family" in fields and "model" in fields:
        name += f" (family {fields['cpu family']}, model {fields['model']})"
    return name


def main_all(args) -> None:
    import jax

    from scenegen_jax.allocator import find_tcmalloc

    allocator = "tcmalloc" if find_tcmalloc(os.environ) else "system"
    if allocator == "system" and args.only != "torch":
        print("bench: ours runs on glibc's malloc (no tcmalloc found, or SCENEGEN_MALLOC="
              "system), up to 1.7x slower at grid 320, T 25 (apt install libtcmalloc-minimal4; "
              "scenegen_jax/allocator.py)", file=sys.stderr)
    rows: list[dict] = [{
        "what": "env", "machine": platform.processor() or platform.machine(),
        **cpu_fields(), "allocator": allocator,
        "cpus": os.cpu_count(), "python": platform.python_version(), "jax": jax.__version__,
        **device_fields(), "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }]
    accel = args.suite == "accel"
    if not accel and not args.no_first:
        rows += first_results(args)
    if args.only in (None, "ours"):
        rows += accel_ours(args) if accel else cpu_ours(args)
        rows.append({**ceiling_ours(args.runs), "ours": True})
    if args.only in (None, "torch"):
        rows += accel_peer(args) if accel else cpu_peer(args)
    if args.only and os.path.exists(args.out):  # keep the other side's rows from last time
        with open(args.out) as f:
            kept = [r for r in json.load(f)["rows"] if r.get("ours") is (args.only == "torch")]
        rows += [r for r in kept if r.get("what") != "env" or "torch" in r]
    report = {"rows": rows, "summary": summarize(rows)}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report["summary"], indent=1))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--out", help="default: bench/results.json, or results_accel.json")
    p.add_argument("--only", choices=("ours", "torch"))
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--workdir", help="trained cpu model: sample on real maps (cpu config)")
    p.add_argument("--data", default="runs/cache_cpu_val", help="cache for --workdir sampling")
    p.add_argument("--suite", choices=("cpu", "accel"), default="cpu",
                   help="accel: the paper preset on the accelerator jax finds, against the "
                   "reference on the same CUDA device (bench/results_accel.json)")
    p.add_argument("--ref", default=TORCH_REF, help="the reference's folder (accel suite)")
    p.add_argument("--isa", choices=("AVX2",),
                   help="run both sides as on an AVX2-only CPU: CPUID without AVX-512 and AMX "
                   "(bench/avx2_only.c; needs cc and the CPU's `cpuid_fault`; default out: "
                   "bench/results_avx2.json)")
    p.add_argument("--no-first", action="store_true",
                   help="skip the time-to-first-result rows (bench/first_result.py)")
    sub = p.add_subparsers(dest="cmd")
    sub.add_parser("first", help="only the time-to-first-result rows (both sides, or --only)")
    c = sub.add_parser("case", help="one measurement of ours, in this process")
    c.add_argument("kind", choices=("train", "score", "sample", "raster"))
    c.add_argument("--config", default="paper", choices=("paper", "cpu"))
    c.add_argument("--grid", type=int, default=128)
    c.add_argument("--steps", type=int, default=25, help="T, generation steps (last = stop)")
    c.add_argument("--window", type=int, help="train and score: BPTT window (default: T, one "
                   "window; the paper preset's is 25)")
    c.add_argument("--step-loop", choices=("compiled", "unrolled"),
                   help="train and score: a window's steps as a compiled loop or unrolled "
                   "(default: the backend's, `backend.compiled_step_loop`)")
    c.add_argument("--batch", type=int, default=1)
    c.add_argument("--runs", type=int, default=5)
    c.add_argument("--parallel", type=int, help="sampling: scenes vmapped together "
                   "(default: sample_batch's, 1 on CPU)")
    c.add_argument("--workers", type=int, help="sampling and scoring: concurrent calls on "
                   "parts of the batch (default: one per core on CPU)")
    c.add_argument("--remat", choices=("on", "off"),
                   help="train: recompute the backbone and heads in the backward pass (default: "
                   "the preset's: for paper, on where the step without it would not fit in memory)")
    c.add_argument("--workdir")
    c.add_argument("--data")
    args = p.parse_args()
    if args.isa and isa_cap() != args.isa:
        cap_isa(args.isa)
        if args.cmd == "case" and isa_cap():  # this process runs it: again, under the cap
            os.execv(sys.executable, [sys.executable, *sys.argv])
    default = {"accel": "results_accel.json"}.get(args.suite) or (
        "results_avx2.json" if args.isa else "results.json")
    args.out = args.out or os.path.join(HERE, default)
    if args.cmd == "first":
        rows = first_results(args)
        print(json.dumps([{k: v for k, v in r.items() if k != "cmd"} for r in rows], indent=1))
    elif args.cmd == "case":
        from scenegen_jax.allocator import reexec_with_tcmalloc

        reexec_with_tcmalloc()  # as the `scenegen` command runs ours: on tcmalloc if installed
        print("RESULT " + json.dumps(run_case(args)), flush=True)
    else:
        main_all(args)


if __name__ == "__main__":
    main()
