"""`scenegen sample` end to end, and the given actors' records (`--given`): values, overlaps
with each other and with the egos of the scenes they meet, validation."""

from __future__ import annotations

import json
import math
import os
import re

import numpy as np
import pytest
from sampling_helpers import (
    TINY,
    write_val_cache,
)

from scenegen_jax.sampling import (
    actor_records,
    actors_from_records,
)
from scenegen_jax.train.step import init_state


@pytest.fixture(scope="module")
def val_cache(tmp_path_factory, data_root):
    """A tiny-config cache of every 20th validation frame (8 scenes)."""
    return write_val_cache(str(tmp_path_factory.mktemp("cache_val_tiny")), data_root)


def test_cli_sample_end_to_end(tmp_path, val_cache, monkeypatch):
    """A workdir holding an (untrained) checkpoint -> `scenegen sample` outputs."""
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.cli import main
    from scenegen_jax.data.scenarionet import frames_from_scenario, read_scenario
    from scenegen_jax.train.loop import save_or_check_config

    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, TINY)
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1)
    ckpt.save(init_state(TINY), force=True)
    ckpt.close()
    given = tmp_path / "given.jsonl"
    given.write_text(json.dumps({"actors": [
        {"class": "vehicle", "x": 12.0, "y": 3.5, "width": 2.0, "length": 4.6, "heading": 0.1,
         "vx": 5.0, "vy": 0.0},
        {"class": "pedestrian", "x": -20.0, "y": 25.0, "vx": 1.0, "vy": 0.5},
    ]}) + "\n")
    out = tmp_path / "out"
    argv = ["sample", "--workdir", workdir, "--data", val_cache.path, "--num", "2",
            "--out", str(out), "--seed", "3", "--index", "1", "5", "--batch-size", "1",
            "--heatmaps", "--given", str(given)]
    main(argv)
    rows = [json.loads(line) for line in (out / "scenes.jsonl").read_text().splitlines()]
    assert [r["map_index"] for r in rows] == [1, 5]
    for r in rows:
        assert r["num_given"] == 2 and len(r["actors"]) >= 2
        first = r["actors"][:2]
        assert first[0]["class"] == "pedestrian" and first[1]["class"] == "vehicle"
        assert first[1]["x"] == pytest.approx(12.0) and first[1]["heading"] == pytest.approx(0.1)
        for rec in r["actors"]:
            assert all(math.isfinite(rec[k]) for k in ("x", "y", "width", "length", "heading",
                                                        "vx", "vy"))
            assert (
                abs(rec["x"]) < TINY.grid.region_m / 2 and abs(rec["y"]) <= TINY.grid.region_m / 2
            )
    for r in rows:
        assert (out / "png" / f"{r['scene']}.png").stat().st_size > 1000
        assert (out / "heatmaps" / f"{r['scene']}.png").stat().st_size > 1000
        scenario = read_scenario(out / "scenarionet" / f"sd_scenegen_{r['scene']}.pkl")
        ((frame, _),) = frames_from_scenario(scenario, "test")
        assert frame.num_actors == len(r["actors"])
        got = sorted(map(tuple, frame.position.round(3)))
        want = sorted((round(a["x"], 3), round(a["y"], 3)) for a in r["actors"])
        np.testing.assert_allclose(got, want, atol=2e-3)
    assert (out / "scenarionet" / "dataset_summary.pkl").exists()
    # The same seed reproduces the scenes exactly.
    first = (out / "scenes.jsonl").read_text()
    main(argv[:8] + [str(tmp_path / "again")] + argv[9:])
    assert (tmp_path / "again" / "scenes.jsonl").read_text() == first
    # The records parse back (as --given input) to the same actors.
    rec = actors_from_records(rows[0]["actors"], TINY, "roundtrip")
    assert actor_records(rec) == rows[0]["actors"]
    # Given boxes that overlap the ego of a cache scene exit 2 naming the line and the actor;
    # --allow-overlap keeps them.
    overlapping = tmp_path / "overlapping.jsonl"
    overlapping.write_text(
        "\n"
        + json.dumps(
            {
                "actors": [
                    {
                        "class": "vehicle",
                        "x": 3.0,
                        "y": 0.5,
                        "width": 2.0,
                        "length": 4.6,
                        "heading": 0.1,
                        "vx": 0.0,
                        "vy": 0.0,
                    }
                ]
            }
        )
        + "\n"
    )
    bad = argv[:8] + [str(tmp_path / "bad")] + argv[9:-1] + [str(overlapping)]
    with pytest.raises(SystemExit) as exit_info:
        main(bad)
    assert exit_info.value.code == 2
    assert re.match(
        rf"{re.escape(str(overlapping))}:2: actors\[0\] \(vehicle at x=3 m, y=0.5 m\) "
        r"overlaps the ego \(width 1.95 m, length 4.88 m",
        str(exit_info.value.__cause__),
    )
    main(bad + ["--allow-overlap"])
    rows = [json.loads(line) for line in (tmp_path / "bad" / "scenes.jsonl").open()]
    assert [(r["num_given"], r["actors"][0]["x"]) for r in rows] == [(1, pytest.approx(3.0))] * 2
    # Stopped after its first scene (Ctrl-C): exit 130 and no scenes.jsonl, nor a partial one,
    # that would pass for a finished run's.
    import scenegen_jax.cli.sample as sample_cli

    written = []

    def stopped(*a, **k):
        if written:
            raise KeyboardInterrupt
        written.append(1)
        return sample_cli_write(*a, **k)

    sample_cli_write = sample_cli.write_sampled
    monkeypatch.setattr(sample_cli, "write_sampled", stopped)
    with pytest.raises(SystemExit) as exit_info:
        main(argv[:8] + [str(tmp_path / "stopped")] + argv[9:])
    assert exit_info.value.code == 130 and written
    assert len(os.listdir(tmp_path / "stopped" / "png")) == 1
    assert not [n for n in os.listdir(tmp_path / "stopped") if n.startswith("scenes.jsonl")]


def _vehicle(x, y, heading=0.0, width=2.0, length=4.0, cls="vehicle"):
    return {
        "class": cls,
        "x": x,
        "y": y,
        "width": width,
        "length": length,
        "heading": heading,
        "vx": 0.0,
        "vy": 0.0,
    }


def test_given_values_must_be_finite_numbers():
    for key, value, message in [
        ("x", True, r"not a number \(True\)"),
        ("y", "5", r"not a number \('5'\)"),
        ("vx", False, r"not a number \(False\)"),
        ("width", [2.0], r"not a number"),
        ("heading", float("inf"), "NaN or inf"),
        ("vy", float("nan"), "NaN or inf"),
        ("length", 10**400, "out of range"),
    ]:
        with pytest.raises(ValueError, match=rf"^f\.jsonl:3: actors\[1\]\.{key}: {message}"):
            actors_from_records(
                [_vehicle(20.0, 5.0), {**_vehicle(10.0, -5.0), key: value}], TINY, "f.jsonl:3"
            )
    # JSON's NaN and Infinity literals are read by json.loads and refused the same way.
    row = json.loads('{"class": "pedestrian", "x": 1.0, "y": Infinity, "vx": 0, "vy": 0}')
    with pytest.raises(ValueError, match=r"actors\[0\]\.y: NaN or inf"):
        actors_from_records([row], TINY, "f.jsonl:1")


def test_given_overlaps_are_refused_unless_allowed():
    ego = np.array([[2.0, 4.0]])  # width, length m; at the origin, heading 0
    pair = [_vehicle(20.0, 5.0), _vehicle(10.0, 5.0), _vehicle(12.0, 6.5, heading=0.3)]
    with pytest.raises(
        ValueError,
        match=r"^f\.jsonl:2: actors\[1\] \(vehicle at x=10 m, "
        r"y=5 m\) and actors\[2\] \(vehicle at x=12 m, y=6\.5 m\) overlap; "
        r"pass --allow-overlap",
    ):
        actors_from_records(pair, TINY, "f.jsonl:2", ego)
    on_ego = [_vehicle(-20.0, 5.0), _vehicle(1.5, 1.2, width=0.7, length=1.8, cls="bicyclist")]
    with pytest.raises(
        ValueError,
        match=r"^f\.jsonl:2: actors\[1\] \(bicyclist at x=1\.5 m, "
        r"y=1\.2 m\) overlaps the ego \(width 2 m, length 4 m at the origin\)",
    ):
        actors_from_records(on_ego, TINY, "f.jsonl:2", ego)
    for records in (pair, on_ego):  # allowed: kept unchanged
        kept = actors_from_records(records, TINY, "f.jsonl:2", ego, allow_overlap=True)
        assert sorted(r["x"] for r in actor_records(kept)) == sorted(r["x"] for r in records)
    # Touching is not overlapping; pedestrians are points (as in collision rejection); each
    # ego size given is checked (a longer ego reaches the vehicle ahead).
    ahead = [
        _vehicle(4.0, 0.0),
        _vehicle(0.0, 3.5, heading=math.pi / 2),
        {"class": "pedestrian", "x": 0.2, "y": 0.0, "vx": 0.0, "vy": 0.0},
    ]
    assert int(actors_from_records(ahead, TINY, "f", ego).valid.sum()) == 3
    with pytest.raises(
        ValueError,
        match=r"actors\[0\] .* overlaps the ego \(width 2 m, "
        r"length 6 m",
    ):
        actors_from_records(ahead, TINY, "f", np.array([[2.0, 4.0], [2.0, 6.0]]))


def test_given_lines_are_checked_against_the_egos_they_meet():
    from scenegen_jax.cli import build_parser
    from scenegen_jax.sampling.export import given_from_lines

    ahead = json.dumps({"actors": [_vehicle(6.0, 0.0)]})  # x in [4, 8] m
    lines = [ahead, "", ahead]
    egos = np.array([[2.0, 4.0], [2.0, 10.0], [2.0, 4.0]])  # scenes 0, 1, 2: lines 1, 3, 1
    with pytest.raises(
        ValueError,
        match=r"^given.jsonl:3: actors\[0\] .* overlaps "
        r"the ego \(width 2 m, length 10 m",
    ):
        given_from_lines(lines, "given.jsonl", TINY, egos)
    assert len(given_from_lines(lines, "given.jsonl", TINY, egos[[0, 2, 0]])) == 2
    assert len(given_from_lines(lines, "given.jsonl", TINY, egos, allow_overlap=True)) == 2
    args = ["sample", "--workdir", "w", "--data", "d", "--num", "1", "--out", "o"]
    assert build_parser().parse_args(args + ["--allow-overlap"]).allow_overlap
    assert not build_parser().parse_args(args).allow_overlap


def test_given_records_are_validated():
    # Each error names the file and line, then the actor's field.
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors\[0\]\.class: 'truck' is not"):
        actors_from_records([{"class": "truck", "x": 0, "y": 0}], TINY, "f.jsonl:1")
    ok = {"class": "pedestrian", "x": 0, "y": 0, "vx": 0, "vy": 0}
    with pytest.raises(
        ValueError,
        match=r"^f\.jsonl:1: actors\[1\]\.x/y: \(40, 0\) m lies "
        r"outside the 80 m region",
    ):  # the region is [-40, 40) m
        actors_from_records([ok, {**ok, "x": 40.0}], TINY, "f.jsonl:1")
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors\[0\]\.width/length: box sizes"):
        actors_from_records(
            [
                {
                    "class": "vehicle",
                    "x": 1,
                    "y": 1,
                    "width": 0,
                    "length": 4,
                    "heading": 0,
                    "vx": 0,
                    "vy": 0,
                }
            ],
            TINY,
            "f.jsonl:1",
        )
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors\[0\]\.x: NaN or inf"):
        actors_from_records(
            [
                {
                    "class": "vehicle",
                    "x": float("nan"),
                    "y": 1,
                    "width": 2,
                    "length": 4,
                    "heading": 0,
                    "vx": 0,
                    "vy": 0,
                }
            ],
            TINY,
            "f.jsonl:1",
        )
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors\[0\]\.vx: out of range$"):
        actors_from_records([{**ok, "vx": 10**39}], TINY, "f.jsonl:1")  # float32 tops 3.4e38
    with pytest.raises(ValueError, match=r"^f\.jsonl:1: actors: 50 actors, more than max_actors"):
        actors_from_records([ok] * 50, TINY, "f.jsonl:1")


def test_given_actors_are_held_to_the_readers_road_user_limits():
    """What prepare drops (`frame.drop_beyond_limits`) is refused as given, naming the line."""
    from scenegen_jax.sampling.export import given_from_lines

    fast = {**_vehicle(20.0, 5.0), "vx": 1e6}
    huge = _vehicle(-20.0, -15.0, width=31.0, length=35.0)
    crowd = {"class": "pedestrian", "x": 5.0, "y": 5.0, "width": 40.0, "vx": 0, "vy": 0}
    lines = [json.dumps({"actors": [_vehicle(20.0, 5.0)]}), json.dumps({"actors": [fast]})]
    with pytest.raises(ValueError, match=r"^g\.jsonl:2: actors\[0\]\.vx/vy: speed 1e\+06 m/s, "
                       r"beyond 100 m/s$"):
        given_from_lines(lines, "g.jsonl", TINY, np.array([[2.0, 4.0]]))
    with pytest.raises(ValueError, match=r"^f:1: actors\[1\]\.width/length: \(31, 35\) m, "
                       r"beyond 30 m$"):
        actors_from_records([_vehicle(20.0, 5.0), huge], TINY, "f:1")
    with pytest.raises(ValueError, match=r"actors\[0\]\.width/length: \(40, 0\.6\) m"):
        actors_from_records([crowd], TINY, "f:1")
    at_limits = [{**_vehicle(20.0, 5.0, width=2.5, length=30.0), "vx": 60.0, "vy": 80.0}]
    assert int(actors_from_records(at_limits, TINY, "f:1").valid.sum()) == 1


def test_a_sample_stopped_before_writing_removes_the_out_folder_it_made(tmp_path, val_cache,
                                                                       monkeypatch):
    """SIGINT before the first scene is written: the --out folders this run made are gone;
    a folder that was there before stays."""
    import signal

    import scenegen_jax.sampling.batch as batch
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.cli import main
    from scenegen_jax.signals import Stopped
    from scenegen_jax.train.loop import save_or_check_config

    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, TINY)
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1)
    ckpt.save(init_state(TINY), force=True)
    ckpt.close()

    def interrupted(*args, **kwargs):
        raise Stopped(signal.SIGINT)

    monkeypatch.setattr(batch, "sample_on_cache", interrupted)
    argv = ["sample", "--workdir", workdir, "--data", val_cache.path, "--num", "1", "--out"]
    mine = tmp_path / "mine"
    mine.mkdir()
    for out in (tmp_path / "new" / "out", mine):
        with pytest.raises(SystemExit) as exit_info:
            main([*argv, str(out)])
        assert exit_info.value.code == 130
    assert not (tmp_path / "new").exists()  # made by the run: removed, its parent too
    assert os.listdir(mine) == []  # there before: kept, without the run's empty folders
