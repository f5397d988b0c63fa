"""Argoverse 2 reader and `prepare` on the real logs, and its handling of bad input."""

from __future__ import annotations

import collections
import glob
import json
import os
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
import shapely

from scenegen_jax.cli import main as cli_main
from scenegen_jax.data.av2 import CATEGORY_TO_CLASS, read_log
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


@pytest.fixture
def log_copy(data_root, tmp_path):
    src = sorted(glob.glob(os.path.join(data_root, "train", "*")))[0]
    dst = tmp_path / os.path.basename(src)
    shutil.copytree(src, dst)
    os.chmod(dst, 0o755)
    for p in dst.rglob("*"):
        os.chmod(p, 0o755 if p.is_dir() else 0o644)
    return dst


def _rewrite(path, fn):
    table = feather.read_table(path)
    cols = {name: table.column(name).to_numpy(zero_copy_only=False) for name in table.column_names}
    fn(cols)
    feather.write_feather(pa.table(cols), path)


def test_missing_map_file_names_the_folder(log_copy):
    for p in (log_copy / "map").glob("log_map_archive_*.json"):
        p.unlink()
    with pytest.raises(FileNotFoundError, match="log_map_archive"):
        list(read_log(str(log_copy), collections.Counter()))


def test_corrupt_feather_names_the_file(log_copy):
    (log_copy / "annotations.feather").write_bytes(b"not a feather file at all")
    with pytest.raises(ValueError, match="annotations.feather"):
        list(read_log(str(log_copy), collections.Counter()))


def test_missing_field_names_the_field(log_copy):
    _rewrite(log_copy / "annotations.feather", lambda c: c.pop("qz"))
    with pytest.raises(ValueError, match="qz"):
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


def test_map_polygons_match_shapely_area(all_frames):
    # The drivable channel at 0.25 m/px covers the clipped polygons' area within 2%.
    f = all_frames["val"][0][0]
    size, res = 320, 0.25
    raster = rasterize_map(f.map, size, res)[..., ALL_MAP_CHANNELS.index("drivable_area")]
    union = shapely.union_all([shapely.Polygon(p).buffer(0) for p in f.map.drivable_areas])
    clipped = union.intersection(shapely.box(-40, -40, 40, 40))
    assert raster.sum() * res * res == pytest.approx(clipped.area, rel=0.02)
