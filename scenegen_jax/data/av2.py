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
import logging
import os
from collections.abc import Iterator

import numpy as np

from scenegen_jax.data.av2_map import read_map
from scenegen_jax.frame import MAX_SIZE_M, Frame, future_positions
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE, wrap_angle
from scenegen_jax.vector_map import VectorMap

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
# Fields that are not numbers (m, rad, quaternion components), by the kind they must hold.
FIELD_KINDS = {"timestamp_ns": "integer", "track_uuid": "string", "category": "string"}
# Nominal ego footprint (Argoverse 2 vehicles), (width, length) m.
AV2_EGO_SIZE = (1.95, 4.88)
# Quaternions whose norm is further than this from 1 are not rotations.
QUATERNION_NORM_TOL = 1e-3


def list_logs(root: str, split: str) -> list[str]:
    """Sorted log directories of `root/split`; raises if there are none."""
    split_dir = os.path.join(root, split)
    if not os.path.isdir(split_dir):
        raise FileNotFoundError(f"{split_dir}: no such split directory")
    logs = sorted(p for p in glob.glob(os.path.join(split_dir, "*")) if os.path.isdir(p))
    if not logs:
        raise FileNotFoundError(f"{split_dir}: no log directories")
    return logs


def _field_kind(name: str) -> str:
    """What a field's values must be: "integer" (timestamps), "string" (ids, categories) or
    "number" (integer or floating point; nulls read as NaN and the row is dropped)."""
    return FIELD_KINDS.get(name, "number")


def read_table(path: str, columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Reads named feather columns into numpy; errors name the file and the field.

    Each column must hold its field's kind of value (`FIELD_KINDS`); timestamps and strings
    must have no nulls. A damaged file raises ValueError, never a pyarrow error.
    """
    import pyarrow as pa
    import pyarrow.feather as feather

    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: file not found")
    try:
        with open(path, "rb") as f:  # Python opens it: pyarrow refuses non-UTF-8 path bytes
            table = feather.read_table(f)
        table.validate(full=True)  # offsets and UTF-8: a damaged buffer is caught here
    except Exception as e:  # pyarrow raises several types for corrupt files
        raise ValueError(f"{path}: not a readable feather file ({e})") from e
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise ValueError(f"{path}: missing field(s) {missing}")
    out = {}
    for c in columns:
        column, kind = table.column(c), _field_kind(c)
        t = column.type.value_type if pa.types.is_dictionary(column.type) else column.type
        ok = {
            "integer": pa.types.is_integer(t),
            "string": pa.types.is_string(t) or pa.types.is_large_string(t),
            "number": pa.types.is_integer(t) or pa.types.is_floating(t),
        }[kind]
        if not ok and len(column):  # an empty table's columns may have any type
            raise ValueError(f"{path}: field {c}: expected {kind} values, got {column.type}")
        if kind != "number" and column.null_count:
            raise ValueError(f"{path}: field {c}: {column.null_count} missing values")
        try:
            out[c] = column.to_numpy(zero_copy_only=False)
        except pa.ArrowException as e:
            raise ValueError(f"{path}: field {c}: unreadable ({e})") from e
    return out


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


class DropCounter(collections.Counter):
    """Counts dropped rows by reason ("category:BOLLARD", "invalid:size", ...)."""


def _drop(
    keep: np.ndarray, bad: np.ndarray, reason: str, drops: collections.Counter, path: str
) -> np.ndarray:
    """`keep` [R] without the kept rows in `bad` [R], which are counted and logged."""
    bad = keep & bad
    if bad.any():
        drops[reason] += int(bad.sum())
        log.warning("%s: %d rows dropped (%s)", path, bad.sum(), reason)
    return keep & ~bad


def _keep_rows(ann: dict[str, np.ndarray], drops: collections.Counter, path: str) -> np.ndarray:
    """bool [R]: annotation rows to use; every other row is counted in `drops` by reason.

    Reasons: "category:<NAME>" (unmodelled), "invalid:<field>" (NaN/inf, or a size <= 0),
    "invalid:size" (length or width over MAX_SIZE_M), "invalid:quaternion" (norm not 1
    within QUATERNION_NORM_TOL), "invalid:duplicate_row" (a track's second row at a
    timestamp: the first kept row of each (track_uuid, timestamp_ns) is used).
    """
    categories = ann["category"].astype(str)
    keep = np.isin(categories, list(CATEGORY_TO_CLASS))
    for cat in np.unique(categories[~keep]):
        n = int(np.sum(categories == cat))
        drops[f"category:{cat}"] += n
        if cat not in DROPPED_CATEGORIES:
            log.warning("%s: unknown category %r in %d rows, dropped", path, cat, n)
    numeric = ("length_m", "width_m", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
    values = {f: ann[f].astype(np.float64) for f in numeric}
    for field in numeric:
        keep = _drop(keep, ~np.isfinite(values[field]), f"invalid:{field}", drops, path)
    for field in ("length_m", "width_m"):
        keep = _drop(keep, values[field] <= 0, f"invalid:{field}", drops, path)
    too_big = (values["length_m"] > MAX_SIZE_M) | (values["width_m"] > MAX_SIZE_M)
    keep = _drop(keep, too_big, "invalid:size", drops, path)
    norm = np.sqrt(sum(values[k] ** 2 for k in ("qw", "qx", "qy", "qz")))
    not_unit = ~(np.abs(norm - 1.0) <= QUATERNION_NORM_TOL)
    keep = _drop(keep, not_unit, "invalid:quaternion", drops, path)
    kept = np.flatnonzero(keep)
    pairs = np.rec.fromarrays([ann["track_uuid"].astype(str)[kept], ann["timestamp_ns"][kept]])
    first = np.zeros(len(keep), bool)
    first[kept[np.unique(pairs, return_index=True)[1]]] = True  # stable: first in file order
    return _drop(keep, ~first, "invalid:duplicate_row", drops, path)


def _read_poses(
    path: str, drops: collections.Counter
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ego poses sorted by time: timestamps [P] ns, rotations [P, 3, 3], translations [P, 3] m.

    An empty table, NaN/inf, a quaternion that is not a rotation or two different poses at
    one timestamp raise ValueError naming the file and the field (the ego pose of every sweep
    matters, so a bad one is not dropped). Copies of a pose are dropped and counted
    ("ego_pose:duplicate_row"): kept, they would bend the ego velocity's finite differences.
    """
    poses = read_table(path, POSE_COLUMNS)
    pose_t = poses["timestamp_ns"].astype(np.int64)
    if len(pose_t) == 0:
        raise ValueError(f"{path}: field timestamp_ns: no ego poses")
    order = np.argsort(pose_t, kind="stable")
    quat = np.stack([poses[k][order] for k in ("qw", "qx", "qy", "qz")], -1).astype(np.float64)
    trans = np.stack([poses[k][order] for k in ("tx_m", "ty_m", "tz_m")], -1).astype(np.float64)
    if not np.all(np.isfinite(trans)) or not np.all(np.isfinite(quat)):
        raise ValueError(f"{path}: NaN or inf in field tx_m/ty_m/tz_m or qw/qx/qy/qz")
    bad = np.abs(np.linalg.norm(quat, axis=-1) - 1.0) > QUATERNION_NORM_TOL
    if bad.any():
        raise ValueError(
            f"{path}: field qw/qx/qy/qz: {int(bad.sum())} poses are not unit quaternions"
        )
    pose_t = pose_t[order]
    same_t = np.r_[False, pose_t[1:] == pose_t[:-1]]
    if same_t.any():
        pose = np.concatenate([quat, trans], axis=-1)
        if np.any(pose[same_t] != pose[np.flatnonzero(same_t) - 1]):
            raise ValueError(f"{path}: field timestamp_ns: different ego poses at one timestamp")
        drops["ego_pose:duplicate_row"] += int(same_t.sum())
        log.warning("%s: %d rows dropped (ego_pose:duplicate_row)", path, same_t.sum())
        pose_t, quat, trans = pose_t[~same_t], quat[~same_t], trans[~same_t]
    return pose_t, quat_to_matrix(*quat.T), trans


def read_log(log_dir: str, drops: DropCounter, crop_radius_m: float = 80.0) -> Iterator[Frame]:
    """Yields one Frame per annotated timestamp of a log, in time order.

    Rows that cannot be used (see `_keep_rows`; also rows without an ego pose at their
    timestamp, "invalid:no_ego_pose"), copies of ego poses (`_read_poses`) and degenerate
    map elements (`vector_map_from_json`) are dropped, counted in `drops` and logged;
    nothing is dropped silently. A sweep whose rows are all dropped is a frame without
    actors. A log without any usable sweep (no
    annotation rows, no ego poses, or no annotated timestamp with an ego pose) raises
    ValueError naming the file and the field; so do unreadable files and missing fields.
    """
    ann_path = os.path.join(log_dir, "annotations.feather")
    pose_path = os.path.join(log_dir, "city_SE3_egovehicle.feather")
    ann = read_table(ann_path, ANNOTATION_COLUMNS)
    if len(ann["timestamp_ns"]) == 0:
        raise ValueError(f"{ann_path}: field timestamp_ns: no annotation rows")
    pose_t, pose_rot, pose_trans = _read_poses(pose_path, drops)
    city_map, map_drops = read_map(log_dir)
    log_id = os.path.basename(os.path.normpath(log_dir))

    keep = _keep_rows(ann, drops, ann_path)
    t_ns = ann["timestamp_ns"].astype(np.int64)
    pose_idx = np.clip(np.searchsorted(pose_t, t_ns), 0, len(pose_t) - 1)
    has_pose = pose_t[pose_idx] == t_ns
    if not has_pose.any():
        raise ValueError(
            f"{ann_path}: field timestamp_ns: no annotated timestamp has an ego pose in {pose_path}"
        )
    keep = _drop(keep, ~has_pose, "invalid:no_ego_pose", drops, ann_path)
    drops.update(map_drops)

    categories = ann["category"].astype(str)
    cls = np.array([CATEGORY_TO_CLASS.get(c, -1) for c in categories], np.int32)
    pos_ego = np.stack([ann["tx_m"], ann["ty_m"], ann["tz_m"]], -1).astype(np.float64)
    yaw = quat_to_yaw(*(ann[k].astype(np.float64) for k in ("qw", "qx", "qy", "qz")))
    size = np.stack([ann["width_m"], ann["length_m"]], -1).astype(np.float64)
    track = ann["track_uuid"].astype(str)

    vel_ego = _track_velocities(keep, track, t_ns, pos_ego, pose_rot[pose_idx],
                                pose_trans[pose_idx])
    # Ego velocity from its own poses.
    ego_v_city = finite_difference(pose_t * 1e-9, pose_trans)
    ego_v = np.einsum("nji,nj->ni", pose_rot, ego_v_city)[:, :2]
    times_ns, track_k, track_xyz, observed = _track_positions(keep, track, t_ns, pos_ego,
                                                              pose_rot[pose_idx],
                                                              pose_trans[pose_idx])
    times_s = (times_ns - times_ns[0]) * 1e-9
    no_pose = np.eye(3)

    for ts in np.unique(t_ns):
        rows = np.flatnonzero(keep & (t_ns == ts))
        p = int(np.searchsorted(pose_t, ts))
        if p >= len(pose_t) or pose_t[p] != ts:
            continue  # counted above as no_ego_pose
        r, t = pose_rot[p], pose_trans[p]
        city_from_ego = _city_from_ego(r, t)
        local_map = city_map.crop(t[:2], crop_radius_m)
        # City -> ego with the full 3D rotation, keeping x, y (consistent with annotations).
        ego_map = _map_to_ego(local_map, r, t)
        yield Frame(
            scene_id=f"{log_id}/{ts}",
            source=ann_path,
            cls=cls[rows],
            position=pos_ego[rows, :2],
            size=size[rows],
            heading=wrap_angle(yaw[rows]),
            velocity=vel_ego[rows],
            track_id=track[rows],
            ego_velocity=ego_v[p],
            ego_size=np.asarray(AV2_EGO_SIZE, np.float64),
            map=ego_map,
            city_from_ego=city_from_ego,
            # The tracks moved into this ego frame with its full 3D pose, as the annotations
            # are: their x, y are the ego-frame positions the future holds.
            future=future_positions(
                np.einsum("ji,ntj->nti", r, track_xyz[track_k[rows]] - t)[..., :2],
                observed[track_k[rows]], times_s, int(np.searchsorted(times_ns, ts)), no_pose),
        )


def _track_positions(keep: np.ndarray, track: np.ndarray, t_ns: np.ndarray,
                     pos_ego: np.ndarray, rot: np.ndarray, trans: np.ndarray):
    """The kept rows as tracks in the city frame: (annotation times [U] ns sorted, each row's
    track index [R], city positions [K, U, 3] m, observed [K, U])."""
    times_ns = np.unique(t_ns)
    _, k = np.unique(track, return_inverse=True)
    xyz = np.full((int(k.max()) + 1 if len(k) else 0, len(times_ns), 3), np.nan)
    rows = np.flatnonzero(keep)
    city = np.einsum("nij,nj->ni", rot[rows], pos_ego[rows]) + trans[rows]
    xyz[k[rows], np.searchsorted(times_ns, t_ns[rows])] = city
    return times_ns, k, xyz, np.isfinite(xyz).all(-1)


def _track_velocities(keep: np.ndarray, track: np.ndarray, t_ns: np.ndarray,
                      pos_ego: np.ndarray, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Ground velocity [R, 2] m/s of the kept rows in each row's ego frame: each track's
    city-frame positions (rows at ego poses rot [R, 3, 3], trans [R, 3]) differenced over
    time, turned back into the row's ego frame; 0 for the other rows."""
    pos_city = np.einsum("nij,nj->ni", rot, pos_ego) + trans
    vel_ego = np.zeros((len(t_ns), 2))
    kept_rows = np.flatnonzero(keep)
    for _, rows in _group(track[kept_rows]):
        rows = kept_rows[rows]
        rows = rows[np.argsort(t_ns[rows])]
        v_city = finite_difference(t_ns[rows] * 1e-9, pos_city[rows])
        vel_ego[rows] = np.einsum("nji,nj->ni", rot[rows], v_city)[:, :2]
    return vel_ego


def _city_from_ego(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The ego's planar pose [3, 3] in the city frame: its yaw and x, y of the 3D pose."""
    yaw_ego = float(np.arctan2(r[1, 0], r[0, 0]))
    return np.array(
        [
            [np.cos(yaw_ego), -np.sin(yaw_ego), t[0]],
            [np.sin(yaw_ego), np.cos(yaw_ego), t[1]],
            [0.0, 0.0, 1.0],
        ]
    )


def _map_to_ego(city_map: VectorMap, rot: np.ndarray, trans: np.ndarray) -> VectorMap:
    # Map points carry no z here; project the 3D inverse pose onto the ground plane.
    r2 = rot[:2, :2].T
    return city_map.transform(r2, -r2 @ trans[:2])


def _group(keys: np.ndarray):
    """(key, row indices) for each distinct key; nothing for no keys."""
    if len(keys) == 0:
        return
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    bounds = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1], True])
    for a, b in zip(bounds[:-1], bounds[1:], strict=False):
        yield sorted_keys[a], order[a:b]
