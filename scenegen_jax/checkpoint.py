"""Orbax checkpoints of the train state: periodic saves, keep the last few, restore the latest
good one (the whole state to resume training, or only some of its entries, e.g. the
parameters, to score or sample).

Every saved step carries the sha256 of each array and of each file orbax wrote (`CHECKSUM_FILE`
in the step's folder), written after orbax committed the step: a step folder without it is a
save that did not finish (killed between the two) or lost its sums, and is not used. The
files are checked before orbax opens anything of a step (its restore, its metadata, and, in a
training run, orbax's listing of the steps), so a damaged file is named and skipped without
orbax parsing it (a read that failed half way left orbax's other reads unfinished, reported
later as "Exception ignored" and "Event loop is closed" tracebacks); the arrays are checked
after the restore, so flipped bytes inside a parameter file are caught rather than loaded. In
a training run (`heal=True`) a step that is incomplete, does not restore or does not verify is
set aside: moved to `<checkpoints>.damaged/<step>-<time>` with a warning naming both paths,
so that it neither blocks the save of the same step later nor takes one of the `keep` slots.
Orbax's temporary folders left by a killed save are removed when a training run opens the
folder.

A save may carry a small JSON record beside the arrays (`EXTRA_FILE`, checked with the files),
e.g. the training loop's partial metrics sums, so that a resumed run logs what the
uninterrupted one did.

In a multi-process job every process saves and restores its part of the same checkpoint
(orbax coordinates them), and process 0 alone writes the checksums and moves or removes
folders.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pathlib
import shutil
import time
from collections.abc import Callable

import jax
import numpy as np
import orbax.checkpoint as ocp

from scenegen_jax.backend import is_main_process, sync_processes
from scenegen_jax.files import written_whole
from scenegen_jax.jsonfile import read_json

log = logging.getLogger(__name__)
CHECKSUM_FILE = "scenegen_sha256.json"
FILE_KEY = "file:"  # CHECKSUM_FILE's keys of file sums; the arrays' are their tree paths
TMP_MARKER = ".orbax-checkpoint-tmp"
EXTRA_FILE = "scenegen_extra.json"  # `Checkpointer.save`'s extra record
ITEM = "default"  # the folder of a step that holds the state (orbax's name for one item)


def tree_checksums(tree) -> dict[str, str]:
    """sha256 of every array of `tree` (dtype, shape and bytes), keyed by its path."""
    out = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        if jax.dtypes.issubdtype(getattr(leaf, "dtype", None), jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        x = np.ascontiguousarray(jax.device_get(leaf))
        h = hashlib.sha256(f"{x.dtype.str}{x.shape}".encode())
        h.update(x.tobytes())
        out[jax.tree_util.keystr(path)] = h.hexdigest()
    return out


def file_checksums(directory: str) -> dict[str, str]:
    """sha256 of every file under a saved step's folder but the checksums' own, keyed
    FILE_KEY + its path relative to the folder."""
    out = {}
    for root, _, names in os.walk(directory):
        for name in names:
            path = os.path.join(root, name)
            rel = os.path.relpath(path, directory)
            if not rel.startswith(CHECKSUM_FILE):
                with open(path, "rb") as f:
                    out[FILE_KEY + rel] = hashlib.file_digest(f, "sha256").hexdigest()
    return out


def _entries(state) -> dict:
    """A NamedTuple state's entries as saved: every one but those that are None."""
    return {k: v for k, v in state._asdict().items() if v is not None}


def _abstract(x, sharding=None):
    """Shape, dtype and sharding (default: the first local device) for restoring an array
    (or abstract array)."""
    sharding = sharding or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)


class DamagedCheckpoint(Exception):
    """A saved step whose files or arrays differ from the checksums written with them."""


class IncompleteCheckpoint(Exception):
    """A step folder without its checksums: a save that did not finish, or lost its sums."""


def step_folders(directory: str) -> list[int]:
    """The steps saved in `directory` (its folders named by a step number), ascending;
    orbax's temporary folders of unfinished saves are not among them."""
    if not os.path.isdir(directory):
        return []
    return sorted(int(n) for n in os.listdir(directory)
                  if n.isdigit() and os.path.isdir(os.path.join(directory, n)))


def read_checksums(folder: str) -> dict:
    """The checksums saved in a step's folder.

    Raises:
      IncompleteCheckpoint: there are none.
      DamagedCheckpoint: they cannot be read.
    """
    path = os.path.join(folder, CHECKSUM_FILE)
    if not os.path.isfile(path):
        raise IncompleteCheckpoint(f"{path}: missing (the save did not finish, or the file was "
                                   "removed), so the step cannot be verified")
    try:
        want = read_json(path)
    except OSError as e:
        raise DamagedCheckpoint(f"{path}: unreadable checksums ({e})") from e
    except ValueError as e:  # names the file
        raise DamagedCheckpoint(f"unreadable checksums: {e}") from e
    if not isinstance(want, dict):
        raise DamagedCheckpoint(f"{path}: checksums are not a JSON object")
    return want


def verify_files(folder: str, want: dict) -> None:
    """Checks a step's saved files against their sums `want` (before orbax reads them): a
    missing or changed file is named; files added since are left alone."""
    want = {k: v for k, v in want.items() if k.startswith(FILE_KEY)}
    if not want:
        return  # saved before file sums
    got = file_checksums(folder)
    bad = sorted(k[len(FILE_KEY):] for k in want if want[k] != got.get(k))
    if bad:
        # The file names first: the warning cuts the message at 200 characters.
        raise DamagedCheckpoint(f"files missing or changed since the save: {bad[:5]} "
                                f"(in {folder})")


def checked_step(folder: str) -> dict:
    """The checksums of a step whose files verify (`read_checksums`, `verify_files`)."""
    want = read_checksums(folder)
    verify_files(folder, want)
    return want


class Checkpointer:
    """Saves every `every` steps into `directory`, keeping the newest `keep`.

    `heal`: a training run's checkpointer; it removes orbax temporaries and sets incomplete
    and damaged steps aside before orbax lists the steps. Readers (score, sample) leave the
    folder as it is and only skip them; they never start orbax's manager, which reads every
    step's metadata.
    """

    def __init__(self, directory: str, every: int, keep: int = 3, heal: bool = False):
        self.directory = os.path.abspath(directory)
        self.heal = heal
        self.every, self.keep = every, keep
        self._manager = None
        if heal:
            self._remove_temporaries()
            self._set_aside_unverified()
            self._manager = self._new_manager()  # only verified steps left to list

    def _new_manager(self) -> ocp.CheckpointManager:
        return ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(
                max_to_keep=self.keep,
                save_interval_steps=max(self.every, 1),
                create=True,
                enable_async_checkpointing=False,
            ),
        )

    @property
    def manager(self) -> ocp.CheckpointManager:
        """Orbax's manager of the folder, started on the first save."""
        if self._manager is None:
            self._manager = self._new_manager()
        return self._manager

    def _remove_temporaries(self) -> None:
        if is_main_process() and os.path.isdir(self.directory):
            for name in sorted(os.listdir(self.directory)):
                if TMP_MARKER in name:
                    log.warning("%s: removing an unfinished save (%s)", self.directory, name)
                    shutil.rmtree(os.path.join(self.directory, name), ignore_errors=True)
        sync_processes("checkpoint temporaries removed")

    def _set_aside_unverified(self) -> None:
        """Sets aside every step that is incomplete or whose files do not verify."""
        for step in step_folders(self.directory):
            try:
                checked_step(self._folder(step))
            except (IncompleteCheckpoint, DamagedCheckpoint) as e:
                self._skip(step, e)

    def _folder(self, step: int) -> str:
        return os.path.join(self.directory, str(step))

    def due(self, step: int, force: bool = False) -> bool:
        """Whether `save` saves `step` (every `every` steps, and the first step of a folder
        without checkpoints; always with `force`)."""
        return force or self.manager.should_save(step)

    def save(self, state, force: bool = False, extra: Callable[[], dict] | None = None) -> bool:
        """Saves a state (a NamedTuple with a `step` entry, e.g. `train.step.TrainState`) if
        the step is due (or `force`); returns whether it saved. Entries that are None (e.g.
        `TrainState.ema` without a moving average) are not saved, so the checkpoint has the
        entries of one saved before they existed. `extra`: called only when the step is saved,
        gives a JSON object kept with it (`extra`)."""
        step = int(state.step)
        entries = _entries(state)
        saved = self.manager.save(step, args=ocp.args.StandardSave(entries), force=force)
        if saved:
            self.manager.wait_until_finished()
            record = None if extra is None else extra()
            if is_main_process():
                folder = self._folder(step)
                if record is not None:
                    with written_whole(os.path.join(folder, EXTRA_FILE)) as tmp, \
                            open(tmp, "w") as f:
                        json.dump(record, f)
                sums = {**tree_checksums(entries), **file_checksums(folder)}  # before the file
                with written_whole(os.path.join(folder, CHECKSUM_FILE)) as tmp, \
                        open(tmp, "w") as f:
                    json.dump(sums, f)
            sync_processes(f"checksums of step {step} written")
        return saved

    def extra(self, step: int) -> dict | None:
        """The JSON object saved with `step` (`save`'s `extra`); None when it has none. Read
        after the step restored: its file was verified with the others."""
        path = os.path.join(self._folder(step), EXTRA_FILE)
        if not os.path.isfile(path):
            return None
        record = read_json(path)
        if not isinstance(record, dict):
            raise ValueError(f"{path}: expected a JSON object, got {type(record).__name__}")
        return record

    def _verify(self, step: int, restored: dict, want: dict) -> None:
        """Checks the restored arrays against the checksums saved with them (only the saved
        entries that were restored, for a partial restore)."""
        path = os.path.join(self._folder(step), CHECKSUM_FILE)
        got = tree_checksums(restored)
        entries = tuple(f"[{k!r}]" for k in restored)
        want = {k: v for k, v in want.items() if k.startswith(entries)}
        bad = sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))
        if bad:
            raise DamagedCheckpoint(f"{path}: arrays differ from their checksums: {bad[:5]}")

    def _skip(self, step: int, e: Exception) -> None:
        """Leaves `step` out, saying why in one line; a training run sets it aside."""
        what = "incomplete" if isinstance(e, IncompleteCheckpoint) else "unreadable or damaged"
        where = f"moved to {self._set_aside(step)}; " if self.heal else ""
        log.warning("%s: checkpoint at step %d is %s (%s: %s); %strying the previous one",
                    self.directory, step, what, type(e).__name__, str(e)[:200], where)

    def _set_aside(self, step: int) -> str:
        """Moves `step`'s folder out of the checkpoints; returns where to."""
        src = self._folder(step)
        dst = os.path.join(self.directory + ".damaged", f"{step}-{time.strftime('%Y%m%dT%H%M%S')}")
        sync_processes(f"step {step} checked")  # every process is done reading it
        if is_main_process():
            os.makedirs(os.path.dirname(dst), exist_ok=True)
            os.rename(src, dst)
        sync_processes(f"step {step} set aside")
        if self._manager is not None:
            self._manager.reload()
        return dst

    def restore_latest(self, template, step: int | None = None, sharding=None):
        """The newest checkpoint that restores cleanly and matches its checksums, or None when
        there is none.

        `template`: the state (a NamedTuple of arrays or abstract arrays), restored whole and
        returned as that type (its None entries stay None and are not read); or a dict of
        some of its entries (e.g. {"params": ...}), restored alone (the others are not read)
        and returned as a dict, with `step` the checkpoint's step.
        With `step`, that checkpoint only (ValueError naming the saved steps if it is not
        there; None if it does not restore). `sharding`: where every restored array goes
        (default: the first local device; a training run: replicated over its mesh).
        """
        whole = hasattr(template, "_asdict")
        abstract = jax.tree.map(
            lambda x: _abstract(x, sharding), _entries(template) if whole else dict(template)
        )
        steps = step_folders(self.directory)[::-1]
        if step is not None:
            if step not in steps:
                raise ValueError(
                    f"{self.directory}: no checkpoint at step {step}; saved: {sorted(steps)}"
                )
            steps = [step]
        for step in steps:
            try:
                want = checked_step(self._folder(step))
            except (IncompleteCheckpoint, DamagedCheckpoint) as e:
                self._skip(step, e)
                continue
            mismatch = self._shape_mismatch(step, abstract)
            if mismatch:  # not damage: every checkpoint of the run has these shapes
                raise ValueError(
                    f"{self.directory}/{step}: {mismatch}; the checkpoints were saved by a model "
                    "of another config (was the workdir's config.json changed?)"
                )
            try:
                restored = _restore_step(self._folder(step), abstract, whole)
                self._verify(step, restored, want)
            except Exception as e:  # orbax raises many types for damaged files
                self._skip(step, e)
                continue
            log.info("%s: restored the checkpoint of step %d", self.directory, step)
            return type(template)(**restored) if whole else dict(restored, step=step)
        return None

    def _shape_mismatch(self, step: int, abstract) -> str | None:
        """The first array of `abstract` whose saved shape at `step` differs, as text; None
        when all agree, or when orbax's metadata cannot be read (the restore then decides)."""
        try:
            path = pathlib.Path(self._folder(step), ITEM)
            tree = ocp.StandardCheckpointHandler().metadata(path).tree
            saved = {jax.tree_util.keystr(k): tuple(m.shape)
                     for k, m in jax.tree_util.tree_flatten_with_path(tree)[0]}
        except Exception:  # a damaged or foreign step: its restore reports it
            return None
        for k, x in jax.tree_util.tree_flatten_with_path(abstract)[0]:
            key = jax.tree_util.keystr(k)
            if key in saved and saved[key] != tuple(x.shape):
                return f"{key}: saved with shape {saved[key]}, the config's model has {x.shape}"
        return None

    def close(self) -> None:
        if self._manager is not None:
            self._manager.wait_until_finished()
            self._manager.close()


def _restore_step(folder: str, abstract: dict, whole: bool) -> dict:
    """The arrays of a verified step's folder as `abstract` gives them: every saved entry
    (`whole`), or only those of `abstract` (the others are not read)."""
    path = pathlib.Path(folder, ITEM)
    if whole:
        with ocp.Checkpointer(ocp.StandardCheckpointHandler()) as reader:
            return reader.restore(path, args=ocp.args.StandardRestore(abstract))
    args = ocp.args.PyTreeRestore(
        abstract,
        restore_args=ocp.checkpoint_utils.construct_restore_args(abstract),
        partial_restore=True,
    )
    with ocp.Checkpointer(ocp.PyTreeCheckpointHandler()) as reader:
        return reader.restore(path, args=args)
