"""File I/O: atomic writes (files renamed into place, folders swapped in whole) and JSON reads
whose errors name the file and the place."""

import json

import pytest

from tactile_deploy.atomic import atomic_path, replace_folder, write_json
from tactile_deploy.jsonfile import read_json


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


class _DocError(ValueError):
    pass


def test_read_json_errors_name_the_file_line_and_column(tmp_path):
    good = tmp_path / "good.json"
    write_json(good, {"a": [1, 2]})
    assert read_json(good, _DocError) == {"a": [1, 2]}
    bad = tmp_path / "bad.json"
    bad.write_text('{"a": 1,\n "b" 2}')
    with pytest.raises(_DocError, match=r"bad.json: not valid JSON \(line 2, column 6: Expecting ':' delimiter\)"):
        read_json(bad, _DocError)
    binary = tmp_path / "frame.json"
    binary.write_bytes(b"\x89PNG\xff\xfe")
    with pytest.raises(_DocError, match="frame.json: not a text file \\(expected a JSON plugin manifest\\)"):
        read_json(binary, _DocError, "a JSON plugin manifest")
