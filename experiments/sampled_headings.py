"""Where sampled vehicles point, by heading bin: what lies behind a heading MMD that is worse
than the baselines' although the vehicles on lanes are aligned with them.

`scenegen evaluate`'s protocol on `--num` scenes spread over the caches (the same conditioning
scenes, baselines and SceneGen samples at the model's temperature): for the real scenes and each
method, the mean of the per-scene heading histograms over vehicles (`eval.mmd`'s 16 bins of
22.5 degrees relative to the ego; bin 0 = the ego's direction, 8 = oncoming), then, for the
vehicles within 40 m in each bin, their share, the share standing on a lane and the share on
the drivable area (as `eval.realism`); and for the vehicles within 40 m off every lane, the
share parallel to the nearest lane (its axis within 20 degrees of theirs: either direction) and
the share perpendicular to it (more than 70 degrees; `nearest_lane` channels). One JSON line.

  .venv/bin/python experiments/sampled_headings.py --pretrained cpu-av2-womd \
      --data runs/cache_cpu_womdjson_val runs/cache_cpu_womdpkl_val \
      --train-data runs/cache_cpu_womdjson_train runs/cache_cpu_womdpkl_train --num 64
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from scenegen_jax.cli.common import add_model_args, load_model, location_temperature
from scenegen_jax.data.union import load_union
from scenegen_jax.eval import evaluate as ev
from scenegen_jax.eval.mmd import HEADING_BINS, HEADING_WIDTH, scene_histograms
from scenegen_jax.eval.realism import map_canvases, vehicle_cells
from scenegen_jax.sampling import SamplerOptions

RADIUS_M = 40.0


def bin_table(canvases, scenes, cfg) -> dict:
    """Per heading bin: share of the vehicles within RADIUS_M, and of those the share on a
    lane and on the drivable area."""
    bins, lane, drivable = [], [], []
    for canvas, actors in zip(canvases, scenes, strict=True):
        cells = vehicle_cells(canvas, actors, cfg, RADIUS_M)
        rel = np.mod(np.asarray(actors.heading, np.float64)[cells.slots] + 0.5 * HEADING_WIDTH,
                     2 * np.pi)
        bins.append(np.minimum((rel // HEADING_WIDTH).astype(int), HEADING_BINS - 1))
        lane.append(cells.on_lane)
        drivable.append(cells.on_drivable)
    bins, lane, drivable = (np.concatenate(x) for x in (bins, lane, drivable))
    out = {"vehicles": len(bins)}
    for b in range(HEADING_BINS):
        m = bins == b
        out[str(b)] = [round(float(m.mean()), 3), round(float(lane[m].mean()), 2) if m.any()
                       else None, round(float(drivable[m].mean()), 2) if m.any() else None]
    return out


def off_lane_axes(canvases, scenes, cfg) -> dict:
    """Of the vehicles within RADIUS_M off every lane and in range of the nearest lane: their
    number, the share parallel to the nearest lane (axes within 20 degrees) and the share
    perpendicular (more than 70 degrees)."""
    axis = []
    for canvas, actors in zip(canvases, scenes, strict=True):
        cells = vehicle_cells(canvas, actors, cfg, RADIUS_M)
        off = ~cells.on_lane & np.isfinite(cells.nearest_direction)
        heading = np.asarray(actors.heading, np.float64)[cells.slots[off]]
        diff = np.degrees(np.abs(np.angle(np.exp(1j * (heading - cells.nearest_direction[off])))))
        axis.append(np.minimum(diff, 180.0 - diff))
    axis = np.concatenate(axis)
    share = (lambda m: round(float(m.mean()), 3)) if len(axis) else (lambda m: None)
    return {"vehicles": len(axis), "parallel": share(axis < 20.0),
            "perpendicular": share(axis > 70.0)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_model_args(p)
    p.add_argument("--data", required=True, nargs="+")
    p.add_argument("--train-data", required=True, nargs="+")
    p.add_argument("--num", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--location-temperature", type=float)
    args = p.parse_args()
    cfg, params, step, sampler = load_model(args)
    cache, train = load_union(args.data, cfg), load_union(args.train_data, cfg)
    indices = np.linspace(0, len(cache) - 1, min(args.num, len(cache))).astype(int)
    maps, scenes = ev.real_scenes(cache, indices, cfg)
    methods = ev.sample_baselines(cfg, cache, indices, train, args.seed)
    options = SamplerOptions(location_temperature=location_temperature(args, sampler))
    methods["SceneGen"] = ev.sample_scenegen(params, cfg, maps, scenes, args.seed,
                                             options=options)
    methods = {"real": [s.actors for s in scenes], **methods}
    canvases = list(map_canvases(cache, indices, cfg))
    report = {"step": step, "data": args.data, "columns": "share, on lane, on drivable"}
    for name, sets in methods.items():
        hist = scene_histograms(sets, "vehicle", cfg.grid.region_m)["heading"].mean(0)
        report[name] = {"mean_histogram": [round(float(x), 3) for x in hist],
                        "bins": bin_table(canvases, sets, cfg),
                        "off_lane": off_lane_axes(canvases, sets, cfg)}
    print(json.dumps(report))


if __name__ == "__main__":
    main()
