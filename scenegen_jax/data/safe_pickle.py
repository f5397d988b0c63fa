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
import math
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


class OversizedPickleError(ValueError):
    """A pickle is larger, or builds more, than any scenario needs."""


# The largest scenario pickles the converters write are tens of MB (a 20 s WOMD scenario is
# about 2 MB); a file far beyond that is not a scenario, and reading it whole would take its
# size in memory before any check could run.
MAX_PICKLE_BYTES = 1 << 30
# Items (container entries, characters, array elements) an honest pickle builds per byte of
# its file: each comes from at least one opcode or data byte, and the copies a converter's
# pickle makes (`OrderedDict(list)`, `set(list)`) take a few more. A few allowed calls build
# far more from a few bytes (`list(range(30_000_000))` is 43 bytes), so every call's size is
# counted against this budget before the call runs. ITEMS_FLOOR covers the smallest files.
ITEMS_PER_BYTE = 8
ITEMS_FLOOR = 1 << 16


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


def _arg_items(value: Any, counts_ints: bool) -> float:
    """Items a call copies or makes from one argument: its length, an int itself where the
    callable makes that many (`bytes(n)`); inf where the length does not fit an int
    (`range(10**20)`)."""
    if isinstance(value, bool):
        return 0
    if isinstance(value, int):
        return value if counts_ints else 0
    try:
        return len(value)
    except OverflowError:
        return float("inf")
    except TypeError:
        return 0


def _shape_items(value: Any) -> float:
    """Elements of an array of shape `value` (an int or a tuple of ints; else 0)."""
    dims = (value,) if isinstance(value, int) else value
    if not isinstance(dims, tuple) or not all(isinstance(d, int) for d in dims):
        return 0
    return math.prod(max(d, 0) for d in dims)


# Text of which `str` only decodes or formats a number; the text of a container is its
# nested items' text, which can grow exponentially with the pickle (a list of lists of the
# same list), so `str` of anything else is refused.
_STR_ARGS = (str, bytes, bytearray, int, float)


def _planned_items(name: str, args: tuple) -> float:
    """Items the allowed callable `name` builds from `args`, known before it runs."""
    if name == "str" and not all(isinstance(a, _STR_ARGS) for a in args):
        return float("inf")
    if name in ("ndarray", "_reconstruct"):  # (shape, ...) / (subtype, shape, dtype)
        shape = args[0] if name == "ndarray" and args else args[1] if len(args) > 1 else ()
        return _shape_items(shape)
    return sum(_arg_items(a, counts_ints=name in ("bytes", "bytearray")) for a in args)


def _built_items(value: Any) -> float:
    """Items `value` holds (a range holds none: it is lazy)."""
    if isinstance(value, np.ndarray):
        return _shape_items(value.shape)
    return 0 if isinstance(value, range) else _arg_items(value, counts_ints=False)


# The allowed callables that build in proportion to their arguments; the others (numbers,
# slices, ranges, dtypes, scalars and arrays from the file's own bytes) build a bounded amount.
_SIZED_CALLS = ("list", "tuple", "set", "frozenset", "bytearray", "bytes", "str", "dict",
                "OrderedDict", "defaultdict", "Counter", "ndarray", "_reconstruct")


def _base(value: Any) -> Any:
    """The allowed class a guard class stands for (`_ItemBudget.guard`), else `value`."""
    return value.__dict__.get("_guarded", value) if isinstance(value, type) else value


class _ItemBudget:
    """The items the calls of one pickle may still build (`ITEMS_PER_BYTE`)."""

    def __init__(self, path: str, file_bytes: int):
        self.path = path
        self.file_bytes = file_bytes
        self.left = max(ITEMS_FLOOR, ITEMS_PER_BYTE * file_bytes)

    def spend(self, name: str, items: float) -> None:
        self.left -= items
        if self.left < 0:
            what = "an unbounded number of" if items == float("inf") else f"{items:.0f}"
            raise OversizedPickleError(
                f"{self.path}: a call of {name} builds {what} items, beyond what a pickle of "
                f"{self.file_bytes} bytes holds ({ITEMS_PER_BYTE} per byte): not a scenario")

    def guard(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """`fn`, refused before it runs where its arguments would take the budget below 0,
        then charged for what it built. A class stays a class (pickle's NEWOBJ needs one): a
        subclass whose `__new__` builds and returns the allowed class's own instance."""
        name = getattr(fn, "__name__", "")
        if name not in _SIZED_CALLS:
            return fn

        def build(*args: Any, **kwargs: Any) -> Any:
            args = tuple(_base(a) for a in args)  # `defaultdict(list)`, `_reconstruct(ndarray)`
            kwargs = {k: _base(v) for k, v in kwargs.items()}
            self.spend(name, _planned_items(name, (*args, *kwargs.values())))
            out = fn(*args, **kwargs)
            self.spend(name, _built_items(out))
            return out

        if not isinstance(fn, type):
            return build
        return type(name, (fn,), {"__new__": lambda cls, *a, **k: build(*a, **k),
                                  "_guarded": fn})


class _RestrictedUnpickler(pickle.Unpickler):
    """An Unpickler whose `find_class` resolves only the allow-list above, each callable
    held to the file's item budget (`_ItemBudget`)."""

    def __init__(self, file: Any, path: str, file_bytes: int):
        super().__init__(file)
        self._path = path
        self._budget = _ItemBudget(path, file_bytes)
        self._guards: dict[tuple[str, str], Any] = {}

    def find_class(self, module: str, name: str) -> Any:
        key = (module, name)
        # Python 2 names (protocol 0-2 pickles) mapped as pickle's own fix_imports does; a
        # mapped name is still checked against the allow-list.
        if key in _compat_pickle.NAME_MAPPING:
            key = _compat_pickle.NAME_MAPPING[key]
        elif module in _compat_pickle.IMPORT_MAPPING:
            key = (_compat_pickle.IMPORT_MAPPING[module], name)
        if key not in self._guards and key in _PLAIN_GLOBALS:
            self._guards[key] = self._budget.guard(_PLAIN_GLOBALS[key])
        elif key not in self._guards and key in _NUMPY_GLOBALS:
            self._guards[key] = self._budget.guard(_numpy_attr(*_NUMPY_GLOBALS[key]))
        if key in self._guards:
            return self._guards[key]
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
      OversizedPickleError: the file is over `MAX_PICKLE_BYTES`, or its calls build more
        than `ITEMS_PER_BYTE` items per byte of it.
    """
    path_str = os.fspath(path)
    with open(path_str, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size > MAX_PICKLE_BYTES:
            raise OversizedPickleError(
                f"{path_str}: {size} bytes, over the {MAX_PICKLE_BYTES} a scenario pickle may "
                "take")
        try:
            return _RestrictedUnpickler(f, path_str, size).load()
        except (UnsafePickleError, OversizedPickleError):
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
