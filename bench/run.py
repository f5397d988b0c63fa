"""`make bench`: our train step, batched scoring and batched sampling against the PyTorch
reference (`../shared/bench/torch_ref`), on the same shapes, in one run; JSON out.

    .venv/bin/python bench/run.py                      # everything -> bench/results.json
    .venv/bin/python bench/run.py --only ours          # skip the reference
    .venv/bin/python bench/run.py case train --grid 128 --steps 25 --batch 1   # one case

Every case runs in its own subprocess, so its peak memory (ru_maxrss) is its own, and each
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
real validation maps, `--workdir`). The `paper` preset recomputes the backbone and heads in
the train step's backward pass (`Config.remat`: less memory for more compute); train rows
with `"remat": false` are the same step storing them.

Sampling. The reference times one generation step per scene (16 actors already placed);
our rollout generates whole scenes, so we report ms per scene-step = wall time / the scene
steps generated (each scene's actors, plus its stopping step). Scenes vmapped together run as
many iterations as the longest of them (finished scenes idle: that cost is ours); on CPU
`sample_batch` runs the scenes one by one (`parallel` = 1; a B = 32 row with the whole batch
vmapped is measured too). Random weights would stop at once, so the stop logit is lowered by
10 (scenes then end when the ordering mask leaves no bin, or at max_actors).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
TORCH_REF = os.path.normpath(os.path.join(REPO, "..", "shared", "bench", "torch_ref"))
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
            from scenegen_jax.train.loop import load_workdir_config

            cfg = load_workdir_config(args.workdir).replace(rotate_augment=False)
        return cfg.replace(max_actors=args.steps - 1) if args.kind != "sample" else cfg
    return get_config(
        "paper",
        grid_size=args.grid,
        m_per_px=80.0 / args.grid,
        max_actors=args.steps - 1,
        bptt_window=args.steps,
        batch_size=args.batch,
        rotate_augment=False,
        **({} if args.remat is None else {"remat": args.remat == "on"}),
    )


def run_case(args) -> dict:
    import jax
    from synthetic import synthetic_batch

    from scenegen_jax.eval.nll import score_batch
    from scenegen_jax.train.step import compile_train_step, init_state

    cfg = case_config(args)
    c_in = len(cfg.map_channels) + ACTOR_CHANNELS
    out = {"what": args.kind, "ours": True, "config": cfg.name, "grid": cfg.grid_size,
           "hidden": cfg.hidden, "batch": args.batch, "map_ch": len(cfg.map_channels)}
    state = init_state(cfg)
    if args.kind == "train":
        cfg = cfg.replace(batch_size=args.batch)
        batch = jax.device_put(synthetic_batch(cfg, args.batch, args.steps - 1))
        t = time.perf_counter()
        step = compile_train_step(cfg, state, batch)  # as the training loop does
        out["compile_s"] = time.perf_counter() - t
        holder = {"state": state}

        def fn():
            holder["state"], stats = step(holder["state"], batch)
            return stats["loss"]

        out.update(timed(fn, args.runs), steps=args.steps, remat=cfg.remat)
        flops = paper_flops(cfg.grid_size, args.steps, c_in, cfg.hidden)[1]
        out["GFLOP"] = flops * args.batch / 1e9
    elif args.kind == "score":
        batch = jax.device_put(synthetic_batch(cfg, args.batch, args.steps - 1, seed=1))
        score = jax.jit(lambda p, b: score_batch(p, b, cfg)["class"])
        out.update(timed(lambda: score(state.params, batch), args.runs), steps=args.steps)
        out["scenes_per_s"] = args.batch / out["median_s"]
        flops = paper_flops(cfg.grid_size, args.steps, c_in, cfg.hidden)[0]
        out["GFLOP"] = flops * args.batch / 1e9
    else:
        out.update(sample_case(cfg, state.params, args))
        out["GFLOP"] = step_flops(cfg.grid_size, c_in, cfg.hidden) * args.batch / 1e9
        out["median_s_per_step"] = out["per_scene_step_ms"] * args.batch / 1e3
        out["GFLOPs_per_s"] = out["GFLOP"] / out["median_s_per_step"]
    if args.kind != "sample":
        out["GFLOPs_per_s"] = out["GFLOP"] / out["median_s"]
    out["peak_rss_GiB"] = round(peak_rss_gib(), 2)
    return out


def sample_case(cfg, params, args) -> dict:
    """Sampling throughput: whole scenes, B at once, M = cfg.proposals."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from synthetic import synthetic_batch

    from scenegen_jax.sampling.rollout import FULL, sample_scenes
    from scenegen_jax.scene import STOP
    from scenegen_jax.train.step import crop_batch

    b = args.batch
    if args.workdir:  # the trained model on real validation maps: realistic scene lengths
        from scenegen_jax.data.cache import load_cache
        from scenegen_jax.train.data import gather_batch
        from scenegen_jax.train.loop import load_trained

        cfg, state = load_trained(args.workdir)
        cfg = cfg.replace(rotate_augment=False)
        params = jax.device_put(jax.device_get(state.params))
        cache = load_cache(args.data)
        idx = np.arange(b) * max(len(cache) // b, 1) % len(cache)
        host = gather_batch(cache, idx, cfg)
    else:
        params = jax.tree.map(lambda x: x, params)
        bias = params["class_mlp2"]["bias"]
        params["class_mlp2"]["bias"] = bias.at[STOP].add(-10.0)
        host = synthetic_batch(cfg, b, 0, seed=2)
    maps, scenes = crop_batch(host, jnp.zeros(b), cfg)
    counter = iter(range(10**6))
    last = {}

    def fn():
        s = sample_scenes(jax.random.key(next(counter)), params, cfg, maps, scenes.ego,
                          parallel=args.parallel)
        last["s"] = s
        return s.actors.valid

    r = timed(fn, args.runs)
    s = jax.device_get(last["s"])
    count = s.actors.valid.sum(-1).reshape(-1)
    iterations = count + (s.stop_reason.reshape(-1) != FULL)
    r.update(
        proposals=cfg.proposals,
        max_actors=cfg.max_actors,
        actors_per_scene=float(count.mean()),
        loop_iterations=int(iterations.max()),
        scene_steps=int(iterations.sum()),
        parallel=args.parallel,
        scenes_per_s=b / r["median_s"],
        per_scene_step_ms=1e3 * r["median_s"] / int(iterations.sum()),
        trained_model=bool(args.workdir),
    )
    return r


# ----------------------------------------------------------------------------- orchestration
def _run(cmd: list[str], timeout: float = 1800) -> list[dict]:
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=REPO)
    rows = [json.loads(line[7:]) for line in p.stdout.splitlines() if line.startswith("RESULT ")]
    if p.returncode != 0 or not rows:
        tail = (p.stderr or p.stdout)[-2000:]
        return [{"what": "error", "cmd": cmd, "returncode": p.returncode, "stderr_tail": tail}]
    for r in rows:
        r["cmd"] = " ".join(os.path.relpath(c, REPO) if c.startswith(REPO) else c for c in cmd)
    return rows


def ours(kind: str, **kw) -> list[dict]:
    cmd = [sys.executable, os.path.join(HERE, "run.py"), "case", kind]
    for k, v in kw.items():
        cmd += [f"--{k.replace('_', '-')}", str(v)]
    return _run(cmd)


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


def peer(py: str, sub: str, *extra: str) -> list[dict]:
    rows = _run([py, os.path.join(TORCH_REF, "bench.py"), sub, *extra])
    for r in rows:
        r["ours"] = False
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


def summarize(rows: list[dict]) -> dict:
    """Ratios ours / reference (throughput; > 1 means we are faster) on matching shapes."""

    def find(ours_, what, grid, batch, fast=False, remat=False, **kw):
        for r in rows:
            if (r.get("ours") == ours_ and r.get("what") == what and r.get("grid") == grid
                    and r.get("batch") == batch and r.get("median_s")
                    and (ours_ or bool(r.get("bf16")) == fast)
                    and bool(r.get("remat")) == remat
                    and all(r.get(k) == v for k, v in kw.items())):
                return r
        return None

    out = {}
    for grid in (64, 128, 320):
        for what, ref_what in (("train", "train_step"), ("score", "score_fwd")):
            # The paper preset recomputes in the backward (remat); train rows without it too.
            for fast, remat in ((False, True), (True, True), (False, False)):
                o = find(True, what, grid, 1, config="paper", remat=remat and what == "train")
                p = find(False, ref_what, grid, 1, fast)
                if o and p and o.get("steps") == p.get("steps") and (remat or what == "train"):
                    key = f"{what}_grid{grid}_T{o['steps']}_B1_vs_{'bf16_cl' if fast else 'fp32'}"
                    key = key.replace(f"{what}_", f"{what}_noremat_", 1) if not remat else key
                    out[key] = {
                        "ours_s": o["median_s"], "ref_s": p["median_s"],
                        "speedup": p["median_s"] / o["median_s"],
                        "ours_peak_GiB": o["peak_rss_GiB"], "ref_peak_GiB": p["peak_rss_GiB"],
                    }
        for fast in (False, True):
            p = find(False, "sample_step", grid, 8, fast)
            for b in (1, 32):
                o = find(True, "sample", grid, b, config="paper", parallel=None)
                if o and p:
                    out[f"sample_grid{grid}_ours_B{b}_vs_ref_B8_{'bf16' if fast else 'fp32'}"] = {
                        "ours_ms_per_scene_step": o["per_scene_step_ms"],
                        "ref_ms_per_scene_step": p["per_scene_ms"],
                        "speedup": p["per_scene_ms"] / o["per_scene_step_ms"]}
    return out


def main_all(args) -> None:
    rows: list[dict] = [{
        "what": "env", "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(), "python": platform.python_version(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }]
    r = args.runs
    big = max(2, r // 2)
    if args.only in (None, "ours"):
        import jax

        rows[0]["jax"] = jax.__version__
        for grid in (64, 128):
            rows += ours("train", grid=grid, steps=25, batch=1, runs=r)
            rows += ours("score", grid=grid, steps=25, batch=1, runs=r)
        rows += ours("train", grid=128, steps=25, batch=1, runs=r, remat="off")
        rows += ours("score", grid=128, steps=25, batch=8, runs=big)
        for b in (1, 32):
            rows += ours("sample", grid=128, batch=b, runs=r if b == 1 else big)
        # The whole batch vmapped (the accelerator default), for comparison.
        rows += ours("sample", grid=128, batch=32, runs=big, parallel=32)
        rows += ours("train", grid=320, steps=5, batch=1, runs=big)
        rows += ours("train", grid=320, steps=5, batch=1, runs=big, remat="off")
        rows += ours("score", grid=320, steps=25, batch=1, runs=big)
        cpu = {"config": "cpu"}
        rows += ours("train", steps=25, batch=4, runs=r, **cpu)
        rows += ours("score", steps=25, batch=8, runs=r, **cpu)
        if args.workdir and not os.path.isdir(os.path.join(args.workdir, "checkpoints")):
            rows.append({"what": "skipped", "reason": f"{args.workdir}: no trained model; train "
                         "the cpu model (experiments/results/README.md) to time its sampling"})
        elif args.workdir:
            for b in (1, 32):
                rows += ours("sample", batch=b, runs=big, workdir=args.workdir, data=args.data,
                             **cpu)
        rows.append({**ceiling_ours(r), "ours": True})
    if args.only in (None, "torch"):
        py = torch_env()
        if py is None:
            rows.append({"what": "error", "reason": f"{TORCH_REF} not found"})
        else:
            m = ["--map-ch", str(MAP_CHANNELS)]
            for fast in ([], ["--channels-last", "--bf16"]):
                for grid in (64, 128):
                    rows += peer(py, "train", "--grid", str(grid), "--steps", "25", *m, *fast)
                    rows += peer(py, "score", "--grid", str(grid), "--steps", "25", *m, *fast)
                for b in ("1", "8"):
                    rows += peer(py, "sample", "--grid", "128", "--batch", b, *m, *fast)
                rows += peer(py, "train", "--grid", "320", "--steps", "5", "--runs", "3", *m,
                             *fast)
                rows += peer(py, "score", "--grid", "320", "--steps", "25", "--runs", "3", *m,
                             *fast)
            rows += peer(py, "ceiling")
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
    p.add_argument("--out", default=os.path.join(HERE, "results.json"))
    p.add_argument("--only", choices=("ours", "torch"))
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--workdir", help="trained cpu model: sample on real maps (cpu config)")
    p.add_argument("--data", default="runs/cache_cpu_val", help="cache for --workdir sampling")
    sub = p.add_subparsers(dest="cmd")
    c = sub.add_parser("case", help="one measurement of ours, in this process")
    c.add_argument("kind", choices=("train", "score", "sample"))
    c.add_argument("--config", default="paper", choices=("paper", "cpu"))
    c.add_argument("--grid", type=int, default=128)
    c.add_argument("--steps", type=int, default=25, help="T, generation steps (last = stop)")
    c.add_argument("--batch", type=int, default=1)
    c.add_argument("--runs", type=int, default=5)
    c.add_argument("--parallel", type=int, help="sampling: scenes vmapped together "
                   "(default: sample_batch's, 1 on CPU)")
    c.add_argument("--remat", choices=("on", "off"),
                   help="train: recompute the backbone and heads in the backward pass (default: "
                   "the preset's, on for paper)")
    c.add_argument("--workdir")
    c.add_argument("--data")
    args = p.parse_args()
    if args.cmd == "case":
        print("RESULT " + json.dumps(run_case(args)), flush=True)
    else:
        main_all(args)


if __name__ == "__main__":
    main()
