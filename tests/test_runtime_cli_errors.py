"""User mistakes and awkward set-ups of the runtime commands: mesh formats and pads of `pad
export`, image folders of any common suffix, `plugins copy` naming, wrongly typed manifest
fields, out-of-range publish ports, and an operator cache that cannot be written."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from tactile_deploy.cli.main import app

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ROOT / "plugins" / "gelslim2"
runner = CliRunner()


def _clean_error(res, code: int = 2) -> str:
    """The output of a refused command: the given exit code, an `error:` line, no traceback."""
    assert res.exit_code == code, res.output
    assert isinstance(res.exception, SystemExit), res.exception
    assert "error:" in res.output and "Traceback" not in res.output
    return " ".join(res.output.split())


# ------------------------------------------------------------------------------------ pad export
def test_pad_export_offers_only_formats_it_writes(tmp_path):
    help_text = runner.invoke(app, ["pad", "export", "--help"]).output
    assert "xdmf" not in help_text
    res = runner.invoke(app, ["pad", "export", "--out", str(tmp_path / "pad.xdmf")])
    text = _clean_error(res)
    assert "'.xdmf'" in text and ".vtu" in text and ".stl" in text
    assert not list(tmp_path.iterdir())                         # nothing written, nothing partial


def test_pad_export_writes_glb_in_metres_and_the_rest_in_mm(tmp_path):
    import trimesh

    from tactile_deploy.pad.asset import load_pad

    radius_mm = float(np.abs(load_pad().vertices[:, 0]).max())
    for suffix, unit in ((".glb", 1e-3), (".ply", 1.0)):
        out = tmp_path / f"pad{suffix}"
        assert runner.invoke(app, ["pad", "export", "--out", str(out)]).exit_code == 0
        mesh = trimesh.load(out, force="mesh", process=False)
        assert np.abs(mesh.vertices[:, 0]).max() == pytest.approx(radius_mm * unit, rel=1e-6)


def test_pad_export_unknown_pad_lists_the_shipped_ones(tmp_path):
    for args in (["pad", "export", "--out", str(tmp_path / "p.vtu"), "--pad", "nosuch"],
                 ["pad", "info", "--pad", "nosuch"]):
        text = _clean_error(runner.invoke(app, args))
        assert "'nosuch'" in text and "gelslim" in text
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------------ image folders
def _write_frames(folder: Path, names: list[str]) -> list[np.ndarray]:
    folder.mkdir(exist_ok=True)
    frames = []
    for name in names:                                  # grey level: 40 x rank in name order
        img = np.full((24, 32, 3), 40 * sorted(names).index(name), np.uint8)
        cv2.imwrite(str(folder / name), img)
        frames.append(img)
    return frames


def test_image_folder_reads_every_common_image_suffix_in_name_order(tmp_path):
    from tactile_deploy.runtime.sources.config import parse_source
    from tactile_deploy.runtime.sources.factory import make_source

    _write_frames(tmp_path, ["c.bmp", "a.jpg", "b.JPEG", "d.png", "e.tif", "f.tiff"])
    (tmp_path / "notes.txt").write_text("not a frame")
    with make_source(parse_source(str(tmp_path))) as src:
        got = list(src)
    assert len(got) == 6 and [f.index for f in got] == list(range(6))
    assert src.unreadable_files == [] and src.stats.unreadable == 0
    levels = [int(f.image[0, 0, 0]) for f in got]
    assert levels == [0, 40, 80, 120, 160, 200]                 # a, b, c, d, e, f


def test_image_folder_explicit_pattern_and_no_images(tmp_path):
    from tactile_deploy.runtime.sources.base import SourceError
    from tactile_deploy.runtime.sources.config import ImageFolderSourceConfig
    from tactile_deploy.runtime.sources.factory import make_source

    _write_frames(tmp_path, ["a.jpg", "b.png", "c.png"])
    with make_source(ImageFolderSourceConfig(path=str(tmp_path), pattern="*.png")) as src:
        assert len(list(src)) == 2
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("x")
    with pytest.raises(SourceError, match=r"no image files \(\.png, \.jpg"):
        make_source(ImageFolderSourceConfig(path=str(empty))).connect()


def test_image_folder_names_its_unreadable_files(tmp_path, caplog):
    from tactile_deploy.runtime.sources.config import ImageFolderSourceConfig
    from tactile_deploy.runtime.sources.factory import make_source

    _write_frames(tmp_path, ["a.jpg", "c.jpg"])
    (tmp_path / "b.jpg").write_bytes(b"\xff\xd8 truncated jpeg")
    with caplog.at_level(logging.WARNING), make_source(
            ImageFolderSourceConfig(path=str(tmp_path), loop=True)) as src:
        got = [src.read() for _ in range(5)]                    # loops: b.jpg met twice
    assert all(f is not None for f in got)
    assert src.unreadable_files == ["b.jpg"] and src.stats.unreadable == 2


def test_run_accepts_a_folder_of_jpg_frames(tmp_path):
    from test_runtime_support import build_test_plugin

    from tactile_deploy.runtime.sources.npz import load_clip

    plugin = build_test_plugin(tmp_path / "testsensor", n_frames=3)
    frames, _, _ = load_clip(plugin.demo_clip_path())
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, rgb in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:04d}.jpg"), cv2.cvtColor(np.asarray(rgb), cv2.COLOR_RGB2BGR))
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--source", str(folder),
                              "--no-forces"])
    assert res.exit_code == 0, res.output
    assert "no files match" not in res.output


# ------------------------------------------------------------------------------------ plugins copy
def test_plugins_copy_names_the_copy_after_its_folder(tmp_path, monkeypatch, caplog):
    from tactile_deploy.runtime.plugins import PLUGIN_PATH_ENV, SensorPlugin, load_manifest

    res = runner.invoke(app, ["plugins", "copy", "gelslim2", str(tmp_path / "mycopy")])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "as plugin 'mycopy'" in text and "mesh/mycopy" in text
    assert "shadows no other plugin" in text and "shadows the original" not in text
    assert load_manifest(tmp_path / "mycopy").name == "mycopy"

    res = runner.invoke(app, ["plugins", "copy", "gelslim2", str(tmp_path / "gelslim2")])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "as plugin 'gelslim2'" in text and "shadows the plugin 'gelslim2'" in text
    assert str(SHIPPED) in text

    monkeypatch.setenv(PLUGIN_PATH_ENV, str(tmp_path))
    with caplog.at_level(logging.WARNING):
        mine, same = SensorPlugin.load("mycopy"), SensorPlugin.load("gelslim2")
    assert "manifest name" not in caplog.text                  # no mismatch warning on use
    assert mine.name == "mycopy" and mine.folder == tmp_path / "mycopy"
    assert same.folder == tmp_path / "gelslim2"                 # shadows the shipped one
    # `--source virtual` on the renamed copy: the virtual sensor it was calibrated on
    from tactile_deploy.runtime.sources.config import parse_source
    from tactile_deploy.runtime.sources.factory import make_source

    assert make_source(parse_source("virtual"), mine).sensor_name == "gelslim2"

    text = _clean_error(runner.invoke(app, ["plugins", "copy", "gelslim2", str(tmp_path / "My Copy")]))
    assert "'My Copy'" in text and "field 'name'" in text
    assert not (tmp_path / "My Copy").exists()


# ------------------------------------------------------------------------------------ manifest types
@pytest.mark.parametrize("edit, field", [
    (lambda d: d["material"].update(E_mpa="0.3"), "material.E_mpa"),
    (lambda d: d["family"].update(pad_version="1"), "family.pad_version"),
    (lambda d: d["default_source"].update(loop="yes"), "default_source.demo.loop"),
    (lambda d: d["camera"].update(image_width_px=640.0), "camera.image_width_px"),
])
def test_wrongly_typed_manifest_fields_are_refused(tmp_path, edit, field):
    doc = json.loads((SHIPPED / "plugin.json").read_text())
    edit(doc)
    folder = tmp_path / "broken"
    folder.mkdir()
    (folder / "plugin.json").write_text(json.dumps(doc, indent=2))
    res = runner.invoke(app, ["plugins", "validate", str(folder), "--no-model"])
    text = _clean_error(res, code=1)
    assert f"field '{field}'" in text


def test_manifest_takes_json_integers_for_numbers_and_arrays_for_tuples(tmp_path):
    from tactile_deploy.runtime.plugins import load_manifest

    doc = json.loads((SHIPPED / "plugin.json").read_text())
    doc["material"]["E_mpa"] = 1
    assert isinstance(doc["camera"]["homography_px_to_mm"], list)
    (tmp_path / "plugin.json").write_text(json.dumps(doc))
    m = load_manifest(tmp_path)
    assert m.material.E_mpa == 1.0 and isinstance(m.camera.homography_px_to_mm, tuple)


# ------------------------------------------------------------------------------------ publish
@pytest.mark.parametrize("address", ["tcp://*:99999", "tcp://*:0", "tcp://127.0.0.1:65536",
                                     "tcp://*:port", "tcp://*"])
def test_publish_refuses_ports_zeromq_would_change(address):
    from tactile_deploy.runtime.publish import MeshPublisher, PublishError

    with pytest.raises(PublishError, match="cannot publish on"):
        MeshPublisher(address, "testsensor", topology=None)


def test_publish_still_binds_any_free_port():
    from tactile_deploy.runtime.publish import check_address

    for address in ("tcp://*:5555", "tcp://127.0.0.1:*", "tcp://[::1]:65535", "ipc:///tmp/x.sock"):
        check_address(address)


# ------------------------------------------------------------------------------------ cache
@pytest.fixture()
def small_mesh():
    from tactile_deploy.pad.geometry import PadGeometry
    from tactile_deploy.pad.mesh import build_pad_mesh

    return build_pad_mesh(PadGeometry(name="small", radius_mm=5.0, edge_mm=1.0, n_layers=2))


@pytest.fixture()
def fresh_warning(monkeypatch):
    from tactile_deploy.fem import simulator

    monkeypatch.setattr(simulator, "_cache_warned", False, raising=False)


def test_a_cache_folder_that_cannot_be_made_warns_once_and_keeps_the_result(
        tmp_path, monkeypatch, caplog, small_mesh, fresh_warning):
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.runtime.forces import SurfaceStiffness

    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("TACTILE_DEPLOY_CACHE_DIR", str(blocker / "cache"))
    with caplog.at_level(logging.WARNING):
        stiff = SurfaceStiffness.for_pad(small_mesh, 0.45)
        sim = ContactSimulator(small_mesh, Material(nu=0.45), assembly="numpy")
        assert sim.prepare() is True
    assert stiff.matrix.shape == (len(stiff.nodes),) * 2 and np.all(np.isfinite(stiff.matrix))
    assert sim.compliance.shape[0] == sim.n_operator_columns
    warnings = [r.getMessage() for r in caplog.records if "cannot write the cache" in r.getMessage()]
    assert len(warnings) == 1 and str(blocker / "cache") in warnings[0]
    assert "TACTILE_DEPLOY_CACHE_DIR" in warnings[0]


def test_a_read_only_cache_folder_warns_and_keeps_the_result(tmp_path, monkeypatch, caplog,
                                                             small_mesh, fresh_warning):
    from tactile_deploy.fem import simulator
    from tactile_deploy.runtime.forces import SurfaceStiffness

    def refuse(path):
        raise PermissionError(13, "Permission denied", str(path))

    cache = tmp_path / "cache"
    cache.mkdir()
    monkeypatch.setenv("TACTILE_DEPLOY_CACHE_DIR", str(cache))
    monkeypatch.setattr(simulator, "atomic_path", refuse)   # as a read-only folder
    with caplog.at_level(logging.WARNING):
        stiff = SurfaceStiffness.for_pad(small_mesh, 0.45)
    assert np.all(np.isfinite(stiff.matrix)) and not list(cache.iterdir())
    assert "cannot write the cache in" in caplog.text and "Permission denied" in caplog.text
