"""Cameras without hardware: the device listing on a fake sysfs/udev tree, selection by serial
and by-id path, the control requests (size, rate, exposure and white balance locked) against a
fake V4L2 driver, and the real OpenCV capture code path on a video file."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from test_runtime_support import build_test_plugin
from typer.testing import CliRunner

from tactile_deploy.cli.main import app
from tactile_deploy.runtime.sources.camera import (
    V4L2_EXPOSURE_AUTO,
    V4L2_EXPOSURE_MANUAL,
    OpenCVCamera,
)
from tactile_deploy.runtime.sources.config import CameraSourceConfig, parse_source
from tactile_deploy.runtime.sources.devices import (
    CameraNotFoundError,
    list_cameras,
    resolve_camera,
)

runner = CliRunner()


def _fake_tree(root: Path) -> tuple[Path, Path]:
    """A sysfs + /dev tree as Linux makes it for two USB cameras: a GelSight Mini (image node
    video0 and metadata node video1) and a webcam (video2), with udev's by-id links."""
    sysfs, dev = root / "sys" / "class" / "video4linux", root / "dev"
    devices = root / "sys" / "devices" / "usb1"
    cams = [("video0", "GelSight Mini R0B 2D16-V7R5: Ge", 0, "1-2", "2D16V7R5", "0c45", "636d"),
            ("video1", "GelSight Mini R0B 2D16-V7R5: Ge", 1, "1-2", "2D16V7R5", "0c45", "636d"),
            ("video2", "HD Webcam: HD Webcam", 0, "1-3", "SN0001", "046d", "0825")]
    (dev / "v4l" / "by-id").mkdir(parents=True)
    (dev / "v4l" / "by-path").mkdir(parents=True)
    for node, name, index, port, serial, vid, pid in cams:
        usb = devices / port
        (usb / f"{port}:1.0").mkdir(parents=True, exist_ok=True)
        for attr, value in (("serial", serial), ("idVendor", vid), ("idProduct", pid),
                            ("product", name.split(":")[0]), ("manufacturer", "Acme")):
            (usb / attr).write_text(value + "\n")
        d = sysfs / node
        d.mkdir(parents=True)
        (d / "name").write_text(name + "\n")
        (d / "index").write_text(f"{index}\n")
        os.symlink(usb / f"{port}:1.0", d / "device")
        (dev / node).write_text("")
        product = name.split(":")[0].replace(" ", "_")
        os.symlink(f"../../{node}", dev / "v4l" / "by-id" / f"usb-Acme_{product}_{serial}-video-index{index}")
        os.symlink(f"../../{node}", dev / "v4l" / "by-path" / f"pci-0000:00:14.0-usb-0:{port[-1]}:1.0-video-index{index}")
    return sysfs, dev


def test_cameras_are_listed_with_serial_and_stable_paths(tmp_path):
    sysfs, dev = _fake_tree(tmp_path)
    cams = list_cameras(sysfs, dev)
    assert [c.index for c in cams] == [0, 1, 2]
    mini, meta, web = cams
    assert mini.path == str(dev / "video0") and mini.name.startswith("GelSight Mini")
    assert (mini.serial, mini.vendor_id, mini.product_id) == ("2D16V7R5", "0c45", "636d")
    assert mini.by_id.endswith("usb-Acme_GelSight_Mini_R0B_2D16-V7R5_2D16V7R5-video-index0")
    assert mini.is_image_node and not meta.is_image_node and web.serial == "SN0001"
    # the command: a table, and JSON for scripts
    res = runner.invoke(app, ["cameras", "--sysfs", str(sysfs), "--dev", str(dev)],
                        env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    assert "2D16V7R5" in res.output and "metadata?" in res.output and "serial:SERIAL" in res.output
    res = runner.invoke(app, ["cameras", "--json", "--sysfs", str(sysfs), "--dev", str(dev)])
    listed = json.loads(res.output)
    assert [c["serial"] for c in listed] == ["2D16V7R5", "2D16V7R5", "SN0001"]
    res = runner.invoke(app, ["cameras", "--sysfs", str(tmp_path / "none")])
    assert res.exit_code == 0 and "no video devices found" in res.output


def test_source_by_serial_or_by_id_path_finds_the_image_node(tmp_path):
    sysfs, dev = _fake_tree(tmp_path)
    assert parse_source("serial:SN0001") == CameraSourceConfig(device="serial:SN0001")
    assert resolve_camera("serial:2D16V7R5", sysfs, dev) == str(dev / "video0")   # not video1
    assert resolve_camera("serial:SN0001", sysfs, dev) == str(dev / "video2")
    link = next((dev / "v4l" / "by-id").glob("*SN0001*"))
    assert resolve_camera(str(link), sysfs, dev) == os.path.realpath(dev / "video2")
    assert resolve_camera(3, sysfs, dev) == 3
    with pytest.raises(CameraNotFoundError, match="no camera with serial 'XYZ'.*SN0001"):
        resolve_camera("serial:XYZ", sysfs, dev)


class FakeV4L2:
    """A camera driver as OpenCV's V4L2 backend presents it: sizes snap to the modes the camera
    has, automatic exposure and white balance drift to the scene's values while on, and setting
    a control in automatic mode is refused."""

    MODES = [(640, 480), (1280, 720)]

    def __init__(self, device):
        self.device = device
        self.p = {cv2.CAP_PROP_FRAME_WIDTH: 1280, cv2.CAP_PROP_FRAME_HEIGHT: 720,
                  cv2.CAP_PROP_FPS: 30.0, cv2.CAP_PROP_FOURCC: cv2.VideoWriter_fourcc(*"YUYV"),
                  cv2.CAP_PROP_AUTO_EXPOSURE: V4L2_EXPOSURE_AUTO, cv2.CAP_PROP_EXPOSURE: 300.0,
                  cv2.CAP_PROP_AUTO_WB: 1, cv2.CAP_PROP_WB_TEMPERATURE: 6500.0}
        self.frame = np.zeros((480, 640, 3), np.uint8)

    def isOpened(self):
        return True

    def set(self, prop, value):
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            w = value if prop == cv2.CAP_PROP_FRAME_WIDTH else self.p[cv2.CAP_PROP_FRAME_WIDTH]
            mode = min(self.MODES, key=lambda m: abs(m[0] - w))
            self.p[cv2.CAP_PROP_FRAME_WIDTH], self.p[cv2.CAP_PROP_FRAME_HEIGHT] = mode
            return True
        if prop == cv2.CAP_PROP_FPS:
            self.p[prop] = min(float(value), 30.0)
            return True
        if prop == cv2.CAP_PROP_EXPOSURE and self.p[cv2.CAP_PROP_AUTO_EXPOSURE] != V4L2_EXPOSURE_MANUAL:
            return False
        if prop == cv2.CAP_PROP_WB_TEMPERATURE and self.p[cv2.CAP_PROP_AUTO_WB]:
            return False
        self.p[prop] = value
        return True

    def get(self, prop):
        return float(self.p.get(prop, 0.0))

    def read(self):
        if self.p[cv2.CAP_PROP_AUTO_EXPOSURE] != V4L2_EXPOSURE_MANUAL:   # auto: drift to 157
            self.p[cv2.CAP_PROP_EXPOSURE] += 0.5 * (157.0 - self.p[cv2.CAP_PROP_EXPOSURE])
        if self.p[cv2.CAP_PROP_AUTO_WB]:
            self.p[cv2.CAP_PROP_WB_TEMPERATURE] += 0.5 * (4800.0 - self.p[cv2.CAP_PROP_WB_TEMPERATURE])
        h, w = int(self.p[cv2.CAP_PROP_FRAME_HEIGHT]), int(self.p[cv2.CAP_PROP_FRAME_WIDTH])
        return True, np.zeros((h, w, 3), np.uint8)

    def release(self):
        pass


def test_camera_is_asked_for_the_plugin_size_and_locks_exposure_and_white_balance(tmp_path,
                                                                                 caplog):
    from tactile_deploy.runtime.sources.factory import camera_config_for_plugin, make_source

    plugin = build_test_plugin(tmp_path / "p", n_frames=2)
    default = CameraSourceConfig(device=0, fps=25.0, exposure="lock", white_balance="lock",
                                 settle_s=0.05)
    with_camera = SimpleNamespace(manifest=plugin.manifest.model_copy(
        update={"default_source": default}), name="p", hooks=plugin.hooks)
    cfg = camera_config_for_plugin(parse_source("0"), with_camera)      # --source 0
    assert (cfg.width_px, cfg.height_px, cfg.fps) == (640, 480, 25.0)
    assert (cfg.exposure, cfg.white_balance, cfg.settle_s) == ("lock", "lock", 0.05)
    drivers = []
    cam = make_source(parse_source("0"), with_camera,
                      capture_factory=lambda d: drivers.append(FakeV4L2(d)) or drivers[-1])
    with cam:
        frame = cam.read()
    drv = drivers[-1]
    assert frame.image.shape == (480, 640, 3)
    # locked at what the automatic controls chose, in manual mode
    assert drv.p[cv2.CAP_PROP_AUTO_EXPOSURE] == V4L2_EXPOSURE_MANUAL
    assert drv.p[cv2.CAP_PROP_EXPOSURE] == pytest.approx(157.0, abs=1.0)
    assert drv.p[cv2.CAP_PROP_AUTO_WB] == 0
    assert drv.p[cv2.CAP_PROP_WB_TEMPERATURE] == pytest.approx(4800.0, abs=20.0)
    got = cam.settings["delivered"]
    assert (got["width_px"], got["height_px"], got["fps"], got["fourcc"]) == (640, 480, 25.0, "YUYV")
    assert got["exposure"] == drv.p[cv2.CAP_PROP_EXPOSURE] and cam.settings["refused"] == []
    # manual values; a size the camera does not have is reported, not hidden
    drivers.clear()
    cfg = CameraSourceConfig(device=0, width_px=800, height_px=600, fps=60.0, exposure=120.0,
                             white_balance=5000.0)
    cam = OpenCVCamera(cfg, capture_factory=lambda d: drivers.append(FakeV4L2(d)) or drivers[-1])
    with caplog.at_level(logging.WARNING), cam:
        cam.read()
    assert drivers[-1].p[cv2.CAP_PROP_EXPOSURE] == 120.0
    assert drivers[-1].p[cv2.CAP_PROP_WB_TEMPERATURE] == 5000.0
    assert "does not deliver what was asked" in caplog.text
    assert "width_px 640 (asked 800)" in caplog.text and "fps 30 (asked 60)" in caplog.text


def test_camera_code_path_on_a_real_opencv_capture_of_a_file(tmp_path):
    """The camera source with OpenCV's own VideoCapture (on a file instead of a device): frames
    arrive converted to RGB, the settings it cannot change are reported as refused, what it
    delivers is read back and ends up in the run summary."""
    from tactile_deploy.runtime.predictor import MeshPredictor
    from tactile_deploy.runtime.run import Runner, RunOptions, summary_text
    from tactile_deploy.runtime.sources.npz import load_clip
    from tactile_deploy.runtime.sources.video import write_video

    plugin = build_test_plugin(tmp_path / "p", n_frames=4)
    frames, _, _ = load_clip(plugin.demo_clip_path())
    video = write_video(tmp_path / "clip.avi", frames, fps=20.0, fourcc="MJPG")
    direct = []
    cap = cv2.VideoCapture(str(video))
    while (ok := cap.read())[0]:
        direct.append(cv2.cvtColor(ok[1], cv2.COLOR_BGR2RGB))
    # The grab thread can reach the 4-frame file's end before a loaded machine's runner has
    # taken 2 frames (it failed so once under pytest -n 2): reopening the file goes on from its start.
    cfg = CameraSourceConfig(device=str(video), width_px=640, height_px=480, fps=20.0,
                             exposure=100.0, reconnect_timeout_s=5.0)
    cam = OpenCVCamera(cfg, capture_factory=cv2.VideoCapture)
    summary = Runner(MeshPredictor.from_plugin(plugin), cam, RunOptions(max_frames=2)).run()
    assert summary.frames == 2
    got = summary.source_settings["delivered"]
    assert (got["width_px"], got["height_px"], got["fps"], got["fourcc"]) == (640, 480, 20.0, "MJPG")
    assert "exposure" in summary.source_settings["refused"]        # a file has no exposure
    assert "camera delivered 640x480 px MJPG at 20 fps" in summary_text(summary)
    with OpenCVCamera(cfg, capture_factory=cv2.VideoCapture) as cam2:
        f = cam2.read()
    assert any(np.array_equal(f.image, d) for d in direct)          # RGB, as decoded
