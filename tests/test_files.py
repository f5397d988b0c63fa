"""Output files written whole or not at all (`scenegen_jax.files.written_whole`), and a data
set's files found under its root through links (`files_under`)."""

from __future__ import annotations

import errno
import os
import stat

import pytest

from scenegen_jax.data.safe_pickle import dump_pickle, load_pickle
from scenegen_jax.data.sources import source_files, source_spec
from scenegen_jax.files import files_under, written_whole


def test_a_failed_write_leaves_the_earlier_file_and_no_temporary(tmp_path):
    path = tmp_path / "out.json"
    with written_whole(str(path)) as tmp, open(tmp, "w") as f:
        assert tmp.endswith(".json") and tmp != str(path)  # the format's extension kept
        f.write("first")
    assert path.read_text() == "first"
    for stop in (KeyboardInterrupt, RuntimeError):
        with pytest.raises(stop), written_whole(str(path)) as tmp, open(tmp, "w") as f:
            f.write("cut sh")
            raise stop
        assert path.read_text() == "first" and os.listdir(tmp_path) == ["out.json"]


def test_an_os_error_without_a_file_names_the_output(tmp_path):
    path = str(tmp_path / "scores.csv")
    with pytest.raises(OSError, match="No space left on device") as e, written_whole(path):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as a write() on a full disk
    assert e.value.errno == errno.ENOSPC and e.value.filename == path
    assert os.listdir(tmp_path) == []
    # Nested: the inner file is the one named, not the outer output.
    inner = str(tmp_path / "png" / "a.png")
    with pytest.raises(OSError) as e, written_whole(path), written_whole(inner):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert e.value.filename == inner
    missing = str(tmp_path / "missing.part")
    with pytest.raises(FileNotFoundError, match="missing.part"), written_whole(path):
        open(missing).close()  # an error naming its own file keeps its message


def test_exported_pickles_get_the_umasks_permissions(tmp_path):
    """ScenarioNet files are readable as any file the user writes (a private temporary file
    renamed into place would make them 0600)."""
    plain = tmp_path / "plain"
    plain.write_bytes(b"")
    dump_pickle({"id": "a"}, tmp_path / "sd_a.pkl")
    assert load_pickle(tmp_path / "sd_a.pkl") == {"id": "a"}
    mode = stat.S_IMODE
    assert mode(os.stat(tmp_path / "sd_a.pkl").st_mode) == mode(os.stat(plain).st_mode)


def test_figures_keep_the_format_of_their_name(tmp_path):
    """Rendered through a temporary file, an image is still in the format its name asks for,
    and a name without an extension still gets `.png`, as matplotlib gives it."""
    import matplotlib.pyplot as plt

    from scenegen_jax.viz.render import save_figure

    for name, head in (("a", b"\x89PNG"), ("b.png", b"\x89PNG"), ("c.svg", b"<?xml")):
        fig = plt.figure(figsize=(1, 1))
        save_figure(fig, str(tmp_path / name), dpi=20)
        path = tmp_path / (name if "." in name else f"{name}.png")
        assert path.read_bytes().startswith(head), name
    assert sorted(os.listdir(tmp_path)) == ["a.png", "b.png", "c.svg"]


def test_files_under_follows_links_once_each(tmp_path):
    root, other = tmp_path / "root", tmp_path / "other"
    (root / "sub").mkdir(parents=True)
    (other / "deep").mkdir(parents=True)
    for path in (root / "a.json", root / "sub" / "b.json", other / "c.json",
                 other / "deep" / "d.json", root / "summary.json", root / "e.txt"):
        path.write_text("{}")
    (root / "linked").symlink_to(other)  # a folder of links: walked
    (root / "c_again.json").symlink_to(other / "c.json")  # a second path to c.json
    (root / "sub" / "a_link.json").symlink_to(root / "a.json")
    (root / "sub" / "loop").symlink_to(root)  # back to an ancestor: not walked again
    (root / "dangling.json").symlink_to(tmp_path / "missing.json")
    got = [p.relative_to(root).as_posix() for p in files_under(root, ".json",
                                                                 skip=("summary.json",))]
    # Each file once, by its first path in sorted order.
    assert got == ["a.json", "c_again.json", "linked/deep/d.json", "sub/b.json"]
    with pytest.raises(FileNotFoundError, match="not a directory"):
        files_under(root / "a.json", ".json")


@pytest.mark.parametrize("kind, folder, suffix", [("scenarionet", "scenarionet", ".pkl"),
                                                  ("womd_json", "gpudrive_json", ".json")])
def test_a_dataset_of_linked_folders_reads_every_file(tmp_path, womd_root, kind, folder,
                                                      suffix):
    # One real val file linked in, and the whole real train folder linked as a sub-folder.
    data = os.path.join(womd_root, folder)
    train = sorted(n for n in os.listdir(os.path.join(data, "train")) if n.endswith(suffix))
    val = sorted(n for n in os.listdir(os.path.join(data, "val")) if n.endswith(suffix))
    (tmp_path / val[0]).symlink_to(os.path.join(data, "val", val[0]))
    (tmp_path / "more").symlink_to(os.path.join(data, "train"))
    files = source_files(source_spec(kind, str(tmp_path)))
    assert [os.path.basename(f) for f in files] == [val[0], *train]
    assert len(train) > 10
