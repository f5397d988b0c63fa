"""What several subcommands share: `--set FIELD=VALUE` overrides, the model of
`--pretrained NAME|DIR` or `--workdir` (`--step`), output files checked before the work,
and multi-process runs (`--distributed`) with the merge of the
processes' parts of an output."""

from __future__ import annotations

import argparse
import os


def overrides(pairs: list[str]) -> dict[str, str]:
    """{field: value} of `--set FIELD=VALUE ...` (values still strings)."""
    out = {}
    for pair in pairs or []:
        if "=" not in pair:
            raise ValueError(f"--set {pair!r}: must look like FIELD=VALUE")
        k, v = pair.split("=", 1)
        if k == "name":
            raise ValueError(f"--set {pair!r}: `name` labels the preset (train and prepare "
                             "choose it with --config); it is not a setting")
        out[k] = v
    return out


def check_output(flag: str, path: str, folder: bool = False) -> None:
    """Fails now, not after the work, where the output `path` (a file, or with `folder` a
    directory) cannot be written: a directory where a file goes, a file where a folder goes,
    or a folder this process may not write into (read-only, no permission). Makes the
    folders it needs."""
    if not folder and os.path.isdir(path):
        raise ValueError(f"{flag} {path}: a directory; give a file path")
    where = os.path.abspath(path) if folder else os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(where, exist_ok=True)
    except OSError as e:
        raise ValueError(f"{flag} {path}: cannot make the folder {where} ({e.strerror})") from e
    if not os.access(where, os.W_OK):
        raise ValueError(f"{flag} {path}: the folder {where} is not writable")
    if not folder:
        check_name_length(flag, path, where)


def check_name_length(flag: str, path: str, where: str) -> None:
    """Fails where the file name of `path` is longer than the folder `where` allows
    (NAME_MAX, 255 bytes on most file systems), counting the temporary name
    `files.written_whole` writes first (".<pid>.tmp" added)."""
    try:
        limit = os.pathconf(where, "PC_NAME_MAX")
    except (OSError, ValueError):  # a file system that does not say: the write decides
        return
    name = len(os.path.basename(path).encode())
    extra = len(f".{os.getpid()}.tmp")
    if name + extra > limit:
        raise ValueError(f"{flag} {path[:60]}...: the file name is {name} bytes; the folder "
                         f"{where} allows {limit - extra} (its file system's {limit}, less "
                         f"{extra} for the temporary name written first)")


def load_model(args):
    """(config, parameters, training step, recommended sampler settings) of `--pretrained
    NAME` or `--workdir` (`--step`); the settings are the pretrained manifest's "sampler"
    entry ({} for a workdir)."""
    import jax

    sampler = {}
    if args.pretrained is not None:
        if args.step is not None:
            raise ValueError("--step selects a checkpoint of --workdir; a pretrained model has one")
        from scenegen_jax.pretrained import load_pretrained

        cfg, params, manifest = load_pretrained(args.pretrained)
        step, sampler = manifest["step"], manifest.get("sampler", {})
    else:
        from scenegen_jax.workdir import load_params

        cfg, params, step = load_params(args.workdir, args.step)
    # Uncommitted copies: restored arrays are committed to a device, and jit compiles a
    # separate executable for committed inputs.
    return cfg, jax.device_put(jax.device_get(params)), step, sampler


def location_temperature(args, sampler: dict) -> float:
    """`--location-temperature`, else the model's recommended one, else 1 (the paper's)."""
    if args.location_temperature is not None:
        return args.location_temperature
    return float(sampler.get("location_temperature", 1.0))


def add_model_args(sp) -> None:
    """`--workdir DIR [--step N]` or `--pretrained NAME`: the model a command uses."""
    which = sp.add_mutually_exclusive_group(required=True)
    which.add_argument("--workdir", type=path_arg,
                       help="training workdir (config + checkpoints)")
    which.add_argument(
        "--pretrained", metavar="NAME", type=path_arg,
        help="a model shipped with the package (`scenegen models` lists them) or a directory "
        "written by `scenegen export-model`",
    )
    sp.add_argument("--step", type=int, help="checkpoint step of --workdir (default: the latest)")


def path_arg(text: str) -> str:
    """argparse type: a file or folder path (or a model name), not empty."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"{text!r}: an empty path; give a file or folder")
    return text


def finite_float(text: str) -> float:
    """argparse type: a finite number."""
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0")
    return value


def integer_in(least: int, below: int | None = None):
    """argparse type: an integer >= `least` (and < `below`)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"{text!r} must be an integer >= {least}")
        if below is not None and value >= below:
            raise argparse.ArgumentTypeError(f"{text!r} must be an integer below {below}")
        return value

    parse.__name__ = f"integer >= {least}"  # argparse names the type in some errors
    return parse


positive_int = integer_in(1)  # argparse types
nonnegative_int = integer_in(0)
# A seed: JAX keys and numpy's generators take 32 bits; larger ones would wrap onto these.
seed_int = integer_in(0, 2**32)  # as `sampling.batch.seed_key` checks in the library


def add_temperature_arg(sp) -> None:
    """`--location-temperature T` of the commands that sample."""
    sp.add_argument(
        "--location-temperature", type=positive_float, metavar="T",
        help="divide the location logits by T before sampling a bin (beyond the paper, whose "
        "sampler is T = 1; below 1 favours the model's likelier bins). Default: the one a "
        "pretrained model recommends (its manifest's sampler entry), else 1",
    )


def add_distributed_args(sp, what: str) -> None:
    """`--distributed [--coordinator HOST:PORT --num-processes N --process-id I]`."""
    sp.add_argument(
        "--distributed",
        action="store_true",
        help=f"multi-process {what} (jax.distributed): run one process per host with the "
        "same arguments; under SLURM, Open MPI or on Cloud TPU JAX finds the others itself",
    )
    sp.add_argument("--coordinator", metavar="HOST:PORT",
                    help="with --distributed: process 0's address (default: "
                    "JAX_COORDINATOR_ADDRESS or the cluster's)")
    sp.add_argument("--num-processes", type=int, metavar="N", help="with --distributed")
    sp.add_argument("--process-id", type=int, metavar="I", help="with --distributed: 0..N-1")


def start_distributed(args) -> None:
    """Joins the multi-process job of `--distributed` (nothing without it)."""
    from scenegen_jax import backend

    if args.distributed:
        backend.start_distributed(args.coordinator, args.num_processes, args.process_id)
    elif args.coordinator or args.num_processes is not None or args.process_id is not None:
        raise ValueError("--coordinator, --num-processes and --process-id need --distributed")


def part_path(path: str, index: int, count: int) -> str:
    """The file of process `index`'s part of `path` when `count` processes write it."""
    return f"{path}.part-{index:05d}-of-{count:05d}"


def merge_parts(path: str, arrays: dict):
    """With several processes: each writes its part of per-scene `arrays` (concatenated
    along axis 0 in process order) to PATH.part-I-of-N.npz; process 0 reads them all back,
    removes them and returns the whole; the others return None. With one process: `arrays`.
    """
    import jax
    import numpy as np

    from scenegen_jax.backend import sync_processes

    count, index = jax.process_count(), jax.process_index()
    if count == 1:
        return arrays
    part = lambda i: part_path(path, i, count) + ".npz"  # noqa: E731
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez(part(index), **arrays)
    sync_processes(f"parts of {path} written")
    if index:
        return None
    parts = []
    for i in range(count):
        with np.load(part(i), allow_pickle=False) as f:
            parts.append({k: f[k] for k in f.files})
        os.remove(part(i))
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
