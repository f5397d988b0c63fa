"""Two things at once, and stops at random moments, on the real command line.

Two `train` and two `prepare` started together on one target: one works, the other is
refused in one line naming the first. SIGINT (to the process group, as Ctrl-C sends it),
SIGTERM or SIGKILL (to the command alone) at a random moment of `prepare`, `train`, `score`
or `sample`: no traceback, no process left behind, no partial output under a final name,
and the same command run again finishes; a stopped `train` then logs the uninterrupted
run's metrics. `make test` draws `SCENEGEN_STRESS_SEEDS` (default 3) cases, `make fuzz` 20.
"""

from __future__ import annotations

import json
import math
import os
import random
import signal
import subprocess
import sys
import time

import pytest
from processes import alive, children
from small import metrics_rows, train_cmd

from scenegen_jax.data.cache import load_cache

SEEDS = range(int(os.environ.get("SCENEGEN_STRESS_SEEDS", "3")))
STEPS = 6
COMMANDS = ("prepare", "train", "score", "sample")
STOPS = (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)
ENV = {**os.environ, "JAX_PLATFORMS": "cpu"}


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "scenegen_jax.cli", *args]


def _prepare_cmd(data_root: str, out: str) -> list[str]:
    return _cli("prepare", "--source", "av2", "--root", data_root, "--split", "val",
                "--config", "tiny", "--stride", "20", "--workers", "2", "--out", out)


def _command(name: str, paths: dict, out: str) -> list[str]:
    if name == "prepare":
        return _prepare_cmd(paths["data_root"], out)
    if name == "train":
        return train_cmd(paths["cache"], out, STEPS)
    if name == "score":
        return _cli("score", "--workdir", paths["model"], "--data", paths["cache"],
                    "--out", os.path.join(out, "scores.csv"))
    return _cli("sample", "--workdir", paths["model"], "--data", paths["cache"], "--num", "2",
                "--out", os.path.join(out, "samples"))


def _wait_gone(pids: set[int], seconds: float = 60.0) -> list[int]:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and any(alive(p) for p in pids):
        time.sleep(0.3)
    return [p for p in pids if alive(p)]


def _rows(path: str) -> list[dict]:
    return [{k: v for k, v in json.loads(r).items() if k != "steps_per_s"}
            for r in metrics_rows(path)]


def _check_finished(name: str, out: str, paths: dict) -> None:
    """The output of a command that finished: whole and complete."""
    if name == "prepare":
        assert len(load_cache(out)) == len(load_cache(paths["cache_val"]))
    elif name == "train":
        rows, want = _rows(os.path.join(out, "metrics.jsonl")), paths["reference_rows"]
        assert [r["step"] for r in rows] == [r["step"] for r in want]
        for row, ref in zip(rows, want, strict=True):
            assert row.keys() == ref.keys(), row["step"]
            for k, v in ref.items():
                same = row[k] == v or (isinstance(v, float) and math.isclose(row[k], v,
                                                                            rel_tol=1e-5))
                assert same, (row["step"], k, row[k], v)
    elif name == "score":
        with open(os.path.join(out, "scores.csv")) as f:
            assert len(f.read().splitlines()) == len(load_cache(paths["cache"])) + 1
    else:
        with open(os.path.join(out, "samples", "scenes.jsonl")) as f:
            assert len(f.read().splitlines()) == 2


def _temporaries(out: str) -> list[str]:
    return [os.path.join(d, n) for d, _, names in os.walk(out) for n in names if ".tmp" in n]


@pytest.fixture(scope="module")
def paths(tmp_path_factory, tiny_train_cache, data_root):
    """The inputs of every case: a small cache, a trained workdir and the rows it logged,
    and the val cache `prepare` writes in the cases."""
    root = tmp_path_factory.mktemp("stress")
    model = str(root / "model")
    subprocess.run(train_cmd(tiny_train_cache.path, model, STEPS), env=ENV, check=True,
                   capture_output=True)
    cache_val = str(root / "val")
    subprocess.run(_prepare_cmd(data_root, cache_val), env=ENV, check=True,
                   capture_output=True)
    return {"cache": tiny_train_cache.path, "model": model, "data_root": data_root,
            "cache_val": cache_val,
            "reference_rows": _rows(os.path.join(model, "metrics.jsonl"))}


@pytest.mark.slow
@pytest.mark.parametrize("name", ["train", "prepare"])
def test_two_started_together_one_works_the_other_is_refused(name, paths, tmp_path):
    out = str(tmp_path / "target")
    procs = [subprocess.Popen(_command(name, paths, out), env=ENV, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(timeout=600), p.communicate()[1]) for p in procs]
    assert sorted(rc for rc, _ in results) == [0, 2], results
    refused = next(err for rc, err in results if rc == 2)
    assert "locked by pid" in refused and "Traceback" not in refused
    _check_finished(name, out, paths)
    assert not _temporaries(out)


@pytest.mark.slow
@pytest.mark.parametrize("seed", SEEDS)
def test_a_stop_at_a_random_moment_leaves_nothing_half_done(seed, paths, tmp_path):
    rng = random.Random(seed)
    name, stop = rng.choice(COMMANDS), rng.choice(STOPS)
    delay = rng.uniform(0.5, 12.0)
    out = str(tmp_path / "out")
    if name != "train":
        os.makedirs(out)
    proc = subprocess.Popen(_command(name, paths, out), env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    watched: set[int] = set()
    deadline = time.monotonic() + delay
    while time.monotonic() < deadline and proc.poll() is None:
        watched |= children(proc.pid)
        time.sleep(0.05)
    case = f"seed {seed}: {stop.name} to {name} after {delay:.1f} s"
    if proc.poll() is None:
        watched |= children(proc.pid)
        if stop == signal.SIGINT:
            os.killpg(proc.pid, stop)  # Ctrl-C reaches the whole group
        else:
            os.kill(proc.pid, stop)
    _, err = proc.communicate(timeout=600)
    stopped = {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGKILL: -9}[stop]
    assert proc.returncode in (0, stopped), (case, err)
    if stop != signal.SIGKILL:
        assert "Traceback" not in err, (case, err)
        assert not _temporaries(out), case  # SIGKILL alone leaves its temporary files
    assert not _wait_gone(watched), case
    if proc.returncode == 0:
        _check_finished(name, out, paths)
        return
    again = subprocess.run(_command(name, paths, out), env=ENV, capture_output=True, text=True)
    assert again.returncode == 0, (case, again.stderr)
    _check_finished(name, out, paths)
