"""Output files written whole or not at all (standard library only)."""

from __future__ import annotations

import contextlib
import os


@contextlib.contextmanager
def written_whole(path: str):
    """Yields a temporary path beside `path` to write; renames it to `path` when the block
    ends and removes it when the block fails, so an interrupted or failed write (a full
    disk, Ctrl-C) leaves no partial `path` that looks complete. An OSError without a file
    name names `path`."""
    tmp = f"{path}.tmp"
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as e:
        if e.filename is not None:  # names its own file
            raise
        raise OSError(e.errno, f"{path}: {e.strerror or e}") from e
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
