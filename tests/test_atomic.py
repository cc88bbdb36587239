"""Atomic writes: files renamed into place, folders swapped in whole."""

import json

import pytest

from tactile_deploy.atomic import atomic_path, replace_folder, write_json


def test_failed_write_leaves_the_previous_file(tmp_path):
    path = tmp_path / "a.json"
    write_json(path, {"v": 1})
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert json.loads(path.read_text()) == {"v": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]


def test_replace_folder_puts_the_new_folder_in_place_and_removes_the_old(tmp_path):
    target = tmp_path / "plugin"
    for version in ("1", "2"):
        staging = tmp_path / f".plugin.partial-{version}"
        staging.mkdir()
        (staging / "version.txt").write_text(version)
        replace_folder(staging, target)
        assert (target / "version.txt").read_text() == version
        assert sorted(p.name for p in tmp_path.iterdir()) == ["plugin"]
