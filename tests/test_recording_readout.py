"""A learned read-out in the one-command calibration from recorded presses (``--readout``).

End to end: the DIGIT virtual sensor's ball presses, recorded in the
real recordings' layout, calibrated with ``exported/digit_readout.onnx`` (trained on other virtual
units of the DIGIT design, never on this one); new presses read through the written plugin
against the surface their frames were shaded from, within 1.5 contact radii, against the 20 um
target of the depth checks (the same presses through the shading-model plugin are the baseline
beside it). A read-out of another pad's design is refused with what to do instead.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tactile_deploy.shipped import model_path

BALL_MM = 1.5


def test_presses_too_small_for_the_readout_grid_are_named():
    from tactile_deploy.calibration.recording.readout import MIN_REGION_CELLS, measurable
    from tactile_deploy.calibration.shading.presses import PressSet

    # circles (column, row, radius) in cells of a 40 x 54 grid: inside the view, cut by its left
    # edge (8 cells of it in the grid), and too small anywhere (0.8 x 1.5 cells covers 5)
    circles = np.array([[20.0, 27.0, 4.0], [-1.5, 27.0, 3.5], [20.0, 27.0, 1.5]])
    presses = PressSet(np.zeros((54, 40, 3), np.uint8), np.zeros((3, 54, 40, 3), np.uint8),
                       ["in", "edge", "small"], circles)
    rows, cols = np.mgrid[0:54, 0:40]
    counts = [int((np.hypot(cols - c[0], rows - c[1]) < 0.8 * c[2]).sum()) for c in circles]
    assert counts[0] >= MIN_REGION_CELLS > max(counts[1:]), counts
    assert measurable(presses).tolist() == [True, False, False]


@pytest.fixture(scope="module")
def digit_recording(tmp_path_factory):
    from tactile_deploy.calibration.virtual_recordings import record_ball_presses
    from tactile_deploy.sensors.catalog import load_sensor

    sensor = load_sensor("digit")
    sensor.prepare()
    rec = record_ball_presses(sensor, 16, radius_mm=BALL_MM, depth_range_mm=(0.4, 1.1), seed=5)
    folder = tmp_path_factory.mktemp("digit") / "presses"
    rec.save(folder)
    return sensor, folder


def _calibrate(sensor, folder: Path, out: Path, readout=None):
    from tactile_deploy.calibration.recording.build import calibrate_recording

    return calibrate_recording("digit-unit", "digit", folder, ball_radius_mm=BALL_MM,
                               annotations=folder / "annotate.csv", shallow_presses=True,
                               mm_per_px=float(sensor.optics.camera.mm_per_px_x), out=out,
                               folds=4, readout=readout, say=lambda m: None)


def test_recorded_presses_read_by_the_family_readout(digit_recording, tmp_path):
    from tactile_deploy.calibration.shading.virtual_check import near_contact_errors, virtual_ball_presses
    from tactile_deploy.pad.family import FAMILIES
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin

    sensor, folder = digit_recording
    readout = model_path("digit_readout.onnx")
    learned = _calibrate(sensor, folder, tmp_path / "learned", readout)
    shading = _calibrate(sensor, folder, tmp_path / "shading")
    assert validate_plugin(learned.plugin).ok
    plugin = SensorPlugin.load(learned.plugin)
    assert plugin.readout is not None and (learned.plugin / "readout.onnx").is_file()
    assert plugin.manifest.readout_depth_gain == 1.0
    assert plugin.manifest.camera.grid.pitch_x_mm == pytest.approx(35.0 / 128)
    assert learned.metrics["depth from"] == "learned read-out digit_readout.onnx"
    assert shading.metrics["depth from"] == "the fitted shading model"

    grid = plugin.manifest.camera.grid
    depth_grid = FAMILIES["digit"].depth_grid
    presses = virtual_ball_presses(sensor, grid, 6, 0, seed=2024, ball_radius_mm=BALL_MM,
                                   depth_range_mm=(0.4, 1.0), depth_grid=depth_grid)
    errors = {}
    for name, result in (("learned", learned), ("shading", shading)):
        pipeline = ImagingPipeline.from_plugin(SensorPlugin.load(result.plugin))
        depths = np.stack([pipeline.frame_to_depth(f) for f in presses.frames])
        errors[name] = near_contact_errors(depths, presses, depth_grid=depth_grid)["near"]
    print({k: np.round(v, 1) for k, v in errors.items()})
    assert errors["learned"].mean() <= 20.0, errors
    assert errors["learned"].mean() < errors["shading"].mean(), errors


def test_readout_of_another_pad_is_refused(digit_recording, tmp_path):
    from tactile_deploy.calibration.recording.errors import PlausibilityError

    sensor, folder = digit_recording
    with pytest.raises(PlausibilityError) as e:
        _calibrate(sensor, folder, tmp_path / "p", model_path("gelslim_readout.onnx"))
    text = str(e.value)
    assert "'gelslim1'" in text and "'gelslim'" in text and "--pad 'digit'" in text
    assert "exported/digit_readout.onnx" in text and not (tmp_path / "p").exists()


def test_a_contact_past_the_edge_of_the_view_goes_on_across_the_depth_grid(digit_recording, tmp_path):
    """DIGIT's depth grid (its sensing area) reaches 0.25 mm past the read-out's view at the top
    and bottom (0.13 mm at the sides); the calibration sets the plugin to carry the depth at the
    view's edge across that strip. A 6 mm ball whose contact runs 1.9 mm past the view's top
    edge: the strip's depth against the surface the frame was shaded from, with the plugin's
    extension and with depth 0 there."""
    from scipy import ndimage

    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.pad.family import FAMILIES
    from tactile_deploy.runtime.pipeline import GridResampler, ImagingPipeline
    from tactile_deploy.runtime.plugins import SensorPlugin

    sensor, folder = digit_recording
    result = _calibrate(sensor, folder, tmp_path / "p", model_path("digit_readout.onnx"))
    plugin = SensorPlugin.load(result.plugin)
    m = plugin.manifest
    depth_grid = FAMILIES["digit"].depth_grid
    strip_mm = max(depth_grid.x_max_mm - m.camera.grid.x_max_mm, depth_grid.y_max_mm - m.camera.grid.y_max_mm)
    assert m.view_edge_extension_mm == pytest.approx(strip_mm, abs=1e-6) and 0.2 < strip_mm < 0.3
    extended = ImagingPipeline.from_plugin(plugin)
    zero = ImagingPipeline(m.camera, plugin.shading_model, plugin.reference_frame, plugin.noise_reference,
                           m.noise_reference.handling, m.depth_grid, plugin.hooks, readout=plugin.readout,
                           readout_gain=m.readout_depth_gain)
    out = sensor.press(AnalyticSphere(6.0), ContactPose(x_mm=0.0, y_mm=m.camera.grid.y_max_mm - 1.0,
                                                       depth_mm=0.7), np.random.default_rng(3))
    truth = GridResampler(sensor.renderer.grid, depth_grid)(np.asarray(out.surface_depth_mm, np.float32))
    y = depth_grid.y_max_mm - (np.arange(depth_grid.ny) + 0.5) * depth_grid.pitch_y_mm   # row 0: largest y
    strip = (y > m.camera.grid.y_max_mm)[:, None] & (truth > 0.1)
    contact = ndimage.binary_dilation(truth > 0.01, iterations=4)
    err = {}
    for name, pipeline in (("extended", extended), ("zero", zero)):
        d = pipeline.frame_to_depth(out.frame)
        err[name] = [1e3 * np.sqrt(np.mean((d[k] - truth[k]) ** 2)) for k in (strip, contact)]
    print({k: np.round(v, 1) for k, v in err.items()}, int(strip.sum()), "strip cells")
    assert strip.sum() >= 40
    strip_depth_um = 1e3 * np.sqrt(np.mean(truth[strip] ** 2))
    assert err["zero"][0] > 0.7 * strip_depth_um        # the cliff: the strip read as flat (300 of 369 um)
    assert err["extended"][0] < 0.3 * err["zero"][0]
    assert err["extended"][1] < 0.5 * err["zero"][1]
