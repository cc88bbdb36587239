"""Lens distortion: extra radial distortion of the camera lens (optical, optics stage).

Physics. Wide-angle lenses of compact sensors image straight lines of the pad as curves; the
OpenCV radial model maps undistorted normalised coordinates x to ``x (1 + k1 r^2 + k2 r^4)``.
This effect is a distortion the sensor's calibrated camera mapping does not have: ``k1``, ``k2``
(barrel for k1 < 0, pincushion for k1 > 0) about a centre ``centre_dx_px``, ``centre_dy_px``
away from the principal point, so every feature moves radially from that centre by ``k1 r^3 +
k2 r^5`` (normalised units).

* Frames: ``k1``, ``k2`` are added to the camera mapping's own coefficients (the homography to
  the pad is unchanged); the distortion is then about the principal point (the camera model has
  no other centre: a centre offset is not rendered in frames).
* Depth maps made by a pipeline calibrated on the nominal camera: the map at plane point p shows
  the surface at ``q = H(E^-1(H^-1 p))`` with H the homography (undistorted px -> mm) and E the
  extra distortion about its centre in undistorted normalised coordinates; the map's values
  follow the local stretch of that view with ``depth_gain_exponent`` (1: a pipeline integrating
  slopes; 0: a resampled map; :mod:`tactile_deploy.sensors.depth_view`). Through a camera whose
  homography is close to a similarity (every shipped one), a radial distortion of the depth map
  about a pad point is this effect with the centre at that point.

Signature: the image position of a pad point moves radially, by an amount that grows with the
cube of its distance from the centre; null value ``k1 = k2 = 0`` reproduces the nominal sensor
exactly (whatever the centre and exponent).

Residual it leaves: tangential (decentring) terms and higher orders; a camera mapping calibrated
on the distorted sensor (``tactile-deploy calibrate camera``) removes it.

Realistic range: k1 from -0.35 to 0.2 (Raspberry Pi wide-angle modules reach -0.3; a
calibration fitted on the image centre alone misses 0.1-0.2 either way), |k2| < 0.1, the centre
within 40 px of the principal point.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.imaging.camera_mapping import camera_mapping_from_parameters
from tactile_deploy.sensors.effects.base import Effect, EffectParams


class LensDistortionParams(EffectParams):
    k1: float = Field(0.0, ge=-0.6, le=0.6, description="Added r^2 coefficient, dimensionless "
                      "(normalised coordinates); 0 = none (null).")
    k2: float = Field(0.0, ge=-0.3, le=0.3, description="Added r^4 coefficient, dimensionless.")
    centre_dx_px: float = Field(0.0, ge=-200.0, le=200.0, description="Centre of the added "
                                "distortion right of the principal point, undistorted px (depth "
                                "maps only).")
    centre_dy_px: float = Field(0.0, ge=-200.0, le=200.0, description="Centre of the added "
                                "distortion below the principal point, undistorted px (depth "
                                "maps only).")
    depth_gain_exponent: float = Field(1.0, ge=-1.0, le=2.0, description="Depth maps: values "
                                       "scale as det(view stretch)^(-exponent/2); 1 = a pipeline "
                                       "integrating slopes, 0 = a resampled map.")


def _radial_inverse(rho_d: np.ndarray, k1: float, k2: float) -> np.ndarray:
    """rho with ``rho (1 + k1 rho^2 + k2 rho^4) = rho_d`` (Newton from rho_d), (k,)."""
    rho = np.array(rho_d, np.float64)
    for _ in range(30):
        r2 = rho * rho
        f = rho * (1.0 + r2 * (k1 + k2 * r2)) - rho_d
        df = 1.0 + r2 * (3.0 * k1 + 5.0 * k2 * r2)
        step = f / np.where(np.abs(df) < 1e-6, 1e-6, df)
        rho = rho - step
        if np.all(np.abs(step) < 1e-13):
            break
    return rho


class LensDistortion(Effect):
    __doc__ = __doc__
    name = "lens_distortion"
    kind = "optical"
    stage = "optics"
    Params = LensDistortionParams
    moves_view = True
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"k1": (-0.35, 0.2),
                                                                 "k2": (-0.1, 0.1)}

    @property
    def is_null(self) -> bool:
        return self.params.k1 == 0.0 and self.params.k2 == 0.0

    def optics(self, model):
        p = self.params
        if p.k1 == 0.0 and p.k2 == 0.0:
            return model

        cam = model.camera
        d = cam.dist_coeffs.copy()
        d[0] += p.k1
        d[1] += p.k2
        # The homography is kept; building the mapping rescales it to W = 1 at the (new)
        # undistorted image centre and re-derives mm per px.
        new = camera_mapping_from_parameters(cam.image_size, cam.camera_matrix, d,
                                             cam.homography, grid=cam.grid)
        return model.model_copy(update={"camera": new})

    def view_points(self, xy_mm: np.ndarray, camera) -> np.ndarray:
        p = self.params
        xy = np.asarray(xy_mm, np.float64)
        if p.k1 == 0.0 and p.k2 == 0.0:
            return xy
        k = camera.intrinsics
        h = camera.homography
        hom = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ np.linalg.inv(h).T
        u = hom[:, :2] / hom[:, 2:3]  # undistorted px
        x = (u[:, 0] - k.cx_px - p.centre_dx_px) / k.fx_px
        y = (u[:, 1] - k.cy_px - p.centre_dy_px) / k.fy_px
        rho_d = np.hypot(x, y)
        rho = _radial_inverse(rho_d, p.k1, p.k2)
        ratio = np.where(rho_d > 0, rho / np.where(rho_d > 0, rho_d, 1.0), 1.0)
        u2 = np.stack([x * ratio * k.fx_px + k.cx_px + p.centre_dx_px,
                       y * ratio * k.fy_px + k.cy_px + p.centre_dy_px], axis=1)
        q = np.concatenate([u2, np.ones((len(u2), 1))], axis=1) @ h.T
        return q[:, :2] / q[:, 2:3]
