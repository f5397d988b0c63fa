"""Multi-process training: two `scenegen train --distributed` processes on this machine."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import time

import jax
import numpy as np
import pytest
from small import train_cmd

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
            raise AssertionError(f"a training process exited with {rc}:\n{text}")


# Conv biases followed by a GroupNorm (which removes them) and the location logits' bias
# (a softmax over the grid ignores it) have a gradient of exactly zero; their float noise
# is turned into steps of up to lr by Adam in any two runs that sum in different orders.
ZERO_GRADIENT = re.compile(r"^(backbone\d+|loc\d+)_b$")


def _assert_same_training(workdir_a, workdir_b, step):
    """Every parameter's change since initialisation agrees to 1e-3 of its size."""
    from flax.traverse_util import flatten_dict

    cfg, a = load_trained(workdir_a, step)
    _, b = load_trained(workdir_b, step)
    init = flatten_dict(jax.device_get(init_state(cfg).params), sep="/")
    a = flatten_dict(jax.device_get(a.params), sep="/")
    b = flatten_dict(jax.device_get(b.params), sep="/")
    compared = 0
    for name, x0 in init.items():
        if ZERO_GRADIENT.match(name):
            continue
        da, db = a[name] - x0, b[name] - x0
        assert np.linalg.norm(da - db) <= 1e-3 * np.linalg.norm(da) + 1e-7, (name, step)
        compared += 1
    assert compared > 20


@pytest.mark.slow
def test_two_process_training_equals_one_process_and_resumes(tiny_train_cache, tmp_path):
    """Two processes (coordinator on 127.0.0.1), each feeding its half of every global batch:
    the same parameters as one process with the whole batch; after a kill of one process and
    a restart of both, the same parameters as the uninterrupted run."""
    cache = tiny_train_cache.path
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    logs = tmp_path / "logs"
    logs.mkdir()
    single = str(tmp_path / "single")
    subprocess.run(train_cmd(cache, single, 8, "--keep", "20"), check=True, env=env,
                   capture_output=True)

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

    _wait(_launch_two_processes(cache, str(pair), at_kill + 2, env, logs), logs)
    assert int(load_trained(str(pair))[1].step) == at_kill + 2
    _assert_same_training(single, str(pair), at_kill + 2)
    # Process 0 alone writes the metrics: one row per logged step, replayed rows dropped.
    rows = [json.loads(line)["step"] for line in (pair / "metrics.jsonl").read_text().splitlines()]
    assert rows == list(range(2, at_kill + 3, 2))
