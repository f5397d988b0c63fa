"""The `scenegen` command line: one entry point with subcommands."""

from __future__ import annotations

import argparse
import collections
import json
import logging
import os
import sys

from tqdm import tqdm

from scenegen_jax.config import PRESETS, get_config


def _overrides(pairs: list[str]) -> dict[str, str]:
    out = {}
    for pair in pairs or []:
        if "=" not in pair:
            raise SystemExit(f"override {pair!r} must look like field=value")
        k, v = pair.split("=", 1)
        out[k] = v
    return out


def cmd_prepare(args) -> None:
    from scenegen_jax.data.cache import write_cache

    cfg = get_config(args.config, **_overrides(args.set))
    if args.stride < 1:
        raise SystemExit("--stride must be >= 1")
    drops: collections.Counter = collections.Counter()
    if args.source == "av2":
        from scenegen_jax.data.av2 import read_split

        frames = read_split(args.root, args.split, drops, stride=args.stride)
    else:
        from scenegen_jax.data.scenarionet import read_scenarionet

        frames = _scenarionet_frames(read_scenarionet(args.root), drops, args.stride)
    with tqdm(desc=f"prepare {args.source}:{args.split}", unit="scene", file=sys.stderr) as bar:
        summary = write_cache(frames, args.out, cfg, drops, progress=bar)
    print(json.dumps({"out": args.out, "config": cfg.name, **summary.to_dict()}))


def _scenarionet_frames(pairs, drops: collections.Counter, stride: int):
    for i, (frame, dropped) in enumerate(pairs):
        drops.update({f"category:{k}": v for k, v in dropped.items()})
        if i % stride == 0:
            yield frame


def cmd_render(args) -> None:
    import numpy as np

    from scenegen_jax.data.cache import cached_scene, load_cache
    from scenegen_jax.raster.transform import scene_from_cached
    from scenegen_jax.viz.render import render_scene

    cache = load_cache(args.cache)
    cfg = get_config(cache.meta["config"]["name"], **_overrides(args.set))
    cache.check_config(cfg)
    indices = args.index if args.index else [0]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    for n, index in enumerate(indices):
        canvas, actors, ego = cached_scene(cache, index, cfg)
        theta = np.deg2rad(args.rotate)
        map_raster, scene, _ = scene_from_cached(canvas, actors, ego, theta, cfg)
        out = args.out if len(indices) == 1 else _numbered(args.out, n, index)
        render_scene(out, np.asarray(map_raster), cfg.map_channels, scene.actors, scene.ego, cfg,
                     title=f"{cache.scene_ids[index]}  ({int(np.sum(scene.actors.valid))} actors)")
        print(out)


def _numbered(path: str, n: int, index: int) -> str:
    root, ext = os.path.splitext(path)
    return f"{root}_{index:05d}{ext or '.png'}"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="scenegen", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    sp = sub.add_parser("prepare", help="read logs into a preprocessed cache")
    sp.add_argument("--source", choices=("av2", "scenarionet"), default="av2")
    sp.add_argument("--root", required=True, help="dataset root (av2: holds train/ and val/)")
    sp.add_argument("--split", default="train", help="av2 split folder (train, val)")
    sp.add_argument("--out", required=True, help="cache directory to write")
    sp.add_argument("--config", default="tiny", choices=sorted(PRESETS))
    sp.add_argument("--stride", type=int, default=1, help="keep every N-th frame of a log")
    sp.add_argument("--set", nargs="*", metavar="FIELD=VALUE", help="config overrides")
    sp.set_defaults(func=cmd_prepare)

    sp = sub.add_parser("render", help="render cached real scenes to PNG")
    sp.add_argument("--cache", required=True)
    sp.add_argument("--index", type=int, nargs="*", help="scene indices (default 0)")
    sp.add_argument("--out", required=True, help="PNG path (numbered when several indices)")
    sp.add_argument("--rotate", type=float, default=0.0, help="rotate about the ego, degrees")
    sp.add_argument("--set", nargs="*", metavar="FIELD=VALUE", help="config overrides")
    sp.set_defaults(func=cmd_render)
    return p


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    for noisy in ("jax", "absl", "matplotlib", "orbax"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    try:
        args.func(args)
    except (FileNotFoundError, ValueError, IndexError) as e:
        logging.getLogger("scenegen").error("%s", e)
        raise SystemExit(2) from e


if __name__ == "__main__":
    main()
