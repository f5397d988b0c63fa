"""Every input error of the CLI: one log line naming the file (or the field), exit code 2, no
traceback unless -v. Each case damages a real input before any model work starts."""

from __future__ import annotations

import collections
import logging
import os
import shutil

import pytest

from scenegen_jax import cli
from scenegen_jax.config import get_config
from scenegen_jax.data.cache import write_cache
from scenegen_jax.data.sources import read_frames, source_spec


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory, data_root) -> str:
    """A tiny-config cache of a few real val frames."""
    out = str(tmp_path_factory.mktemp("cli_errors_cache"))
    drops = collections.Counter()
    frames = read_frames(source_spec("av2", data_root, "val", 40), drops)
    write_cache(frames, out, get_config("tiny"), drops)
    return out


def _copy(src: str, tmp_path) -> str:
    dst = str(tmp_path / "cache")
    shutil.copytree(src, dst)
    return dst


def _truncate(path: str) -> None:
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)


def _damaged_log_root(tmp_path, cache, data_root):
    root = tmp_path / "av2"
    (root / "train" / "log_with_garbage").mkdir(parents=True)
    (root / "train" / "log_with_garbage" / "annotations.feather").write_bytes(b"not arrow")
    argv = [
        "prepare",
        "--root",
        str(root),
        "--split",
        "train",
        "--out",
        str(tmp_path / "o"),
        "--strict",
        "--workers",
        "1",
    ]
    return argv, "log_with_garbage"


def _truncated_actors(tmp_path, cache, data_root):
    c = _copy(cache, tmp_path)
    _truncate(os.path.join(c, "actors.npz"))
    return ["train", "--data", c, "--workdir", str(tmp_path / "w"), "--steps", "1"], "actors.npz"


def _truncated_maps(tmp_path, cache, data_root):
    c = _copy(cache, tmp_path)
    _truncate(os.path.join(c, "maps.npy"))
    return ["render", "--cache", c, "--out", str(tmp_path / "r.png")], "maps.npy"


def _output_under_a_file(tmp_path, cache, data_root):
    (tmp_path / "a_file").write_text("")
    return ["render", "--cache", cache, "--out", str(tmp_path / "a_file" / "r.png")], "a_file"


def _bad_set_value(tmp_path, cache, data_root):
    argv = [
        "train",
        "--data",
        cache,
        "--workdir",
        str(tmp_path / "w"),
        "--steps",
        "1",
        "--set",
        "gn_groups=5",
    ]
    return argv, "gn_groups"


def _missing_cache(tmp_path, cache, data_root):
    missing = str(tmp_path / "no_such_cache")
    return ["render", "--cache", missing, "--out", str(tmp_path / "r.png")], "no_such_cache"


def _workdir_without_checkpoints(tmp_path, cache, data_root):
    w = tmp_path / "w"
    w.mkdir()
    (w / "config.json").write_text(get_config("tiny").to_json())
    argv = ["score", "--workdir", str(w), "--data", cache, "--out", str(tmp_path / "s.csv")]
    return argv, "checkpoints"


def _truncated_config(tmp_path, cache, data_root):
    w = tmp_path / "w"
    w.mkdir()
    (w / "config.json").write_text(get_config("tiny").to_json()[:40])
    argv = ["score", "--workdir", str(w), "--data", cache, "--out", str(tmp_path / "s.csv")]
    return argv, "config.json"


def _missing_pretrained(tmp_path, cache, data_root):
    argv = [
        "score",
        "--pretrained",
        str(tmp_path / "no_model"),
        "--data",
        cache,
        "--out",
        str(tmp_path / "s.csv"),
    ]
    return argv, "no_model"


def _set_without_value(tmp_path, cache, data_root):
    return ["prepare", "--root", data_root, "--out", str(tmp_path / "o"), "--set",
            "batch_size"], "--set 'batch_size'"


def _set_of_the_preset_name(tmp_path, cache, data_root):
    return ["prepare", "--root", data_root, "--out", str(tmp_path / "o"), "--set",
            "name=cpu"], "--config"


def _bad_list_value(tmp_path, cache, data_root):
    return ["prepare", "--root", data_root, "--out", str(tmp_path / "o"), "--set",
            "ego_size_m=1,abc"], "ego_size_m: expected a list of float, got '1,abc'"


def _score_out_is_a_directory(tmp_path, cache, data_root):
    argv = ["score", "--pretrained", "cpu-av2-womd", "--data", cache, "--out", str(tmp_path)]
    return argv, f"--out {tmp_path}: a directory"


def _malformed_cap(tmp_path, cache, data_root):
    argv = ["sample", "--pretrained", "cpu-av2-womd", "--data", cache, "--num", "1", "--out",
            str(tmp_path / "s"), "--cap", "vehicle"]
    return argv, "--cap 'vehicle'"


def _top_k_without_render(tmp_path, cache, data_root):
    argv = ["score", "--pretrained", "cpu-av2-womd", "--data", cache, "--out",
            str(tmp_path / "s.csv"), "--top-k", "2"]
    return argv, "--top-k K needs --render DIR"


def _step_of_a_pretrained_model(tmp_path, cache, data_root):
    argv = ["score", "--pretrained", "cpu-av2-womd", "--step", "3", "--data", cache, "--out",
            str(tmp_path / "s.csv")]
    return argv, "--step selects a checkpoint of --workdir"


def _the_same_cache_twice(tmp_path, cache, data_root):
    argv = ["train", "--data", cache, os.path.join(cache, "."), "--workdir", str(tmp_path / "w"),
            "--steps", "1"]
    return argv, "listed twice"


CASES = [
    _malformed_cap,
    _top_k_without_render,
    _step_of_a_pretrained_model,
    _the_same_cache_twice,
    _set_without_value,
    _set_of_the_preset_name,
    _bad_list_value,
    _score_out_is_a_directory,
    _damaged_log_root,
    _truncated_actors,
    _truncated_maps,
    _output_under_a_file,
    _bad_set_value,
    _missing_cache,
    _workdir_without_checkpoints,
    _truncated_config,
    _missing_pretrained,
]


def _run(argv, caplog):
    caplog.clear()
    with caplog.at_level(logging.ERROR, logger="scenegen"), pytest.raises(SystemExit) as e:
        cli.main(argv)
    errors = [r for r in caplog.records if r.name == "scenegen" and r.levelno >= logging.ERROR]
    return e.value.code, errors


@pytest.mark.parametrize("case", CASES, ids=lambda f: f.__name__.strip("_"))
def test_input_error_is_one_line_naming_the_file_and_exit_2(
    case, cache_dir, data_root, tmp_path, caplog
):
    argv, named = case(tmp_path, cache_dir, data_root)
    code, errors = _run(argv, caplog)
    assert code == 2
    assert len(errors) == 1, [r.getMessage() for r in errors]
    message = errors[0].getMessage()
    assert named in message and "\n" not in message, message
    assert not errors[0].exc_info  # no traceback without -v


def test_verbose_adds_the_traceback(cache_dir, data_root, tmp_path, caplog):
    argv, named = _truncated_actors(tmp_path, cache_dir, data_root)
    code, errors = _run(["-v", *argv], caplog)
    assert code == 2 and len(errors) == 1
    assert named in errors[0].getMessage() and errors[0].exc_info is not None


TRAIN = ["train", "--data", "c", "--workdir", "w"]
COMPARE = ["compare", "--a", "a", "--b", "b"]
SAMPLE = ["sample", "--workdir", "w", "--data", "c", "--num", "1", "--out", "o"]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([*TRAIN, "--log-every", "0"], "argument --log-every: '0' must be an integer >= 1"),
        ([*TRAIN, "--keep", "0"], "argument --keep: '0' must be an integer >= 1"),
        ([*TRAIN, "--steps", "-5"], "argument --steps: '-5' must be an integer >= 0"),
        ([*TRAIN, "--minutes", "nan"], "argument --minutes: 'nan' must be a finite number"),
        ([*COMPARE, "--block", "0"], "argument --block: '0' must be an integer >= 1"),
        ([*COMPARE, "--seed", "x"], "argument --seed: 'x' is not an integer"),
        ([*SAMPLE, "--seed", "-1"], "argument --seed: '-1' must be an integer >= 0"),
        ([*SAMPLE, "--seed", str(2**32)], f"argument --seed: '{2**32}' must be an integer below"),
        ([*SAMPLE, "--proposals", "1001"], "argument --proposals: '1001' must be an integer below"),
        ([*SAMPLE, "--batch-size", "0"], "argument --batch-size: '0' must be an integer >= 1"),
        (["render", "--cache", "c", "--rotate", "inf"],
         "argument --rotate: 'inf' must be a finite number"),
    ],
)
def test_flag_values_are_checked_before_any_work(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2 and message in capsys.readouterr().err
