"""JSON text and files, read with errors that name the file: bad JSON, bad UTF-8, an integer
beyond Python's digit limit, or nesting deeper than Python's parser goes (a RecursionError,
which would otherwise end a whole `prepare` run with a traceback)."""

from __future__ import annotations

import json
import os
from typing import Any


def parse_json(text: str | bytes, where: str) -> Any:
    """The value of JSON `text`; a ValueError naming `where` (a file) if it is not JSON."""
    try:
        return json.loads(text)
    except ValueError as e:  # JSONDecodeError, UnicodeDecodeError, an over-long integer
        raise ValueError(f"{where}: not valid JSON ({e})") from e
    except RecursionError as e:
        raise ValueError(f"{where}: not valid JSON (nested too deeply)") from e


def read_json(path: str | os.PathLike) -> Any:
    """The value of the JSON file `path` (`parse_json`); OSError if it cannot be read."""
    with open(path, "rb") as f:
        return parse_json(f.read(), str(path))
