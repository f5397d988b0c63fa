"""Trained models shipped with the package, and the file format they are shipped in.

A pretrained model is a directory of three files:

  config.json     the `Config` it was trained with (`Config.to_json`)
  params.msgpack  its parameters, serialised by `flax.serialization` (msgpack: plain arrays,
                  loading runs no code from the file)
  manifest.json   {"sha256": of params.msgpack, "parameters": count, "step": training step,
                   "source": the workdir it was exported from, and optionally "sampler":
                   the `SamplerOptions` fields its figures were measured with, which
                   `scenegen sample` and `evaluate` use unless told otherwise, e.g.
                   {"location_temperature": 0.7}}

(`save_pretrained`, `scenegen export-model`); a model shipped with the package also has a
human-readable `MODEL_CARD.md` beside them. Beside it may ship its companions
(`COMPANIONS`), each in its own folder with the same three files (`save_companion`; its
config.json the companion's config, the config preset whose grid it reads and its held-out
figures): `forecaster/`, the motion forecaster whose features give `evaluate`'s Features MMD,
and `layoutvae/`, the LayoutVAE baseline. `load_pretrained(name)` finds `name` among
the directories of this package (`available()`), or takes a path to such a directory,
verifies the checksum and every array's shape against the config's model, and returns
(config, parameters, manifest): no training state, no optimizer.
"""

from __future__ import annotations

import hashlib
import json
import os

import jax
import numpy as np
from flax import serialization
from flax.traverse_util import flatten_dict

from scenegen_jax.config import Config, get_config
from scenegen_jax.jsonfile import read_json
from scenegen_jax.model.forecaster import ForecasterConfig, init_forecaster
from scenegen_jax.model.layout_vae import LayoutVAEConfig, init_layout_vae
from scenegen_jax.model.network import init_params
from scenegen_jax.sampling.rollout import SamplerOptions

PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))
CONFIG_FILE = "config.json"
PARAMS_FILE = "params.msgpack"
MANIFEST_FILE = "manifest.json"
# Models shipped beside a SceneGen model, by folder: (config class, parameter initialiser).
COMPANIONS = {
    "forecaster": (ForecasterConfig, init_forecaster),
    "layoutvae": (LayoutVAEConfig, init_layout_vae),
}


def available() -> list[str]:
    """Names of the pretrained models installed with the package."""
    return sorted(
        d for d in os.listdir(PACKAGE_DIR)
        if os.path.isfile(os.path.join(PACKAGE_DIR, d, MANIFEST_FILE))
    )


def resolve(name_or_dir: str) -> str:
    """The directory of a shipped model name, or `name_or_dir` itself if it is one.

    Raises:
      FileNotFoundError naming the installed models when neither exists.
    """
    if os.path.isfile(os.path.join(name_or_dir, MANIFEST_FILE)):
        return name_or_dir
    path = os.path.join(PACKAGE_DIR, name_or_dir)
    if os.sep not in name_or_dir and os.path.isfile(os.path.join(path, MANIFEST_FILE)):
        return path
    raise FileNotFoundError(
        f"{name_or_dir}: no pretrained model of that name or directory with {MANIFEST_FILE}; "
        f"installed: {available() or 'none'}"
    )


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# The manifest's "sampler" fields (`SamplerOptions` fields a model may recommend).
SAMPLER_FIELDS = ("location_temperature",)


def check_sampler(sampler, where: str) -> dict:
    """`sampler` if it is a manifest's valid "sampler" entry, else a ValueError naming
    `where` (the file) and the field."""
    if not isinstance(sampler, dict):
        raise ValueError(f"{where}: field sampler must be an object, got {sampler!r}")
    for k, v in sampler.items():
        if k not in SAMPLER_FIELDS:
            raise ValueError(f"{where}: field sampler.{k} is not one of {SAMPLER_FIELDS}")
        try:
            SamplerOptions(**{k: v})
        except ValueError as e:
            raise ValueError(f"{where}: field sampler.{k}: {e}") from None
    return sampler


def check_manifest(manifest, where: str) -> dict:
    """`manifest` if it is a valid manifest (the fields `save_pretrained` writes), else a
    ValueError naming `where` (the file) and the field."""
    if not isinstance(manifest, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(manifest).__name__}")
    kinds = {"sha256": (str, "a string"), "parameters": (int, "an integer"),
             "step": (int, "an integer"), "source": (str, "a string")}
    for field, (kind, name) in kinds.items():
        value = manifest.get(field)
        if isinstance(value, bool) or not isinstance(value, kind):
            raise ValueError(f"{where}: field {field}: expected {name}, got {value!r}")
    if manifest["step"] < 0:
        raise ValueError(f"{where}: field step: expected an integer >= 0, got {manifest['step']}")
    check_sampler(manifest.get("sampler", {}), where)
    return manifest


def save_pretrained(directory: str, cfg: Config, params, step: int, source: str,
                    sampler: dict | None = None) -> dict:
    """Writes `params` of a model of config `cfg` as a pretrained model directory, with the
    sampler settings it recommends (`sampler`, optional); returns the manifest. Overwrites
    the three files of an existing one."""
    extra = {"sampler": check_sampler(dict(sampler), "sampler")} if sampler else {}
    return _write_model(directory, cfg.to_json(), params, step, source, extra)


def _write_model(directory: str, config_text: str, params, step: int, source: str,
                 extra: dict) -> dict:
    """Writes config.json, params.msgpack and manifest.json (with `extra` fields)."""
    params = jax.device_get(params)
    data = serialization.to_bytes(params)
    manifest = {
        "sha256": _sha256(data),
        "parameters": int(sum(np.size(x) for x in jax.tree.leaves(params))),
        "step": int(step),
        "source": source,
        **extra,
    }
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, CONFIG_FILE), "w") as f:
        f.write(config_text + "\n")
    with open(os.path.join(directory, PARAMS_FILE), "wb") as f:
        f.write(data)
    with open(os.path.join(directory, MANIFEST_FILE), "w") as f:
        json.dump(manifest, f, indent=1)
        f.write("\n")
    return manifest


def save_companion(model_dir: str, kind: str, cfg, preset: str, params, step: int,
                   source: str, figures: dict) -> dict:
    """Writes a trained companion (`COMPANIONS`) into `model_dir`/`kind`/ (config: `cfg`, the
    config preset whose grid it reads, its held-out `figures`); returns the manifest."""
    config = {"config": preset, **cfg.to_dict(), "figures": figures}
    return _write_model(os.path.join(model_dir, kind), json.dumps(config, indent=1), params,
                        step, source, {})


def load_companion(name_or_dir: str, kind: str):
    """(config, parameters, config.json's fields) of the companion `kind` shipped with a
    model (a name or a pretrained directory), or None when the model has none.

    Raises ValueError naming the file as `load_pretrained` does.
    """
    config_class, init = COMPANIONS[kind]
    directory = os.path.join(resolve(name_or_dir), kind)
    if not os.path.isfile(os.path.join(directory, MANIFEST_FILE)):
        return None
    config_path = os.path.join(directory, CONFIG_FILE)
    fields = read_json(config_path)
    try:
        cfg = config_class.from_dict(fields, get_config(fields["config"]).grid)
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{config_path}: not a {kind} config ({e!r})") from e
    template = jax.eval_shape(lambda: init(cfg))
    params, _ = _read_params(directory, template)
    return cfg, params, fields


def load_pretrained(name_or_dir: str) -> tuple[Config, dict, dict]:
    """(config, parameters, manifest) of a shipped model name or a pretrained directory.

    Raises:
      FileNotFoundError: no such model (the message lists the installed ones).
      ValueError naming the file: a checksum mismatch (damaged or edited parameters), or a
        parameter missing or of the wrong shape for the config's model.
    """
    directory = resolve(name_or_dir)
    config_path = os.path.join(directory, CONFIG_FILE)
    with open(config_path, "rb") as f:
        cfg = Config.from_json(f.read(), config_path)
    template = jax.eval_shape(lambda: init_params(cfg.model, jax.random.key(0)))
    params, manifest = _read_params(directory, template)
    return cfg, params, manifest


def _read_params(directory: str, template) -> tuple[dict, dict]:
    """(parameters, manifest) of a model directory: the checksum and every array's shape
    checked against `template` (abstract arrays)."""
    paths = {k: os.path.join(directory, k) for k in (PARAMS_FILE, MANIFEST_FILE)}
    manifest = check_manifest(read_json(paths[MANIFEST_FILE]), paths[MANIFEST_FILE])
    with open(paths[PARAMS_FILE], "rb") as f:
        data = f.read()
    if _sha256(data) != manifest.get("sha256"):
        raise ValueError(
            f"{paths[PARAMS_FILE]}: sha256 differs from {MANIFEST_FILE}'s (damaged or edited)"
        )
    try:
        raw = serialization.msgpack_restore(data)
    except Exception as e:  # msgpack raises several types for malformed bytes
        raise ValueError(f"{paths[PARAMS_FILE]}: not a msgpack parameter file ({e})") from e
    want = flatten_dict(template, sep="/")
    got = flatten_dict(raw, sep="/")
    for path, spec in want.items():
        if path not in got:
            raise ValueError(f"{paths[PARAMS_FILE]}: parameter {path} is missing")
        if np.shape(got[path]) != spec.shape:
            raise ValueError(
                f"{paths[PARAMS_FILE]}: parameter {path} has shape {np.shape(got[path])}, "
                f"the config's model needs {spec.shape}"
            )
    extra = sorted(set(got) - set(want))
    if extra:
        raise ValueError(f"{paths[PARAMS_FILE]}: parameters the model does not have: {extra}")
    params = serialization.from_state_dict(template, raw)
    params = jax.tree.map(lambda x, s: np.asarray(x, s.dtype), params, template)
    return params, manifest
