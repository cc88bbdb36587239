"""``tactile-deploy discrepancy``: user mistakes are refused in one line, before any work, and
nothing the user made is lost (version files, report folders, inputs).

Malformed or nonsense measured data and bad output paths are refused before the analysis (the
analysis itself is replaced by a stand-in that fails the test when reached); one end-to-end run
on 8 contacts checks the report, the verdict's unit-named keys and the version history.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tactile_deploy.calibration.discrepancy.apply import apply_effect
from tactile_deploy.calibration.discrepancy.measured import (
    MeasuredDataError,
    load_measured,
    save_measured,
)
from tactile_deploy.optics import Light, OpticsModel, simple_camera
from tactile_deploy.sensors.config import (
    EffectSpec,
    SensorConfigError,
    VirtualSensorConfig,
    load_sensor_config,
)

OPTICS = OpticsModel(
    camera=simple_camera(160, 120, 0.1, k1=-0.1),
    lights=(Light(name="r", kind="point", position_mm=(0.0, 25.0, -6.0),
                  colour_grey=(230, 25, 20)),),
    ambient_grey=(40.0, 40.0, 45.0))
N = 4


def _config(name: str = "unit") -> VirtualSensorConfig:
    return VirtualSensorConfig(name=name, family="gelslim", optics=OPTICS)


def _arrays(**changes) -> dict:
    """A valid 4-sample .npz layout with ``changes`` (None removes a field)."""
    arrays = {"indenter": np.array(["sphere_r4"] * N), "x_mm": np.zeros(N),
              "y_mm": np.zeros(N), "theta_deg": np.zeros(N), "depth_mm": np.full(N, 0.5),
              "force_n": np.full(N, 1.0), "depth": np.zeros((N, 128, 128), np.float32)}
    arrays.update(changes)
    return {k: v for k, v in arrays.items() if v is not None}


@pytest.fixture
def no_analysis(monkeypatch):
    """The simulator and the analysis fail the test when reached: errors must come first."""
    from tactile_deploy.calibration.discrepancy import workflow
    from tactile_deploy.cli import common

    def reached(*args, **kwargs):
        raise AssertionError("the analysis started before the error was found")

    monkeypatch.setattr(common, "prepare_simulator", reached)
    monkeypatch.setattr(workflow, "find_discrepancy", reached)


def _invoke(*args):
    from tactile_deploy.cli.main import app

    out = CliRunner().invoke(app, ["discrepancy", *map(str, args)])
    text = " ".join(out.output.split())
    assert "Traceback" not in out.output and not isinstance(out.exception, AssertionError), \
        out.output + repr(out.exception)
    return out, text


# ------------------------------------------------------------- versions are never overwritten
def test_apply_never_overwrites_existing_version_files(tmp_path):
    model = tmp_path / "unit.json"
    model.write_text(_config().model_dump_json(indent=2) + "\n")
    first = apply_effect(str(model), load_sensor_config(model),
                         EffectSpec(name="zero_offset", params={"offset_mm": 0.02}), {})
    versions = first.history.parent
    kept = {p.name: p.read_bytes() for p in versions.glob("v*.json")}
    assert sorted(kept) == ["v1.json", "v2.json"]
    # a history that is not readable: the message's advice (move it away) ...
    first.history.write_text("{")
    with pytest.raises(SensorConfigError, match="version files beside it are kept"):
        apply_effect(str(model), load_sensor_config(model),
                     EffectSpec(name="zero_offset", params={"offset_mm": 0.03}), {})
    first.history.rename(tmp_path / "history.json.bak")
    # ... leads to new versions under new numbers, the old files untouched
    second = apply_effect(str(model), load_sensor_config(model),
                          EffectSpec(name="zero_offset", params={"offset_mm": 0.03}), {})
    for name, data in kept.items():
        assert (versions / name).read_bytes() == data, name
    assert second.version == 4 and second.previous.name == "v3.json"
    history = json.loads(second.history.read_text())
    assert [(v["version"], v["file"]) for v in history["versions"]] == [(3, "v3.json"),
                                                                        (4, "v4.json")]
    assert load_sensor_config(model).effects[0].params["offset_mm"] == 0.03


# ------------------------------------------------------------------- malformed measured data
def _write_csv(folder: Path, contact_ids: list[str]) -> None:
    folder.mkdir()
    np.save(folder / "d0.npy", np.zeros((128, 128), np.float32))
    rows = ["indenter,x_mm,y_mm,theta_deg,depth_mm,force_n,depth_file,contact_id"]
    rows += [f"sphere_r4,0,0,,0.5,1,d0.npy,{c}" for c in contact_ids]
    (folder / "contacts.csv").write_text("\n".join(rows) + "\n")


@pytest.mark.parametrize("case,changes,expected", [
    ("object_indenter", {"indenter": np.array(["sphere_r4"] * N, dtype=object)},
     "field 'indenter' cannot be read .*np.array\\(names, dtype=str\\)"),
    ("noise_vector", {"noise_mm": np.array([0.005, 0.005])},
     "field 'noise_mm' must be one number .*got shape \\(2,\\)"),
    ("contact_id_strings", {"contact_id": np.array(["a", "b", "c", "d"])},
     "field 'contact_id' must be integers .*'a' in sample 0"),
])
def test_malformed_npz_is_one_error_line_naming_file_and_field(tmp_path, monkeypatch,
                                                             no_analysis, case, changes,
                                                             expected):
    monkeypatch.chdir(tmp_path)
    np.savez(f"{case}.npz", **_arrays(**changes))
    with pytest.raises(MeasuredDataError, match=f"{case}.npz: {expected}"):
        load_measured(f"{case}.npz")
    out, text = _invoke("--sensor", "gelslim1", "--measured", f"{case}.npz")
    assert out.exit_code == 2 and out.output.startswith("error: "), out.output
    assert f"{case}.npz" in text and "field '" in text


def test_csv_with_an_empty_contact_id_cell_names_the_row(tmp_path, monkeypatch, no_analysis):
    monkeypatch.chdir(tmp_path)
    _write_csv(tmp_path / "m", ["0", "1", "", "3"])
    with pytest.raises(MeasuredDataError, match="contacts.csv, row 4: column 'contact_id' must "
                                                "be an integer, got ''"):
        load_measured("m")
    out, text = _invoke("--sensor", "gelslim1", "--measured", "m")
    assert out.exit_code == 2 and "row 4: column 'contact_id'" in text


def test_unforeseen_loading_errors_are_one_line_too(tmp_path, monkeypatch, no_analysis):
    from tactile_deploy.calibration.discrepancy import measured

    def broken(path):
        raise KeyError("x_mm")

    monkeypatch.setattr(measured, "load_measured", broken)
    monkeypatch.chdir(tmp_path)
    np.savez("m.npz", **_arrays())
    out, text = _invoke("--sensor", "gelslim1", "--measured", "m.npz")
    assert out.exit_code == 2 and text.startswith("error: m.npz: cannot be read")
    assert "KeyError" in text and "docs/discrepancy.md" in text


# ---------------------------------------------------------- nonsense measured data, at load
@pytest.mark.parametrize("changes,expected", [
    ({"depth_mm": np.full(N, -0.5)},
     ("field 'depth_mm' of sample 0 is -0.5 mm, expected a depth in mm pushed into the gel, > 0 .*"
     "positive into the gel")),
    ({"depth_mm": np.zeros(N)}, "field 'depth_mm' of sample 0 is 0 mm, expected"),
    ({"noise_mm": np.float64(0.0)},
     "field 'noise_mm' must be > 0 mm .*null threshold.*got 0.0; give the noise"),
    ({"depth": np.full((N, 128, 128), 450.0, np.float32)},
     ("field 'depth' reaches 450 mm in sample 0, deeper than the 3 mm gel pad: maps must be in mm.*"
     "in um")),
])
def test_nonsense_measured_data_is_refused_at_load(tmp_path, monkeypatch, no_analysis, changes,
                                                   expected):
    monkeypatch.chdir(tmp_path)
    np.savez("m.npz", **_arrays(**changes))
    with pytest.raises(MeasuredDataError, match=f"m.npz: {expected}"):
        load_measured("m.npz")
    out, text = _invoke("--sensor", "gelslim1", "--measured", "m.npz")
    assert out.exit_code == 2 and text.startswith("error: m.npz: field '")


def test_a_partly_given_pose_is_refused_naming_the_sample_and_field(tmp_path, monkeypatch,
                                                                     no_analysis):
    monkeypatch.chdir(tmp_path)
    x = np.zeros(N)
    x[3] = np.nan
    np.savez("m.npz", **_arrays(x_mm=x))
    with pytest.raises(MeasuredDataError, match="sample 3 has y_mm, depth_mm but no x_mm"):
        load_measured("m.npz")
    out, text = _invoke("--sensor", "gelslim1", "--measured", "m.npz")
    assert out.exit_code == 2 and "sample 3 has y_mm, depth_mm but no x_mm" in text
    # all three absent: the contact is estimated, as before
    nan = np.full(N, np.nan)
    np.savez("est.npz", **_arrays(x_mm=nan, y_mm=nan, depth_mm=nan))
    data = load_measured("est.npz")
    assert not any(data.known(i) for i in range(N))


# ------------------------------------------------------------ outputs checked before the work
def test_outputs_are_checked_before_the_analysis(tmp_path, monkeypatch, no_analysis):
    monkeypatch.chdir(tmp_path)
    np.savez("m.npz", **_arrays())
    np.savez("other.npz", **_arrays())
    base = ["--sensor", "gelslim1", "--measured", "m.npz"]
    out, text = _invoke(*base, "--report", "other.npz")
    assert out.exit_code == 2 and "--report other.npz is a file, not a folder" in text
    out, text = _invoke(*base, "--report", "m.npz")
    assert out.exit_code == 2 and "is also an input" in text
    out, text = _invoke(*base, "--apply", "--model-dir", "/nonexist")
    assert out.exit_code == 2 and "folder /nonexist does not exist" in text
    Path("gelslim1.json").write_text("{}")
    out, text = _invoke(*base, "--apply")
    assert out.exit_code == 2 and "gelslim1.json exists already" in text
    rep = Path("rep")
    rep.mkdir()
    (rep / "report.md").write_text("an earlier report")
    out, text = _invoke(*base, "--report", "rep")
    assert out.exit_code == 2
    assert "rep exists: pass --overwrite to replace it, or choose another --report" in text
    (rep / "notes.txt").write_text("mine")
    out, text = _invoke(*base, "--report", "rep", "--overwrite")
    assert out.exit_code == 2 and "rep holds notes.txt, which is not part of a report" in text
    out, text = _invoke(*base, "--report", ".", "--overwrite")
    assert out.exit_code == 2 and "current folder or one above it" in text
    Path("sub").mkdir()
    Path("m.npz").rename("sub/m.npz")
    out, text = _invoke(*[("sub/m.npz" if a == "m.npz" else a) for a in base], "--report", "sub",
                        "--overwrite")
    assert out.exit_code == 2 and "holds sub/m.npz, an input of this command" in text
    assert (rep / "report.md").read_text() == "an earlier report"


def test_a_failed_report_leaves_the_existing_folder_as_it_was(tmp_path, monkeypatch):
    from tactile_deploy.calibration.discrepancy import report

    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "report.md").write_text("an earlier report")

    def half(result, folder):
        (folder / "verdict.json").write_text("{}")
        raise OSError("disk full")

    monkeypatch.setattr(report, "_write_report_files", half)
    with pytest.raises(report.OutputPathError, match="rep exists: pass --overwrite"):
        report.write_report(None, rep)
    (rep / "notes.txt").write_text("the user's")            # not a report's file: never replaced
    with pytest.raises(report.OutputPathError, match="notes.txt, which is not part of a report"):
        report.write_report(None, rep, overwrite=True)
    (rep / "notes.txt").unlink()
    monkeypatch.chdir(rep)
    with pytest.raises(report.OutputPathError, match="current folder"):
        report.write_report(None, ".", overwrite=True)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(OSError, match="disk full"):
        report.write_report(None, rep, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rep"]  # no staging folder left
    assert sorted(p.name for p in rep.iterdir()) == ["report.md"]
    assert (rep / "report.md").read_text() == "an earlier report"


# ----------------------------------------------------------------------- an end-to-end run
def test_report_history_and_verdict_carry_the_real_folds_units_and_data(pad_sim, tmp_path,
                                                                        monkeypatch):
    from tactile_deploy.calibration.discrepancy.synthetic import hidden_effect_data, random_contacts
    from tactile_deploy.sensors.virtual import VirtualSensor

    monkeypatch.chdir(tmp_path)
    cfg = _config()
    Path("unit.json").write_text(cfg.model_dump_json(indent=2) + "\n")
    sensor = VirtualSensor(cfg, simulator=pad_sim)
    contacts = random_contacts(8, 4, radius_mm=7.0, indenters=("sphere_r4", "flat_punch"))
    data = hidden_effect_data(sensor, [EffectSpec(name="zero_offset",
                                                  params={"offset_mm": 0.03})],
                              contacts, 0.005, 4)
    Path("data").mkdir()
    save_measured("data/m.npz", data)
    rep = Path("rep")
    rep.mkdir()
    (rep / "report.md").write_text("an earlier report")
    out, _ = _invoke("--sensor", "unit.json", "--measured", "data/m.npz",
                     "--candidates", "zero_offset,depth_scale,dome", "--null-replicates", "40",
                     "--folds", "3", "--json", "--report", "rep", "--overwrite", "--apply")
    assert out.exit_code == 0, out.output
    doc = json.loads(out.stdout)
    assert doc["verdict"] == "effect" and doc["format_version"] == 2
    assert {"gap_before_mm", "gap_after_mm"} <= set(doc) and "gap_before" not in doc
    assert {"gap_before_fraction", "gap_after_fraction"} <= set(doc["force"])
    assert "gap_before" not in doc["force"]
    assert 0 < doc["force"]["gap_before_fraction"] < 1
    # the report: replaced as a whole, folds as given, no staging folder left
    md = (rep / "report.md").read_text()
    assert "(3-fold, grouped by contact)" in " ".join(md.split()) and "5-fold" not in md
    assert json.loads((rep / "verdict.json").read_text())["gap_before_mm"] == doc["gap_before_mm"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    # the history names the measured data absolutely, with its checksum
    history = json.loads(Path("unit.versions/history.json").read_text())
    reason = history["versions"][-1]["reason"]
    assert reason["measured"] == str((tmp_path / "data" / "m.npz").resolve())
    assert reason["measured_sha256"] == hashlib.sha256(
        Path("data/m.npz").read_bytes()).hexdigest()
    assert reason["gap_before_mm"] == doc["gap_before_mm"]
