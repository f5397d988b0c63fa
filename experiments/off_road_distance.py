"""How far off the road the sampled vehicles off the drivable area stand: for each sampled
vehicle within 40 m of the ego whose centre pixel is off the drivable area (the test of
`scenegen evaluate`'s realism rows), its distance to the nearest drivable pixel of the cache's
canvas (m). Near misses at the road's edge (one pixel) would point at the raster's resolution;
metres away, at parking lots and driveways.

    .venv/bin/python experiments/off_road_distance.py --cache runs/cache_cpu_av2_val \
        --samples OUT/scenes.jsonl

(`OUT` from `scenegen sample --data` the same cache.) Without `--samples` it measures the
cache's own (real) actors; `--class` picks another class than vehicles, for example

    .venv/bin/python experiments/off_road_distance.py --cache runs/cache_cpu_av2_train \
        --class bicyclist

`distance_m_percentiles` are over the actors off the drivable area, `all_distance_m_percentiles`
over every counted actor (0 on the drivable area). `--by-order 4` also splits the share on the
drivable area by each actor's place among its scene's actors of the class in canonical order
(ascending bin of the model's grid: the order in which the model samples them), in groups of
4 (the first 4, the next 4, ...; the last group holds the rest):

    .venv/bin/python experiments/off_road_distance.py --cache runs/cache_cpu_womdjson_val \
        --samples OUT/scenes.jsonl --by-order 4

`--by-log` splits the share by the log (or file) a scene comes from, the part of its scene id
before the first `/`: the Argoverse 2 training logs differ (one parks a third of its
vehicles off the drivable area, the other two few). `scenes_without_off_drivable` and
`off_drivable_in_top_tenth` (the share of the actors off the drivable area that stand in the
tenth of the scenes with the most of them) say whether they are spread over the scenes or
stand in a few crowded ones. `off_share_before_any_off` and `off_share_after_one_off` (each
with its count of actors) split the actors within 40 m by whether an earlier one of their
scene in canonical order stands off the drivable area: a model that has put one vehicle in a
parking lot puts the next ones there too.

`--by-place` splits the counted actors by where they stand: on the drivable area and on a
lane (the lane orientation channels, as `scenegen evaluate`'s lane alignment), on the
drivable area off the lanes, off it by at most `NEAR_M` (a car at the kerb) and further off
(a lot or a driveway), with the share of each that stands still (speed at most the config's
`zero_speed`, the model's v = 0 point mass). With `--by-log` each log gets the split too: the
Argoverse 2 logs disagree on whether a parking area is drawn as drivable area.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from scipy.ndimage import distance_transform_edt

from scenegen_jax.config import Config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.eval.realism import map_canvases
from scenegen_jax.raster.map import ALL_MAP_CHANNELS, ORIENTATION_CHANNELS
from scenegen_jax.scene import CLASS_NAMES, VEHICLE, bin_index

RADIUS_M = 40.0
PERCENTILES = (25, 50, 75, 90)
NEAR_M = 3.0  # off the drivable area by at most this: at the kerb, not in a lot
PLACES = ("on_lane", "on_drivable_off_lanes", "off_drivable_near", "off_drivable_far")


def sampled_scenes(samples_path: str, cls: str):
    """(map index, [(x m, y m, speed m/s)] of the actors of class `cls`) of each scene of a
    samples JSONL."""
    with open(samples_path) as f:
        for line in f:
            scene = json.loads(line)
            yield scene["map_index"], [(a["x"], a["y"], float(np.hypot(a["vx"], a["vy"])))
                                       for a in scene["actors"] if a["class"] == cls]


def real_scenes(cache, cls: str):
    """The same for the cache's own scenes."""
    actors = cache.actors
    for i in range(len(cache)):
        sel = np.asarray(actors.valid[i]) & (np.asarray(actors.cls[i]) == CLASS_NAMES.index(cls))
        position = np.asarray(actors.position[i], np.float64)[sel]
        speed = np.linalg.norm(np.asarray(actors.velocity[i], np.float64)[sel], axis=-1)
        yield i, [(x, y, s) for (x, y), s in zip(position, speed, strict=True)]


def _grid_config(cache) -> Config:
    """A config of the cache's grid (size and resolution)."""
    return Config().replace(grid_size=int(cache.meta["grid_size"]),
                            m_per_px=float(cache.meta["m_per_px"]))


def scene_cells(cache, map_index: int, actors) -> list[tuple[float, bool] | None]:
    """For each (x, y, speed) of `actors`: its distance (m) to the nearest drivable pixel of map
    `map_index`'s canvas (0 on it) and whether it stands on a lane, or None when it is not
    counted: `RADIUS_M` or more from the ego, or off the canvas."""
    m = float(cache.meta["m_per_px"])
    canvas = next(map_canvases(cache, [map_index], _grid_config(cache)))
    road = canvas[..., ALL_MAP_CHANNELS.index("drivable_area")] >= 0.5
    lane = np.hypot(*(canvas[..., ALL_MAP_CHANNELS.index(c)] for c in ORIENTATION_CHANNELS)) > 0.5
    half = road.shape[0] * m / 2
    distance = distance_transform_edt(~road) * m
    out = []
    for x, y, _ in actors:
        row, col = int((half - y) // m), int((x + half) // m)
        counted = (np.hypot(x, y) < RADIUS_M and 0 <= row < road.shape[0]
                   and 0 <= col < road.shape[1])
        out.append((float(distance[row, col]), bool(lane[row, col])) if counted else None)
    return out


def scene_distances(cache, map_index: int, actors) -> list[float | None]:
    """The distances of `scene_cells`."""
    return [None if c is None else c[0] for c in scene_cells(cache, map_index, actors)]


def road_distances(cache, scenes) -> list[list[float | None]]:
    """`scene_distances` of each scene of `scenes`, its actors in canonical order
    (`in_canonical_order`)."""
    return [scene_distances(cache, map_index, in_canonical_order(cache, actors))
            for map_index, actors in scenes]


def counted(distances: list[float | None]) -> np.ndarray:
    """The counted distances of one scene's `road_distances`."""
    return np.array([x for x in distances if x is not None])


def in_canonical_order(cache, actors: list) -> list:
    """`actors` (x, y, speed) sorted by ascending bin of the cache's model grid
    (`scene.bin_index`: the canonical order in which the model samples them)."""
    cfg = _grid_config(cache)
    if not actors:
        return []
    key = np.asarray(bin_index(np.asarray(actors, np.float32)[:, :2], cfg.grid))
    return [actors[i] for i in np.argsort(key, kind="stable")]


def by_order(per_scene: list[list[float | None]], group: int, groups: int = 4) -> list[dict]:
    """The share on the drivable area of the counted actors at each place in canonical
    order (`road_distances`), in `groups` groups of `group` places (the last one open-ended)."""
    parts = [[] for _ in range(groups)]
    for distances in per_scene:
        for k, d in enumerate(distances):
            if d is not None:
                parts[min(k // group, groups - 1)].append(d)
    rows = []
    for g, part in enumerate(parts):
        last = "" if g == groups - 1 else g * group + group
        rows.append(
            {
                "places": f"{g * group + 1}-{last}",
                "actors": len(part),
                "on_drivable_share": round(float(np.mean(np.array(part) == 0)), 4)
                if part
                else None,
            }
        )
    return rows


def concentration(per_scene: list[np.ndarray]) -> dict:
    """How the actors off the drivable area spread over the scenes (each scene's `counted`)."""
    counts = np.array([np.sum(d > 0) for d in per_scene], int)
    top = np.sort(counts)[::-1][: max(1, len(counts) // 10)]
    return {
        "scenes_without_off_drivable": round(float(np.mean(counts == 0)), 4),
        "off_drivable_in_top_tenth": round(float(top.sum() / max(counts.sum(), 1)), 4),
    }


def cascade(per_scene: list[np.ndarray]) -> dict:
    """The share off the drivable area of the counted actors with no actor off it before them
    in their scene's canonical order, and of those with one (each scene's `counted`)."""
    after = np.concatenate(
        [np.zeros(0, bool)] + [np.cumsum(d > 0) - (d > 0) > 0 for d in per_scene]
    )
    off = np.concatenate([np.zeros(0, bool)] + [d > 0 for d in per_scene])
    return {
        f"off_share_{name}": (
            round(float(np.mean(off[sel])), 4) if np.any(sel) else None,
            int(np.sum(sel)),
        )
        for name, sel in (("before_any_off", ~after), ("after_one_off", after))
    }


def by_place(cache, scenes, still_mps: float) -> dict:
    """Of the counted actors of `scenes`, the share in each of `PLACES` and, of those, the share
    standing still (speed <= `still_mps`)."""
    count, still = np.zeros(len(PLACES)), np.zeros(len(PLACES))
    for map_index, actors in scenes:
        for cell, (_, _, speed) in zip(scene_cells(cache, map_index, actors), actors, strict=True):
            if cell is not None:
                distance, on_lane = cell
                k = (0 if on_lane else 1) if distance == 0 else (2 if distance <= NEAR_M else 3)
                count[k] += 1
                still[k] += speed <= still_mps
    total = max(count.sum(), 1)
    return {
        name: {
            "share": round(float(c / total), 4),
            "still_share": round(float(s / c), 3) if c else None,
        }
        for name, c, s in zip(PLACES, count, still, strict=True)
    }


def by_log(cache, scenes, per_scene: list[np.ndarray], still_mps: float | None) -> dict:
    """The share on the drivable area, `concentration` and `cascade` of each log's scenes, and
    their `by_place` unless `still_mps` is None."""
    logs = {}
    for scene, d in zip(scenes, per_scene, strict=True):
        logs.setdefault(cache.scene_ids[scene[0]].split("/")[0], []).append((scene, d))
    out = {}
    for log, pairs in logs.items():
        part = [d for _, d in pairs]
        every = np.concatenate(part)
        out[log] = {
            "scenes": len(part),
            "actors": len(every),
            "on_drivable_share": round(float(np.mean(every == 0)), 4) if len(every) else None,
            **concentration(part),
            **cascade(part),
        }
        if still_mps is not None:
            out[log]["by_place"] = by_place(cache, [s for s, _ in pairs], still_mps)
    return out


def percentiles(d: np.ndarray) -> dict:
    pct = np.percentile(d, PERCENTILES).round(1).tolist() if len(d) else [None] * len(PERCENTILES)
    return dict(zip(map(str, PERCENTILES), pct, strict=True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cache", required=True)
    parser.add_argument("--samples", help="sampled scenes (JSONL); default: the cache's own")
    parser.add_argument("--class", dest="cls", default=CLASS_NAMES[VEHICLE], choices=CLASS_NAMES)
    parser.add_argument(
        "--by-order",
        type=int,
        metavar="N",
        help="also the share by place in canonical order, in groups of N",
    )
    parser.add_argument(
        "--by-log",
        action="store_true",
        help="also the share by log (the scene id's part before its first /)",
    )
    parser.add_argument(
        "--by-place",
        action="store_true",
        help="also the share on a lane, on the drivable area off the lanes, off "
        f"it within {NEAR_M:g} m and further, with the share standing still",
    )
    args = parser.parse_args()
    cache = load_cache(args.cache)
    saved = Config.from_json(json.dumps(cache.meta["config"]), f"{args.cache}/meta.json")
    still_mps = float(saved.grid.zero_speed) if args.by_place else None
    scenes = list(
        sampled_scenes(args.samples, args.cls) if args.samples else real_scenes(cache, args.cls)
    )
    in_order = road_distances(cache, scenes)
    per_scene = [counted(d) for d in in_order]
    every, m = np.concatenate([np.zeros(0), *per_scene]), float(cache.meta["m_per_px"])
    d = every[every > 0]
    print(
        json.dumps(
            {
                "class": args.cls,
                "actors": len(every),
                "off_drivable": len(d),
                "on_drivable_share": round(1 - len(d) / max(len(every), 1), 4),
                "distance_m_percentiles": percentiles(d),
                "all_distance_m_percentiles": percentiles(every),
                # a neighbouring pixel, diagonals included
                "share_within_one_pixel": round(float(np.mean(d <= m * 2**0.5)), 4)
                if len(d)
                else None,
                **concentration(per_scene),
                **cascade(per_scene),
                **({"by_place": by_place(cache, scenes, still_mps)} if args.by_place else {}),
                **({"by_log": by_log(cache, scenes, per_scene, still_mps)} if args.by_log else {}),
                **({"by_order": by_order(in_order, args.by_order)} if args.by_order else {}),
            }
        )
    )


if __name__ == "__main__":
    main()
