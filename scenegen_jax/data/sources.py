"""One entry point to read frames from any supported source (recorded in caches).

A source is a `spec` dict: {"kind", "root", "split", "stride"}. Its unit of work is a file
(`source_files`): an Argoverse 2 log directory, an Argoverse 2 forecasting scenario folder, a
ScenarioNet pickle, a GPUDrive / Nocturne JSON scenario, or one record (one scenario) of a
Waymo Scenario TFRecord file; `read_file` turns one into frames, so that `prepare` can read
units in parallel and skip a bad one without losing the others. `stride` is in steps of the source's
10 Hz tracks: the default, 10, keeps one frame per second of every log or scenario.
"""

from __future__ import annotations

import collections
import logging
import numbers
import os
from collections.abc import Iterator

from scenegen_jax.frame import Frame, drop_beyond_limits

log = logging.getLogger(__name__)

SOURCES = ("av2", "av2_forecasting", "scenarionet", "womd", "womd_json")
DEFAULT_STRIDE = 10  # steps: one frame per second of a 10 Hz log


def source_spec(kind: str, root: str, split: str | None = None, stride: int = DEFAULT_STRIDE):
    """The description of a source that `read_frames` takes and caches record.

    `split` is a sub-folder of `root` (Argoverse 2 sensor logs and forecasting: default
    "train"; the other sources: optional, every file under `root` when None).
    """
    if kind not in SOURCES:
        raise ValueError(f"unknown source {kind!r}; choose one of {SOURCES}")
    if isinstance(stride, bool) or not isinstance(stride, numbers.Integral) or stride < 1:
        raise ValueError(f"stride must be an integer >= 1, got {stride!r}")
    if kind in ("av2", "av2_forecasting") and split is None:
        split = "train"
    return {"kind": kind, "root": os.path.abspath(root), "split": split, "stride": int(stride)}


def source_files(spec: dict) -> list[str]:
    """The units of work of a source, sorted: files, Argoverse 2 log or scenario
    directories, or Waymo TFRecord records (`womd_tfrecord.scenario_files`)."""
    if spec["kind"] == "av2":
        from scenegen_jax.data.av2 import list_logs

        return list_logs(spec["root"], spec["split"])
    root = os.path.join(spec["root"], spec["split"]) if spec.get("split") else spec["root"]
    if spec["kind"] == "av2_forecasting":
        from scenegen_jax.data.av2_forecasting import scenario_files
    elif spec["kind"] == "womd":
        from scenegen_jax.data.womd_tfrecord import scenario_files
    elif spec["kind"] == "scenarionet":
        from scenegen_jax.data.scenarionet import scenario_files
    else:
        from scenegen_jax.data.womd_json import scenario_files
    return [str(p) for p in scenario_files(root)]


def read_file(spec: dict, path: str) -> tuple[list[Frame], collections.Counter]:
    """Frames of one file of a source, and the rows and map features it dropped, by reason;
    actors beyond the physical limits of every source (`frame.drop_beyond_limits`) among
    them.

    Raises ValueError / OSError naming the file (and the field) when the file is unusable.
    """
    frames, drops = _read_source_file(spec, path)
    kept, beyond = [], collections.Counter()
    for frame in frames:
        frame, dropped = drop_beyond_limits(frame)
        beyond.update(dropped)
        kept.append(frame)
    if beyond:
        log.warning("%s: rows dropped beyond the limits of a road user: %s", path, dict(beyond))
    return kept, drops + beyond


def _read_source_file(spec: dict, path: str) -> tuple[list[Frame], collections.Counter]:
    stride = spec["stride"]
    if spec["kind"] == "av2":
        from scenegen_jax.data.av2 import read_log

        drops: collections.Counter = collections.Counter()
        frames = [f for i, f in enumerate(read_log(path, drops)) if i % stride == 0]
        return frames, drops
    if spec["kind"] == "scenarionet":
        from scenegen_jax.data.scenarionet import frames_from_scenario, read_scenario

        imported = frames_from_scenario(read_scenario(path), path, stride=stride)
        drops = collections.Counter()
        for item in imported:
            drops.update(item.dropped)
        return [item.frame for item in imported], drops
    if spec["kind"] == "av2_forecasting":
        from scenegen_jax.data import av2_forecasting as reader
    elif spec["kind"] == "womd":
        from scenegen_jax.data import womd_tfrecord as reader
    else:
        from scenegen_jax.data import womd_json as reader
    return reader.read_file(path, stride)


def read_frames(spec: dict, drops: collections.Counter) -> Iterator[Frame]:
    """Frames of every file of a source, in order; dropped rows are counted into `drops`."""
    for path in source_files(spec):
        frames, dropped = read_file(spec, path)
        drops.update(dropped)
        yield from frames
