"""The recipe runner: prepares a recipe's caches, trains its phases in order (each resuming
where it stopped) and exports its model (`recipes`, `scenegen reproduce`)."""

from __future__ import annotations

import logging
import os
import sys

from tqdm import tqdm

from scenegen_jax.config import Config, get_config
from scenegen_jax.data.cache_layout import READABLE_VERSIONS
from scenegen_jax.jsonfile import read_json
from scenegen_jax.recipes import Recipe, Run
from scenegen_jax.train.loop import train
from scenegen_jax.workdir import check_model_target, has_checkpoint, load_params

log = logging.getLogger(__name__)


def cache_path(recipe: Recipe, cache_dir: str, name: str) -> str:
    """Where the recipe's cache `name` is (or will be) prepared."""
    return os.path.abspath(os.path.join(cache_dir, f"{recipe.config}_{name}"))


def _current_cache(path: str) -> bool:
    """Whether `path` holds a cache that this scenegen reads."""
    meta_path = os.path.join(path, "meta.json")
    if not os.path.isfile(meta_path):
        return False
    meta = read_json(meta_path)
    return isinstance(meta, dict) and meta.get("version") in READABLE_VERSIONS


def prepare_caches(recipe: Recipe, cache_dir: str, data_root: str, names=None,
                   workers: int | None = None) -> dict[str, str]:
    """Prepares each of the recipe's caches (or of `names`) that is not there yet, or was
    written by a scenegen whose cache version this one does not read; returns name -> cache
    directory."""
    from scenegen_jax.data.prepare import prepare
    from scenegen_jax.data.sources import source_spec

    cfg = get_config(recipe.config)
    out = {}
    for name in names if names is not None else recipe.caches:
        spec = recipe.caches[name]
        path = cache_path(recipe, cache_dir, name)
        if not _current_cache(path):
            source = source_spec(spec.source, os.path.join(data_root, spec.root), spec.split,
                                 spec.stride)
            with tqdm(desc=f"prepare {name}", unit="file", file=sys.stderr) as bar:
                summary, _ = prepare(source, path, cfg, workers=workers, progress=bar)
            log.info("%s: %d scenes", path, summary.scenes)
        out[name] = path
    return out


def phase_workdir(workdir: str, run: Run, index: int) -> str:
    return os.path.join(workdir, run.name, run.phases[index].name)


def phase_config(recipe: Recipe, run: Run, index: int) -> Config:
    return get_config(recipe.config, **recipe.phase_overrides(run, run.phases[index]))


def train_run(recipe: Recipe, run: Run, workdir: str, caches: dict[str, str],
              progress: bool = True) -> str:
    """Trains every phase of `run` in order under WORKDIR/RUN/PHASE; a phase already at its
    step count only checks its workdir. Returns the last phase's workdir."""
    previous = None
    for index, phase in enumerate(run.phases):
        path = phase_workdir(workdir, run, index)
        init = previous if phase.init_from_previous else None
        if init is not None and not has_checkpoint(path):
            log.info("%s/%s starts from %s", run.name, phase.name, init)
        train(phase_config(recipe, run, index), [caches[n] for n in phase.data], path,
              phase.steps, save_every=recipe.save_every, keep=1, progress=progress,
              init_from=init)
        previous = path
    return previous


def run_recipe(recipe: Recipe, workdir: str, cache_dir: str, data_root: str,
               runs: list[str] | None = None, out: str | None = None,
               progress: bool = True, workers: int | None = None) -> dict:
    """Runs `recipe` (or only its `runs`) and, with `out`, exports its model run's last
    phase there as a pretrained model; `workers`: processes preparing a missing cache
    (default one per core). Returns {run name: last phase's workdir}."""
    from scenegen_jax.pretrained import save_pretrained

    selected = [recipe.run(name) for name in runs] if runs else list(recipe.runs)
    if out is not None and recipe.model_run not in [run.name for run in selected]:
        raise ValueError(f"--out exports the recipe's model, run {recipe.model_run!r}: "
                         f"include it in --run (or leave --run out)")
    if out is not None:
        check_model_target("--out", out)
    needed = sorted({n for run in selected for phase in run.phases for n in phase.data})
    caches = prepare_caches(recipe, cache_dir, data_root, needed, workers)
    done = {run.name: train_run(recipe, run, workdir, caches, progress) for run in selected}
    if out is not None:
        final = done[recipe.model_run]
        cfg, params, step = load_params(final)
        save_pretrained(out, cfg, params, step, final, dict(recipe.sampler))
    return done
