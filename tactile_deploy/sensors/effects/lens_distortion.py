"""Lens distortion: extra radial distortion of the camera lens (optical, optics stage).

Physics. Wide-angle lenses of compact sensors image straight lines of the pad as curves; the
OpenCV radial model maps undistorted normalised coordinates x to ``x (1 + k1 r^2 + k2 r^4)``.
This effect adds ``k1``, ``k2`` to the camera mapping's own coefficients (the homography to the
pad is unchanged), so every feature moves radially from the principal point by
``k1 r^3 + k2 r^5`` (normalised units; barrel for k1 < 0).

Signature: the image position of a pad point moves radially, by an amount that grows with the
cube of its distance from the principal point; null value ``k1 = k2 = 0`` reproduces the nominal
sensor exactly.

Residual it leaves: tangential (decentring) terms and higher orders; a camera mapping calibrated
on the distorted sensor (``tactile-deploy calibrate camera``) removes it.

Realistic range: k1 from -0.35 to 0.05 (Raspberry Pi wide-angle modules reach -0.3), |k2| < 0.1.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from tactile_deploy.imaging.camera_mapping import camera_mapping_from_parameters
from tactile_deploy.sensors.effects.base import Effect, EffectParams


class LensDistortionParams(EffectParams):
    k1: float = Field(0.0, ge=-0.6, le=0.3, description="Added r^2 coefficient, dimensionless "
                      "(normalised coordinates); 0 = none (null).")
    k2: float = Field(0.0, ge=-0.3, le=0.3, description="Added r^4 coefficient, dimensionless.")


class LensDistortion(Effect):
    __doc__ = __doc__
    name = "lens_distortion"
    kind = "optical"
    stage = "optics"
    Params = LensDistortionParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"k1": (-0.35, 0.05), "k2": (-0.1, 0.1)}

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
