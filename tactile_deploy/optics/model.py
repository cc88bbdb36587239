"""RGB optics of a vision-based tactile sensor: every parameter, with units, in one pydantic model.

What the model describes (the renderer is :mod:`tactile_deploy.optics.render`)::

    sensing-surface height z(x, y) (sensor frame, mm)
        --normals (finite differences, mm)-->
        --coloured LEDs: Lambertian + Blinn-Phong specular, fall-off, ambient-->
        --gel texture (albedo), vignetting, exposure gain-->  radiance, grey levels (float)
        --optical blur, shot + read noise, 8-bit quantisation, saturation at 255-->  RGB uint8

Frames and conventions
----------------------
* **Sensor frame**: origin at the centre of the sensing (top) surface, z up and out of the gel,
  mm. The camera and the LEDs sit on the gel side (z < 0) and look at the *inside* of the
  reflective membrane. The surface normal used for shading is the one facing the camera:
  for a height map ``z = f(x, y)``, ``n = (f_x, f_y, -1) / sqrt(1 + f_x^2 + f_y^2)``.
* **Light direction** (directional LEDs): ``azimuth_deg`` counter-clockwise from sensor +x (seen
  from outside the gel) towards the light, ``elevation_deg`` above the sensing plane on the camera
  side: the unit vector from the surface to the light is
  ``l = (cos el cos az, cos el sin az, -sin el)``. A flat surface receives ``n . l = sin el``.
* **Point LEDs**: ``position_mm`` in the sensor frame (z < 0). The light vector is evaluated at
  the *deformed* surface point, with inverse-square fall-off normalised to the light's distance
  to the origin: a point light's ``colour_grey`` is what it adds at the origin of a flat surface
  at normal incidence.
* **Camera pixels**: raw frames as the camera delivers them (u right, v down, pixel centres at
  integers), mapped to the sensing plane by a :class:`~tactile_deploy.imaging.camera_mapping.
  CameraMapping` (lens distortion + homography). Frames are RGB (not OpenCV's BGR).
* **Grey levels**: the 8-bit output scale, 0..255. Every intensity parameter is in grey levels
  at exposure gain 1 and unit albedo.

Files: a model is JSON (:func:`save_optics`, atomic), read back by :func:`load_optics`, which
names the file and field of any problem.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, model_validator

from tactile_deploy.atomic import write_text
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.imaging.camera_mapping import (
    CameraMapping,
    camera_mapping_from_parameters,
)
from tactile_deploy.jsonfile import read_json

#: Version of the optics model file format.
FORMAT_VERSION = 1


RGB = tuple[float, float, float]
XYZ = tuple[float, float, float]


class OpticsModelError(ValueError):
    """An optics model file or argument is invalid (the message names the file and field)."""


class Light(StrictModel):
    """One LED (or LED group) illuminating the inside of the sensing membrane."""

    name: str = Field("led", description="Label of the light, e.g. 'red'.")
    kind: Literal["directional", "point"] = Field(
        "directional", description="Directional (far) light or a near point light.")
    azimuth_deg: float = Field(
        0.0, description="Directional: azimuth of the direction towards the light, degrees "
        "counter-clockwise from sensor +x.")
    elevation_deg: float = Field(
        30.0, gt=0.0, le=90.0, description="Directional: elevation of the light above the "
        "sensing plane on the camera side, degrees.")
    position_mm: XYZ = Field(
        (0.0, 20.0, -3.0), description="Point: position of the light in the sensor frame, mm "
        "(z < 0: on the camera side of the sensing surface).")
    colour_grey: RGB = Field(
        (100.0, 0.0, 0.0), description="Grey levels (R, G, B) the light adds at the sensor origin "
        "on a flat surface at normal incidence (n . l = 1), unit albedo, exposure gain 1.")
    falloff_per_mm: float = Field(
        0.0, ge=0.0, le=2.0, description="Attenuation of the light as it crosses the pad, 1/mm: "
        "the irradiance is multiplied by exp(falloff * s), s the position along the in-plane "
        "direction towards the light, mm (0 at the origin: brighter near the LED).")
    specular_grey: RGB = Field(
        (0.0, 0.0, 0.0), description="Blinn-Phong specular amplitude (R, G, B), grey levels at "
        "perfect mirror alignment.")
    shininess: float = Field(
        20.0, ge=1.0, le=500.0, description="Blinn-Phong exponent of the specular lobe, "
        "dimensionless (larger = sharper highlight).")

    @model_validator(mode="after")
    def _check(self) -> Light:
        if self.kind == "point" and not self.position_mm[2] < 0:
            raise ValueError(
                f"light {self.name!r}: a point light must sit below the sensing surface "
                f"(position_mm z < 0), got z = {self.position_mm[2]} mm")
        if any(c < 0 for c in self.colour_grey) or any(c < 0 for c in self.specular_grey):
            raise ValueError(f"light {self.name!r}: colour_grey and specular_grey must be >= 0, "
                             f"got {self.colour_grey} and {self.specular_grey}")
        return self

    def direction(self) -> XYZ:
        """Directional light: unit vector from the surface to the light, sensor frame."""
        az, el = math.radians(self.azimuth_deg), math.radians(self.elevation_deg)
        return (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), -math.sin(el))

    def inplane_direction(self) -> tuple[float, float]:
        """Unit in-plane direction from the origin towards the light (for the fall-off)."""
        if self.kind == "directional":
            az = math.radians(self.azimuth_deg)
            return (math.cos(az), math.sin(az))
        x, y, _ = self.position_mm
        r = math.hypot(x, y)
        return (x / r, y / r) if r > 0 else (0.0, 0.0)


class Vignetting(StrictModel):
    """Radial darkening of the lens: gain ``1 + k2 rho^2 + k4 rho^4``, rho = distance from the
    principal point divided by the half diagonal of the image (0 centre, 1 corner)."""

    k2: float = Field(0.0, ge=-1.0, le=1.0, description="rho^2 coefficient, dimensionless.")
    k4: float = Field(0.0, ge=-1.0, le=1.0, description="rho^4 coefficient, dimensionless.")

    @model_validator(mode="after")
    def _check(self) -> Vignetting:
        corner = 1.0 + self.k2 + self.k4
        if corner <= 0.05:
            raise ValueError(f"vignetting k2={self.k2}, k4={self.k4} darkens the corners to "
                             f"gain {corner:.3f}; the gain must stay > 0.05")
        return self


class GelTexture(StrictModel):
    """Albedo texture of the membrane coating: ``albedo = 1 + rms * g(x, y)``, g a Gaussian
    random field of unit variance with Gaussian correlation length ``length_mm`` (sensor
    frame), fixed for a sensor by ``seed``."""

    rms: float = Field(0.0, ge=0.0, le=0.3, description="Relative albedo variation (1 sigma).")
    length_mm: float = Field(0.15, ge=0.05, le=5.0, description="Correlation length, mm.")
    seed: int = Field(0, ge=0, description="Seed of the texture field.")


class SensorNoise(StrictModel):
    """Image sensor noise in grey levels: variance ``read^2 + gain * signal``."""

    read_noise_grey: float = Field(0.0, ge=0.0, le=20.0, description="Read noise, grey levels "
                                   "(1 sigma).")
    conversion_gain_grey_per_e: float = Field(
        0.0, ge=0.0, le=1.0, description="Grey levels per photo-electron: the shot-noise variance "
        "is this times the signal in grey levels (0 = no shot noise).")


class OpticsModel(StrictModel):
    """Everything between the deformed sensing surface and the 8-bit RGB frame."""

    format_version: Literal[1] = Field(FORMAT_VERSION, description="Version of this file format.")
    camera: CameraMapping = Field(description="Camera resolution, lens and homography to the "
                                  "sensing plane (raw px <-> sensor mm).")
    lights: tuple[Light, ...] = Field(description="The LEDs, 1 to 8.", min_length=1, max_length=8)
    ambient_grey: RGB = Field((0.0, 0.0, 0.0), description="Light reaching the camera whatever "
                              "the surface orientation (R, G, B), grey levels.")
    camera_position_mm: XYZ = Field(
        (0.0, 0.0, -25.0), description="Centre of projection of the camera in the sensor frame, "
        "mm (z < 0); sets the viewing direction of the specular term.")
    vignetting: Vignetting = Field(default_factory=Vignetting, description="Lens vignetting.")
    texture: GelTexture = Field(default_factory=GelTexture, description="Membrane albedo texture.")
    exposure_gain: float = Field(1.0, gt=0.0, le=10.0, description="Multiplies the radiance "
                                 "before noise and quantisation, dimensionless.")
    blur_sigma_px: float = Field(0.0, ge=0.0, le=5.0, description="Gaussian optical blur, raw px.")
    noise: SensorNoise = Field(default_factory=SensorNoise, description="Sensor noise.")
    saturation_grey: float = Field(255.0, gt=0.0, le=255.0, description="Level at which a pixel "
                                   "saturates (full well), grey levels; output is 8-bit.")
    surface_pitch_mm: float | None = Field(
        None, gt=0.0, le=1.0, description="Pitch of the height map the frame is shaded from, mm "
        "(None: the camera's finest mm per px on the pad).")

    @model_validator(mode="after")
    def _check(self) -> OpticsModel:
        if not self.camera_position_mm[2] < 0:
            raise ValueError(f"camera_position_mm must be below the sensing surface (z < 0), got "
                             f"{self.camera_position_mm}")
        if any(a < 0 for a in self.ambient_grey):
            raise ValueError(f"ambient_grey must be >= 0, got {self.ambient_grey}")
        return self

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) of the frames, px."""
        return self.camera.image_size


def simple_camera(width_px: int, height_px: int, mm_per_px: float, *, mirrored: bool = False,
                  centre_mm: tuple[float, float] = (0.0, 0.0), rotation_deg: float = 0.0,
                  aspect: float = 1.0, k1: float = 0.0, k2: float = 0.0,
                  tilt: tuple[float, float] = (0.0, 0.0), focal_px: float | None = None
                  ) -> CameraMapping:
    """A camera mapping built from a few physical numbers (no calibration frames needed).

    The image centre looks at ``centre_mm`` (sensor frame); columns run along sensor +x rotated by
    ``rotation_deg`` and rows along -y (the pad seen from outside the gel), or along +y when
    ``mirrored``. ``mm_per_px`` is the scale along the columns, ``aspect`` multiplies it along
    the rows (anisotropic pixel scale). ``tilt`` = (h20, h21): perspective terms of the
    homography, 1/px (an oblique view). ``k1``, ``k2``: radial lens distortion on normalised
    coordinates with focal length ``focal_px`` (default: the image width).
    """
    import numpy as np

    f = float(focal_px or width_px)
    cx, cy = (width_px - 1) / 2.0, (height_px - 1) / 2.0
    c, s = math.cos(math.radians(rotation_deg)), math.sin(math.radians(rotation_deg))
    sy = 1.0 if mirrored else -1.0
    a = np.array([[mm_per_px, 0.0], [0.0, sy * mm_per_px * aspect]])
    rot = np.array([[c, -s], [s, c]])
    lin = rot @ a
    h = np.eye(3)
    h[:2, :2] = lin
    h[:2, 2] = np.array(centre_mm) - lin @ np.array([cx, cy])
    h[2, 0], h[2, 1] = tilt
    h[2, 2] = 1.0 - tilt[0] * cx - tilt[1] * cy
    k = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    return camera_mapping_from_parameters((width_px, height_px), k, [k1, k2, 0.0, 0.0, 0.0], h)


# --------------------------------------------------------------------------------- files
def save_optics(model: OpticsModel, path: str | os.PathLike) -> None:
    """Write ``model`` as JSON (atomic: temporary file + rename)."""
    write_text(path, model.model_dump_json(indent=2) + "\n")


def format_validation_error(path, err: ValidationError, what: str) -> str:
    """One line per bad field: file, field path, message and the value found."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "(document)"
        got = e.get("input")
        got_txt = (json.dumps(got) if isinstance(got, (int, float, str, bool, type(None)))
                   and not (isinstance(got, float) and not math.isfinite(got)) else
                   (str(got) if isinstance(got, float) else type(got).__name__))
        lines.append(f"  field '{loc}': {e['msg']} (got {got_txt})")
    return f"{path}: invalid {what}:\n" + "\n".join(lines)


def load_optics(path: str | os.PathLike) -> OpticsModel:
    """Read and validate an optics model JSON written by :func:`save_optics`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"optics model {path} not found")
    doc = read_json(path, OpticsModelError, "a JSON optics model")
    if not isinstance(doc, dict) or doc.get("format_version") != FORMAT_VERSION:
        got = doc.get("format_version") if isinstance(doc, dict) else type(doc).__name__
        raise OpticsModelError(f"{path}: field 'format_version' must be {FORMAT_VERSION}, got "
                               f"{got!r}")
    try:
        return OpticsModel.model_validate(doc)
    except ValidationError as e:
        raise OpticsModelError(format_validation_error(path, e, "optics model")) from None
