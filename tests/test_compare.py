"""Paired model comparison: point estimates by hand, intervals against scipy's bootstrap."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from scenegen_jax.cli import main
from scenegen_jax.distributions import TERMS
from scenegen_jax.eval.compare import compare_files, load_scores, paired_difference
from scenegen_jax.scene import STOP


def _scores(location, cls, valid):
    """Scores of scenes [S, T]: `location` NLL, every other term 1 nat per step."""
    location = np.asarray(location, np.float32)
    out = {k: np.ones_like(location) for k in TERMS}
    out["location"] = location
    out["step_cls"] = np.asarray(cls, np.int32)
    out["step_valid"] = np.asarray(valid, bool)
    return out


def test_point_estimate_by_hand():
    # Scene 0: a vehicle and a pedestrian, then the stop step; scene 1: a vehicle, stop, pad.
    cls = [[0, 1, STOP], [0, STOP, 0]]
    valid = [[True, True, True], [True, True, False]]
    a = _scores([[5.0, 9.0, 100.0], [7.0, 100.0, 100.0]], cls, valid)
    b = _scores([[4.0, 10.0, 0.0], [5.0, 0.0, 0.0]], cls, valid)
    # vehicles: (5 - 4 + 7 - 5) / 2; pedestrian: (9 - 10) / 1; all: (1 - 1 + 2) / 3.
    assert paired_difference([a], [b], cls=0, block=1)["diff"] == pytest.approx(1.5)
    assert paired_difference([a], [b], cls=1, block=1)["diff"] == pytest.approx(-1.0)
    assert paired_difference([a], [b], block=1)["diff"] == pytest.approx(2 / 3)
    # total: the other four terms are equal in A and B, so the same differences.
    assert paired_difference([a], [b], "total", cls=0)["diff"] == pytest.approx(1.5)
    # Two pairs are averaged scene by scene: the second pair has no difference.
    assert paired_difference([a, a], [b, a], cls=0)["diff"] == pytest.approx(0.75)
    none = paired_difference([a], [b], cls=2)
    assert none["actors"] == 0 and none["diff"] is None
    same = paired_difference([a], [a], block=1)
    assert (same["diff"], same["low"], same["high"]) == (0.0, 0.0, 0.0)
    # The two scenes make one block of 10: no interval, the estimate still.
    assert paired_difference([a], [b], cls=0)["low"] is None


def test_interval_matches_scipy_bootstrap_for_single_scene_blocks():
    rng = np.random.default_rng(1)
    s = 300
    diff = rng.normal(-0.2, 1.0, s)
    cls, valid = np.zeros((s, 1), int), np.ones((s, 1), bool)  # one vehicle per scene
    b = _scores(rng.normal(8.0, 1.0, (s, 1)), cls, valid)
    a = _scores(b["location"] + diff[:, None].astype(np.float32), cls, valid)
    ours = paired_difference([a], [b], cls=0, block=1, samples=20000)
    ref = scipy.stats.bootstrap(
        (diff,), np.mean, n_resamples=20000, method="percentile", random_state=0
    ).confidence_interval
    se = diff.std() / np.sqrt(s)
    assert ours["diff"] == pytest.approx(diff.mean(), abs=1e-5)
    assert ours["low"] == pytest.approx(ref.low, abs=0.05 * se)
    assert ours["high"] == pytest.approx(ref.high, abs=0.05 * se)


def test_blocks_widen_the_interval_of_correlated_scenes():
    rng = np.random.default_rng(2)
    diff = np.repeat(rng.normal(0.0, 1.0, 30), 10)  # 10 identical frames per draw
    cls, valid = np.zeros((300, 1), int), np.ones((300, 1), bool)
    b = _scores(np.zeros((300, 1)), cls, valid)
    a = _scores(diff[:, None], cls, valid)
    one = paired_difference([a], [b], block=1)
    ten = paired_difference([a], [b], block=10)
    # Resampling single frames treats 300 frames as independent: sqrt(10) too narrow.
    ratio = (ten["high"] - ten["low"]) / (one["high"] - one["low"])
    assert 2.3 < ratio < 4.3


def test_files_of_other_scenes_or_fields_are_errors(tmp_path, capsys):
    cls, valid = [[0, STOP]], [[True, True]]
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    np.savez(a, **_scores([[3.0, 1.0]], cls, valid))
    np.savez(b, **_scores([[2.0, 1.0]], cls, valid))
    main(["compare", "--a", str(a), "--b", str(b), "--out", str(tmp_path / "r.json")])
    assert "+1.000" in capsys.readouterr().out
    other = tmp_path / "other.npz"
    np.savez(other, **_scores([[2.0, 1.0]], [[1, STOP]], valid))
    with pytest.raises(ValueError, match="other.npz: field 'step_cls' differs"):
        compare_files([str(a)], [str(other)])
    broken = tmp_path / "broken.npz"
    np.savez(broken, location=np.zeros((1, 2)))
    with pytest.raises(ValueError, match="broken.npz: missing field 'class'"):
        load_scores(str(broken))
    with pytest.raises(SystemExit):
        main(["compare", "--a", str(a), "--b", str(broken)])


def test_damaged_files_and_bad_options_are_named(tmp_path):
    cls, valid = [[0, STOP], [0, STOP]], [[True, True], [True, True]]
    good = _scores([[3.0, 1.0], [2.0, 1.0]], cls, valid)
    nan = {**good, "location": np.array([[np.nan, 1.0], [2.0, 1.0]], np.float32)}
    np.savez(tmp_path / "nan.npz", **nan)
    with pytest.raises(ValueError, match=r"nan.npz: field 'location': NaN or inf at an actor"):
        load_scores(str(tmp_path / "nan.npz"))
    # NaN at a padded step (not an actor's) is no actor's NLL: read as it is.
    pad = {**good, "location": np.array([[3.0, 1.0], [2.0, np.nan]], np.float32),
           "step_valid": np.array([[True, True], [True, False]])}
    np.savez(tmp_path / "pad.npz", **pad)
    assert load_scores(str(tmp_path / "pad.npz"))["location"].shape == (2, 2)
    np.savez(tmp_path / "short.npz", **{**good, "box": np.zeros((2, 1), np.float32)})
    with pytest.raises(ValueError, match=r"short.npz: field 'box': shape \(2, 1\)"):
        load_scores(str(tmp_path / "short.npz"))
    np.savez(tmp_path / "objects.npz", **{**good, "class": np.array([None, 1], object)})
    with pytest.raises(ValueError, match="objects.npz: not a `score --actors-out` .npz"):
        load_scores(str(tmp_path / "objects.npz"))
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(ValueError, match=r"one.npy: not a `score --actors-out` .npz \(one "
                       r"float64 array of shape \(3,\)\)"):
        load_scores(str(tmp_path / "one.npy"))
    (tmp_path / "scores.csv").write_text("scene,nll\n0,1.0\n")
    with pytest.raises(ValueError, match="scores.csv: not a `score --actors-out` .npz"):
        load_scores(str(tmp_path / "scores.csv"))
    for option, value in (("block", 0), ("samples", -5), ("seed", -1)):
        with pytest.raises(ValueError, match=f"--{option}: expected an integer >= "):
            paired_difference([good], [good], **{option: value})
