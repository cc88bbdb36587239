"""Sampled camera pixels with their true surface and observed colour, and the per-frame grey
offsets solved over their far field."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tactile_deploy.calibration.optics_fit.parameters import OpticsFitError
from tactile_deploy.calibration.optics_fit.press_surface import sphere_press_surface

#: Grey level at or above which a channel counts as saturated.
SATURATED_GREY = 254

@dataclass
class ShadingSamples:
    """Sampled camera pixels with their true surface and observed colour.

    uv_px : (k, 2) raw px; xy_mm : (k, 2) sensor-frame points at rest, mm; z_mm, fx, fy : (k,)
    surface height (mm) and slopes there; observed : (k, 3) float64 grey levels (RGB);
    frame : (k,) int, index of the frame each sample comes from; far : (k,) bool, far-field
    pixels used for the per-frame offsets; weight : (k,) float, least-squares weight.
    """

    uv_px: np.ndarray
    xy_mm: np.ndarray
    z_mm: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    observed: np.ndarray
    frame: np.ndarray
    far: np.ndarray
    weight: np.ndarray
    circle_mm: np.ndarray | None = None
    albedo: np.ndarray | None = None

    def __post_init__(self):
        k = len(self.uv_px)
        for name in ("xy_mm", "z_mm", "fx", "fy", "observed", "frame", "far", "weight"):
            arr = getattr(self, name)
            if len(arr) != k:
                raise OpticsFitError(f"ShadingSamples.{name} has {len(arr)} rows, expected {k}")
        if k == 0:
            raise OpticsFitError("no samples to fit")

    @staticmethod
    def concatenate(parts: Sequence[ShadingSamples]) -> ShadingSamples:
        names = ("uv_px", "xy_mm", "z_mm", "fx", "fy", "observed", "frame", "far", "weight")
        out = ShadingSamples(*(np.concatenate([getattr(p, n) for p in parts]) for n in names))
        if all(p.circle_mm is not None for p in parts):
            out.circle_mm = np.concatenate([p.circle_mm for p in parts])
        return out

    def press_surface(self, sinking_scale: float, ball_radius_mm: float,
                      radius_scale: float = 1.0):
        """``(z, fx, fy)`` of every sample from ``circle_mm`` (:func:`sphere_press_surface`),
        with every contact radius multiplied by ``radius_scale``."""
        z = np.zeros(len(self.z_mm))
        fx, fy = z.copy(), z.copy()
        c = self.circle_mm
        for key in np.unique(c[np.isfinite(c[:, 2])], axis=0):
            sel = np.all(c == key, axis=1)
            a = min(key[2] * radius_scale, 0.98 * ball_radius_mm)
            z[sel], fx[sel], fy[sel] = sphere_press_surface(self.xy_mm[sel], key[:2], a,
                                                            ball_radius_mm, sinking_scale)
        return z, fx, fy

def usable(observed: np.ndarray) -> np.ndarray:
    """(k,) bool: no channel saturated."""
    return np.all(observed < SATURATED_GREY, axis=1)

def frame_offsets(residual: np.ndarray, frame: np.ndarray, far: np.ndarray,
                  n_frames: int) -> np.ndarray:
    """Per-frame, per-channel mean residual over far-field samples: (n_frames, 3) grey levels."""
    out = np.zeros((n_frames, 3))
    for f in range(n_frames):
        sel = (frame == f) & far
        if np.any(sel):
            out[f] = residual[sel].mean(axis=0)
    return out
