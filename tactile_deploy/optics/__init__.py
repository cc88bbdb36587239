"""RGB optics of vision-based tactile sensors: model (units, validation) and renderer.

Numpy and OpenCV only. See docs/optics.md.
"""

from tactile_deploy.optics.model import (
    GelTexture,
    Light,
    OpticsModel,
    OpticsModelError,
    SensorNoise,
    Vignetting,
    load_optics,
    save_optics,
    simple_camera,
)
from tactile_deploy.optics.render import (
    OpticsRenderer,
    grid_for_camera,
    radiance_reference,
)

__all__ = [
    "GelTexture",
    "Light",
    "OpticsModel",
    "OpticsModelError",
    "OpticsRenderer",
    "SensorNoise",
    "Vignetting",
    "grid_for_camera",
    "load_optics",
    "radiance_reference",
    "save_optics",
    "simple_camera",
]
