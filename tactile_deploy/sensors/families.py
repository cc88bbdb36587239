"""Virtual sensors of the GelSight Mini and DIGIT families, built from their published optics.

``python -m tactile_deploy.sensors.families`` writes ``assets/sensors/gelsight_mini.json`` and
``assets/sensors/digit.json`` (loaded like every shipped virtual sensor,
:mod:`tactile_deploy.sensors.catalog`). Sensor frame as the pad families
(:mod:`tactile_deploy.pad.family`): image columns along +x, rows along -y, mm.

* ``digit``: 240 x 320 px portrait frames at 19.58 px per mm over the sensing area (the
  real DIGIT unit of FOTS), no lens distortion (TACTO renders DIGIT with a pinhole camera); three
  LEDs, red, green and blue, as point lights on a circle of 20 mm radius at 30, 150 and 270
  degrees, 17 mm behind the gel (TACTO ``config_digit.yml``: light plane at x = 5 mm, gel at
  22 mm); the 0.5 mm curve of the gel as the dome effect (FOTS's curved gel model); 60 fps (the
  DIGIT paper).
* ``gelsight_mini``: 320 x 240 px landscape frames over the 18.6 x 14.3 mm field of view (the
  datasheet; the manufacturer's 320 x 240 px default), 25 fps; the LED layout of the GelSight
  Mini is not published: three coloured LEDs 120 degrees apart lighting the gel from its sides
  (directional, low elevation), the GelSight arrangement, with the colour gains and elevations of
  the GelSight-class optics fitted to real ball presses (``gelsight_fots``); stated in the
  config's description.

Intensities, ambient light, vignetting and noise are assumptions chosen to give an unsaturated
no-contact frame of 90-170 grey levels with the camera noise of ``gelsight_fots``.
"""

from __future__ import annotations

import math

import numpy as np

from tactile_deploy.fem.material import Material
from tactile_deploy.optics.model import GelTexture, Light, OpticsModel, SensorNoise, Vignetting
from tactile_deploy.sensors.config import (
    SENSOR_DIR,
    EffectSpec,
    VirtualSensorConfig,
    save_sensor_config,
)


def _crop_camera(width_px: int, height_px: int, mm_per_px: float, grid):
    from tactile_deploy.imaging.camera_mapping import camera_mapping_from_parameters

    s = float(mm_per_px)
    cu, cv = (width_px - 1) / 2.0, (height_px - 1) / 2.0
    hmat = [[s, 0.0, -s * cu], [0.0, -s, s * cv], [0.0, 0.0, 1.0]]
    k = [[float(width_px), 0.0, cu], [0.0, float(width_px), cv], [0.0, 0.0, 1.0]]
    return camera_mapping_from_parameters((width_px, height_px), k, np.zeros(5), hmat, grid=grid)


def digit_config() -> VirtualSensorConfig:
    from tactile_deploy.pad.family import FAMILIES

    fam = FAMILIES["digit"]
    camera = _crop_camera(240, 320, 1 / 19.58, fam.depth_grid)
    lights = []
    for name, angle, colour in (("red", 30.0, (170.0, 12.0, 8.0)),
                                ("green", 150.0, (10.0, 160.0, 14.0)),
                                ("blue", 270.0, (8.0, 14.0, 180.0))):
        a = math.radians(angle)
        lights.append(Light(name=name, kind="point", position_mm=(round(20 * math.cos(a), 4),
                                                                  round(20 * math.sin(a), 4),
                                                                  -17.0),
                            colour_grey=colour, specular_grey=(6.0, 6.0, 6.0), shininess=30.0))
    optics = OpticsModel(camera=camera, lights=tuple(lights), ambient_grey=(35.0, 35.0, 40.0),
                         camera_position_mm=(0.0, 0.0, -22.0),
                         vignetting=Vignetting(k2=-0.15), texture=GelTexture(rms=0.01, seed=4),
                         blur_sigma_px=0.5,
                         noise=SensorNoise(read_noise_grey=1.5, conversion_gain_grey_per_e=0.03))
    return VirtualSensorConfig(
        name="digit", family="digit", pad="digit",
        description="DIGIT: 240 x 320 px portrait at 19.58 px/mm, red/green/blue point LEDs on a "
        "20 mm circle at 30/150/270 degrees, 17 mm behind the gel (TACTO config_digit.yml), the "
        "gel's 0.5 mm curve (FOTS), 60 fps (DIGIT paper); intensities, ambient, vignetting and "
        "noise assumed.",
        material=Material(nu=0.48), optics=optics,
        effects=(EffectSpec(name="dome", params={"height_mm": 0.5}),), fps=60.0, seed=11)


def gelsight_mini_config() -> VirtualSensorConfig:
    from tactile_deploy.pad.family import FAMILIES
    from tactile_deploy.sensors.catalog import sensor_config

    fam = FAMILIES["gelsight_mini"]
    camera = _crop_camera(320, 240, 18.6 / 320, fam.depth_grid)
    fitted = {light.name: light for light in sensor_config("gelsight_fots").optics.lights}
    lights = []
    for name, azimuth in (("red", 90.0), ("green", 210.0), ("blue", 330.0)):
        f = fitted[name]
        lights.append(Light(name=name, kind="directional", azimuth_deg=azimuth,
                            elevation_deg=round(f.elevation_deg, 3),
                            colour_grey=tuple(round(c, 3) for c in f.colour_grey),
                            falloff_per_mm=round(f.falloff_per_mm, 5)))
    optics = OpticsModel(camera=camera, lights=tuple(lights), ambient_grey=(95.0, 115.0, 120.0),
                         camera_position_mm=(0.0, 0.0, -25.0), vignetting=Vignetting(k2=0.05),
                         blur_sigma_px=0.5,
                         noise=SensorNoise(read_noise_grey=1.5, conversion_gain_grey_per_e=0.03))
    return VirtualSensorConfig(
        name="gelsight_mini", family="gelsight_mini", pad="gelsight_mini",
        description="GelSight Mini: 320 x 240 px over the 18.6 x 14.3 mm field of view "
        "(datasheet), 25 fps; LED layout not published: red, green and blue directional LEDs 120 "
        "degrees apart at the elevations and colour gains fitted to real GelSight-class presses "
        "(gelsight_fots); ambient, vignetting and noise assumed.",
        material=Material(nu=0.48), optics=optics, fps=25.0, seed=12)


def main() -> None:
    for config in (gelsight_mini_config(), digit_config()):
        path = SENSOR_DIR / f"{config.name}.json"
        save_sensor_config(config, path)
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
