"""Warm starts: a model's parameters from another model's (a training workdir or a pretrained
model), extended where the config adds inputs (map channels, orientation sectors, coordinates,
the canonical order channel, the attribute MLPs' map weights), split where it has one MLP per
attribute, and started afresh where the heading frame changes."""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np
from flax.traverse_util import flatten_dict, unflatten_dict

from scenegen_jax.config import Config
from scenegen_jax.model.network import ATTRIBUTES, MAP_CHANNEL_AXIS
from scenegen_jax.pretrained import load_pretrained
from scenegen_jax.workdir import CHECKPOINTS, load_params

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
    if cfg.model.heading_lane_frame == source_cfg.model.heading_lane_frame:
        return ()
    if not cfg.model.separate_attribute_mlps:
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

