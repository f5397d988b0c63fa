"""Scoring real scenes: `scenegen score`, `evaluate` (the paper's Table 1) and `compare`."""

from __future__ import annotations

import json
import logging
import os
import sys

from scenegen_jax.cli.common import (
    add_distributed_args,
    add_model_args,
    add_temperature_arg,
    check_output,
    load_model,
    location_temperature,
    merge_parts,
    nonnegative_int,
    positive_int,
    seed_int,
    start_distributed,
)
from scenegen_jax.cli.sample import check_temperature
from scenegen_jax.files import written_whole


def cmd_score(args) -> None:
    """Scores every scene of the --data caches; with --distributed each process scores its
    share and process 0 writes the outputs of all."""
    import jax
    import numpy as np

    from scenegen_jax.backend import is_main_process, process_share
    from scenegen_jax.data.union import load_union
    from scenegen_jax.eval.nll import (
        score_cache,
        source_slices,
        summarize_by_source,
        summarize_scores,
    )

    if args.top_k and not args.render:
        raise ValueError("--top-k K needs --render DIR")
    check_output("--out", args.out)  # found now, not after the scoring
    if args.actors_out:
        if not args.actors_out.endswith(".npz"):  # as np.savez names it
            args.actors_out += ".npz"
        check_output("--actors-out", args.actors_out)
    if args.render:
        check_output("--render", args.render, folder=True)
    start_distributed(args)
    cfg, params, _, _ = load_model(args)
    cache = load_union(args.data, cfg)  # every --data cache, its scenes one after another
    share = process_share(len(cache))  # with several processes: its share of the scenes
    if not share:
        raise ValueError(f"{len(cache)} scenes cannot be shared by {jax.process_count()} "
                         "processes")
    scores = score_cache(params, cache, cfg, batch_size=args.batch_size, scenes=share,
                         progress=is_main_process())
    scores = merge_parts(args.out, scores)
    if scores is None:  # not process 0, which writes the outputs
        return
    write_scores_csv(args.out, scores, cache)
    summary = summarize_scores(scores)
    summary["by_source"] = summarize_by_source(scores, cache)
    if args.top_k:
        summary["rendered"] = _render_worst(scores, cache, cfg, args.top_k, args.render)
    print(json.dumps({"out": args.out, **summary}))
    if args.actors_out:
        parts = source_slices(cache)  # per scene: its source's number in source_labels
        which = np.concatenate([np.full(p.stop - p.start, n) for n, (_, p) in enumerate(parts)])
        with written_whole(args.actors_out) as tmp, open(tmp, "wb") as f:
            np.savez(f, **scores, source=which,
                     source_labels=np.array([name for name, _ in parts]))


def write_scores_csv(path: str, scores: dict, cache) -> None:
    """One row per scene: its index in its own cache, id, actors, whether they are all the
    region's (0: truncated to max_actors, no stop token), scene NLL, NLL per actor, each
    term's NLL and its source (the cache's label)."""
    import csv

    from scenegen_jax.distributions import TERMS
    from scenegen_jax.eval.nll import actor_steps, complete_scenes, source_slices

    total = sum(scores[k] for k in TERMS)
    n_actors = actor_steps(scores).sum(1)
    complete = complete_scenes(scores)
    # surrogateescape: a path's bytes that are not UTF-8 (in `source`) are written back as is.
    with (written_whole(path) as tmp,
          open(tmp, "w", newline="", encoding="utf-8", errors="surrogateescape") as f):
        writer = csv.writer(f)
        writer.writerow(["index", "scene_id", "actors", "complete", "scene_nll", "nll_per_actor",
                         *[f"{k}_nll" for k in TERMS], "source"])
        for source, part in source_slices(cache):
            for i in range(part.start, part.stop):
                per_actor = total[i].sum() / max(n_actors[i], 1)
                writer.writerow([i - part.start, cache.scene_ids[i], int(n_actors[i]),
                                 int(complete[i]), f"{total[i].sum():.4f}", f"{per_actor:.4f}",
                                 *[f"{scores[k][i].sum():.4f}" for k in TERMS], source])


def _render_worst(scores, cache, cfg, k: int, out_dir: str) -> list[str]:
    """Renders the k least likely scenes with their least likely actor highlighted."""
    import numpy as np

    from scenegen_jax.eval.nll import worst_scenes
    from scenegen_jax.likelihood.batch import grid_scene
    from scenegen_jax.scene import CLASS_NAMES
    from scenegen_jax.viz.render import render_scene

    os.makedirs(out_dir, exist_ok=True)
    paths = []
    for rank, (i, step, per_actor, terms) in enumerate(worst_scenes(scores, k)):
        map_raster, scene = grid_scene(cache, i, cfg.grid)
        cls = CLASS_NAMES[int(scene.actors.cls[step])]
        worst = ", ".join(f"{t} {v:.1f}" for t, v in terms.items())
        path = os.path.join(out_dir, f"top{rank + 1:02d}_{i:05d}.png")
        render_scene(
            path,
            np.asarray(map_raster),
            cfg.grid.map_channels,
            scene.actors,
            scene.ego,
            cfg,
            highlight=step,
            title=f"#{rank + 1} {cache.scene_ids[i]}: {per_actor:.2f} nats/actor\n"
            f"highlighted {cls} ({sum(terms.values()):.1f} nats: {worst})",
        )
        paths.append(path)
    return paths


def _companions(args) -> dict:
    """{kind: (config, parameters)} of the companions (the forecaster, the learned
    baselines) shipped with `--companions`, else with the `--pretrained` model; each one
    missing is logged (its column or row is left out)."""
    from scenegen_jax.pretrained import COMPANIONS, load_companion

    source = args.companions or args.pretrained
    out = {}
    for kind in COMPANIONS:
        found = load_companion(source, kind) if source else None
        if found is None:
            logging.getLogger("scenegen").warning(
                "no %s (%s): left out of the table; give --companions MODEL", kind,
                f"{source} ships none" if source else "a --workdir model")
        else:
            out[kind] = found[:2]
    return out


def cmd_evaluate(args) -> None:
    from scenegen_jax.data.union import load_union
    from scenegen_jax.eval.evaluate import evaluate, format_table
    from scenegen_jax.sampling import SamplerOptions

    check_temperature(args.location_temperature)
    check_output("--out", args.out)  # found now, not after the sampling
    cfg, params, step, sampler = load_model(args)
    cache = load_union(args.data, cfg)
    train_cache = load_union(args.train_data, cfg)
    both = {os.path.realpath(p) for p in args.data} & {os.path.realpath(p) for p in args.train_data}
    if both:  # the Procedural baseline would be fitted on the scenes it is scored against
        logging.getLogger("scenegen").warning(
            "%s: in both --data and --train-data; the figures are not on held-out scenes",
            ", ".join(sorted(both)))
    options = SamplerOptions(location_temperature=location_temperature(args, sampler))
    report = evaluate(params, cfg, cache, train_cache, args.num, args.seed, options,
                      _companions(args))
    report["step"] = step
    report["command"] = " ".join(["scenegen", *sys.argv[1:]])
    with written_whole(args.out) as tmp, open(tmp, "w") as f:
        json.dump(report, f, indent=1)
    print(format_table(report))


def cmd_compare(args) -> None:
    from scenegen_jax.eval.compare import compare_files

    if args.out:
        check_output("--out", args.out)
    report = compare_files(args.a, args.b, args.term, args.block, args.samples, args.seed)
    if args.out:
        with written_whole(args.out) as tmp, open(tmp, "w") as f:
            json.dump(report, f, indent=1)
    print(f"{args.term} NLL per actor, A minus B (95% block-bootstrap interval)")
    for name, r in report["rows"].items():
        if r["actors"] and r["low"] is None:
            print(f"  {name:<11} {r['diff']:+.3f} (no interval: the scenes make one block of "
                  f"--block {args.block})  ({r['actors']} actors)")
        elif r["actors"]:
            print(f"  {name:<11} {r['diff']:+.3f} [{r['low']:+.3f}, {r['high']:+.3f}]"
                  f"  ({r['actors']} actors)")
        else:
            print(f"  {name:<11} no actors")


def add_parsers(sub) -> None:
    """Registers this module's subcommands."""
    sp = sub.add_parser("score", help="NLL of real scenes under a trained model")
    add_model_args(sp)
    add_distributed_args(sp, "scoring")
    sp.add_argument("--data", required=True, nargs="+", metavar="CACHE",
                    help="cache directories to score (summary also per source)")
    sp.add_argument("--out", required=True, help="CSV, one row per scene (with its source)")
    sp.add_argument("--batch-size", type=positive_int, default=8,
                    help="scenes per batch and device, split into concurrent calls (one per "
                    "core on CPU)")
    sp.add_argument("--actors-out", help="optional .npz of per-step NLL terms")
    sp.add_argument("--top-k", type=nonnegative_int, default=0,
                    help="render the K scenes with the highest NLL per actor (needs --render)")
    sp.add_argument("--render", help="directory for the --top-k renders")
    sp.set_defaults(func=cmd_score)

    sp = sub.add_parser("evaluate", help="NLL and MMD of SceneGen and baselines (Table 1)")
    add_model_args(sp)
    sp.add_argument("--data", required=True, nargs="+", metavar="CACHE",
                    help="caches of the evaluation split (NLL also per source)")
    sp.add_argument("--train-data", required=True, nargs="+", metavar="CACHE",
                    help="training caches (Procedural's KDE)")
    sp.add_argument("--num", type=positive_int, default=64, help="conditioning scenes for MMD")
    sp.add_argument("--companions", metavar="MODEL",
                    help="the pretrained model (name or directory) whose forecaster (Features "
                    "MMD) and learned baselines to read (default: --pretrained's own)")
    sp.add_argument("--seed", type=seed_int, default=0)
    add_temperature_arg(sp)
    sp.add_argument("--out", required=True, help="report JSON")
    sp.set_defaults(func=cmd_evaluate)

    sp = sub.add_parser(
        "compare", help="paired NLL difference of two models on the same scenes, with intervals"
    )
    sp.add_argument("--a", nargs="+", required=True,
                    help="model A's `score --actors-out` files (one per seed)")
    sp.add_argument("--b", nargs="+", required=True, help="model B's, paired with --a in order")
    sp.add_argument("--term", default="location",
                    help="class, location, box, heading, velocity or total")
    sp.add_argument("--block", type=positive_int, default=10,
                    help="consecutive scenes per bootstrap block")
    sp.add_argument("--samples", type=positive_int, default=2000, help="bootstrap resamples")
    sp.add_argument("--seed", type=nonnegative_int, default=0)
    sp.add_argument("--out", help="optional report JSON")
    sp.set_defaults(func=cmd_compare)
