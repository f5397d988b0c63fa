"""How far off the road the sampled vehicles off the drivable area stand: for each sampled
vehicle within 40 m of the ego whose centre pixel is off the drivable area (the test of
`scenegen evaluate`'s realism rows), its distance to the nearest drivable pixel of the cache's
canvas (m). Near misses at the road's edge (one pixel) would point at the raster's resolution;
metres away, at parking lots and driveways.

    .venv/bin/python experiments/off_road_distance.py --cache runs/cache_cpu_av2_val \
        --samples OUT/scenes.jsonl

(`OUT` from `scenegen sample --data` the same cache.)
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from scipy.ndimage import distance_transform_edt

from scenegen_jax.data.cache import load_cache
from scenegen_jax.raster.map import ALL_MAP_CHANNELS
from scenegen_jax.scene import CLASS_NAMES, VEHICLE

RADIUS_M = 40.0
PERCENTILES = (25, 50, 75, 90)


def off_road_distances(cache_path: str, samples_path: str) -> tuple[int, np.ndarray, float]:
    """(vehicles within `RADIUS_M` on the canvas, distances (m) of those off the drivable
    area to its nearest pixel, the canvas's m per pixel)."""
    cache = load_cache(cache_path)
    m = float(cache.meta["m_per_px"])
    drivable = ALL_MAP_CHANNELS.index("drivable_area")
    counted, out = 0, []
    with open(samples_path) as f:
        for line in f:
            scene = json.loads(line)
            road = np.asarray(cache.maps[scene["map_index"]][..., drivable]) >= 0.5
            half = road.shape[0] * m / 2
            distance = distance_transform_edt(~road) * m
            for a in scene["actors"]:
                if a["class"] != CLASS_NAMES[VEHICLE] or np.hypot(a["x"], a["y"]) >= RADIUS_M:
                    continue
                row, col = int((half - a["y"]) // m), int((a["x"] + half) // m)
                if 0 <= row < road.shape[0] and 0 <= col < road.shape[1]:
                    counted += 1
                    if not road[row, col]:
                        out.append(distance[row, col])
    return counted, np.array(out), m


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cache", required=True)
    parser.add_argument("--samples", required=True)
    args = parser.parse_args()
    counted, d, m = off_road_distances(args.cache, args.samples)
    pct = np.percentile(d, PERCENTILES).round(1).tolist() if len(d) else [None] * 4
    print(json.dumps({"vehicles": counted, "off_drivable": len(d),
                      "on_drivable_share": round(1 - len(d) / max(counted, 1), 4),
                      "distance_m_percentiles": dict(zip(map(str, PERCENTILES), pct, strict=True)),
                      # a neighbouring pixel, diagonals included
                      "share_within_one_pixel": round(float(np.mean(d <= m * 2**0.5)), 4)
                      if len(d) else None}))


if __name__ == "__main__":
    main()
