"""Fuzzed paths: a data set assembled from links under odd names reads each file once, and
outputs under odd names are written whole or refused in one line.

Hypothesis draws folder and file names (any characters a file system takes, spaces, leading
dashes, non-ASCII) and a layout of links to real Waymo JSON scenes (read in place): a file
linked twice, a folder linked beside itself, a link back to the root. `source_files` must list
each real file once and every listed unit must read; an output written through
`files.written_whole` or the CLI's `check_output` under an odd name either lands whole under
that name or is a one-line error naming it. Profiles: conftest.py (25 fixed examples in
`make test`, 200 new ones in `make fuzz`).
"""

from __future__ import annotations

import os
import uuid

from conftest import WOMD_ROOT
from hypothesis import given
from hypothesis import strategies as st

from scenegen_jax.cli.common import check_output
from scenegen_jax.data.sources import read_file, source_files, source_spec
from scenegen_jax.files import written_whole

SCENES = [os.path.join(WOMD_ROOT, "gpudrive_json", "val", n)
          for n in ("74e892ddfe3b9b8.json", "tfrecord-00068-of-01000_277.json")]
# Names a POSIX file system takes: no "/" or NUL, not "." or "..", at most 255 bytes.
NAMES = st.text(st.characters(blacklist_characters="/\0", blacklist_categories=("Cs",)),
                min_size=1, max_size=40).filter(
    lambda n: n not in (".", "..") and len(n.encode()) <= 200)


def _fresh(tmp_path_factory) -> str:
    return str(tmp_path_factory.getbasetemp() / f"paths-{uuid.uuid4().hex}")


@given(folder=NAMES, names=st.lists(NAMES, min_size=2, max_size=2, unique=True),
       twice=st.booleans(), loop=st.booleans())
def test_linked_data_sets_under_odd_names_read_each_file_once(tmp_path_factory, folder, names,
                                                              twice, loop):
    root = _fresh(tmp_path_factory)
    inner = os.path.join(root, folder)
    os.makedirs(inner)
    for name, scene in zip(names, SCENES, strict=True):
        os.symlink(scene, os.path.join(inner, name + ".json"))
    if twice:  # the first scene linked a second time, and the folder beside itself
        os.symlink(SCENES[0], os.path.join(root, "again.json"))
        os.symlink(inner, os.path.join(root, "same folder"))
    if loop:
        os.symlink(root, os.path.join(inner, "back to the root"))
    units = source_files(source_spec("womd_json", root, stride=30))
    assert sorted(os.path.realpath(u) for u in units) == sorted(SCENES)
    for unit in units:
        frames, _ = read_file(source_spec("womd_json", root, stride=30), unit)
        assert frames


@given(folder=NAMES, name=NAMES)
def test_outputs_under_odd_names_land_whole_or_are_refused_in_one_line(tmp_path_factory,
                                                                        folder, name):
    out = os.path.join(_fresh(tmp_path_factory), folder, name + ".csv")
    try:
        check_output("--out", out)
    except ValueError as e:
        assert "--out" in str(e) and "\n" not in str(e)
        return
    with written_whole(out) as tmp, open(tmp, "w") as f:
        f.write("a,b\n")
    with open(out) as f:
        assert f.read() == "a,b\n"
    assert os.listdir(os.path.dirname(out)) == [os.path.basename(out)]
