"""`scenegen sample`: new scenes on the maps and egos of cache scenes, with their files."""

from __future__ import annotations

import json
import os
import sys

from tqdm import tqdm

from scenegen_jax.cli.common import (
    add_distributed_args,
    add_model_args,
    add_temperature_arg,
    check_output,
    integer_in,
    load_model,
    location_temperature,
    part_path,
    positive_int,
    seed_int,
    start_distributed,
)
from scenegen_jax.config import Config
from scenegen_jax.files import written_whole

# Best-of-M proposals at most (the paper's ablation goes to 20): memory grows with M.
MAX_PROPOSALS = 1000


def check_temperature(value: float | None) -> None:
    """Refuses a `--location-temperature` below `SamplerOptions`' least before any work
    (None: not given)."""
    from scenegen_jax.sampling.rollout import MIN_LOCATION_TEMPERATURE

    if value is not None and value < MIN_LOCATION_TEMPERATURE:
        raise ValueError(f"--location-temperature {value:g}: must be at least "
                         f"{MIN_LOCATION_TEMPERATURE:g} (below it the draw is already the "
                         "likeliest bin, and the divided logits leave float32's range)")


def parse_caps(pairs, cfg: Config):
    """Per-class caps int32 [3] from `--cap CLASS=N ...` (default: max_actors each)."""
    import numpy as np

    from scenegen_jax.scene import CLASS_NAMES, NUM_CLASSES

    caps = np.full(NUM_CLASSES, cfg.grid.max_actors, np.int32)
    for pair in pairs or []:
        name, _, value = pair.partition("=")
        if name not in CLASS_NAMES or not value.isdigit():
            raise ValueError(f"--cap {pair!r}: expected CLASS=N with CLASS in {CLASS_NAMES}")
        caps[CLASS_NAMES.index(name)] = min(int(value), cfg.grid.max_actors)  # no more slots
    return caps


def write_sampled(out: str, scene, cache, cfg: Config, seed: int, heatmap_steps) -> dict:
    """Writes one sampled scene's PNG (and heatmaps); returns its scenes.jsonl row."""
    from scenegen_jax.sampling import STOP_REASONS, actor_records
    from scenegen_jax.viz.heatmap import render_heatmaps
    from scenegen_jax.viz.render import render_scene

    scene_id, map_id = f"sample_{scene.index:06d}", cache.scene_ids[scene.map_index]
    records = actor_records(scene.actors)
    ego = scene.ego
    title = f"{scene_id} on {map_id}  ({len(records)} actors, {scene.num_given} given)"
    render_scene(os.path.join(out, "png", f"{scene_id}.png"), scene.map_raster,
                 cfg.grid.map_channels, scene.actors, ego, cfg, title=title)
    if heatmap_steps:
        render_heatmaps(os.path.join(out, "heatmaps", f"{scene_id}.png"), scene.map_raster,
                        cfg.grid.map_channels, scene.heatmaps, scene.heatmap_cls, heatmap_steps,
                        scene.actors, ego, cfg, title=title)
    return {
        "scene": scene_id, "map_index": scene.map_index, "map_scene_id": map_id, "seed": seed,
        "num_given": scene.num_given, "stop_reason": STOP_REASONS[scene.stop_reason],
        "rejected": scene.rejected,
        "ego": {"width": float(ego.size[0]), "length": float(ego.size[1]),
                "vx": float(ego.velocity[0]), "vy": float(ego.velocity[1])},
        "actors": records,
    }


def conditioning(args, cfg: Config, cache) -> tuple[list[int], list]:
    """The cache scenes to cycle through (`--index`, checked) and the `--given` actors."""
    from scenegen_jax.sampling.export import given_from_lines

    indices = list(args.index) if args.index else list(range(len(cache)))
    for i in indices:
        if not 0 <= i < len(cache):
            raise IndexError(f"{cache.path}: --index {i} out of range [0, {len(cache)})")
    given = []
    if args.given:  # scene k is sampled beside the ego of cache scene indices[k mod len]
        scene_egos = cache.ego_size[[indices[k % len(indices)] for k in range(args.num)]]
        with open(args.given, "rb") as f:  # bytes: bad UTF-8 is named with its line
            given = given_from_lines(f, args.given, cfg, scene_egos, args.allow_overlap)
    return indices, given


def missing_folders(path: str) -> list[str]:
    """The folders of `path` (itself, then its parents) that do not exist yet: the ones
    `os.makedirs(path)` makes, innermost first."""
    out, path = [], os.path.abspath(path)
    while not os.path.lexists(path) and os.path.dirname(path) != path:
        out.append(path)
        path = os.path.dirname(path)
    return out


def remove_empty_folders(folders: list[str]) -> None:
    """Removes each of `folders` (innermost first) that is empty; keeps the others."""
    for folder in folders:
        try:
            os.rmdir(folder)
        except OSError:  # not empty (something was written), or already gone
            continue


def cmd_sample(args) -> None:
    """Samples scenes on the maps and egos of cache scenes; writes JSON lines, ScenarioNet
    pickles, PNGs and (with --heatmaps) per-step location heatmaps. With --distributed each
    process samples its share of the scenes and writes their files; process 0 then joins
    the JSON lines and indexes the ScenarioNet folder. A run that stops (an error, SIGINT,
    SIGTERM) removes the folders it made that are still empty, --out included."""
    check_temperature(args.location_temperature)
    made = missing_folders(args.out)
    check_output("--out", args.out, folder=True)  # found now, not after the sampling
    try:
        sample_into(args, made)
    except BaseException:
        remove_empty_folders(made)
        raise


def sample_into(args, made: list[str]) -> None:
    """`cmd_sample` into its checked --out; the folders it makes are put first in `made`."""
    import jax

    from scenegen_jax.backend import is_main_process, process_share, sync_processes
    from scenegen_jax.data.cache import load_cache
    from scenegen_jax.data.scenarionet import scenario_from_frame, write_dataset
    from scenegen_jax.sampling import HEATMAP_STEPS, SamplerOptions, frame_from_sample
    from scenegen_jax.sampling.batch import sample_on_cache
    from scenegen_jax.scene import CLASS_NAMES

    start_distributed(args)
    cfg, params, _, sampler = load_model(args)
    caps = parse_caps(args.cap, cfg)  # checked before any output is written
    cache = load_cache(args.data)
    cache.check_config(cfg)
    indices, given = conditioning(args, cfg, cache)
    steps = HEATMAP_STEPS if args.heatmaps else ()
    out = os.path.abspath(args.out)
    for sub_dir in ("png", "scenarionet") + (("heatmaps",) if steps else ()):
        made[:0] = missing_folders(os.path.join(out, sub_dir))
        os.makedirs(os.path.join(out, sub_dir), exist_ok=True)
    options = SamplerOptions(proposals=args.proposals, heatmap_steps=steps,
                             location_temperature=location_temperature(args, sampler))
    share, parts = process_share(args.num), jax.process_count()
    scenes = sample_on_cache(params, cfg, cache, args.num, args.seed, indices=indices,
                             given=given, caps=caps,
                             batch_size=args.batch_size, options=options, scenes=share)
    scenarios, counts = [], dict.fromkeys(CLASS_NAMES, 0)
    jsonl_path = os.path.join(out, "scenes.jsonl")
    part_of = lambda i: part_path(jsonl_path, i, parts)  # noqa: E731
    # scenes.jsonl appears when every scene's files are written: a run that stops has none.
    with (
        written_whole(jsonl_path if parts == 1 else part_of(jax.process_index())) as tmp,
        open(tmp, "w") as jsonl,
        tqdm(total=len(share), desc="sample", unit="scene", file=sys.stderr,
             disable=not is_main_process()) as bar,
    ):
        for scene in scenes:
            row = write_sampled(out, scene, cache, cfg, args.seed, steps)
            jsonl.write(json.dumps(row) + "\n")
            for r in row["actors"]:
                counts[r["class"]] += 1
            frame = frame_from_sample(scene.actors, scene.ego, row["map_scene_id"],
                                      city_from_ego=cache.city_from_ego[scene.map_index])
            scenarios.append(scenario_from_frame(frame, row["scene"]))
            bar.update(1)
        write_dataset(scenarios, os.path.join(out, "scenarionet"), index=parts == 1)
    if parts > 1:
        sync_processes(f"samples of {out} written")
        if not is_main_process():
            return
        counts = merge_sample_parts(out, [part_of(i) for i in range(parts)])
    print(json.dumps({"out": out, "scenes": args.num, "actors": counts}))


def merge_sample_parts(out: str, parts: list[str]) -> dict[str, int]:
    """Joins the processes' scenes.jsonl parts (in order) into OUT/scenes.jsonl, removes
    them, indexes OUT/scenarionet over every process's scenarios; returns the actors per
    class."""
    from scenegen_jax.data.scenarionet import index_dataset, scenario_file_name
    from scenegen_jax.scene import CLASS_NAMES

    counts, names = dict.fromkeys(CLASS_NAMES, 0), []
    with written_whole(os.path.join(out, "scenes.jsonl")) as tmp, open(tmp, "w") as jsonl:
        for part in parts:
            with open(part) as f:
                for line in f:
                    jsonl.write(line)
                    row = json.loads(line)
                    names.append(scenario_file_name({"id": row["scene"]}))
                    for r in row["actors"]:
                        counts[r["class"]] += 1
        index_dataset(os.path.join(out, "scenarionet"), names)
    for part in parts:  # merged: only now are they not needed
        os.remove(part)
    return counts


def add_parsers(sub) -> None:
    """Registers this module's subcommands."""
    sp = sub.add_parser("sample", help="sample new scenes on the maps of cache scenes")
    add_model_args(sp)
    add_distributed_args(sp, "sampling")
    sp.add_argument("--data", required=True, help="cache whose maps and egos condition the scenes")
    sp.add_argument("--num", type=positive_int, required=True, help="scenes to sample")
    sp.add_argument("--out", required=True, help="output directory")
    sp.add_argument("--proposals", type=integer_in(1, MAX_PROPOSALS + 1),
                    help="best-of-M proposals of the heading and velocity (default: the "
                    f"config's; at most {MAX_PROPOSALS})")
    sp.add_argument("--seed", type=seed_int, default=0)
    add_temperature_arg(sp)
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
    sp.add_argument("--batch-size", type=positive_int, default=8,
                    help="scenes per batch, split into concurrent calls (one per core on CPU)")
    sp.set_defaults(func=cmd_sample)
