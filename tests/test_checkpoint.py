"""Checkpoints that heal and verify (real scenes, small tiny config, in process): a damaged
newest checkpoint is set aside and the rerun finishes at the uninterrupted run's parameters;
changed array bytes are caught by the checksums, changed or missing files before orbax reads
anything of the step; a step without checksums is incomplete, not loaded; one metrics row
per step after a resume; unfinished saves are removed."""

from __future__ import annotations

import json
import logging
import os
import shutil

import jax
import numpy as np
import pytest
from small import CFG

from scenegen_jax.checkpoint import (
    CHECKSUM_FILE,
    TMP_MARKER,
    Checkpointer,
    step_folders,
    tree_checksums,
)
from scenegen_jax.train.loop import load_trained, train
from scenegen_jax.train.step import init_state

STEPS, EVERY = 12, 4


@pytest.fixture(scope="module")
def uninterrupted(tiny_train_cache, tmp_path_factory):
    """A workdir trained STEPS steps without a stop, checkpoints every EVERY steps."""
    workdir = str(tmp_path_factory.mktemp("full") / "wd")
    train(CFG, tiny_train_cache.path, workdir, STEPS, save_every=EVERY, log_every=2,
          progress=False)
    return workdir


@pytest.fixture(scope="module")
def eight_steps(tiny_train_cache, tmp_path_factory):
    """A workdir trained 8 steps, checkpoints at 4 and 8 (keep 2): each test damages a copy."""
    workdir = str(tmp_path_factory.mktemp("eight") / "wd")
    train(CFG, tiny_train_cache.path, workdir, 8, save_every=EVERY, keep=2, progress=False)
    return workdir


def _copy(workdir, tmp_path) -> str:
    out = str(tmp_path / "wd")
    shutil.copytree(workdir, out)
    return out


def _assert_same(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=1e-6, rtol=0)


def _flip_a_byte_of_the_largest_data_file(folder) -> str:
    """Flips the middle byte of the largest array data file of a saved step's folder; returns
    that file's path relative to the folder."""
    data = os.path.join("default", "ocdbt.process_0", "d")
    big = max(os.listdir(os.path.join(folder, data)),
              key=lambda n: os.path.getsize(os.path.join(folder, data, n)))
    rel = os.path.join(data, big)
    raw = bytearray(open(os.path.join(folder, rel), "rb").read())
    raw[len(raw) // 2] ^= 0xFF
    open(os.path.join(folder, rel), "wb").write(bytes(raw))
    return rel


def orbax_reads(monkeypatch) -> list[int]:
    """The steps orbax is asked to read from now on (a restore, a metadata read, or a
    manager started on a folder, which reads every step's metadata), as a growing list."""
    import orbax.checkpoint as ocp

    opened = []

    def step_of(path) -> int:  # of STEP/default (a restore, metadata) or STEP (a manager's)
        return int(next(p for p in reversed(os.path.abspath(path).split(os.sep)) if p.isdigit()))

    def wrap(cls, name, record):
        original = getattr(cls, name)

        def recorded(self, *args, **kwargs):
            record(*args, **kwargs)
            return original(self, *args, **kwargs)

        monkeypatch.setattr(cls, name, recorded)

    wrap(ocp.Checkpointer, "restore", lambda path, *a, **k: opened.append(step_of(path)))
    wrap(ocp.StandardCheckpointHandler, "metadata", lambda path: opened.append(step_of(path)))
    wrap(ocp.CheckpointManager, "restore", lambda step, *a, **k: opened.append(step))
    wrap(ocp.CheckpointManager, "__init__",
         lambda directory, *a, **k: opened.extend(step_folders(str(directory))))
    return opened


def _steps(workdir):
    return sorted(int(d) for d in os.listdir(os.path.join(workdir, "checkpoints")) if d.isdigit())


def test_damaged_newest_checkpoint_is_set_aside_and_the_rerun_finishes(
        tiny_train_cache, tmp_path, uninterrupted, caplog):
    caplog.set_level(logging.INFO, logger="scenegen_jax.train.loop")
    workdir = _copy(uninterrupted, tmp_path)
    meta = os.path.join(workdir, "checkpoints", str(STEPS), "default", "_METADATA")
    open(meta, "w").close()  # empty: orbax cannot restore the step
    train(CFG, tiny_train_cache.path, workdir, STEPS, save_every=EVERY, log_every=2,
          progress=False)
    # Every scene of the tiny cache holds 13 or more actors in the region, CFG 6 slots.
    n = len(tiny_train_cache)
    assert (
        f"{n} of {n} scenes hold more than max_actors = {CFG.grid.max_actors} actors" in caplog.text
    )
    assert f"checkpoint at step {STEPS} is unreadable or damaged" in caplog.text
    assert "moved to" in caplog.text
    aside = os.listdir(os.path.join(workdir, "checkpoints.damaged"))
    assert len(aside) == 1 and aside[0].startswith(f"{STEPS}-")
    assert _steps(workdir) == [4, 8, 12]
    state = load_trained(workdir)[1]
    assert int(state.step) == STEPS
    _assert_same(state.params, load_trained(uninterrupted)[1].params)
    # One metrics row per logged step, although steps 9-12 ran twice.
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        logged = [json.loads(line)["step"] for line in f]
    assert logged == list(range(2, STEPS + 1, 2))


def test_a_config_of_other_shapes_is_named_not_set_aside(tiny_train_cache, eight_steps, tmp_path):
    """A workdir whose config.json no longer gives the checkpoints' shapes (edited by hand):
    loading names the checkpoint and the first array whose shape differs, and a training run
    refuses it too instead of setting every checkpoint aside as damaged and starting again."""
    from scenegen_jax.workdir import load_params

    workdir = _copy(eight_steps, tmp_path)
    path = os.path.join(workdir, "config.json")
    with open(path) as f:
        saved = json.load(f)
    h = saved["model"]["hidden"]
    wider = {**saved, "model": {**saved["model"], "hidden": 2 * h, "gn_groups": 2 * h}}
    with open(path, "w") as f:
        json.dump(wider, f)
    want = (
        rf"{os.path.join(workdir, 'checkpoints')}/8: \['params'\]\['backbone0_b'\]: saved "
        rf"with shape \({h},\), the config's model has \({2 * h},\)"
    )
    with pytest.raises(ValueError, match=want):
        load_params(workdir)
    with pytest.raises(ValueError, match="another config"):
        train(
            CFG.replace(hidden=2 * h, gn_groups=2 * h),
            tiny_train_cache.path,
            workdir,
            12,
            save_every=EVERY,
            keep=2,
            progress=False,
        )
    assert _steps(workdir) == [4, 8]
    assert not os.path.exists(os.path.join(workdir, "checkpoints.damaged"))


def test_a_workdir_with_a_one_level_config_loads_and_resumes(tiny_train_cache, eight_steps,
                                                             tmp_path):
    """A workdir written before the sub-configs (its config.json one level, every field at
    the top) loads as the same config and parameters, and training resumes it."""
    from scenegen_jax.workdir import load_params

    workdir = _copy(eight_steps, tmp_path)
    path = os.path.join(workdir, "config.json")
    with open(path, "w") as f:
        json.dump(CFG.flat(), f)  # the one-level form: {"name": ..., "grid_size": ..., ...}
    cfg, params, step = load_params(workdir)
    assert (cfg, step) == (CFG, 8)
    _assert_same(params, load_params(eight_steps)[1])
    state = train(CFG, tiny_train_cache.path, workdir, 9, save_every=EVERY, keep=2,
                  progress=False)
    assert int(state.step) == 9 and _steps(workdir) == [8, 9]


def test_tree_checksums_hash_dtype_shape_and_values():
    import hashlib

    x = np.arange(6, dtype=np.float32).reshape(2, 3)
    want = hashlib.sha256(b"<f4(2, 3)" + x.tobytes()).hexdigest()
    assert tree_checksums({"a": x}) == {"['a']": want}
    changed = x.copy()
    changed[1, 2] = 5.5  # one value
    for other in (changed, x.reshape(3, 2), x.view(np.int32)):  # one value, shape, dtype
        assert tree_checksums({"a": other})["['a']"] != want
    # A key is hashed as its data: the same key, the same sum; another key, another sum.
    assert (
        tree_checksums({"k": jax.random.key(1)})
        == tree_checksums({"k": jax.random.key(1)})
        != tree_checksums({"k": jax.random.key(2)})
    )


def test_changed_array_bytes_are_caught_by_the_checksums(
    tiny_train_cache, eight_steps, tmp_path, caplog
):
    workdir = _copy(eight_steps, tmp_path)
    # What a flipped byte inside a parameter file gives when the format does not notice: the
    # arrays restore, with other values than were saved.
    path = os.path.join(workdir, "checkpoints", "8", CHECKSUM_FILE)
    with open(path) as f:
        sums = json.load(f)
    key = next(k for k in sums if "params" in k)
    sums[key] = "0" * 64
    with open(path, "w") as f:
        json.dump(sums, f)
    # A reader skips it (and leaves the folder as it is) ...
    step = int(load_trained(workdir)[1].step)
    assert step == 4
    assert "arrays differ from their checksums" in caplog.text and key in caplog.text
    assert _steps(workdir) == [4, 8]
    # ... and raw bytes flipped in the largest data file are caught too (by orbax or by us).
    _flip_a_byte_of_the_largest_data_file(os.path.join(workdir, "checkpoints", "4"))
    with pytest.raises(FileNotFoundError, match="no readable checkpoint"):
        load_trained(workdir)
    # A training run sets both aside and starts over from scratch.
    train(CFG, tiny_train_cache.path, workdir, 4, save_every=EVERY, keep=2, progress=False)
    assert _steps(workdir) == [1, 4]
    assert len(os.listdir(os.path.join(workdir, "checkpoints.damaged"))) == 2


def test_a_changed_or_missing_file_is_named_before_orbax_reads_it(
    eight_steps, tmp_path, caplog, monkeypatch
):
    import hashlib

    workdir = _copy(eight_steps, tmp_path)
    folder = os.path.join(workdir, "checkpoints", "8")
    with open(os.path.join(folder, CHECKSUM_FILE)) as f:
        sums = json.load(f)
    # Every file orbax wrote has its sha256 beside the arrays' (hashlib on the whole file).
    files = sorted(
        os.path.relpath(os.path.join(r, n), folder)
        for r, _, names in os.walk(folder)
        for n in names
        if n != CHECKSUM_FILE
    )
    assert sorted(k[len("file:") :] for k in sums if k.startswith("file:")) == files
    for rel in files:
        with open(os.path.join(folder, rel), "rb") as f:
            assert sums["file:" + rel] == hashlib.sha256(f.read()).hexdigest(), rel
    opened = orbax_reads(monkeypatch)
    changed = _flip_a_byte_of_the_largest_data_file(folder)
    assert int(load_trained(workdir)[1].step) == 4
    assert set(opened) == {4}  # orbax never opened step 8
    assert "files missing or changed since the save" in caplog.text and changed in caplog.text
    # A deleted file is named the same way.
    caplog.clear()
    shutil.rmtree(os.path.join(workdir, "checkpoints", "4"))
    shutil.copytree(os.path.join(eight_steps, "checkpoints", "8"), folder, dirs_exist_ok=True)
    os.remove(os.path.join(folder, "default", "_METADATA"))
    with pytest.raises(FileNotFoundError, match="no readable checkpoint"):
        load_trained(workdir)
    assert os.path.join("default", "_METADATA") in caplog.text and set(opened) == {4}


def test_unfinished_saves_are_removed(tmp_path):
    ckpts = tmp_path / "checkpoints"
    (ckpts / f"5{TMP_MARKER}-1700000000").mkdir(parents=True)
    c = Checkpointer(str(ckpts), every=1, heal=True)
    c.save(init_state(CFG), force=True)
    c.close()
    assert sorted(os.listdir(ckpts)) == ["0"]


def test_load_params_reads_the_parameters_alone(eight_steps, tmp_path, caplog):
    from scenegen_jax.workdir import load_params

    workdir = _copy(eight_steps, tmp_path)
    cfg, params, step = load_params(workdir)
    assert cfg == CFG and step == 8
    _assert_same(params, load_trained(workdir)[1].params)
    assert int(load_params(workdir, 4)[2]) == 4
    # Only the parameters are read and verified: a wrong optimizer checksum does not matter
    # to them, a wrong parameter checksum makes the reader fall back a step.
    path = os.path.join(workdir, "checkpoints", "8", CHECKSUM_FILE)
    with open(path) as f:
        sums = json.load(f)
    opt = next(k for k in sums if k.startswith("['opt_state']"))
    with open(path, "w") as f:
        json.dump({**sums, opt: "0" * 64}, f)
    assert load_params(workdir)[2] == 8
    par = next(k for k in sums if k.startswith("['params']"))
    with open(path, "w") as f:
        json.dump({**sums, par: "0" * 64}, f)
    assert load_params(workdir)[2] == 4
    assert "arrays differ from their checksums" in caplog.text and par in caplog.text


def test_a_step_without_checksums_is_incomplete_and_not_loaded(
        tiny_train_cache, eight_steps, tmp_path, caplog, monkeypatch):
    """A step that orbax committed but that has no checksums (the run was killed between the
    two, or the file was removed) is not loaded unverified: readers fall back to the previous
    step, saying so in one line, and a training run sets it aside and trains it again."""
    workdir = _copy(eight_steps, tmp_path)
    missing = os.path.join(workdir, "checkpoints", "8", CHECKSUM_FILE)
    os.remove(missing)
    opened = orbax_reads(monkeypatch)
    assert int(load_trained(workdir)[1].step) == 4
    assert 8 not in opened
    lines = [r.getMessage() for r in caplog.records if "step 8" in r.getMessage()]
    assert len(lines) == 1 and "checkpoint at step 8 is incomplete" in lines[0]
    assert missing in lines[0] and "trying the previous one" in lines[0]
    assert _steps(workdir) == [4, 8]  # a reader leaves the folder as it is
    state = train(CFG, tiny_train_cache.path, workdir, 8, save_every=EVERY, keep=2,
                  progress=False)
    assert int(state.step) == 8 and _steps(workdir) == [4, 8]
    assert os.path.isfile(missing)  # saved again, whole
    assert [n.split("-")[0] for n in os.listdir(workdir + "/checkpoints.damaged")] == ["8"]
    _assert_same(state.params, load_trained(eight_steps)[1].params)


@pytest.mark.parametrize("heal", [False, True], ids=["reader", "training"])
def test_orbax_reads_nothing_of_a_damaged_step(eight_steps, tmp_path, caplog, monkeypatch,
                                               heal):
    """The checksums are verified before orbax touches a step: not even its manager, which
    parses every step's _CHECKPOINT_METADATA when it starts, sees a damaged one (orbax logged
    its parse error, and its failed reads ended in "Event loop is closed" tracebacks)."""
    workdir = _copy(eight_steps, tmp_path)
    meta = os.path.join(workdir, "checkpoints", "8", "_CHECKPOINT_METADATA")
    with open(meta, "r+b") as f:
        f.truncate(os.path.getsize(meta) // 2)
    opened = orbax_reads(monkeypatch)
    caplog.set_level(logging.INFO)
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=EVERY, keep=2, heal=heal)
    restored = ckpt.restore_latest(jax.eval_shape(lambda: init_state(CFG)))
    ckpt.close()
    assert int(restored.step) == 4 and 8 not in opened and 4 in opened
    assert "files missing or changed since the save: ['_CHECKPOINT_METADATA']" in caplog.text
    noise = [r.getMessage() for r in caplog.records
             if r.name.startswith(("absl", "orbax")) and r.levelno >= logging.WARNING]
    assert not noise, noise
    assert _steps(workdir) == ([4] if heal else [4, 8])
