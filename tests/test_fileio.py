"""Output folders: written all or nothing, and with overwrite only the writer's entries replaced."""

import pytest

from o3d_mvps.errors import OutputExistsError
from o3d_mvps.fileio import atomic_folder


def earlier_output(path):
    path.mkdir()
    for name, text in {"result.txt": "old", "optional.txt": "old", "notes.txt": "mine"}.items():
        (path / name).write_text(text)
    (path / "frames").mkdir()
    (path / "frames" / "000009.txt").write_text("old frame")
    return path


def test_overwrite_replaces_only_the_writers_entries(tmp_path):
    out = earlier_output(tmp_path / "out")
    with atomic_folder(out, overwrite=True, layout=["optional.txt"]) as tmp:
        (tmp / "result.txt").write_text("new")
        (tmp / "frames").mkdir()
        (tmp / "frames" / "000000.txt").write_text("new frame")
    assert sorted(p.name for p in out.iterdir()) == ["frames", "notes.txt", "result.txt"]
    assert (out / "result.txt").read_text() == "new" and (out / "notes.txt").read_text() == "mine"
    assert [p.name for p in (out / "frames").iterdir()] == ["000000.txt"]  # a folder is replaced whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporary sibling left


def test_a_failure_leaves_the_earlier_output_as_it_was(tmp_path):
    out = earlier_output(tmp_path / "out")
    with pytest.raises(RuntimeError), atomic_folder(out, overwrite=True, layout=["optional.txt"]) as tmp:
        (tmp / "result.txt").write_text("new")
        raise RuntimeError("disk full")
    assert {p.name: p.read_text() for p in out.iterdir() if p.is_file()} == {
        "result.txt": "old", "optional.txt": "old", "notes.txt": "mine"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_non_empty_folder_is_refused_in_python_wording(tmp_path):
    out = earlier_output(tmp_path / "out")
    with pytest.raises(OutputExistsError, match="pass overwrite=True"), atomic_folder(out):
        pytest.fail("the block must not run")
