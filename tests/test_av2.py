"""Argoverse 2 reader and `prepare` on the real logs, and its handling of bad input."""

from __future__ import annotations

import collections
import glob
import json
import os
import re
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
import shapely

from scenegen_jax.cli import main as cli_main
from scenegen_jax.config import get_config
from scenegen_jax.data.av2 import CATEGORY_TO_CLASS, read_log
from scenegen_jax.data.av2_map import vector_map_from_json
from scenegen_jax.data.prepare import prepare
from scenegen_jax.data.sources import source_spec
from scenegen_jax.raster.map import ALL_MAP_CHANNELS, rasterize_map
from scenegen_jax.scene import CLASS_NAMES, PEDESTRIAN, VEHICLE


def _direct_counts(data_root: str, split: str):
    """(frames, rows per class) straight from the feather files."""
    frames, counts = 0, collections.Counter()
    for path in sorted(glob.glob(os.path.join(data_root, split, "*", "annotations.feather"))):
        table = feather.read_table(path, columns=["timestamp_ns", "category"])
        frames += len(set(table.column("timestamp_ns").to_pylist()))
        for cat in table.column("category").to_pylist():
            if cat in CATEGORY_TO_CLASS:
                counts[CLASS_NAMES[CATEGORY_TO_CLASS[cat]]] += 1
    return frames, counts


def test_prepare_counts_match_feather(data_root, tmp_path, capsys):
    cli_main(
        [
            "prepare",
            "--root",
            data_root,
            "--split",
            "train",
            "--out",
            str(tmp_path / "c"),
            "--config",
            "tiny",
            "--stride",
            "1",
        ]
    )
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    frames, counts = _direct_counts(data_root, "train")
    assert summary["scenes"] == frames == 468
    for name in CLASS_NAMES:
        assert summary["actors"][name] + summary["outside_region"][name] == counts[name]
    assert summary["actors"]["vehicle"] > 1000
    assert summary["dropped"]["category:BOLLARD"] > 0
    assert summary["dropped"]["category:EGO_VEHICLE"] == 156


def test_heading_agrees_with_velocity_for_moving_vehicles(all_frames):
    by_log = collections.defaultdict(list)
    for split in ("train", "val"):
        for f in all_frames[split][0]:
            m = (f.cls == VEHICLE) & (np.linalg.norm(f.velocity, axis=1) > 2.0)
            direction = np.arctan2(f.velocity[m, 1], f.velocity[m, 0])
            diff = np.angle(np.exp(1j * (direction - f.heading[m])))
            by_log[f.scene_id.split("/")[0]].extend(np.abs(np.degrees(diff)))
    assert len(by_log) == 4
    for log_id, angles in by_log.items():
        assert len(angles) > 100, log_id
        assert np.median(angles) < 5.0, (log_id, np.median(angles))


def test_vehicle_lengths_and_pedestrians(all_frames):
    frames = all_frames["train"][0] + all_frames["val"][0]
    lengths = np.concatenate([f.size[f.cls == VEHICLE, 1] for f in frames])
    assert 3.5 < np.median(lengths) < 6.0
    ped_speed = np.concatenate(
        [np.linalg.norm(f.velocity[f.cls == PEDESTRIAN], axis=1) for f in frames]
    )
    assert np.median(ped_speed) < 2.5  # walking pace, not the ego's speed


def test_vehicles_lie_on_drivable_area(all_frames):
    size, res = 320, 0.25
    ch = ALL_MAP_CHANNELS.index("drivable_area")
    inside = total = 0
    for split in ("train", "val"):
        for f in all_frames[split][0][::20]:
            raster = rasterize_map(f.map, size, res)[..., ch]
            pos = f.position[(f.cls == VEHICLE) & (np.linalg.norm(f.position, axis=1) < 40)]
            col = np.floor((pos[:, 0] + 40) / res).astype(int)
            row = np.floor((40 - pos[:, 1]) / res).astype(int)
            ok = (row >= 0) & (row < size) & (col >= 0) & (col < size)
            inside += int(raster[row[ok], col[ok]].sum())
            total += int(ok.sum())
    assert total > 500
    assert inside / total >= 0.80, inside / total


def test_velocity_is_over_ground_not_relative(all_frames):
    # Parked cars: a moving ego sees them drift backwards, but their ground speed is ~0.
    speeds = []
    for f in all_frames["train"][0]:
        if np.linalg.norm(f.ego_velocity) > 5:
            speeds.extend(np.linalg.norm(f.velocity[f.cls == VEHICLE], axis=1))
    assert len(speeds) > 100
    assert np.mean(np.asarray(speeds) < 0.5) > 0.2  # many static vehicles stay static


# ---------------------------------------------------------------- bad input


def _copy_log(src, dst):
    shutil.copytree(src, dst)
    os.chmod(dst, 0o755)
    for p in dst.rglob("*"):
        os.chmod(p, 0o755 if p.is_dir() else 0o644)
    return dst


@pytest.fixture
def log_copy(data_root, tmp_path):
    src = sorted(glob.glob(os.path.join(data_root, "train", "*")))[0]
    return _copy_log(src, tmp_path / os.path.basename(src))


def _rewrite(path, fn):
    """Rewrites a feather file with fn(columns) (in place, or the dict fn returns)."""
    table = feather.read_table(path)
    cols = {name: table.column(name).to_numpy(zero_copy_only=False) for name in table.column_names}
    out = fn(cols)
    cols = out if isinstance(out, dict) else cols
    feather.write_feather(pa.table(cols), path)


def _modelled_rows(log_dir) -> int:
    table = feather.read_table(os.path.join(log_dir, "annotations.feather"), columns=["category"])
    return int(
        np.isin(
            table.column("category").to_numpy(zero_copy_only=False), list(CATEGORY_TO_CLASS)
        ).sum()
    )


def test_missing_map_file_names_the_folder(log_copy):
    for p in (log_copy / "map").glob("log_map_archive_*.json"):
        p.unlink()
    with pytest.raises(FileNotFoundError,
                       match=re.escape(f"{log_copy / 'map'}: no log_map_archive_")):
        list(read_log(str(log_copy), collections.Counter()))


def test_corrupt_feather_names_the_file(log_copy):
    (log_copy / "annotations.feather").write_bytes(b"not a feather file at all")
    with pytest.raises(ValueError, match=re.escape(f"{log_copy / 'annotations.feather'}:")):
        list(read_log(str(log_copy), collections.Counter()))


def test_missing_field_names_the_field(log_copy):
    _rewrite(log_copy / "annotations.feather", lambda c: c.pop("qz"))
    want = f"{log_copy / 'annotations.feather'}: missing field(s) ['qz']"
    with pytest.raises(ValueError, match=re.escape(want)):
        list(read_log(str(log_copy), collections.Counter()))


def test_bad_rows_are_dropped_and_counted(log_copy):
    baseline = sum(f.num_actors for f in read_log(str(log_copy), collections.Counter()))

    def corrupt(c):
        cat = c["category"].astype(object)
        rows = np.flatnonzero(np.isin(cat, list(CATEGORY_TO_CLASS)))[:5]
        c["tx_m"] = c["tx_m"].copy()
        c["tx_m"][rows[0]] = np.nan
        c["length_m"] = c["length_m"].copy()
        c["length_m"][rows[1]] = 0.0
        c["width_m"] = c["width_m"].copy()
        c["width_m"][rows[2]] = -1.0
        cat[rows[3]] = "FLYING_SAUCER"
        c["category"] = cat.astype(str)

    _rewrite(log_copy / "annotations.feather", corrupt)
    drops = collections.Counter()
    frames = list(read_log(str(log_copy), drops))
    assert drops["invalid:tx_m"] == 1
    assert drops["invalid:length_m"] == 1
    assert drops["invalid:width_m"] == 1
    assert drops["category:FLYING_SAUCER"] == 1
    assert sum(f.num_actors for f in frames) == baseline - 4
    for f in frames:
        assert np.all(np.isfinite(f.position)) and np.all(f.size > 0)


def _no_rows(c):
    return {k: v[:0] for k, v in c.items()}


def _shift_times(c):
    c["timestamp_ns"] = c["timestamp_ns"] + 1  # 1 ns off every ego pose


def _all_bollards(c):
    c["category"] = np.full(len(c["category"]), "BOLLARD")


def _zero_pose_quaternion(c):
    for k in ("qw", "qx", "qy", "qz"):
        c[k] = c[k].copy()
        c[k][3] = 0.0


UNUSABLE_LOGS = {
    "no_annotation_rows": (
        "annotations.feather", _no_rows,
        r"annotations\.feather: field timestamp_ns: no annotation rows"),
    "no_ego_poses": (
        "city_SE3_egovehicle.feather", _no_rows,
        r"city_SE3_egovehicle\.feather: field timestamp_ns: no ego poses"),
    "no_timestamp_with_a_pose": (
        "annotations.feather", _shift_times,
        r"annotations\.feather: field timestamp_ns: no annotated timestamp has an ego pose"),
    "zero_pose_quaternion": (
        "city_SE3_egovehicle.feather", _zero_pose_quaternion,
        r"city_SE3_egovehicle\.feather: field qw/qx/qy/qz: 1 poses are not unit"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(UNUSABLE_LOGS))
def test_unusable_log_names_the_file_and_field(log_copy, case):
    name, damage, message = UNUSABLE_LOGS[case]
    _rewrite(log_copy / name, damage)
    with pytest.raises(ValueError, match=message):
        list(read_log(str(log_copy), collections.Counter()))


def test_log_of_dropped_categories_gives_empty_counted_frames(log_copy):
    timestamps = feather.read_table(log_copy / "annotations.feather").column("timestamp_ns")
    rows, sweeps = len(timestamps), len(set(timestamps.to_pylist()))
    _rewrite(log_copy / "annotations.feather", _all_bollards)
    drops = collections.Counter()
    frames = list(read_log(str(log_copy), drops))
    assert len(frames) == sweeps and all(f.num_actors == 0 for f in frames)
    assert drops == {"category:BOLLARD": rows}


def test_prepare_skips_and_names_unusable_logs(data_root, tmp_path):
    """Bad logs and an empty folder beside a good log: the split is read, each bad log is
    counted and named with its field; --strict stops at the first."""
    src = sorted(glob.glob(os.path.join(data_root, "train", "*")))[0]
    split = tmp_path / "root" / "train"
    _copy_log(src, split / "a_good")
    _copy_log(src, split / "b_bollards")
    _rewrite(split / "b_bollards" / "annotations.feather", _all_bollards)
    for case, (name, damage, _) in sorted(UNUSABLE_LOGS.items()):
        _rewrite(_copy_log(src, split / f"c_{case}") / name, damage)
    (split / "d_empty").mkdir()
    spec = source_spec("av2", str(tmp_path / "root"), "train", stride=10)
    summary, _ = prepare(spec, str(tmp_path / "cache"), get_config("tiny"), workers=1)
    frames_per_log = 16  # 156 sweeps at stride 10
    assert summary.files == 2 + len(UNUSABLE_LOGS) + 1
    assert summary.scenes == 2 * frames_per_log and summary.empty_scenes == frames_per_log
    assert summary.bad_files == {"FileNotFoundError": 1, "ValueError": len(UNUSABLE_LOGS)}
    named = {os.path.basename(b["file"]): b["error"] for b in summary.bad_file_list}
    assert sorted(named) == sorted([f"c_{case}" for case in UNUSABLE_LOGS] + ["d_empty"])
    for case, (_, _, message) in UNUSABLE_LOGS.items():
        error = named[f"c_{case}"]
        assert error.startswith(f"ValueError: {split / f'c_{case}'}/") and re.search(message, error)
    assert named["d_empty"].endswith(f"{split / 'd_empty' / 'annotations.feather'}: file not found")
    categories = feather.read_table(os.path.join(src, "annotations.feather")).column("category")
    bollards = categories.to_pylist().count("BOLLARD")
    assert summary.dropped["category:BOLLARD"] == bollards + len(categories)
    with pytest.raises(ValueError, match=r"c_no_annotation_rows/annotations\.feather"):
        prepare(spec, str(tmp_path / "strict"), get_config("tiny"), workers=1, strict=True)
    assert os.listdir(tmp_path / "strict") == []  # no unfinished maps file left behind
    # Into the good cache: a failed run leaves it whole, with every file as it was.
    before = {name: (tmp_path / "cache" / name).read_bytes()
              for name in os.listdir(tmp_path / "cache")}
    with pytest.raises(ValueError, match=r"c_no_annotation_rows/annotations\.feather"):
        prepare(spec, str(tmp_path / "cache"), get_config("tiny"), workers=1, strict=True)
    (tmp_path / "empty_root" / "train" / "d_empty").mkdir(parents=True)
    with pytest.raises(ValueError, match="no scenes to write"):
        prepare(source_spec("av2", str(tmp_path / "empty_root"), "train"),
                str(tmp_path / "cache"), get_config("tiny"), workers=1)
    assert {name: (tmp_path / "cache" / name).read_bytes()
            for name in os.listdir(tmp_path / "cache")} == before


def test_a_log_under_a_path_that_is_not_utf8_reads(log_copy, tmp_path):
    """A folder name with bytes that are not UTF-8 (Linux allows them): the log reads to the
    same frames. pyarrow refuses such a path, so a reader handing it the path would count the
    good log as unreadable."""
    odd = tmp_path / os.fsdecode(b"logs\xff")
    odd.mkdir()
    os.rename(log_copy, odd / log_copy.name)
    drops, frames = collections.Counter(), list(read_log(str(odd / log_copy.name),
                                                         collections.Counter()))
    want = list(read_log(str(_copy_log(odd / log_copy.name, tmp_path / "plain")), drops))
    assert len(frames) == len(want) > 0
    for a, b in zip(frames, want, strict=True):
        np.testing.assert_array_equal(a.position, b.position)


def test_implausible_rows_are_counted_drops(log_copy, caplog):
    """Zero and non-unit quaternions, boxes over 30 m and duplicate (track, timestamp) rows
    are dropped with a reason; a quaternion within the 1e-3 tolerance is kept."""
    duplicated = {}

    def corrupt(c):
        rows = np.flatnonzero(np.isin(c["category"], list(CATEGORY_TO_CLASS)))[:6]
        for k in ("qw", "qx", "qy", "qz", "length_m", "width_m"):
            c[k] = c[k].copy()
        for k in ("qw", "qx", "qy", "qz"):
            c[k][rows[0]] = 0.0  # zero quaternion
            c[k][rows[1]] *= 2.0  # norm 2
            c[k][rows[5]] *= 1.0 + 5e-4  # within tolerance: kept
        c["length_m"][rows[2]] = 1e6
        c["width_m"][rows[3]] = 31.0
        extra = {k: c[k][rows[4]] for k in c}  # the same track and timestamp, 5 m further on
        duplicated.update(track=extra["track_uuid"], t=extra["timestamp_ns"], x=extra["tx_m"])
        extra["tx_m"] += 5.0
        for k in c:
            c[k] = np.append(c[k], extra[k])

    _rewrite(log_copy / "annotations.feather", corrupt)
    drops = collections.Counter()
    with caplog.at_level("WARNING", logger="scenegen_jax.data.av2"):
        frames = list(read_log(str(log_copy), drops))
    assert drops["invalid:quaternion"] == 2
    assert drops["invalid:size"] == 2
    assert drops["invalid:duplicate_row"] == 1
    assert sum(f.num_actors for f in frames) == _modelled_rows(log_copy) - 5  # all else kept
    (frame,) = [f for f in frames if f.scene_id.endswith(f"/{duplicated['t']}")]
    rows = frame.track_id == duplicated["track"]
    assert rows.sum() == 1 and frame.position[rows, 0][0] == pytest.approx(duplicated["x"])
    for f in frames:
        assert np.all(f.size <= 30.0)
    logged = caplog.text
    for reason in ("invalid:quaternion", "invalid:size", "invalid:duplicate_row"):
        assert re.search(rf"annotations\.feather: \d+ rows dropped \({reason}\)", logged)


def _pt(x, y):
    return {"x": x, "y": y, "z": 0.0}


def test_degenerate_map_polygons_are_counted_drops(log_copy, caplog):
    (path,) = (log_copy / "map").glob("log_map_archive_*.json")
    data = json.loads(path.read_text())
    clean, clean_drops = vector_map_from_json(data, str(path))
    assert clean_drops == {}
    lane = next(iter(data["lane_segments"].values()))
    data["drivable_areas"]["900"] = {"id": 900, "area_boundary": [_pt(0, 0), _pt(5, 0)]}
    data["drivable_areas"]["901"] = {"id": 901, "area_boundary": [_pt(0, 0), _pt(5, 0), _pt(9, 0)]}
    data["pedestrian_crossings"]["902"] = {
        "edge1": [_pt(0, 0), _pt(4, 0)],
        "edge2": [_pt(0, 0), _pt(4, 0)],
    }
    data["lane_segments"]["903"] = {**lane, "id": 903, "right_lane_boundary": [_pt(1, 1)]}
    data["lane_segments"]["904"] = {
        **lane,
        "id": 904,
        "right_lane_boundary": lane["left_lane_boundary"],
    }
    path.write_text(json.dumps(data))
    vmap, dropped = vector_map_from_json(data, str(path))
    assert dropped == {
        "map:degenerate_drivable_area": 2,
        "map:degenerate_crosswalk": 1,
        "map:degenerate_lane": 2,
    }
    assert len(vmap.lanes) == len(clean.lanes)
    assert len(vmap.crosswalks) == len(clean.crosswalks)
    assert len(vmap.drivable_areas) == len(clean.drivable_areas)
    # Through read_log, the map drops land in the log's counter (once per log) and the log.
    drops = collections.Counter()
    with caplog.at_level("WARNING", logger="scenegen_jax.data.av2"):
        next(read_log(str(log_copy), drops))
    assert drops["map:degenerate_drivable_area"] == 2 and drops["map:degenerate_lane"] == 2
    assert f"{path}: 2 map elements dropped (map:degenerate_lane)" in caplog.text
    # A lane mark type Argoverse 2 does not have is counted and not drawn; an intersection
    # flag that is not a boolean (the string "false" would read as true) is an error.
    data["lane_segments"]["906"] = {**lane, "id": 906, "left_lane_mark_type": 7}
    vmap, dropped = vector_map_from_json(data, str(path))
    assert dropped["map:unknown_mark_type"] == 1
    assert next(ln for ln in vmap.lanes if ln.id == 906).left_mark == "UNKNOWN"
    data["lane_segments"]["906"] = {**lane, "id": 906, "is_intersection": "false"}
    with pytest.raises(ValueError, match=r"field lane_segments\[906\]\.is_intersection: expected "
                       r"true or false, got 'false'"):
        vector_map_from_json(data, str(path))
    del data["lane_segments"]["906"]
    # Malformed points are errors naming the field, not drops.
    data["drivable_areas"]["905"] = {"area_boundary": [{"x": 1.0}]}
    with pytest.raises(ValueError, match=r"field drivable_areas\[905\]\.area_boundary"):
        vector_map_from_json(data, str(path))


def test_map_polygons_match_shapely_area(all_frames):
    # The drivable channel at 0.25 m/px covers the clipped polygons' area within 2%.
    f = all_frames["val"][0][0]
    size, res = 320, 0.25
    raster = rasterize_map(f.map, size, res)[..., ALL_MAP_CHANNELS.index("drivable_area")]
    union = shapely.union_all([shapely.Polygon(p).buffer(0) for p in f.map.drivable_areas])
    clipped = union.intersection(shapely.box(-40, -40, 40, 40))
    assert raster.sum() * res * res == pytest.approx(clipped.area, rel=0.02)
    assert {g.map.dataset for frames, _ in all_frames.values() for g in frames} == {"av2"}
