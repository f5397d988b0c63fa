"""Argoverse 2 sensor-log reader: every annotated frame becomes a Frame in the ego frame.

Log layout (original Argoverse 2): `<log>/annotations.feather` (cuboids in the ego frame at
each 10 Hz sweep, quaternion rotation), `<log>/city_SE3_egovehicle.feather` (ego poses) and
`<log>/map/log_map_archive_*.json` (lane segments, crosswalks, drivable areas, city frame).

Velocity is over the ground: each track is moved into the city frame with the ego poses,
differentiated in time (centred differences, one-sided at track ends and gaps), then rotated
into the frame of the scene's ego.
"""

from __future__ import annotations

import collections
import glob
import json
import logging
import os
from collections.abc import Iterator

import numpy as np

from scenegen_jax.data.frame import Frame
from scenegen_jax.data.vector_map import LANE_TYPES, Lane, VectorMap
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE

log = logging.getLogger(__name__)

VEHICLE_CATEGORIES = (
    "REGULAR_VEHICLE",
    "LARGE_VEHICLE",
    "BUS",
    "BOX_TRUCK",
    "TRUCK",
    "TRUCK_CAB",
    "VEHICULAR_TRAILER",
    "SCHOOL_BUS",
    "ARTICULATED_BUS",
    "RAILED_VEHICLE",
)
CATEGORY_TO_CLASS: dict[str, int] = {
    **{c: VEHICLE for c in VEHICLE_CATEGORIES},
    "PEDESTRIAN": PEDESTRIAN,
    "BICYCLE": BICYCLIST,
    "BICYCLIST": BICYCLIST,
    "MOTORCYCLE": BICYCLIST,
    "MOTORCYCLIST": BICYCLIST,
}
# Known Argoverse 2 categories we do not model (dropped and counted by name).
DROPPED_CATEGORIES = (
    "EGO_VEHICLE",
    "BOLLARD",
    "CONSTRUCTION_CONE",
    "CONSTRUCTION_BARREL",
    "SIGN",
    "STOP_SIGN",
    "MOBILE_PEDESTRIAN_CROSSING_SIGN",
    "MESSAGE_BOARD_TRAILER",
    "TRAFFIC_LIGHT_TRAILER",
    "WHEELED_DEVICE",
    "WHEELED_RIDER",
    "WHEELCHAIR",
    "STROLLER",
    "DOG",
    "ANIMAL",
    "OFFICIAL_SIGNALER",
)
ANNOTATION_COLUMNS = (
    "timestamp_ns", "track_uuid", "category", "length_m", "width_m",
    "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m",
)  # fmt: skip
POSE_COLUMNS = ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
# Nominal ego footprint (Argoverse 2 vehicles), (width, length) m.
AV2_EGO_SIZE = (1.95, 4.88)


def list_logs(root: str, split: str) -> list[str]:
    """Sorted log directories of `root/split`; raises if there are none."""
    split_dir = os.path.join(root, split)
    if not os.path.isdir(split_dir):
        raise FileNotFoundError(f"{split_dir}: no such split directory")
    logs = sorted(p for p in glob.glob(os.path.join(split_dir, "*")) if os.path.isdir(p))
    if not logs:
        raise FileNotFoundError(f"{split_dir}: no log directories")
    return logs


def read_table(path: str, columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Reads named feather columns into numpy; errors name the file and the field."""
    import pyarrow.feather as feather

    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: file not found")
    try:
        table = feather.read_table(path)
    except Exception as e:  # pyarrow raises several types for corrupt files
        raise ValueError(f"{path}: not a readable feather file ({e})") from e
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise ValueError(f"{path}: missing field(s) {missing}")
    return {c: table.column(c).to_numpy(zero_copy_only=False) for c in columns}


def quat_to_matrix(qw, qx, qy, qz) -> np.ndarray:
    """[..., 3, 3] rotation matrices of (normalised) quaternions."""
    q = np.stack([qw, qx, qy, qz], axis=-1).astype(np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def quat_to_yaw(qw, qx, qy, qz) -> np.ndarray:
    """Yaw (rotation about +z) of quaternions, rad in (-pi, pi]."""
    return np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))


def finite_difference(t_s: np.ndarray, values: np.ndarray, max_gap_s: float = 0.25) -> np.ndarray:
    """Time derivative of one sorted track: centred inside, one-sided at ends and gaps.

    Args:
      t_s: [T] increasing times, s.
      values: [T, D] samples.
      max_gap_s: neighbours further apart than this are treated as a track break.
    Returns:
      [T, D] derivative; zeros for a track with a single sample.
    """
    n = len(t_s)
    out = np.zeros_like(values, dtype=np.float64)
    if n < 2:
        return out
    dt = np.diff(t_s)
    has_prev = np.concatenate([[False], dt <= max_gap_s])
    has_next = np.concatenate([dt <= max_gap_s, [False]])
    idx = np.arange(n)
    prev = np.where(has_prev, idx - 1, idx)
    nxt = np.where(has_next, np.minimum(idx + 1, n - 1), idx)
    span = t_s[nxt] - t_s[prev]
    ok = span > 0
    out[ok] = (values[nxt[ok]] - values[prev[ok]]) / span[ok, None]
    return out


def read_map(log_dir: str) -> VectorMap:
    """The log's vector map in the city frame."""
    paths = sorted(glob.glob(os.path.join(log_dir, "map", "log_map_archive_*.json")))
    if not paths:
        raise FileNotFoundError(
            f"{os.path.join(log_dir, 'map')}: no log_map_archive_*.json map file"
        )
    path = paths[0]
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: unreadable map JSON ({e})") from e
    return vector_map_from_json(data, path)


def _points(items, path: str, field: str) -> np.ndarray:
    try:
        pts = np.array([[p["x"], p["y"]] for p in items], np.float64)
    except (KeyError, TypeError) as e:
        raise ValueError(f"{path}: field {field}: malformed point list ({e})") from e
    if pts.ndim != 2 or len(pts) < 2 or not np.all(np.isfinite(pts)):
        raise ValueError(f"{path}: field {field}: needs >= 2 finite points")
    return pts


def vector_map_from_json(data: dict, path: str) -> VectorMap:
    """Parses an Argoverse 2 `log_map_archive` dict."""
    for key in ("lane_segments", "pedestrian_crossings", "drivable_areas"):
        if key not in data:
            raise ValueError(f"{path}: missing field {key}")
    lanes = []
    for lid, seg in data["lane_segments"].items():
        where = f"lane_segments[{lid}]"
        lane_type = str(seg.get("lane_type", "VEHICLE"))
        if lane_type not in LANE_TYPES:
            raise ValueError(f"{path}: field {where}.lane_type: unknown {lane_type!r}")
        lanes.append(
            Lane(
                id=int(seg.get("id", lid)),
                lane_type=lane_type,
                left=_points(
                    seg.get("left_lane_boundary", []), path, f"{where}.left_lane_boundary"
                ),
                right=_points(
                    seg.get("right_lane_boundary", []), path, f"{where}.right_lane_boundary"
                ),
                left_mark=str(seg.get("left_lane_mark_type", "NONE")),
                right_mark=str(seg.get("right_lane_mark_type", "NONE")),
                is_intersection=bool(seg.get("is_intersection", False)),
                successors=tuple(int(s) for s in seg.get("successors", []) or []),
                predecessors=tuple(int(s) for s in seg.get("predecessors", []) or []),
            )
        )
    crosswalks = []
    for cid, cw in data["pedestrian_crossings"].items():
        e1 = _points(cw.get("edge1", []), path, f"pedestrian_crossings[{cid}].edge1")
        e2 = _points(cw.get("edge2", []), path, f"pedestrian_crossings[{cid}].edge2")
        crosswalks.append(np.concatenate([e1, e2[::-1]], axis=0))
    areas = [
        _points(da.get("area_boundary", []), path, f"drivable_areas[{did}].area_boundary")
        for did, da in data["drivable_areas"].items()
    ]
    return VectorMap(lanes=tuple(lanes), crosswalks=tuple(crosswalks), drivable_areas=tuple(areas))


class DropCounter(collections.Counter):
    """Counts dropped rows by reason ("category:BOLLARD", "invalid:size", ...)."""


def read_log(log_dir: str, drops: DropCounter, crop_radius_m: float = 80.0) -> Iterator[Frame]:
    """Yields one Frame per annotated timestamp of a log, in time order.

    Rows of unmodelled categories and rows with NaN/inf or non-positive sizes are dropped and
    counted in `drops` (and logged); nothing is dropped silently.
    """
    ann_path = os.path.join(log_dir, "annotations.feather")
    pose_path = os.path.join(log_dir, "city_SE3_egovehicle.feather")
    ann = read_table(ann_path, ANNOTATION_COLUMNS)
    poses = read_table(pose_path, POSE_COLUMNS)
    city_map = read_map(log_dir)
    log_id = os.path.basename(os.path.normpath(log_dir))

    # Ego poses, indexed by timestamp.
    pose_t = poses["timestamp_ns"].astype(np.int64)
    order = np.argsort(pose_t)
    pose_t = pose_t[order]
    pose_rot = quat_to_matrix(*(poses[k][order] for k in ("qw", "qx", "qy", "qz")))
    pose_trans = np.stack([poses[k][order] for k in ("tx_m", "ty_m", "tz_m")], -1)
    if not np.all(np.isfinite(pose_trans)) or not np.all(np.isfinite(pose_rot)):
        raise ValueError(f"{pose_path}: NaN or inf in field tx_m/ty_m/tz_m or quaternion")

    categories = ann["category"].astype(str)
    keep = np.zeros(len(categories), bool)
    for cat in np.unique(categories):
        rows = categories == cat
        if cat in CATEGORY_TO_CLASS:
            keep |= rows
        else:
            drops[f"category:{cat}"] += int(rows.sum())
            if cat not in DROPPED_CATEGORIES:
                log.warning(
                    "%s: unknown category %r in %d rows, dropped", ann_path, cat, rows.sum()
                )
    numeric = ("length_m", "width_m", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
    for field in numeric:
        bad = keep & ~np.isfinite(ann[field].astype(np.float64))
        if bad.any():
            drops[f"invalid:{field}"] += int(bad.sum())
            log.warning("%s: field %s: %d rows with NaN/inf dropped", ann_path, field, bad.sum())
            keep &= ~bad
    for field in ("length_m", "width_m"):
        bad = keep & (ann[field] <= 0)
        if bad.any():
            drops[f"invalid:{field}"] += int(bad.sum())
            log.warning("%s: field %s: %d rows with size <= 0 dropped", ann_path, field, bad.sum())
            keep &= ~bad

    t_ns = ann["timestamp_ns"].astype(np.int64)
    pose_idx = np.searchsorted(pose_t, t_ns)
    pose_idx = np.clip(pose_idx, 0, len(pose_t) - 1)
    no_pose = keep & (pose_t[pose_idx] != t_ns)
    if no_pose.any():
        drops["invalid:no_ego_pose"] += int(no_pose.sum())
        log.warning(
            "%s: %d rows without an ego pose at their timestamp dropped", ann_path, no_pose.sum()
        )
        keep &= ~no_pose

    cls = np.array([CATEGORY_TO_CLASS.get(c, -1) for c in categories], np.int32)
    pos_ego = np.stack([ann["tx_m"], ann["ty_m"], ann["tz_m"]], -1).astype(np.float64)
    yaw = quat_to_yaw(*(ann[k].astype(np.float64) for k in ("qw", "qx", "qy", "qz")))
    size = np.stack([ann["width_m"], ann["length_m"]], -1).astype(np.float64)
    track = ann["track_uuid"].astype(str)

    # Ground velocity: city-frame tracks, finite differences, back into each row's ego frame.
    rot = pose_rot[pose_idx]
    pos_city = np.einsum("nij,nj->ni", rot, pos_ego) + pose_trans[pose_idx]
    vel_ego = np.zeros((len(t_ns), 2))
    kept_rows = np.flatnonzero(keep)
    for _, rows in _group(track[kept_rows]):
        rows = kept_rows[rows]
        rows = rows[np.argsort(t_ns[rows])]
        v_city = finite_difference(t_ns[rows] * 1e-9, pos_city[rows])
        vel_ego[rows] = np.einsum("nji,nj->ni", rot[rows], v_city)[:, :2]

    # Ego velocity from its own poses.
    ego_v_city = finite_difference(pose_t * 1e-9, pose_trans)
    ego_v = np.einsum("nji,nj->ni", pose_rot, ego_v_city)[:, :2]

    for ts in np.unique(t_ns):
        rows = np.flatnonzero(keep & (t_ns == ts))
        p = int(np.searchsorted(pose_t, ts))
        if p >= len(pose_t) or pose_t[p] != ts:
            continue  # counted above as no_ego_pose
        r, t = pose_rot[p], pose_trans[p]
        yaw_ego = float(np.arctan2(r[1, 0], r[0, 0]))
        city_from_ego = np.array(
            [
                [np.cos(yaw_ego), -np.sin(yaw_ego), t[0]],
                [np.sin(yaw_ego), np.cos(yaw_ego), t[1]],
                [0.0, 0.0, 1.0],
            ]
        )
        local_map = city_map.crop(t[:2], crop_radius_m)
        # City -> ego with the full 3D rotation, keeping x, y (consistent with annotations).
        ego_map = _map_to_ego(local_map, r, t)
        yield Frame(
            scene_id=f"{log_id}/{ts}",
            source=ann_path,
            cls=cls[rows],
            position=pos_ego[rows, :2],
            size=size[rows],
            heading=np.mod(yaw[rows], 2 * np.pi),
            velocity=vel_ego[rows],
            track_id=track[rows],
            ego_velocity=ego_v[p],
            ego_size=np.asarray(AV2_EGO_SIZE, np.float64),
            map=ego_map,
            city_from_ego=city_from_ego,
        )


def _map_to_ego(city_map: VectorMap, rot: np.ndarray, trans: np.ndarray) -> VectorMap:
    # Map points carry no z here; project the 3D inverse pose onto the ground plane.
    r2 = rot[:2, :2].T
    return city_map.transform(r2, -r2 @ trans[:2])


def _group(keys: np.ndarray):
    """(key, row indices) for each distinct key."""
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    bounds = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1], True])
    for a, b in zip(bounds[:-1], bounds[1:], strict=False):
        yield sorted_keys[a], order[a:b]


def read_split(root: str, split: str, drops: DropCounter, stride: int = 1) -> Iterator[Frame]:
    """Frames of every log of a split (every `stride`-th frame of each log)."""
    for log_dir in list_logs(root, split):
        for i, frame in enumerate(read_log(log_dir, drops)):
            if i % stride == 0:
                yield frame
