"""Files: outputs written whole or not at all, and a data set's input files found under its
root (standard library only)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path


@contextlib.contextmanager
def written_whole(path: str):
    """Yields a temporary path beside `path` to write; renames it to `path` when the block
    ends and removes it when the block fails, so an interrupted or failed write (a full
    disk, Ctrl-C) leaves no partial `path` that looks complete.

    The temporary name ends as `path` does (`scores.123.tmp.csv`: tools that read the format
    from the extension see the same one) and holds the process id (two runs writing the same
    output do not share it). An OSError that names no file is raised naming `path`.
    """
    root, ext = os.path.splitext(path)
    tmp = f"{root}.{os.getpid()}.tmp{ext}"
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as e:
        if e.filename is not None:  # names its own file (an inner block's, or another input)
            raise
        raise OSError(e.errno, e.strerror or str(e), path) from e
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def files_under(root: str | os.PathLike, suffix: str, skip: tuple[str, ...] = (), *,
                infix: bool = False) -> list[Path]:
    """Sorted files named `*suffix` under `root`, recursively, following symbolic links to
    files and folders (a data set assembled from links reads as a copy would), each file once:
    a file reached by two paths (two links, a link and its target) is listed by the path
    the walk meets first (a folder's files, by name, before its sub-folders, by name), and
    a link back to a folder already walked is not walked again. Names in `skip` are left
    out. With `infix`, names that hold `suffix` anywhere count (`*suffix*`: Waymo names its
    shards `training.tfrecord-00000-of-01000`).

    Raises:
      FileNotFoundError: `root` is not a directory.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a directory")
    found: dict[str, Path] = {}
    walked: set[str] = set()
    for folder, dirs, names in os.walk(root, followlinks=True):
        real = os.path.realpath(folder)
        if real in walked:  # a link to a folder already walked (or to an ancestor)
            dirs[:] = []
            continue
        walked.add(real)
        dirs.sort()
        for name in sorted(names):
            path = Path(folder, name)
            matches = suffix in name if infix else name.endswith(suffix)
            if matches and name not in skip and path.is_file():
                found.setdefault(os.path.realpath(path), path)
    return sorted(set(found.values()))
