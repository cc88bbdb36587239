"""Pad families as data: the published shape of a sensor's gel -> a mesh, its supports and grids.

A :class:`PadFamily` describes one sensor design's elastomer pad in the **sensor frame** (origin
at the centre of the sensing surface, z out of the gel, mm):

* the outline (a disc of ``radius_mm``, or a rectangle of ``width_mm`` along x by
  ``length_mm`` along y), the gel ``thickness_mm`` and an optional ``crown_mm`` (sag of a domed
  sensing surface from its apex to the rim);
* how it is held: ``backplate`` ("bonded": cast on the rigid window, every bottom node fixed;
  "sliding": the bottom may slide) and ``sides`` ("free", or "fixed" to a rigid frame);
* the **sensing area**: the part of the top face the camera sees (a rectangle, sensor frame),
  meshed at ``sensing_spacing_mm`` while the rest of the pad coarsens to
  ``outer_spacing_mm``;
* the **depth grid** that follows the sensing area: square cells of ``depth_pitch_mm``
  covering it (row 0 at the largest y, columns along +x);
* where each number comes from (``sources``) and what had to be assumed (``assumptions``).

:func:`PadFamily.geometry` gives the mesher's :class:`~tactile_deploy.pad.geometry.PadGeometry`,
:func:`tactile_deploy.fem.constraints.family_supports` the FEM's supports. The shipped families are in
:data:`FAMILIES`; ``tactile_deploy/pad/asset.py`` freezes their meshes with a hash and a card.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from tactile_deploy.fileformat import StrictModel
from tactile_deploy.imaging.camera_mapping import OutputGrid
from tactile_deploy.pad.geometry import PadGeometry


class SensingArea(StrictModel):
    """Rectangle of the sensing surface seen by the camera (sensor frame, mm)."""

    x_min_mm: float = Field(description="Left edge, mm.")
    x_max_mm: float = Field(description="Right edge, mm.")
    y_min_mm: float = Field(description="Bottom edge, mm.")
    y_max_mm: float = Field(description="Top edge, mm.")

    @model_validator(mode="after")
    def _check(self) -> SensingArea:
        if not (self.x_max_mm > self.x_min_mm and self.y_max_mm > self.y_min_mm):
            raise ValueError(f"sensing area must have x_max > x_min and y_max > y_min, got "
                             f"{self.model_dump()}")
        return self

    @property
    def width_mm(self) -> float:
        return self.x_max_mm - self.x_min_mm

    @property
    def length_mm(self) -> float:
        return self.y_max_mm - self.y_min_mm


class Source(StrictModel):
    """Where a number of the family comes from."""

    what: str = Field(description="The quantities taken from this source.")
    reference: str = Field(description="The source: a datasheet, paper, or repository file "
                           "(URL and, for code, the file path).")


class PadFamily(StrictModel):
    """A sensor design's pad (module docstring). Lengths in mm, sensor frame."""

    name: str = Field(pattern=r"^[a-z0-9][a-z0-9_]*$", description="Family and pad name.")
    description: str = Field(description="The sensor design in one line.")
    outline: Literal["disc", "rectangle"] = Field(description="Pad outline seen from above.")
    radius_mm: float | None = Field(None, gt=0, description="Disc radius, mm.")
    width_mm: float | None = Field(None, gt=0, description="Rectangle extent along x, mm.")
    length_mm: float | None = Field(None, gt=0, description="Rectangle extent along y, mm.")
    thickness_mm: float = Field(gt=0, description="Gel thickness at the apex, mm.")
    crown_mm: float = Field(0.0, ge=0, description="Sag of a domed sensing surface from the "
                            "apex to the rim, mm (0: flat).")
    backplate: Literal["bonded", "sliding"] = Field(
        "bonded", description="'bonded': the gel is cast on the rigid window (bottom fixed).")
    sides: Literal["free", "fixed"] = Field("free", description="Side walls free, or held by "
                                            "a rigid frame.")
    sensing_area: SensingArea = Field(description="Part of the top face the camera sees.")
    sensing_spacing_mm: float = Field(gt=0, description="Node spacing on the sensing area, mm.")
    outer_spacing_mm: float = Field(gt=0, description="Largest node spacing outside it, mm.")
    spacing_growth: float = Field(1.25, ge=1.0, description="Interval-to-interval growth of "
                                  "the spacing outside the sensing area.")
    n_layers: int = Field(ge=1, description="Element layers through the thickness.")
    top_layer_mm: float = Field(0.0, ge=0, description="Thickness of the top element layer, "
                                "mm (0: uniform layers).")
    layer_growth: float = Field(1.0, ge=1.0, description="Layer-to-layer thickness ratio, "
                                "top down.")
    depth_grid: OutputGrid = Field(description="Grid of the depth maps of this family (row 0 "
                                   "at the largest y, columns along +x).")
    sources: tuple[Source, ...] = Field((), description="Where the numbers come from.")
    assumptions: tuple[str, ...] = Field((), description="What nothing published fixes, and "
                                         "the value chosen.")

    @model_validator(mode="after")
    def _check(self) -> PadFamily:
        if self.outline == "disc" and self.radius_mm is None:
            raise ValueError(f"pad family {self.name!r}: a disc needs radius_mm")
        if self.outline == "rectangle" and (self.width_mm is None or self.length_mm is None):
            raise ValueError(f"pad family {self.name!r}: a rectangle needs width_mm and length_mm")
        a = self.sensing_area
        corners = [(a.x_min_mm, a.y_min_mm), (a.x_max_mm, a.y_max_mm),
                   (a.x_min_mm, a.y_max_mm), (a.x_max_mm, a.y_min_mm)]
        if self.outline == "rectangle":
            inside = all(abs(x) <= 0.5 * self.width_mm + 1e-9 and abs(y) <= 0.5 * self.length_mm
                         + 1e-9 for x, y in corners)
        else:
            inside = all(math.hypot(x, y) <= self.radius_mm + 1e-9 for x, y in corners)
        if not inside:
            raise ValueError(f"pad family {self.name!r}: the sensing area {a.model_dump()} does "
                             "not lie inside the pad's outline")
        if self.crown_mm >= self.thickness_mm:
            raise ValueError(f"pad family {self.name!r}: crown_mm {self.crown_mm} must be "
                             f"smaller than thickness_mm {self.thickness_mm}")
        return self

    # ----------------------------------------------------------------- derived
    def geometry(self) -> PadGeometry:
        """The mesher's configuration of this pad."""
        common = dict(name=self.name, thickness_mm=self.thickness_mm,
                      dome_height_mm=self.crown_mm, n_layers=self.n_layers,
                      top_layer_mm=self.top_layer_mm, layer_growth=self.layer_growth)
        if self.outline == "disc":
            if self.sensing_spacing_mm == self.outer_spacing_mm:
                return PadGeometry(shape="disc", radius_mm=self.radius_mm,
                                   edge_mm=self.sensing_spacing_mm, **common)
            a = self.sensing_area
            core = max(math.hypot(x, y) for x in (a.x_min_mm, a.x_max_mm)
                       for y in (a.y_min_mm, a.y_max_mm))
            return PadGeometry(shape="disc", radius_mm=self.radius_mm, edge_mm=self.outer_spacing_mm,
                               core_radius_mm=core, core_edge_mm=self.sensing_spacing_mm,
                               edge_growth=self.spacing_growth, **common)
        a = self.sensing_area
        if abs(a.x_min_mm + a.x_max_mm) > 1e-9 or abs(a.y_min_mm + a.y_max_mm) > 1e-9:
            raise ValueError(f"pad family {self.name!r}: the mesher needs a sensing area centred "
                             "on the pad")
        return PadGeometry(shape="box", width_mm=self.width_mm, length_mm=self.length_mm,
                           edge_mm=self.outer_spacing_mm, core_edge_mm=self.sensing_spacing_mm,
                           core_half_width_mm=0.5 * a.width_mm,
                           core_half_length_mm=0.5 * a.length_mm,
                           edge_growth=self.spacing_growth, **common)


def depth_grid_over(area: SensingArea, pitch_mm: float) -> OutputGrid:
    """Square cells of ``pitch_mm`` covering ``area`` (centred on it, rounded up)."""
    nx = math.ceil(area.width_mm / pitch_mm - 1e-9)
    ny = math.ceil(area.length_mm / pitch_mm - 1e-9)
    cx = 0.5 * (area.x_min_mm + area.x_max_mm)
    cy = 0.5 * (area.y_min_mm + area.y_max_mm)
    hx, hy = 0.5 * nx * pitch_mm, 0.5 * ny * pitch_mm
    return OutputGrid(x_min_mm=round(cx - hx, 9), x_max_mm=round(cx + hx, 9),
                      y_min_mm=round(cy - hy, 9), y_max_mm=round(cy + hy, 9), nx=nx, ny=ny)


# ---------------------------------------------------------------------------- shipped families
GELSLIM = PadFamily(
    name="gelslim",
    description="GelSlim-class finger of the paper: a 35 mm gel disc, 3 mm thick, on a rigid "
    "backplate.",
    outline="disc", radius_mm=17.5, thickness_mm=3.0,
    sensing_area=SensingArea(x_min_mm=-12.37, x_max_mm=12.37, y_min_mm=-12.37, y_max_mm=12.37),
    sensing_spacing_mm=0.972, outer_spacing_mm=0.972, n_layers=4,
    depth_grid=OutputGrid(),
    sources=(Source(what="pad r 17.5 mm x 3 mm on a rigid backplate, 128 x 128 depth maps over "
                    "+-17.5 mm, ~5.4k-node tet mesh",
                    reference="Zhu et al., Learning to Synthesize Volumetric Meshes from "
                    "Vision-based Tactile Imprints (../shared/seed/paper.tex)"),),
    assumptions=("sensing area: the largest square inside the disc (the camera's view differs "
                 "per unit; the camera mapping's imaging grid is what is read)",),
)

_MINI_AREA = SensingArea(x_min_mm=-9.3, x_max_mm=9.3, y_min_mm=-7.15, y_max_mm=7.15)
GELSIGHT_MINI = PadFamily(
    name="gelsight_mini",
    description="GelSight Mini: a 25.25 x 20.75 mm gel pad, 4 mm thick, on a clear window; the "
    "camera sees 18.6 x 14.3 mm of it.",
    outline="rectangle", width_mm=25.25, length_mm=20.75, thickness_mm=4.0,
    sensing_area=_MINI_AREA,
    sensing_spacing_mm=0.5, outer_spacing_mm=1.25, spacing_growth=1.3,
    n_layers=5, top_layer_mm=0.5, layer_growth=1.3,
    depth_grid=depth_grid_over(_MINI_AREA, 0.15),
    sources=(
        Source(what="field of view 18.6 x 14.3 mm (the sensing area), camera 8 MP at 25 fps, "
               "320 x 240 px processing default",
               reference="GelSight Mini datasheet, page 3: https://www.gelsight.com/wp-content/"
               "uploads/productsheet/Mini/GelSight_Datasheet_GSMini.pdf"),
        Source(what="gel pad 25.25 mm x 20.75 mm x 4 mm (derived from the manufacturer's CAD of "
               "the gel pad and case), case 32 x 28 x 24 mm",
               reference="TacEx GelSight Mini sensor model (tacex_assets Sensors/GelSight_Mini, "
               "README and GelSightMiniCfg.gelpad_dimensions), itself from "
               "https://github.com/gelsightinc/gsrobotics docs/CAD/gsmini_shell.zip"),
        Source(what="320 x 240 px frames at 0.0634 mm per px ('mini gel 18x24mm at 240x320') in "
               "the manufacturer's examples",
               reference="https://github.com/gelsightinc/gsrobotics examples (show3d.py, mmpp)"),
    ),
    assumptions=(
        "thickness 4.0 mm: the gel pad model's height (TacEx's configuration uses 4.5 mm, which "
        "we read as gel plus the attachment plate)",
        "flat sensing surface (crown 0): no published crown",
        "sides free: the pad's side walls are not bonded to the case",
        "the sensing area is centred on the pad and its long side runs along x (the camera's "
        "landscape axis)",
    ),
)

_DIGIT_AREA = SensingArea(x_min_mm=-6.129, x_max_mm=6.129, y_min_mm=-8.172, y_max_mm=8.172)
DIGIT = PadFamily(
    name="digit",
    description="DIGIT: an 18.35 x 24.9 mm gel, 3 mm thick, on an acrylic window; the camera "
    "(240 x 320 px portrait) sees about 12.3 x 16.3 mm of it.",
    outline="rectangle", width_mm=18.35, length_mm=24.9, thickness_mm=3.0,
    sensing_area=_DIGIT_AREA,
    sensing_spacing_mm=0.5, outer_spacing_mm=1.25, spacing_growth=1.3,
    n_layers=5, top_layer_mm=0.5, layer_growth=1.2,
    depth_grid=depth_grid_over(_DIGIT_AREA, 0.15),
    sources=(
        Source(what="gel 18.35 mm (width, across the finger) x 24.90 mm (along it) of a DIGIT "
               "unit, 19.58 px per mm at 240 x 320 px, the gel model with a 0.5 mm curve",
               reference="FOTS (Rancho-zhao/FOTS) mlp_calib/config/normal_to_rgb.yaml (gel_width, "
               "gel_height of unit D00001, mm_to_pixel) and assets/stls/gel/digit_curve_0_5.STL"),
        Source(what="camera 240 x 320 px portrait, three LEDs (red, green, blue) on a circle of "
               "20 mm radius at 30, 150 and 270 degrees, gel 20 x 30 mm in the renderer",
               reference="TACTO (facebookresearch/tacto) tacto/config_digit.yml"),
        Source(what="the design (enclosure, gel, electronics)",
               reference="Lambeta et al., DIGIT, IEEE RA-L 5(3) 2020, arXiv 2005.14679; "
               "https://github.com/facebookresearch/digit-design"),
    ),
    assumptions=(
        "thickness 3.0 mm: not published; a simplified housing model shows the gel protruding "
        "3.8 mm including its curve and rim",
        "flat mesh: FOTS models the gel with a 0.5 mm curve; depth is measured from the rest "
        "surface, and a virtual DIGIT carries the curve as its dome effect (a curved mesh would "
        "change forces by the curve's share of the 3 mm gel)",
        "sensing area 12.3 x 16.4 mm: the 240 x 320 px view at 19.58 px per mm, centred",
        "sides free",
    ),
)

#: The shipped pad families, by name.
FAMILIES: dict[str, PadFamily] = {f.name: f for f in (GELSLIM, GELSIGHT_MINI, DIGIT)}


class UnknownFamilyError(KeyError):
    """A pad family name that is not shipped (the message lists the shipped ones)."""

    def __str__(self) -> str:
        return str(self.args[0])


def get_family(name: str) -> PadFamily:
    """The shipped family ``name``."""
    if name not in FAMILIES:
        raise UnknownFamilyError(f"unknown pad family {name!r}; shipped: "
                                 f"{', '.join(sorted(FAMILIES))}")
    return FAMILIES[name]
