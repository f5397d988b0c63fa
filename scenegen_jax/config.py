"""Frozen configuration dataclasses and the presets `paper`, `cpu` and `tiny`.

Every shape in the library comes from a `Config`; nothing is hard-coded for one grid.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
from typing import Any

from scenegen_jax.config_fields import (
    ALL_LAYER_GROUPS,
    DATASETS,
    LAYER_GROUPS,
    PAPER_LAYER_GROUPS,
    config_problems,
    flatten_json,
    parse_value,
    typed_value,
)
from scenegen_jax.jsonfile import parse_json

__all__ = ["ALL_LAYER_GROUPS", "DATASETS", "LAYER_GROUPS", "PAPER_LAYER_GROUPS", "Config",
           "GridConfig", "ModelConfig", "PRESETS", "SampleConfig", "TrainConfig",
           "apply_overrides", "from_flat", "get_config"]

# The sub-configs' fields, by sub-config, in `Config` order; every field name is unique
# across them, so `--set FIELD=VALUE` and `Config.replace(FIELD=...)` name fields flat.
SECTIONS = ("grid", "model", "train", "sample")


class _Part:
    """What every sub-config has beside its fields."""

    def replace(self, **kw: Any):
        return dataclasses.replace(self, **kw)


@dataclasses.dataclass(frozen=True)
class GridConfig(_Part):
    """The raster grid and the scene representation on it: what data, rasters, the model and
    the sampler share. Row/column convention: `scene.py`.

    Attributes:
      grid_size: H = W of every raster, pixels.
      m_per_px: raster resolution, metres per pixel (region side = grid_size * m_per_px).
      map_layers: layer groups rasterized as map channels (see `LAYER_GROUPS`); the presets
        take the paper's (`PAPER_LAYER_GROUPS`).
      max_actors: N, actor slots per scene (excluding the ego). A scene with more actors in
        the region keeps the first N in canonical order and has no stop token
        (`Scene.complete`).
      zero_speed: speeds (m/s) at or below this are the v = 0 point mass.
      pedestrian_size_m: nominal pedestrian footprint side, m (pedestrians are points).
      ego_size_m: (width, length) of the ego box, m.
    """

    grid_size: int = 32
    m_per_px: float = 2.5
    map_layers: tuple[str, ...] = PAPER_LAYER_GROUPS
    max_actors: int = 49
    zero_speed: float = 0.2
    pedestrian_size_m: float = 0.6
    ego_size_m: tuple[float, float] = (1.95, 4.9)

    @property
    def region_m(self) -> float:
        """Side of the square region of interest, m."""
        return self.grid_size * self.m_per_px

    @property
    def bin_area(self) -> float:
        """Area of one location bin, m^2."""
        return self.m_per_px**2

    @property
    def map_channels(self) -> tuple[str, ...]:
        """Names of the map raster channels, in order."""
        return tuple(c for g in ALL_LAYER_GROUPS if g in self.map_layers for c in LAYER_GROUPS[g])

    @property
    def canvas_size(self) -> int:
        """Side (px) of the canvas that holds the grid under every rotation about the ego: the
        disc of the actors a cache keeps, and the unrotated rasters the realism checks read."""
        return self.grid_size + 2 * math.ceil(self.grid_size * (math.sqrt(2.0) - 1.0) / 2.0 + 1.0)


@dataclasses.dataclass(frozen=True)
class ModelConfig(_Part):
    """The network and the grid it runs on: everything the scorer and the sampler compile
    against (with `SampleConfig` and the sampler's options).

    Attributes:
      grid: the grid (`GridConfig`).
      hidden: ConvLSTM / backbone channels.
      backbone_layers: 3x3 conv layers in the backbone.
      gn_groups: GroupNorm groups. The presets use one group per channel (the paper does not
        give the count): with several channels per group, a channel whose mean falls below
        its group's goes negative everywhere after the norm and dies behind the ReLU, and
        with it the backbone's heading information.
      num_mixtures: K, mixture components of box, heading and velocity (velocity has at
        least 2: the v = 0 point mass and one moving component).
      bptt_window: W, steps per window of the unroll: the ConvLSTM state is carried across
        windows; training backpropagates within a window (truncated backprop through time).
      coord_channels: two more input channels, each pixel's row and column in [-1, 1]
        (beyond the paper's input; off in the presets). The network is otherwise fully
        convolutional and cannot tell the top of the grid from the middle, where the first
        actor in canonical order stands.
      orientation_bins: K more input channels, the lane orientation binned over K equal
        sectors of the circle (each lane pixel splits its weight between the two sectors
        nearest its direction; 0 disables, the presets' default). The same information as the
        (cos, sin) channels, in a code that per-scene normalisation keeps: GroupNorm with one
        channel per group reduces cos(lane direction) on a straight road to its sign, but a
        sector's mask stays a mask. Needs the `lanes` layers.
      order_channel: one more input channel, 1 on the bins the canonical order still allows
        for the next actor (at or after the previous actor's bin, every bin at the first
        step) and 0 before (beyond the paper's input). It is what sampling's ordering mask
        removes, which the fully convolutional network cannot otherwise see: without it the
        unmasked distribution it learns and the masked one it is sampled from differ, and the
        class head cannot tell how much room the order leaves.
      attribute_map_input: the attribute MLPs also take the map channels at the actor's bin
        (beyond the paper, whose MLPs see the backbone's feature vector only). The raw map
        at the bin holds the lane direction that the heading needs; the 16-channel backbone
        passes on only part of it. Needs map layers and `separate_attribute_mlps`.
      attribute_map_skip: with `attribute_map_input`, the map channels at the bin also enter
        each attribute MLP's last layer, a linear path (beyond the paper) from the lane
        direction (cos, sin) to the heading mixture's directions, which the hidden ReLU
        layers approximate too coarsely to keep sampled headings along their lanes.
      heading_lane_frame: the heading mixture's directions are relative to the nearest
        lane's direction at the actor's bin (beyond the paper; the distribution is still the
        paper's von Mises mixture, turned by a known angle): the heading MLP gives angles
        against the lane, so one set of weights serves every street's direction, and a
        vehicle off the lanes (parked along or across the street) starts from the street's
        axis rather than from the grid's. No turn where no centreline is within
        `raster.map.NEAREST_LANE_MAX_M`. Needs the `nearest_lane` map layers.
      separate_attribute_mlps: one three-layer MLP per attribute (box, heading, velocity), as
        the paper's MLP_box, MLP_theta and MLP_v (the presets). False, the form of checkpoints
        whose config lacks this field, is one MLP whose last layer outputs all three: the
        heading then shares its hidden units with the box and velocity, and mostly fails to
        learn.
    """

    grid: GridConfig = GridConfig()
    hidden: int = 16
    backbone_layers: int = 5
    gn_groups: int = 16
    num_mixtures: int = 3
    bptt_window: int = 25
    coord_channels: bool = False
    orientation_bins: int = 0
    order_channel: bool = False
    attribute_map_input: bool = False
    attribute_map_skip: bool = False
    heading_lane_frame: bool = False
    separate_attribute_mlps: bool = False


@dataclasses.dataclass(frozen=True)
class TrainConfig(_Part):
    """What only training reads.

    Attributes:
      hard_negatives: bins in the training location normaliser (hard negative mining); at or
        above grid_size^2 it is the full softmax.
      batch_size: scenes per training step (global, across devices).
      learning_rate: Adam step size (after the warm-up).
      warmup_steps: steps of a linear learning-rate ramp from 0 to `learning_rate` (beyond the
        paper; 0 disables). Adam's first steps move every weight by about the full step size
        whatever its gradient; the ramp keeps them from silencing backbone channels.
      decay_steps: after the warm-up, steps of a cosine decay of the learning rate from
        `learning_rate` to 0, then 0 (beyond the paper; 0 keeps it constant): it decays the
        noise of constant-rate Adam at small batches.
      grad_clip: global-norm clip (0 disables).
      ema_decay: d of an exponential moving average of the parameters, updated after every
        step as d * average + (1 - d) * parameters from the parameters the run starts with
        (beyond the paper; 0, the default, keeps none). With it, `score`, `sample`,
        `evaluate`, `export-model` and `--init-from` read the average instead of the last
        step's parameters (`workdir.load_params`); about 1 / (1 - d) steps are averaged.
      rotate_augment: random rotation about the ego during training.
      map_dropout: probability that a training scene's map channels are all zeroed (beyond the
        paper): the model must then place actors from the actors alone, as a model without a
        map does, instead of only memorising where vehicles stand on the training maps.
      remat: recompute the backbone and heads in the train step's backward pass instead of
        storing their activations (same values and gradients; less memory, more compute):
        true, false, or "auto" (the `paper` preset's): false where the step without it
        fits in the memory free when training starts, else true (`train.step.resolve_remat`).
      train_layers: map layer groups (of `map_layers`) whose weights alone train (beyond the
        paper; fine-tuning): every other parameter, and the weights of every other map
        channel, keep the values the run starts from. For a model extended with a layer group
        by `--init-from` (its new weights start at zero), e.g. the `dataset` layers. Empty,
        with `train_params` empty too (the default): every parameter trains.
      train_params: parameters (top-level names of the parameter tree, e.g. `lstm1_order`)
        that train in full beside `train_layers` (beyond the paper; fine-tuning); every
        other parameter keeps its starting values.
      seed: base random seed.
    """

    hard_negatives: int = 512
    batch_size: int = 4
    learning_rate: float = 1e-3
    warmup_steps: int = 0
    decay_steps: int = 0
    grad_clip: float = 1.0
    ema_decay: float = 0.0
    rotate_augment: bool = True
    map_dropout: float = 0.0
    remat: bool | str = False  # true, false or "auto"
    train_layers: tuple[str, ...] = ()
    train_params: tuple[str, ...] = ()
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class SampleConfig(_Part):
    """The sampler's defaults that a model's config carries.

    Attributes:
      proposals: M, best-of-M draws of the heading and velocity when sampling (the box size
        and the position are one draw each; `sampling.rollout`).
    """

    proposals: int = 10


def _section_fields() -> dict[str, str]:
    """{flat field name: its section} over every sub-config (the grid's are the model's)."""
    out = {f.name: "grid" for f in dataclasses.fields(GridConfig)}
    for section, cls in (("model", ModelConfig), ("train", TrainConfig),
                         ("sample", SampleConfig)):
        out.update({f.name: section for f in dataclasses.fields(cls) if f.name != "grid"})
    return out


FIELD_SECTIONS: dict[str, str] = _section_fields()


@dataclasses.dataclass(frozen=True)
class Config:
    """Every hyperparameter, by concern: the model (with its grid), training and sampling.
    Functions take the part they read: the grid (`cfg.model.grid`) for data and rasters,
    the model for the network, the scorer and the sampler, the whole config for training.

    Attributes:
      name: preset name.
      model: `ModelConfig` (its `grid`: `GridConfig`).
      train: `TrainConfig`.
      sample: `SampleConfig`.
    """

    name: str = "tiny"
    model: ModelConfig = ModelConfig()
    train: TrainConfig = TrainConfig()
    sample: SampleConfig = SampleConfig()

    def __post_init__(self):
        for section, cls in (("model", ModelConfig), ("train", TrainConfig),
                             ("sample", SampleConfig)):
            if not isinstance(getattr(self, section), cls):
                raise ValueError(f"invalid config: {section} must be a {cls.__name__}, got "
                                 f"{type(getattr(self, section)).__name__}")
        if not isinstance(self.model.grid, GridConfig):
            raise ValueError("invalid config: model.grid must be a GridConfig")
        problems = config_problems(types.SimpleNamespace(**self.flat()))
        if problems:
            raise ValueError("invalid config: " + "; ".join(problems))

    @property
    def grid(self) -> GridConfig:
        """The model's grid (`model.grid`)."""
        return self.model.grid

    def flat(self) -> dict[str, Any]:
        """{field: value} over every sub-config, with `name`."""
        out: dict[str, Any] = {"name": self.name}
        for part in (self.model.grid, self.model, self.train, self.sample):
            out.update({f.name: getattr(part, f.name) for f in dataclasses.fields(part)
                        if f.name != "grid"})
        return out

    def replace(self, **kw: Any) -> Config:
        """This config with fields replaced, each named flat (`grid_size=64`,
        `learning_rate=3e-4`) or a whole sub-config (`model=...`)."""
        return from_flat({**self.flat(), **_flatten_sections(kw)})

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2)

    @classmethod
    def from_json(cls, text: str | bytes, source: str = "config") -> Config:
        """The config of `to_json` text, or of the one-level form written before the
        sub-configs (every field at the top level), which reads as the same config; errors
        name `source` (a file) and the field."""
        d = parse_json(text, source)
        if not isinstance(d, dict):
            raise ValueError(f"{source}: expected a JSON object of config fields")
        flat = flatten_json(d, source)
        unknown = sorted(set(flat) - set(FIELD_SECTIONS) - {"name"})
        if unknown:
            raise ValueError(f"{source}: unknown config field(s) {unknown}")
        default = cls().flat()
        for key, value in flat.items():
            flat[key] = typed_value(key, value, type(default[key]), source)
        try:
            return from_flat(flat)
        except ValueError as e:
            raise ValueError(f"{source}: {e}") from e

    def differences(self, other: Config) -> list[str]:
        """'field: self value != other value' for every field that differs."""
        mine, theirs = self.flat(), other.flat()
        return [f"{k}: {mine[k]!r} != {theirs[k]!r}" for k in mine if mine[k] != theirs[k]]


def from_flat(flat: dict[str, Any]) -> Config:
    """The config of {field: value} over every sub-config (missing fields: defaults)."""
    unknown = sorted(set(flat) - set(FIELD_SECTIONS) - {"name"})
    if unknown:
        raise ValueError(f"unknown config field(s) {unknown}; fields: "
                         f"{sorted(FIELD_SECTIONS)}")
    parts = {s: {k: v for k, v in flat.items() if FIELD_SECTIONS.get(k) == s}
             for s in SECTIONS}
    kw = {"model": ModelConfig(grid=GridConfig(**parts["grid"]), **parts["model"]),
          "train": TrainConfig(**parts["train"]), "sample": SampleConfig(**parts["sample"])}
    if "name" in flat:
        kw["name"] = flat["name"]
    return Config(**kw)


def _flatten_sections(kw: dict[str, Any]) -> dict[str, Any]:
    """`replace` keywords with whole sub-configs spread into their fields."""
    out = {}
    for key, value in kw.items():
        if dataclasses.is_dataclass(value) and key in ("model", "grid", "train", "sample"):
            fields = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
            if key == "model":
                fields.update(_flatten_sections({"grid": fields.pop("grid")}))
            out.update(fields)
        else:
            out[key] = value
    return out


PRESETS: dict[str, Config] = {
    # As published: 80 m x 80 m at 0.25 m/px, K = 10, 10,000 hard negatives, batch 16.
    "paper": from_flat(dict(
        name="paper",
        grid_size=320,
        m_per_px=0.25,
        max_actors=128,
        hidden=32,
        gn_groups=32,
        num_mixtures=10,
        hard_negatives=10_000,
        batch_size=16,
        learning_rate=1e-4,
        grad_clip=0.0,
        separate_attribute_mlps=True,
        # Recomputes only where the step would not fit: its batch of 16 on one accelerator.
        # On CPU, where a scene's step fits, recomputing would only cost time.
        remat="auto",
    )),
    # Trains on 2 CPU cores: 1.25 m/px over the same 80 m region, half the paper's width.
    "cpu": from_flat(dict(
        name="cpu",
        grid_size=64,
        m_per_px=1.25,
        max_actors=39,
        bptt_window=20,
        hidden=16,
        gn_groups=16,
        num_mixtures=10,
        # The full softmax over the 4,096 bins: with 2,000 hard negatives (half the grid) the
        # location term stays at flat logits.
        hard_negatives=64 * 64,
        batch_size=4,
        learning_rate=1e-3,
        separate_attribute_mlps=True,
    )),
    # Tests and the demo: minutes on 2 cores. The full softmax over its 1,024 bins, as `cpu`.
    "tiny": from_flat(dict(hard_negatives=32 * 32, separate_attribute_mlps=True)),
}


def get_config(name: str, /, **overrides: Any) -> Config:
    """Returns a preset with `overrides` applied (values parsed from strings if needed)."""
    if name not in PRESETS:
        raise ValueError(f"unknown config {name!r}; choose one of {sorted(PRESETS)}")
    return apply_overrides(PRESETS[name], **overrides)


def apply_overrides(base: Config, /, **overrides: Any) -> Config:
    """`base` with fields replaced; string values are parsed to the field's type."""
    current = base.flat()
    parsed: dict[str, Any] = {}
    for key, value in overrides.items():
        if key not in current:
            raise ValueError(f"unknown config field {key!r}; fields: {sorted(current)}")
        parsed[key] = parse_value(current[key], value, key)
    return base.replace(**parsed)
