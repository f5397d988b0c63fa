"""`scenegen prepare` and `scenegen render`: logs into caches, cached scenes into PNGs."""

from __future__ import annotations

import json
import logging
import math
import os
import sys

from tqdm import tqdm

from scenegen_jax.cli.common import finite_float, overrides
from scenegen_jax.config import PRESETS, Config, apply_overrides, get_config
from scenegen_jax.data.sources import DEFAULT_STRIDE, SOURCES


def cmd_prepare(args) -> None:
    from scenegen_jax.data.prepare import prepare
    from scenegen_jax.data.sources import source_spec

    cfg = get_config(args.config, **overrides(args.set))
    spec = source_spec(args.source, args.root, args.split, args.stride)
    shard = parse_shard(args.shard) if args.shard else None
    if os.path.isfile(os.path.join(args.out, "meta.json")):
        logging.getLogger("scenegen").warning("%s: a cache is there; it is replaced", args.out)
    with tqdm(desc=f"prepare {args.source}", unit="file", file=sys.stderr) as bar:
        summary, rate = prepare(
            spec, args.out, cfg, workers=args.workers, strict=args.strict, progress=bar,
            shard=shard,
        )
    out = {"out": args.out, "config": cfg.name, "scenes_per_s": round(rate, 2)}
    if shard:
        out["shard"] = list(shard)
    print(json.dumps({**out, **summary.to_dict()}))


def parse_shard(text: str) -> tuple[int, int]:
    """(I, N) of `--shard I/N`."""
    index, _, count = text.partition("/")
    if not (index.isdigit() and count.isdigit()) or not 0 <= int(index) < int(count):
        raise ValueError(f"--shard {text!r}: expected I/N with 0 <= I < N, e.g. 0/8")
    return int(index), int(count)


def _image_path(path: str) -> str:
    """The file `render_scene` writes for `path`: a name without an extension gets `.png`
    (`viz.render.save_figure`), and the command prints the file it wrote."""
    return path if os.path.splitext(path)[1] else path + ".png"


def _numbered(path: str, n: int, index: int) -> str:
    root, ext = os.path.splitext(path)
    return f"{root}_{index:05d}{ext or '.png'}"


def rotation_rad(degrees: float) -> float:
    """`--rotate` degrees as radians in [-pi, pi]: reduced modulo 360 first (exactly, for any
    finite angle), so an angle like 1e300 degrees turns the scene rather than becoming a
    float32 angle whose sine and cosine are NaN."""
    return math.radians(math.remainder(degrees, 360.0))


def cmd_render(args) -> None:
    import numpy as np

    from scenegen_jax.data.cache import load_cache
    from scenegen_jax.likelihood.batch import grid_scene
    from scenegen_jax.viz.render import render_scene

    cache = load_cache(args.cache)
    saved = Config.from_json(json.dumps(cache.meta["config"]), f"{args.cache}/meta.json")
    cfg = apply_overrides(saved, **overrides(args.set))
    cache.check_config(cfg)
    indices = args.index if args.index else [0]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    theta = rotation_rad(args.rotate)
    for n, index in enumerate(indices):
        map_raster, scene = grid_scene(cache, index, cfg.grid, theta)
        out = _image_path(args.out) if len(indices) == 1 else _numbered(args.out, n, index)
        render_scene(
            out,
            np.asarray(map_raster),
            cfg.grid.map_channels,
            scene.actors,
            scene.ego,
            cfg,
            title=f"{cache.scene_ids[index]}  ({int(np.sum(scene.actors.valid))} actors)",
        )
        print(out)


def add_parsers(sub) -> None:
    """Registers this module's subcommands."""
    sp = sub.add_parser("prepare", help="read logs into a preprocessed cache")
    sp.add_argument("--source", choices=SOURCES, default="av2",
                    help="av2: Argoverse 2 sensor logs; av2_forecasting: Argoverse 2 motion-"
                    "forecasting scenarios; womd: Waymo Scenario TFRecords; scenarionet: "
                    "ScenarioNet pickles; womd_json: Waymo scenes as GPUDrive / Nocturne JSON")
    sp.add_argument("--root", required=True,
                    help="dataset root (av2, av2_forecasting: holds train/ and val/)")
    sp.add_argument("--split", help="sub-folder of --root (av2, av2_forecasting: default "
                    "train; others: all files under --root when not given)")
    sp.add_argument("--out", required=True, help="cache directory to write")
    sp.add_argument("--config", default="tiny", choices=sorted(PRESETS))
    sp.add_argument("--stride", type=int, default=DEFAULT_STRIDE,
                    help="keep every N-th step of a log or scenario (10 Hz: default 10, one "
                    "frame per second)")
    sp.add_argument("--workers", type=int, help="processes (default: one per core)")
    sp.add_argument("--shard", metavar="I/N",
                    help="prepare only part I of N of the files, into OUT/shard-0000I-of-0000N/ "
                    "(N jobs, e.g. a SLURM array, make one cache that every command reads)")
    sp.add_argument("--strict", action="store_true",
                    help="stop at the first unusable file instead of skipping and counting it")
    sp.add_argument("--set", nargs="*", metavar="FIELD=VALUE", help="config overrides")
    sp.set_defaults(func=cmd_prepare)

    sp = sub.add_parser("render", help="render cached real scenes to PNG")
    sp.add_argument("--cache", required=True)
    sp.add_argument("--index", type=int, nargs="*", help="scene indices (default 0)")
    sp.add_argument("--out", required=True, help="PNG path (numbered when several indices)")
    sp.add_argument("--rotate", type=finite_float, default=0.0,
                    help="rotate about the ego, degrees")
    sp.add_argument("--set", nargs="*", metavar="FIELD=VALUE", help="config overrides")
    sp.set_defaults(func=cmd_render)
