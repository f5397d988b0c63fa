"""The recipe machinery end to end on the `tiny` config: the shipped model's recipe with its
runs and phases kept (a phase from scratch, a phase started from the previous one that trains
only some parameters, the export) but two steps per phase and a small real cache."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
from flax.traverse_util import flatten_dict

from scenegen_jax.pretrained import load_pretrained
from scenegen_jax.recipes import BOX_MLP, CPU_AV2_WOMD, CacheSpec, get_recipe
from scenegen_jax.train.recipe import cache_path, phase_config, run_recipe
from scenegen_jax.workdir import load_params


def tiny_recipe():
    """The shipped recipe at the `tiny` config: every run and phase kind as shipped, each
    phase two steps on one Argoverse 2 cache (stride 40: 4 frames a log)."""
    runs = tuple(
        dataclasses.replace(run, phases=tuple(
            dataclasses.replace(p, steps=2, data=("av2",), overrides={
                **p.overrides, "decay_steps": 1}) for p in run.phases))
        for run in CPU_AV2_WOMD.runs
    )
    return dataclasses.replace(
        CPU_AV2_WOMD, config="tiny", runs=runs, save_every=1,
        overrides={**CPU_AV2_WOMD.overrides, "warmup_steps": 1},
        caches={"av2": CacheSpec("av2", "av2_sensor_mini", "train", stride=40)},
    )


def test_recipe_declares_every_phase_kind():
    recipe = get_recipe("cpu-av2-womd")
    assert recipe.model_run in [r.name for r in recipe.runs]
    kinds = {p.init_from_previous for r in recipe.runs for p in r.phases}
    assert kinds == {False, True}
    for run in recipe.runs:
        assert not run.phases[0].init_from_previous  # every run starts from scratch
        for phase in run.phases:
            assert set(phase.data) <= set(recipe.caches)
            phase_config(recipe, run, run.phases.index(phase))  # a valid config
    with pytest.raises(ValueError, match="unknown recipe"):
        get_recipe("nope")


def test_tiny_recipe_end_to_end(tmp_path, data_root):
    recipe = tiny_recipe()
    shared = os.path.dirname(data_root)
    workdir, out = str(tmp_path / "run"), str(tmp_path / "model")
    # The model's run: both phase kinds and the export (the no-map run is a base phase again,
    # on other map layers: its config is checked above).
    done = run_recipe(recipe, workdir, str(tmp_path / "caches"), shared, runs=["map"],
                      out=out, progress=False, workers=1)
    assert set(done) == {"map"}
    assert os.path.isfile(os.path.join(cache_path(recipe, str(tmp_path / "caches"), "av2"),
                                       "meta.json"))
    base = flatten_dict(load_params(os.path.join(workdir, "map", "base"))[1], sep="/")
    cfg_box, box, step = load_params(os.path.join(workdir, "map", "box"))
    box = flatten_dict(box, sep="/")
    assert step == 2 and cfg_box.train.train_params == BOX_MLP
    # The box phase starts from the base phase and moves only the box MLP.
    moved = {k for k in base if not np.array_equal(base[k], box[k])}
    assert moved and {k.split("/")[0] for k in moved} <= set(BOX_MLP)
    # The exported model is the model run's last phase, with the recipe's sampler settings.
    cfg, params, manifest = load_pretrained(out)
    assert cfg == cfg_box and manifest["sampler"] == dict(recipe.sampler)
    for k, v in flatten_dict(params, sep="/").items():
        np.testing.assert_array_equal(v, box[k])
    # A second call resumes: every phase is at its step count, nothing trains again.
    before = os.path.getmtime(os.path.join(workdir, "map", "box", "metrics.jsonl"))
    run_recipe(recipe, workdir, str(tmp_path / "caches"), shared, runs=["map"],
               progress=False, workers=1)
    assert os.path.getmtime(os.path.join(workdir, "map", "box", "metrics.jsonl")) == before
    with pytest.raises(ValueError, match="include it in --run"):
        run_recipe(recipe, workdir, str(tmp_path / "caches"), shared, runs=["nomap"], out=out,
                   progress=False)
