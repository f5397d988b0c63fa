"""ScenarioNet tracks and timing: per-track state arrays, the SDC, time stamps, the steps
to import and the velocity-mismatch quirk.

Tracks are read whatever their converter: per-step arrays as [T] or [T, 1], box sizes as
`length` / `width` or `size` [T, 3], `valid` as bool or 0/1 floats, the SDC by `sdc_id` or
`sdc_track_index`, time stamps from `metadata.ts` or a top-level `ts`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from scenegen_jax.data.scenarionet_schema import (
    CLASS_FROM_TYPE,
    _array,
    _err,
    _get,
    _int,
    _series,
    _valid_mask,
)

DEFAULT_STEP_S = 0.1  # when a file has no usable `ts`
MOVING_MPS = 2.0
VELOCITY_MISMATCH_REL_ERR = 0.3
MIN_MOVING_SAMPLES = 10


class _Track(NamedTuple):
    """One track's state arrays (world frame), validated for shape."""

    type: str
    position: np.ndarray  # [T, 2] m
    width: np.ndarray  # [T] m
    length: np.ndarray  # [T] m
    heading: np.ndarray  # [T] rad
    velocity: np.ndarray  # [T, 2] m/s
    valid: np.ndarray  # [T] bool


def _read_track(tid: str, track: Any, length: int, source: str) -> _Track:
    field = f"tracks[{tid!r}]"
    ttype = track.get("type") if isinstance(track, Mapping) else None
    if not isinstance(ttype, str):
        meta = track.get("metadata") if isinstance(track, Mapping) else None
        ttype = meta.get("type") if isinstance(meta, Mapping) else None
    if not isinstance(ttype, str):
        raise _err(source, f"{field}.type", "missing or not a string")
    state = _get(track, "state", source, field)
    sf = f"{field}.state"
    position = _array(_get(state, "position", source, sf), source, f"{sf}.position", 2, 2)[:, :2]
    if "length" in state and "width" in state:
        lengths = _series(state["length"], source, f"{sf}.length")
        widths = _series(state["width"], source, f"{sf}.width")
    elif "size" in state:  # MetaDrive's older Waymo pickles: size [T, 3] = (length, width, height)
        size = _array(state["size"], source, f"{sf}.size", 2, 2)
        lengths, widths = size[:, 0], size[:, 1]
    else:
        raise _err(source, f"{sf}.length", "missing (and no size)")
    heading = _series(_get(state, "heading", source, sf), source, f"{sf}.heading")
    velocity = _array(_get(state, "velocity", source, sf), source, f"{sf}.velocity", 2, 2)[:, :2]
    valid = _valid_mask(_get(state, "valid", source, sf), source, f"{sf}.valid")
    arrays = dict(
        position=position,
        width=widths,
        length=lengths,
        heading=heading,
        velocity=velocity,
        valid=valid,
    )
    for name, arr in arrays.items():
        if len(arr) != length:
            raise _err(source, f"{sf}.{name}", f"has {len(arr)} steps, scenario length is {length}")
    return _Track(type=ttype, **arrays)


def _finite_at(tr: _Track, t: int) -> str | None:
    """The first state field with NaN/inf at step t, or None."""
    for name in ("position", "heading", "velocity", "width", "length"):
        if not np.all(np.isfinite(getattr(tr, name)[t])):
            return name
    return None


def _find_sdc(scenario: Mapping, meta: Mapping, tracks: Mapping, source: str) -> str:
    """The SDC's key in `tracks` (as a str): `metadata.sdc_id`, else a `sdc_track_index` (top
    level, then in metadata) that names a track, else one that indexes `tracks` in order."""
    if "sdc_id" in meta:
        sdc_id = str(meta["sdc_id"])
        if sdc_id not in tracks:
            raise _err(source, "metadata.sdc_id", f"{sdc_id!r} is not a key of tracks")
        return sdc_id
    for where, holder in (("sdc_track_index", scenario), ("metadata.sdc_track_index", meta)):
        if "sdc_track_index" not in holder:
            continue
        value = holder["sdc_track_index"]
        if isinstance(value, (bool, np.bool_)):  # an int to isinstance, never an index here
            raise _err(source, where, f"expected a track id or index, got {value!r}")
        if str(value) in tracks:
            return str(value)
        if isinstance(value, (int, np.integer)) and 0 <= int(value) < len(tracks):
            return list(tracks)[int(value)]
        raise _err(source, where, f"{value!r} names no track and is no index into tracks")
    raise _err(source, "metadata.sdc_id", "missing (and no sdc_track_index)")


def _timestamps(scenario: Mapping) -> np.ndarray | None:
    """The file's time stamps (s) from `metadata.ts` or a top-level `ts`, if readable."""
    meta = scenario.get("metadata")
    ts = meta.get("ts") if isinstance(meta, Mapping) else None
    if ts is None:
        ts = scenario.get("ts")
    if ts is None:
        return None
    try:
        arr = np.asarray(ts, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int beyond float
        return None
    return arr if len(arr) >= 2 and np.all(np.isfinite(arr)) else None


def scenario_sample_rate_hz(scenario: Mapping) -> float | None:
    """Sample rate (Hz) of a scenario: 1 / the median step of `metadata.ts` or a top-level
    `ts`; None when the file has no usable time stamps."""
    if not isinstance(scenario, Mapping):
        return None
    ts = _timestamps(scenario)
    if ts is None:
        return None
    step = float(np.median(np.diff(ts)))
    return 1.0 / step if step > 0 else None


def _step_times(scenario: Mapping, length: int) -> np.ndarray:
    """[length] time (s) of each step: the file's `ts` when it has one entry per step and
    increases; else steps of its median interval, or of DEFAULT_STEP_S."""
    ts = _timestamps(scenario)
    if ts is not None and len(ts) == length and np.all(np.diff(ts) > 0):
        return ts
    rate = scenario_sample_rate_hz(scenario)
    step = 1.0 / rate if rate else DEFAULT_STEP_S
    return np.arange(length) * step


def velocity_mismatch(tracks: Sequence[_Track], times: np.ndarray) -> bool:
    """Whether a file's velocities disagree with its positions.

    Centred finite differences of the positions over valid steps (with the steps' times) are
    compared with the stored velocities of actors of our classes moving faster than
    MOVING_MPS: a mismatch when the median relative error exceeds VELOCITY_MISMATCH_REL_ERR
    (with at least MIN_MOVING_SAMPLES such samples). nuScenes' early converter writes zero
    velocities, for example.
    """
    rel = []
    dt = (times[2:] - times[:-2])[:, None]
    for tr in tracks:
        if tr.type not in CLASS_FROM_TYPE or len(tr.valid) < 3:
            continue
        both = tr.valid[2:] & tr.valid[:-2] & tr.valid[1:-1]
        if not both.any():
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            fd = (tr.position[2:] - tr.position[:-2]) / dt
        speed = np.linalg.norm(fd, axis=1)
        v = tr.velocity[1:-1]
        ok = both & np.isfinite(speed) & (speed > MOVING_MPS) & np.all(np.isfinite(v), axis=1)
        rel.append(np.linalg.norm(v[ok] - fd[ok], axis=1) / speed[ok])
    err = np.concatenate(rel) if rel else np.zeros(0)
    return len(err) >= MIN_MOVING_SAMPLES and float(np.median(err)) > VELOCITY_MISMATCH_REL_ERR


def _steps(
    time_index: int | Sequence[int] | None,
    all_steps: bool,
    stride: int | None,
    sdc: _Track,
    meta: Mapping,
    length: int,
    source: str,
) -> list[int]:
    if stride is not None:
        if all_steps or time_index is not None:
            raise _err(source, "stride", "give only one of time_index, all_steps and stride")
        if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
            raise _err(source, "stride", f"expected a positive integer, got {stride!r}")
        steps = [t for t in range(0, length, int(stride)) if sdc.valid[t]]
    elif all_steps:
        steps = [int(t) for t in np.flatnonzero(sdc.valid)]
    elif time_index is None:
        steps = [_int(meta.get("current_time_index", 0), source, "metadata.current_time_index")]
    elif isinstance(time_index, (int, np.integer)):
        steps = [int(time_index)]
    else:
        steps = [_int(t, source, "time_index") for t in time_index]
    for t in steps:
        if not 0 <= t < length:
            raise _err(source, "time_index", f"{t} outside [0, {length})")
    return steps
