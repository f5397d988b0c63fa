"""A training workdir as the other commands read it: `config.json` and a checkpoint
(`restore`), of which scoring, sampling and export read only the parameters (`load_params`),
without the optimizer state or anything of `train/`; and as a run writes it: alone
(`writing`, a lock), never into a folder of another kind (`folder_kind`), and leaving the
folder as it found it when the run fails before its first checkpoint.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable, Iterator
from typing import Any

import jax

from scenegen_jax.backend import is_main_process
from scenegen_jax.checkpoint import Checkpointer, step_folders
from scenegen_jax.config import Config
from scenegen_jax.data.cache_layout import SHARD_RE
from scenegen_jax.locks import LOCK_FILE, exclusive
from scenegen_jax.model.network import init_params

CONFIG_FILE = "config.json"
CHECKPOINTS = "checkpoints"
# The files that tell what a folder is, by kind (`folder_kind`): a cache (`data.cache_layout`;
# a sharded one has shard folders instead), an exported model (`pretrained`), a workdir.
KIND_FILES = {
    "cache": ("meta.json", "actors.npz", "map_index.npy"),
    "exported model": ("manifest.json", "params.msgpack"),
    "training workdir": ("data.json", "metrics.jsonl", CHECKPOINTS),
}


def load_workdir_config(workdir: str) -> Config:
    """The config a workdir was trained with."""
    path = os.path.join(workdir, CONFIG_FILE)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: not a training workdir (no {CONFIG_FILE})")
    with open(path, "rb") as f:
        return Config.from_json(f.read(), path)


def restore(workdir: str, template_of: Callable[[Config], Any], step: int | None = None):
    """(config, checkpoint) of a training workdir: its newest readable checkpoint, or the one
    saved at `step`, restored into the (abstract) tree `template_of(config)`: the entries of
    the train state to read."""
    cfg = load_workdir_config(workdir)
    directory = os.path.join(workdir, CHECKPOINTS)
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"{directory}: no checkpoints (train this workdir first)")
    ckpt = Checkpointer(directory, every=1)
    try:
        restored = ckpt.restore_latest(template_of(cfg), step)
    finally:
        ckpt.close()
    if restored is None:
        raise FileNotFoundError(f"{directory}: no readable checkpoint")
    return cfg, restored


def load_params(workdir: str, step: int | None = None):
    """(config, parameters, step) of a training workdir: the parameters of its newest readable
    checkpoint, or of the one saved at `step`; only the parameters are read. A run with
    `ema_decay` gives its parameters' moving average (`train.step.TrainState.ema`) instead."""
    cfg, restored = restore(workdir, _params_template, step)
    return cfg, restored[_params_entry(cfg)], int(restored["step"])


def _params_entry(cfg: Config) -> str:
    """The train state's entry that holds the parameters to use."""
    return "ema" if cfg.train.ema_decay > 0 else "params"


def _params_template(cfg: Config) -> dict:
    return {_params_entry(cfg): jax.eval_shape(lambda: init_params(cfg.model, jax.random.key(0)))}


def folder_kind(path: str) -> tuple[str | None, str | None]:
    """(kind, the entry that tells) of a folder by its files: "cache", "exported model",
    "training workdir" (KIND_FILES; a config.json alone tells nothing: all three have one),
    or "other" for a folder with other entries; (None, None) for a missing or empty one (a
    lock file aside)."""
    if not os.path.isdir(path):
        return None, None
    names = sorted(set(os.listdir(path)) - {LOCK_FILE})
    for kind, files in KIND_FILES.items():
        found = [n for n in files if n in names]
        if found:
            return kind, found[0]
    shards = [n for n in names if SHARD_RE.fullmatch(n)]
    if shards:
        return "cache", shards[0]
    return ("other", names[0]) if names else (None, None)


def check_train_target(workdir: str) -> None:
    """Refuses a --workdir that holds a cache or an exported model: a run would write its
    config.json and checkpoints among their files."""
    kind, entry = folder_kind(workdir)
    if kind in ("cache", "exported model"):
        raise ValueError(f"--workdir {workdir}: holds {entry}, so it is {_a(kind)}, not a "
                         "training workdir; give a new folder (or a workdir of `train`)")


def check_model_target(flag: str, directory: str) -> None:
    """Refuses an export into a folder that is not an exported model (nor missing or
    empty): the export would overwrite or mix with its files."""
    kind, entry = folder_kind(directory)
    if kind not in (None, "exported model"):
        what = "something else" if kind == "other" else _a(kind)
        raise ValueError(f"{flag} {directory}: holds {entry}, so it is {what}, not an "
                         "exported model; give a new or empty folder, or an exported model "
                         "to replace")


def _a(kind: str) -> str:
    return f"an {kind}" if kind[0] in "aeiou" else f"a {kind}"


def has_checkpoint(workdir: str) -> bool:
    """Whether a run has saved a step into `workdir` (verified or not): from then on the
    workdir's config.json and data.json bind its resumes."""
    return bool(step_folders(os.path.join(workdir, CHECKPOINTS)))


def _missing_ancestor(path: str) -> str | None:
    """The outermost folder of `path` (itself included) that does not exist yet."""
    path, missing = os.path.abspath(path), None
    while not os.path.exists(path):
        missing, path = path, os.path.dirname(path)
    return missing


def _remove_created(workdir: str, before: set[str]) -> None:
    """Removes the entries of `workdir` that are not in `before` (its lock file aside)."""
    for name in sorted(set(os.listdir(workdir)) - before - {LOCK_FILE}):
        path = os.path.join(workdir, name)
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path, ignore_errors=True)
        else:
            os.remove(path)


def _remove_empty_folders(folder: str, outermost: str) -> None:
    """Removes `folder` and its parents up to `outermost` while they are empty."""
    folder = os.path.abspath(folder)
    while True:
        try:
            os.rmdir(folder)
        except OSError:  # not empty: another run's files or lock
            return
        if folder == outermost:
            return
        folder = os.path.dirname(folder)


@contextlib.contextmanager
def writing(workdir: str, what: str) -> Iterator[None]:
    """Holds WORKDIR/.lock for the block (`locks.exclusive`; a second run is refused with its
    holder's pid and host), in which a run writes `workdir`; when the block fails in a
    workdir that had no checkpoint and still has none, it removes what the block created
    (files, folders, the workdir itself), so that a corrected rerun finds the folder as it
    was. `what`: what the run does, as a refused one shows it. In a multi-process job
    process 0 alone does this (the others write no workdir files)."""
    if not is_main_process():
        yield
        return
    created = _missing_ancestor(workdir)
    undo = False
    try:
        with exclusive(os.path.join(workdir, LOCK_FILE), what):
            before = set(os.listdir(workdir))
            fresh = not has_checkpoint(workdir)  # else a resume: what it set aside stays
            try:
                yield
            except BaseException:
                undo = fresh and not has_checkpoint(workdir)
                if undo:
                    _remove_created(workdir, before)
                raise
    finally:
        if undo and created is not None:  # after the lock file is gone
            _remove_empty_folders(workdir, created)
