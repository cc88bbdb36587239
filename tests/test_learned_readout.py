"""The learned read-out: its features (against their definition), its ONNX contract and errors,
the exported graph against the torch network, the training command, the unit's depth gain
(a planted scale), a plugin that names it, and the exported read-out on presses of unseen
shapes of the virtual GelSlim 2 against the surface their frames were shaded from."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tactile_deploy.imaging.camera_mapping import OutputGrid
from tactile_deploy.imaging.learned_readout import (
    COLOUR_SCALE_GREY,
    POSITION_SCALE_MM,
    FeatureMaker,
    LearnedReadout,
    ReadoutError,
)

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ROOT / "exported" / "gelslim_readout.onnx"
GRID = OutputGrid(x_min_mm=-3.0, x_max_mm=2.6, y_min_mm=-1.4, y_max_mm=2.8, nx=20, ny=15)


def _reference(rng):
    ref = rng.integers(60, 200, (GRID.ny, GRID.nx, 3)).astype(np.uint8)
    ref[2, 3] = (255, 120, 90)
    return ref


def test_features_follow_their_definition():
    rng = np.random.default_rng(0)
    ref = _reference(rng)
    make = FeatureMaker(ref, GRID)
    # the reference itself: no colour change, its own saturation, illumination and positions
    f = make(ref)
    assert f.shape == (11, GRID.ny, GRID.nx) and f.dtype == np.float32
    assert np.all(f[0:3] == 0)
    assert f[3, 2, 3] == 1 and f[3].sum() == 1 and f[4:6].sum() == 0
    np.testing.assert_allclose(f[6:9], np.moveaxis(ref, -1, 0) / 255.0, atol=1e-7)
    j, i = 7, 4   # column, row: x = x_min + (j + 0.5) pitch, y = y_max - (i + 0.5) pitch
    assert f[9, i, j] == pytest.approx((-3.0 + 7.5 * 0.28) / POSITION_SCALE_MM, abs=1e-6)
    assert f[10, i, j] == pytest.approx((2.8 - 4.5 * 0.28) / POSITION_SCALE_MM, abs=1e-6)
    # a whole-frame drift of +10 grey is the frame's offset: removed; a local change is kept,
    # scaled by the reference's gain (channel mean / pixel value) and COLOUR_SCALE_GREY
    frame = ref.astype(int) + 10
    frame[8, 5, 1] += 40
    frame = np.clip(frame, 0, 255).astype(np.uint8)
    f = make(frame)
    gain = ref[..., 1].mean() / ref[8, 5, 1]
    assert f[1, 8, 5] == pytest.approx(40 * gain / COLOUR_SCALE_GREY, rel=1e-4)
    others = np.ones((GRID.ny, GRID.nx), bool)
    others[8, 5] = others[2, 3] = False
    assert np.abs(f[0:3][:, others]).max() < 1e-5


def test_frames_of_the_wrong_shape_are_refused():
    make = FeatureMaker(_reference(np.random.default_rng(1)), GRID)
    with pytest.raises(ReadoutError, match=r"frame must be \(15, 20, 3\) uint8"):
        make(np.zeros((15, 21, 3), np.uint8))
    with pytest.raises(ReadoutError, match="reference must be"):
        FeatureMaker(np.zeros((15, 20, 3), np.float32), GRID)


torch = pytest.importorskip("torch")


def _tiny_network(tmp_path, metadata_update=None):
    from tactile_deploy.imaging import learned_readout as lr
    from tactile_deploy.learning.readout_network import ReadoutNet
    from tactile_deploy.learning.readout_network import export_onnx

    torch.manual_seed(0)
    net = ReadoutNet(4).eval()
    meta = {"readout_format": lr.READOUT_FORMAT, "feature_version": lr.FEATURE_VERSION,
            "colour_scale_grey": repr(lr.COLOUR_SCALE_GREY),
            "position_scale_mm": repr(lr.POSITION_SCALE_MM), "saturation_level": 254}
    meta.update(metadata_update or {})
    path = tmp_path / "readout.onnx"
    export_onnx(net, path, meta)
    return net, path


def test_exported_graph_matches_the_network_on_any_grid_size(tmp_path):
    from tactile_deploy.learning.readout_network import DEPTH_UNIT_MM

    net, path = _tiny_network(tmp_path)
    readout = LearnedReadout(path)
    x = np.random.default_rng(2).normal(size=(11, 37, 53)).astype(np.float32)
    with torch.no_grad():
        want = net(torch.from_numpy(x)[None])[0, 2].numpy() * DEPTH_UNIT_MM
    got = readout.depth_mm(x)
    assert got.shape == (37, 53)
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_readout_files_that_break_the_contract_are_named(tmp_path):
    with pytest.raises(ReadoutError, match="not found"):
        LearnedReadout(tmp_path / "none.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ReadoutError, match="junk.onnx: onnxruntime cannot load it"):
        LearnedReadout(junk)
    _, path = _tiny_network(tmp_path, {"readout_format": "something else"})
    with pytest.raises(ReadoutError, match="metadata field 'readout_format'"):
        LearnedReadout(path)
    _, path = _tiny_network(tmp_path, {"feature_version": 99})
    with pytest.raises(ReadoutError, match="metadata field 'feature_version' must be '1'.*'99'"):
        LearnedReadout(path)


def test_training_command_writes_a_loadable_model_and_its_card(tmp_path):
    from tactile_deploy.training.shading_net.train import main

    out = tmp_path / "r.onnx"
    assert main(["--units", "1", "--presses", "6", "--epochs", "1", "--width", "4",
                 "--out", str(out)]) == 0
    readout = LearnedReadout(out)
    card = json.loads(out.with_suffix(".json").read_text())
    import hashlib

    assert card["sha256"] == hashlib.sha256(out.read_bytes()).hexdigest()
    assert card["design"] == readout.metadata["design"] == "gelslim1"
    assert card["data"]["presses_per_unit"] == 6 and card["family"]["units"] == 1


def test_depth_gain_recovers_a_planted_scale():
    """The unit's gain is the median of intrusion / deepest cell: a read-out that makes every
    press 7 % too shallow (and one outlier) gets 1 / 0.93 back; the rig's offset is added."""
    from tactile_deploy.calibration.shading.readout_gain import readout_depth_gain

    intrusion = np.array([0.3, 0.45, 0.6, 0.75, 0.9])
    offset = 0.03
    truths = intrusion + offset
    scale = np.array([0.93, 0.93, 0.93, 0.93, 0.6])

    class Pipeline:
        readout = object()

        def frame_to_depth(self, frame):
            k = int(frame[0, 0, 0])
            d = np.zeros((128, 128), np.float32)
            d[60:64, 60:64] = truths[k] * scale[k]
            return d

    frames = np.arange(5, dtype=np.uint8)[:, None, None, None] * np.ones((1, 2, 2, 3), np.uint8)
    gain, ratios = readout_depth_gain(Pipeline(), frames, intrusion, offset)
    assert gain == pytest.approx(1 / 0.93, rel=1e-6)
    assert len(ratios) == 5
    with pytest.raises(ValueError, match="one intrusion per frame"):
        readout_depth_gain(Pipeline(), frames, intrusion[:3], offset)


@pytest.fixture(scope="module")
def gelslim2_with_readout(tmp_path_factory):
    """The shipped gelslim2 plugin with the exported read-out added to its manifest (a copy)."""
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.checksums import file_sha256

    src = ROOT / "plugins" / "gelslim2"
    folder = tmp_path_factory.mktemp("plugins") / "gelslim2"
    shutil.copytree(src, folder)
    doc = json.loads((folder / "plugin.json").read_text())
    for key, path in (("model", (src / doc["model"]["path"]).resolve()), ("readout", SHIPPED)):
        shutil.copyfile(path, folder / path.name)
        doc[key] = {"path": path.name, "sha256": file_sha256(path)}
    doc["readout_depth_gain"] = 1.02
    (folder / "plugin.json").write_text(json.dumps(doc))
    return SensorPlugin.load(folder)


def test_plugin_pipeline_reads_with_the_readout_and_its_gain(gelslim2_with_readout):
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import validate_plugin

    plugin = gelslim2_with_readout
    assert validate_plugin(plugin.folder).ok
    pipe = ImagingPipeline.from_plugin(plugin)
    assert pipe.readout is not None and pipe.readout_gain == pytest.approx(1.02)
    frame = plugin.reference_frame
    image = pipe.rectify(frame)
    want = plugin.readout.depth_mm(pipe.features(image)) * np.float32(1.02)
    np.testing.assert_allclose(pipe.imaging_depth(frame), want, atol=1e-7)


def test_readout_reads_unseen_shapes_closer_than_the_shading_model(gelslim2_with_readout):
    """Presses of the shared indenter meshes (shapes neither the shading model nor the
    read-out's training saw) of the virtual GelSlim 2, against the surface their frames were
    shaded from: the read-out's error over the contact and its rim is smaller than the shading
    model's of the same plugin."""
    from tactile_deploy.calibration.shading.virtual_check import contact_region_errors, virtual_shape_presses
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.sensors import load_sensor

    plugin = gelslim2_with_readout
    novel = sorted((ROOT.parent / "shared" / "data" / "indenters").glob("*.stl"))
    assert novel, "the shared indenter meshes are missing (../shared/data/indenters)"
    sensor = load_sensor("gelslim2")
    sensor.prepare()
    presses = virtual_shape_presses(sensor, plugin.manifest.camera.grid, novel, 8, seed=5150)
    m = plugin.manifest
    learned = ImagingPipeline.from_plugin(plugin)
    table = ImagingPipeline(m.camera, plugin.shading_model, plugin.reference_frame, None, "keep",
                            m.depth_grid)
    e_learned = contact_region_errors([learned.frame_to_depth(f) for f in presses.frames],
                                      presses.truths)
    e_table = contact_region_errors([table.frame_to_depth(f) for f in presses.frames],
                                    presses.truths)
    print(f"\nregion RMSE (um): read-out {e_learned['region'].round(1)}, table "
          f"{e_table['region'].round(1)}")
    assert np.nanmean(e_learned["region"]) < np.nanmean(e_table["region"])


def test_a_changed_readout_file_is_refused_by_validation(gelslim2_with_readout, tmp_path):
    from tactile_deploy.runtime.plugins import validate_plugin

    folder = tmp_path / "gelslim2"
    shutil.copytree(gelslim2_with_readout.folder, folder)
    data = bytearray((folder / SHIPPED.name).read_bytes())
    data[-1] ^= 0xFF
    (folder / SHIPPED.name).write_bytes(bytes(data))
    report = validate_plugin(folder)
    assert not report.ok
    assert any("readout" in p for p in report.problems), report.problems


def test_network_from_onnx_gives_back_the_exported_network(tmp_path):
    """The weights read back from an exported read-out make the same depth as onnxruntime does
    with the file; a file that is not a read-out is named."""
    import onnx
    from onnx import TensorProto, helper

    from tactile_deploy.learning.readout_finetuning import network_from_onnx
    from tactile_deploy.learning.readout_network import DEPTH_UNIT_MM

    _, path = _tiny_network(tmp_path)
    net = network_from_onnx(path)
    assert net.width == 4
    x = np.random.default_rng(4).normal(size=(11, 24, 40)).astype(np.float32)
    with torch.no_grad():
        got = net(torch.from_numpy(x)[None])[0, 2].numpy() * DEPTH_UNIT_MM
    np.testing.assert_allclose(got, LearnedReadout(path).depth_mm(x), atol=1e-5)
    other = tmp_path / "identity.onnx"
    graph = helper.make_graph([helper.make_node("Identity", ["a"], ["b"])], "g",
                              [helper.make_tensor_value_info("a", TensorProto.FLOAT, [1])],
                              [helper.make_tensor_value_info("b", TensorProto.FLOAT, [1])])
    onnx.save(helper.make_model(graph), str(other))
    with pytest.raises(ValueError, match="identity.onnx: not a read-out"):
        network_from_onnx(other)


def test_finetuning_moves_a_network_to_a_planted_one(tmp_path):
    """Fine-tuning a network on the outputs of another (planted) network brings its depth on
    held-out inputs much closer to the planted one's."""
    from tactile_deploy.learning.readout_finetuning import finetune_network, network_from_onnx
    from tactile_deploy.learning.readout_network import DEPTH_UNIT_MM, ReadoutNet

    torch.manual_seed(7)
    planted = ReadoutNet(4).eval()
    _, path = _tiny_network(tmp_path)
    student = network_from_onnx(path)
    rng = np.random.default_rng(5)
    x = rng.normal(size=(40, 11, 16, 16)).astype(np.float32)
    with torch.no_grad():
        y = planted(torch.from_numpy(x)).numpy()

    def depth_error(net):
        with torch.no_grad():
            d = net(torch.from_numpy(x[32:]))[:, 2].numpy()
        return float(np.sqrt(np.mean((d - y[32:, 2]) ** 2))) * DEPTH_UNIT_MM

    before = depth_error(student)
    student, losses = finetune_network(student, x[:32], y[:32], steps=300, lr=3e-3, seed=1)
    assert np.mean(losses[-20:]) < 0.2 * np.mean(losses[:20])
    assert depth_error(student) < 0.3 * before, (before, depth_error(student))


def test_finetuning_without_torch_says_what_to_install(monkeypatch):
    import sys

    from tactile_deploy.calibration.shading.readout_finetune import FinetuneUnavailable, finetune_unit_readout

    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(FinetuneUnavailable, match=r"tactile-deploy\[train\].*readout_steps to 0"):
        finetune_unit_readout(None, [], [], [], Path("x.onnx"), "unit")
