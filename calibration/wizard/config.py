"""Settings of the calibration wizard (``tactile-deploy calibrate --sensor NEW --config FILE``).

One JSON file, every field optional (defaults suit a GelSlim-class sensor): the JSON Schema is
committed as ``calibration/wizard/wizard_config.schema.json`` (``python -m
tactile_deploy.calibration.formats`` rewrites it; a test fails when it drifts). Lengths in mm, sensor
frame (origin at the centre of the sensing surface, z out of the gel).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, model_validator

from tactile_deploy.calibration.shading.fit import ShadingFitConfig
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_json, validation_error_text

FORMAT_VERSION = 1
SCHEMA_PATH = Path(__file__).with_name("wizard_config.schema.json")



class WizardConfigError(ValueError):
    """A wizard config file is missing or invalid (the message names file, field, values)."""


class ReferenceSettings(StrictModel):
    """Step 1: the no-contact reference frame."""

    n_frames: int = Field(16, ge=1, le=1000, description="Frames averaged into the reference "
                          "frame; their depth maps also give the noise reference.")


class CameraSettings(StrictModel):
    """Step 2: the camera mapping (lens, homography to the sensing plane, mm per px)."""

    target: Literal["dots", "charuco", "crop"] = Field(
        "dots", description="'dots': a plate of pins on a square lattice pressed into the gel; "
        "'charuco': a printed ChArUco board laid on the sensing plane; 'crop': no target, the "
        "frames are already rectified at mm_per_px (e.g. a GelSight recording).")
    pitch_mm: float = Field(2.5, gt=0, description="dots: lattice pitch, mm.")
    grid: tuple[int, int] = Field((9, 7), description="dots: pins (columns along sensor x, "
                                  "rows along y); every pin must be in view.")
    pin_radius_mm: float = Field(0.75, gt=0, description="dots: radius of the pins' caps, mm.")
    press_depth_mm: float = Field(0.35, gt=0, le=1.5, description="dots: how deep the plate is "
                                  "pressed, mm.")
    blur_px: float = Field(6.0, gt=0, description="dots: smoothing before detection, px (about "
                           "half a pin's image radius).")
    free_lens: tuple[str, ...] = Field(
        ("k1", "k2"), description="Lens coefficients fitted (of cx, cy, k1, k2, p1, p2): one "
        "view of a grid that does not reach the image corners determines few.")
    u_axis: Literal["+x", "-x", "+y", "-y"] = Field("+x", description="Sensor axis along image "
                                                     "right (within 45 degrees).")
    v_axis: Literal["+x", "-x", "+y", "-y"] = Field("-y", description="Sensor axis along image "
                                                     "down (within 45 degrees).")
    n_frames: int = Field(4, ge=1, description="Frames of the pressed target averaged.")
    board: str | None = Field(None, description="charuco: board JSON written by `calibrate "
                              "make-board` (None: the default board).")
    mm_per_px: float | None = Field(None, gt=0, description="crop: scale of the frames, mm per "
                                    "px (required for 'crop').")
    crop: tuple[int, int, int, int] | None = Field(
        None, description="crop: (x0, y0, width, height) px of the frame to use (None: all).")

    @model_validator(mode="after")
    def _check(self) -> CameraSettings:
        if self.target == "crop" and self.mm_per_px is None:
            raise ValueError("camera.target 'crop' needs camera.mm_per_px (the frames' scale, "
                             "mm per px)")
        unknown = sorted(set(self.free_lens) - {"cx", "cy", "k1", "k2", "p1", "p2"})
        if unknown:
            raise ValueError(f"camera.free_lens has unknown coefficient(s) {unknown}; known: "
                             "cx, cy, k1, k2, p1, p2")
        if min(self.grid) < 2:
            raise ValueError(f"camera.grid must be at least 2 x 2 pins, got {list(self.grid)}")
        return self


class PressSettings(StrictModel):
    """Step 3: ball presses for the shading model (and the FEM fit when forces are measured)."""

    ball_radius_mm: float = Field(3.0, gt=0, description="Radius of the calibration ball, mm.")
    n_presses: int = Field(24, ge=3, le=500, description="Number of presses, spread over the "
                           "view.")
    depth_range_mm: tuple[float, float] = Field(
        (0.3, 0.9), description="Depths of the presses (rig; a guide when pressing by hand), "
        "mm. Press at least as deep as the contacts to measure: the shading table only knows "
        "slopes it has seen.")
    edge_margin: float = Field(
        1.2, ge=0.3, le=3.0, description="Distance of the press centres from the edges of the "
        "imaging grid, in contact radii of the deepest press.")
    frames_per_press: int = Field(1, ge=1, description="Frames averaged per press.")
    seed: int = Field(0, ge=0, description="Seed of the press plan (positions, depth order).")
    annotations: str | None = Field(
        None, description="CSV img_names,center_x,center_y,radius (px of the imaging grid, "
        "names press_000.png ...) replacing the detected circles.")

    @model_validator(mode="after")
    def _check(self) -> PressSettings:
        lo, hi = self.depth_range_mm
        if not 0 < lo <= hi <= 1.5:
            raise ValueError(f"presses.depth_range_mm must satisfy 0 < min <= max <= 1.5 mm, "
                             f"got {list(self.depth_range_mm)}")
        if math.sqrt(2 * self.ball_radius_mm * hi) >= self.ball_radius_mm:
            raise ValueError(f"presses: a {self.ball_radius_mm} mm ball pressed {hi} mm has a "
                             "contact as wide as itself; press less deep or use a larger ball")
        return self


class ShadingSettings(StrictModel):
    """Step 4: the shading model (tactile_deploy.calibration.shading.fit.ShadingFitConfig settings)."""

    bins: int = Field(24, ge=4, le=128, description="Colour bins per channel.")
    node_spacing_mm: float = Field(3.0, gt=0, description="Spacing of the table's position "
                                   "grid, mm.")
    kernel_sigma_mm: float = Field(1.0, gt=0, description="Position smoothing of the table, mm.")
    folds: int = Field(4, ge=0, description="Cross-validation folds for the figures of merit "
                       "(0: none; otherwise at least 2 and at most the number of presses).")
    ring_targets: Literal["fem", "none"] = Field(
        "fem", description="Training targets for the sunken gel around each contact: 'fem' "
        "(the ball press solved by the FEM of the family's pad at the press's place and depth, "
        "nu = fem.prior_nu) or 'none' (those pixels get no target).")
    ring_stride: int = Field(4, ge=1, le=16, description="With ring_targets 'fem': one pixel in "
                             "this many along each axis takes part (a ring pixel weighs "
                             "1 / ring_stride^2 of a contact pixel).")
    prior: Literal["colour-polynomial", "image-mean"] = Field(
        "colour-polynomial", description="What a table entry with few samples falls back to: "
        "'colour-polynomial' (a polynomial in colour whose coefficients vary quadratically over "
        "the image, fitted to all presses: keeps each place's colour-to-slope relation, which "
        "point-like LEDs beside the gel make position-dependent) or 'image-mean' (the colour "
        "bin's mean over the whole image).")


class FemSettings(StrictModel):
    """Step 5 (optional): the FEM material (nu from depth maps, E from forces)."""

    enabled: bool = Field(True, description="Run the FEM fit (otherwise the prior is used).")
    nu_grid: tuple[float, ...] = Field(
        (0.48,), description="Poisson ratios at which exact surface operators are computed "
        "(about 20 s each, cached); with several, nu is searched between the first and the "
        "last, e.g. [0.40, 0.43, 0.46, 0.49]. One value fixes nu (then only E is fitted): the "
        "default, because nu from depth maps reconstructed by a shading model is biased "
        "(docs/calibration.md).")
    method: Literal["brent", "cem"] = Field("brent", description="Search over nu: bounded Brent "
                                            "or the cross-entropy method of the paper.")
    bootstrap: int = Field(10, ge=0, description="Bootstrap resamples for the spread of nu.")
    fit_depth_offset: bool = Field(True, description="With a rig: fit the error of its depth "
                                   "zero (touch-off) together with E from the forces.")
    prior_E_mpa: float = Field(0.3, gt=0, description="E used when the data cannot give it "
                               "(no forces), MPa.")
    prior_nu: float = Field(0.48, ge=0, lt=0.5, description="nu used when the fit is off.")

    @model_validator(mode="after")
    def _check(self) -> FemSettings:
        if not self.nu_grid or any(not 0 <= v < 0.5 for v in self.nu_grid):
            raise ValueError(f"fem.nu_grid must hold Poisson ratios in [0, 0.5), got "
                             f"{list(self.nu_grid)}")
        if len(set(self.nu_grid)) != len(self.nu_grid):
            raise ValueError(f"fem.nu_grid has repeated values: {list(self.nu_grid)}")
        return self


class RigSettings(StrictModel):
    """How the rig presses (None: the rig config's value, or its default)."""

    force_limit_n: float | None = Field(None, gt=0, description="Force at which a press stops "
                                        "and backs off, N.")
    approach_step_mm: float | None = Field(None, gt=0, description="Z step between force "
                                           "readings while pressing, mm.")
    approach_clearance_mm: float | None = Field(None, gt=0, description="Height above the gel "
                                                "where stepping starts, mm.")
    travel_height_mm: float | None = Field(None, gt=0, description="Sensor-frame z of travel "
                                           "moves, mm.")

    def overrides(self) -> dict:
        """The fields that are set, as RigConfig fields."""
        return {k: v for k, v in self.model_dump().items() if v is not None}


class WizardConfig(StrictModel):
    """The calibration wizard's settings (``--config FILE``)."""

    format_version: Literal[1] = Field(FORMAT_VERSION, description="Version of this format.")
    description: str = Field("", description="One line about the sensor (goes into the "
                             "plugin manifest).")
    family: str = Field("gelslim", description="Sensor family: its pad mesh and ONNX model.")
    model: str | None = Field(None, description="The family's ONNX model (None: "
                              "exported/gelslim_mesh.onnx of a source checkout).")
    copy_model: bool = Field(True, description="Copy the model into the plugin folder (a "
                             "self-contained plugin) instead of referencing it by path.")
    readout: str | None = Field(None, description="A learned read-out of the sensor's design "
                                "(.onnx from `python -m tactile_deploy.training.shading_net`) for the plugin to "
                                "turn frames into depth with instead of the fitted shading model "
                                "(None: the shading model); a relative path is relative to the "
                                "current folder. The noise reference is made with it, and its "
                                "depth gain on this unit is calibrated from the rig's presses.")
    readout_steps: int = Field(0, ge=0, le=100_000, description="Adam steps of fine-tuning the "
                               "read-out on this unit's ball presses (their FEM depth at the "
                               "rig's intrusion plus its fitted zero offset) and no-contact "
                               "frames, written into the plugin as readout.onnx; needs torch "
                               "(the train extra). 0 (default): the design's read-out as it is, "
                               "with the unit's depth gain (docs/shading.md: with a good camera "
                               "mapping, fine-tuning on FEM targets is worse on the virtual "
                               "GelSlim 2).")
    rig_config: str | None = Field(None, description="Rig config JSON (docs/rig.md): stage frame, "
                                   "limits, force limit. Ports from --rig/--gauge override it.")
    rig: RigSettings = Field(default_factory=RigSettings)
    reference: ReferenceSettings = Field(default_factory=ReferenceSettings)
    camera: CameraSettings = Field(default_factory=CameraSettings)
    presses: PressSettings = Field(default_factory=PressSettings)
    shading: ShadingSettings = Field(default_factory=ShadingSettings)
    fem: FemSettings = Field(default_factory=FemSettings)

    @model_validator(mode="after")
    def _check(self) -> WizardConfig:
        f = self.shading.folds
        if f and not 2 <= f <= self.presses.n_presses:
            raise ValueError(f"shading.folds must be 0 or lie in [2, presses.n_presses="
                             f"{self.presses.n_presses}], got {f}")
        return self


def shading_fit_config(settings: ShadingSettings) -> ShadingFitConfig:
    """The :class:`~tactile_deploy.calibration.shading.fit.ShadingFitConfig` of the wizard's shading settings."""
    return ShadingFitConfig(bins=settings.bins, node_spacing_mm=settings.node_spacing_mm,
                            kernel_sigma_mm=settings.kernel_sigma_mm,
                            ring_stride=settings.ring_stride, prior_model=settings.prior)


def wizard_config_from_dict(doc: dict, source: str = "<dict>") -> WizardConfig:
    """Validate a config document; errors name ``source`` and each bad field."""
    if not isinstance(doc, dict):
        raise WizardConfigError(f"{source}: expected a JSON object, got {type(doc).__name__}")
    if doc.get("format_version", FORMAT_VERSION) != FORMAT_VERSION:
        raise WizardConfigError(f"{source}: field 'format_version': this version reads "
                                f"{FORMAT_VERSION}, the file has {doc.get('format_version')!r}")
    try:
        return WizardConfig.model_validate(doc)
    except ValidationError as e:
        raise WizardConfigError(validation_error_text(
            source, e, "wizard config",
            f"the format is described by {SCHEMA_PATH.name} in calibration/wizard/")) from None


def load_wizard_config(path: str | os.PathLike) -> WizardConfig:
    """Read and validate a wizard config JSON file."""
    path = Path(path)
    if not path.is_file():
        raise WizardConfigError(f"wizard config {path} not found")
    doc = read_json(path, WizardConfigError, "a JSON wizard config")
    return wizard_config_from_dict(doc, str(path))

