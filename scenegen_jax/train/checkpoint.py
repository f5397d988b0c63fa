"""Orbax checkpoints of the train state: periodic saves, keep the last few, resume from the
latest readable one (a corrupt or half-written latest is reported and skipped)."""

from __future__ import annotations

import logging
import os

import jax
import orbax.checkpoint as ocp

from scenegen_jax.train.step import TrainState

log = logging.getLogger(__name__)


class Checkpointer:
    """Saves every `every` steps into `directory`, keeping the newest `keep`."""

    def __init__(self, directory: str, every: int, keep: int = 3):
        self.directory = os.path.abspath(directory)
        self.manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(
                max_to_keep=keep,
                save_interval_steps=max(every, 1),
                create=True,
                enable_async_checkpointing=False,
            ),
        )

    def save(self, state: TrainState, force: bool = False) -> bool:
        """Saves if the step is due (or `force`); returns whether it saved."""
        return self.manager.save(
            int(state.step), args=ocp.args.StandardSave(state._asdict()), force=force
        )

    def restore_latest(self, template: TrainState, step: int | None = None) -> TrainState | None:
        """The newest checkpoint that restores cleanly, or None when there is none.

        With `step`, that checkpoint only (ValueError naming the saved steps if it is not
        there; None if it does not restore).
        """
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, template._asdict())
        steps = sorted(self.manager.all_steps(), reverse=True)
        if step is not None:
            if step not in steps:
                raise ValueError(
                    f"{self.directory}: no checkpoint at step {step}; saved: {sorted(steps)}"
                )
            steps = [step]
        for step in steps:
            try:
                restored = self.manager.restore(step, args=ocp.args.StandardRestore(abstract))
            except Exception as e:  # orbax raises many types for damaged files
                log.warning(
                    "%s: checkpoint at step %d is unreadable (%s: %s); trying the previous one",
                    self.directory,
                    step,
                    type(e).__name__,
                    str(e)[:200],
                )
                continue
            log.info("%s: restored the checkpoint of step %d", self.directory, step)
            return TrainState(**restored)
        return None

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()
