"""`prepare`: a source's files -> a cache, read and encoded in a process pool.

Each file (an Argoverse 2 log, a ScenarioNet pickle, a GPUDrive JSON scenario) is read and
its frames encoded in a worker (actors padded, map elements moved to the world frame); the
parent writes them in file order, so the cache does not depend on the number of workers. A
file that cannot be read is skipped and counted under its reason (`Summary.bad_files`, file
names in `bad_file_list` and the log), unless `strict`.
"""

from __future__ import annotations

import collections
import concurrent.futures
import logging
import multiprocessing
import pickle
import time
from typing import NamedTuple

from scenegen_jax import signals
from scenegen_jax.backend import contiguous_part, cpu_cores
from scenegen_jax.config import Config
from scenegen_jax.data.cache_layout import shard_dir
from scenegen_jax.data.cache_write import CacheWriter, EncodedFrame, Summary, encode_frame
from scenegen_jax.data.sources import read_file, source_files

log = logging.getLogger(__name__)
# What a damaged or foreign file raises in our readers (ValueError includes JSON errors;
# RecursionError: a pickle nested too deeply; the others: a layout no reader check foresaw).
FILE_ERRORS = (ValueError, OSError, EOFError, pickle.UnpicklingError, KeyError, TypeError,
               IndexError, AttributeError, RecursionError)


class FileResult(NamedTuple):
    path: str
    frames: list[EncodedFrame]
    drops: collections.Counter
    error: str | None  # "<ExceptionType>: message" when the file was unusable


def encode_file(spec: dict, path: str, cfg: Config, strict: bool = False) -> FileResult:
    """Reads and encodes one file; an unusable file gives an error string (or raises)."""
    try:
        frames, drops = read_file(spec, path)
    except FILE_ERRORS as e:
        error = f"{type(e).__name__}: {e}"
        if not strict:
            return FileResult(path, [], collections.Counter(), error)
        if isinstance(e, OSError) or (isinstance(e, ValueError) and path in str(e)):
            raise
        raise ValueError(f"{path}: {error}") from e  # the CLI's bad-input error, naming the file
    return FileResult(path, [encode_frame(f, cfg) for f in frames], drops, None)


def prepare(
    spec: dict,
    out_dir: str,
    cfg: Config,
    *,
    workers: int | None = None,
    strict: bool = False,
    progress=None,
    shard: tuple[int, int] | None = None,
) -> tuple[Summary, float]:
    """Writes the cache of source `spec` into `out_dir`.

    Args:
      spec: a source (`sources.source_spec`).
      shard: (I, N): only part I of N of the source's files (contiguous, in file order),
        into `cache.shard_dir(out_dir, I, N)`; N such jobs, run anywhere, make one cache.
      workers: processes (default: one per available core; 1 reads in this process).
      strict: stop at the first unusable file (its error names the file and field).
      progress: optional tqdm-like object, updated once per file.

    Returns:
      (summary, scenes per second of wall time).
    """
    files = source_files(spec)
    if shard is not None:
        index, count = shard
        out_dir = shard_dir(out_dir, index, count)
        part = contiguous_part(len(files), index, count)
        if not part:
            raise ValueError(f"--shard {index}/{count}: no files for this shard ({len(files)} "
                             f"files in all); use at most {len(files)} shards")
        files = files[part.start : part.stop]
        spec = {**spec, "shard": [index, count]}
    workers = workers or cpu_cores()
    start = time.perf_counter()
    with CacheWriter(out_dir, cfg, spec) as writer:
        drops = _encode_into(writer, spec, files, cfg, workers, strict, progress)
        summary = writer.close(drops)
    return summary, summary.scenes / max(time.perf_counter() - start, 1e-9)


def _encode_into(writer: CacheWriter, spec: dict, files: list[str], cfg: Config, workers: int,
                 strict: bool, progress) -> collections.Counter:
    """Encodes `files` (in `workers` processes) into `writer` in file order, counting the
    unusable ones in its summary; returns the readers' dropped rows."""
    drops: collections.Counter = collections.Counter()
    bad: collections.Counter = collections.Counter()
    if progress is not None:
        progress.reset(total=len(files))

    def consume(result: FileResult) -> None:
        writer.summary.files += 1
        if result.error is not None:
            reason = result.error.split(":", 1)[0]
            bad[reason] += 1
            writer.summary.bad_file_list.append({"file": result.path, "error": result.error})
            log.warning(
                "skipped %s",
                result.error if result.path in result.error else f"{result.path}: {result.error}",
            )
        for enc in result.frames:
            writer.add(enc)
        drops.update(result.drops)
        if progress is not None:
            progress.update(1)

    if workers <= 1 or len(files) <= 1:
        for path in files:
            consume(encode_file(spec, path, cfg, strict))
    else:
        # Spawned, not forked: the parent may already run JAX's threads. At most
        # 2 * workers files in flight, so finished maps never pile up in memory. Workers
        # leave stop signals to this process: when it stops, files not started are
        # cancelled, and each worker ends after the file it is reading.
        context = multiprocessing.get_context("spawn")
        n = min(workers, len(files))
        with concurrent.futures.ProcessPoolExecutor(
                n, mp_context=context, initializer=signals.ignore_in_worker) as pool:
            pending = collections.deque()
            try:
                for path in files:
                    pending.append(pool.submit(encode_file, spec, path, cfg, strict))
                    if len(pending) >= 2 * n:
                        consume(pending.popleft().result())  # file order
                while pending:
                    consume(pending.popleft().result())
            except BaseException:
                pool.shutdown(wait=False, cancel_futures=True)
                raise
    writer.summary.bad_files = dict(sorted(bad.items()))
    return drops
