"""Pixel scale: the camera's millimetres per pixel differ from the calibrated ones (optical).

Physics. The most common camera-calibration error: the calibration target's pitch or the
distance to the pad was off, so every millimetre per pixel is off by the same factor
(``scale``); and non-square effective pixels (an oblique view, a mirror, a slightly anamorphic
lens) make them differ along one image direction (``anisotropy`` along the image direction
``axis_deg``, degrees from +u toward +v; 90 = along the rows, v). The mapping from undistorted
pixels to the pad becomes ``H S`` with ``S = (1 + scale) (I + anisotropy n n^T)`` about the
principal point (n the unit vector along ``axis_deg``): features look smaller by ``1 + scale``
and shorter along n by ``1 + anisotropy``.

* Frames: the camera mapping's homography becomes ``H S`` (exact).
* Depth maps made by a pipeline calibrated on the nominal camera: the map at plane point p shows
  the surface at ``q = H S H^-1 p``, its values following the local stretch of that view with
  ``depth_gain_exponent`` (1: a pipeline integrating slopes; 0: a resampled map;
  :mod:`tactile_deploy.sensors.depth_view`).

Signature: a circular contact images as an ellipse whose axis ratio along n is
``1 / (1 + anisotropy)``, and every contact's image is ``1 / (1 + scale)`` as large; null value
``scale = anisotropy = 0`` reproduces the nominal sensor exactly.

Residual it leaves: a general perspective change of the view (model it in the camera mapping);
the camera mapping calibration measures and removes it.

Realistic range: scale -0.08 to 0.08 (a target 1 mm closer to a 15 mm focal distance: 7 %),
anisotropy -0.05 to 0.05 (a 3 degree tilt of the view gives 0.1 %, a mirror 20 degrees off 45
several percent).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.imaging.camera_mapping import camera_mapping_from_parameters
from tactile_deploy.sensors.effects.base import Effect, EffectParams


class PixelScaleParams(EffectParams):
    anisotropy: float = Field(0.0, ge=-0.3, le=0.3, description="Relative change of mm per px "
                              "along the image direction axis_deg; 0 = square (null).")
    axis_deg: float = Field(90.0, ge=-180.0, le=360.0, description="Image direction of the "
                            "anisotropy, degrees from +u toward +v (90: along the rows, v).")
    scale: float = Field(0.0, ge=-0.3, le=0.3, description="Relative change of mm per px in "
                         "every direction; 0 = none (null).")
    depth_gain_exponent: float = Field(1.0, ge=-1.0, le=2.0, description="Depth maps: values "
                                       "scale as det(view stretch)^(-exponent/2); 1 = a pipeline "
                                       "integrating slopes, 0 = a resampled map.")


class PixelScale(Effect):
    __doc__ = __doc__
    name = "pixel_scale"
    kind = "optical"
    stage = "optics"
    Params = PixelScaleParams
    moves_view = True
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"anisotropy": (-0.05, 0.05),
                                                                 "scale": (-0.08, 0.08)}

    @property
    def is_null(self) -> bool:
        return self.params.anisotropy == 0.0 and self.params.scale == 0.0

    def stretch_px(self, cx_px: float, cy_px: float) -> np.ndarray:
        """(3, 3): undistorted px -> undistorted px of the stretched view, about (cx, cy)."""
        p = self.params
        a = math.radians(p.axis_deg)
        n = np.array([math.cos(a), math.sin(a)])
        s2 = (1.0 + p.scale) * (np.eye(2) + p.anisotropy * np.outer(n, n))
        c = np.array([cx_px, cy_px])
        out = np.eye(3)
        out[:2, :2] = s2
        out[:2, 2] = c - s2 @ c
        return out

    def optics(self, model):
        if self.is_null:
            return model

        cam = model.camera
        stretch = self.stretch_px(cam.intrinsics.cx_px, cam.intrinsics.cy_px)
        new = camera_mapping_from_parameters(cam.image_size, cam.camera_matrix, cam.dist_coeffs,
                                             cam.homography @ stretch, grid=cam.grid)
        return model.model_copy(update={"camera": new})

    def view_points(self, xy_mm: np.ndarray, camera) -> np.ndarray:
        xy = np.asarray(xy_mm, np.float64)
        if self.is_null:
            return xy
        h = camera.homography
        m = h @ self.stretch_px(camera.intrinsics.cx_px, camera.intrinsics.cy_px) @ \
            np.linalg.inv(h)
        q = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ m.T
        return q[:, :2] / q[:, 2:3]
