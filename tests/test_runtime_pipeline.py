"""Imaging pipeline: stage by stage against the shading module and independent references, and
on the real GelSight ball presses of ../shared/data/real (held out from the shading fit) against
the ball they were made with, within the calibration's tolerance."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from test_runtime_support import blob_frame, build_linear_onnx, build_test_plugin

from tactile_deploy.imaging.camera_mapping import OutputGrid
from tactile_deploy.imaging.shading import DepthFromShading, save_shading
from tactile_deploy.runtime.pipeline import (
    GridResampler,
    ImagingPipeline,
    Laps,
    apply_noise_reference,
    shading_gradients,
    subtract_reference,
)
from tactile_deploy.runtime.plugins import MODEL_GRID, SensorPlugin, write_plugin
from tactile_deploy.imaging.camera_mapping import crop_camera_mapping
from tactile_deploy.pad.topology import MeshTopology
from tactile_deploy.runtime.predictor import MeshPredictor
from tactile_deploy.runtime.sources.npz import save_clip

BALL_RADIUS_MM = 2.35
MM_PER_PX = 1 / 19.58
FOLDS = 7


@pytest.fixture(scope="module")
def real(shared_data, tmp_path_factory):
    """A plugin of the real sensor built from 36 presses; the other 6 are held out."""
    from tactile_deploy.calibration.shading.fit import fit_shading
    from tactile_deploy.calibration.shading.presses import load_presses

    d = shared_data / "real" / "fots_gelsight_ballpress"
    if not (d / "annotate.csv").is_file():
        pytest.fail(f"real ball presses not found in {d}")
    presses = load_presses(d / "background.png", d, d / "annotate.csv")
    fold = np.arange(len(presses)) % FOLDS
    model = fit_shading(presses.subset(fold != 0), BALL_RADIUS_MM, MM_PER_PX).model
    held = np.flatnonzero(fold == 0)
    folder = tmp_path_factory.mktemp("real") / "fots_gelsight"
    folder.mkdir()
    h, w = presses.shape
    camera = crop_camera_mapping(w, h, MM_PER_PX)
    save_shading(model, folder / "shading.npz")
    cv2.imwrite(str(folder / "reference.png"), cv2.cvtColor(presses.reference, cv2.COLOR_RGB2BGR))
    pipe = ImagingPipeline(camera, model, presses.reference, None, "keep")
    np.save(folder / "noise_reference.npy", pipe.frame_to_depth(presses.reference))
    save_clip(folder / "demo.npz", presses.frames[held], np.arange(len(held)) * 50_000_000)
    topo = MeshTopology.from_pad()
    topo.save(folder / "topology.npz")
    build_linear_onnx(folder / "model.onnx", topo, ood_threshold=None)
    write_plugin(folder, {
        "name": "fots_gelsight", "description": "GelSight-class sensor of the FOTS ball presses",
        "family": {"name": "gelslim", "mesh_hash": topo.mesh_hash},
        "camera": json.loads(camera.model_dump_json()),
        "material": {"E_mpa": 0.3, "nu": 0.48}, "default_source": {"kind": "demo"},
        "noise_handling": "keep"},
        {"model": folder / "model.onnx", "shading": folder / "shading.npz",
         "reference_frame": folder / "reference.png",
         "noise_reference": folder / "noise_reference.npy", "demo_clip": folder / "demo.npz",
         "topology": folder / "topology.npz"})
    return presses, held, model, SensorPlugin.load(folder)


def test_real_presses_reproduce_the_ball_within_the_calibration_tolerance(real):
    """Held-out presses through the plugin's pipeline: identical to the shading module, and
    shape error <= 20 um mean / 40 um worst, fitted ball radius within 5 % (the shading
    calibration's tolerance)."""
    from tactile_deploy.calibration.shading.evaluate import press_result

    presses, held, model, plugin = real
    pipe = ImagingPipeline.from_plugin(plugin)
    reference = DepthFromShading(model, presses.reference)
    results = []
    for i in held:
        depth = pipe.imaging_depth(presses.frames[i])
        assert np.array_equal(depth, reference.depth(presses.frames[i]))
        results.append(press_result(presses.names[i], depth, presses.circles[i], presses.shape,
                                    MM_PER_PX, BALL_RADIUS_MM))
    shape = np.array([r.shape_um for r in results])
    radius = np.array([r.radius_error for r in results])
    print("\nheld-out presses: shape error um", np.round(shape, 1), "radius error %",
          np.round(100 * radius, 1))
    assert shape.mean() <= 20.0 and shape.max() <= 40.0
    assert np.abs(radius).max() <= 0.05


def test_real_frames_on_the_model_grid(real):
    """The 12 x 16 mm view of the real sensor lands in the middle of the +-17.5 mm model grid,
    volume conserved (area-weighted resampling), zero outside its field of view."""
    presses, held, _, plugin = real
    pipe = ImagingPipeline.from_plugin(plugin)
    frame = presses.frames[held[0]]
    img = pipe.imaging_depth(frame)
    dm = pipe.frame_to_depth(frame)
    vol_img = img.sum() * MM_PER_PX ** 2
    vol_model = dm.sum() * MODEL_GRID.pitch_x_mm ** 2
    assert abs(vol_model - vol_img) < 1e-4 * abs(vol_img)
    x = -17.5 + (np.arange(128) + 0.5) * MODEL_GRID.pitch_x_mm
    outside = np.abs(x) > 240 * MM_PER_PX / 2 + MODEL_GRID.pitch_x_mm
    assert np.all(dm[:, outside] == 0)
    pred = MeshPredictor.from_plugin(plugin).predict_frame(frame)
    assert pred.vertices_mm.shape == (5380, 3) and np.array_equal(pred.depth_mm, dm)


# ------------------------------------------------------------------------------------ stages
@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    return build_test_plugin(tmp_path_factory.mktemp("syn") / "testsensor")


def test_stages_compose_to_the_shading_module(synthetic):
    """rectify -> resample -> subtract_reference -> shading_gradients equals DepthFromShading's
    gradients on the rectified frame, and each stage can be called alone."""
    pipe = ImagingPipeline.from_plugin(synthetic)
    frame = blob_frame(synthetic.reference_frame)
    rect = pipe.rectify(frame)
    ref_rect = pipe.rectify(synthetic.reference_frame)
    g_col, g_row = shading_gradients(subtract_reference(rect, pipe.tables), rect, pipe.tables)
    e_col, e_row = DepthFromShading(synthetic.shading_model, ref_rect).image_gradients(rect)
    assert np.array_equal(g_col, e_col) and np.array_equal(g_row, e_row)
    laps = Laps().start()
    pipe.frame_to_depth(frame, laps)
    assert list(laps.times_ns) == ["check", "rectify", "resample", "reference", "shading",
                                   "poisson", "depth_grid"]


def test_rectification_averages_each_cell():
    """Supersampled rectification = the mean of the point samples inside each grid cell, checked
    against point sampling at the sub-cell centres (an independent remap per sub-cell)."""
    from test_runtime_support import make_camera, make_reference

    from tactile_deploy.imaging.camera_mapping import rectify
    from tactile_deploy.runtime.pipeline import (
        Rectifier,
        default_supersample,
        rectify_frame,
        resample_to_grid,
    )

    cam = make_camera()
    assert default_supersample(cam) == 2          # 0.273 mm cells over 0.075 mm pixels: capped
    frame = make_reference(5)
    frame = np.ascontiguousarray(np.clip(frame.astype(int) + np.random.default_rng(0).integers(
        -30, 30, frame.shape), 0, 255).astype(np.uint8))
    r = Rectifier(cam, 2)
    out = resample_to_grid(rectify_frame(frame, r), r).astype(float)
    g = cam.grid
    sub = []
    for dy in (-0.25, 0.25):
        for dx in (-0.25, 0.25):
            shifted = g.model_copy(update={"x_min_mm": g.x_min_mm + dx * g.pitch_x_mm,
                                           "x_max_mm": g.x_max_mm + dx * g.pitch_x_mm,
                                           "y_min_mm": g.y_min_mm + dy * g.pitch_y_mm,
                                           "y_max_mm": g.y_max_mm + dy * g.pitch_y_mm})
            sub.append(rectify(frame, cam.model_copy(update={"grid": shifted})).astype(float))
    mean = np.mean(sub, axis=0)
    assert np.abs(out - mean).max() <= 1.5          # uint8 rounding of both, 1/32 px table steps
    assert np.abs(out - mean).mean() < 0.3
    assert Rectifier(cam, 1).supersample == 1


def test_noise_reference_handling(synthetic):
    pipe_sub = ImagingPipeline.from_plugin(synthetic)              # manifest: subtract
    m = synthetic.manifest
    pipe_keep = ImagingPipeline(m.camera, synthetic.shading_model, synthetic.reference_frame,
                                synthetic.noise_reference, "keep")
    frame = blob_frame(synthetic.reference_frame)
    diff = pipe_keep.frame_to_depth(frame) - pipe_sub.frame_to_depth(frame)
    assert np.allclose(diff, synthetic.noise_reference, atol=1e-6)
    with pytest.raises(ValueError, match="'subtract' or 'keep'"):
        apply_noise_reference(diff, None, "ignore")


def test_unloaded_sensor_gives_flat_depth(synthetic):
    m = synthetic.manifest
    pipe = ImagingPipeline(m.camera, synthetic.shading_model, synthetic.reference_frame, None, "keep")
    assert np.abs(pipe.frame_to_depth(synthetic.reference_frame)).max() < 1e-6


@pytest.mark.parametrize("extend_mm", [0.0, 0.9])
@pytest.mark.parametrize("src", [
    OutputGrid(x_min_mm=-6.1, x_max_mm=6.3, y_min_mm=-8.0, y_max_mm=8.2, nx=240, ny=320),
    OutputGrid(x_min_mm=-20, x_max_mm=20, y_min_mm=-20, y_max_mm=20, nx=50, ny=50),
    OutputGrid(x_min_mm=3.0, x_max_mm=30.0, y_min_mm=-30.0, y_max_mm=-1.0, nx=77, ny=91),
])
def test_grid_resampler_against_supersampling(src, extend_mm):
    """Area averaging checked against brute-force supersampling of the piecewise-constant
    source (each destination cell averaged over 32 x 32 sample points); with ``extend_mm`` the
    source's edge cells reach that far past its edges (a point within it along x and along y
    takes the nearest cell's value), 0 beyond."""
    rng = np.random.default_rng(2)
    depth = rng.uniform(0, 1, (src.ny, src.nx)).astype(np.float32)
    dst = OutputGrid(nx=32, ny=32)
    out = GridResampler(src, dst, extend_mm)(depth)
    k = 32
    fx = dst.x_min_mm + (np.arange(dst.nx * k) + 0.5) * dst.pitch_x_mm / k
    fy = dst.y_max_mm - (np.arange(dst.ny * k) + 0.5) * dst.pitch_y_mm / k
    col = np.floor((fx - src.x_min_mm) / src.pitch_x_mm).astype(int)
    row = np.floor((src.y_max_mm - fy) / src.pitch_y_mm).astype(int)
    in_x = (fx >= src.x_min_mm - extend_mm) & (fx < src.x_max_mm + extend_mm)
    in_y = (fy > src.y_min_mm - extend_mm) & (fy <= src.y_max_mm + extend_mm)
    vals = np.where(in_y[:, None] & in_x[None, :],
                    depth[np.clip(row, 0, src.ny - 1)[:, None], np.clip(col, 0, src.nx - 1)[None, :]],
                    0.0)
    brute = vals.reshape(dst.ny, k, dst.nx, k).mean(axis=(1, 3))
    # sampling error of the brute force: a source edge inside a destination cell moves by
    # at most one sample column / row
    assert np.abs(out - brute).max() < 2.5 / k
    assert np.abs(out - brute).mean() < 0.2 / k
    if extend_mm and src.x_min_mm > dst.x_min_mm:   # cells the plain resampling leaves (partly) at 0
        assert np.abs(out - GridResampler(src, dst)(depth)).max() > 0.3
    assert GridResampler(dst, dst).identity


def test_grid_resampler_refuses_a_negative_extension():
    with pytest.raises(ValueError, match="extend_mm must be >= 0 mm, got -0.1"):
        GridResampler(OutputGrid(), OutputGrid(nx=32, ny=32), -0.1)


def test_frame_check_messages(synthetic):
    pipe = ImagingPipeline.from_plugin(synthetic)
    from tactile_deploy.runtime.pipeline import FrameError

    with pytest.raises(FrameError, match="numpy array"):
        pipe.frame_to_depth([[1, 2]])
    with pytest.raises(FrameError, match="grey frame"):
        pipe.frame_to_depth(np.zeros((480, 640), np.uint8))
    with pytest.raises(FrameError, match="camera mapping is for 640x480 px"):
        pipe.frame_to_depth(np.zeros((240, 320, 3), np.uint8))
