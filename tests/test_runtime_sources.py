"""Frame sources: recorded .npz clips, video files, image folders, the OpenCV camera (a fake
VideoCapture: frames, drops, a camera that vanishes and comes back or not), the factory and the
--source parser."""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np
import pytest
from test_runtime_support import FakeCapture

from tactile_deploy.runtime.sources.base import SourceDisconnectedError, SourceError
from tactile_deploy.runtime.sources.camera import OpenCVCamera
from tactile_deploy.runtime.sources.config import (
    CameraSourceConfig,
    DemoSourceConfig,
    ImageFolderSourceConfig,
    NpzSourceConfig,
    SourceSpecError,
    VideoSourceConfig,
    VirtualSourceConfig,
    parse_source,
)
from tactile_deploy.runtime.sources.factory import make_source, open_clip
from tactile_deploy.runtime.sources.npz import ClipFormatError, load_clip, save_clip
from tactile_deploy.runtime.sources.video import write_video


def _frames(n=5, h=48, w=64):
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    return np.stack([np.roll(base, 3 * i, axis=1) for i in range(n)])


# ------------------------------------------------------------------------------------ files
def test_npz_clip_round_trip_and_playback(tmp_path):
    frames = _frames()
    t = np.arange(5) * 40_000_000
    save_clip(tmp_path / "c.npz", frames, t, {"sensor": "x"})
    f2, t2, meta = load_clip(tmp_path / "c.npz")
    assert np.array_equal(f2, frames) and np.array_equal(t2, t) and meta == {"sensor": "x"}
    with make_source(NpzSourceConfig(path=str(tmp_path / "c.npz"))) as src:
        got = list(src)
    assert [g.index for g in got] == [0, 1, 2, 3, 4]
    assert [g.t_source_ns for g in got] == t.tolist()
    assert all(np.array_equal(g.image, f) for g, f in zip(got, frames))
    assert all(b.t_mono_ns >= a.t_mono_ns for a, b in zip(got, got[1:]))
    with make_source(NpzSourceConfig(path=str(tmp_path / "c.npz"), loop=True)) as src:
        idx = [src.read().t_source_ns for _ in range(7)]
    assert idx == [*t.tolist(), *t[:2].tolist()]


def test_npz_clip_errors(tmp_path):
    with pytest.raises(ClipFormatError, match="'frames' must be \\(N, H, W, 3\\) uint8"):
        save_clip(tmp_path / "a.npz", np.zeros((2, 4, 4), np.uint8), [0, 1])
    with pytest.raises(ClipFormatError, match="start at 0 and increase strictly"):
        save_clip(tmp_path / "a.npz", _frames(2), [0, 0])
    np.savez(tmp_path / "b.npz", images=_frames(2))
    with pytest.raises(ClipFormatError, match=r"\['frames', 'timestamps_ns'\] missing"):
        load_clip(tmp_path / "b.npz")
    (tmp_path / "c.npz").write_bytes(b"PK\x03\x04 broken")
    with pytest.raises(ClipFormatError, match="not a readable .npz"):
        load_clip(tmp_path / "c.npz")
    with pytest.raises(ClipFormatError, match="not found"):
        load_clip(tmp_path / "none.npz")


def test_video_file_is_rgb_with_timestamps(tmp_path):
    frames = np.zeros((6, 48, 64, 3), np.uint8)
    frames[..., 0] = 200                               # pure red in RGB
    frames[:, :, : 8 * 1] = 0
    write_video(tmp_path / "v.avi", frames, fps=25.0, fourcc="MJPG")
    with open_clip(tmp_path / "v.avi") as src:
        got = list(src)
    assert len(got) == 6
    img = got[2].image
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    assert img[20, 40, 0] > 150 and img[20, 40, 2] < 60   # red stays red (BGR converted)
    ts = [g.t_source_ns for g in got]
    assert ts[0] == 0 and np.allclose(np.diff(ts), 40e6, rtol=0.05)
    with pytest.raises(SourceError, match="file not found"):
        make_source(VideoSourceConfig(path=str(tmp_path / "none.mp4"))).connect()


def test_image_folder_skips_unreadable_files(tmp_path, caplog):
    frames = _frames(3)
    for i, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    (tmp_path / "001b.png").write_bytes(b"not a png")
    with caplog.at_level(logging.WARNING):
        with make_source(ImageFolderSourceConfig(path=str(tmp_path), fps=10)) as src:
            got = list(src)
    assert len(got) == 3 and src.stats.unreadable == 1
    assert all(np.array_equal(g.image, f) for g, f in zip(got, frames))
    assert [g.t_source_ns for g in got] == [0, 100_000_000, 200_000_000]
    assert "001b.png" in caplog.text
    with pytest.raises(SourceError, match="no files match"):
        make_source(ImageFolderSourceConfig(path=str(tmp_path), pattern="*.jpg")).connect()


# ------------------------------------------------------------------------------------ camera
def _camera(script, **cfg):
    config = CameraSourceConfig(device=3, **cfg)
    return OpenCVCamera(config, capture_factory=lambda dev: FakeCapture(script),
                        sleep=lambda s: time.sleep(min(s, 0.002)))


def test_camera_delivers_rgb_frames_and_counts_drops():
    bgr = [cv2.cvtColor(f, cv2.COLOR_RGB2BGR) for f in _frames(4)]
    script = {"frames": bgr, "period_s": 0.001}
    cam = _camera(script)
    with cam:
        first = cam.read()
        assert any(np.array_equal(first.image, f) for f in _frames(4))   # RGB again
        time.sleep(0.05)                      # the consumer is slow: frames pile up
        second = cam.read()
    produced = script["reads"]
    assert cam.stats.dropped > 5
    assert cam.stats.delivered + cam.stats.dropped <= produced <= cam.stats.delivered + cam.stats.dropped + 2
    assert second.t_mono_ns > first.t_mono_ns and second.t_source_ns is None


def test_camera_reconnects_after_vanishing(caplog):
    bgr = [cv2.cvtColor(f, cv2.COLOR_RGB2BGR) for f in _frames(2)]
    script = {"frames": bgr, "period_s": 0.0005, "fail_after": 3, "down_opens": 3}
    cam = _camera(script, reconnect_timeout_s=5.0)
    with caplog.at_level(logging.WARNING), cam:
        got = [cam.read() for _ in range(8)]
    assert all(g is not None for g in got)
    assert cam.stats.reconnects == 1
    assert script["opens"] == 1 + 4            # first open, 3 failed attempts, then success
    assert "stopped delivering frames" in caplog.text and "is back after 4 attempt(s)" in caplog.text


def test_camera_gone_for_good_raises_after_timeout():
    script = {"frames": [np.zeros((8, 8, 3), np.uint8)], "fail_after": 2, "down_opens": None}
    cam = _camera(script, reconnect_timeout_s=0.5, max_backoff_s=0.2)
    with cam:
        cam.read()
        with pytest.raises(SourceDisconnectedError, match="camera 3 disappeared and did not come "
                           "back within 0.5 s"):
            for _ in range(10):
                cam.read()


def test_camera_that_never_opens():
    script = {"frames": [], "gone": True, "down_opens": None}
    with pytest.raises(SourceError, match="camera 3 could not be opened"):
        _camera(script).connect()


# ------------------------------------------------------------------------------------ parsing
@pytest.mark.parametrize("text, kind", [
    ("demo", "demo"), ("0", "camera"), ("camera:2", "camera"), ("/dev/video2", "camera"),
    ("virtual", "virtual"), ("virtual:gelslim1", "virtual"), ("clip.mp4", "video"),
    ("rec.npz", "npz"),
])
def test_parse_source_forms(text, kind):
    cfg = parse_source(text)
    assert cfg.kind == kind
    if text == "virtual:gelslim1":
        assert cfg.sensor == "gelslim1"
    if text == "/dev/video2":
        assert cfg.device == "/dev/video2"


def test_parse_source_folder_and_unknown(tmp_path):
    assert parse_source(str(tmp_path)).kind == "images"
    with pytest.raises(SourceSpecError, match="Accepted forms"):
        parse_source("rtsp-something")


def test_factory_needs_a_plugin_for_demo_and_virtual():
    with pytest.raises(SourceError, match="--sensor"):
        make_source(DemoSourceConfig())
    with pytest.raises(SourceError, match="virtual:NAME"):
        make_source(VirtualSourceConfig())


def test_virtual_sensor_source(pad_sim):
    """The virtual sensor as a frame source: frames at its frame rate with scripted presses,
    an unknown sensor named with the shipped ones."""
    from tactile_deploy.runtime.sources.virtual import VirtualSensorSource

    src = make_source(parse_source("virtual:gelslim1").model_copy(update={"n_frames": 14}))
    assert isinstance(src, VirtualSensorSource)
    with src:
        got = list(src)
    assert len(got) == 14 and got[0].image.shape == (480, 640, 3)
    assert np.allclose(np.diff([g.t_source_ns for g in got]), 1e9 / 30, atol=1)
    change = [np.abs(g.image.astype(int) - got[0].image).max() for g in got]
    assert max(change) > 40                          # a press is in the clip
    with pytest.raises(SourceError, match="unknown virtual sensor 'nope'.*gelslim1"):
        make_source(parse_source("virtual:nope")).connect()
