"""Sensor plugins: manifest validation, committed schema, registry (folders, search path, entry
points with code hooks), the `plugins` commands, and every kind of broken plugin."""

from __future__ import annotations

import json
import shutil
import textwrap
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pytest
from test_runtime_support import blob_frame, build_linear_onnx, build_test_plugin
from typer.testing import CliRunner

from tactile_deploy.cli.main import app
from tactile_deploy.checksums import file_sha256
from tactile_deploy.runtime.plugins import discovery as plugins_mod
from tactile_deploy.runtime.plugins import (
    PLUGIN_PATH_ENV,
    PluginError,
    PluginManifest,
    SensorPlugin,
    discover_plugins,
    find_plugin,
    load_manifest,
    validate_plugin,
)
from tactile_deploy.pad.topology import MeshTopology

runner = CliRunner()


@pytest.fixture(scope="module")
def plugin_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("plugins")
    build_test_plugin(root / "testsensor")
    return root / "testsensor"


@pytest.fixture
def plugin_copy(plugin_dir, tmp_path) -> Path:
    """A private copy to break (the model is shared through its absolute path)."""
    dst = tmp_path / "testsensor"
    shutil.copytree(plugin_dir, dst)
    return dst


def _manifest_doc(folder: Path) -> dict:
    return json.loads((folder / "plugin.json").read_text())


def _write_doc(folder: Path, doc: dict) -> None:
    (folder / "plugin.json").write_text(json.dumps(doc, indent=2))


# ------------------------------------------------------------------------------------ manifest
def test_valid_plugin_passes_every_check(plugin_dir):
    report = validate_plugin(plugin_dir)
    assert report.ok, report.problems
    for item in ("manifest", "model checksum", "pad mesh hash", "shading model", "demo clip",
                 "topology", "model contract"):
        assert item in report.checked


def test_manifest_round_trip_and_strictness(plugin_dir, tmp_path):
    doc = _manifest_doc(plugin_dir)
    m = PluginManifest.model_validate(doc)
    assert m.name == "testsensor" and m.noise_reference.handling == "subtract"
    assert m.default_source.kind == "demo"
    bad = dict(doc, colour="blue")
    with pytest.raises(Exception, match="colour"):
        PluginManifest.model_validate(bad)


@pytest.mark.parametrize("edit, field, expected", [
    (lambda d: d["material"].update(E_mpa=-1.0), "material.E_mpa", "greater than 0"),
    (lambda d: d["model"].update(sha256="xyz"), "model.sha256", "pattern"),
    (lambda d: d["noise_reference"].update(handling="ignore"), "noise_reference.handling", "subtract"),
    (lambda d: d["depth_grid"].update(nx=64), "depth_grid", "model grid"),
    (lambda d: d["default_source"].update(kind="radio"), "default_source", "radio"),
    (lambda d: d["camera"].update(mm_per_px_x=0.5), "camera", "does not match"),
])
def test_invalid_manifest_fields_are_named(plugin_copy, edit, field, expected):
    doc = _manifest_doc(plugin_copy)
    edit(doc)
    _write_doc(plugin_copy, doc)
    with pytest.raises(PluginError) as e:
        load_manifest(plugin_copy)
    msg = str(e.value)
    assert str(plugin_copy / "plugin.json") in msg and field in msg and expected in msg


def test_manifest_not_json_or_wrong_version(plugin_copy):
    (plugin_copy / "plugin.json").write_text("{ not json")
    with pytest.raises(PluginError, match="not valid JSON"):
        load_manifest(plugin_copy)
    (plugin_copy / "plugin.json").write_text(json.dumps({"format_version": 7}))
    with pytest.raises(PluginError, match="reads version 1, the file has 7"):
        load_manifest(plugin_copy)
    (plugin_copy / "plugin.json").unlink()
    with pytest.raises(PluginError, match="not found"):
        load_manifest(plugin_copy)


# ------------------------------------------------------------------------------------ files
def test_missing_file_is_reported_with_field_and_path(plugin_copy):
    (plugin_copy / "shading.npz").unlink()
    report = validate_plugin(plugin_copy, check_model=False)
    assert not report.ok
    assert any("'shading.path'" in p and "does not exist" in p for p in report.problems)
    with pytest.raises(PluginError, match="does not exist"):
        _ = SensorPlugin.load(plugin_copy).shading_model


def test_changed_file_fails_its_checksum(plugin_copy):
    ref = plugin_copy / "reference.png"
    data = bytearray(ref.read_bytes())
    data[-20] ^= 0xFF
    ref.write_bytes(bytes(data))
    plugin = SensorPlugin.load(plugin_copy)
    with pytest.raises(PluginError) as e:
        _ = plugin.reference_frame
    assert "reference_frame.sha256" in str(e.value) and "expected" in str(e.value)


def test_corrupt_files_with_matching_checksums_are_refused(plugin_copy):
    """A file replaced by garbage and the checksum updated (a careless rebuild): the loader
    still refuses it, naming the file."""
    doc = _manifest_doc(plugin_copy)
    for key, name in (("shading", "shading.npz"), ("noise_reference", "noise_reference.npy"),
                      ("demo_clip", "demo.npz"), ("model", "broken.onnx")):
        p = plugin_copy / name
        p.write_bytes(b"garbage" * 10)
        doc[key]["path"] = name
        doc[key]["sha256"] = file_sha256(p)
    _write_doc(plugin_copy, doc)
    report = validate_plugin(plugin_copy)
    text = "\n".join(report.problems)
    assert "shading.npz: not a readable .npz" in text
    assert "noise reference" in text and "not a readable .npy" in text
    assert "demo.npz: not a readable .npz" in text
    assert "broken.onnx" in text and "cannot load it" in text


def test_wrong_shapes_are_refused(plugin_copy):
    doc = _manifest_doc(plugin_copy)
    np.save(plugin_copy / "noise_reference.npy", np.zeros((64, 64), np.float32))
    doc["noise_reference"]["sha256"] = file_sha256(plugin_copy / "noise_reference.npy")
    _write_doc(plugin_copy, doc)
    report = validate_plugin(plugin_copy, check_model=False)
    assert any("must be a (128, 128) float depth map" in p and "(64, 64)" in p
               for p in report.problems)


def test_model_for_another_mesh_is_refused(plugin_copy):
    topo = MeshTopology.from_pad()
    other = plugin_copy / "other_mesh.onnx"
    build_linear_onnx(other, topo, mesh_hash="0" * 64)
    doc = _manifest_doc(plugin_copy)
    doc["model"] = {"path": "other_mesh.onnx", "sha256": file_sha256(other)}
    _write_doc(plugin_copy, doc)
    report = validate_plugin(plugin_copy)
    assert any("mesh hash 0000000000000000... differs from the sensor family's pad mesh" in p
               for p in report.problems)
    from tactile_deploy.runtime.predictor import MeshPredictor, ModelContractError

    with pytest.raises(ModelContractError, match="trained for another mesh"):
        MeshPredictor.from_plugin(plugin_copy)


def test_model_with_wrong_input_name_is_refused(plugin_copy):
    topo = MeshTopology.from_pad()
    p = plugin_copy / "renamed.onnx"
    build_linear_onnx(p, topo, input_name="image")
    doc = _manifest_doc(plugin_copy)
    doc["model"] = {"path": "renamed.onnx", "sha256": file_sha256(p)}
    _write_doc(plugin_copy, doc)
    report = validate_plugin(plugin_copy)
    assert any("expected an input named 'depth', the model has ['image']" in p
               for p in report.problems)


def test_family_hash_of_another_pad_is_refused(plugin_copy):
    doc = _manifest_doc(plugin_copy)
    doc["family"]["mesh_hash"] = "f" * 64
    _write_doc(plugin_copy, doc)
    report = validate_plugin(plugin_copy)
    assert any("family.mesh_hash" in p and "another pad mesh" in p for p in report.problems)


# ------------------------------------------------------------------------------------ registry
def test_search_path_and_shadowing(plugin_dir, tmp_path, monkeypatch):
    second = tmp_path / "more"
    shutil.copytree(plugin_dir, second / "testsensor")
    monkeypatch.setenv(PLUGIN_PATH_ENV, f"{plugin_dir}{__import__('os').pathsep}{second}")
    by_name, shadowed = discover_plugins()
    assert by_name["testsensor"].folder == plugin_dir
    assert [s.folder for s in shadowed if s.name == "testsensor"] == [second / "testsensor"]
    assert find_plugin("testsensor").folder == plugin_dir
    with pytest.raises(PluginError, match="unknown sensor plugin 'nosuch'.*testsensor"):
        find_plugin("nosuch")


def test_entry_point_plugin_with_code_hooks(plugin_dir, tmp_path, monkeypatch):
    """A third-party package registers a plugin through the entry-point group and adds its own
    preprocessing (here: it swaps the frame's red and green channels) and depth post-processing."""
    pkg = tmp_path / "thirdparty_sensor.py"
    pkg.write_text(textwrap.dedent(f"""
        import numpy as np
        from pathlib import Path
        from tactile_deploy.runtime.plugins import PluginEntry, PluginHooks

        class Hooks(PluginHooks):
            calls = 0
            def preprocess_frame(self, frame):
                Hooks.calls += 1
                return np.ascontiguousarray(frame[..., [1, 0, 2]])
            def postprocess_depth(self, depth_mm):
                return depth_mm + 0.25

        PLUGIN = PluginEntry(Path({str(plugin_dir)!r}), Hooks())
        """))
    monkeypatch.syspath_prepend(str(tmp_path))
    eps = [EntryPoint("acme", "thirdparty_sensor:PLUGIN", plugins_mod.ENTRY_POINT_GROUP),
           EntryPoint("broken", "no_such_module:X", plugins_mod.ENTRY_POINT_GROUP)]
    monkeypatch.setattr(plugins_mod, "entry_points", lambda group: eps if group == plugins_mod.ENTRY_POINT_GROUP else [])
    monkeypatch.delenv(PLUGIN_PATH_ENV, raising=False)
    by_name, _ = discover_plugins()
    assert "acme" in by_name and "broken" not in by_name
    assert by_name["acme"].origin.startswith("entry point thirdparty_sensor:PLUGIN")
    plugin = SensorPlugin.load("acme")
    from tactile_deploy.runtime.pipeline import ImagingPipeline

    pipe = ImagingPipeline.from_plugin(plugin)
    frame = blob_frame(plugin.reference_frame)
    depth = pipe.frame_to_depth(frame)
    assert type(plugin.hooks).calls == 2        # the reference at setup, then the frame
    m = plugin.manifest
    plain = ImagingPipeline(m.camera, plugin.shading_model, plugin.reference_frame[..., [1, 0, 2]],
                            plugin.noise_reference, m.noise_reference.handling)
    expected = plain.frame_to_depth(np.ascontiguousarray(frame[..., [1, 0, 2]])) + 0.25
    assert np.array_equal(depth, expected)
    assert np.abs(depth - 0.25).max() > 0.01      # the press is there


# ------------------------------------------------------------------------------------ CLI
def test_cli_list_show_validate(plugin_dir, monkeypatch):
    monkeypatch.setenv(PLUGIN_PATH_ENV, str(plugin_dir.parent))
    res = runner.invoke(app, ["plugins", "list"])
    assert res.exit_code == 0 and "testsensor" in res.output
    res = runner.invoke(app, ["plugins", "show", "testsensor"])
    assert res.exit_code == 0, res.output
    assert "640x480 px" in res.output and "noise handling 'subtract'" in res.output
    res = runner.invoke(app, ["plugins", "validate", str(plugin_dir)])
    assert res.exit_code == 0 and "is valid" in res.output
    res = runner.invoke(app, ["plugins", "show", "nosuch"])
    assert res.exit_code == 2 and "plugins list" in res.output


def test_cli_validate_fails_on_a_broken_plugin(plugin_copy):
    (plugin_copy / "demo.npz").unlink()
    res = runner.invoke(app, ["plugins", "validate", str(plugin_copy), "--no-model"])
    assert res.exit_code == 1
    assert "demo_clip.path" in res.output and "problem" in res.output


def test_write_plugin_never_replaces_a_manifest(plugin_dir, tmp_path):
    from tactile_deploy.runtime.plugins import write_plugin

    dst = tmp_path / "p"
    shutil.copytree(plugin_dir, dst)
    before = (dst / "plugin.json").read_text()
    with pytest.raises(PluginError, match="exists; pass overwrite=True"):
        write_plugin(dst, {}, {})
    assert (dst / "plugin.json").read_text() == before


def test_crop_camera_mapping_copies_pixels():
    from tactile_deploy.imaging.camera_mapping import rectify
    from tactile_deploy.imaging.camera_mapping import crop_camera_mapping

    img = np.random.default_rng(0).integers(0, 255, (32, 24, 3), dtype=np.uint8)
    cam = crop_camera_mapping(24, 32, 0.05, crop=(4, 6, 16, 20))
    out = rectify(img, cam)
    assert out.shape == (20, 16, 3) and np.array_equal(out, img[6:26, 4:20])
    assert not cam.image_mirrored and abs(cam.mm_per_px_x - 0.05) < 1e-9


def test_copy_keeps_the_shared_files_and_never_overwrites(tmp_path):
    """The shipped plugins name the family model and the read-out in exported/ by relative
    path: a plain folder copy loses them, ``plugins copy`` keeps them (absolute paths)."""
    from tactile_deploy.runtime.plugins import copy_plugin

    src = Path(__file__).resolve().parent.parent / "plugins" / "gelslim2"
    plain = tmp_path / "plain"
    shutil.copytree(src, plain, ignore=shutil.ignore_patterns("adapted"))
    assert not validate_plugin(plain, check_model=False).ok       # what the command fixes

    out = copy_plugin(src, tmp_path / "mine")
    assert validate_plugin(out).ok
    original, copy = SensorPlugin.load(src), SensorPlugin.load(out)
    for key in original.manifest.files():
        assert copy.path_of(key).resolve() == (original.path_of(key).resolve()
                                               if key in ("model", "readout") else
                                               (out / Path(original.manifest.files()[key].path)).resolve())
    assert Path(copy.manifest.model.path).is_absolute()
    assert not Path(copy.manifest.shading.path).is_absolute()
    assert not (out / "adapted").exists()

    before = (out / "plugin.json").read_text()
    with pytest.raises(PluginError, match="exists; choose a new folder"):
        copy_plugin(src, out)
    assert (out / "plugin.json").read_text() == before
    res = runner.invoke(app, ["plugins", "copy", "gelslim2", str(tmp_path / "cli")])
    assert res.exit_code == 0, res.output
    assert validate_plugin(tmp_path / "cli", check_model=False).ok
    res = runner.invoke(app, ["plugins", "copy", "gelslim2", str(tmp_path / "cli")])
    assert res.exit_code != 0 and "exists" in res.output


def test_copy_with_another_model_runs_it_and_refuses_one_of_another_contract(tmp_path):
    """``plugins copy --model``: the graph for gels that grip in place of the family model (by
    absolute path and sha256, adapted versions not carried over); a model that is not a mesh model
    of the plugin's pad, a missing file and --with-adapted are refused, and nothing is left."""
    from tactile_deploy.checksums import file_sha256
    from tactile_deploy.runtime.plugins import copy_plugin

    root = Path(__file__).resolve().parent.parent
    grip = root / "exported" / "gelslim_mesh_grip.onnx"
    out = copy_plugin(root / "plugins" / "gelslim2", tmp_path / "grip1", model=grip)
    assert validate_plugin(out).ok
    copy = SensorPlugin.load(out)
    assert copy.path_of("model").resolve() == grip.resolve()
    assert copy.manifest.model.sha256 == file_sha256(grip) and copy.manifest.adapted_model is None
    for bad, message in ((root / "exported" / "gelsight_mini_readout.onnx", "input named 'depth'"),
                         (tmp_path / "none.onnx", "no such file")):
        with pytest.raises(PluginError, match=message):
            copy_plugin(root / "plugins" / "gelslim2", tmp_path / "bad", model=bad)
    with pytest.raises(PluginError, match="adapted from its own model"):
        copy_plugin(root / "plugins" / "gelslim2", tmp_path / "bad", with_adapted=True, model=grip)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grip1"]
    res = runner.invoke(app, ["plugins", "copy", "gelslim2", str(tmp_path / "cli"), "--model", str(grip)])
    assert res.exit_code == 0 and "it runs the model" in res.output, res.output
