"""The config's vocabulary: the map layer groups, and the checks and parsing of field values
that `config.Config` applies (from JSON, from `--set FIELD=VALUE` strings)."""

from __future__ import annotations

import math
from typing import Any

# Map layer groups and the raster channels each contributes, in channel order.
LAYER_GROUPS: dict[str, tuple[str, ...]] = {
    "lanes": (
        "lane_vehicle",
        "lane_bike",
        "lane_bus",
        "lane_centerline",
        "lane_boundary_crossable",
        "lane_boundary_uncrossable",
        "lane_intersection",
        "lane_orientation_cos",
        "lane_orientation_sin",
    ),
    "drivable": ("drivable_area",),
    "crosswalks": ("crosswalk",),
    # Beyond the paper: the direction of the nearest lane centreline at every pixel, on and
    # off the lanes (`raster.map.NEAREST_LANE_MAX_M`).
    "nearest_lane": ("nearest_lane_cos", "nearest_lane_sin"),
    # Beyond the paper: which data set the scene comes from, one constant plane per known
    # data set (`DATASETS`), 1 on the scene's own (all 0 for another or an unknown one).
    # Data sets differ in their annotation (Waymo's vehicle boxes are larger than Argoverse
    # 2's) and in what their maps draw; a model trained on several can tell them apart.
    "dataset": ("dataset_av2", "dataset_waymo"),
}
# The data sets of the "dataset" layers, as ScenarioNet names them (`metadata.dataset`).
DATASETS: tuple[str, ...] = ("av2", "waymo")
# Every group, in channel order: what a cache stores.
ALL_LAYER_GROUPS: tuple[str, ...] = ("lanes", "drivable", "crosswalks", "nearest_lane", "dataset")
# The paper's map layers: the presets' default.
PAPER_LAYER_GROUPS: tuple[str, ...] = ("lanes", "drivable", "crosswalks")



def flatten_json(d: dict, source: str) -> dict[str, Any]:
    """{field: value} of a config JSON object, nested (`to_json`) or one level."""
    out = {k: v for k, v in d.items() if k not in ("model", "train", "sample")}
    for section in ("model", "train", "sample"):
        if section not in d:
            continue
        part = d[section]
        if not isinstance(part, dict):
            raise ValueError(f"{source}: field {section}: expected an object, got {part!r}")
        part = dict(part)
        if section == "model":
            grid = part.pop("grid", {})
            if not isinstance(grid, dict):
                raise ValueError(f"{source}: field model.grid: expected an object, got "
                                 f"{grid!r}")
            part.update(grid)
        clash = sorted(set(part) & set(out))
        if clash:
            raise ValueError(f"{source}: field(s) {clash} given twice")
        out.update(part)
    return out


def typed_value(key: str, value: Any, want: type, source: str) -> Any:
    """A JSON value as the field's type; errors name `source` and the field."""
    if key == "remat" and value == "auto":
        return value
    if want is tuple:
        if not isinstance(value, list):
            raise ValueError(f"{source}: field {key}: expected a list, got {value!r}")
        return tuple(value)
    if want is float and isinstance(value, int) and not isinstance(value, bool):
        try:
            return float(value)
        except OverflowError as e:
            raise ValueError(f"{source}: field {key}: integer out of float range") from e
    if type(value) is not want:
        raise ValueError(f"{source}: field {key}: expected {want.__name__}, got {value!r}")
    return value


# Integer fields become int32 arrays and shapes in the compiled programs, the seed a 32-bit
# key (JAX's keys and numpy's generators; larger ones would wrap onto these or overflow).
INT_LIMIT = 2**31
SEED_LIMIT = 2**32


def int_problem(name: str, value: Any, least: int, below: int = INT_LIMIT) -> str | None:
    """Why the integer field `name` cannot be `value` (not an integer, < `least`, or not
    below `below`); None if it can."""
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        return f"{name}: must be an integer >= {least}, got {value!r}"
    if value >= below:
        return f"{name}: must be an integer below {below} (2**{below.bit_length() - 1}), got " \
               f"{value}"
    return None


def slots_problem(grid_size: Any, max_actors: Any) -> str | None:
    """Why a scene of a `grid_size` grid cannot have `max_actors` slots: more than the grid
    has location bins. Each slot is one step of the sequential unroll over a full grid of
    activations, and a region holding more actors than its bins would put several road
    users in one bin, which the occupancy rasters cannot tell apart; None if it can (or
    either is not a positive integer, which `int_problem` reports)."""
    if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1
               for v in (grid_size, max_actors)):
        return None
    if max_actors > grid_size**2:
        return f"max_actors: must be at most {grid_size**2} (the grid's {grid_size} x " \
               f"{grid_size} location bins), got {max_actors}"
    return None


def config_problems(cfg) -> list[str]:
    """Every field value of `cfg` that cannot work, with the reason (empty if none)."""
    out = []
    named = [g for g in cfg.map_layers if isinstance(g, str)]
    if len(named) != len(cfg.map_layers):
        out.append(f"map_layers: must be group names (strings), got {cfg.map_layers!r}")
    unknown = sorted(set(named) - set(LAYER_GROUPS))
    if unknown:
        out.append(f"map_layers: unknown groups {unknown}; known: {list(ALL_LAYER_GROUPS)}")
    if not all(isinstance(n, str) and n for n in cfg.train_params):
        out.append(f"train_params: must be parameter names, got {cfg.train_params!r}")
    absent = [g for g in cfg.train_layers if g not in cfg.map_layers]
    if absent:
        out.append(f"train_layers: {absent} not in map_layers {list(cfg.map_layers)}")
    positive_ints = ("grid_size", "max_actors", "hidden", "backbone_layers", "gn_groups",
                     "num_mixtures", "hard_negatives", "bptt_window", "batch_size", "proposals")
    out += [p for name in positive_ints if (p := int_problem(name, getattr(cfg, name), 1))]
    if problem := int_problem("seed", cfg.seed, 0, SEED_LIMIT):
        out.append(problem)
    if problem := slots_problem(cfg.grid_size, cfg.max_actors):
        out.append(problem)
    if isinstance(cfg.hidden, int) and isinstance(cfg.gn_groups, int) and cfg.gn_groups >= 1 \
            and cfg.hidden % cfg.gn_groups:
        out.append(f"gn_groups: must divide hidden ({cfg.hidden}), got {cfg.gn_groups}")
    bins = cfg.orientation_bins
    if problem := int_problem("orientation_bins", bins, 0):
        out.append(problem)
    elif bins and "lanes" not in cfg.map_layers:
        out.append("orientation_bins: needs the 'lanes' map layers (the lane orientation), "
                   f"got map_layers {cfg.map_layers!r}")
    if cfg.attribute_map_input is True and not (cfg.map_layers and cfg.separate_attribute_mlps):
        out.append("attribute_map_input: needs map layers and separate_attribute_mlps, got "
                   f"map_layers {cfg.map_layers!r}, "
                   f"separate_attribute_mlps {cfg.separate_attribute_mlps!r}")
    if cfg.attribute_map_skip is True and cfg.attribute_map_input is not True:
        out.append("attribute_map_skip: needs attribute_map_input, got "
                   f"{cfg.attribute_map_input!r}")
    if cfg.heading_lane_frame is True and "nearest_lane" not in cfg.map_layers:
        out.append("heading_lane_frame: needs the 'nearest_lane' map layers, got map_layers "
                   f"{cfg.map_layers!r}")
    for name in ("m_per_px", "learning_rate", "pedestrian_size_m"):
        v = getattr(cfg, name)
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            out.append(f"{name}: must be a finite number > 0, got {v!r}")
    out += [p for name in ("warmup_steps", "decay_steps")
            if (p := int_problem(name, getattr(cfg, name), 0))]
    for name in ("grad_clip", "zero_speed"):
        v = getattr(cfg, name)
        if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
            out.append(f"{name}: must be a finite number >= 0, got {v!r}")
    if not (isinstance(cfg.ema_decay, int | float) and 0.0 <= cfg.ema_decay < 1.0):
        out.append(f"ema_decay: must be in [0, 1), got {cfg.ema_decay!r}")
    if not (isinstance(cfg.map_dropout, int | float) and 0.0 <= cfg.map_dropout <= 1.0):
        out.append(f"map_dropout: must be in [0, 1], got {cfg.map_dropout!r}")
    if len(cfg.ego_size_m) != 2 or not all(
        isinstance(v, int | float) and math.isfinite(v) and v > 0 for v in cfg.ego_size_m
    ):
        out.append(f"ego_size_m: must be two numbers > 0 (width, length), got {cfg.ego_size_m!r}")
    if not (isinstance(cfg.remat, bool) or cfg.remat == "auto"):
        out.append(f"remat: must be true, false or \"auto\", got {cfg.remat!r}")
    for name in ("rotate_augment", "coord_channels", "order_channel",
                 "attribute_map_input", "attribute_map_skip", "heading_lane_frame",
                 "separate_attribute_mlps"):
        if not isinstance(getattr(cfg, name), bool):
            out.append(f"{name}: must be true or false, got {getattr(cfg, name)!r}")
    return out


def parse_value(current: Any, value: Any, key: str = "value") -> Any:
    """A `--set` value (a string) as the type of the field's `current` value."""
    if not isinstance(value, str):
        return value
    if key == "remat" and value.lower() == "auto":
        return "auto"
    if isinstance(current, bool) or key == "remat":
        if value.lower() not in ("true", "false"):
            also = ' (or "auto")' if key == "remat" else ""
            raise ValueError(f"{key}: must be true or false{also}, got {value!r}")
        return value.lower() == "true"
    if isinstance(current, tuple) and value.lower() in ("", "none"):
        return ()
    try:
        if isinstance(current, int):
            return int(value)
        if isinstance(current, float):
            return float(value)
        if isinstance(current, tuple):
            items = [v for v in value.split(",") if v]
            return tuple(type(current[0])(v) if current else v for v in items)
    except ValueError as e:
        kind = f"a list of {type(current[0]).__name__}" if isinstance(current, tuple) else \
            type(current).__name__
        raise ValueError(f"{key}: expected {kind}, got {value!r}") from e
    return value
