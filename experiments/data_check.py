"""Sanity figures of prepared caches of real scenes, per cache and over all of them.

For each cache: the share of vehicle centres within 40 m of the ego on the `drivable` raster
(all, moving and standing vehicles), the median vehicle length, and the scenarios whose
moving vehicles' median heading-to-velocity angle is 5 degrees or more.

  .venv/bin/python experiments/data_check.py --config cpu --cache runs/cache_cpu_av2_train \
      runs/cache_cpu_av2_val --out experiments/results/data_check_av2.json
"""

from __future__ import annotations

import argparse
import json

from scenegen_jax.config import get_config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.eval.realism import real_data_check


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--cache", nargs="+", required=True)
    p.add_argument("--config", default="cpu")
    p.add_argument("--out")
    args = p.parse_args()
    cfg = get_config(args.config)
    report, on, total = {}, 0.0, 0
    for path in args.cache:
        cache = load_cache(path)
        cache.check_config(cfg)
        r = real_data_check(cache, cfg)
        angles = r.pop("heading_velocity_deg")
        r["scenarios_heading_velocity_ge_5deg"] = {
            k: v for k, v in angles.items() if v[0] >= 5.0
        }
        r["scenarios_with_moving_vehicles"] = len(angles)
        report[path] = r
        on += r["drivable_share"] * r["vehicles_within_40m"]
        total += r["vehicles_within_40m"]
    report["all"] = {"drivable_share": on / max(total, 1), "vehicles_within_40m": total}
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
