"""Every input error of the CLI: one log line naming the file (or the field), exit code 2, no
traceback unless -v. Each case damages a real input before any model work starts."""

from __future__ import annotations

import collections
import logging
import os
import shutil
import subprocess
import sys

import pytest

from scenegen_jax import cli
from scenegen_jax.config import get_config
from scenegen_jax.data.cache_write import write_cache
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
    _truncate(os.path.join(c, "map_points.npy"))
    return ["render", "--cache", c, "--out", str(tmp_path / "r.png")], "map_points.npy"


def _output_under_a_file(tmp_path, cache, data_root):
    (tmp_path / "a_file").write_text("")
    return ["render", "--cache", cache, "--out", str(tmp_path / "a_file" / "r.png")], "a_file"


def _outputs_under_a_file(command):
    """`command` with its output file under a regular file: refused before any model work."""
    def case(tmp_path, cache, data_root):
        (tmp_path / "a_file").write_text("")
        out = str(tmp_path / "a_file" / ("out.npz" if command == "actors-out" else "out"))
        argv = {
            "score": ["score", "--pretrained", "cpu-av2-womd", "--data", cache, "--out", out],
            "actors-out": ["score", "--pretrained", "cpu-av2-womd", "--data", cache, "--out",
                           str(tmp_path / "s.csv"), "--actors-out", out],
            "evaluate": ["evaluate", "--pretrained", "cpu-av2-womd", "--data", cache,
                         "--train-data", cache, "--num", "1", "--out", out],
            "sample": ["sample", "--pretrained", "cpu-av2-womd", "--data", cache, "--num", "1",
                       "--out", out],
        }[command]
        flag = "--actors-out" if command == "actors-out" else "--out"
        return argv, f"{flag} {out}: cannot make the folder"
    case.__name__ = f"_{command}_under_a_file"
    return case


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


def _seed_beyond_32_bits(tmp_path, cache, data_root):
    return ["train", "--data", cache, "--workdir", str(tmp_path / "w"), "--steps", "1", "--set",
            "seed=99999999999999999999"], "seed: must be an integer below 4294967296"


def _more_slots_than_bins(tmp_path, cache, data_root):
    return ["train", "--data", cache, "--workdir", str(tmp_path / "w"), "--steps", "1", "--set",
            "max_actors=100000"], "max_actors: must be at most 1024 (the grid's 32 x 32"


def _temperature_below_the_least(command):
    """`--location-temperature 1e-300` (0 in float32: every scene empty) is refused."""
    def case(tmp_path, cache, data_root):
        argv = {
            "sample": ["sample", "--workdir", str(tmp_path / "w"), "--data", cache, "--num", "1",
                       "--out", str(tmp_path / "s")],
            "evaluate": ["evaluate", "--workdir", str(tmp_path / "w"), "--data", cache,
                         "--train-data", cache, "--out", str(tmp_path / "e.json")],
        }[command]
        return ([*argv, "--location-temperature", "1e-300"],
                "--location-temperature 1e-300: must be at least 0.001")
    case.__name__ = f"_{command}_temperature_below_the_least"
    return case


def _train_into_a_cache(tmp_path, cache, data_root):
    c = _copy(cache, tmp_path)
    return (["train", "--data", cache, "--workdir", c, "--steps", "1"],
            f"--workdir {c}: holds meta.json, so it is a cache, not a training workdir")


def _train_into_an_exported_model(tmp_path, cache, data_root):
    from scenegen_jax.pretrained import resolve

    model = str(tmp_path / "model")
    shutil.copytree(resolve("cpu-av2-womd"), model)
    return (["train", "--data", cache, "--workdir", model, "--steps", "1"],
            "holds manifest.json, so it is an exported model, not a training workdir")


def _score_out_name_too_long(tmp_path, cache, data_root):
    out = str(tmp_path / ("x" * 300 + ".csv"))
    return (["score", "--pretrained", "cpu-av2-womd", "--data", cache, "--out", out],
            "the file name is 304 bytes")


CASES = [
    _seed_beyond_32_bits,
    _more_slots_than_bins,
    *(_temperature_below_the_least(c) for c in ("sample", "evaluate")),
    _train_into_a_cache,
    _train_into_an_exported_model,
    _score_out_name_too_long,
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
    *(_outputs_under_a_file(c) for c in ("score", "actors-out", "evaluate", "sample")),
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
        (["score", "--pretrained", "", "--data", "c", "--out", "o"],
         "argument --pretrained: '': an empty path"),
        (["train", "--data", "c", "--workdir", ""], "argument --workdir: '': an empty path"),
    ],
)
def test_flag_values_are_checked_before_any_work(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2 and message in capsys.readouterr().err


def test_an_unknown_compile_cache_switch_is_named(monkeypatch, tmp_path, caplog):
    """SCENEGEN_COMPILE_CACHE takes on/off words; another value (`none`) is refused, not
    read as on."""
    monkeypatch.setenv("SCENEGEN_COMPILE_CACHE", "none")
    code, errors = _run(["score", "--pretrained", "cpu-av2-womd", "--data", str(tmp_path),
                         "--out", str(tmp_path / "s.csv")], caplog)
    assert code == 2 and "SCENEGEN_COMPILE_CACHE=none: use off" in errors[0].getMessage()


def _command(env: dict[str, str], *argv: str) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "SCENEGEN_"))}
    return subprocess.run([sys.executable, "-m", "scenegen_jax.cli", *argv],
                          env={**clean, **env}, capture_output=True, text=True, timeout=300)


def test_a_backend_this_machine_lacks_is_one_line_and_exit_2():
    out = _command({"JAX_PLATFORMS": "tpu"}, "models")
    assert out.returncode == 2, out.stderr
    assert "JAX_PLATFORMS=tpu: JAX cannot start that backend here" in out.stderr
    assert "Traceback" not in out.stderr


def test_jaxs_global_switches_in_the_environment_change_nothing(cache_dir, tmp_path):
    """JAX_ENABLE_X64=1 (float64 by default) and JAX_NUMPY_RANK_PROMOTION=raise broke every
    model command; the command sets them as the package needs: the same scores."""
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.train.loop import save_or_check_config
    from scenegen_jax.train.step import init_state

    cfg = get_config("tiny")
    workdir = str(tmp_path / "wd")
    save_or_check_config(workdir, cfg)
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1)
    ckpt.save(init_state(cfg), force=True)
    ckpt.close()
    scores = {}
    for name, env in (("plain", {}),
                      ("switched", {"JAX_ENABLE_X64": "1", "JAX_NUMPY_RANK_PROMOTION": "raise"})):
        out = tmp_path / f"{name}.csv"
        run = _command({**env, "SCENEGEN_COMPILE_CACHE": "off"}, "score", "--workdir", workdir,
                       "--data", cache_dir, "--out", str(out))
        assert run.returncode == 0, run.stderr
        scores[name] = out.read_text()
    assert scores["switched"] == scores["plain"] and scores["plain"].count("\n") > 2


@pytest.fixture(scope="module")
def tiny_workdir(tmp_path_factory) -> str:
    """A workdir of the tiny config with one checkpoint (untrained parameters)."""
    from scenegen_jax.checkpoint import Checkpointer
    from scenegen_jax.train.loop import save_or_check_config
    from scenegen_jax.train.step import init_state

    workdir = str(tmp_path_factory.mktemp("cli_errors_workdir") / "wd")
    save_or_check_config(workdir, get_config("tiny"))
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1)
    ckpt.save(init_state(get_config("tiny")), force=True)
    ckpt.close()
    return workdir


def test_a_second_train_on_a_workdir_is_refused_naming_the_holder(cache_dir, tmp_path,
                                                                   caplog):
    """While a run holds a workdir, another `train` on it is one line naming the holder's pid
    and host, and writes nothing there."""
    import socket

    from scenegen_jax.locks import exclusive
    from scenegen_jax.workdir import LOCK_FILE

    workdir = tmp_path / "w"
    with exclusive(str(workdir / LOCK_FILE), "training into w"):
        code, errors = _run(["train", "--data", cache_dir, "--workdir", str(workdir), "--steps",
                             "1"], caplog)
        assert sorted(os.listdir(workdir)) == [LOCK_FILE]
    assert code == 2 and len(errors) == 1
    assert (f"locked by pid {os.getpid()} on host {socket.gethostname()} (training into w, "
            "since ") in errors[0].getMessage()
    assert not errors[0].exc_info


def test_export_refuses_a_folder_that_is_not_an_exported_model(tiny_workdir, tmp_path, caplog,
                                                                capsys):
    foreign = tmp_path / "p"
    foreign.mkdir()
    (foreign / "config.json").write_text('{"someone": "else\'s"}')
    code, errors = _run(["export-model", "--workdir", tiny_workdir, "--out", str(foreign)],
                        caplog)
    assert code == 2 and len(errors) == 1
    assert (f"--out {foreign}: holds config.json, so it is something else, not an exported "
            "model") in errors[0].getMessage()
    assert sorted(os.listdir(foreign)) == ["config.json"]
    assert (foreign / "config.json").read_text() == '{"someone": "else\'s"}'
    code, errors = _run(["export-model", "--workdir", tiny_workdir, "--out", tiny_workdir],
                        caplog)
    assert code == 2 and "so it is a training workdir" in errors[0].getMessage()
    # A new folder, then the exported model it holds, are written.
    model = str(tmp_path / "model")
    for _ in range(2):
        cli.main(["export-model", "--workdir", tiny_workdir, "--out", model])
    assert sorted(os.listdir(model)) == ["config.json", "manifest.json", "params.msgpack"]


def test_render_prints_the_file_it_wrote(cache_dir, tmp_path, capsys):
    out = tmp_path / "o" / "x"
    cli.main(["render", "--cache", cache_dir, "--out", str(out)])
    printed = capsys.readouterr().out.strip().splitlines()[-1]
    assert printed == f"{out}.png" and os.path.isfile(printed) and not out.exists()


def test_render_turns_a_huge_angle_as_the_same_angle_modulo_360(cache_dir, tmp_path):
    import matplotlib.image

    def pixels(rotate: str):
        out = tmp_path / f"r{rotate}.png"
        cli.main(["render", "--cache", cache_dir, "--out", str(out), "--rotate", rotate])
        return matplotlib.image.imread(out)

    huge, reduced, unturned = pixels("1e308"), pixels("-64"), pixels("0")  # 1e308 = -64 (360)
    assert (huge == reduced).all() and not (huge == unturned).all()
