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
        ({"max_actors": "100000"}, r"max_actors: must be at most 1024 \(the grid's 32 x 32"),
        ({"max_actors": "65", "grid_size": "8"}, "max_actors: must be at most 64"),
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
    assert get_config("tiny", rotate_augment="false").train.rotate_augment is False
    assert get_config("tiny", remat="True").train.remat is True
    assert get_config("tiny", remat="auto").train.remat == "auto"
    assert get_config("paper", remat="false").train.remat is False
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
    model = d["model"]
    with pytest.raises(ValueError, match="w/config.json: field hidden: expected int"):
        Config.from_json(json.dumps({**d, "model": {**model, "hidden": "16"}}), "w/config.json")
    with pytest.raises(ValueError, match="w/config.json: invalid config: gn_groups"):
        Config.from_json(json.dumps({**d, "model": {**model, "gn_groups": 5}}), "w/config.json")
    with pytest.raises(ValueError, match=r"w/config.json: field\(s\) \['hidden'\] given twice"):
        Config.from_json(json.dumps({**d, "hidden": 16}), "w/config.json")
    with pytest.raises(ValueError, match="w/config.json: field train: expected an object"):
        Config.from_json(json.dumps({**d, "train": [1]}), "w/config.json")


def test_sub_configs_hold_each_concern():
    cfg = get_config("cpu", learning_rate="3e-4", proposals="20", hidden="32", gn_groups="32")
    assert cfg.grid is cfg.model.grid
    assert (cfg.grid.grid_size, cfg.grid.m_per_px, cfg.grid.region_m) == (64, 1.25, 80.0)
    assert (cfg.model.hidden, cfg.model.num_mixtures) == (32, 10)
    assert (cfg.train.learning_rate, cfg.sample.proposals) == (3e-4, 20)
    # A training setting leaves the model config, which the scorer and sampler compile
    # against, equal (and equally hashed).
    other = cfg.replace(learning_rate=1e-3, seed=5, batch_size=8)
    assert other.model == cfg.model and hash(other.model) == hash(cfg.model)
    assert other.train != cfg.train
    # Whole sub-configs replace as one.
    assert cfg.replace(model=PRESETS["tiny"].model).model == PRESETS["tiny"].model
    assert cfg.replace(train=PRESETS["tiny"].train).train == PRESETS["tiny"].train
    assert cfg.flat()["hidden"] == 32 and set(cfg.flat()) == set(PRESETS["tiny"].flat())


def test_one_level_config_json_of_older_workdirs_reads_as_the_same_config():
    # The form written before the sub-configs: every field at the top level (hand-written
    # here, field by field as that writer wrote them).
    old = {"name": "cpu", "grid_size": 64, "m_per_px": 1.25,
           "map_layers": ["lanes", "drivable", "crosswalks", "nearest_lane", "dataset"],
           "max_actors": 39, "hidden": 16, "backbone_layers": 5, "gn_groups": 16,
           "num_mixtures": 10, "hard_negatives": 4096, "bptt_window": 20, "batch_size": 4,
           "learning_rate": 0.003, "warmup_steps": 50, "decay_steps": 250, "grad_clip": 1.0,
           "ema_decay": 0.0, "proposals": 10, "zero_speed": 0.2, "pedestrian_size_m": 0.6,
           "ego_size_m": [1.95, 4.9], "rotate_augment": True, "map_dropout": 0.0,
           "remat": False, "train_layers": [], "train_params": ["box0_b", "box0_w"],
           "coord_channels": True, "orientation_bins": 0, "order_channel": True,
           "attribute_map_input": True, "attribute_map_skip": True,
           "heading_lane_frame": True, "separate_attribute_mlps": True, "seed": 70}
    cfg = Config.from_json(json.dumps(old), "old/config.json")
    want = get_config("cpu", map_layers="lanes,drivable,crosswalks,nearest_lane,dataset",
                      learning_rate="3e-3", warmup_steps="50", decay_steps="250",
                      train_params="box0_b,box0_w", coord_channels="true",
                      order_channel="true", attribute_map_input="true",
                      attribute_map_skip="true", heading_lane_frame="true", seed="70")
    assert cfg == want, cfg.differences(want)
    assert Config.from_json(cfg.to_json()) == cfg  # and it is written nested from now on
    assert set(json.loads(cfg.to_json())) == {"name", "model", "train", "sample"}
    # A config without the fields added later (older still) takes their defaults.
    later = ("separate_attribute_mlps", "attribute_map_input", "attribute_map_skip",
             "heading_lane_frame", "seed")
    older = {k: v for k, v in old.items() if k not in later}
    assert Config.from_json(json.dumps(older)).model.separate_attribute_mlps is False


def test_config_mismatch_names_the_fields(tmp_path):
    from scenegen_jax.train.loop import save_or_check_config

    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, get_config("tiny"))
    save_or_check_config(workdir, get_config("tiny", seed="3"))  # no checkpoint: not bound
    save_or_check_config(workdir, get_config("tiny"))
    os.makedirs(os.path.join(workdir, "checkpoints", "1"))  # a saved step binds the config
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
