"""The restricted unpickler (`data.safe_pickle`): code-running and unknown globals refused,
numpy arrays and containers loaded at every protocol, truncated files named, atomic dumps,
MetaDrive's ScenarioDescription read as a dict, and pickles that build far more than their
size refused before they build it."""

from __future__ import annotations

import collections
import os
import pickle
import time
import tracemalloc

import numpy as np
import pytest
from scenarionet_fixtures import hand_frame

from scenegen_jax.data import safe_pickle
from scenegen_jax.data import scenarionet as sn
from scenegen_jax.data.prepare import encode_file
from scenegen_jax.data.safe_pickle import (
    CorruptPickleError,
    OversizedPickleError,
    UnsafePickleError,
    dump_pickle,
    load_pickle,
)


class _Exploit:
    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class _Plain:
    pass


def test_code_running_pickle_is_refused(tmp_path):
    marker = tmp_path / "pwned_marker"
    path = tmp_path / "sd_evil.pkl"
    with open(path, "wb") as f:
        pickle.dump({"tracks": _Exploit(str(marker))}, f)
    with pytest.raises(UnsafePickleError, match=r"sd_evil\.pkl.*(posix|os|nt)\.system"):
        load_pickle(path)
    assert not marker.exists()
    # read_scenarionet refuses it too, and still runs nothing
    with pytest.raises(UnsafePickleError):
        list(sn.read_scenarionet(tmp_path))
    assert not marker.exists()


@pytest.mark.parametrize(
    "payload",
    [
        b"cbuiltins\neval\n(S'1+1'\ntR.",  # protocol 0 GLOBAL builtins.eval
        b"\x80\x04\x95\x00\x00\x00\x00\x00\x00\x00\x00\x8c\x08builtins\x8c\x07getattr\x93.",
        b"cbuiltins\n__import__\n(S'os'\ntR.",
    ],
)
def test_dangerous_builtins_are_refused(tmp_path, payload):
    path = tmp_path / "p.pkl"
    path.write_bytes(payload)
    with pytest.raises(UnsafePickleError, match=r"p\.pkl: refusing to unpickle global builtins\."):
        load_pickle(path)


def test_arbitrary_classes_are_refused(tmp_path):
    path = tmp_path / "obj.pkl"
    with open(path, "wb") as f:
        pickle.dump({"a": _Plain()}, f)
    with pytest.raises(UnsafePickleError, match="_Plain"):
        load_pickle(path)


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_numpy_and_containers_load_at_every_protocol(tmp_path, protocol):
    obj = {
        "f32": np.arange(6, dtype=np.float32).reshape(2, 3),
        "f64_fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        "bool": np.array([True, False]),
        "str": np.array(["a", "bc"]),
        "empty": np.zeros((0, 3)),
        "scalar": np.float32(2.5),
        "int": np.int64(7),
        "nested": [(1, 2.0, "x", None, b"by"), {3, 4}, frozenset({5})],
        "dd": collections.defaultdict(int, {"a": 1}),
    }
    path = tmp_path / "ok.pkl"
    with open(path, "wb") as f:
        pickle.dump(obj, f, protocol=protocol)
    got = load_pickle(path)
    for key in ("f32", "f64_fortran", "bool", "str", "empty"):
        np.testing.assert_array_equal(got[key], obj[key])
        assert got[key].dtype == obj[key].dtype
    assert got["scalar"] == np.float32(2.5) and got["scalar"].dtype == np.float32
    assert got["int"] == 7 and got["nested"] == obj["nested"] and got["dd"] == {"a": 1}


def test_truncated_pickle_names_the_file(tmp_path):
    s = sn.scenario_from_frame(hand_frame(), "x")
    path = tmp_path / "sd_trunc.pkl"
    sn.write_scenario(s, path)
    data = path.read_bytes()
    for cut in (len(data) // 3, len(data) - 1, 1):
        path.write_bytes(data[:cut])
        with pytest.raises(CorruptPickleError, match=r"sd_trunc\.pkl: truncated or corrupt"):
            load_pickle(path)
    path.write_bytes(b"")
    with pytest.raises(CorruptPickleError, match=r"sd_trunc\.pkl"):
        load_pickle(path)
    path.write_bytes(b"not a pickle at all")
    with pytest.raises(CorruptPickleError, match=r"sd_trunc\.pkl"):
        load_pickle(path)
    with pytest.raises(FileNotFoundError):
        load_pickle(tmp_path / "missing.pkl")


def test_dump_pickle_is_atomic_and_round_trips(tmp_path):
    path = tmp_path / "sub" / "a.pkl"
    dump_pickle({"a": np.arange(3)}, path)
    np.testing.assert_array_equal(load_pickle(path)["a"], np.arange(3))
    assert [p.name for p in path.parent.iterdir()] == ["a.pkl"]  # no temp files left


_SD_GLOBAL = b"cmetadrive.scenario.scenario_description\nScenarioDescription\n"  # GLOBAL


_SD_ITEMS = b"(X\x02\x00\x00\x00idX\x03\x00\x00\x00abcX\x06\x00\x00\x00tracks}u."


@pytest.mark.parametrize(
    ("payload", "want"),
    [
        # protocol 2: GLOBAL, EMPTY_TUPLE, NEWOBJ (cls.__new__(cls)), MARK, items, SETITEMS
        (b"\x80\x02" + _SD_GLOBAL + b")\x81" + _SD_ITEMS, {"id": "abc", "tracks": {}}),
        # protocol 4: the same class by STACK_GLOBAL (what Python 3 writes)
        (
            b"\x80\x04\x8c'metadrive.scenario.scenario_description\x94"
            b"\x8c\x13ScenarioDescription\x94\x93)\x81" + _SD_ITEMS,
            {"id": "abc", "tracks": {}},
        ),
        # protocol 0: GLOBAL called with no arguments
        (_SD_GLOBAL + b"(tR.", {}),
    ],
)
def test_metadrive_scenario_description_loads_as_a_dict(tmp_path, payload, want):
    """Older ScenarioNet files pickled MetaDrive's ScenarioDescription (a dict subclass)."""
    path = tmp_path / "sd_old.pkl"
    path.write_bytes(payload)
    got = load_pickle(path)
    assert type(got) is dict and got == want


@pytest.mark.parametrize(
    ("payload", "name"),
    [
        (b"\x80\x02c__main__\nFoo\n)\x81.", "__main__.Foo"),
        (b"cmetadrive.scenario.scenario_description\nOther\n(tR.", "scenario_description.Other"),
        (b"cmetadrive.type\nMetaDriveType\n(tR.", "metadrive.type.MetaDriveType"),
    ],
)
def test_other_classes_stay_refused(tmp_path, payload, name):
    path = tmp_path / "p.pkl"
    path.write_bytes(payload)
    with pytest.raises(UnsafePickleError, match=name.replace(".", r"\.")):
        load_pickle(path)


def test_os_system_global_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "ran"
    path = tmp_path / "p.pkl"
    path.write_bytes(b"cos\nsystem\n(S'touch " + str(marker).encode() + b"'\ntR.")
    with pytest.raises(UnsafePickleError, match=r"os\.system"):
        load_pickle(path)
    assert not marker.exists()


# Lists 0..5 (memo 0..5), each holding 30 references to the one before.
_NESTED_LISTS = b"(lp0\n0" + b"".join(b"(lp%d\n" % k + b"g%d\na" % (k - 1) * 30 + b"0"
                                        for k in range(1, 6))
_LIST_OF_RANGE = b"cbuiltins\nlist\n(cbuiltins\nrange\n(I30000000\ntRtR."  # list(range(3e7))


@pytest.mark.parametrize(
    "payload",
    [
        _LIST_OF_RANGE,
        # protocol 2 NEWOBJ: tuple.__new__(tuple, range(30_000_000))
        b"\x80\x02cbuiltins\ntuple\ncbuiltins\nrange\nJ\x80\xc3\xc9\x01\x85R\x85\x81.",
        b"cbuiltins\nbytes\n(I10000000000\ntR.",  # bytes(10**10)
        b"cbuiltins\nlist\n(cbuiltins\nrange\n(L10**20\ntRtR.".replace(b"10**20", b"1" + b"0" * 20),
        b"cnumpy\nndarray\n((I100000\nI100000\nttR.",  # numpy.ndarray((1e5, 1e5))
        # numpy.core.multiarray._reconstruct(numpy.ndarray, (10**10,), b"b")
        b"cnumpy.core.multiarray\n_reconstruct\n(cnumpy\nndarray\n(I10000000000\ntS'b'\ntR.",
        # str of 30 references to a list of 30 references to ... (5 deep): 24 million "[]"
        _NESTED_LISTS + b"cbuiltins\nstr\n(g5\ntR.",
    ],
)
def test_a_small_pickle_that_builds_a_huge_object_is_refused_before_it_builds_it(tmp_path,
                                                                                 payload):
    path = tmp_path / "bomb.pkl"
    path.write_bytes(payload)
    tracemalloc.start()
    started = time.monotonic()
    try:
        with pytest.raises(OversizedPickleError, match=r"bomb\.pkl: a call of \w+ builds"):
            load_pickle(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert time.monotonic() - started < 1.0 and peak < 2**20


def test_a_pickle_larger_than_any_scenario_is_refused_unread(tmp_path, monkeypatch):
    path = tmp_path / "huge.pkl"
    dump_pickle({"a": np.zeros(1000)}, path)
    monkeypatch.setattr(safe_pickle, "MAX_PICKLE_BYTES", 1000)
    with pytest.raises(OversizedPickleError, match=r"huge\.pkl: \d+ bytes, over the 1000"):
        load_pickle(path)


def test_prepare_counts_a_pickle_bomb_as_a_bad_file_naming_it(tmp_path):
    root = tmp_path / "sn"
    root.mkdir()
    (root / "bomb.pkl").write_bytes(_LIST_OF_RANGE)
    spec = {"kind": "scenarionet", "root": str(root), "split": None, "stride": 1}
    result = encode_file(spec, str(root / "bomb.pkl"), None)
    assert result.frames == [] and result.error.startswith("OversizedPickleError: ")
    assert "bomb.pkl" in result.error
