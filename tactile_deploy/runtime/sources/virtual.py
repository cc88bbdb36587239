"""A virtual sensor (:mod:`tactile_deploy.sensors`) as a frame source: scripted presses rendered
as camera frames, for trying the runtime without hardware and for end-to-end checks.

The default script: ``n_frames`` at the sensor's frame rate, with presses of library indenters at
seeded random places inside the camera's view (ramp in, hold, ramp out), a short rest between.
Timestamps are the script's (``t_source_ns``); frames come as fast as they are rendered (a few
per second) unless ``live`` paces them to the wall clock.
"""

from __future__ import annotations

import numpy as np

from tactile_deploy.imaging.camera_mapping import pixels_to_sensor_mm
from tactile_deploy.runtime.sources.base import Frame, FrameSource, SourceError
from tactile_deploy.sensors import load_sensor
from tactile_deploy.sensors.catalog import UnknownSensorError
from tactile_deploy.sensors.virtual import PressEvent, PressScript

#: Indenters of the default script.
SCRIPT_INDENTERS = ("sphere_r4", "cylinder_side", "cross", "flat_punch", "ellipsoid", "sphere_r6")


def default_script(sensor, n_frames: int, seed: int = 0):
    """A :class:`~tactile_deploy.sensors.virtual.PressScript` filling ``n_frames`` frames."""

    fps = sensor.config.fps
    duration = n_frames / fps
    rng = np.random.default_rng([seed, 0x76697274])
    x0, x1, y0, y1 = _view_box(sensor)
    events, t = [], 0.1
    # phases of 0.25, 0.2, 0.25 s and 0.1 s of rest; shorter when one press would not fit
    k = min(1.0, max(duration - 0.1, 1e-3) / 0.8)
    press, hold, release, rest = 0.25 * k, 0.2 * k, 0.25 * k, 0.1 * k
    while t + press + hold + release <= duration + 1e-9:
        events.append(PressEvent(
            indenter=SCRIPT_INDENTERS[len(events) % len(SCRIPT_INDENTERS)],
            x_mm=float(rng.uniform(x0, x1)), y_mm=float(rng.uniform(y0, y1)),
            theta_deg=float(rng.uniform(0, 180)), depth_mm=float(rng.uniform(0.4, 0.9)),
            start_s=t, press_s=press, hold_s=hold, release_s=release))
        t += press + hold + release + rest
    return PressScript(tuple(events), duration_s=duration)


def _view_box(sensor, margin_mm: float = 3.0):
    """Box (x0, x1, y0, y1) mm the camera sees (pixel centres 5 % inside the image), shrunk."""

    cam = sensor.optics.camera
    w, h = cam.image_size
    u, v = np.meshgrid(np.linspace(0.05 * w, 0.95 * w, 9), np.linspace(0.05 * h, 0.95 * h, 9))
    xy = pixels_to_sensor_mm(np.stack([u.ravel(), v.ravel()], 1), cam)
    x0, y0 = np.percentile(xy, 10, axis=0)
    x1, y1 = np.percentile(xy, 90, axis=0)
    return x0 + margin_mm, max(x1 - margin_mm, x0 + margin_mm), y0 + margin_mm, max(
        y1 - margin_mm, y0 + margin_mm)


class VirtualSensorSource(FrameSource):
    """Frames of the virtual sensor ``sensor`` (name or JSON path) playing ``script`` (default:
    :func:`default_script`)."""

    def __init__(self, sensor: str, n_frames: int = 60, seed: int = 0, loop: bool = False,
                 script=None, live: bool = False):
        super().__init__()
        self.sensor_name = str(sensor)
        self.name = f"virtual sensor {self.sensor_name}"
        self.n_frames = int(n_frames)
        self.seed = int(seed)
        self.finite = not loop
        self._loop = bool(loop)
        self._script = script
        self._live = bool(live)
        self._sensor = None
        self._k = 0

    @property
    def frame_count(self) -> int | None:
        return None if self._loop else self.n_frames

    def _open(self) -> None:
        try:
            self._sensor = load_sensor(self.sensor_name)
        except UnknownSensorError as e:
            raise SourceError(f"{self.name}: {e}") from None
        if self._script is None:
            self._script = default_script(self._sensor, self.n_frames, self.seed)
        self._sensor.connect(self._script, live=self._live)
        self._k = 0

    def _read(self) -> Frame | None:
        if self._k >= self.n_frames:
            if not self._loop:
                return None
            self._sensor.connect(self._script, live=self._live)
            self._k = 0
        image = self._sensor.read()
        self._k += 1
        return self._frame(image, int(round(self._sensor.last_timestamp_s * 1e9)))

    def _close(self) -> None:
        if self._sensor is not None:
            self._sensor.disconnect()
