"""Orbax checkpoints of the train state: periodic saves, keep the last few, restore the latest
good one (the whole state to resume training, or only some of its entries, e.g. the
parameters, to score or sample).

Every saved step carries the sha256 of each array and of each file orbax wrote (`CHECKSUM_FILE`
in the step's folder). The files are checked before orbax opens them, so a damaged file is
named and skipped without orbax parsing it (a read that failed half way left orbax's other
reads unfinished, reported later as "Exception ignored" tracebacks); the arrays are checked
after the restore, so flipped bytes inside a parameter file are caught rather than loaded
(steps saved before the file sums verify their arrays only). In a training run (`heal=True`) a
step that does not restore or verify is set aside: moved to
`<checkpoints>.damaged/<step>-<time>` with a warning naming both paths, so that it neither
blocks the save of the same step later nor takes one of the `keep` slots. Orbax's temporary
folders left by a killed save are removed when a training run opens the folder.

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
    """A saved step whose arrays differ from the checksums written with them."""


class Checkpointer:
    """Saves every `every` steps into `directory`, keeping the newest `keep`.

    `heal`: a training run's checkpointer; it removes orbax temporaries and sets damaged
    steps aside. Readers (score, sample) leave the folder as it is and only skip them.
    """

    def __init__(self, directory: str, every: int, keep: int = 3, heal: bool = False):
        self.directory = os.path.abspath(directory)
        self.heal = heal
        if heal:
            self._remove_temporaries()
        self.manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(
                max_to_keep=keep,
                save_interval_steps=max(every, 1),
                create=True,
                enable_async_checkpointing=False,
            ),
        )

    def _remove_temporaries(self) -> None:
        if is_main_process() and os.path.isdir(self.directory):
            for name in sorted(os.listdir(self.directory)):
                if TMP_MARKER in name:
                    log.warning("%s: removing an unfinished save (%s)", self.directory, name)
                    shutil.rmtree(os.path.join(self.directory, name), ignore_errors=True)
        sync_processes("checkpoint temporaries removed")

    def save(self, state, force: bool = False) -> bool:
        """Saves a state (a NamedTuple with a `step` entry, e.g. `train.step.TrainState`) if
        the step is due (or `force`); returns whether it saved. Entries that are None (e.g.
        `TrainState.ema` without a moving average) are not saved, so the checkpoint has the
        entries of one saved before they existed."""
        step = int(state.step)
        entries = _entries(state)
        saved = self.manager.save(step, args=ocp.args.StandardSave(entries), force=force)
        if saved:
            self.manager.wait_until_finished()
            if is_main_process():
                folder = os.path.join(self.directory, str(step))
                path = os.path.join(folder, CHECKSUM_FILE)
                sums = {**tree_checksums(entries), **file_checksums(folder)}  # before the file
                with written_whole(path) as tmp, open(tmp, "w") as f:
                    json.dump(sums, f)
            sync_processes(f"checksums of step {step} written")
        return saved

    def _checksums(self, step: int) -> dict | None:
        """The checksums saved with `step`; None (with a warning) for a step saved without."""
        path = os.path.join(self.directory, str(step), CHECKSUM_FILE)
        if not os.path.isfile(path):
            log.warning("%s: no checksums (saved by an older version); not verified", path)
            return None
        try:
            want = read_json(path)
        except OSError as e:
            raise DamagedCheckpoint(f"{path}: unreadable checksums ({e})") from e
        except ValueError as e:  # names the file
            raise DamagedCheckpoint(f"unreadable checksums: {e}") from e
        if not isinstance(want, dict):
            raise DamagedCheckpoint(f"{path}: checksums are not a JSON object")
        return want

    def _verify_files(self, step: int, want: dict) -> None:
        """Checks the step's saved files against their sums (before orbax reads them): a
        missing or changed file is named; files added since are left alone."""
        folder = os.path.join(self.directory, str(step))
        want = {k: v for k, v in want.items() if k.startswith(FILE_KEY)}
        if not want:
            return  # saved before file sums
        got = file_checksums(folder)
        bad = sorted(k[len(FILE_KEY):] for k in want if want[k] != got.get(k))
        if bad:
            # The file names first: the warning cuts the message at 200 characters.
            raise DamagedCheckpoint(f"files missing or changed since the save: {bad[:5]} "
                                    f"(in {folder})")

    def _verify(self, step: int, restored: dict, want: dict) -> None:
        """Checks the restored arrays against the checksums saved with them (only the saved
        entries that were restored, for a partial restore)."""
        path = os.path.join(self.directory, str(step), CHECKSUM_FILE)
        got = tree_checksums(restored)
        entries = tuple(f"[{k!r}]" for k in restored)
        want = {k: v for k, v in want.items() if k.startswith(entries)}
        bad = sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))
        if bad:
            raise DamagedCheckpoint(f"{path}: arrays differ from their checksums: {bad[:5]}")

    def _set_aside(self, step: int) -> None:
        src = os.path.join(self.directory, str(step))
        dst = os.path.join(self.directory + ".damaged", f"{step}-{time.strftime('%Y%m%dT%H%M%S')}")
        if is_main_process():
            os.makedirs(os.path.dirname(dst), exist_ok=True)
            os.rename(src, dst)
            log.warning("%s: damaged checkpoint moved to %s", src, dst)
        sync_processes(f"damaged step {step} set aside")
        self.manager.reload()

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
        if whole:
            args = ocp.args.StandardRestore(abstract)
        else:
            args = ocp.args.PyTreeRestore(
                abstract,
                restore_args=ocp.checkpoint_utils.construct_restore_args(abstract),
                partial_restore=True,
            )
        steps = sorted(self.manager.all_steps(), reverse=True)
        if step is not None:
            if step not in steps:
                raise ValueError(
                    f"{self.directory}: no checkpoint at step {step}; saved: {sorted(steps)}"
                )
            steps = [step]
        for step in steps:
            mismatch = self._shape_mismatch(step, abstract)
            if mismatch:  # not damage: every checkpoint of the run has these shapes
                raise ValueError(
                    f"{self.directory}/{step}: {mismatch}; the checkpoints were saved by a model "
                    "of another config (was the workdir's config.json changed?)"
                )
            try:
                want = self._checksums(step)
                if want is not None:
                    self._verify_files(step, want)
                restored = self.manager.restore(step, args=args)
                if want is not None:
                    self._verify(step, restored, want)
            except Exception as e:  # orbax raises many types for damaged files
                log.warning(
                    "%s: checkpoint at step %d is unreadable or damaged (%s: %s); trying the "
                    "previous one",
                    self.directory,
                    step,
                    type(e).__name__,
                    str(e)[:200],
                )
                if self.heal:
                    self._set_aside(step)
                continue
            log.info("%s: restored the checkpoint of step %d", self.directory, step)
            return type(template)(**restored) if whole else dict(restored, step=step)
        return None

    def _shape_mismatch(self, step: int, abstract) -> str | None:
        """The first array of `abstract` whose saved shape at `step` differs, as text; None
        when all agree, or when orbax's metadata cannot be read (the restore then decides)."""
        try:
            path = pathlib.Path(self.directory, str(step), "default")
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
        self.manager.wait_until_finished()
        self.manager.close()
