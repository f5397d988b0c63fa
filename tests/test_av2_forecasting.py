"""Argoverse 2 Motion Forecasting reader on the real scenarios (both parquet releases), its
cache against the map JSON, and its handling of bad input."""

from __future__ import annotations

import collections
import json
import os
import re
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import shapely

from scenegen_jax.cli import main as cli_main
from scenegen_jax.config import get_config
from scenegen_jax.data import av2_forecasting as fc
from scenegen_jax.data.av2 import AV2_EGO_SIZE
from scenegen_jax.data.cache import load_cache
from scenegen_jax.data.prepare import prepare
from scenegen_jax.data.sources import read_file, source_files, source_spec
from scenegen_jax.raster.map import ALL_MAP_CHANNELS
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE, in_region

OLDER_RELEASE = "0a1e6f0a-1817-4a98-b02e-db8c9327d151"  # with map_id and slice_id
STEPS = list(range(0, 110, 10))  # the default stride's frames
VEHICLE_TYPES = ("vehicle", "bus")


@pytest.fixture(scope="module")
def root(forecast_root) -> str:
    return forecast_root


def _spec(root: str, split: str, stride: int = 10) -> dict:
    return source_spec("av2_forecasting", root, split, stride)


def _scenarios(root: str) -> list[str]:
    return [p for split in ("train", "val") for p in source_files(_spec(root, split))]


def _parquet(folder: str) -> str:
    name = os.path.basename(folder)
    return os.path.join(folder, f"scenario_{name}.parquet")


def _rows(folder: str) -> dict[str, np.ndarray]:
    """Every column of a scenario's parquet file, read here with pyarrow alone."""
    table = pq.read_table(_parquet(folder))
    return {c: table.column(c).to_numpy(zero_copy_only=False) for c in table.column_names}


@pytest.fixture(scope="module")
def read(root):
    """{scenario folder: (frames, drops)} of the three scenarios at the default stride."""
    return {p: read_file(_spec(root, "train"), p) for p in _scenarios(root)}


# ---------------------------------------------------------------- the real scenarios


def test_scenario_folders_of_each_split(root):
    train = source_files(_spec(root, "train"))
    val = source_files(_spec(root, "val"))
    assert [os.path.basename(p) for p in train] == [
        "0a0a2bb7-c4f4-44cd-958a-9ee15cb34aca", OLDER_RELEASE]
    assert [os.path.basename(p) for p in val] == ["00a0ec58-1fb9-4a2b-bfd7-f4e5da7a9eff"]


def test_both_schema_releases_read(root, read):
    releases = {}
    for folder, (frames, _) in read.items():
        names = pq.read_schema(_parquet(folder)).names
        releases[os.path.basename(folder)] = "map_id" in names and "slice_id" in names
        assert [f.scene_id for f in frames] == [
            f"{os.path.basename(folder)}/{s}" for s in STEPS]
        assert sum(f.num_actors for f in frames) > 100
    assert releases[OLDER_RELEASE] and sum(releases.values()) == 1


def test_every_row_at_a_frame_is_an_actor_or_a_counted_drop(read):
    """Rows of the dropped types at the frames' steps are counted by type; the other rows,
    observed or in the hidden future alike, are the frames' actors with their class."""
    want_cls = {"vehicle": VEHICLE, "bus": VEHICLE, "pedestrian": PEDESTRIAN,
                "cyclist": BICYCLIST, "motorcyclist": BICYCLIST}
    seen_types = set()
    for folder, (frames, drops) in read.items():
        rows = _rows(folder)
        at_frames = np.isin(rows["timestep"], STEPS) & (rows["track_id"] != "AV")
        types = collections.Counter(rows["object_type"][at_frames])
        seen_types |= set(types)
        want_drops = {f"type:{t}": n for t, n in types.items() if t not in want_cls}
        assert dict(drops) == want_drops
        for f, step in zip(frames, STEPS, strict=True):
            sel = (rows["timestep"] == step) & (rows["track_id"] != "AV")
            sel &= np.isin(rows["object_type"], list(want_cls))
            by_track = dict(zip(rows["track_id"][sel], rows["object_type"][sel], strict=True))
            assert sorted(f.track_id) == sorted(by_track)
            assert [int(c) for c in f.cls] == [want_cls[by_track[t]] for t in f.track_id]
    assert {"riderless_bicycle", "static", "background", "motorcyclist"} <= seen_types
    # Steps 50.. are the future the challenge hides (observed false): real rows, read.
    frames, _ = next(iter(read.values()))
    assert all(f.num_actors > 0 for f in frames[5:])


def test_every_frame_sees_from_the_av_track(read):
    for folder, (frames, _) in read.items():
        rows = _rows(folder)
        for f, step in zip(frames, STEPS, strict=True):
            (av,) = np.flatnonzero((rows["track_id"] == "AV") & (rows["timestep"] == step))
            x, y, h = rows["position_x"][av], rows["position_y"][av], rows["heading"][av]
            c, s = np.cos(h), np.sin(h)
            np.testing.assert_allclose(f.city_from_ego, [[c, -s, x], [s, c, y], [0, 0, 1]],
                                       atol=1e-9)
            v = np.array([rows["velocity_x"][av], rows["velocity_y"][av]])
            np.testing.assert_allclose(f.ego_velocity, [c * v[0] + s * v[1],
                                                        -s * v[0] + c * v[1]], atol=1e-9)
            assert "AV" not in f.track_id
            np.testing.assert_array_equal(f.ego_size, AV2_EGO_SIZE)


def _hand_checked(frame, rows, track: str, step: int):
    """(position, heading, velocity) in the ego frame of `track` at `step`, by hand."""
    (av,) = np.flatnonzero((rows["track_id"] == "AV") & (rows["timestep"] == step))
    (r,) = np.flatnonzero((rows["track_id"] == track) & (rows["timestep"] == step))
    h0 = rows["heading"][av]
    dx = rows["position_x"][r] - rows["position_x"][av]
    dy = rows["position_y"][r] - rows["position_y"][av]
    vx, vy = rows["velocity_x"][r], rows["velocity_y"][r]
    c, s = np.cos(h0), np.sin(h0)
    heading = (rows["heading"][r] - h0) % (2 * np.pi)
    return (c * dx + s * dy, -s * dx + c * dy), heading, (c * vx + s * vy, -s * vx + c * vy)


@pytest.mark.parametrize("scenario, track, step", [
    ("0a0a2bb7-c4f4-44cd-958a-9ee15cb34aca", "89108", 0),  # an observed row
    ("00a0ec58-1fb9-4a2b-bfd7-f4e5da7a9eff", "71530", 70),  # a future row
])
def test_actor_rows_hand_checked(read, scenario, track, step):
    folder = next(p for p in read if os.path.basename(p) == scenario)
    frames, _ = read[folder]
    frame = frames[STEPS.index(step)]
    rows = _rows(folder)
    position, heading, velocity = _hand_checked(frame, rows, track, step)
    (i,) = np.flatnonzero(frame.track_id == track)
    np.testing.assert_allclose(frame.position[i], position, atol=1e-9)
    assert frame.heading[i] == pytest.approx(heading, abs=1e-9)
    np.testing.assert_allclose(frame.velocity[i], velocity, atol=1e-9)


def test_moving_vehicles_head_where_they_go(read):
    for folder, (frames, _) in read.items():
        diffs = []
        for f in frames:
            m = (f.cls == VEHICLE) & (np.linalg.norm(f.velocity, axis=1) > 2.0)
            direction = np.arctan2(f.velocity[m, 1], f.velocity[m, 0])
            diffs.extend(np.abs(np.degrees(np.angle(np.exp(1j * (direction - f.heading[m]))))))
        assert len(diffs) > 20 and np.median(diffs) < 2.0, folder


def test_sizes_are_unmeasured_placeholders(read):
    for folder, (frames, _) in read.items():
        rows = _rows(folder)
        for f, step in zip(frames, STEPS, strict=True):
            assert f.size_measured.dtype == bool and f.size_measured.shape == (f.num_actors,)
            assert not f.size_measured.any()
            at = rows["timestep"] == step
            types = dict(zip(rows["track_id"][at], rows["object_type"][at], strict=True))
            want = [fc.PLACEHOLDER_SIZE_M[types[t]] for t in f.track_id]
            np.testing.assert_array_equal(f.size, np.reshape(want, (-1, 2)))


# ---------------------------------------------------------------- the cache and the map


@pytest.fixture(scope="module")
def caches(root, tmp_path_factory):
    """(summary, cache) of each split, prepared with the cpu config in one process."""
    out = {}
    for split in ("train", "val"):
        path = str(tmp_path_factory.mktemp(f"fc_{split}"))
        summary, _ = prepare(_spec(root, split), path, get_config("cpu"), workers=1)
        out[split] = (summary, load_cache(path))
    return out


def _cache_shares(cache, cfg) -> dict[str, tuple[int, int]]:
    """{scenario id: (vehicle centres on the drivable channel drawn from the cache, vehicles)}
    over the cache's scenes, vehicles within the grid region."""
    from scenegen_jax.eval.realism import map_canvases

    channel = ALL_MAP_CHANNELS.index("drivable_area")
    out = collections.defaultdict(lambda: (0, 0))
    canvases = map_canvases(cache, range(len(cache)), cfg)
    for (i, scene_id), canvas in zip(enumerate(cache.scene_ids), canvases, strict=True):
        half = canvas.shape[0] * cfg.grid.m_per_px / 2
        a = cache.actors
        sel = a.valid[i] & (a.cls[i] == VEHICLE) & in_region(a.position[i], cfg.grid)
        pos = a.position[i][sel].astype(np.float64)
        col = np.floor((pos[:, 0] + half) / cfg.grid.m_per_px).astype(int)
        row = np.floor((half - pos[:, 1]) / cfg.grid.m_per_px).astype(int)
        on, n = out[scene_id.split("/")[0]]
        out[scene_id.split("/")[0]] = (on + int(np.sum(canvas[row, col, channel] > 0.5)),
                                       n + len(pos))
    return dict(out)


def _json_share(folder: str, half_m: float) -> tuple[int, int]:
    """(vehicle centres on the map JSON's drivable areas, vehicles) at the frames' steps,
    vehicles within `half_m` of the AV along its axes, all in the city frame."""
    name = os.path.basename(folder)
    with open(os.path.join(folder, f"log_map_archive_{name}.json")) as f:
        areas = json.load(f)["drivable_areas"].values()
    union = shapely.union_all(
        [shapely.Polygon([(p["x"], p["y"]) for p in a["area_boundary"]]) for a in areas])
    rows = _rows(folder)
    on = n = 0
    for step in STEPS:
        (av,) = np.flatnonzero((rows["track_id"] == "AV") & (rows["timestep"] == step))
        sel = (rows["timestep"] == step) & np.isin(rows["object_type"], VEHICLE_TYPES)
        sel &= rows["track_id"] != "AV"
        x, y = rows["position_x"][sel], rows["position_y"][sel]
        h = rows["heading"][av]
        dx, dy = x - rows["position_x"][av], y - rows["position_y"][av]
        along, across = np.cos(h) * dx + np.sin(h) * dy, -np.sin(h) * dx + np.cos(h) * dy
        inside = (np.abs(along) < half_m) & (np.abs(across) < half_m)
        on += int(shapely.contains_xy(union, x[inside], y[inside]).sum())
        n += int(inside.sum())
    return on, n


def test_cached_drivable_area_agrees_with_the_map_json(root, caches):
    """Per scenario, the share of vehicle centres on the cached drivable channel is the share
    on the JSON's drivable polygons within 2 percentage points."""
    cfg = get_config("cpu")
    shares = {}
    for split, (_, cache) in caches.items():
        for scenario, (on, n) in _cache_shares(cache, cfg).items():
            json_on, json_n = _json_share(os.path.join(root, split, scenario),
                                          cfg.grid.region_m / 2)
            assert n == json_n > 20, scenario  # the same vehicles on both sides
            shares[scenario] = (on / n, json_on / json_n)
    assert len(shares) == 3
    for scenario, (cached, direct) in shares.items():
        assert abs(cached - direct) <= 0.02, (scenario, cached, direct)


def test_prepare_summary_counts_the_dropped_types(caches):
    train, val = caches["train"][0], caches["val"][0]
    assert train.files == 2 and train.scenes == 22 and val.files == 1 and val.scenes == 11
    assert not train.bad_files and not val.bad_files
    assert {"type:riderless_bicycle", "type:static", "type:background"} <= set(train.dropped)
    assert {"type:static", "type:background"} <= set(val.dropped)


def test_cli_prepare_prints_the_drops(root, tmp_path, capsys):
    cli_main(["prepare", "--source", "av2_forecasting", "--root", root, "--split", "val",
              "--config", "tiny", "--out", str(tmp_path / "c"), "--workers", "1"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rows = _rows(source_files(_spec(root, "val"))[0])
    at = np.isin(rows["timestep"], STEPS)
    for t in ("static", "background"):
        assert summary["dropped"][f"type:{t}"] == int(np.sum(at & (rows["object_type"] == t)))
    assert summary["scenes"] == 11


# ---------------------------------------------------------------- bad input


@pytest.fixture
def scenario_copy(root, tmp_path):
    """A writable copy of the newer-release train scenario."""
    src = source_files(_spec(root, "train"))[0]
    dst = tmp_path / "train" / os.path.basename(src)
    shutil.copytree(src, dst)
    os.chmod(dst, 0o755)
    for p in dst.iterdir():
        os.chmod(p, 0o644)
    return dst


def _rewrite(folder, fn):
    """Rewrites a scenario's parquet file with fn(columns) (in place or the dict returned)."""
    path = _parquet(str(folder))
    table = pq.read_table(path)
    cols = {c: table.column(c).to_numpy(zero_copy_only=False) for c in table.column_names}
    out = fn(cols)
    pq.write_table(pa.table(out if isinstance(out, dict) else cols), path)
    return path


def _read(folder, stride: int = 10):
    return fc.read_file(str(folder), stride)


def test_missing_columns_are_named(scenario_copy):
    path = _rewrite(scenario_copy, lambda c: {k: v for k, v in c.items()
                                              if k not in ("heading", "velocity_y")})
    with pytest.raises(ValueError, match=re.escape(
            f"{path}: missing field(s) ['heading', 'velocity_y']")):
        _read(scenario_copy)


@pytest.mark.parametrize("field, values, kind", [
    ("timestep", lambda v: v.astype(np.float64), "integer"),
    ("position_x", lambda v: v.astype(str), "number"),
    ("track_id", lambda v: np.arange(len(v)), "string"),
])
def test_wrong_dtypes_are_named(scenario_copy, field, values, kind):
    def damage(c):
        c[field] = values(c[field])

    path = _rewrite(scenario_copy, damage)
    with pytest.raises(ValueError, match=re.escape(f"{path}: field {field}: expected {kind}")):
        _read(scenario_copy)


def test_nulls_in_ids_are_errors(scenario_copy):
    def damage(c):
        ids = c["track_id"].astype(object)
        ids[3] = None
        c["track_id"] = pa.array(ids, pa.string())

    path = _rewrite(scenario_copy, damage)
    with pytest.raises(ValueError, match=re.escape(f"{path}: field track_id: 1 missing")):
        _read(scenario_copy)


def test_no_av_track_is_an_error(scenario_copy):
    def damage(c):
        c["track_id"] = np.where(c["track_id"] == "AV", "not_the_av", c["track_id"])

    path = _rewrite(scenario_copy, damage)
    with pytest.raises(ValueError, match=re.escape(f"{path}: field track_id: no finite row "
                                                   "of the track 'AV'")):
        _read(scenario_copy)


def test_corrupt_parquet_and_missing_map_name_the_file(scenario_copy):
    path = _parquet(str(scenario_copy))
    (map_path,) = scenario_copy.glob("log_map_archive_*.json")
    map_path.unlink()
    with pytest.raises(FileNotFoundError, match=re.escape(f"{map_path}: map file not found")):
        _read(scenario_copy)
    with open(path, "wb") as f:
        f.write(b"PAR1 this is not parquet")
    with pytest.raises(ValueError, match=re.escape(f"{path}: not a readable parquet file")):
        fc.read_columns(path)


def test_timesteps_beyond_the_scenario_are_errors(scenario_copy):
    def damage(c):
        c["timestep"] = c["timestep"].copy()
        c["timestep"][0] = 110

    path = _rewrite(scenario_copy, damage)
    with pytest.raises(ValueError, match=re.escape(f"{path}: field timestep: values 0..110")):
        _read(scenario_copy)


def test_bad_rows_are_counted_drops(scenario_copy, caplog):
    """NaN rows are "invalid:nan", a track's second row at a step "invalid:duplicate_row",
    an unknown type "type:<name>" (and logged), a NaN ego row drops its frame, and an ego
    missing at a step drops that frame: all counted, the rest read as before."""
    frames_before, drops_before = _read(scenario_copy)
    actors_before = {f.scene_id: f.num_actors for f in frames_before}
    damaged = []

    def damage(c):
        for k in ("position_x", "heading", "velocity_y", "object_type", "track_id"):
            c[k] = c[k].copy()
        actors = np.flatnonzero((c["timestep"] == 20) & (c["track_id"] != "AV")
                                & (c["object_type"] == "vehicle"))
        c["position_x"][actors[0]] = np.nan
        c["heading"][actors[1]] = np.inf
        c["velocity_y"][actors[2]] = np.nan
        c["object_type"][actors[3]] = "flying_saucer"
        damaged.extend(c["track_id"][actors[:4]])
        (av,) = np.flatnonzero((c["timestep"] == 40) & (c["track_id"] == "AV"))
        c["heading"][av] = np.nan
        (av,) = np.flatnonzero((c["timestep"] == 60) & (c["track_id"] == "AV"))
        c["track_id"][av] = "AV_gone"  # an unknown vehicle track now; the step has no ego
        copy = {k: np.append(v, v[actors[4]]) for k, v in c.items()}
        copy["position_x"][-1] += 5.0  # the same track and step, 5 m further on
        return copy

    _rewrite(scenario_copy, damage)
    with caplog.at_level("WARNING", logger="scenegen_jax.data.av2_forecasting"):
        frames, drops = _read(scenario_copy)
    assert drops - drops_before == {"invalid:nan": 3, "type:flying_saucer": 1,
                                    "invalid:duplicate_row": 1, "frame:invalid_ego": 1,
                                    "frame:no_ego": 1}
    assert [f.scene_id.split("/")[1] for f in frames] == [
        str(s) for s in STEPS if s not in (40, 60)]
    at_20 = next(f for f in frames if f.scene_id.endswith("/20"))
    assert at_20.num_actors == actors_before[at_20.scene_id] - 4
    assert not set(damaged) & set(at_20.track_id)
    for f in frames:
        assert np.all(np.isfinite(f.position)) and np.all(np.isfinite(f.heading))
    assert "unknown object type 'flying_saucer' in 1 rows" in caplog.text
    assert "3 dropped (invalid:nan)" in caplog.text


def test_a_test_split_file_without_the_future_counts_the_missing_frames(scenario_copy):
    """The test split ships only the observed history (steps 0..49): its later steps have
    no AV row and are counted, not errors."""
    _rewrite(scenario_copy, lambda c: {k: v[c["observed"]] for k, v in c.items()})
    frames, drops = _read(scenario_copy)
    assert [f.scene_id.split("/")[1] for f in frames] == ["0", "10", "20", "30", "40"]
    assert drops["frame:no_ego"] == 6


def test_stride_picks_the_frames(scenario_copy):
    frames, _ = _read(scenario_copy, stride=25)
    assert [f.scene_id.split("/")[1] for f in frames] == ["0", "25", "50", "75", "100"]


def test_scenario_files_follow_links_and_need_scenarios(scenario_copy, tmp_path):
    linked = tmp_path / "linked"
    linked.mkdir()
    os.symlink(scenario_copy, linked / scenario_copy.name)
    assert fc.scenario_files(linked) == [str(linked / scenario_copy.name)]
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no Argoverse 2 forecasting scenarios"):
        fc.scenario_files(tmp_path / "empty")
