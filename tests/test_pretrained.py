"""Pretrained models: the exported directory restores the same parameters, refuses damaged or
mismatched files with the file's name, and `--pretrained` samples what `--workdir` samples."""

from __future__ import annotations

import json
import os

import jax
import numpy as np
import pytest
from small import CFG

from scenegen_jax.config import get_config
from scenegen_jax.pretrained import (
    PARAMS_FILE,
    available,
    load_pretrained,
    save_pretrained,
)
from scenegen_jax.train.step import init_state

TINY = get_config("tiny")


def _assert_same_tree(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_roundtrip_is_bit_exact(tmp_path):
    params = init_state(TINY, seed=3).params
    manifest = save_pretrained(str(tmp_path / "m"), TINY, params, step=7, source="here")
    cfg, restored, got = load_pretrained(str(tmp_path / "m"))
    assert cfg == TINY and got == manifest and got["step"] == 7
    assert got["parameters"] == sum(np.size(x) for x in jax.tree.leaves(params))
    _assert_same_tree(params, restored)


def test_recommended_sampler_settings_roundtrip_and_are_checked(tmp_path):
    import argparse

    from scenegen_jax.cli.common import location_temperature

    d = tmp_path / "m"
    params = init_state(TINY).params
    save_pretrained(str(d), TINY, params, step=1, source="here",
                    sampler={"location_temperature": 0.7})
    sampler = load_pretrained(str(d))[2]["sampler"]
    assert sampler == {"location_temperature": 0.7}
    given, unset = (argparse.Namespace(location_temperature=t) for t in (0.5, None))
    assert location_temperature(given, sampler) == 0.5  # the command line wins
    assert location_temperature(unset, sampler) == 0.7  # then the model's
    assert location_temperature(unset, {}) == 1.0  # then the paper's
    manifest_path = d / "manifest.json"
    good = json.loads(manifest_path.read_text())
    for bad, field in (({"location_temperature": 0}, "sampler.location_temperature"),
                       ({"location_temperature": "0.7"}, "sampler.location_temperature"),
                       ({"proposals": 3}, "sampler.proposals"), ([0.7], "sampler")):
        manifest_path.write_text(json.dumps({**good, "sampler": bad}))
        with pytest.raises(ValueError, match=f"{manifest_path}: field {field}"):
            load_pretrained(str(d))
    # The other fields, checked before the parameters are read.
    without_step = {k: v for k, v in good.items() if k != "step"}
    for bad, message in ((without_step, "field step: expected an integer, got None"),
                         ({**good, "step": True}, "field step: expected an integer, got True"),
                         ({**good, "step": -1}, "field step: expected an integer >= 0"),
                         ({**good, "sha256": 5}, "field sha256: expected a string"),
                         ([], "expected a JSON object, got list")):
        manifest_path.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=f"^{manifest_path}: {message}"):
            load_pretrained(str(d))


def test_damaged_or_mismatched_files_name_the_file(tmp_path):
    d = tmp_path / "m"
    save_pretrained(str(d), TINY, init_state(TINY).params, step=1, source="here")
    path = d / PARAMS_FILE
    good = path.read_bytes()
    damaged = bytearray(good)
    damaged[len(damaged) // 2] ^= 0x40
    path.write_bytes(bytes(damaged))
    with pytest.raises(ValueError, match=f"{path}: sha256 differs"):
        load_pretrained(str(d))
    path.write_bytes(good)
    # A config whose model has other shapes than the saved parameters.
    (d / "config.json").write_text(TINY.replace(hidden=8, gn_groups=2).to_json())
    with pytest.raises(ValueError, match=f"{path}: parameter .* has shape"):
        load_pretrained(str(d))
    with pytest.raises(FileNotFoundError, match="no pretrained model of that name"):
        load_pretrained("no-such-model")


def test_the_shipped_model_is_installed():
    # The model the README and `make demo` use; the parametrized test below would skip, not
    # fail, if no model were found.
    assert "cpu-av2-womd" in available()


@pytest.mark.parametrize("name", available())
def test_shipped_models_load(name):
    cfg, params, manifest = load_pretrained(name)
    assert manifest["step"] > 0
    assert sum(np.size(x) for x in jax.tree.leaves(params)) == manifest["parameters"]
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(params))
    here = os.path.dirname(os.path.abspath(__file__))
    card = os.path.join(here, "..", "scenegen_jax", "pretrained", name, "MODEL_CARD.md")
    assert os.path.isfile(card), f"{name}: no model card"
    assert cfg.name


@pytest.mark.slow
def test_cli_pretrained_samples_as_the_workdir(tmp_path, tiny_train_cache, capsys):
    from scenegen_jax.cli import main
    from scenegen_jax.train.loop import train

    workdir, model = str(tmp_path / "wd"), str(tmp_path / "model")
    train(CFG, tiny_train_cache.path, workdir, steps=2, progress=False)  # the small test model
    main(["export-model", "--workdir", workdir, "--out", model])
    assert json.loads(capsys.readouterr().out)["step"] == 2
    common = ["--data", tiny_train_cache.path, "--num", "2", "--seed", "1", "--batch-size", "1"]
    main(["sample", "--workdir", workdir, "--out", str(tmp_path / "a"), *common])
    main(["sample", "--pretrained", model, "--out", str(tmp_path / "b"), *common])
    a = (tmp_path / "a" / "scenes.jsonl").read_text()
    assert a and a == (tmp_path / "b" / "scenes.jsonl").read_text()
