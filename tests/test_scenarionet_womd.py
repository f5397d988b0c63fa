"""ScenarioNet import of the real Waymo pickles in ../shared/data/womd_mini: every stride
frame, the data set, actor counts against the files' tracks, headings and sizes, maps."""

from __future__ import annotations

import collections
import glob
import os

import numpy as np
import pytest
import shapely

from scenegen_jax.data import scenarionet as sn
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE
from scenegen_jax.vector_map import ROAD_EDGE

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


WOMD_ROOT = os.path.normpath(os.path.join(REPO, "..", "shared", "data", "womd_mini", "scenarionet"))


WOMD_STRIDE = 10


def _womd_sdc(scenario: dict):
    """The SDC's key in `tracks`: metadata.sdc_id (S1, S2) or the top-level sdc_track_index
    (S3: an int, and so are S3's track keys; S4: a str)."""
    meta = scenario.get("metadata", {})
    return meta["sdc_id"] if "sdc_id" in meta else scenario["sdc_track_index"]


@pytest.fixture(scope="module")
def womd():
    """{file name: (scenario, stride frames)} of every womd_mini ScenarioNet pickle, read once."""
    paths = sorted(glob.glob(os.path.join(WOMD_ROOT, "*", "*.pkl")))
    if not paths:
        pytest.fail(f"real data missing: {WOMD_ROOT} (../shared must sit beside the repo)")
    out = {}
    for path in paths:
        scenario = sn.read_scenario(path)
        out[os.path.basename(path)] = (
            scenario,
            sn.frames_from_scenario(scenario, path, stride=WOMD_STRIDE),
        )
    return out


def test_womd_every_pickle_imports_every_stride_frame(womd):
    assert len(womd) == 18
    for name, (scenario, frames) in womd.items():
        tracks = scenario["tracks"]
        sdc = tracks[_womd_sdc(scenario)]["state"]
        n = len(sdc["position"])
        valid = np.asarray(sdc["valid"]).reshape(n) != 0
        want = [t for t in range(0, n, WOMD_STRIDE) if valid[t]]
        assert [int(g.frame.scene_id.rsplit("/", 1)[1]) for g in frames] == want, name
        assert sn.scenario_sample_rate_hz(scenario) == pytest.approx(10.0, rel=0.01), name


def test_womd_maps_know_their_data_set_where_the_file_says(womd):
    """S1 and S2 carry metadata.dataset "waymo"; S3 and S4 have no metadata (README)."""
    datasets = collections.Counter()
    for name, (scenario, frames) in womd.items():
        want = scenario.get("metadata", {}).get("dataset", "")
        assert {f.map.dataset for f, _ in frames} == {want}, name
        datasets[want] += 1
    assert datasets == {"waymo": 13, "": 5}


def test_womd_actor_counts_equal_the_files_tracks(womd):
    """Per step and class: actors == tracks valid there with that type (the SDC aside)."""
    cls_of = {"VEHICLE": VEHICLE, "PEDESTRIAN": PEDESTRIAN, "CYCLIST": BICYCLIST}
    for name, (scenario, frames) in womd.items():
        sdc = _womd_sdc(scenario)
        others = [tr for tid, tr in scenario["tracks"].items() if tid != sdc]
        for frame, dropped in frames:
            t = int(frame.scene_id.rsplit("/", 1)[1])
            want = collections.Counter(
                tr["type"] for tr in others if np.asarray(tr["state"]["valid"]).reshape(-1)[t]
            )
            got = collections.Counter(int(c) for c in frame.cls)
            assert got == {cls_of[k]: v for k, v in want.items() if k in cls_of}, (name, t)
            assert not any(k.startswith(("invalid:", "type:")) for k in dropped), (name, dropped)


def test_womd_headings_agree_with_velocities_and_sizes_are_plausible(womd):
    for name, (_, frames) in womd.items():
        angles, lengths = [], []
        for frame, _ in frames:
            veh = frame.cls == VEHICLE
            moving = veh & (np.linalg.norm(frame.velocity, axis=1) > 2.0)
            v = frame.velocity[moving]
            angles.append(
                np.angle(np.exp(1j * (frame.heading[moving] - np.arctan2(v[:, 1], v[:, 0]))))
            )
            lengths.append(frame.size[veh, 1])
            assert np.all(frame.size[veh, 1] >= frame.size[veh, 0])
        assert np.degrees(np.median(np.abs(np.concatenate(angles)))) < 5.0, name
        assert 3.5 < np.median(np.concatenate(lengths)) < 6.0, name
        assert not any(d["quirk:velocity_mismatch"] for _, d in frames), name


def test_womd_maps(womd):
    for name, (scenario, frames) in womd.items():
        frame, dropped = frames[0]
        vmap = frame.map
        assert vmap.lanes and vmap.lines and vmap.drivable_areas, name
        marks = collections.Counter(line.mark for line in vmap.lines)
        assert marks[ROAD_EDGE] > 0 and sum(marks.values()) > marks[ROAD_EDGE], name
        features = scenario["map_features"].values()
        types = collections.Counter(f["type"] for f in features if isinstance(f["type"], str))
        # every crosswalk and driveway is kept; one drivable polygon per lane plus driveways
        assert len(vmap.crosswalks) == types["CROSSWALK"] + types["CROSS_WALK"], name
        assert len(vmap.drivable_areas) == len(vmap.lanes) + types["DRIVEWAY"], name
        assert dropped["map:malformed_type"] == sum(
            not isinstance(f["type"], str) for f in features
        )
        for kind in ("STOP_SIGN", "stop_sign", "SPEED_BUMP"):
            assert dropped[f"map:{kind}"] == types[kind], (name, kind)
        # the ego stands on the drivable surface
        around = [p for p in vmap.drivable_areas if np.all(p.min(0) <= 0) and np.all(p.max(0) >= 0)]
        assert any(shapely.Polygon(p).contains(shapely.Point(0.0, 0.0)) for p in around), name


def test_complex_numbers_are_refused_not_cast():
    """A complex array where reals belong is an error naming the field; a cast to float would
    drop the imaginary part silently (found by the fuzz tests)."""
    path = os.path.join(WOMD_ROOT, "val", "8799c31b5be1f312.pkl")
    scenario = sn.read_scenario(path)
    tracks = dict(scenario["tracks"])
    tid = next(iter(tracks))
    state = dict(tracks[tid]["state"])
    state["position"] = np.asarray(state["position"]).astype(np.complex128) * (1 + 1e-3j)
    tracks[tid] = {**tracks[tid], "state": state}
    with pytest.raises(ValueError, match="complex numbers") as e:
        sn.frames_from_scenario({**scenario, "tracks": tracks}, path, stride=50)
    assert path in str(e.value) and "position" in str(e.value)
