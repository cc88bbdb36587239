"""Drift of the no-contact image: what the calibration saw, and a check of every frame against it.

The shading model and the learned read-out read a frame as its difference from the no-contact
reference frame, after removing a per-channel illumination offset estimated on the frame's
non-contact pixels (:func:`~tactile_deploy.imaging.shading.frame_offset`). Two things drift in
use: the LEDs' brightness (the offset grows) and the gel or the optics (the non-contact pixels
no longer match the reference after the offset: the residual grows). A calibration records what
it saw of both (:class:`ReferenceRange`, in the plugin's manifest); :class:`DriftMonitor` measures
every few frames and warns once when a frame leaves that range (and once when it is back),
naming the command that re-takes the reference (``tactile-deploy reference``).

Frames: (H, W, 3) uint8 RGB, raw camera pixels; grey levels 0-255.
"""

from __future__ import annotations

import logging

import numpy as np
from pydantic import Field

from tactile_deploy.fileformat import StrictModel

log = logging.getLogger(__name__)


class ReferenceRange(StrictModel):
    """The no-contact image as the calibration saw it (grey levels)."""

    offset_grey_max: tuple[float, float, float] = Field(
        description="Largest |illumination offset| per channel (R, G, B) of the calibration's "
        "frames against the reference, grey levels.")
    residual_grey_max: float = Field(
        ge=0, description="Largest RMS of the non-contact pixels' difference from the reference "
        "after the offset, over the calibration's frames, grey levels.")
    n_frames: int = Field(ge=1, description="Frames the range was measured on.")


def non_contact_residual(frame: np.ndarray, reference: np.ndarray, offset: np.ndarray,
                         inlier_grey: float = 12.0, step: int = 3) -> float:
    """RMS (grey levels) of ``frame - reference - offset`` over the pixels (every ``step``-th)
    whose three channels lie within ``inlier_grey`` of it: the non-contact area's mismatch."""
    d = frame[::step, ::step].astype(np.float32) - reference[::step, ::step] - offset
    inliers = np.all(np.abs(d) < inlier_grey, axis=-1)
    if not inliers.any():
        return float(inlier_grey)
    return float(np.sqrt(np.mean(d[inliers] ** 2)))


def measure(frames, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (N, 3) and non-contact residuals (N,) of frames against ``reference``."""
    from tactile_deploy.imaging.shading import frame_offset

    offs, res = [], []
    for f in frames:
        off = frame_offset(f, reference)
        offs.append(off)
        res.append(non_contact_residual(f, reference, off))
    return np.asarray(offs, np.float64).reshape(-1, 3), np.asarray(res, np.float64)


def reference_range(frames, reference: np.ndarray) -> ReferenceRange:
    """The :class:`ReferenceRange` of calibration frames (presses and no-contact frames alike:
    the offset and the residual are measured on the non-contact pixels)."""
    offs, res = measure(frames, reference)
    return ReferenceRange(offset_grey_max=tuple(float(v) for v in np.abs(offs).max(axis=0)),
                          residual_grey_max=float(res.max()), n_frames=len(res))


class DriftMonitor:
    """Checks frames against a :class:`ReferenceRange` (module docstring).

    A frame has drifted when a channel's |offset| exceeds ``1.5 x`` the calibration's largest
    plus 4 grey levels, or its non-contact residual exceeds ``1.5 x`` the calibration's largest
    plus 1 grey level (margins for camera noise on a few frames). ``every``: frames between
    checks.
    """

    def __init__(self, rng: ReferenceRange, reference: np.ndarray, sensor: str = "SENSOR",
                 every: int = 5):
        self.range = rng
        self.reference = np.ascontiguousarray(reference)
        self.sensor = sensor
        self.every = max(1, int(every))
        self.offset_limit = 1.5 * np.asarray(rng.offset_grey_max) + 4.0
        self.residual_limit = 1.5 * rng.residual_grey_max + 1.0
        self.drifted = False
        self.drifted_frames = 0
        self._seen = 0

    def check(self, frame: np.ndarray, index: int | None = None) -> str | None:
        """Measure one frame (every ``every``-th call); returns the warning text when the
        stream leaves (or comes back into) the calibrated range, else None."""
        from tactile_deploy.imaging.shading import frame_offset

        self._seen += 1
        if (self._seen - 1) % self.every or frame.shape != self.reference.shape:
            return None
        off = frame_offset(frame, self.reference)
        res = non_contact_residual(frame, self.reference, off)
        out = bool(np.any(np.abs(off) > self.offset_limit) or res > self.residual_limit)
        where = "" if index is None else f"frame {index}: "
        if out:
            self.drifted_frames += 1
        if out and not self.drifted:
            self.drifted = True
            rgb = ", ".join(f"{v:+.0f}" for v in off)
            seen = ", ".join(f"{v:.0f}" for v in self.range.offset_grey_max)
            return (f"{where}the no-contact image has drifted beyond what the calibration saw "
                    f"(illumination offset R, G, B {rgb} grey levels against at most {seen}; "
                    f"non-contact mismatch {res:.1f} against at most "
                    f"{self.range.residual_grey_max:.1f}): depth and meshes may be off. With "
                    f"nothing touching the sensor, re-take the reference: tactile-deploy "
                    f"reference --sensor {self.sensor}")
        if not out and self.drifted:
            self.drifted = False
            return f"{where}the no-contact image is back within the calibrated range"
        return None


class DriftCheckingHooks:
    """Plugin hooks that run a :class:`DriftMonitor` on every raw frame and log its warnings,
    then hand the frame to the plugin's own hooks (which they wrap)."""

    def __init__(self, hooks, monitor: DriftMonitor):
        self.inner = hooks
        self.monitor = monitor
        self._armed = False

    def preprocess_frame(self, frame: np.ndarray) -> np.ndarray:
        if self._armed:   # the pipeline's first call is the reference frame itself
            message = self.monitor.check(frame)
            if message:
                log.warning(message)
        self._armed = True
        return self.inner.preprocess_frame(frame)

    def postprocess_depth(self, depth_mm: np.ndarray) -> np.ndarray:
        return self.inner.postprocess_depth(depth_mm)

    def open_source(self, config):
        return self.inner.open_source(config)
