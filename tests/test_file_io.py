"""File I/O: atomic writes (files renamed into place, folders swapped in whole) and JSON reads
whose errors name the file and the place."""

import json

import pytest

from tactile_deploy.atomic import atomic_path, replace_folder, write_json
from tactile_deploy.jsonfile import read_json, validation_error_text


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


def test_validation_error_text_names_each_field_and_its_value():
    from pydantic import BaseModel, Field, ValidationError

    class Inner(BaseModel):
        k2: float = Field(allow_inf_nan=False)

    class Doc(BaseModel, extra="forbid"):
        scale_mm: float = Field(gt=0)
        inner: Inner
        sizes: list[int]

    with pytest.raises(ValidationError) as err:
        Doc.model_validate({"scale_mm": -0.5, "inner": {"k2": float("nan")},
                            "sizes": [1, "x"], "colour": {"r": 1}})
    text = validation_error_text("cfg.json", err.value, "test document", "see doc.md")
    lines = text.splitlines()
    assert lines[0] == "cfg.json: invalid test document:"
    assert "  field 'scale_mm': Input should be greater than 0 (got -0.5)" in lines
    assert any(ln.startswith("  field 'inner.k2':") and ln.endswith("(got nan)") for ln in lines)
    assert any(ln.startswith("  field 'sizes.1':") and ln.endswith('(got "x")') for ln in lines)
    assert any(ln.startswith("  field 'colour': Extra inputs") and ln.endswith("(got dict)")
               for ln in lines)
    assert lines[-1] == "  (see doc.md)"


def test_write_json_writes_strict_json_with_null_for_non_finite_numbers(tmp_path):
    import numpy as np

    path = tmp_path / "summary.json"
    write_json(path, {"p50_ms": float("nan"), "rates": [1.5, np.float32(np.inf), np.float64(-np.inf)],
                      "pair": (2, "x")})

    def refuse(name):
        raise AssertionError(f"{path} holds {name}, which strict JSON parsers refuse")

    assert json.loads(path.read_text(), parse_constant=refuse) == {
        "p50_ms": None, "rates": [1.5, None, None], "pair": [2, "x"]}
