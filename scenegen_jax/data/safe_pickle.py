"""Restricted pickle loading: numpy arrays and builtin containers only, never code.

ScenarioNet stores scenarios as pickles. A plain `pickle.load` runs whatever callable the file
names (`os.system`, `builtins.eval`, ...), so every pickle in this project goes through
`load_pickle`, whose unpickler resolves only an explicit allow-list of globals. The one class
outside numpy and builtins it accepts is MetaDrive's `ScenarioDescription` (module
`metadrive.scenario.scenario_description`), which older ScenarioNet files pickled: it is a
dict subclass, and it is read as a plain `dict` (nothing of MetaDrive is imported or run).
"""

from __future__ import annotations

import _compat_pickle
import builtins
import collections
import importlib
import os
import pickle
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from scenegen_jax.files import written_whole


class UnsafePickleError(ValueError):
    """A pickle names a global outside the allow-list (it could run code)."""


class CorruptPickleError(ValueError):
    """A pickle is truncated or malformed."""


def _numpy_attr(submodule: str, name: str) -> Callable[..., Any]:
    """numpy.<_core|core>.<submodule>.<name>, preferring numpy 2's `_core` (no warning)."""
    for package in ("numpy._core", "numpy.core"):
        try:
            return getattr(importlib.import_module(f"{package}.{submodule}"), name)
        except (ImportError, AttributeError):
            continue
    raise ImportError(f"numpy has no {submodule}.{name}")


def _latin1_encode(text: str, encoding: str = "utf-8") -> bytes:
    """`_codecs.encode` as protocol 0-2 pickles use it for bytes; only latin-1 is allowed."""
    if encoding.lower().replace("-", "") not in ("latin1", "iso88591"):
        raise pickle.UnpicklingError(f"_codecs.encode with encoding {encoding!r} is not allowed")
    return text.encode("latin-1")


# numpy pickles name these under numpy.core (numpy 1.x) or numpy._core (numpy 2.x); protocol 5
# uses _frombuffer, protocols 2-4 use _reconstruct; scalars use multiarray.scalar.
_NUMPY_GLOBALS: dict[tuple[str, str], tuple[str, str]] = {}
for _pkg in ("numpy.core", "numpy._core"):
    _NUMPY_GLOBALS[(f"{_pkg}.multiarray", "_reconstruct")] = ("multiarray", "_reconstruct")
    _NUMPY_GLOBALS[(f"{_pkg}.multiarray", "scalar")] = ("multiarray", "scalar")
    _NUMPY_GLOBALS[(f"{_pkg}.numeric", "_frombuffer")] = ("numeric", "_frombuffer")

_PLAIN_GLOBALS: dict[tuple[str, str], Any] = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("_codecs", "encode"): _latin1_encode,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("collections", "defaultdict"): collections.defaultdict,
    ("collections", "Counter"): collections.Counter,
    # Older ScenarioNet / MetaDrive files pickled the scenario as MetaDrive's
    # `ScenarioDescription`, a dict subclass with no state of its own: read as a plain dict.
    ("metadrive.scenario.scenario_description", "ScenarioDescription"): dict,
}
# Builtin containers and plain value types; nothing that evaluates, imports or reflects.
for _name in (
    "dict",
    "list",
    "tuple",
    "set",
    "frozenset",
    "bytearray",
    "bytes",
    "str",
    "int",
    "float",
    "bool",
    "complex",
    "slice",
    "range",
):
    _PLAIN_GLOBALS[("builtins", _name)] = getattr(builtins, _name)


class _RestrictedUnpickler(pickle.Unpickler):
    """An Unpickler whose `find_class` resolves only the allow-list above."""

    def __init__(self, file: Any, path: str):
        super().__init__(file)
        self._path = path

    def find_class(self, module: str, name: str) -> Any:
        key = (module, name)
        # Python 2 names (protocol 0-2 pickles) mapped as pickle's own fix_imports does; a
        # mapped name is still checked against the allow-list.
        if key in _compat_pickle.NAME_MAPPING:
            key = _compat_pickle.NAME_MAPPING[key]
        elif module in _compat_pickle.IMPORT_MAPPING:
            key = (_compat_pickle.IMPORT_MAPPING[module], name)
        if key in _PLAIN_GLOBALS:
            return _PLAIN_GLOBALS[key]
        if key in _NUMPY_GLOBALS:
            return _numpy_attr(*_NUMPY_GLOBALS[key])
        raise UnsafePickleError(
            f"{self._path}: refusing to unpickle global {key[0]}.{key[1]}; only numpy arrays and "
            "builtin containers are allowed (the file may try to run code)"
        )

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafePickleError(f"{self._path}: persistent ids are not allowed in pickles")


def load_pickle(path: str | os.PathLike) -> Any:
    """Loads a pickle that may contain only numpy arrays, numpy scalars and builtin containers
    (and MetaDrive `ScenarioDescription`s, which load as plain dicts).

    Raises:
      FileNotFoundError: no such file.
      UnsafePickleError: the pickle names any other global (nothing from it is executed).
      CorruptPickleError: the pickle is truncated or malformed.
    """
    path_str = os.fspath(path)
    with open(path_str, "rb") as f:
        try:
            return _RestrictedUnpickler(f, path_str).load()
        except UnsafePickleError:
            raise
        except (
            EOFError,
            pickle.UnpicklingError,
            struct.error,
            ValueError,
            TypeError,
            IndexError,
            KeyError,
            AttributeError,
            ImportError,
            UnicodeDecodeError,
            OverflowError,
            MemoryError,
        ) as e:
            raise CorruptPickleError(
                f"{path_str}: truncated or corrupt pickle ({type(e).__name__}: {e})"
            ) from e


def dump_pickle(obj: Any, path: str | os.PathLike, protocol: int = 4) -> None:
    """Writes `obj` whole or not at all (`files.written_whole`), creating parent directories.

    Protocol 4 is what ScenarioNet writes (Python's default) and what Python >= 3.4 reads.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with written_whole(os.fspath(target)) as tmp, open(tmp, "wb") as f:
        pickle.dump(obj, f, protocol=protocol)
