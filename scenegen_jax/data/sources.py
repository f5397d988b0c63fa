"""One entry point to read frames from any supported source (recorded in caches)."""

from __future__ import annotations

import collections
import os
from collections.abc import Iterator

from scenegen_jax.data.frame import Frame

SOURCES = ("av2", "scenarionet")


def source_spec(kind: str, root: str, split: str, stride: int) -> dict:
    """The description of a source that `read_frames` takes and caches record."""
    if kind not in SOURCES:
        raise ValueError(f"unknown source {kind!r}; choose one of {SOURCES}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    return {"kind": kind, "root": os.path.abspath(root), "split": split, "stride": stride}


def read_frames(spec: dict, drops: collections.Counter) -> Iterator[Frame]:
    """Frames of a source spec; dropped rows are counted into `drops`."""
    if spec["kind"] == "av2":
        from scenegen_jax.data.av2 import read_split

        yield from read_split(spec["root"], spec["split"], drops, stride=spec["stride"])
        return
    from scenegen_jax.data.scenarionet import read_scenarionet

    for i, (frame, dropped) in enumerate(read_scenarionet(spec["root"])):
        drops.update(dropped)
        if i % spec["stride"] == 0:
            yield frame
