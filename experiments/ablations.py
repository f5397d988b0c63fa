"""Ablations of the paper's Table 3 / Figure 6 at the `cpu` config.

Sweeps:
  mixtures    K in {1, 3, 5, 10}                       (trained, val NLL)
  map_layers  none / lanes / +drivable / +crosswalks    (trained, val NLL)
  proposals   M in {1, 10, 20}                          (sampling only, MMD on val)

Each trained member is a `cpu` model trained from scratch for the same number of steps
(`--steps`, same seed, data order and batch size), then scored on the val cache; `--seed N`
trains a repeat with another seed (initialisation, data order, augmentation), reported beside
seed 0. One member per call, so two members can train side by side, one per core:

  taskset -c 0 .venv/bin/python experiments/ablations.py train mixtures 1 --steps 279
  taskset -c 1 .venv/bin/python experiments/ablations.py train mixtures 3 --steps 279
  .venv/bin/python experiments/ablations.py sample proposals 10 --workdir runs/cpu_map
  .venv/bin/python experiments/ablations.py report mixtures      # table + plot

A member already trained elsewhere with the same settings (e.g. a map / no-map pair) is
brought in with `adopt SWEEP VALUE SUMMARY.json --steps N`, which records where it came from.
Results: experiments/results/ablations/SWEEP_VALUE.json, experiments/results/ablation_SWEEP.md
and .png.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
RESULTS = os.path.join(HERE, "results")
BIN = os.path.dirname(sys.executable)

SWEEPS = {
    "mixtures": {"values": ["1", "3", "5", "10"], "label": "mixture components K"},
    "map_layers": {
        "values": ["none", "lanes", "lanes,drivable", "lanes,drivable,crosswalks"],
        "label": "map layers",
    },
    "proposals": {"values": ["1", "10", "20"], "label": "proposals M (best-of-M)"},
}
MAX_SEEDS = 10  # repeats looked for by `report`
NLL_COLUMNS = ("scene_nll", "nll_per_actor", "location_nll_per_vehicle", "nll_per_vehicle",
               "nll_per_pedestrian", "nll_per_bicyclist")  # fmt: skip


def member_name(sweep: str, value: str, seed: int = 0) -> str:
    return f"{sweep}_{value.replace(',', '+')}" + (f"_seed{seed}" if seed else "")


def member_path(sweep: str, value: str, seed: int = 0) -> str:
    return os.path.join(RESULTS, "ablations", member_name(sweep, value, seed) + ".json")


def overrides(sweep: str, value: str, seed: int) -> list[str]:
    seeded = [f"seed={seed}"] if seed else []
    if sweep == "mixtures":
        return [f"num_mixtures={value}", *seeded]
    if sweep == "map_layers":
        return [f"map_layers={value}", *seeded]
    raise ValueError(f"{sweep} is not a training sweep")


def run(cmd: list[str]) -> str:
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    return subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=REPO).stdout


def write(path: str, record: dict) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(record, f, indent=1)
    print(path)


def cmd_train(args) -> None:
    values = SWEEPS[args.sweep]["values"]
    if args.value not in values:
        raise SystemExit(f"{args.sweep}: value {args.value!r} not in {values}")
    workdir = os.path.join(args.runs, member_name(args.sweep, args.value, args.seed))
    sets = overrides(args.sweep, args.value, args.seed)
    train = [os.path.join(BIN, "scenegen"), "train", "--config", "cpu", "--data", args.train_data,
             "--workdir", workdir, "--steps", str(args.steps), "--set", *sets]
    t0 = time.time()
    run(train)
    minutes = (time.time() - t0) / 60
    csv = os.path.join(workdir, "val_scores.csv")
    score = [os.path.join(BIN, "scenegen"), "score", "--workdir", workdir, "--data",
             args.val_data, "--out", csv]
    summary = json.loads(run(score).strip().splitlines()[-1])
    write(member_path(args.sweep, args.value, args.seed), {
        "sweep": args.sweep, "value": args.value, "seed": args.seed, "steps": args.steps,
        "train_minutes_this_call": round(minutes, 1), "date": time.strftime("%Y-%m-%d"),
        "commands": [" ".join(train), " ".join(score)], "val": summary,
    })


def cmd_adopt(args) -> None:
    with open(args.summary) as f:
        summary = json.load(f)
    write(member_path(args.sweep, args.value), {
        "sweep": args.sweep, "value": args.value, "steps": args.steps,
        "date": time.strftime("%Y-%m-%d"), "adopted_from": args.summary,
        "commands": [args.command] if args.command else [], "val": summary,
    })


def cmd_sample(args) -> None:
    import numpy as np

    from scenegen_jax.data.cache import load_cache
    from scenegen_jax.eval.evaluate import MMD_ROWS, real_scenes, sample_scenegen
    from scenegen_jax.eval.mmd import mmd_table
    from scenegen_jax.eval.realism import drivable_share, map_canvases
    from scenegen_jax.train.loop import load_trained

    cfg, state = load_trained(args.workdir)
    cfg = cfg.replace(proposals=int(args.value))
    cache = load_cache(args.val_data)
    indices = np.linspace(0, len(cache) - 1, min(args.num, len(cache))).astype(int)
    maps, scenes = real_scenes(cache, indices, cfg)
    samples = sample_scenegen(state.params, cfg, maps, scenes, args.seed)
    mmd = mmd_table([s.actors for s in scenes], samples, region_m=cfg.grid.region_m)
    on = total = 0
    for canvas, actors in zip(map_canvases(cache, indices, cfg), samples, strict=True):
        a, b = drivable_share(canvas, actors, cfg)
        on, total = on + a, total + b
    write(member_path(args.sweep, args.value), {
        "sweep": args.sweep, "value": args.value, "workdir": args.workdir,
        "step": int(state.step), "scenes": len(indices), "seed": args.seed,
        "date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
        "mmd": {r: mmd.get(r) for r in MMD_ROWS},
        "vehicles_on_drivable": on / total if total else None,
    })


def cmd_report(args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spec = SWEEPS[args.sweep]
    records = []
    for v in spec["values"]:
        for seed in range(MAX_SEEDS):
            path = member_path(args.sweep, v, seed)
            if os.path.exists(path):
                with open(path) as f:
                    records.append({"seed": seed, **json.load(f)})
    if not records:
        raise SystemExit(f"no results for {args.sweep} yet")
    lines = [f"# Ablation: {spec['label']} (`cpu` config, val log)", ""]
    if args.sweep == "proposals":
        from scenegen_jax.eval.evaluate import MMD_ROWS

        r0 = records[0]
        lines += [f"Model `{r0['workdir']}` at step {r0['step']}, {r0['scenes']} conditioning "
                  "scenes of the val log, MMD^2 against the real scenes (lower is better).", "",
                  "| M | " + " | ".join(MMD_ROWS) + " | vehicles on drivable |",
                  "|---" * (len(MMD_ROWS) + 2) + "|"]
        for r in records:
            row = [f"{r['mmd'][k]:.4f}" if r["mmd"].get(k) is not None else "-"
                   for k in MMD_ROWS]
            lines.append(f"| {r['value']} | " + " | ".join(row)
                         + f" | {100 * r['vehicles_on_drivable']:.1f}% |")
        ys = {k: [r["mmd"][k] for r in records] for k in ("class/all", "area/all", "speed/all",
                                                           "heading/all")}
        ylabel = "MMD^2"
    else:
        lines += [f"Every member: `cpu` config trained from scratch for {records[0]['steps']} "
                  "steps (batch 4), scored on all 157 val scenes (nats). Seed 0 unless the "
                  "seed column says otherwise; the plot shows each seed and their mean.", "",
                  "| " + spec["label"] + " | seed | " + " | ".join(NLL_COLUMNS) + " |",
                  "|---" * (len(NLL_COLUMNS) + 2) + "|"]
        for r in records:
            row = [f"{r['val'][k]:.3f}" if r["val"].get(k) is not None else "-"
                   for k in NLL_COLUMNS]
            lines.append(f"| {r['value']} | {r['seed']} | " + " | ".join(row) + " |")
        ys = {k: [r["val"][k] for r in records] for k in ("nll_per_actor",
                                                           "location_nll_per_vehicle")}
        ylabel = "val NLL (nats)"
    lines += ["", "Commands:", ""]
    for r in records:
        cmds = r.get("commands") or [r.get("command", "")]
        extra = f" (adopted from {r['adopted_from']})" if r.get("adopted_from") else ""
        seed = f" (seed {r['seed']})" if r["seed"] else ""
        lines += [f"- {r['value']}{seed}{extra}:"] + [f"  `{c}`" for c in cmds if c]
    md = os.path.join(RESULTS, f"ablation_{args.sweep}.md")
    with open(md, "w") as f:
        f.write("\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(5, 3.2))
    values = list(dict.fromkeys(r["value"] for r in records))
    xs = [v.replace("lanes,drivable,crosswalks", "+crosswalks").replace("lanes,drivable",
                                                                          "+drivable")
          for v in values]
    for k, v in ys.items():
        per = [[y for r, y in zip(records, v, strict=True) if r["value"] == x] for x in values]
        line = ax.plot(xs, [sum(p) / len(p) for p in per], marker="o", label=k)[0]
        for i, p in enumerate(per):
            if len(p) > 1:
                ax.scatter([i] * len(p), p, s=10, color=line.get_color(), alpha=0.6)
    ax.set_xlabel(spec["label"])
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(md[:-3] + ".png", dpi=120)
    print(md)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--train-data", default="runs/cache_cpu_train")
    p.add_argument("--val-data", default="runs/cache_cpu_val")
    p.add_argument("--runs", default="runs/ablation", help="workdirs of the trained members")
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("sweep", choices=("mixtures", "map_layers"))
    t.add_argument("value")
    t.add_argument("--steps", type=int, required=True)
    t.add_argument("--seed", type=int, default=0, help="a repeat with another seed")
    a = sub.add_parser("adopt")
    a.add_argument("sweep", choices=("mixtures", "map_layers"))
    a.add_argument("value")
    a.add_argument("summary", help="JSON summary printed by `scenegen score`")
    a.add_argument("--steps", type=int, required=True)
    a.add_argument("--command", help="how that model was trained and scored")
    s = sub.add_parser("sample")
    s.add_argument("sweep", choices=("proposals",))
    s.add_argument("value")
    s.add_argument("--workdir", required=True)
    s.add_argument("--num", type=int, default=32)
    s.add_argument("--seed", type=int, default=0)
    r = sub.add_parser("report")
    r.add_argument("sweep", choices=tuple(SWEEPS))
    args = p.parse_args()
    {"train": cmd_train, "adopt": cmd_adopt, "sample": cmd_sample, "report": cmd_report}[
        args.cmd
    ](args)


if __name__ == "__main__":
    main()
