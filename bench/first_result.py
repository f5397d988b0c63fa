"""Time to the first result: seconds from this process's start (the kernel's start time of the
process, so the interpreter's start and every import count) to the first finished train step,
scoring batch or sampling batch, with no compilation cache. What a user waits for before a
run shows any progress. One measurement per process; prints one `RESULT {json}` line.

    .venv/bin/python bench/first_result.py ours train --config tiny
    .venv/bin/python bench/first_result.py export --config paper --grid 128 --model /tmp/m
    .venv/bin/python bench/first_result.py ours score --model /tmp/m
    bench/.venv-torch/bin/python bench/first_result.py ref train --grid 128   # the reference

Ours runs what the command line runs for the first batch of a preset as it ships (`tiny`,
`cpu`; `paper` at `--grid`, T 25, B 1, the reference's shape): `train_step_for_run` (the
split step on XLA:CPU; the one-program step starts compiling once the first step is done,
as in a run of 1,000 steps)
and one step on a fresh state of the preset, on a batch of its size; for scoring and sampling, the
model loaded from a model directory as `scenegen score|sample --pretrained DIR` loads it (those
commands never draw initial parameters), then the scorer's compiled call on the `score`
command's default batch (8 scenes, one call per core), or `sample_scenes` on 8 maps (cropped
one at a time as `scenegen sample` crops them). The
directory comes from `export` in an earlier process (not timed): the preset's initial
parameters with the stop logit lowered as in `run.py`'s sampling case, so that sampled scenes
fill rather than stop at once. Synthetic scenes (`synthetic.py`): the shapes, not the data,
set the compile time. The reference (eager PyTorch, `../shared/bench/torch_ref/model.py`)
runs one train step, one scoring forward pass and one sampling step at the same grid, T and B.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
TORCH_REF = os.path.normpath(os.path.join(HERE, "..", "..", "shared", "bench", "torch_ref"))
MAP_CHANNELS = 11  # as run.py: our lanes 9 + drivable 1 + crosswalks 1
BATCH = 8  # the `score` and `sample` commands' default --batch-size


def process_age_s() -> float:
    """Seconds since this process started (Linux: /proc/self/stat field 22 against
    /proc/uptime; 10 ms resolution)."""
    with open("/proc/self/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()  # after "pid (comm)": field 3 onwards
    with open("/proc/uptime") as f:
        uptime = float(f.read().split()[0])
    return uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK")


def bench_config(config: str, grid: int):
    """The preset as it ships; `paper` at `grid` with the reference's T 25 (24 actors and the
    stop) and B 1."""
    from scenegen_jax.config import get_config

    if config == "paper":
        cfg = get_config("paper", grid_size=grid, m_per_px=80.0 / grid, max_actors=24,
                         bptt_window=25, batch_size=1)
    else:
        cfg = get_config(config)
    return cfg.replace(rotate_augment=False)


def export_model(config: str, grid: int, model: str) -> None:
    """Writes the model directory the score and sample rows load (`save_pretrained`): the
    preset's initial parameters, the stop logit lowered by 10."""
    from scenegen_jax.pretrained import save_pretrained
    from scenegen_jax.scene import STOP
    from scenegen_jax.train.step import init_state

    cfg = bench_config(config, grid)
    params = init_state(cfg).params
    params["class_mlp2"]["bias"] = params["class_mlp2"]["bias"].at[STOP].add(-10.0)
    save_pretrained(model, cfg, params, 0, "bench/first_result.py export")


def ours(kind: str, config: str, grid: int, model: str | None) -> dict:
    os.environ["JAX_ENABLE_COMPILATION_CACHE"] = "false"
    import jax

    jax.config.update("jax_enable_compilation_cache", False)
    from synthetic import synthetic_batch

    from scenegen_jax.allocator import active
    from scenegen_jax.backend import concurrent_map, default_workers, scoring_compiler_options
    from scenegen_jax.eval.nll import score_batch
    from scenegen_jax.pretrained import load_pretrained
    from scenegen_jax.train.programs import train_step_for_run
    from scenegen_jax.train.step import init_state

    t_import = process_age_s()
    if kind == "train":
        cfg = bench_config(config, grid)
    elif model is None:
        raise SystemExit(f"{kind} loads a model: --model DIR (written by `export`)")
    else:
        cfg, params, _ = load_pretrained(model)
    out = {"what": f"first_{kind}", "ours": True, "config": cfg.name, "grid": cfg.grid.grid_size,
           "max_actors": cfg.grid.max_actors, "imports_s": t_import, "allocator": active()}
    if kind == "train":
        state = init_state(cfg)
        batch = jax.device_put(synthetic_batch(cfg, cfg.train.batch_size, cfg.grid.max_actors))
        t = process_age_s()
        out["init_s"] = t - t_import
        step = train_step_for_run(cfg, state, batch, None, steps=1000)
        out["compile_s"] = process_age_s() - t
        jax.block_until_ready(step(state, batch))
        out["step_s"] = process_age_s() - t - out["compile_s"]
        out["batch"] = cfg.train.batch_size
    elif kind == "score":
        b = 1 if cfg.name == "paper" else BATCH
        workers = min(default_workers(), b)
        batch = synthetic_batch(cfg, b, cfg.grid.max_actors, seed=1)
        part = b // workers
        parts = [jax.tree.map(lambda x, i=i: x[i * part:(i + 1) * part], batch)
                 for i in range(workers)]
        score = jax.jit(lambda p, b: score_batch(p, b, cfg.model)["class"],
                        compiler_options=scoring_compiler_options())
        jax.block_until_ready(list(concurrent_map(lambda x: score(params, x), parts, workers)))
        out.update(batch=b, workers=workers)
    else:
        from scenegen_jax.sampling import sample_scenes

        b = 1 if cfg.name == "paper" else BATCH
        host = synthetic_batch(cfg, b, 0, seed=2)
        s = sample_scenes(jax.random.key(0), params, cfg, host.maps, host.ego)
        jax.block_until_ready(s.actors.valid)
        out["batch"] = b
    out["first_result_s"] = process_age_s()
    out["backend"] = jax.default_backend()
    return out


def ref(kind: str, grid: int) -> dict:
    import torch

    torch.set_num_threads(int(os.environ.get("REF_THREADS", "2")))  # as its bench.py
    sys.path.insert(0, TORCH_REF)
    import model as M

    t_import = process_age_s()
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    net = M.SceneGen(map_ch=MAP_CHANNELS)
    steps, b = 25, 1
    if kind == "sample":
        net.eval()
        scene = M.random_scene(net, b, grid, grid, n_existing=16, gen=g)
        M.sample_step(net, scene, 10)
    else:
        x_seq, tgt = M.random_inputs(steps, b, MAP_CHANNELS, grid, grid, gen=g)
        if kind == "train":
            net.train()
            M.train_step(net, torch.optim.Adam(net.parameters(), lr=1e-4), x_seq, tgt)
        else:
            net.eval()
            with torch.inference_mode():
                M.scene_nll(net, x_seq, tgt)
    return {
        "what": f"first_{kind}",
        "ours": False,
        "grid": grid,
        "batch": b,
        "steps": steps,
        "imports_s": t_import,
        "first_result_s": process_age_s(),
        "threads": torch.get_num_threads(),
    }


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("side", choices=("ours", "ref", "export"))
    p.add_argument("kind", nargs="?", choices=("train", "score", "sample"))
    p.add_argument("--config", default="tiny", choices=("tiny", "cpu", "paper"))
    p.add_argument("--grid", type=int, default=128, help="paper preset and the reference")
    p.add_argument("--model", help="model directory: written by export, read by score, sample")
    a = p.parse_args()
    sys.path.insert(0, HERE)
    if a.side == "export":
        if not a.model:
            p.error("export needs --model DIR")
        export_model(a.config, a.grid, a.model)
        return
    if a.kind is None:
        p.error(f"{a.side} needs a kind: train, score or sample")
    if a.side == "ours":  # as the `scenegen` command starts: again, on tcmalloc if installed
        from scenegen_jax.allocator import reexec_with_tcmalloc

        reexec_with_tcmalloc()
    row = ours(a.kind, a.config, a.grid, a.model) if a.side == "ours" else ref(a.kind, a.grid)
    print("RESULT " + json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
