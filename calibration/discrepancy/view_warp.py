"""Depth maps seen through a camera that is not the one the imaging pipeline was calibrated for.

A sensor's depth maps come from its imaging pipeline, which maps camera pixels to the sensing
plane with the *calibrated* camera mapping ``N``. If the real optics map the plane with another
mapping ``R`` (an optics effect: extra lens distortion, anisotropic pixel scale), the surface
point q is imaged at pixel ``R(q)`` and reported at the plane point ``p = N^-1(R(q))``. The
measured map at p therefore shows the surface at::

    q(p) = R^-1(N(p))            (sensor frame, mm)

and, since a shading pipeline measures slopes (mm/mm) and integrates them over the calibrated
grid, its depth is scaled by the local stretch of the view: ``measured(p) = true(q(p)) /
sqrt(det dq/dp)`` (the isotropic part; an anisotropic stretch is integrated as a least-squares
compromise between the two directions, of which this is the first-order mean). Outside the
camera's view (raw pixels off the frame) the map is left as it is.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates

from tactile_deploy.imaging.camera_mapping import (
    CameraMapping,
    pixels_to_sensor_mm,
    sensor_mm_to_pixels,
)


class ViewWarp:
    """The change of a (128, 128) depth map when ``calibrated`` is replaced by ``true``.

    camera : the :class:`~tactile_deploy.camera.depth.DepthCamera` of the maps.
    """

    def __init__(self, calibrated: CameraMapping, true: CameraMapping, camera):
        centres = camera.pixel_centres_mm()  # (H, W, 2), image rows
        h, w = centres.shape[:2]
        p = centres.reshape(-1, 2)
        uv = sensor_mm_to_pixels(p, calibrated)
        width, height = calibrated.image_size
        inside = ((uv[:, 0] >= -0.5) & (uv[:, 0] <= width - 0.5) & (uv[:, 1] >= -0.5)
                  & (uv[:, 1] <= height - 0.5))
        q = p.copy()
        with np.errstate(all="ignore"):
            q[inside] = pixels_to_sensor_mm(uv[inside], true)
        ok = np.all(np.isfinite(q), axis=1)
        q[~ok] = p[~ok]
        q = q.reshape(h, w, 2)
        pitch = camera.pitch_mm
        dqx_dc = np.gradient(q[..., 0], axis=1) / pitch
        dqy_dc = np.gradient(q[..., 1], axis=1) / pitch
        dqx_dr = -np.gradient(q[..., 0], axis=0) / pitch  # rows run along -y
        dqy_dr = -np.gradient(q[..., 1], axis=0) / pitch
        det = dqx_dc * dqy_dr - dqy_dc * dqx_dr
        gain = np.where(det > 0.25, 1.0 / np.sqrt(np.maximum(det, 0.25)), 1.0)
        gain[~(inside & ok).reshape(h, w)] = 1.0
        half = camera.half_extent_mm
        #: (2, H, W) fractional (row, column) of q(p) in the map; (H, W) depth gain.
        self.coords = np.stack([(half - q[..., 1]) / pitch - 0.5, (q[..., 0] + half) / pitch - 0.5])
        self.gain = gain
        #: largest displacement |q - p| over the view, mm
        self.max_shift_mm = float(np.abs(q.reshape(-1, 2) - p).max())

    def __call__(self, depth_mm: np.ndarray) -> np.ndarray:
        """The map ``depth_mm`` (128, 128) mm as the pipeline reports it, (128, 128) float64."""
        d = np.asarray(depth_mm, np.float64)
        return self.gain * map_coordinates(d, self.coords, order=1, mode="constant", cval=0.0)
