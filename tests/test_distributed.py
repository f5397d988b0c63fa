"""Multi-process training: two `scenegen train --distributed` processes on this machine."""

from __future__ import annotations

import csv
import json
import os
import socket
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
from small import (
    assert_same_adam_training,
    metrics_rows,
    train_args,
    train_cmd,
    with_xla_flags,
)

from scenegen_jax import cli
from scenegen_jax.backend import cpu_cores
from scenegen_jax.data.safe_pickle import load_pickle
from scenegen_jax.train.loop import load_trained
from scenegen_jax.train.step import init_state


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _launch_two_processes(cache, workdir, steps, env, logs):
    """Two `scenegen train --distributed` processes on this machine (one CPU device each)."""
    port = _free_port()
    procs = []
    for i in range(2):
        cmd = train_cmd(cache, workdir, steps, "--keep", "20", "--distributed",
                         "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2",
                         "--process-id", str(i))
        log = open(logs / f"{os.path.basename(workdir)}_{i}_{len(list(logs.iterdir()))}.log", "w")
        procs.append(subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT))
    return procs


def _wait(procs, logs, timeout=240):
    for p in procs:
        rc = p.wait(timeout=timeout)
        if rc:
            text = "\n".join(f.read_text()[-1500:] for f in sorted(logs.iterdir()))
            raise AssertionError(f"a process exited with {rc}:\n{text}")


def _assert_same_training(workdir_a, workdir_b, step):
    """The two workdirs' parameters at `step` are those of one training
    (`small.assert_same_adam_training`)."""
    from flax.traverse_util import flatten_dict

    cfg, a = load_trained(workdir_a, step)
    _, b = load_trained(workdir_b, step)
    init, a, b = (flatten_dict(jax.device_get(p), sep="/")
                  for p in (init_state(cfg).params, a.params, b.params))
    assert_same_adam_training(init, a, b, cfg.train.learning_rate, step)


@pytest.fixture(scope="module")
def single_run(tiny_train_cache, tmp_path_factory) -> str:
    """A workdir trained by one process for 8 steps, every even step's checkpoint kept."""
    single = str(tmp_path_factory.mktemp("single") / "run")
    cli.main(train_args(tiny_train_cache.path, single, 8, "--keep", "20"))  # in this process
    return single


@pytest.mark.slow
def test_two_process_training_equals_one_process_and_resumes(
    tiny_train_cache, single_run, tmp_path
):
    """Two processes (coordinator on 127.0.0.1), each feeding its half of every global batch:
    the same parameters as one process with the whole batch; after a kill of one process and
    a restart of both, the same parameters as the uninterrupted run."""
    cache, single = tiny_train_cache.path, single_run
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    logs = tmp_path / "logs"
    logs.mkdir()

    pair = tmp_path / "pair"
    procs = _launch_two_processes(cache, str(pair), 100, env, logs)
    ckpts = pair / "checkpoints"
    deadline = time.time() + 240
    while time.time() < deadline and not [
        d for d in ckpts.glob("[0-9]*/scenegen_sha256.json") if int(d.parent.name) >= 2
    ]:
        assert all(p.poll() is None for p in procs), [f.read_text() for f in logs.iterdir()]
        time.sleep(0.1)
    procs[1].kill()  # one process dies; the other cannot go on alone: a restart of both
    procs[0].kill()
    for p in procs:
        p.wait()
    at_kill = int(load_trained(str(pair))[1].step)
    assert 2 <= at_kill <= 6, at_kill
    _assert_same_training(single, str(pair), at_kill)
    metrics = str(pair / "metrics.jsonl")
    before = [row for row in metrics_rows(metrics) if json.loads(row)["step"] <= at_kill]
    assert len(before) == at_kill // 2

    _wait(_launch_two_processes(cache, str(pair), at_kill + 2, env, logs), logs)
    assert int(load_trained(str(pair))[1].step) == at_kill + 2
    _assert_same_training(single, str(pair), at_kill + 2)
    # Process 0 alone writes the metrics: one row per logged step, replayed rows dropped; the
    # rows before the kill stay as written (timings included), so the pair resumed from its
    # checkpoint rather than starting again, and set none aside as damaged.
    after = metrics_rows(metrics)
    assert after[: len(before)] == before
    assert [json.loads(row)["step"] for row in after] == list(range(2, at_kill + 3, 2))
    assert not os.path.exists(str(ckpts) + ".damaged")


def _launch(argv, env, logs, processes=1):
    """`scenegen ARGV` in this process (`env` None), as one process, or as `processes` joined
    by --distributed."""
    if env is None:
        cli.main(argv)
        return
    port = _free_port()
    procs = []
    for i in range(processes):
        cmd = [sys.executable, "-m", "scenegen_jax.cli", *argv]
        if processes > 1:
            cmd += ["--distributed", "--coordinator", f"127.0.0.1:{port}", "--num-processes",
                    str(processes), "--process-id", str(i)]
        log = open(logs / f"{argv[0]}_{processes}_{i}_{len(list(logs.iterdir()))}.log", "w")
        procs.append(subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT))
    _wait(procs, logs)


def _read_csv(path):
    with open(path) as f:
        rows = list(csv.reader(f))
    return rows[0], [r[:2] + [float(x) for x in r[2:-1]] + r[-1:] for r in rows[1:]]


@pytest.mark.slow
def test_score_and_sample_on_several_devices_and_two_processes(
    tiny_train_cache, single_run, tmp_path
):
    """`score` and `sample` give the same files on one device, on several devices of one
    process, and split over two processes (each its share of the scenes, merged by
    process 0), bit for bit.

    As many devices as cores, 2 to 4: XLA:CPU sizes its thread pool to the larger of the
    cores and the devices, and splits a program's loops into as many parts as it has
    threads, which moves a float step between the vector loop and its scalar remainder (a
    box a float step wider from the same key). Within one thread count the devices must not
    matter."""
    cache = tiny_train_cache.path
    logs = tmp_path / "logs"
    logs.mkdir()
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    workdir = single_run
    devices = min(4, max(2, cpu_cores()))
    runs = {"one": (None, 1),  # in this process, as single_run trained
            "devices": (with_xla_flags(
                env, f"--xla_force_host_platform_device_count={devices}"), 1),
            "two_processes": (env, 2)}
    for name, (run_env, processes) in runs.items():
        out = tmp_path / name
        _launch(["score", "--workdir", workdir, "--data", cache, "--out", str(out / "s.csv"),
                 "--batch-size", "8"], run_env, logs, processes)
        _launch(["sample", "--workdir", workdir, "--data", cache, "--num", "5", "--seed", "3",
                 "--batch-size", "2", "--out", str(out / "samples")], run_env, logs, processes)
    header, want = _read_csv(tmp_path / "one" / "s.csv")
    assert len(want) == len(tiny_train_cache)
    want_lines = (tmp_path / "one" / "samples" / "scenes.jsonl").read_text().splitlines()
    assert len(want_lines) == 5
    for name in ("devices", "two_processes"):
        got_header, got = _read_csv(tmp_path / name / "s.csv")
        assert got_header == header and len(got) == len(want)
        for a, b in zip(want, got, strict=True):
            assert a[:3] == b[:3] and a[-1] == b[-1]
            np.testing.assert_array_equal(a[3:-1], b[3:-1])
        samples = tmp_path / name / "samples"
        assert samples.joinpath("scenes.jsonl").read_text().splitlines() == want_lines
        assert sorted(p.name for p in samples.iterdir()) == ["png", "scenarionet", "scenes.jsonl"]
        assert len(list(samples.joinpath("png").iterdir())) == 5
        index = load_pickle(samples / "scenarionet" / "dataset_summary.pkl")
        want_index = load_pickle(tmp_path / "one" / "samples" / "scenarionet" /
                                 "dataset_summary.pkl")
        assert list(index) == list(want_index) and len(index) == 5
