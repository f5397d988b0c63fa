"""Training recipes: how a shipped model is trained, declared as data.

A recipe names its config preset and overrides, the caches it trains on (each a source to
`prepare`), and one or more runs, each a sequence of phases. A phase trains for a number of
steps with its own config overrides and caches, from scratch or from the parameters of the
run's previous phase (`init_from_previous`). The runner (`train.recipe.run_recipe`,
`scenegen reproduce NAME`) prepares the missing caches, trains each phase in its own workdir
(resuming where a phase stopped), and exports the model run's last phase.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any


@dataclasses.dataclass(frozen=True)
class CacheSpec:
    """A cache a recipe trains on: `scenegen prepare --source SOURCE --root DATA/ROOT
    --split SPLIT --stride STRIDE` at the recipe's config."""

    source: str
    root: str  # relative to the data root (default ../shared/data)
    split: str | None
    stride: int = 10


@dataclasses.dataclass(frozen=True)
class Phase:
    """One `scenegen train` of a run.

    Attributes:
      name: the phase's workdir, under the run's.
      steps: training steps of this phase.
      overrides: config fields on top of the recipe's and the run's.
      data: names of the recipe's caches trained on together (uniform over their scenes).
      init_from_previous: start from the parameters of the run's previous phase (a fresh
        optimizer; `train.loop.warm_started`) instead of from scratch.
    """

    name: str
    steps: int
    overrides: Mapping[str, Any]
    data: tuple[str, ...]
    init_from_previous: bool = False


@dataclasses.dataclass(frozen=True)
class Run:
    """A model of a recipe: its config overrides and its phases, in order."""

    name: str
    overrides: Mapping[str, Any]
    phases: tuple[Phase, ...]


@dataclasses.dataclass(frozen=True)
class Recipe:
    """A shipped model's training.

    Attributes:
      name: the pretrained model it makes.
      config: the preset (`config.PRESETS`).
      overrides: config fields every run shares.
      caches: name -> source of every cache a phase reads.
      runs: the models trained; `model_run` is the one shipped, the others are its
        comparisons (e.g. the same recipe without a map).
      model_run: the run whose last phase is exported.
      sampler: the manifest's sampler settings (`pretrained.SAMPLER_FIELDS`).
      save_every: steps between checkpoints (each phase keeps its newest only).
    """

    name: str
    config: str
    overrides: Mapping[str, Any]
    caches: Mapping[str, CacheSpec]
    runs: tuple[Run, ...]
    model_run: str
    sampler: Mapping[str, Any]
    save_every: int = 50

    def run(self, name: str) -> Run:
        for run in self.runs:
            if run.name == name:
                return run
        raise ValueError(f"recipe {self.name}: no run {name!r}; runs: "
                         f"{[r.name for r in self.runs]}")

    def phase_overrides(self, run: Run, phase: Phase) -> dict[str, Any]:
        """The config overrides of one phase: the recipe's, the run's, then the phase's."""
        return {**self.overrides, **run.overrides, **phase.overrides}


# The box MLP's parameters (`model.network`): the last phase of `cpu-av2-womd` trains only
# them, at a higher learning rate, which leaves the location, class, heading and velocity
# terms exactly as the base phase left them.
BOX_MLP = ("box0_b", "box0_map_w", "box0_w", "box1_b", "box1_w", "box2_b", "box2_map_w",
           "box2_w")
TRAIN_CACHES = ("av2_train", "womd_json_train", "womd_scenarionet_train")
MAP_INPUTS = {
    "map_layers": "lanes,drivable,crosswalks,nearest_lane,dataset",
    "attribute_map_input": True,
    "attribute_map_skip": True,
    "heading_lane_frame": True,
}

CPU_AV2_WOMD = Recipe(
    name="cpu-av2-womd",
    config="cpu",
    overrides={"coord_channels": True, "order_channel": True, "warmup_steps": 50},
    caches={
        "av2_train": CacheSpec("av2", "av2_sensor_mini", "train", stride=1),
        "womd_json_train": CacheSpec("womd_json", "womd_mini/gpudrive_json", "train"),
        "womd_scenarionet_train": CacheSpec("scenarionet", "womd_mini/scenarionet", "train"),
    },
    runs=(
        Run("map", MAP_INPUTS, (
            Phase("base", 5000, {"learning_rate": 1e-3, "decay_steps": 4950, "seed": 0},
                  TRAIN_CACHES),
            Phase("box", 300, {"train_params": ",".join(BOX_MLP), "learning_rate": 3e-3,
                               "decay_steps": 250, "seed": 1},
                  TRAIN_CACHES, init_from_previous=True),
        )),
        # The same base phase without map layers (only which data set a scene comes from):
        # what the model card's "map against no map" figures compare with.
        Run("nomap", {"map_layers": "dataset"}, (
            Phase("base", 5000, {"learning_rate": 1e-3, "decay_steps": 4950, "seed": 0},
                  TRAIN_CACHES),
        )),
    ),
    model_run="map",
    sampler={"location_temperature": 0.7},
)

RECIPES: dict[str, Recipe] = {CPU_AV2_WOMD.name: CPU_AV2_WOMD}


def get_recipe(name: str) -> Recipe:
    if name not in RECIPES:
        raise ValueError(f"unknown recipe {name!r}; recipes: {sorted(RECIPES)}")
    return RECIPES[name]
