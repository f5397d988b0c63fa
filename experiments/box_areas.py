"""Vehicle box areas (width x length, m^2) of real scenes in caches and of sampled scenes:
percentiles per source, to see whether a model gives each data set its own box sizes.

    .venv/bin/python experiments/box_areas.py --caches runs/cache_cpu_av2_train \
        runs/cache_cpu_av2_val --samples OUT/scenes.jsonl ...

(`OUT` from `scenegen sample ... --out OUT`.) Real scenes count every vehicle of the cache
whose centre lies in the region of interest, as `scenegen evaluate`'s MMD^2 does (the cache
also holds vehicles beyond it, as far as a rotation can reach; `--whole-canvas` counts those
too); sampled ones every sampled vehicle (all in the region).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.scene import CLASS_NAMES, VEHICLE, in_region

PERCENTILES = (10, 25, 50, 75, 90)


def cache_areas(path: str, whole_canvas: bool = False) -> np.ndarray:
    cache = load_cache(path)
    actors = cache.actors
    keep = np.asarray(actors.valid) & (np.asarray(actors.cls) == VEHICLE)
    if not whole_canvas:
        cfg = Config.from_json(json.dumps(cache.meta["config"]))
        keep &= in_region(np.asarray(actors.position), cfg.grid)
    size = np.asarray(actors.size)[keep]
    return size[:, 0] * size[:, 1]


def sample_areas(path: str) -> np.ndarray:
    with open(path) as f:
        rows = [json.loads(line) for line in f]
    return np.array([a["width"] * a["length"] for r in rows for a in r["actors"]
                     if a["class"] == CLASS_NAMES[VEHICLE]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--caches", nargs="*", default=[])
    parser.add_argument("--samples", nargs="*", default=[])
    parser.add_argument("--whole-canvas", action="store_true",
                        help="count the caches' vehicles beyond the region too")
    args = parser.parse_args()
    sources = [(p, cache_areas(p, args.whole_canvas)) for p in args.caches]
    sources += [(p, sample_areas(p)) for p in args.samples]
    for name, areas in sources:
        pct = np.percentile(areas, PERCENTILES).round(2).tolist()
        print(json.dumps({"source": name, "vehicles": len(areas),
                          "percentiles": dict(zip(map(str, PERCENTILES), pct, strict=True)),
                          "share_over_15_m2": round(float(np.mean(areas > 15.0)), 4)}))


if __name__ == "__main__":
    main()
