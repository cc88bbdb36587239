"""Virtual sensors: shipped catalog and its files, frames with their truth, the frame source,
recordings checked by independent readers and detectors, and ``simulate --sensor --rgb``."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from tactile_deploy.calibration.virtual_recordings import record_ball_presses, record_target_frames
from tactile_deploy.indenters import AnalyticSphere, ContactPose
from tactile_deploy.sensors import (
    SensorConfigError,
    list_sensors,
    load_sensor,
    load_sensor_config,
    save_sensor_config,
    sensor_config,
)
from tactile_deploy.sensors.catalog import UnknownSensorError
from tactile_deploy.sensors.virtual import (
    PressEvent,
    PressScript,
    SensorNotConnectedError,
    VirtualSensor,
)

BALL = AnalyticSphere(4.0)


@pytest.fixture(scope="module")
def gelslim1(pad_sim):
    return load_sensor("gelslim1", simulator=pad_sim)


@pytest.fixture(scope="module")
def gelslim2(pad_sim):
    return load_sensor("gelslim2", simulator=pad_sim)


def test_catalog_files_validate():
    assert {"gelslim1", "gelslim2", "gelsight_fots"} <= set(list_sensors())
    configs = {n: sensor_config(n) for n in list_sensors()}
    for name, cfg in configs.items():
        assert cfg.name == name
    g1, g2, fots = configs["gelslim1"], configs["gelslim2"], configs["gelsight_fots"]
    # Two units of one design: same family, pad, resolution and light count; other LEDs, lens,
    # noise and effects.
    assert g1.family == g2.family == "gelslim"
    assert g1.optics.image_size == g2.optics.image_size == (640, 480)
    assert g1.optics.lights != g2.optics.lights
    assert g1.optics.camera.distortion != g2.optics.camera.distortion
    assert g1.optics.noise != g2.optics.noise
    assert {e.name for e in g2.effects} - {e.name for e in g1.effects}
    # The third is of another kind.
    assert fots.family == "gelsight" and fots.optics.image_size == (240, 320)
    assert {lt.kind for lt in fots.optics.lights} == {"directional"}
    assert "dome" in {e.name for e in fots.effects}
    with pytest.raises(UnknownSensorError, match="shipped: .*gelslim1"):
        sensor_config("gelslim9")


def test_config_errors_name_the_file_and_field(tmp_path):
    cfg = sensor_config("gelslim2")
    path = tmp_path / "s.json"
    save_sensor_config(cfg, path)
    assert load_sensor_config(path) == cfg
    doc = json.loads(path.read_text())
    doc["effects"][0]["params"]["offset_mm"] = 5.0
    path.write_text(json.dumps(doc))
    with pytest.raises(SensorConfigError) as err:
        load_sensor_config(path)
    msg = str(err.value)
    assert str(path) in msg and "effects.0.params" in msg and "zero_offset" in msg
    assert "offset_mm" in msg and "5.0" in msg
    doc["effects"][0] = {"name": "wobble", "params": {}}
    path.write_text(json.dumps(doc))
    with pytest.raises(SensorConfigError, match="unknown effect 'wobble'; known effects"):
        load_sensor_config(path)
    path.write_text("{not json")
    with pytest.raises(SensorConfigError, match="not valid JSON"):
        load_sensor_config(path)


def test_press_returns_frame_and_consistent_truth(gelslim1, pad_sim):
    from tactile_deploy.simulation.contact import ContactError, simulate_contact

    pose = ContactPose(x_mm=2.0, y_mm=-1.0, depth_mm=0.6)
    out = gelslim1.press(BALL, pose, np.random.default_rng(0))
    assert out.frame.shape == (480, 640, 3) and out.frame.dtype == np.uint8
    assert out.in_contact and out.force_n > 0
    # The truth is the simulator's own contact (gelslim1 has no mechanical effects).
    ref = simulate_contact(BALL, pose, pad_sim.material, simulator=pad_sim)
    np.testing.assert_allclose(out.depth_mm, ref.depth_mm, atol=1e-6)
    np.testing.assert_allclose(out.vertices_mm, ref.vertices_mm, atol=1e-6)
    assert out.force_n == pytest.approx(ref.force_n, rel=1e-9)
    # The shaded surface follows the ball inside the contact: its deepest point is the tip.
    assert out.surface_depth_mm.max() == pytest.approx(0.6, abs=2e-3)
    # The frame changes where the ball is, and only around it.
    diff = np.abs(out.frame.astype(int) - gelslim1.reference_frame(
        np.random.default_rng(0)).astype(int)).sum(-1)
    from tactile_deploy.imaging.camera_mapping import sensor_mm_to_pixels

    u, v = sensor_mm_to_pixels(np.array([[2.0, -1.0]]), gelslim1.optics.camera)[0]
    vv, uu = np.mgrid[0:480, 0:640]
    dist = np.hypot(uu - u, vv - v) * gelslim1.optics.camera.mm_per_px_x
    assert diff[dist < 2.0].mean() > 10 * max(diff[dist > 8.0].mean(), 1.0)
    with pytest.raises(ContactError, match="exceeds 1.5 mm"):
        gelslim1.press(BALL, ContactPose(depth_mm=1.6))


def test_two_units_render_the_same_contact_differently(gelslim1, gelslim2):
    """Sensor-to-sensor transfer: same contact, nearly the same truth, different frames."""
    pose = ContactPose(x_mm=-1.0, y_mm=1.0, depth_mm=0.5)
    a = gelslim1.press(BALL, pose)
    b = gelslim2.press(BALL, pose)
    assert np.abs(a.frame.astype(int) - b.frame.astype(int)).mean() > 4.0  # noise-free frames
    # gelslim2 presses 0.03 mm deeper and tilted: the truth differs by a little, not by much.
    assert 0.01 < b.depth_mm.max() - a.depth_mm.max() < 0.05


def test_frame_source_timing_and_lifecycle(pad_sim):
    cfg = sensor_config("gelslim1")
    small = cfg.model_copy(update={"fps": 200.0})
    sensor = VirtualSensor(small, simulator=pad_sim)
    with pytest.raises(SensorNotConnectedError, match="connect"):
        sensor.read()
    script = PressScript((PressEvent("sphere_r4", x_mm=1.0, depth_mm=0.5, start_s=0.01,
                                     press_s=0.01, hold_s=0.01, release_s=0.01),),
                         duration_s=0.05)
    t0 = time.monotonic()
    got = list(sensor.frames(script, live=True))
    elapsed = time.monotonic() - t0
    times = [t for t, _ in got]
    assert times == pytest.approx([k / 200.0 for k in range(11)])
    assert elapsed >= 0.05 - 1e-3  # never faster than the camera
    assert not sensor.is_connected
    from tactile_deploy.imaging.camera_mapping import sensor_mm_to_pixels

    ref = sensor.reference_frame().astype(int)
    u, v = sensor_mm_to_pixels(np.array([[1.0, 0.0]]), sensor.optics.camera)[0].astype(int)
    near = (slice(v - 40, v + 40), slice(u - 40, u + 40))  # +-1.5 mm around the press
    change = [np.abs(f[near].astype(int) - ref[near]).mean() for _, f in got]
    pressing = [script.state(t)[0] is not None for t in times]
    assert any(pressing) and not all(pressing)
    assert min(c for c, p in zip(change, pressing) if p) > 2 * max(
        c for c, p in zip(change, pressing) if not p)
    # Context manager, reproducible frames.
    with sensor:
        assert sensor.is_connected
        f0 = sensor.read()
        assert sensor.last_timestamp_s == 0.0
    assert not sensor.is_connected
    with sensor:
        np.testing.assert_array_equal(sensor.read(), f0)


def test_recorded_ball_presses_read_back_and_circles_match_the_images(gelslim1, tmp_path):
    from tactile_deploy.calibration.optics_fit import load_fots

    rec = record_ball_presses(gelslim1, 3, radius_mm=2.5, depth_range_mm=(0.4, 0.8), seed=1)
    assert rec.frames.shape == (3, 480, 640, 3)
    rec.save(tmp_path)
    back = load_fots(tmp_path)  # an independent reader of the FOTS layout
    np.testing.assert_array_equal(back.reference, rec.reference)
    np.testing.assert_array_equal(back.frames, rec.frames)
    np.testing.assert_allclose(back.circles, rec.circles_px, atol=0.01)
    for frame, (cu, cv, rp), a_mm, pose in zip(rec.frames, rec.circles_px, rec.contact_radius_mm,
                                               rec.poses):
        diff = np.abs(frame.astype(float) - rec.reference).sum(-1)
        w = np.where(diff > 0.3 * diff.max(), diff, 0.0)
        vv, uu = np.mgrid[0:480, 0:640]
        cu_img, cv_img = (w * uu).sum() / w.sum(), (w * vv).sum() / w.sum()
        assert np.hypot(cu_img - cu, cv_img - cv) < 0.25 * rp
        # Contact radius: below the rigid ball's intersection with the flat pad, sqrt(2 R d - d^2)
        # (the gel sinks around the ball); above half of Hertz's half-space radius sqrt(R d), the
        # 1 mm mesh resolving the contact only to its nodes (measured 0.65-0.90 mm here for
        # Hertz 1.09-1.41 mm and the bound 1.46-1.83 mm).
        r, d = 2.5, pose.depth_mm
        assert 0.5 * np.sqrt(r * d) < a_mm < np.sqrt(2 * r * d - d * d)


def _blob_centres(frame, reference, blur_px=4.0, frac=0.5):
    """Centroids of the blobs of |frame - reference| (norm over channels, smoothed, threshold at
    ``frac`` of its 99th percentile)."""
    import cv2

    d = frame.astype(np.float32) - reference.astype(np.float32)
    mag = cv2.GaussianBlur(np.sqrt((d * d).sum(-1)), (0, 0), blur_px)
    mask = (mag > frac * np.percentile(mag, 99)).astype(np.uint8)
    _, _, stats, centres = cv2.connectedComponentsWithStats(mask)
    return centres[1:][stats[1:, 4] > 30]


def test_target_frames_show_the_pins_near_their_true_pixels(gelslim1):
    """Pressed pin grid through the full optics: every pin is a blob near where the camera
    mapping projects it. The blobs' centroids are pulled by the shading around each pin, which
    the 1 mm mesh resolves only coarsely (and by the lights' asymmetry): a few px, not more.
    (The renderer's own geometry is exact: test_optics.py.)"""
    rec = record_target_frames(gelslim1)
    assert rec.frames.shape == (1, 480, 640, 3) and rec.pins_mm.shape == (1, 63, 2)
    found = _blob_centres(rec.frames[0], rec.reference)
    assert len(found) == 63
    d = np.linalg.norm(rec.pins_px[0][:, None] - found[None], axis=2).min(axis=1)
    mm = d * gelslim1.optics.camera.mm_per_px_x
    assert np.median(mm) < 0.1 and np.percentile(mm, 95) < 0.3, np.sort(mm)[-5:]


@pytest.mark.parametrize("depth_mm", [0.35, 0.5])
def test_dot_detection_finds_the_pins_apexes_and_the_true_camera(gelslim2, depth_mm):
    """The pressed pin grid of the virtual GelSlim 2 (LEDs at the rim, clipped channels, a
    strong lens): the detected dot centres against the pins' true pixels (the sensor's own
    camera mapping), and the mapping fitted from them against that camera over the imaging grid.
    The blobs' centroids are the check's teeth: pulled towards the lit flank, they miss by px."""
    from tactile_deploy.calibration.camera.dots import calibrate_dots, detect_dots
    from tactile_deploy.imaging.imaging_grid import imaging_grid, with_grid
    from tactile_deploy.imaging.camera_mapping import build_remap
    from tactile_deploy.indenters import ContactPose

    rec = record_target_frames(gelslim2, poses=[ContactPose(depth_mm=depth_mm)])
    true_px = rec.pins_px[0]
    det = detect_dots(rec.frames[0], rec.reference, blur_sigma_px=6.0)

    def errors(found):
        return np.linalg.norm(true_px[:, None] - found[None], axis=2).min(axis=1)

    apex, centroid = errors(det.centres_px), errors(det.centroids_px)
    assert det.at_apex.all() and len(det.centres_px) == 63
    assert np.median(apex) < 0.8 and apex.max() < 3.0, np.sort(apex)[-5:]
    assert np.median(centroid) > 0.8 and centroid.max() > 5.0     # what the refinement fixes

    camera = gelslim2.optics.camera
    grid = imaging_grid(camera)

    def mapping_error_mm(refine):
        fit, _ = calibrate_dots(rec.frames[0], rec.reference, 2.5, grid_shape=(9, 7),
                                u_axis="+x", v_axis="-y", free_lens=("k1", "k2"),
                                blur_sigma_px=6.0, refine=refine)
        a = np.asarray(build_remap(with_grid(fit.mapping, grid)), np.float64)
        b = np.asarray(build_remap(with_grid(camera, grid)), np.float64)
        return np.hypot(*(a - b)) * camera.mm_per_px_x

    refined, plain = mapping_error_mm(True), mapping_error_mm(False)
    assert refined.max() < 0.06 and refined.mean() < 0.03, (refined.mean(), refined.max())
    assert plain.max() > 2 * refined.max() and plain.mean() > 2 * refined.mean()


def test_simulate_cli_renders_rgb_frame(tmp_path):
    import cv2
    from typer.testing import CliRunner

    from tactile_deploy.cli.main import app

    out = tmp_path / "c.npz"
    runner = CliRunner()
    res = runner.invoke(app, ["simulate", "--sensor", "gelslim1", "--rgb", "--indenter",
                              "sphere_r4", "--x", "1", "--y", "2", "--depth", "0.5", "--out",
                              str(out)])
    assert res.exit_code == 0, res.output
    from tactile_deploy.simulation.contact_file import load_contact

    contact = load_contact(out)   # the format's reader checks the arrays and the metadata
    d, meta = contact.arrays, contact.metadata.model_dump()
    frame = d["frame"]
    assert d["depth"].shape == (128, 128) and d["depth"].max() > 0.4
    assert meta["frame_shape"] == [480, 640, 3] and meta["pose_reached"]["depth_mm"] > 0
    assert frame.shape == (480, 640, 3) and frame.dtype == np.uint8
    png = cv2.imread(str(out.with_suffix(".png")))[..., ::-1]
    np.testing.assert_array_equal(png, frame)
    assert meta["sensor"] == "gelslim1"
    bad = runner.invoke(app, ["simulate", "--rgb", "--indenter", "sphere_r4", "--out",
                              str(tmp_path / "x.npz")])
    assert bad.exit_code != 0 and "--sensor" in bad.output
    bad = runner.invoke(app, ["simulate", "--sensor", "gelslim9", "--indenter", "sphere_r4",
                              "--out", str(tmp_path / "y.npz")])
    assert bad.exit_code != 0 and "gelslim1" in bad.output


def test_packages_import_without_torch_or_warp():
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('torch', 'warp'):\n"
        "            raise ImportError('blocked ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import tactile_deploy.optics, tactile_deploy.sensors\n"
        "from tactile_deploy.sensors.effects import list_effects, effect_class\n"
        "[effect_class(n) for n in list_effects()]\n"
        "assert 'torch' not in sys.modules and 'warp' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
