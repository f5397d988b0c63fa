"""The training driver (`train.loop`) and its workdir: a saved step read back, the moving
average saved and resumed, the compilation cache, a killed run resumed exactly, the logged
metrics."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from small import (
    CFG,
    metrics_rows,
    train_args,
    train_cmd,
    two_small_scenes,
)
from train_batches import batch_of

from scenegen_jax import cli
from scenegen_jax.train.step import (
    init_state,
    make_train_step,
)


@pytest.fixture(scope="module")
def small_scenes(tiny_train_cache):
    return two_small_scenes(tiny_train_cache)


def _params(workdir, step=None):
    from scenegen_jax.train.loop import load_trained

    cfg, state = load_trained(workdir, step)
    return int(state.step), jax.tree.leaves(state.params)


def test_load_trained_picks_a_saved_step(tmp_path):
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.train.loop import load_trained, save_or_check_config

    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, CFG)
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1, keep=5)
    state = init_state(CFG)
    for step in (1, 2):
        ckpt.save(state._replace(step=jnp.asarray(step, state.step.dtype)), force=True)
    ckpt.close()
    assert int(load_trained(workdir)[1].step) == 2
    assert int(load_trained(workdir, 1)[1].step) == 1
    with pytest.raises(ValueError, match=r"no checkpoint at step 5; saved: \[1, 2\]"):
        load_trained(workdir, 5)


def _saved_entries(folder: str) -> str:
    """The text of orbax's tree metadata of a saved step (its entries' key paths)."""
    paths = [os.path.join(d, "_METADATA") for d, _, files in os.walk(folder)
             if "_METADATA" in files]
    assert paths, f"no orbax metadata under {folder}"
    return "".join(open(p).read() for p in paths)


def test_ema_averages_every_steps_parameters_resumes_and_is_what_the_workdir_gives(
        tiny_train_cache, small_scenes, tmp_path):
    """With `ema_decay` d the state carries a_k = d a_(k-1) + (1 - d) p_k from the starting
    parameters (the recurrence in numpy over the steps' own parameters), in buffers of its
    own (the donating step takes both); a checkpoint keeps it and a resumed step continues
    it; `load_params` (what score, sample, export-model and --init-from read) gives it, and
    without `ema_decay` the last parameters, saved without an `ema` entry."""
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.train.loop import load_trained, save_or_check_config
    from scenegen_jax.workdir import load_params

    cfg = CFG.replace(ema_decay=0.75)
    step = make_train_step(cfg)
    batch = batch_of(tiny_train_cache, small_scenes)
    state = init_state(cfg)
    average = [np.asarray(x) for x in jax.tree.leaves(state.params)]
    saved_at_two = None
    for k in range(3):
        state, _ = step(state, batch)
        average = [0.75 * a + 0.25 * np.asarray(p)
                   for a, p in zip(average, jax.tree.leaves(state.params), strict=True)]
        if k == 1:
            workdir = str(tmp_path / "ema")
            save_or_check_config(workdir, cfg)
            ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1)
            ckpt.save(state, force=True)
            ckpt.close()
            saved_at_two = [a.copy() for a in average]
    for a, e in zip(jax.tree.leaves(state.ema), average, strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-6, atol=1e-7)
    moved = [np.abs(np.asarray(e) - np.asarray(p)).max()
             for e, p in zip(jax.tree.leaves(state.ema), jax.tree.leaves(state.params),
                             strict=True)]
    assert max(moved) > 1e-4, "the average lags the parameters"

    cfg_read, params, at = load_params(workdir)
    assert at == 2 and cfg_read.train.ema_decay == 0.75
    for a, e in zip(jax.tree.leaves(params), saved_at_two, strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-6, atol=1e-7)
    _, resumed = load_trained(workdir)
    resumed, _ = step(resumed, batch)
    for a, e in zip(jax.tree.leaves(resumed.ema), jax.tree.leaves(state.ema), strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-6, atol=1e-7)

    plain = str(tmp_path / "plain")
    save_or_check_config(plain, CFG)
    ckpt = Checkpointer(os.path.join(plain, "checkpoints"), every=1)
    ckpt.save(state._replace(ema=None, step=jnp.asarray(7, jnp.int32)), force=True)
    ckpt.close()
    assert "('ema'," in _saved_entries(os.path.join(workdir, "checkpoints", "2"))
    assert "('ema'," not in _saved_entries(os.path.join(plain, "checkpoints", "7"))
    _, params, _ = load_params(plain)
    for a, e in zip(jax.tree.leaves(params), jax.tree.leaves(state.params), strict=True):
        np.testing.assert_array_equal(a, e)
    assert load_trained(plain)[1].ema is None


def test_compile_cache_is_written_where_configured(tmp_path):
    script = """
import json, os, jax, jax.numpy as jnp
from scenegen_jax.cli import enable_compile_cache
os.environ["SCENEGEN_COMPILE_CACHE"] = "off"
off = enable_compile_cache()
del os.environ["SCENEGEN_COMPILE_CACHE"]
on = enable_compile_cache()
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.jit(lambda x: jnp.cumsum(x) * 3)(jnp.arange(5.0)).block_until_ready()
print(json.dumps({"off": off, "on": on, "files": sorted(os.listdir(on))}))
"""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION", "SCENEGEN"))}
    env.update(XDG_CACHE_HOME=str(tmp_path), JAX_PLATFORMS="cpu")
    res = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.splitlines()[-1])
    assert out["off"] is None
    assert out["on"] == str(tmp_path / "scenegen_jax" / "jax")
    assert any(f.startswith("jit__lambda-") for f in out["files"]), out["files"]


@pytest.mark.slow
def test_killed_run_resumes_exactly(tiny_train_cache, tmp_path):
    cache = tiny_train_cache.path
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    steps = 10
    full = str(tmp_path / "full")
    cli.main(train_args(cache, full, steps))  # in this process: CFG's programs are traced

    killed = str(tmp_path / "killed")
    proc = subprocess.Popen(
        train_cmd(cache, killed, steps),
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    ckpts = os.path.join(killed, "checkpoints")
    deadline = time.time() + 300
    while time.time() < deadline:
        done = [d for d in os.listdir(ckpts)] if os.path.isdir(ckpts) else []
        if any(d.isdigit() and int(d) >= 4 for d in done):
            break
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    step_at_kill, _ = _params(killed)
    assert 4 <= step_at_kill < steps
    metrics = os.path.join(killed, "metrics.jsonl")
    before = [row for row in metrics_rows(metrics) if json.loads(row)["step"] <= step_at_kill]
    assert len(before) == step_at_kill // 2  # a row every 2 steps, each before its checkpoint
    cli.main(train_args(cache, killed, steps))  # resumes from the killed process's checkpoint
    # The killed process's rows stay as it wrote them, timings included: the run went on from
    # its checkpoint (a run started again from step 0 would rewrite them) ...
    after = metrics_rows(metrics)
    assert after[: len(before)] == before
    assert [json.loads(row)["step"] for row in after] == list(range(2, steps + 1, 2))
    assert not os.path.exists(ckpts + ".damaged")  # ... and set no checkpoint aside

    s_full, p_full = _params(full)
    s_killed, p_killed = _params(killed)
    assert s_full == s_killed == steps
    for a, b in zip(p_full, p_killed, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6, rtol=0)


def test_logged_metrics_are_means_over_the_logged_steps():
    """`summarize` on hand-made sums of two steps: loss and gradient norm per batch, NLL per
    scene, per actor of each class and per vehicle (the box term per vehicle with a measured
    box); None for a class with no actor."""
    from scenegen_jax.train.loop import summarize

    stats = {"batches": 2, "scenes": 8, "loss": 30.0, "grad_norm": 5.0, "nll_sum_stop": 4.0,
             **{f"nll_{k}": 16.0 for k in ("class", "location", "box", "heading", "velocity")},
             "count_vehicle": 10, "count_box_vehicle": 6, "nll_sum_vehicle": 25.0,
             "count_pedestrian": 4,
             "nll_sum_pedestrian": 2.0, "count_bicyclist": 0, "nll_sum_bicyclist": 0.0,
             **{f"nll_{k}_sum_vehicle": 3.0 for k in ("location", "box", "heading", "velocity")}}
    row = summarize(stats)
    assert row["loss"] == 15.0 and row["grad_norm"] == 2.5
    assert row["nll_location"] == 2.0 and row["nll_stop"] == 0.5
    assert row["nll_per_vehicle"] == 2.5 and row["nll_per_pedestrian"] == 0.5
    assert row["nll_per_bicyclist"] is None
    assert row["heading_per_vehicle"] == pytest.approx(0.3)
    assert row["box_per_vehicle"] == pytest.approx(0.5)  # over the 6 measured boxes


def _rows_without_timing(path: str) -> list[dict]:
    return [{k: v for k, v in json.loads(row).items() if k != "steps_per_s"}
            for row in metrics_rows(path)]


def test_a_resumed_run_logs_the_rows_of_the_uninterrupted_one(tiny_train_cache, tmp_path):
    """Checkpoints every 3 steps, a row every 2: the run stopped after step 4 resumes from
    step 3, and its row of step 4 averages steps 3 and 4 as the uninterrupted run's did (the
    checkpoint keeps the sums of the steps since the last row), not step 4 alone."""
    import shutil

    from scenegen_jax.train.loop import train

    full = str(tmp_path / "full")
    train(CFG, tiny_train_cache.path, full, 6, save_every=3, log_every=2, progress=False)
    stopped = str(tmp_path / "stopped")
    shutil.copytree(full, stopped)
    shutil.rmtree(os.path.join(stopped, "checkpoints", "6"))  # as a kill before step 6's save
    train(CFG, tiny_train_cache.path, stopped, 6, save_every=3, log_every=2, progress=False)
    want = _rows_without_timing(os.path.join(full, "metrics.jsonl"))
    assert [r["step"] for r in want] == [2, 4, 6]
    assert _rows_without_timing(os.path.join(stopped, "metrics.jsonl")) == want


def test_a_run_that_fails_before_its_first_checkpoint_leaves_the_workdir_as_found(
        tiny_train_cache, tmp_path):
    """A run that fails before its first checkpoint removes what it wrote (config.json,
    data.json, checkpoints/, the folders it made), and config and data files without a
    checkpoint (a run killed before its first) bind nothing: the corrected rerun trains."""
    from scenegen_jax.train.loop import save_or_check_config, train

    cache = tiny_train_cache.path
    broken = CFG.replace(train_params=("nonexistent",))  # refused when the step is built
    new = tmp_path / "new" / "run"
    with pytest.raises(ValueError, match="train_params: no parameter"):
        train(broken, cache, str(new), 2, progress=False)
    assert not (tmp_path / "new").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's")
    with pytest.raises(ValueError, match="train_params: no parameter"):
        train(broken, cache, str(mine), 2, progress=False)
    assert sorted(os.listdir(mine)) == ["notes.txt"]
    # What a run killed before its first checkpoint leaves: another config and other data.
    save_or_check_config(str(mine), CFG.replace(seed=5))
    other = {"caches": [{"path": str(tmp_path / "other"), "source": "av2", "scenes": 3}],
             "weights": None, "shares": [1.0]}
    (mine / "data.json").write_text(json.dumps(other))
    state = train(CFG, cache, str(mine), 1, progress=False)
    assert int(state.step) == 1
    with open(mine / "config.json") as f:
        assert json.load(f)["train"]["seed"] == CFG.train.seed


def test_a_diverged_run_is_one_line_naming_the_step_and_the_learning_rate(
        tiny_train_cache, tmp_path, caplog):
    import logging

    args = [*train_args(tiny_train_cache.path, str(tmp_path / "w"), 4, "--log-every", "1"),
            "learning_rate=1e9"]  # one more --set
    with caplog.at_level(logging.ERROR, logger="scenegen"), pytest.raises(SystemExit) as e:
        cli.main(args)
    errors = [r for r in caplog.records if r.name == "scenegen"]
    assert e.value.code == 2 and len(errors) == 1, [r.getMessage() for r in errors]
    message = errors[0].getMessage()
    assert re.search(r"training diverged: the loss is nan at step \d+; lower --set "
                     r"learning_rate \(now 1e\+09\)", message), message
    assert "\n" not in message and not errors[0].exc_info


def test_the_loss_check_names_the_steps_of_the_row():
    from scenegen_jax.train.loop import NonFiniteLoss, check_finite_loss

    check_finite_loss(3.0, 0, 10, CFG)
    with pytest.raises(NonFiniteLoss, match=r"the loss is inf at steps 11-20; lower"):
        check_finite_loss(float("inf"), 10, 20, CFG)
    with pytest.raises(ValueError, match=r"the loss is nan at step 2; lower"):  # the CLI's
        check_finite_loss(float("nan"), 1, 2, CFG)
