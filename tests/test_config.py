"""Config values are validated in one place: every bad `--set` value or damaged config.json
ends in one error naming the field (and the file), never a traceback or a silent change."""

from __future__ import annotations

import json
import os

import pytest

from scenegen_jax.config import PRESETS, Config, get_config


@pytest.mark.parametrize(
    "override, message",
    [
        ({"gn_groups": "5"}, "gn_groups: must divide hidden"),
        ({"bptt_window": "0"}, "bptt_window: must be an integer >= 1"),
        ({"warmup_steps": "-1"}, "warmup_steps: must be an integer >= 0"),
        ({"decay_steps": "-5"}, "decay_steps: must be an integer >= 0"),
        ({"batch_size": "0"}, "batch_size: must be an integer >= 1"),
        ({"max_actors": "0"}, "max_actors: must be an integer >= 1"),
        ({"rotate_augment": "ture"}, "rotate_augment: must be true or false"),
        ({"remat": "1"}, "remat: must be true or false"),
        ({"learning_rate": "fast"}, "learning_rate: expected float"),
        ({"learning_rate": "-1e-3"}, "learning_rate: must be a finite number > 0"),
        ({"grad_clip": "nan"}, "grad_clip: must be a finite number >= 0"),
        ({"map_dropout": "1.5"}, "map_dropout: must be in"),
        ({"ema_decay": "1"}, r"ema_decay: must be in \[0, 1\), got 1.0"),
        ({"ema_decay": "-0.5"}, r"ema_decay: must be in \[0, 1\)"),
        ({"map_layers": "lanes,roads"}, "map_layers: unknown groups"),
        ({"orientation_bins": "-2"}, "orientation_bins: must be an integer >= 0"),
        ({"orientation_bins": "8", "map_layers": "drivable"},
         "orientation_bins: needs the 'lanes' map layers"),
        ({"attribute_map_input": "true", "map_layers": "none"},
         "attribute_map_input: needs map layers"),
        ({"attribute_map_skip": "true"}, "attribute_map_skip: needs attribute_map_input"),
        ({"heading_lane_frame": "true"}, "heading_lane_frame: needs the 'nearest_lane' map"),
        ({"ego_size_m": "2"}, "ego_size_m: must be two numbers"),
        ({"colour": "red"}, "unknown config field 'colour'"),
    ],
)
def test_bad_overrides_name_the_field(override, message):
    with pytest.raises(ValueError, match=message):
        get_config("tiny", **override)


def test_booleans_parse_exactly():
    assert get_config("tiny", rotate_augment="false").rotate_augment is False
    assert get_config("tiny", remat="True").remat is True
    assert get_config("tiny", remat="auto").remat == "auto"
    assert get_config("paper", remat="false").remat is False
    with pytest.raises(ValueError, match=r'remat: must be true, false or "auto"'):
        get_config("tiny").replace(remat="sometimes")


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_roundtrip_through_json(name):
    cfg = PRESETS[name]
    assert Config.from_json(cfg.to_json()) == cfg


def test_damaged_config_json_names_the_file_and_field():
    text = get_config("tiny").to_json()
    with pytest.raises(ValueError, match="w/config.json: not valid JSON"):
        Config.from_json(text[: len(text) // 2], "w/config.json")
    d = json.loads(text)
    with pytest.raises(ValueError, match=r"w/config.json: unknown config field\(s\) \['bogus'\]"):
        Config.from_json(json.dumps({**d, "bogus": 1}), "w/config.json")
    with pytest.raises(ValueError, match="w/config.json: field hidden: expected int"):
        Config.from_json(json.dumps({**d, "hidden": "16"}), "w/config.json")
    with pytest.raises(ValueError, match="w/config.json: invalid config: gn_groups"):
        Config.from_json(json.dumps({**d, "gn_groups": 5}), "w/config.json")


def test_config_mismatch_names_the_fields(tmp_path):
    from scenegen_jax.train.loop import save_or_check_config

    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, get_config("tiny"))
    with pytest.raises(ValueError, match=r"learning_rate: 0.001 != 0.002.*seed: 0 != 3"):
        save_or_check_config(workdir, get_config("tiny", learning_rate="2e-3", seed="3"))
    save_or_check_config(workdir, get_config("tiny", remat="auto"))  # memory, not values


def test_loading_a_workdir_without_checkpoints_creates_nothing(tmp_path):
    from scenegen_jax.train.loop import load_trained, save_or_check_config

    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, get_config("tiny"))
    with pytest.raises(FileNotFoundError, match="no checkpoints"):
        load_trained(workdir)
    assert os.listdir(workdir) == ["config.json"]


def test_cli_rejects_zero_sizes_before_any_work(caplog, capsys):
    from scenegen_jax.cli import main

    with pytest.raises(SystemExit, match="2"):
        main(["score", "--workdir", "nowhere", "--data", "nowhere", "--out", "x.csv",
              "--batch-size", "0"])
    assert "argument --batch-size: '0' must be an integer >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="2"):
        main(["evaluate", "--workdir", "nowhere", "--data", "x", "--train-data", "y",
              "--num", "0", "--out", "r.json"])
    assert "argument --num: '0' must be an integer >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["train", "--config", "tiny", "--data", "nowhere", "--workdir", "nowhere",
              "--set", "gn_groups=5"])
    assert e.value.code == 2
    assert "gn_groups: must divide hidden" in caplog.text
