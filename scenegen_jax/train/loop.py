"""The training driver: data order, sharded steps, progress bar, metrics file, checkpoints, and
the warm start of a fresh run (`train.warm_start`)."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import sys
import time

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P
from tqdm import tqdm

from scenegen_jax.backend import is_main_process, make_mesh
from scenegen_jax.checkpoint import Checkpointer
from scenegen_jax.config import Config
from scenegen_jax.data.cache import actors_in_region
from scenegen_jax.data.union import CacheUnion, load_union
from scenegen_jax.distributions import TERMS
from scenegen_jax.files import written_whole
from scenegen_jax.jsonfile import read_json
from scenegen_jax.likelihood.batch import check_batch, gather_batch, local_rows, to_device
from scenegen_jax.likelihood.terms import VEHICLE_TERMS
from scenegen_jax.scene import CLASS_NAMES
from scenegen_jax.signals import raise_pending
from scenegen_jax.train.data import resolve_weights, union_indices
from scenegen_jax.train.programs import train_step_for_run
from scenegen_jax.train.step import (
    TrainState,
    init_state,
    make_optimizer,
    resolve_remat,
    start_ema,
    step_rotations,
)
from scenegen_jax.train.warm_start import reframed, start_params, warm_start
from scenegen_jax.workdir import (
    CHECKPOINTS,
    CONFIG_FILE,
    check_train_target,
    has_checkpoint,
    restore,
    writing,
)

log = logging.getLogger(__name__)
DATA_FILE = "data.json"


def _write_atomic(path: str, text: str) -> None:
    """Writes `text` to `path` whole or not at all (other processes may read it meanwhile);
    in a multi-process job only process 0 writes."""
    if is_main_process():
        with written_whole(path) as tmp, open(tmp, "w") as f:
            f.write(text)


class NonFiniteLoss(FloatingPointError, ValueError):
    """The training loss became NaN or infinite: the run diverged (a ValueError as well, so
    that the command reports it as one line)."""


def save_or_check_config(workdir: str, cfg: Config) -> None:
    """Writes the resolved config beside the checkpoints; a resume must use the same one,
    except for `remat` (memory against time; the same values). Until the workdir has a
    checkpoint nothing is bound to it: a run that stopped before its first one left a
    config that the next run replaces."""
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(workdir, CONFIG_FILE)
    if os.path.exists(path) and has_checkpoint(workdir):
        with open(path) as f:
            saved = Config.from_json(f.read(), path)
        if saved.replace(remat=cfg.train.remat) != cfg:
            raise ValueError(
                f"{path}: this workdir was trained with a different config "
                f"({'; '.join(saved.differences(cfg))}, saved != requested); use a new "
                f"--workdir or the same config and overrides"
            )
        return
    _write_atomic(path, cfg.to_json())


def data_record(union: CacheUnion, weights) -> dict:
    """What a run trains on: the caches (absolute paths, source kinds, scene counts), the
    --weights as given (None: by scene count) and the resulting draw shares."""
    return {
        "caches": [
            {"path": os.path.abspath(c.path), "source": (c.meta.get("source") or {}).get("kind"),
             "scenes": len(c)}
            for c in union.members
        ],
        "weights": None if weights is None else [float(w) for w in weights],
        "shares": resolve_weights(union.sizes, weights).tolist(),
    }


def save_or_check_data(workdir: str, union: CacheUnion, weights=None) -> dict:
    """Writes `data_record` beside the config; a resume must train on the same caches (same
    paths, in the same order, with the same scene counts) and the same shares, since the data
    order is a function of them. A workdir from before this record gets one; one without a
    checkpoint yet gets this run's (`save_or_check_config`)."""
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(workdir, DATA_FILE)
    record = data_record(union, weights)
    if not (os.path.exists(path) and has_checkpoint(workdir)):
        _write_atomic(path, json.dumps(record, indent=1))
        return record
    saved = read_json(path)
    hint = "use the same --data list and --weights, or a new --workdir"
    was = [c["path"] for c in saved["caches"]]
    now = [c["path"] for c in record["caches"]]
    if was != now:
        raise ValueError(f"{path}: this workdir was trained on --data {was}, not {now}; {hint}")
    for a, b in zip(saved["caches"], record["caches"], strict=True):
        if a["scenes"] != b["scenes"]:
            raise ValueError(f"{path}: cache {b['path']} had {a['scenes']} scenes when this run "
                             f"started and has {b['scenes']} now; {hint}")
    if not np.allclose(saved["shares"], record["shares"], rtol=1e-9, atol=0):
        raise ValueError(f"{path}: this workdir was trained with --weights {saved['weights']} "
                         f"(shares {saved['shares']}), not {record['weights']} "
                         f"(shares {record['shares']}); {hint}")
    return saved


def drop_metrics_after(path: str, step: int) -> None:
    """Removes the rows of steps after `step` from a metrics file (a resumed run replays
    them), so that it keeps one row per logged step (process 0's file)."""
    if not is_main_process() or not os.path.isfile(path):
        return
    with open(path) as f:
        lines = f.readlines()
    keep = []
    for line in lines:
        try:
            if json.loads(line)["step"] <= step:
                keep.append(line)
        except (json.JSONDecodeError, KeyError, TypeError):
            pass  # a row cut short by a kill: replayed
    if len(keep) != len(lines):
        log.info("%s: dropping %d rows after step %d (replayed)", path, len(lines) - len(keep),
                 step)
        with written_whole(path) as tmp, open(tmp, "w") as f:
            f.writelines(keep)


def summarize(stats: dict) -> dict:
    """Host-side metrics from summed stats: loss and gradient norm per batch, NLL per scene by
    term, per actor by class."""
    scenes = max(float(stats["scenes"]), 1.0)
    batches = float(stats["batches"])
    out = {"loss": float(stats["loss"]) / batches,
           "grad_norm": float(stats["grad_norm"]) / batches}
    out.update({f"nll_{k}": float(stats[f"nll_{k}"]) / scenes for k in TERMS})
    for name in CLASS_NAMES:
        count = float(stats[f"count_{name}"])
        out[f"nll_per_{name}"] = float(stats[f"nll_sum_{name}"]) / count if count else None
    for k in VEHICLE_TERMS:
        # the box term averages over the vehicles whose box size was measured
        vehicles = float(stats["count_box_vehicle" if k == "box" else "count_vehicle"])
        total = float(stats[f"nll_{k}_sum_vehicle"])
        out[f"{k}_per_vehicle"] = total / vehicles if vehicles else None
    out["nll_stop"] = float(stats["nll_sum_stop"]) / scenes
    return out


def _warn_over_max_actors(cache: CacheUnion, cfg: Config) -> None:
    over = int(np.sum(actors_in_region(cache, cfg) > cfg.grid.max_actors))
    if over:
        log.info("%d of %d scenes hold more than max_actors = %d actors in the region "
                 "(unrotated): each trains on its first %d in canonical order, without a stop "
                 "token", over, len(cache), cfg.grid.max_actors, cfg.grid.max_actors)


def _prepare_workdir(cfg: Config, workdir: str, cache: CacheUnion, weights,
                     init_from: str | None) -> tuple[TrainState, TrainState | None]:
    """(fresh state, warm-started state for a new workdir or None), after writing or checking
    the workdir's config and data record. A warm start into a new workdir is built first, so
    that a bad `init_from` fails before anything is written."""
    state = init_state(cfg)
    warm = None
    if init_from is not None and not has_checkpoint(workdir):
        warm = warm_started(state, cfg, init_from)
    save_or_check_config(workdir, cfg)
    save_or_check_data(workdir, cache, weights)
    return state, warm


def _start_state(ckpt: Checkpointer, state: TrainState, warm: TrainState | None, cfg: Config,
                 init_from: str | None, replicated: NamedSharding
                 ) -> tuple[TrainState, MetricsWindow]:
    """The state training goes on from, replicated, and its metrics window: the newest
    checkpoint's, else the warm start's (`warm`, or built now), else `state`."""
    restored = ckpt.restore_latest(state, sharding=replicated)
    if restored is not None:
        state = restored
        window = resumed_window(ckpt.extra(int(state.step)), int(state.step))
    else:
        window = MetricsWindow(int(state.step))
        if init_from is not None:
            state = warm if warm is not None else warm_started(state, cfg, init_from)
            log.info("starting from the parameters of %s", init_from)
    return jax.device_put(state, replicated), window


def _progress_bar(steps: int, start: int, progress: bool, max_seconds: float | None) -> tqdm:
    # With a time budget the budget usually ends the run, not the step count: no step ETA.
    budget = None if max_seconds is None else (
        "{desc}: {n_fmt}/{total_fmt} steps [{elapsed} of a "
        + f"{tqdm.format_interval(max_seconds)} budget"
        + ", {rate_fmt}{postfix}]"
    )
    return tqdm(
        total=steps, initial=start, desc="train", unit="step", file=sys.stderr,
        disable=not (progress and is_main_process()), bar_format=budget,
    )


def _device_batch(cache: CacheUnion, indices: np.ndarray, thetas: np.ndarray, cfg: Config,
                  data_sharding: NamedSharding):
    """This process's rows `indices` of a global batch at rotations `thetas`, checked, on its
    devices."""
    host = gather_batch(cache, indices, cfg.grid, thetas)
    check_batch(host, [cache.scene_name(i) for i in indices])
    return to_device(host, data_sharding, cfg.train.batch_size)


def check_finite_loss(loss_sum: float, n0: int, done: int, cfg: Config) -> None:
    """Stops a diverged run: NonFiniteLoss when the loss summed over steps n0+1..done is NaN
    or infinite, naming the steps and what to lower."""
    if np.isfinite(loss_sum):
        return
    steps = f"step {done}" if done == n0 + 1 else f"steps {n0 + 1}-{done}"
    raise NonFiniteLoss(
        f"training diverged: the loss is {loss_sum} at {steps}; lower --set learning_rate "
        f"(now {cfg.train.learning_rate:g}) or set grad_clip (now {cfg.train.grad_clip:g}), "
        "in a new --workdir if this one has checkpoints")


def _log_metrics(window: MetricsWindow, done: int, path: str, bar: tqdm, cfg: Config) -> None:
    """Writes the row of the steps of `window` up to `done` to the metrics file and the
    progress bar; a non-finite loss stops the run."""
    acc = jax.device_get(window.sums)
    check_finite_loss(float(acc["loss"]), window.since, done, cfg)
    row = {"step": done, **summarize(acc),
           "steps_per_s": (done - window.since) / window.seconds()}
    if is_main_process():
        with open(path, "a") as f:
            f.write(json.dumps(row) + "\n")
    bar.set_postfix(loss=f"{row['loss']:.2f}", steps_s=f"{row['steps_per_s']:.2f}")


@dataclasses.dataclass
class MetricsWindow:
    """The steps since the last metrics row: the step they follow (`since`), their summed
    stats (`sums`, on the device; None before the first), and the seconds they took before
    this process resumed them (`earlier_s`) plus since `t0` (`time.perf_counter`)."""

    since: int
    sums: dict | None = None
    t0: float = dataclasses.field(default_factory=time.perf_counter)
    earlier_s: float = 0.0

    def add(self, stats: dict) -> None:
        self.sums = stats if self.sums is None else jax.tree.map(
            lambda a, b: a + b, self.sums, stats)

    def seconds(self) -> float:
        return self.earlier_s + time.perf_counter() - self.t0

    def record(self) -> dict:
        """The window as a checkpoint keeps it (`Checkpointer.save`'s extra): each sum with
        its dtype, so that the resumed run adds to the same numbers."""
        sums = None if self.sums is None else {
            k: [np.asarray(v).dtype.str, np.asarray(v).item()]
            for k, v in jax.device_get(self.sums).items()}
        return {"metrics_since": self.since, "metrics_sums": sums,
                "metrics_seconds": self.seconds()}


def resumed_window(record: dict | None, step: int) -> MetricsWindow:
    """The metrics window of a run resumed at `step` from the checkpoint record `record`
    (`MetricsWindow.record`): the rows then average the same steps as the uninterrupted
    run's. A checkpoint without one (saved by an older version) starts a window at `step`."""
    if not record or "metrics_since" not in record:
        return MetricsWindow(step)
    sums = record["metrics_sums"]
    return MetricsWindow(
        int(record["metrics_since"]),
        None if sums is None else {k: np.asarray(v, np.dtype(t)) for k, (t, v) in sums.items()},
        earlier_s=float(record["metrics_seconds"]),
    )


def train(
    cfg: Config,
    data_dir: str | list[str],
    workdir: str,
    steps: int,
    save_every: int = 100,
    log_every: int = 10,
    keep: int = 3,
    progress: bool = True,
    max_seconds: float | None = None,
    init_from: str | None = None,
    weights: list[float] | None = None,
) -> TrainState:
    """Trains until `steps` total steps (or `max_seconds` of wall time), resuming from
    `workdir`'s latest checkpoint; the last state is always saved. A fresh run (no checkpoint
    yet) with `init_from` starts from the trained parameters of that workdir or pretrained
    model (`start_params`, `warm_start`), with a fresh optimizer and step 0.

    `data_dir`: one cache or a list of caches of this config (`check_compatible`), trained on
    together (`CacheUnion`); each scene is drawn from cache i with probability
    `weights[i]` / sum(weights) (default: uniform over all scenes). The list and the weights
    are kept in WORKDIR/data.json, and a resume must use the same (`save_or_check_data`).

    The run holds the workdir's lock (`workdir.writing`: a second run on it is refused, naming
    this one's pid and host), refuses a folder that is a cache or an exported model, and,
    when it fails before its first checkpoint, leaves the workdir as it found it.

    In a multi-process job (`backend.start_distributed`) every process runs this with the
    same arguments: the mesh spans every process's devices, each process reads only its
    `local_rows` of each global batch of `cfg.train.batch_size` scenes, all save and restore the
    one checkpoint, and process 0 alone writes config.json, data.json, metrics.jsonl and
    the progress bar.
    """
    cache = load_union(data_dir, cfg)
    _warn_over_max_actors(cache, cfg)
    check_train_target(workdir)
    with writing(workdir, f"training into {os.path.abspath(workdir)}"):
        return _train(cfg, cache, workdir, steps, save_every, log_every, keep, progress,
                      max_seconds, init_from, weights)


def _train(cfg: Config, cache: CacheUnion, workdir: str, steps: int, save_every: int,
           log_every: int, keep: int, progress: bool, max_seconds: float | None,
           init_from: str | None, weights: list[float] | None) -> TrainState:
    """`train` in a workdir this process holds."""
    shares = resolve_weights(cache.sizes, weights)
    state, warm = _prepare_workdir(cfg, workdir, cache, weights, init_from)
    mesh = make_mesh()
    step_fn = None  # compiled for the first batch's shapes (every batch has the same)
    data_sharding = NamedSharding(mesh, P("data"))
    ckpt = Checkpointer(os.path.join(workdir, CHECKPOINTS), save_every, keep, heal=True)
    rows = local_rows(data_sharding, cfg.train.batch_size)
    state, window = _start_state(ckpt, state, warm, cfg, init_from, NamedSharding(mesh, P()))
    start = int(state.step)
    metrics_path = os.path.join(workdir, "metrics.jsonl")
    drop_metrics_after(metrics_path, start)
    bar = _progress_bar(steps, start, progress, max_seconds)
    rotations = jax.jit(step_rotations, static_argnums=(2, 3))
    key_data = np.asarray(jax.device_get(state.key))
    t_start = time.perf_counter()
    for step in range(start, steps):
        raise_pending()  # a Ctrl-C or SIGTERM whose exception Python swallowed
        indices = union_indices(cache, shares, cfg.train.batch_size, cfg.train.seed, step)[rows]
        thetas = np.asarray(rotations(key_data, step, cfg.train.batch_size,
                                      cfg.train.rotate_augment))[rows]
        batch = _device_batch(cache, indices, thetas, cfg, data_sharding)
        if step_fn is None:  # remat resolved once, for the programs the run compiles
            step_cfg = resolve_remat(cfg, cfg.train.batch_size // mesh.size)
            step_fn = train_step_for_run(step_cfg, state, batch, mesh, steps - step)
        state, stats = step_fn(state, batch)
        window.add({**stats, "batches": 1})
        done = step + 1
        out_of_time = max_seconds is not None and time.perf_counter() - t_start > max_seconds
        force = done == steps or out_of_time
        if done % log_every == 0 or done == steps:
            _log_metrics(window, done, metrics_path, bar, cfg)
            window = MetricsWindow(done)
        elif ckpt.due(done, force):  # a diverged state is not saved
            check_finite_loss(float(jax.device_get(window.sums["loss"])), window.since, done,
                              cfg)
        ckpt.save(state, force=force, extra=window.record)
        bar.update(1)
        if out_of_time:
            log.info("time budget of %.0f s used after step %d; stopping", max_seconds, done)
            break
    bar.close()
    if hasattr(step_fn, "close"):  # a background compile still running (`train_step_for_run`)
        step_fn.close()
    ckpt.close()
    return state


def warm_started(state: TrainState, cfg: Config, init_from: str) -> TrainState:
    """The fresh `state` with the parameters of `init_from` (`start_params`, `warm_start`),
    and an optimizer and moving average started on them."""
    source_cfg, source = start_params(init_from)
    params = warm_start(state.params, source, init_from, cfg.grid.map_channels,
                        source_cfg.grid.map_channels, fresh=reframed(cfg, source_cfg))
    return state._replace(params=params, opt_state=make_optimizer(cfg).init(params),
                          ema=start_ema(cfg, params))


def load_trained(workdir: str, step: int | None = None) -> tuple[Config, TrainState]:
    """(config, train state) of a training workdir: the latest readable checkpoint, or the
    one saved at `step`."""
    return restore(workdir, lambda cfg: jax.eval_shape(lambda: init_state(cfg)), step)
