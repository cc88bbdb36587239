"""Calibration commands on user mistakes: a clean one-line ``error: ...`` and a non-zero exit,
outputs checked before any work, inputs and existing files never replaced without --overwrite,
and honest figures in what is printed.

Tiny synthetic files where the real data is not needed; the real ball presses
(../shared/data/real/fots_gelsight_ballpress) for the shading summary.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from tactile_deploy.cli.main import app

BALL_RADIUS_MM = 2.35
MM_PER_PX = 1 / 19.58
CONTACTS_HEADER = "depth_file,indenter,x_mm,y_mm,depth_mm,force_n"


def _invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def _error(res, code: int = 2) -> str:
    """The error text of a refused command: exit ``code``, no traceback, one ``error:`` line."""
    assert res.exit_code == code, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("error: ")]
    assert len(lines) == 1, res.output
    return lines[0]


def _write_png(path: Path, img: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), img)
    return path


@pytest.fixture
def tiny(tmp_path):
    """A reference frame and a press folder of two frames, 40 x 32 px, all equal to the
    reference (no contact anywhere)."""
    rng = np.random.default_rng(0)
    ref = rng.integers(60, 200, (32, 40, 3), dtype=np.uint8)
    presses = tmp_path / "presses"
    presses.mkdir()
    for name in ("a.png", "b.png"):
        _write_png(presses / name, ref)
    return _write_png(tmp_path / "ref.png", ref), presses


def _shading_args(reference, presses, out, *extra):
    return ["calibrate", "shading", "--reference", reference, "--presses", presses,
            "--ball-radius-mm", BALL_RADIUS_MM, "--mm-per-px", MM_PER_PX, "--out", out, *extra]


@pytest.fixture
def tiny_model(tmp_path):
    """A valid shading model file for 40 x 32 px frames (a flat table)."""
    from tactile_deploy.imaging.shading import (
        ShadingHeader,
        ShadingModel,
        node_grid_shape,
        save_shading,
    )

    header = ShadingHeader(image_height_px=32, image_width_px=40, mm_per_px=0.05,
                           ball_radius_mm=2.0, bins=4, colour_min=-60.0, colour_max=60.0,
                           saturation_level=250, node_spacing_px=10.0, n_slots=1,
                           offset_inlier_grey=12.0, poisson_weight_x=1.0, poisson_weight_y=1.0,
                           n_presses=2)
    table = np.zeros((*node_grid_shape((32, 40), 10.0), 1, 2), np.float32)
    path = tmp_path / "model.npz"
    save_shading(ShadingModel(header, np.zeros(5 ** 3, np.int64), table), path)
    return path


# ------------------------------------------------------------------ 1. camera --out an input
def test_camera_out_must_be_json_and_not_an_input(tmp_path):
    frames = tmp_path / "dots"
    frames.mkdir()
    ref = _write_png(frames / "reference.png", np.full((30, 40, 3), 90, np.uint8))
    _write_png(frames / "press.png", np.full((30, 40, 3), 120, np.uint8))
    before = ref.read_bytes()
    args = ["calibrate", "camera", "--frames", frames, "--target", "dots", "--pitch-mm", "2.5"]
    msg = _error(_invoke(*args, "--out", ref, "--overwrite"))
    assert "--out" in msg and "reference.png" in msg and ".json" in msg and "'.png'" in msg
    assert ref.read_bytes() == before
    board = tmp_path / "board.json"
    from tactile_deploy.calibration.camera.charuco import CharucoBoardSpec

    board.write_text(CharucoBoardSpec().model_dump_json())
    msg = _error(_invoke("calibrate", "camera", "--frames", frames, "--target", "charuco",
                         "--board", board, "--out", board, "--overwrite"))
    assert "is also an input" in msg and "board.json" in msg
    json.loads(board.read_text())  # untouched
    # an option where the file name should be (`--figure --help`): refused, nothing written
    msg = _error(_invoke(*args, "--out", tmp_path / "m.json", "--figure", "--help"))
    assert "looks like an option" in msg and not (Path.cwd() / "--help").exists()


# ------------------------------------------------------------ 2. existing outputs, duplicates
def test_shading_never_replaces_the_annotations_and_needs_overwrite(tmp_path, tiny):
    reference, presses = tiny
    ann = tmp_path / "mine.csv"
    ann.write_text("img_names,center_x,center_y,radius\na.png,20,16,5\nb.png,21,15,5\n")
    labels = ann.read_text()
    msg = _error(_invoke(*_shading_args(reference, presses, tmp_path / "s.npz", "--annotations",
                                        ann, "--circles-out", ann, "--overwrite")))
    assert "--circles-out" in msg and "mine.csv" in msg and "is also an input" in msg
    assert ann.read_text() == labels
    out = tmp_path / "s.npz"
    out.write_bytes(b"the user's model")
    msg = _error(_invoke(*_shading_args(reference, presses, out)))
    assert "s.npz exists" in msg and "--overwrite" in msg
    assert out.read_bytes() == b"the user's model"
    msg = _error(_invoke(*_shading_args(reference, presses, tmp_path / "t.npz", "--circles-out",
                                        tmp_path / "t.npz")))
    assert "--out and --circles-out" in msg


def test_camera_fem_and_board_outputs_need_overwrite(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    _write_png(frames / "reference.png", np.full((30, 40, 3), 90, np.uint8))
    _write_png(frames / "press.png", np.full((30, 40, 3), 120, np.uint8))
    mapping = tmp_path / "m.json"
    mapping.write_text("{}")
    msg = _error(_invoke("calibrate", "camera", "--frames", frames, "--target", "dots",
                         "--pitch-mm", "2.5", "--out", mapping))
    assert "m.json exists: pass --overwrite" in msg
    board = tmp_path / "board.png"
    board.write_bytes(b"mine")
    msg = _error(_invoke("calibrate", "make-board", "--out", board))
    assert "board.png exists: pass --overwrite" in msg and board.read_bytes() == b"mine"
    contacts = tmp_path / "c.csv"
    contacts.write_text(CONTACTS_HEADER + "\n")
    fem = tmp_path / "fem.json"
    fem.write_text("{}")
    msg = _error(_invoke("calibrate", "fem", "--contacts", contacts, "--out", fem))
    assert "fem.json exists: pass --overwrite" in msg and fem.read_text() == "{}"


def test_rig_simulate_does_not_replace_a_config(tmp_path):
    cfg = tmp_path / "myrig.json"
    cfg.write_text('{"edited": true}')
    res = _invoke("rig", "simulate", "--duration-s", "0.01", "--write-config", cfg)
    assert "myrig.json exists: pass --overwrite" in _error(res, 1)
    assert cfg.read_text() == '{"edited": true}'
    res = _invoke("rig", "simulate", "--duration-s", "0.01", "--config", cfg, "--write-config",
                  cfg, "--overwrite")
    assert "is also an input" in _error(res, 1)
    assert cfg.read_text() == '{"edited": true}'


def test_depth_refuses_duplicate_names_and_existing_maps_before_work(tmp_path, tiny_model):
    img = np.full((32, 40, 3), 100, np.uint8)
    for folder in ("A", "B"):
        (tmp_path / folder).mkdir()
        _write_png(tmp_path / folder / "x.png", img)
    ref = _write_png(tmp_path / "ref.png", img)
    out = tmp_path / "dcoll"
    common = ["--shading", tiny_model, "--reference", ref, "--out", out]
    msg = _error(_invoke("depth", tmp_path / "A" / "x.png", tmp_path / "B" / "x.png", *common))
    assert "A/x.png" in msg and "B/x.png" in msg and "x.npy" in msg
    assert not out.exists()
    out.mkdir()
    np.save(out / "x.npy", np.ones(3))
    msg = _error(_invoke("depth", tmp_path / "A" / "x.png", *common))
    assert "x.npy exists: pass --overwrite" in msg
    assert np.array_equal(np.load(out / "x.npy"), np.ones(3))
    res = _invoke("depth", tmp_path / "A" / "x.png", *common, "--overwrite")
    assert res.exit_code == 0, res.output
    assert np.load(out / "x.npy").shape == (32, 40)


# ------------------------------------------------------------------- 3./4. calibrate fem
def _contacts(tmp_path, *rows) -> Path:
    np.save(tmp_path / "z.npy", np.zeros((128, 128)))
    path = tmp_path / "contacts.csv"
    path.write_text("\n".join([CONTACTS_HEADER, *rows]) + "\n")
    return path


@pytest.mark.parametrize("row, field", [
    ("z.npy,sphere_r4,0,0,0.5,-0.3", "force_n"),
    ("z.npy,sphere_r4,0,0,0.5,0", "force_n"),
    ("z.npy,sphere_r4,0,0,0,0.3", "depth_mm"),
    ("z.npy,sphere_r4,0,0,-0.2,0.3", "depth_mm"),
])
def test_fem_refuses_non_positive_forces_and_depths(tmp_path, row, field):
    msg = _error(_invoke("calibrate", "fem", "--contacts", _contacts(tmp_path, row)))
    assert f"contacts.csv, line 2: field '{field}' must be > 0" in msg


def test_fem_refuses_unknown_indenters_while_reading(tmp_path):
    msg = _error(_invoke("calibrate", "fem", "--contacts",
                         _contacts(tmp_path, "z.npy,sphere_r4,0,0,0.5,0.3",
                                   "z.npy,nosuch,0,0,0.5,0.3")))
    assert "contacts.csv, line 3: field 'indenter'" in msg and "'nosuch'" in msg
    assert "sphere_r4" in msg and "tactile-deploy indenters list" in msg


def test_fem_contacts_with_byte_order_mark(tmp_path):
    from tactile_deploy.calibration.fem_command import read_contacts

    path = _contacts(tmp_path, "z.npy,sphere_r4,0,0,0.5,0.3")
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    (contact,) = read_contacts(path)
    assert contact.force_n == 0.3 and contact.pose.depth_mm == 0.5


@pytest.fixture
def fake_fem(monkeypatch):
    """``calibrate fem`` with the FEM replaced: records the nu grid, returns ``result``."""
    from tactile_deploy.calibration.fem_fit import fit, operator_bank

    seen = {}

    def bank(mesh, friction="frictionless", grid_nu=()):
        seen["grid_nu"] = grid_nu
        return object()

    def fitted(contacts, *args, **kwargs):
        return seen["result"]

    monkeypatch.setattr(operator_bank, "OperatorBank", bank)
    monkeypatch.setattr(fit, "fit_fem_parameters", fitted)
    return seen


def _result(**changes):
    from tactile_deploy.calibration.fem_fit.fit import FemFitResult

    base = {"nu": 0.48, "nu_std": 0.0, "E_mpa": 0.3, "E_std_mpa": 0.0,
            "E_note": "from 1 measured forces", "friction": "frictionless",
            "friction_note": "only one contact law was tried", "method": "brent",
            "evaluations": 1, "rmse_mm": 0.001, "poses": [], "objective_curve": None,
            "nu_note": "fixed at 0.48: the operator bank has one node (give several to fit it)",
            "depth_offset_mm": None}
    return FemFitResult(**{**base, **changes})


def test_fem_prints_no_zero_spreads_and_fixes_nu_by_default(tmp_path, fake_fem):
    fake_fem["result"] = _result()
    out = tmp_path / "fem.json"
    res = _invoke("calibrate", "fem", "--contacts",
                  _contacts(tmp_path, "z.npy,sphere_r4,0,0,0.5,0.3"), "--out", out)
    assert res.exit_code == 0, res.output
    assert fake_fem["grid_nu"] == (0.48,)       # nu fixed, as docs/calibration.md says
    assert "+- 0.0000" not in res.output
    assert "nu = 0.4800 (fixed" in res.output
    assert "E = 0.3000 MPa (one force: no spread" in res.output
    doc = json.loads(out.read_text())
    assert doc["nu_std"] is None and doc["E_std_mpa"] is None and doc["E_mpa"] == 0.3


@pytest.mark.parametrize("E", [float("nan"), -0.3])
def test_fem_writes_no_non_finite_or_negative_E(tmp_path, fake_fem, E):
    fake_fem["result"] = _result(E_mpa=E)
    out = tmp_path / "fem.json"
    msg = _error(_invoke("calibrate", "fem", "--contacts",
                         _contacts(tmp_path, "z.npy,sphere_r4,0,0,0.5,0.3"), "--out", out))
    assert "nothing written" in msg and "E = " in msg
    assert not out.exists()


def test_docs_say_the_fem_command_fixes_nu():
    doc = (Path(__file__).resolve().parent.parent / "docs" / "calibration.md").read_text()
    assert "[--nu-grid 0.48]" in doc and "0.40,0.43,0.46,0.49]" not in doc


# ------------------------------------------------------------------------------- 5. wizard
def test_wizard_source_that_cannot_open_writes_no_state(tmp_path):
    work = tmp_path / "unit8.calibration"
    res = _invoke("calibrate", "--sensor", "unit8", "--source", tmp_path / "nosuch.npz",
                  "--rig", "/dev/no-such-stage", "--gauge", "/dev/no-such-gauge", "--yes",
                  "--out", tmp_path / "unit8")
    msg = _error(res)
    assert "nosuch.npz" in msg and "--source" in msg
    assert not work.exists()
    res = _invoke("calibrate", "--sensor", "unit9", "--source", "virtual:nosuch", "--yes",
                  "--out", tmp_path / "unit9")
    assert "gelslim1" in _error(res)
    assert not (tmp_path / "unit9.calibration").exists()


# ------------------------------------------------------------- 6. tracebacks on user mistakes
def test_annotations_with_spaces_and_byte_order_mark(tmp_path):
    from tactile_deploy.calibration.shading.presses import read_annotations

    p = tmp_path / "ann.csv"
    p.write_bytes(b"\xef\xbb\xbfimg_names, center_x, center_y, radius\r\n"
                  b"0001.png, 76, 182, 38\r\n0002.png, 81, 197, 40\r\n")
    assert read_annotations(p) == {"0001.png": (76.0, 182.0, 38.0),
                                   "0002.png": (81.0, 197.0, 40.0)}


def test_missing_output_folders_are_named_up_front(tmp_path, tiny):
    reference, presses = tiny
    nodir = tmp_path / "nodir"
    frames = tmp_path / "frames"
    frames.mkdir()
    _write_png(frames / "reference.png", np.full((30, 40, 3), 90, np.uint8))
    _write_png(frames / "press.png", np.full((30, 40, 3), 120, np.uint8))
    camera = ["calibrate", "camera", "--frames", frames, "--target", "dots", "--pitch-mm", "2.5"]
    cases = [
        (_shading_args(reference, presses, tmp_path / "s.npz", "--circles-out",
                       nodir / "c.csv"), "--circles-out", 2),
        ([*camera, "--out", nodir / "m.json"], "--out", 2),
        ([*camera, "--out", tmp_path / "m.json", "--figure", nodir / "f.png"], "--figure", 2),
        (["calibrate", "fem", "--contacts", tmp_path / "c.csv", "--out", nodir / "f.json"],
         "--out", 2),
        (["calibrate", "make-board", "--out", nodir / "b.png"], "--out", 2),
        (["rig", "simulate", "--duration-s", "0.01", "--write-config", nodir / "r.json"],
         "--write-config", 1),
    ]
    for args, option, code in cases:
        msg = _error(_invoke(*args), code)
        assert option in msg and f"folder {nodir} does not exist" in msg and "create it" in msg
    assert not (tmp_path / "s.npz").exists() and not (tmp_path / "m.json").exists()


def test_output_paths_of_the_wrong_kind(tmp_path, tiny, tiny_model):
    reference, presses = tiny
    (tmp_path / "X.npz").mkdir()
    msg = _error(_invoke(*_shading_args(reference, presses, tmp_path / "X.npz")))
    assert "X.npz is a folder" in msg
    afile = tmp_path / "afile"
    afile.write_text("keep")
    msg = _error(_invoke("depth", reference, "--shading", tiny_model, "--reference", reference,
                         "--out", afile))
    assert "--out" in msg and "afile is a file" in msg and afile.read_text() == "keep"
    msg = _error(_invoke("calibrate", "make-board", "--out", tmp_path / "board.jpg"))
    assert "must end in .png" in msg and "'.jpg'" in msg


def test_rig_config_that_is_an_image(tmp_path):
    png = _write_png(tmp_path / "ref.png", np.zeros((8, 8, 3), np.uint8))
    res = _invoke("rig", "press", "--config", png, "--x-mm", "0", "--y-mm", "0",
                  "--depth-mm", "1")
    msg = _error(res, 1)
    assert "ref.png: not a text file" in msg and "rig config" in msg


@pytest.mark.parametrize("option, value", [("--ball-radius-mm", "inf"),
                                           ("--ball-radius-mm", "nan"),
                                           ("--mm-per-px", "inf")])
def test_shading_scales_must_be_finite(tmp_path, tiny, option, value):
    reference, presses = tiny
    args = _shading_args(reference, presses, tmp_path / "s.npz")
    args[args.index(option) + 1] = value
    msg = _error(_invoke(*args))
    assert option in msg and "finite" in msg and value in msg


def test_shading_folds_are_checked_before_the_model_is_written(tmp_path, shared_data):
    data = shared_data / "real" / "fots_gelsight_ballpress"
    out = tmp_path / "s.npz"
    msg = _error(_invoke(*_shading_args(data / "background.png", data, out, "--annotations",
                                        data / "annotate.csv", "--folds", "1")))
    assert "--folds" in msg and "got 1" in msg
    assert not out.exists()
    # more folds than presses: known only once the presses are read, still before the fit
    msg = _error(_invoke(*_shading_args(data / "background.png", data, out, "--annotations",
                                        data / "annotate.csv", "--folds", "99")))
    assert "--folds must lie in [2, 42]" in msg and "got 99" in msg
    assert not out.exists()


# ------------------------------------------------------------------------------ 7. messages
def test_detection_failure_names_the_image(tmp_path, tiny):
    reference, presses = tiny
    msg = _error(_invoke(*_shading_args(reference, presses, tmp_path / "s.npz")))
    assert "a.png" in msg and "no contact" in msg and "--annotations" in msg


def test_depth_messages_name_the_files(tmp_path, tiny_model):
    ok = _write_png(tmp_path / "ok.png", np.full((32, 40, 3), 100, np.uint8))
    small = _write_png(tmp_path / "small.png", np.full((30, 20, 3), 100, np.uint8))
    out = tmp_path / "d"
    msg = _error(_invoke("depth", ok, "--shading", tiny_model, "--reference", small,
                         "--out", out))
    assert "small.png" in msg and "model.npz" in msg and "20x30" in msg and "40x32" in msg
    msg = _error(_invoke("depth", small, "--shading", tiny_model, "--reference", ok,
                         "--out", out))
    assert "small.png" in msg and "model.npz" in msg
    csv = tmp_path / "a3.csv"
    csv.write_text("a,b\n1,2\n")
    msg = _error(_invoke("depth", ok, "--shading", csv, "--reference", ok, "--out", out))
    assert "a3.csv" in msg and "not a shading model" in msg and "calibrate shading" in msg
    assert "allow_pickle" not in msg
    notimg = tmp_path / "notimg.png"
    notimg.write_text("hello")
    msg = _error(_invoke("depth", notimg, "--shading", tiny_model, "--reference", ok,
                         "--out", out))
    assert msg.count("notimg.png") == 1
    folder = tmp_path / "p3"
    folder.mkdir()
    msg = _error(_invoke("depth", ok, folder, "--shading", tiny_model, "--reference", ok,
                         "--out", out))
    assert "p3 is a folder" in msg
    assert not out.exists()


# ----------------------------------------------------------------- 8. in-sample figure label
def test_shading_summary_labels_the_in_sample_residual(tmp_path, shared_data):
    data = shared_data / "real" / "fots_gelsight_ballpress"
    presses = tmp_path / "presses"
    presses.mkdir()
    rows = (data / "annotate.csv").read_text().splitlines()
    for name in ("0001.png", "0002.png", "0003.png", "0004.png"):
        (presses / name).write_bytes((data / name).read_bytes())
    ann = tmp_path / "ann.csv"
    ann.write_text("\n".join(rows[:5]) + "\n")
    res = _invoke(*_shading_args(data / "background.png", presses, tmp_path / "s.npz",
                                 "--annotations", ann))
    assert res.exit_code == 0, res.output
    assert "in-sample sphere residual" not in res.output
    assert "in-sample fit residual" in res.output and "not an accuracy figure" in res.output
    assert "--folds N" in res.output


# ------------------------------------------------------------------------------ 9./10. rig
def test_rig_press_deeper_than_the_pad_is_refused():
    from tactile_deploy.calibration.rig import rig_config_from_dict
    from tactile_deploy.calibration.rig.indent import PAD_THICKNESS_MM, IndentationRig
    from tactile_deploy.pad.geometry import PadGeometry

    assert PAD_THICKNESS_MM == PadGeometry().thickness_mm
    res = _invoke("rig", "press", "--stage", "/dev/no-such-port", "--gauge", "/dev/no-such-port",
                  "--x-mm", "0", "--y-mm", "0", "--depth-mm", "5")
    msg = _error(res, 1)
    assert "--depth-mm" in msg and "5 mm" in msg and f"{PAD_THICKNESS_MM:g} mm gel pad" in msg

    class Stage:
        def __init__(self):
            self.moves = []

        def check_limits(self, *point):
            pass

        def move_to(self, **target):
            self.moves.append(target)

    cfg = rig_config_from_dict({"stage": {"port": "x"}, "gauge": {"port": "y"}})
    stage = Stage()
    rig = IndentationRig(cfg, stage=stage, gauge=object())
    with pytest.raises(ValueError, match="gel pad"):
        rig.press(0.0, 0.0, PAD_THICKNESS_MM + 2)
    assert stage.moves == []


def test_rig_simulate_prints_a_runnable_press_command(tmp_path):
    res = _invoke("rig", "simulate", "--duration-s", "0.01")
    assert res.exit_code == 0, res.output
    hint = next(ln for ln in res.output.splitlines() if ln.startswith("try: "))
    assert hint.startswith("try: tactile-deploy rig press --stage /dev/")
    assert "--gauge /dev/" in hint and "--depth-mm 1" in hint
    cfg = tmp_path / "sim.json"
    res = _invoke("rig", "simulate", "--duration-s", "0.01", "--write-config", cfg)
    assert res.exit_code == 0, res.output
    assert f"try: tactile-deploy rig press --config {cfg} " in res.output
    assert math.isfinite(json.loads(cfg.read_text())["force_limit_n"])
