"""A large cache made of real scenes repeated, for measuring what grows with a cache's size
(memory of `train`, disk): a source's frames written over and over, each repetition moved
10 km further east in the world frame so that its map elements are stored anew, as another
city's would be, and its scene ids suffixed with `#<repetition>`.

    .venv/bin/python bench/repeated_cache.py --source womd_json \
        --root ../shared/data/womd_mini/gpudrive_json --split train --config cpu \
        --frames 20000 --out /tmp/womd_20k
    /usr/bin/time -f "%M KB" .venv/bin/scenegen train --config cpu --data /tmp/womd_20k \
        --workdir /tmp/w20k --steps 20

Nothing it writes belongs in the repository: the scenes are the data set's.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import itertools
import json
import sys

import numpy as np
from tqdm import tqdm

from scenegen_jax.config import get_config
from scenegen_jax.data.cache_write import CacheWriter, encode_frame
from scenegen_jax.data.sources import SOURCES, read_frames, source_spec

SHIFT_M = 10_000.0  # world-frame offset between repetitions


def moved(frame, repetition: int):
    """The frame of `repetition`: its world pose moved SHIFT_M m east per repetition."""
    pose = np.array(frame.city_from_ego, np.float64)
    pose[0, 2] += repetition * SHIFT_M
    return dataclasses.replace(frame, scene_id=f"{frame.scene_id}#{repetition}",
                               city_from_ego=pose)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", choices=SOURCES, required=True)
    p.add_argument("--root", required=True)
    p.add_argument("--split")
    p.add_argument("--config", default="cpu")
    p.add_argument("--frames", type=int, required=True, help="frames to write")
    p.add_argument("--out", required=True)
    args = p.parse_args()
    cfg = get_config(args.config)
    spec = source_spec(args.source, args.root, args.split)
    drops = collections.Counter()
    frames = list(read_frames(spec, drops))
    if not frames:
        sys.exit(f"{args.root}: no frames")
    stream = (moved(f, k) for k in itertools.count() for f in frames)
    with CacheWriter(args.out, cfg, {**spec, "repeated_to": args.frames}) as writer:
        for frame in tqdm(itertools.islice(stream, args.frames), total=args.frames,
                          desc="write", unit="frame", file=sys.stderr):
            writer.add(encode_frame(frame, cfg))
        summary = writer.close(drops)
    print(json.dumps({"out": args.out, "scenes": summary.scenes, "read": len(frames)}))


if __name__ == "__main__":
    main()
