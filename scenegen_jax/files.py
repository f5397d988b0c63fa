"""Output files written whole or not at all (standard library only)."""

from __future__ import annotations

import contextlib
import os


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
