"""The public Python API: one `Model` (config and parameters together) that every function
reading a trained model takes first (`prepare` takes it, or a config, after the source and
paths; `train_model` a config), around the library's modules (`import scenegen_jax as
sg`).

    model = sg.load_model("cpu-av2-womd")
    data = sg.prepare("av2", "../shared/data/av2_sensor_mini", "runs/av2_val", model,
                      split="val")
    scores = sg.score(model, data)
    scenes = sg.sample(model, data, num_scenes=4, seed=0)
    sg.render(model, scenes, "out/samples.png")
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import numpy as np

from scenegen_jax.config import Config, get_config
from scenegen_jax.data.union import CacheUnion, load_union
from scenegen_jax.distributions import TERMS
from scenegen_jax.eval import nll
from scenegen_jax.sampling.batch import CacheScene, sample_on_cache
from scenegen_jax.sampling.rollout import SamplerOptions


@dataclasses.dataclass(frozen=True)
class Model:
    """A trained SceneGen: its config, its parameters and where they come from.

    Attributes:
      config: the `Config` it was trained with.
      params: the network's parameter tree (arrays).
      step: the training step of the parameters.
      sampler: the sampler settings it recommends (a pretrained manifest's "sampler", e.g.
        {"location_temperature": 0.7}); `sample` and `evaluate` use them unless told
        otherwise.
      source: the pretrained model or workdir it was loaded from.
    """

    config: Config
    params: Any
    step: int = 0
    sampler: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    source: str = ""

    def sampler_options(self, **overrides: Any) -> SamplerOptions:
        """`SamplerOptions` of the recommended settings with `overrides` (None: keep)."""
        fields = {**self.sampler, **{k: v for k, v in overrides.items() if v is not None}}
        return SamplerOptions(**fields)


def check_model(model: Any, where: str) -> Model:
    """`model` if it is a `Model`, else a TypeError saying what `where` expects."""
    if not isinstance(model, Model):
        raise TypeError(f"{where}: expected a scenegen_jax.Model as the first argument (e.g. "
                        f"sg.load_model('cpu-av2-womd')), got {type(model).__name__}")
    return model


def load_model(name_or_dir: str, step: int | None = None) -> Model:
    """A shipped model's name (`sg.pretrained.available()`), a pretrained directory
    (`scenegen export-model`), or a training workdir (its newest checkpoint, or `step`)."""
    from scenegen_jax.workdir import CHECKPOINTS, load_params

    path = os.fspath(name_or_dir)
    if os.path.isdir(os.path.join(path, CHECKPOINTS)):
        cfg, params, saved_step = load_params(path, step)
        return Model(cfg, _uncommitted(params), saved_step, {}, path)
    if step is not None:
        raise ValueError(f"{path}: step selects a checkpoint of a training workdir; a "
                         "pretrained model has one")
    from scenegen_jax.pretrained import load_pretrained

    cfg, params, manifest = load_pretrained(path)
    return Model(cfg, _uncommitted(params), manifest["step"],
                 dict(manifest.get("sampler", {})), path)


def _uncommitted(params):
    # Restored arrays are committed to a device; jit compiles another program for those.
    return jax.device_put(jax.device_get(params))


def _config_of(model_or_config: Model | Config | str, where: str,
               models: bool = True) -> Config:
    """The config of a Model (where `models`), a Config or a preset name, else a TypeError
    saying what `where` expects."""
    if isinstance(model_or_config, Model):
        if not models:
            raise TypeError(f"{where}: expected a Config or a preset name, got a Model (to "
                            f"start from its parameters: init_from={model_or_config.source!r})")
        return model_or_config.config
    if isinstance(model_or_config, Config):
        return model_or_config
    if isinstance(model_or_config, str):
        return get_config(model_or_config)
    kinds = "a Model, a Config or a preset name" if models else "a Config or a preset name"
    raise TypeError(f"{where}: expected {kinds}, got {type(model_or_config).__name__}")


def prepare(source: str, root: str, out: str, model_or_config: Model | Config | str,
            split: str | None = None, stride: int | None = None,
            workers: int | None = None) -> CacheUnion:
    """Reads a data set (`source`: one of `data.sources.SOURCES`, e.g. "av2", "womd", under
    `root`) into a cache at `out` for the grid of a model, config or preset; returns it
    opened."""
    from scenegen_jax.data.prepare import prepare as prepare_cache
    from scenegen_jax.data.sources import DEFAULT_STRIDE, SOURCES, source_spec

    if not isinstance(source, str):
        raise TypeError(f"prepare: expected the source kind first (one of {SOURCES}), got "
                        f"{type(source).__name__}")
    cfg = _config_of(model_or_config, "prepare")
    spec = source_spec(source, root, split, DEFAULT_STRIDE if stride is None else stride)
    prepare_cache(spec, out, cfg, workers=workers)
    return load_union(out, cfg)


def load_data(model: Model, paths: str | Sequence[str]) -> CacheUnion:
    """Opens one or several caches (read as one) for `model`'s grid."""
    return load_union(paths, check_model(model, "load_data").config)


def train_model(config: Config | str, data: str | Sequence[str], workdir: str, steps: int,
                **options: Any) -> Model:
    """Trains (or resumes) a model of `config` (a `Config` or a preset name) on caches in
    `workdir` for `steps` steps (`train.loop.train`'s `options`: save_every, init_from,
    weights, ...) and returns it."""
    from scenegen_jax.train.loop import train as train_loop

    cfg = _config_of(config, "train_model", models=False)
    state = train_loop(cfg, data, workdir, steps, **options)
    return Model(cfg, _uncommitted(state.ema if cfg.train.ema_decay > 0 else state.params),
                 int(state.step), {}, workdir)


@dataclasses.dataclass(frozen=True)
class Scores:
    """The likelihood of every scene of a cache.

    per_step: term -> float [S, T] NLL (nats), "step_valid" bool [S, T], "step_cls" int
      [S, T], "step_size_measured" bool [S, T] (`eval.nll.score_cache`).
    """

    per_step: Mapping[str, np.ndarray]

    @property
    def scene_nll(self) -> np.ndarray:
        """float [S]: each scene's NLL, nats."""
        return np.sum(sum(self.per_step[k] for k in TERMS), axis=1)

    def summary(self) -> dict:
        """Mean scene NLL, per-actor NLL by class and term (`eval.nll.summarize_scores`)."""
        return nll.summarize_scores(dict(self.per_step))

    def most_unusual(self, k: int) -> list[tuple[int, int, float, dict]]:
        """The k scenes of highest NLL per actor (`eval.nll.worst_scenes`)."""
        return nll.worst_scenes(dict(self.per_step), k)


def score(model: Model, data: CacheUnion | str | Sequence[str], batch_size: int = 8,
          progress: bool = False) -> Scores:
    """Scores every scene of `data` (an opened cache or cache paths) under `model`."""
    model = check_model(model, "score")
    cache = _open(model, data)
    return Scores(nll.score_cache(model.params, cache, model.config, batch_size=batch_size,
                                  progress=progress))


def sample(model: Model, data: CacheUnion | str | Sequence[str], num_scenes: int,
           seed: int = 0, *, indices: Sequence[int] | None = None, batch_size: int = 8,
           location_temperature: float | None = None, proposals: int | None = None,
           ) -> list[CacheScene]:
    """Samples `num_scenes` scenes on the maps and egos of `data`'s scenes (scene k on scene
    `indices[k % len(indices)]`, default every scene in turn); the same seed gives the same
    scenes in any batch size."""
    model = check_model(model, "sample")
    options = model.sampler_options(location_temperature=location_temperature,
                                    proposals=proposals)
    return list(sample_on_cache(model.params, model.config, _open(model, data), num_scenes,
                                seed, indices=indices, batch_size=batch_size, options=options))


def evaluate(model: Model, data: CacheUnion | str | Sequence[str],
             train_data: CacheUnion | str | Sequence[str], num_scenes: int = 64,
             seed: int = 0, companions: str | None = None) -> dict:
    """The paper's Table 1 protocol on `data`: NLL, MMD against the baselines (fitted on
    `train_data`) and realism figures (`eval.evaluate.evaluate`). The Features MMD and the
    learned baselines read the companions shipped with `companions` (a pretrained model's
    name or directory; default: the model's own when it is a pretrained one); those missing
    are left out."""
    from scenegen_jax.eval.evaluate import evaluate as evaluate_model
    from scenegen_jax.pretrained import COMPANIONS, load_companion
    from scenegen_jax.workdir import CHECKPOINTS

    model = check_model(model, "evaluate")
    source = companions
    if source is None and model.source and not os.path.isdir(
            os.path.join(model.source, CHECKPOINTS)):
        source = model.source
    found = {kind: load_companion(source, kind) if source else None for kind in COMPANIONS}
    return evaluate_model(model.params, model.config, _open(model, data),
                          _open(model, train_data), num_scenes, seed, model.sampler_options(),
                          {k: v[:2] for k, v in found.items() if v is not None})


def render(model: Model, scenes: CacheScene | Sequence[CacheScene], path: str) -> list[str]:
    """PNGs of sampled scenes in the paper's colours: `path` for one scene, else `path`
    numbered per scene (`out/samples_00000.png`, ...). Returns the files written."""
    from scenegen_jax.viz.render import render_scene

    model = check_model(model, "render")
    scenes = [scenes] if isinstance(scenes, CacheScene) else list(scenes)
    root, ext = os.path.splitext(path)
    out = []
    for n, scene in enumerate(scenes):
        if not isinstance(scene, CacheScene):
            raise TypeError(f"render: expected sampled scenes (sg.sample), got "
                            f"{type(scene).__name__}")
        file = path if len(scenes) == 1 else f"{root}_{n:05d}{ext or '.png'}"
        os.makedirs(os.path.dirname(os.path.abspath(file)), exist_ok=True)
        render_scene(file, scene.map_raster, model.config.grid.map_channels, scene.actors,
                     scene.ego, model.config, title=f"sample {scene.index}")
        out.append(file)
    return out


def _open(model: Model, data) -> CacheUnion:
    if isinstance(data, CacheUnion):
        data.check_config(model.config)
        return data
    if isinstance(data, Model):
        raise TypeError("expected a cache (sg.load_data or sg.prepare) or cache paths after "
                        "the model, got a second Model")
    return load_union(data, model.config)
