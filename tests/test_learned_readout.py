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
    for bad in ("8", "sixty-four"):
        _, path = _tiny_network(tmp_path, {"window_cells": bad})
        with pytest.raises(ReadoutError, match=f"metadata field 'window_cells' must be a whole number of cells > 32, got '{bad}'"):
            LearnedReadout(path)


def test_training_command_writes_a_loadable_model_and_its_card(tmp_path):
    from tactile_deploy.training.shading_net.train import main

    out = tmp_path / "r.onnx"
    assert main(["--units", "1", "--presses", "6", "--epochs", "1", "--width", "4",
                 "--out", str(out)]) == 0
    readout = LearnedReadout(out)
    from tactile_deploy.training.shading_net.card import load_readout_card

    card = load_readout_card(out.with_suffix(".json"))  # the format's reader: sha256 of r.onnx checked
    assert card.design == readout.metadata["design"] == "gelslim1"
    assert card.data.presses_per_unit == 6 and card.family.units == 1
    assert card.metadata == {k: str(v) for k, v in readout.metadata.items()}


def test_training_crops_do_not_depend_on_the_number_of_workers():
    """Each unit draws its presses from its own seed: two worker processes make the crops one
    process makes, unit by unit, bit for bit."""
    from tactile_deploy.training.shading_net.train import generate_crops

    kwargs = dict(design="gelslim1", units=2, presses=3, seed=11, mix=(0.4, 0.2, 0.4), crop=24, log=lambda m: None)
    serial, forked = generate_crops(**kwargs, workers=1), generate_crops(**kwargs, workers=2)
    assert len(serial) == len(forked) == 6
    np.testing.assert_array_equal(serial.features(), forked.features())
    np.testing.assert_array_equal(serial.depth_mm, forked.depth_mm)
    assert list(serial.kinds) == list(forked.kinds)
    assert np.abs(serial.depth_mm).max() > 0.1          # real presses, not empty maps
    first = generate_crops(**{**kwargs, "units": 1}, workers=1)
    np.testing.assert_array_equal(first.depth_mm, serial.depth_mm[:3])   # unit 1 alike whatever follows


def test_window_starts_and_weights_cover_the_grid():
    from tactile_deploy.imaging.learned_readout import WINDOW_OVERLAP_CELLS, window_starts, window_weights

    assert window_starts(48, 64) == [0] and window_starts(64, 64) == [0]
    assert window_starts(66, 64) == [0, 2]                      # the GelSight Mini's 66-cell-wide grid
    for n, size in ((66, 64), (90, 48), (200, 64), (129, 40)):
        starts = window_starts(n, size)
        assert starts[0] == 0 and starts[-1] + size == n          # the grid's borders are window borders
        assert all(b - a <= size - WINDOW_OVERLAP_CELLS for a, b in zip(starts, starts[1:]))
        w = window_weights(n, size, starts)
        total = np.zeros(n)
        for a, row in zip(starts, w):
            total[a:a + size] += row
        assert total.min() > 0.99 and w[0][0] == 1.0 and w[-1][-1] == 1.0
    with pytest.raises(ValueError, match="wider than the overlap"):
        window_starts(40, 16)


def test_a_grid_wider_than_the_training_crops_is_read_in_windows():
    """The GelSight Mini's read-out grid is 68 cells wide (every whole cell inside its image)
    and its read-out was trained on 64-cell crops (``window_cells`` 64). Read whole, the network
    pads 4 columns on the right that training never padded and over-reads a ball's falling flank
    there; read in windows, the cells only one window covers are exactly that window's read, and
    the flank follows the surface the frame was shaded from (the virtual Mini's FEM press; its
    pad's operators take ~45 s to build)."""
    from tactile_deploy.imaging.imaging_grid import readout_grid, with_grid
    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.runtime.pipeline import GridResampler, Rectifier, rectify_frame, resample_to_grid
    from tactile_deploy.sensors.catalog import load_sensor

    readout = LearnedReadout(ROOT / "exported" / "gelsight_mini_readout.onnx")
    assert readout.window_cells == 64
    sensor = load_sensor("gelsight_mini")
    camera = with_grid(sensor.optics.camera, readout_grid(sensor.optics.camera))
    grid = camera.grid
    assert (grid.ny, grid.nx) == (50, 68)
    rect = Rectifier(camera, 2)
    rng = np.random.default_rng(3)
    reference = resample_to_grid(rectify_frame(sensor.renderer.reference_frame(rng), rect), rect)
    out = sensor.press(AnalyticSphere(1.5), ContactPose(x_mm=grid.x_max_mm - 2.2, y_mm=-2.8, theta_deg=0.0,
                                                       depth_mm=0.9), rng, truth=False)
    truth = GridResampler(sensor.renderer.grid, grid)(np.asarray(out.surface_depth_mm, np.float32))
    features = FeatureMaker(reference, grid)(resample_to_grid(rectify_frame(out.frame, rect), rect))

    windowed = readout.depth_mm(features)
    np.testing.assert_array_equal(windowed[:, :4], readout._run(features[:, :, :64])[:, :4])
    np.testing.assert_array_equal(windowed[:, 64:], readout._run(features[:, :, 4:])[:, 60:])
    whole = readout._run(features)
    flank = (truth > 0.01) & (np.arange(grid.nx)[None, :] >= grid.nx - 8)   # the contact's last 2.2 mm
    assert flank.sum() > 20

    def rmse_um(depth):
        return 1e3 * float(np.sqrt(np.mean((depth[flank] - truth[flank]) ** 2)))

    assert rmse_um(windowed) < 0.5 * rmse_um(whole), (rmse_um(windowed), rmse_um(whole))   # 10.3 vs 27.3 um
    assert rmse_um(windowed) < 20.0, rmse_um(windowed)     # the ball target inside the view


def test_shipped_readout_card_validates_and_names_its_graph(tmp_path):
    """exported/gelslim_readout.json is a read-out card of the graph beside it; the reader names
    the file, the field, what it expected and what it found."""
    import shutil

    from tactile_deploy.training.shading_net.card import ReadoutCardError, load_readout_card

    card = load_readout_card(SHIPPED.with_suffix(".json"))
    assert card.model == SHIPPED.name and card.design == "gelslim1"
    assert card.metadata == {k: str(v) for k, v in LearnedReadout(SHIPPED).metadata.items()}
    doc = json.loads(SHIPPED.with_suffix(".json").read_text())
    bad = tmp_path / "gelslim_readout.json"
    bad.write_text(json.dumps({**doc, "training": {**doc["training"], "epochs": 0}}))
    with pytest.raises(ReadoutCardError, match=r"(?s)gelslim_readout.json.*training.epochs.*greater than or equal to 1.*got 0"):
        load_readout_card(bad)
    shutil.copy(SHIPPED, tmp_path / SHIPPED.name)
    (tmp_path / SHIPPED.name).write_bytes(SHIPPED.read_bytes() + b"x")
    bad.write_text(json.dumps(doc))
    with pytest.raises(ReadoutCardError, match=f"field 'sha256': expected the sha256 of .*, got {doc['sha256']}"):
        load_readout_card(bad)


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


def test_training_features_are_the_runtime_features():
    """The numpy features of the training data (made where OpenCV is not installed) equal the
    runtime's FeatureMaker on the same frames, and both agree on the channel count."""
    from tactile_deploy.imaging import learned_readout as lr
    from tactile_deploy.imaging.camera_mapping import grid_centres_mm
    from tactile_deploy.imaging.shading import frame_offset
    from tactile_deploy.learning.readout_network import N_FEATURES
    from tactile_deploy.training.shading_net import data

    assert N_FEATURES == lr.N_FEATURES
    assert (data.COLOUR_SCALE_GREY, data.POSITION_SCALE_MM) == (lr.COLOUR_SCALE_GREY,
                                                               lr.POSITION_SCALE_MM)
    rng = np.random.default_rng(3)
    ref = _reference(rng)
    frames = np.clip(ref[None].astype(int) + rng.integers(-40, 60, (3, *ref.shape)), 0,
                     255).astype(np.uint8)
    make = FeatureMaker(ref, GRID)
    offsets = np.array([frame_offset(f, ref) for f in frames])
    x, y = grid_centres_mm(GRID)
    got = data.readout_features(frames, offsets, ref, np.stack([x, y]))
    want = np.stack([make(f) for f in frames])
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_crop_file_round_trip(tmp_path):
    """Crops written and read back: frames exact, depth to 1 um, features as before; a crop
    file of other settings is refused by the training command."""
    from tactile_deploy.training.shading_net.crops import Crops, contact_crops, load_crops, read_spec, save_crops
    from tactile_deploy.training.shading_net.data import UnitPresses

    rng = np.random.default_rng(8)
    h, w, n = 20, 30, 5
    ref = rng.integers(50, 250, (h, w, 3)).astype(np.uint8)
    images = np.clip(ref[None].astype(int) + rng.integers(-80, 80, (n, h, w, 3)), 0,
                     255).astype(np.uint8)
    depth = np.zeros((n, h, w), np.float32)
    for k in range(n):
        depth[k, rng.integers(0, h), rng.integers(0, w)] = rng.uniform(0.1, 1.2)
        depth[k] -= 0.02 * rng.random((h, w))            # the bulge around contacts
    xy = np.stack(np.meshgrid(np.arange(w) * 0.27, np.arange(h) * -0.27)).astype(np.float32)
    presses = UnitPresses(images, rng.normal(0, 5, (n, 3)).astype(np.float32), ref, xy, depth,
                          0.27, np.array(["ball", "library", "procedural", "ball", "ball"]))
    crops = Crops.concatenate([contact_crops(presses, rng, 12), contact_crops(presses, rng, 12)])
    assert crops.frames.shape == (2 * n, 12, 12, 3) and crops.unit.max() == 1
    path = tmp_path / "crops.npz"
    save_crops(path, crops, {"seed": 1})
    back = load_crops(path)
    assert np.array_equal(back.frames, crops.frames)
    assert np.abs(back.depth_mm - crops.depth_mm).max() <= 0.5e-3 + 1e-7
    np.testing.assert_allclose(back.features(), crops.features(), atol=1e-6)
    assert read_spec(path) == {"seed": 1}


def test_procedural_indenters_are_what_they_draw():
    """Every family gives an indenter whose envelope, sampled at its grid's pixel centres, is the
    drawn height map (lowest point 0, finite only on the footprint); a flat punch presses flat."""
    from tactile_deploy.indenters import ContactPose
    from tactile_deploy.training.shading_net.shapes import FAMILIES, GridIndenter, random_indenter

    rng = np.random.default_rng(11)
    for family in FAMILIES:
        ind = random_indenter(rng, family)
        g = ind.envelope_grid()
        iy, ix = np.nonzero(np.isfinite(g.heights_mm))
        q = np.c_[g.x0_mm + ix * g.pitch_mm, g.y0_mm + iy * g.pitch_mm]
        np.testing.assert_allclose(ind.envelope_mm(q), g.heights_mm[iy, ix], atol=1e-6)
        assert g.heights_mm[iy, ix].min() == 0.0 and 0 < ind.footprint_radius_mm <= 17.5
    square = np.where((np.abs(np.arange(101) - 50)[:, None] <= 30)
                      & (np.abs(np.arange(101) - 50)[None, :] <= 30), 0.0, np.inf)
    punch = GridIndenter("square", square, pitch_mm=0.05)
    pts = np.array([[0.0, 0.0], [1.4, -1.4], [1.6, 0.0]])
    got = punch.intrusion_mm(pts, ContactPose(x_mm=0.0, y_mm=0.0, depth_mm=0.4))
    assert np.allclose(got[:2], 0.4) and got[2] == -np.inf      # 1.6 mm is beyond the 1.5 mm half-side


def test_crops_train_where_only_torch_is_installed(tmp_path):
    """The fitting command imports neither OpenCV nor pydantic, and its weights export through
    the training command's --weights with the card naming them."""
    import subprocess
    import sys

    from tactile_deploy.training.shading_net.crops import Crops, save_crops

    rng = np.random.default_rng(2)
    n, h, w = 6, 16, 16
    ref = rng.integers(80, 200, (1, 24, 24, 3)).astype(np.uint8)
    crops = Crops(rng.integers(0, 256, (n, h, w, 3)).astype(np.uint8),
                  np.zeros((n, 3), np.float32), rng.uniform(0, 0.5, (n, h, w)).astype(np.float32),
                  np.zeros(n, np.int32), np.full(n, 4, np.int32), np.full(n, 2, np.int32), ref,
                  rng.normal(size=(1, 2, 24, 24)).astype(np.float32), np.array(["ball"] * n), 0.27)
    save_crops(tmp_path / "c.npz", crops, {})
    code = ("import sys; sys.modules['cv2'] = None; sys.modules['pydantic'] = None; "
            "from tactile_deploy.training.shading_net.fitting import main; "
            f"main(['--crops', r'{tmp_path / 'c.npz'}', '--weights-out', r'{tmp_path / 'w.pt'}', "
            "'--epochs', '2', '--width', '4', '--device', 'cpu'])")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    from tactile_deploy.safe_torch import load_torch_file

    saved = load_torch_file(tmp_path / "w.pt")
    assert saved["settings"]["width"] == 4 and len(saved["losses"]) == 2
    # continued from those weights (a step too small to move them): it starts where they ended,
    # and says so
    from tactile_deploy.training.shading_net.fitting import main as fit_main

    assert fit_main(["--crops", str(tmp_path / "c.npz"), "--weights-out", str(tmp_path / "w2.pt"),
                     "--epochs", "1", "--width", "4", "--device", "cpu", "--lr", "1e-12",
                     "--init", str(tmp_path / "w.pt")]) == 0
    cont = load_torch_file(tmp_path / "w2.pt")
    assert cont["settings"]["init"]["weights"] == "w.pt" and cont["settings"]["init"]["epochs"] == 2
    learned = [k for k in saved["state_dict"] if not k.endswith(("running_mean", "running_var",
                                                                  "num_batches_tracked"))]
    assert learned
    for k in learned:
        np.testing.assert_allclose(cont["state_dict"][k].numpy(), saved["state_dict"][k].numpy(),
                                   atol=1e-6, err_msg=k)
    with pytest.raises(SystemExit, match="width 4, not --width 8"):
        fit_main(["--crops", str(tmp_path / "c.npz"), "--weights-out", str(tmp_path / "w3.pt"),
                  "--width", "8", "--device", "cpu", "--init", str(tmp_path / "w.pt")])


def test_validation_command_compares_networks_on_an_unseen_unit(tmp_path, capsys):
    """``python -m tactile_deploy.training.shading_net.validate``: presses of another unit, each network's
    contact-region error per kind; the same network twice gives the same figures, and the
    presses kept in --cache give them again. The error is an RMSE over the contact and its rim."""
    from tactile_deploy.training.shading_net.validate import main, region_rmse_um

    truth = np.zeros((20, 20), np.float32)
    truth[8:12, 8:12] = 0.2
    off = truth + np.float32(0.03)                # 30 um everywhere
    assert region_rmse_um(off, truth) == pytest.approx(30.0, rel=1e-4)
    assert region_rmse_um(truth, truth) == 0.0
    cache = tmp_path / "presses.npz"
    args = [str(SHIPPED), str(SHIPPED), "--presses", "4", "--seed", "3", "--cache", str(cache)]
    assert main(args) == 0
    first = capsys.readouterr().out.strip().splitlines()
    assert len(first) == 2 and first[0] == first[1] and "um mean" in first[0]
    assert cache.is_file()
    assert main(args) == 0
    assert capsys.readouterr().out.strip().splitlines() == first


def test_contact_region_errors_in_the_view_count_only_the_cells_the_camera_sees():
    """A grid covering x in [-5.6, 5.6] mm, y in [-2.8, 2.8] mm: the view mask holds the model
    cells (pitch 35/128 mm) whose centres lie inside it; an error planted only outside the view
    counts in the region's RMSE and not in the in-view RMSE."""
    from tactile_deploy.calibration.shading.virtual_check import contact_region_errors, view_mask

    view = view_mask(OutputGrid(x_min_mm=-5.6, x_max_mm=5.6, y_min_mm=-2.8, y_max_mm=2.8,
                                nx=41, ny=21))
    g = OutputGrid()
    x = g.x_min_mm + (np.arange(g.nx) + 0.5) * g.pitch_x_mm
    y = g.y_max_mm - (np.arange(g.ny) + 0.5) * g.pitch_y_mm
    assert view.shape == (128, 128)
    assert view.sum() == (np.abs(x) < 5.6).sum() * (np.abs(y) < 2.8).sum() == 40 * 20
    truth = np.zeros((1, 128, 128), np.float32)
    truth[0, 54:74, 40:88] = 0.2                      # a bar reaching past the view along x
    est = truth.copy()
    first_column = int(np.argmax(view.any(0)))
    est[0, :, :first_column] += 0.05                 # 50 um off left of the view only
    e = contact_region_errors(est, truth, view=view)
    assert e["region_in_view"][0] == pytest.approx(0.0, abs=1e-3)
    assert e["region"][0] > 10.0
    assert "region_in_view" not in contact_region_errors(est, truth)
