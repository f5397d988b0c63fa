"""The ScenarioNet format's shared vocabulary and field readers.

File names of a dataset directory, the top-level keys of a scenario, the track-type <-> class
and line-type <-> mark tables, and the checked readers (`_get`, `_array`, `_series`,
`_valid_mask`, `_polyline`, `_geometry`, `_int`) that the track, map and frame readers use:
each raises ValueError naming the file and the field. Imports nothing else of `scenarionet*`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE

SUMMARY_FILE = "dataset_summary.pkl"
MAPPING_FILE = "dataset_mapping.pkl"
TOP_LEVEL_KEYS = ("id", "version", "length", "tracks", "map_features", "metadata")
# `metadata.dataset` of our own exports of scenes whose data set is not known (a map's
# `dataset` ""), read back as "".
OWN_DATASET = "scenegen"

CLASS_FROM_TYPE: dict[str, int] = {
    "VEHICLE": VEHICLE,
    "PEDESTRIAN": PEDESTRIAN,
    "CYCLIST": BICYCLIST,
}
TYPE_FROM_CLASS: dict[int, str] = {v: k for k, v in CLASS_FROM_TYPE.items()}

# Argoverse 2 mark names (our Lane.left_mark / right_mark) -> ScenarioNet line types, as in
# ScenarioNet's own Argoverse 2 converter.
LINE_TYPE_FROM_MARK: dict[str, str] = {
    "DOUBLE_SOLID_YELLOW": "ROAD_LINE_SOLID_DOUBLE_YELLOW",
    "DOUBLE_SOLID_WHITE": "ROAD_LINE_SOLID_DOUBLE_WHITE",
    "SOLID_YELLOW": "ROAD_LINE_SOLID_SINGLE_YELLOW",
    "SOLID_WHITE": "ROAD_LINE_SOLID_SINGLE_WHITE",
    "DASHED_WHITE": "ROAD_LINE_BROKEN_SINGLE_WHITE",
    "DASHED_YELLOW": "ROAD_LINE_BROKEN_SINGLE_YELLOW",
    "DASH_SOLID_YELLOW": "ROAD_LINE_SOLID_DOUBLE_YELLOW",
    "DASH_SOLID_WHITE": "ROAD_LINE_SOLID_DOUBLE_WHITE",
    "DOUBLE_DASH_YELLOW": "ROAD_LINE_BROKEN_SINGLE_YELLOW",
    "DOUBLE_DASH_WHITE": "ROAD_LINE_BROKEN_SINGLE_WHITE",
    "SOLID_DASH_WHITE": "ROAD_LINE_BROKEN_SINGLE_WHITE",
    "SOLID_DASH_YELLOW": "ROAD_LINE_BROKEN_SINGLE_YELLOW",
}
# ScenarioNet line types -> the closest Argoverse 2 mark name (crossability preserved).
MARK_FROM_LINE_TYPE: dict[str, str] = {
    "ROAD_LINE_BROKEN_SINGLE_WHITE": "DASHED_WHITE",
    "ROAD_LINE_SOLID_SINGLE_WHITE": "SOLID_WHITE",
    "ROAD_LINE_SOLID_DOUBLE_WHITE": "DOUBLE_SOLID_WHITE",
    "ROAD_LINE_BROKEN_SINGLE_YELLOW": "DASHED_YELLOW",
    "ROAD_LINE_BROKEN_DOUBLE_YELLOW": "DOUBLE_DASH_YELLOW",
    "ROAD_LINE_SOLID_SINGLE_YELLOW": "SOLID_YELLOW",
    "ROAD_LINE_SOLID_DOUBLE_YELLOW": "DOUBLE_SOLID_YELLOW",
    "ROAD_LINE_PASSING_DOUBLE_YELLOW": "SOLID_DASH_YELLOW",
    "UNKNOWN_LINE": "UNKNOWN",
}


def _err(source: str, field: str, msg: str) -> ValueError:
    return ValueError(f"{source}: {field}: {msg}")


def _get(d: Any, key: str, source: str, field: str) -> Any:
    if not isinstance(d, Mapping):
        raise _err(source, field, f"expected a dict, got {type(d).__name__}")
    if key not in d:
        raise _err(source, f"{field}.{key}" if field else key, "missing")
    return d[key]


def _refuse_complex(value: Any, source: str, field: str) -> None:
    """Complex numbers would lose their imaginary part, silently, in a cast to float."""
    if np.iscomplexobj(value):
        raise _err(source, field, "complex numbers where real ones belong")


def _array(
    value: Any, source: str, field: str, ndim: int, min_cols: int = 0, dtype=np.float64
) -> np.ndarray:
    """A numeric array of `ndim` dims (at least `min_cols` columns); finiteness checked later."""
    _refuse_complex(value, source, field)
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError, OverflowError) as e:
        raise _err(source, field, f"not a numeric array ({e})") from e
    if arr.ndim != ndim or (ndim == 2 and arr.shape[1] < min_cols):
        want = f"[N, >={min_cols}]" if ndim == 2 else "[N]"
        raise _err(source, field, f"expected shape {want}, got {arr.shape}")
    return arr


def _series(value: Any, source: str, field: str) -> np.ndarray:
    """[T] float64 of a per-step scalar stored as [T] or [T, 1]."""
    _refuse_complex(value, source, field)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as e:
        raise _err(source, field, f"not a numeric array ({e})") from e
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.ndim != 1:
        raise _err(source, field, f"expected shape [N] or [N, 1], got {arr.shape}")
    return arr


def _valid_mask(value: Any, source: str, field: str) -> np.ndarray:
    """[T] bool of a `valid` array stored as bool or 0/1 numbers, [T] or [T, 1]."""
    arr = np.asarray(value)
    if arr.dtype != bool:
        arr = _series(value, source, field)
        if not np.all(np.isfinite(arr)):
            raise _err(source, field, "NaN or inf")
        return arr != 0
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.ndim != 1:
        raise _err(source, field, f"expected shape [N] or [N, 1], got {arr.shape}")
    return arr


def _polyline(value: Any, source: str, field: str, min_points: int = 1) -> np.ndarray:
    """[P, 2] float64 from a [P, 2] or [P, 3] polyline; NaN/inf or too few points raise."""
    pts = _array(value, source, field, 2, min_cols=2)[:, :2]
    if len(pts) < min_points:
        raise _err(source, field, f"needs at least {min_points} points, got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise _err(source, field, "NaN or inf coordinate")
    return pts


def _geometry(feature: Mapping, keys: Sequence[str], source: str, field: str) -> np.ndarray:
    """[P, 2] points of the first of `keys` the feature has (NaN/inf raise; P may be 0)."""
    for key in keys:
        if key in feature:
            pts = _array(feature[key], source, f"{field}.{key}", 2, min_cols=2)[:, :2]
            if not np.all(np.isfinite(pts)):
                raise _err(source, f"{field}.{key}", "NaN or inf coordinate")
            return pts
    raise _err(source, f"{field}.{keys[0]}", "missing")


def _int(value: Any, source: str, field: str) -> int:
    """An integer field: an int or an integral number (numpy's too), not a string or 91.9."""
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise _err(source, field, f"expected an integer, got {value!r}")
    try:
        out = int(value)
    except (TypeError, ValueError, OverflowError) as e:  # OverflowError: int(inf)
        raise _err(source, field, f"expected an integer, got {value!r}") from e
    if out != value:
        raise _err(source, field, f"expected an integer, got {value!r}")
    return out
