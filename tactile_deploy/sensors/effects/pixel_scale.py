"""Anisotropic pixel scale: the pad's scale differs along image rows and columns (optical).

Physics. Non-square effective pixels: an oblique view, a mirror or a lens with slight anamorphism
makes the millimetres per pixel along the image rows (v) differ from those along the columns
(u). This effect stretches the mapping from pixels to the pad along v about the image centre by
``1 + anisotropy``: mm per px along v is multiplied by it (the homography becomes
``H diag-about-centre(1, 1 + anisotropy)``), so features look shorter along v by that factor.

Signature: a circular contact images as an ellipse whose v / u axis ratio is
``1 / (1 + anisotropy)``; null value ``anisotropy = 0`` reproduces the nominal sensor exactly.

Residual it leaves: a general affine or perspective change of the view (model it in the camera
mapping); the camera mapping calibration measures and removes it.

Realistic range: -0.05 to 0.05 (a 3 degree tilt of the view gives 0.1 %, a mirror 20 degrees off
45 several percent).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from tactile_deploy.imaging.camera_mapping import camera_mapping_from_parameters
from tactile_deploy.sensors.effects.base import Effect, EffectParams


class PixelScaleParams(EffectParams):
    anisotropy: float = Field(0.0, ge=-0.3, le=0.3, description="Relative change of mm per px "
                              "along image rows (v) against columns (u); 0 = square (null).")


class PixelScale(Effect):
    __doc__ = __doc__
    name = "pixel_scale"
    kind = "optical"
    stage = "optics"
    Params = PixelScaleParams
    realistic_range: ClassVar[dict[str, tuple[float, float]]] = {"anisotropy": (-0.05, 0.05)}

    def optics(self, model):
        a = self.params.anisotropy
        if a == 0.0:
            return model

        cam = model.camera
        cy = cam.intrinsics.cy_px
        stretch = np.array([[1.0, 0.0, 0.0], [0.0, 1.0 + a, -a * cy], [0.0, 0.0, 1.0]])
        new = camera_mapping_from_parameters(cam.image_size, cam.camera_matrix, cam.dist_coeffs,
                                             cam.homography @ stretch, grid=cam.grid)
        return model.model_copy(update={"camera": new})
