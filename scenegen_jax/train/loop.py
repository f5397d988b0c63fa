"""The training driver: data order, sharded steps, progress bar, metrics file, checkpoints."""

from __future__ import annotations

import json
import logging
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax.traverse_util import flatten_dict, unflatten_dict
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
from scenegen_jax.model.network import ATTRIBUTES, MAP_CHANNEL_AXIS
from scenegen_jax.pretrained import load_pretrained
from scenegen_jax.scene import CLASS_NAMES
from scenegen_jax.train.data import resolve_weights, union_indices
from scenegen_jax.train.step import (
    TrainState,
    init_state,
    make_optimizer,
    resolve_remat,
    start_ema,
    train_step_for_run,
)
from scenegen_jax.workdir import (
    CHECKPOINTS,
    CONFIG_FILE,
    load_params,
    restore,
)

log = logging.getLogger(__name__)
DATA_FILE = "data.json"


def _write_atomic(path: str, text: str) -> None:
    """Writes `text` to `path` whole or not at all (other processes may read it meanwhile);
    in a multi-process job only process 0 writes."""
    if is_main_process():
        with written_whole(path) as tmp, open(tmp, "w") as f:
            f.write(text)


def save_or_check_config(workdir: str, cfg: Config) -> None:
    """Writes the resolved config beside the checkpoints; a resume must use the same one,
    except for `remat` (memory against time; the same values)."""
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(workdir, CONFIG_FILE)
    if os.path.exists(path):
        with open(path) as f:
            saved = Config.from_json(f.read(), path)
        if saved.replace(remat=cfg.remat) != cfg:
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
    order is a function of them. A workdir from before this record gets one."""
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(workdir, DATA_FILE)
    record = data_record(union, weights)
    if not os.path.exists(path):
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
    vehicles = float(stats["count_vehicle"])
    for k in VEHICLE_TERMS:
        total = float(stats[f"nll_{k}_sum_vehicle"])
        out[f"{k}_per_vehicle"] = total / vehicles if vehicles else None
    out["nll_stop"] = float(stats["nll_sum_stop"]) / scenes
    return out


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

    In a multi-process job (`backend.start_distributed`) every process runs this with the
    same arguments: the mesh spans every process's devices, each process reads only its
    `local_rows` of each global batch of `cfg.batch_size` scenes, all save and restore the
    one checkpoint, and process 0 alone writes config.json, data.json, metrics.jsonl and
    the progress bar.
    """
    cache = load_union(data_dir, cfg)
    over = int(np.sum(actors_in_region(cache, cfg) > cfg.max_actors))
    if over:
        log.info("%d of %d scenes hold more than max_actors = %d actors in the region "
                 "(unrotated): each trains on its first %d in canonical order, without a stop "
                 "token", over, len(cache), cfg.max_actors, cfg.max_actors)
    shares = resolve_weights(cache.sizes, weights)
    state = init_state(cfg)
    warm = None
    if init_from is not None and not os.path.exists(os.path.join(workdir, CONFIG_FILE)):
        warm = warm_started(state, cfg, init_from)  # a new workdir: fail before writing to it
    save_or_check_config(workdir, cfg)
    save_or_check_data(workdir, cache, weights)
    mesh = make_mesh()
    step_fn = None  # compiled for the first batch's shapes (every batch has the same)
    data_sharding = NamedSharding(mesh, P("data"))
    ckpt = Checkpointer(os.path.join(workdir, CHECKPOINTS), save_every, keep, heal=True)
    rows = local_rows(data_sharding, cfg.batch_size)
    replicated = NamedSharding(mesh, P())
    restored = ckpt.restore_latest(state, sharding=replicated)
    if restored is not None:
        state = restored
    elif init_from is not None:
        state = warm if warm is not None else warm_started(state, cfg, init_from)
        log.info("starting from the parameters of %s", init_from)
    state = jax.device_put(state, replicated)
    start = int(state.step)
    metrics_path = os.path.join(workdir, "metrics.jsonl")
    drop_metrics_after(metrics_path, start)
    # With a time budget the budget usually ends the run, not the step count: no step ETA.
    budget = None if max_seconds is None else (
        "{desc}: {n_fmt}/{total_fmt} steps [{elapsed} of a "
        + f"{tqdm.format_interval(max_seconds)} budget"
        + ", {rate_fmt}{postfix}]"
    )
    bar = tqdm(
        total=steps, initial=start, desc="train", unit="step", file=sys.stderr,
        disable=not (progress and is_main_process()), bar_format=budget,
    )
    acc, t0, n0 = None, time.perf_counter(), start
    t_start = t0
    for step in range(start, steps):
        indices = union_indices(cache, shares, cfg.batch_size, cfg.seed, step)[rows]
        host = gather_batch(cache, indices, cfg)
        check_batch(host, [cache.scene_name(i) for i in indices])
        batch = to_device(host, data_sharding, cfg.batch_size)
        if step_fn is None:  # remat resolved once, for the programs the run compiles
            step_cfg = resolve_remat(cfg, cfg.batch_size // mesh.size)
            step_fn = train_step_for_run(step_cfg, state, batch, mesh, steps - step)
        state, stats = step_fn(state, batch)
        stats = {**stats, "batches": 1}
        acc = stats if acc is None else jax.tree.map(lambda a, b: a + b, acc, stats)
        done = step + 1
        if done % log_every == 0 or done == steps:
            acc = jax.device_get(acc)
            if not np.isfinite(float(acc["loss"])):
                raise FloatingPointError(f"step {done}: loss is {float(acc['loss'])}; stopping")
            elapsed = time.perf_counter() - t0
            row = {"step": done, **summarize(acc), "steps_per_s": (done - n0) / elapsed}
            if is_main_process():
                with open(metrics_path, "a") as f:
                    f.write(json.dumps(row) + "\n")
            bar.set_postfix(loss=f"{row['loss']:.2f}", steps_s=f"{row['steps_per_s']:.2f}")
            acc, t0, n0 = None, time.perf_counter(), done
        out_of_time = max_seconds is not None and time.perf_counter() - t_start > max_seconds
        ckpt.save(state, force=done == steps or out_of_time)
        bar.update(1)
        if out_of_time:
            log.info("time budget of %.0f s used after step %d; stopping", max_seconds, done)
            break
    bar.close()
    if hasattr(step_fn, "close"):  # a background compile still running (`train_step_for_run`)
        step_fn.close()
    ckpt.close()
    return state


# Parameters a warm start may lack in its source: the map, lane orientation sector,
# coordinate and canonical order shares of layer 1's input convolution, and the attribute
# MLPs' weights of the map at the bin, first and last layer (a source trained without
# them). Zero, they leave the source's model as is.
ZERO_IF_MISSING = ("lstm1_map", "lstm1_coord", "lstm1_orient", "lstm1_order",
                   *(f"{name}{layer}_map_w" for name in ATTRIBUTES for layer in (0, 2)))
SHARED_ATTRIBUTE_MLP = "attr"  # its parameters' prefix (`separate_attribute_mlps` false)


def widen_map_channels(source: dict, channels: tuple[str, ...],
                       source_channels: tuple[str, ...], name: str) -> dict:
    """Flat `source` parameters read by a model with map channels `channels` instead of the
    `source_channels` they were trained with: each channel keeps its weights, the new ones
    start at zero (adding a layer group leaves the model as is).

    Raises:
      ValueError naming `name` if the source has channels `channels` lacks (a model without
      any map channels reads none of these weights: `source` as is).
    """
    if not channels:
        return source
    missing = [c for c in source_channels if c not in channels]
    if missing:
        raise ValueError(f"{name}: trained with map channels {missing} the config lacks")
    at = [channels.index(c) for c in source_channels]
    out = dict(source)
    for path, axis in MAP_CHANNEL_AXIS.items():
        if path in source:
            x = np.asarray(source[path])
            shape = list(x.shape)
            shape[axis] = len(channels)
            wide = np.zeros(shape, x.dtype)
            index = [slice(None)] * x.ndim
            index[axis] = at
            wide[tuple(index)] = x
            out[path] = wide
    return out


def split_attribute_mlp(source: dict, params: dict) -> dict:
    """Flat parameters of per-attribute MLPs (`ATTRIBUTES`, `separate_attribute_mlps`) that
    compute what the shared MLP in flat `source` computes: each copies its two hidden layers
    and takes its own columns of the last layer. Only the names `params` has and `source`
    lacks; empty if `source` has no shared MLP."""
    if f"{SHARED_ATTRIBUTE_MLP}2_w" not in source:
        return {}
    out, start = {}, 0
    for name in ATTRIBUTES:
        if f"{name}2_w" not in params or f"{name}2_w" in source:
            return {}
        for layer in (0, 1):
            for kind in ("w", "b"):
                out[f"{name}{layer}_{kind}"] = source[f"{SHARED_ATTRIBUTE_MLP}{layer}_{kind}"]
        stop = start + params[f"{name}2_w"].shape[-1]
        out[f"{name}2_w"] = source[f"{SHARED_ATTRIBUTE_MLP}2_w"][..., start:stop]
        out[f"{name}2_b"] = source[f"{SHARED_ATTRIBUTE_MLP}2_b"][..., start:stop]
        start = stop
    return out


def warm_started(state: TrainState, cfg: Config, init_from: str) -> TrainState:
    """The fresh `state` with the parameters of `init_from` (`start_params`, `warm_start`),
    and an optimizer and moving average started on them."""
    source_cfg, source = start_params(init_from)
    params = warm_start(state.params, source, init_from, cfg.map_channels,
                        source_cfg.map_channels, fresh=reframed(cfg, source_cfg))
    return state._replace(params=params, opt_state=make_optimizer(cfg).init(params),
                          ema=start_ema(cfg, params))


def start_params(init_from: str) -> tuple[Config, dict]:
    """(config, parameters) of a training workdir (its newest checkpoint), else of a
    pretrained model's name or directory (`pretrained.load_pretrained`: fine-tuning a shipped
    model)."""
    if os.path.isdir(os.path.join(init_from, CHECKPOINTS)):
        return load_params(init_from)[:2]
    try:
        return load_pretrained(init_from)[:2]
    except FileNotFoundError as e:
        raise FileNotFoundError(f"--init-from: neither a workdir with {CHECKPOINTS}/ nor a "
                                f"pretrained model ({e})") from e


# The heading MLP's last layer: what gives the heading mixture's directions.
HEADING_LAST_LAYER = ("heading2_w", "heading2_b", "heading2_map_w")


def reframed(cfg: Config, source_cfg: Config) -> tuple[str, ...]:
    """The parameters a warm start from a `source_cfg` model must not take for `cfg`: the
    heading MLP's last layer where `heading_lane_frame` differs (its directions meant
    angles in another frame; it starts afresh, as a near-uniform heading, and the hidden
    layers keep what they learnt). Empty where the frames agree.

    Raises:
      ValueError where the frames differ and `cfg` has one attribute MLP for all three (its
      last layer also gives the box and velocity)."""
    if cfg.heading_lane_frame == source_cfg.heading_lane_frame:
        return ()
    if not cfg.separate_attribute_mlps:
        raise ValueError("heading_lane_frame: a warm start from a model in the other frame "
                         "needs separate_attribute_mlps (the heading's own last layer)")
    return HEADING_LAST_LAYER


def warm_start(params, source, name: str, channels: tuple[str, ...] | None = None,
               source_channels: tuple[str, ...] | None = None, fresh: tuple[str, ...] = ()):
    """`params` with every parameter taken from `source` (same names and shapes), so training
    starts from the source's model. With the map channels of both (`channels`,
    `source_channels`), the source's map weights are first widened to `channels`
    (`widen_map_channels`: a model can be extended with a map layer group). The only
    parameters the source may lack are the map, lane orientation sector, coordinate and
    canonical order shares of layer 1's input convolution and the attribute MLPs' map
    weights (`ZERO_IF_MISSING`): they start at zero (those inputs then change nothing until
    training moves them), so a model can be extended with map layers, `orientation_bins`,
    `coord_channels`, `order_channel`, `attribute_map_input` or `attribute_map_skip`; and
    per-attribute MLPs, which start as copies of a shared attribute MLP
    (`split_attribute_mlp`: the same outputs). The parameters named in `fresh` keep their
    values in `params` (`reframed`).

    Raises:
      ValueError naming `name` and the parameter on a shape mismatch or another missing one.
    """
    flat = flatten_dict(params, sep="/")
    src = flatten_dict(source, sep="/")
    src = {**src, **split_attribute_mlp(src, flat)}
    if channels is not None and source_channels is not None:
        src = widen_map_channels(src, tuple(channels), tuple(source_channels), name)
    out = {}
    for path, x in flat.items():
        if path in fresh:
            out[path] = jnp.array(x, copy=True)
        elif path in src:
            if src[path].shape != x.shape:
                raise ValueError(f"{name}: parameter {path} has shape {src[path].shape}, the "
                                 f"config needs {x.shape}")
            # A copy: split MLPs start from the same source array, and a train step donates
            # each parameter's buffer (one buffer may not be donated twice).
            out[path] = jnp.array(src[path], x.dtype, copy=True)
        elif path.split("/")[0] in ZERO_IF_MISSING:
            out[path] = jnp.zeros_like(x)
        else:
            raise ValueError(f"{name}: no parameter {path} to start from")
    return unflatten_dict(out, sep="/")


def load_trained(workdir: str, step: int | None = None) -> tuple[Config, TrainState]:
    """(config, train state) of a training workdir: the latest readable checkpoint, or the
    one saved at `step`."""
    return restore(workdir, lambda cfg: jax.eval_shape(lambda: init_state(cfg)), step)
