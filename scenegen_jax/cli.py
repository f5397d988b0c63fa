"""The `scenegen` command line: one entry point with subcommands."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys

from tqdm import tqdm

from scenegen_jax.config import PRESETS, Config, apply_overrides, get_config
from scenegen_jax.data.sources import DEFAULT_STRIDE, SOURCES


def _overrides(pairs: list[str]) -> dict[str, str]:
    out = {}
    for pair in pairs or []:
        if "=" not in pair:
            raise SystemExit(f"override {pair!r} must look like field=value")
        k, v = pair.split("=", 1)
        out[k] = v
    return out


def cmd_prepare(args) -> None:
    from scenegen_jax.data.prepare import prepare
    from scenegen_jax.data.sources import source_spec

    cfg = get_config(args.config, **_overrides(args.set))
    spec = source_spec(args.source, args.root, args.split, args.stride)
    with tqdm(desc=f"prepare {args.source}", unit="file", file=sys.stderr) as bar:
        summary, rate = prepare(
            spec, args.out, cfg, workers=args.workers, strict=args.strict, progress=bar
        )
    out = {"out": args.out, "config": cfg.name, "scenes_per_s": round(rate, 2)}
    print(json.dumps({**out, **summary.to_dict()}))


def cmd_render(args) -> None:
    import numpy as np

    from scenegen_jax.data.cache import cached_scene, load_cache
    from scenegen_jax.raster.transform import scene_from_cached
    from scenegen_jax.viz.render import render_scene

    cache = load_cache(args.cache)
    saved = Config.from_json(json.dumps(cache.meta["config"]), f"{args.cache}/meta.json")
    cfg = apply_overrides(saved, **_overrides(args.set))
    cache.check_config(cfg)
    indices = args.index if args.index else [0]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    for n, index in enumerate(indices):
        canvas, actors, ego = cached_scene(cache, index, cfg)
        theta = np.deg2rad(args.rotate)
        map_raster, scene, _ = scene_from_cached(canvas, actors, ego, theta, cfg)
        out = args.out if len(indices) == 1 else _numbered(args.out, n, index)
        render_scene(
            out,
            np.asarray(map_raster),
            cfg.map_channels,
            scene.actors,
            scene.ego,
            cfg,
            title=f"{cache.scene_ids[index]}  ({int(np.sum(scene.actors.valid))} actors)",
        )
        print(out)


def _numbered(path: str, n: int, index: int) -> str:
    root, ext = os.path.splitext(path)
    return f"{root}_{index:05d}{ext or '.png'}"


def cmd_train(args) -> None:
    from scenegen_jax.train.loop import train

    cfg = get_config(args.config, **_overrides(args.set))
    if args.distributed:
        import jax

        jax.distributed.initialize()
    state = train(
        cfg,
        args.data,
        args.workdir,
        args.steps,
        save_every=args.save_every,
        log_every=args.log_every,
        keep=args.keep,
        max_seconds=args.minutes * 60 if args.minutes else None,
        init_from=args.init_from,
        weights=args.weights,
    )
    print(json.dumps({"workdir": args.workdir, "step": int(state.step)}))


def cmd_score(args) -> None:
    import csv

    import numpy as np

    from scenegen_jax.distributions import TERMS
    from scenegen_jax.eval.nll import (
        actor_steps,
        score_cache,
        source_slices,
        summarize_by_source,
        summarize_scores,
    )
    from scenegen_jax.train.data import load_union

    if args.top_k < 0 or (args.top_k and not args.render):
        raise SystemExit("--top-k K needs K >= 0 and --render DIR")
    if args.batch_size < 1:
        raise SystemExit(f"--batch-size must be >= 1, got {args.batch_size}")
    cfg, params, _ = load_model(args)
    cache = load_union(args.data, cfg)  # every --data cache, its scenes one after another
    scores = score_cache(params, cache, cfg, batch_size=args.batch_size)
    total = sum(scores[k] for k in TERMS)
    actor = actor_steps(scores)
    n_actors = actor.sum(1)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            [
                "index",
                "scene_id",
                "actors",
                "scene_nll",
                "nll_per_actor",
                *[f"{k}_nll" for k in TERMS],
                "source",
            ]
        )
        # index: the scene's index in its own cache; source: that cache's label.
        for source, part in source_slices(cache):
            for i in range(part.start, part.stop):
                per_actor = total[i].sum() / max(n_actors[i], 1)
                writer.writerow(
                    [
                        i - part.start,
                        cache.scene_ids[i],
                        int(n_actors[i]),
                        f"{total[i].sum():.4f}",
                        f"{per_actor:.4f}",
                        *[f"{scores[k][i].sum():.4f}" for k in TERMS],
                        source,
                    ]
                )
    summary = summarize_scores(scores)
    summary["by_source"] = summarize_by_source(scores, cache)
    if args.top_k:
        summary["rendered"] = _render_worst(scores, cache, cfg, args.top_k, args.render)
    print(json.dumps({"out": args.out, **summary}))
    if args.actors_out:
        parts = source_slices(cache)  # per scene: its source's number in source_labels
        which = np.concatenate([np.full(p.stop - p.start, n) for n, (_, p) in enumerate(parts)])
        np.savez(args.actors_out, **scores, source=which,
                 source_labels=np.array([name for name, _ in parts]))


def _render_worst(scores, cache, cfg, k: int, out_dir: str) -> list[str]:
    """Renders the k least likely scenes with their least likely actor highlighted."""
    import numpy as np

    from scenegen_jax.data.cache import cached_scene
    from scenegen_jax.eval.nll import worst_scenes
    from scenegen_jax.raster.transform import scene_from_cached
    from scenegen_jax.scene import CLASS_NAMES
    from scenegen_jax.viz.render import render_scene

    os.makedirs(out_dir, exist_ok=True)
    paths = []
    for rank, (i, step, per_actor, terms) in enumerate(worst_scenes(scores, k)):
        canvas, actors, ego = cached_scene(cache, i, cfg)
        map_raster, scene, _ = scene_from_cached(canvas, actors, ego, 0.0, cfg)
        cls = CLASS_NAMES[int(scene.actors.cls[step])]
        worst = ", ".join(f"{t} {v:.1f}" for t, v in terms.items())
        path = os.path.join(out_dir, f"top{rank + 1:02d}_{i:05d}.png")
        render_scene(
            path,
            np.asarray(map_raster),
            cfg.map_channels,
            scene.actors,
            scene.ego,
            cfg,
            highlight=step,
            title=f"#{rank + 1} {cache.scene_ids[i]}: {per_actor:.2f} nats/actor\n"
            f"highlighted {cls} ({sum(terms.values()):.1f} nats: {worst})",
        )
        paths.append(path)
    return paths


def read_given(path: str, cfg: Config, scene_ego_sizes, allow_overlap: bool = False) -> list:
    """Given actors (numpy Actors [N]) of each non-blank line of a `sample --given` file.

    Line j of L lines conditions scenes j, j + L, ...; `scene_ego_sizes` [num scenes, 2]
    (width, length) m are the egos of the scenes to sample, so each line's boxes are checked
    against the egos it meets (and each other) unless `allow_overlap`. Errors name the file,
    the line and the field.
    """
    import numpy as np

    from scenegen_jax.sampling import actors_from_records

    rows = []
    with open(path) as f:
        for line_no, line in enumerate(f, 1):
            if not line.strip():
                continue
            where = f"{path}:{line_no}"
            try:
                row = json.loads(line)
            except json.JSONDecodeError as e:
                raise ValueError(f"{where}: not JSON ({e})") from e
            if not isinstance(row, dict) or "actors" not in row:
                raise ValueError(f'{where}: actors: missing (expected {{"actors": [...]}})')
            rows.append((where, row["actors"]))
    if not rows:
        raise ValueError(f"{path}: no given scenes")
    sizes = np.asarray(scene_ego_sizes, np.float64).reshape(-1, 2)
    return [
        actors_from_records(records, cfg, where, np.unique(sizes[j :: len(rows)], axis=0),
                            allow_overlap)
        for j, (where, records) in enumerate(rows)
    ]


def cmd_sample(args) -> None:
    """Samples scenes on the maps and egos of cache scenes; writes JSON lines, ScenarioNet
    pickles, PNGs and (with --heatmaps) per-step location heatmaps."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from scenegen_jax.data.cache import load_cache
    from scenegen_jax.data.scenarionet import scenario_from_frame, write_dataset
    from scenegen_jax.raster.transform import crop_map
    from scenegen_jax.sampling import (
        HEATMAP_STEPS,
        STOP_REASONS,
        actor_records,
        batch_inputs,
        frame_from_sample,
        sample_split,
    )
    from scenegen_jax.scene import CLASS_NAMES, NUM_CLASSES, Actors
    from scenegen_jax.viz.heatmap import render_heatmaps
    from scenegen_jax.viz.render import render_scene

    if args.num < 1 or args.batch_size < 1:
        raise SystemExit("--num and --batch-size must be >= 1")
    if args.proposals is not None and args.proposals < 1:
        raise SystemExit("--proposals must be >= 1")
    cfg, params, _ = load_model(args)
    cache = load_cache(args.data)
    cache.check_config(cfg)
    indices = list(args.index) if args.index else list(range(len(cache)))
    for i in indices:
        if not 0 <= i < len(cache):
            raise IndexError(f"{cache.path}: --index {i} out of range [0, {len(cache)})")
    given_lines = []
    if args.given:
        # Scene k is sampled beside the ego of cache scene indices[k mod len(indices)].
        scene_egos = cache.ego_size[[indices[k % len(indices)] for k in range(args.num)]]
        given_lines = read_given(args.given, cfg, scene_egos, args.allow_overlap)
    caps = np.full(NUM_CLASSES, cfg.max_actors, np.int32)
    for pair in args.cap or []:
        name, _, value = pair.partition("=")
        if name not in CLASS_NAMES or not value.isdigit():
            raise SystemExit(f"--cap {pair!r}: expected CLASS=N with CLASS in {CLASS_NAMES}")
        caps[CLASS_NAMES.index(name)] = int(value)

    out = os.path.abspath(args.out)
    for sub_dir in ("png", "scenarionet") + (("heatmaps",) if args.heatmaps else ()):
        os.makedirs(os.path.join(out, sub_dir), exist_ok=True)
    crop = jax.jit(crop_map, static_argnums=2)
    map_cache: dict[int, np.ndarray] = {}

    def map_of(i: int) -> np.ndarray:
        if i not in map_cache:
            map_cache[i] = np.asarray(crop(jnp.asarray(cache.maps[i]), 0.0, cfg))
        return map_cache[i]

    def ego_of(i: int) -> Actors:
        return Actors(
            cls=np.int32(0),
            position=np.zeros(2, np.float32),
            size=cache.ego_size[i].astype(np.float32),
            heading=np.float32(0.0),
            velocity=cache.ego_velocity[i].astype(np.float32),
            valid=np.bool_(True),
        )

    key = jax.random.key(args.seed)
    steps = HEATMAP_STEPS if args.heatmaps else ()
    scenarios, counts = [], np.zeros(NUM_CLASSES, np.int64)
    b = args.batch_size
    with (
        open(os.path.join(out, "scenes.jsonl"), "w") as jsonl,
        tqdm(total=args.num, desc="sample", unit="scene", file=sys.stderr) as bar,
    ):
        for start in range(0, args.num, b):
            # Scene k uses key fold_in(seed key, k): results do not depend on --batch-size.
            ks = np.minimum(np.arange(start, start + b), args.num - 1)
            map_ids = [indices[k % len(indices)] for k in ks]
            egos = jax.tree.map(lambda *x: np.stack(x), *[ego_of(i) for i in map_ids])
            given, batch_caps = batch_inputs(cfg, b, None, caps)
            if given_lines:
                rows = [given_lines[k % len(given_lines)] for k in ks]
                given = jax.tree.map(lambda *x: np.stack(x), *rows)
            keys = jax.vmap(lambda k: jax.random.fold_in(key, k))(jnp.asarray(ks))[:, None]
            sample = sample_split(
                keys,
                params,
                np.stack([map_of(i) for i in map_ids]),
                egos,
                given,
                batch_caps,
                cfg=cfg,
                proposals=args.proposals,
                heatmap_steps=steps,
            )
            sample = jax.device_get(jax.tree.map(lambda x: x[:, 0], sample))
            for j, k in enumerate(ks[: args.num - start]):
                k, i = int(k), map_ids[j]
                actors = jax.tree.map(lambda x, j=j: x[j], sample.actors)
                ego = ego_of(i)
                scene_id = f"sample_{k:06d}"
                records = actor_records(actors)
                for r in records:
                    counts[CLASS_NAMES.index(r["class"])] += 1
                row = {
                    "scene": scene_id,
                    "map_index": i,
                    "map_scene_id": cache.scene_ids[i],
                    "seed": args.seed,
                    "num_given": int(sample.num_given[j]),
                    "stop_reason": STOP_REASONS[int(sample.stop_reason[j])],
                    "rejected": int(sample.rejected[j]),
                    "ego": {
                        "width": float(ego.size[0]),
                        "length": float(ego.size[1]),
                        "vx": float(ego.velocity[0]),
                        "vy": float(ego.velocity[1]),
                    },
                    "actors": records,
                }
                jsonl.write(json.dumps(row) + "\n")
                frame = frame_from_sample(
                    actors, ego, cache.scene_ids[i], city_from_ego=cache.city_from_ego[i]
                )
                scenarios.append(scenario_from_frame(frame, scene_id))
                title = (
                    f"{scene_id} on {cache.scene_ids[i]}  ({len(records)} actors, "
                    f"{row['num_given']} given)"
                )
                render_scene(
                    os.path.join(out, "png", f"{scene_id}.png"),
                    map_of(i),
                    cfg.map_channels,
                    actors,
                    ego,
                    cfg,
                    title=title,
                )
                if args.heatmaps:
                    render_heatmaps(
                        os.path.join(out, "heatmaps", f"{scene_id}.png"),
                        map_of(i),
                        cfg.map_channels,
                        sample.heatmaps[j],
                        sample.heatmap_cls[j],
                        steps,
                        actors,
                        ego,
                        cfg,
                        title=title,
                    )
                bar.update(1)
    write_dataset(scenarios, os.path.join(out, "scenarionet"))
    print(
        json.dumps(
            {
                "out": out,
                "scenes": args.num,
                "actors": {n: int(c) for n, c in zip(CLASS_NAMES, counts, strict=True)},
            }
        )
    )


def cmd_evaluate(args) -> None:
    from scenegen_jax.eval.evaluate import evaluate, format_table
    from scenegen_jax.train.data import load_union

    if args.num < 1:
        raise SystemExit(f"--num must be >= 1, got {args.num}")
    cfg, params, step = load_model(args)
    cache = load_union(args.data, cfg)
    train_cache = load_union(args.train_data, cfg)
    report = evaluate(params, cfg, cache, train_cache, args.num, args.seed)
    report["step"] = step
    report["command"] = " ".join(["scenegen", *sys.argv[1:]])
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
    print(format_table(report))


def cmd_compare(args) -> None:
    from scenegen_jax.eval.compare import compare_files

    report = compare_files(args.a, args.b, args.term, args.block, args.samples, args.seed)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)
    print(f"{args.term} NLL per actor, A minus B (95% block-bootstrap interval)")
    for name, r in report["rows"].items():
        if r["actors"]:
            print(f"  {name:<11} {r['diff']:+.3f} [{r['low']:+.3f}, {r['high']:+.3f}]"
                  f"  ({r['actors']} actors)")
        else:
            print(f"  {name:<11} no actors")


def load_model(args):
    """(config, parameters, training step) of `--pretrained NAME` or `--workdir` (`--step`)."""
    import jax

    if args.pretrained:
        if args.step is not None:
            raise SystemExit("--step selects a checkpoint of --workdir; a pretrained model has one")
        from scenegen_jax.pretrained import load_pretrained

        cfg, params, manifest = load_pretrained(args.pretrained)
        step = manifest["step"]
    else:
        from scenegen_jax.train.loop import load_trained

        cfg, state = load_trained(args.workdir, args.step)
        params, step = state.params, int(state.step)
    # Uncommitted copies: restored arrays are committed to a device, and jit compiles a
    # separate executable for committed inputs.
    return cfg, jax.device_put(jax.device_get(params)), step


def cmd_export_model(args) -> None:
    from scenegen_jax.pretrained import save_pretrained
    from scenegen_jax.train.loop import load_trained

    cfg, state = load_trained(args.workdir, args.step)
    manifest = save_pretrained(args.out, cfg, state.params, int(state.step), args.workdir)
    print(json.dumps({"out": args.out, **manifest}))


def add_model_args(sp) -> None:
    """`--workdir DIR [--step N]` or `--pretrained NAME`: the model a command uses."""
    which = sp.add_mutually_exclusive_group(required=True)
    which.add_argument("--workdir", help="training workdir (config + checkpoints)")
    which.add_argument(
        "--pretrained", metavar="NAME",
        help="a model shipped with the package (`scenegen models` lists them) or a directory "
        "written by `scenegen export-model`",
    )
    sp.add_argument("--step", type=int, help="checkpoint step of --workdir (default: the latest)")


def cmd_models(args) -> None:
    from scenegen_jax.pretrained import available, load_pretrained

    for name in available():
        cfg, _, manifest = load_pretrained(name)
        print(f"{name}\tconfig {cfg.name}, grid {cfg.grid_size}, step {manifest['step']}, "
              f"{manifest['parameters']} parameters")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="scenegen", description=__doc__)
    p.add_argument(
        "-v", "--verbose", action="store_true", help="debug logging; tracebacks with errors"
    )
    sub = p.add_subparsers(dest="command", required=True)

    sp = sub.add_parser("prepare", help="read logs into a preprocessed cache")
    sp.add_argument("--source", choices=SOURCES, default="av2",
                    help="av2: Argoverse 2 logs; scenarionet: ScenarioNet pickles; womd_json: "
                    "Waymo scenes as GPUDrive / Nocturne JSON")
    sp.add_argument("--root", required=True, help="dataset root (av2: holds train/ and val/)")
    sp.add_argument("--split", help="sub-folder of --root (av2: default train; others: all "
                    "files under --root when not given)")
    sp.add_argument("--out", required=True, help="cache directory to write")
    sp.add_argument("--config", default="tiny", choices=sorted(PRESETS))
    sp.add_argument("--stride", type=int, default=DEFAULT_STRIDE,
                    help="keep every N-th step of a log or scenario (10 Hz: default 10, one "
                    "frame per second)")
    sp.add_argument("--workers", type=int, help="processes (default: one per core)")
    sp.add_argument("--strict", action="store_true",
                    help="stop at the first unusable file instead of skipping and counting it")
    sp.add_argument("--set", nargs="*", metavar="FIELD=VALUE", help="config overrides")
    sp.set_defaults(func=cmd_prepare)

    sp = sub.add_parser("render", help="render cached real scenes to PNG")
    sp.add_argument("--cache", required=True)
    sp.add_argument("--index", type=int, nargs="*", help="scene indices (default 0)")
    sp.add_argument("--out", required=True, help="PNG path (numbered when several indices)")
    sp.add_argument("--rotate", type=float, default=0.0, help="rotate about the ego, degrees")
    sp.add_argument("--set", nargs="*", metavar="FIELD=VALUE", help="config overrides")
    sp.set_defaults(func=cmd_render)
    sp = sub.add_parser("train", help="train a model on a cache")
    sp.add_argument("--config", default="tiny", choices=sorted(PRESETS))
    sp.add_argument("--data", required=True, nargs="+", metavar="CACHE",
                    help="cache directories from `prepare` (same config, any sources), "
                    "trained on together")
    sp.add_argument("--weights", type=float, nargs="+", metavar="W",
                    help="one per --data cache: a scene comes from cache i with probability "
                    "W_i / sum(W) (default: the scene counts, uniform over all scenes)")
    sp.add_argument("--workdir", required=True,
                    help="checkpoints, config.json, data.json, metrics.jsonl")
    sp.add_argument("--steps", type=int, default=1000, help="total steps (resumes if fewer done)")
    sp.add_argument("--save-every", type=int, default=100)
    sp.add_argument("--log-every", type=int, default=10)
    sp.add_argument("--keep", type=int, default=3, help="checkpoints kept")
    sp.add_argument("--minutes", type=float, help="wall-time budget; stops and saves after it")
    sp.add_argument(
        "--init-from",
        metavar="WORKDIR",
        help="a fresh run starts from this workdir's trained parameters (fresh optimizer); "
        "a model without map layers can be extended with them",
    )
    sp.add_argument(
        "--distributed",
        action="store_true",
        help="multi-host: call jax.distributed.initialize() first",
    )
    sp.add_argument("--set", nargs="*", metavar="FIELD=VALUE", help="config overrides")
    sp.set_defaults(func=cmd_train)

    sp = sub.add_parser("score", help="NLL of real scenes under a trained model")
    add_model_args(sp)
    sp.add_argument("--data", required=True, nargs="+", metavar="CACHE",
                    help="cache directories to score (summary also per source)")
    sp.add_argument("--out", required=True, help="CSV, one row per scene (with its source)")
    sp.add_argument("--batch-size", type=int, default=8,
                    help="scenes per batch, split into concurrent calls (one per core on CPU)")
    sp.add_argument("--actors-out", help="optional .npz of per-step NLL terms")
    sp.add_argument("--top-k", type=int, default=0,
                    help="render the K scenes with the highest NLL per actor (needs --render)")
    sp.add_argument("--render", help="directory for the --top-k renders")
    sp.set_defaults(func=cmd_score)

    sp = sub.add_parser("sample", help="sample new scenes on the maps of cache scenes")
    add_model_args(sp)
    sp.add_argument("--data", required=True, help="cache whose maps and egos condition the scenes")
    sp.add_argument("--num", type=int, required=True, help="scenes to sample")
    sp.add_argument("--out", required=True, help="output directory")
    sp.add_argument("--proposals", type=int, help="best-of-M proposals (default: the config's)")
    sp.add_argument("--seed", type=int, default=0)
    sp.add_argument(
        "--given",
        help="JSON lines of actors to condition on (scenes.jsonl format); "
        "scene k uses line k mod lines",
    )
    sp.add_argument(
        "--allow-overlap",
        action="store_true",
        help="keep --given vehicle and bicyclist boxes that overlap each other or the ego "
        "(refused by default)",
    )
    sp.add_argument("--cap", nargs="*", metavar="CLASS=N", help="max actors per class")
    sp.add_argument(
        "--heatmaps",
        action="store_true",
        help="also render location heatmaps at steps 0, 5, 10, 15, 20",
    )
    sp.add_argument(
        "--index", type=int, nargs="*", help="cache scene indices to cycle through (default: all)"
    )
    sp.add_argument("--batch-size", type=int, default=8,
                    help="scenes per batch, split into concurrent calls (one per core on CPU)")
    sp.set_defaults(func=cmd_sample)
    sp = sub.add_parser("evaluate", help="NLL and MMD of SceneGen and baselines (Table 1)")
    add_model_args(sp)
    sp.add_argument("--data", required=True, nargs="+", metavar="CACHE",
                    help="caches of the evaluation split (NLL also per source)")
    sp.add_argument("--train-data", required=True, nargs="+", metavar="CACHE",
                    help="training caches (Procedural's KDE)")
    sp.add_argument("--num", type=int, default=64, help="conditioning scenes for MMD")
    sp.add_argument("--seed", type=int, default=0)
    sp.add_argument("--out", required=True, help="report JSON")
    sp.set_defaults(func=cmd_evaluate)
    sp = sub.add_parser("export-model", help="write a workdir's parameters as a pretrained model")
    sp.add_argument("--workdir", required=True)
    sp.add_argument("--step", type=int, help="checkpoint step (default: the latest)")
    sp.add_argument("--out", required=True, help="directory (config, parameters, manifest)")
    sp.set_defaults(func=cmd_export_model)
    sp = sub.add_parser("models", help="list the pretrained models shipped with the package")
    sp.set_defaults(func=cmd_models)
    sp = sub.add_parser(
        "compare", help="paired NLL difference of two models on the same scenes, with intervals"
    )
    sp.add_argument("--a", nargs="+", required=True,
                    help="model A's `score --actors-out` files (one per seed)")
    sp.add_argument("--b", nargs="+", required=True, help="model B's, paired with --a in order")
    sp.add_argument("--term", default="location",
                    help="class, location, box, heading, velocity or total")
    sp.add_argument("--block", type=int, default=10, help="consecutive scenes per bootstrap block")
    sp.add_argument("--samples", type=int, default=2000, help="bootstrap resamples")
    sp.add_argument("--seed", type=int, default=0)
    sp.add_argument("--out", help="optional report JSON")
    sp.set_defaults(func=cmd_compare)
    return p


COMPILE_CACHE_MAX_BYTES = 2 * 2**30


def enable_compile_cache() -> str | None:
    """Keeps compiled programs across runs in JAX's persistent compilation cache, so that a
    second `train`, `score` or `sample` of the same shapes skips XLA's compilation (about
    half of the train step's 36 s start-up on 2 CPU cores; 150-230 s on a GPU,
    bench/README.md). The directory is JAX_COMPILATION_CACHE_DIR when set, else
    $XDG_CACHE_HOME/scenegen_jax/jax (~/.cache by default), at most 2 GiB (least recently
    used entries go first); SCENEGEN_COMPILE_CACHE=off turns it off. Returns the directory.
    """
    import jax

    if os.environ.get("SCENEGEN_COMPILE_CACHE", "").lower() in ("0", "off", "false", "no"):
        return None
    if not jax.config.jax_compilation_cache_dir:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")
        jax.config.update("jax_compilation_cache_dir", os.path.join(base, "scenegen_jax", "jax"))
        jax.config.update("jax_compilation_cache_max_size", COMPILE_CACHE_MAX_BYTES)
    return jax.config.jax_compilation_cache_dir


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    if args.func in (cmd_train, cmd_score, cmd_sample, cmd_evaluate):
        enable_compile_cache()
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    for noisy in ("jax", "absl", "matplotlib", "orbax"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    try:
        args.func(args)
    except (OSError, ValueError, IndexError) as e:
        # Bad input (a file, a field, a flag): one line naming it, exit 2; -v adds the
        # traceback. Every reader raises these with the file and the field in the message.
        log = logging.getLogger("scenegen")
        log.error("%s", " ".join(str(e).split("\n")), exc_info=args.verbose)
        raise SystemExit(2) from e


if __name__ == "__main__":
    main()
