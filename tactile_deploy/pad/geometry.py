"""Pad geometry configuration.

A pad is an elastomer layer bonded to a rigid backplate. Everything is described in the
**sensor frame**: origin at the centre of the sensing (top) surface, z up and out of the gel,
units mm. The backplate is the plane z = -thickness_mm.

The geometry is parametric so that another pad is a config change, not new code:

* ``shape="disc"``: a cylinder (GelSlim), ``radius_mm``;
* ``shape="box"``: a rectangular gel (GelSight box gel), ``width_mm`` (x) by ``length_mm`` (y);
* ``dome_height_mm > 0``: a pre-curved sensing surface whose apex is the origin and whose rim
  sits ``dome_height_mm`` lower (a paraboloid cap);
* grading (``core_*`` and ``*_growth``) for meshes that must be fine near a contact and coarse far
  away (used by the analytic validation blocks); for a box, ``core_half_width_mm`` and
  ``core_half_length_mm`` bound a central rectangle (the camera's sensing area) meshed at
  ``core_edge_mm``, the spacing growing by ``edge_growth`` up to ``edge_mm`` outside it.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class PadGeometry(BaseModel):
    """Shape and meshing parameters of a pad (all lengths in mm, sensor frame)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = Field("gelslim", description="Short name of the pad, used in file names.")
    shape: Literal["disc", "box"] = Field("disc", description="Outline of the pad seen from above.")
    radius_mm: float = Field(17.5, gt=0, description="Disc radius, mm (shape='disc').")
    width_mm: float = Field(35.0, gt=0, description="Extent along x, mm (shape='box').")
    length_mm: float = Field(35.0, gt=0, description="Extent along y, mm (shape='box').")
    thickness_mm: float = Field(3.0, gt=0, description="Gel thickness at the centre, mm.")
    dome_height_mm: float = Field(
        0.0, ge=0, description="Sag of a domed sensing surface from apex to rim, mm (0 = flat)."
    )
    sector_deg: float = Field(
        360.0,
        gt=0,
        le=360.0,
        description="Angular extent of a disc, degrees; 90 builds a quarter model whose straight "
        "edges lie on the x = 0 and y = 0 symmetry planes (shape='disc').",
    )
    edge_mm: float = Field(0.972, gt=0, description="Target in-plane node spacing, mm.")
    n_layers: int = Field(4, ge=1, description="Number of element layers through the thickness.")
    # Grading (disc only): spacing edge_mm... grows from core_edge_mm outside core_radius_mm.
    core_radius_mm: float = Field(
        0.0, ge=0, description="Radius of the uniformly fine core, mm (0 = no grading)."
    )
    core_edge_mm: float = Field(0.1, gt=0, description="Node spacing inside the core, mm.")
    edge_growth: float = Field(1.15, ge=1.0, description="Ring-to-ring spacing ratio outside the core.")
    core_half_width_mm: float = Field(
        0.0, ge=0, description="Box only: half extent along x of the central rectangle meshed at "
        "core_edge_mm, mm (0 = uniform edge_mm).")
    core_half_length_mm: float = Field(
        0.0, ge=0, description="Box only: half extent along y of that rectangle, mm.")
    top_layer_mm: float = Field(
        0.0, ge=0, description="Thickness of the top element layer, mm (0 = uniform layers)."
    )
    layer_growth: float = Field(1.0, ge=1.0, description="Layer-to-layer thickness ratio, top down.")

    @model_validator(mode="after")
    def _check(self) -> "PadGeometry":
        if self.dome_height_mm >= self.thickness_mm:
            raise ValueError(
                f"dome_height_mm={self.dome_height_mm} must be smaller than "
                f"thickness_mm={self.thickness_mm}: the rim would reach the backplate"
            )
        if self.shape == "box" and self.core_radius_mm > 0:
            raise ValueError("grading (core_radius_mm > 0) is only supported for shape='disc'; a "
                             "box is graded with core_half_width_mm and core_half_length_mm")
        box_core = self.core_half_width_mm > 0 or self.core_half_length_mm > 0
        if box_core and self.shape != "box":
            raise ValueError("core_half_width_mm / core_half_length_mm grade a box; a disc is "
                             "graded with core_radius_mm")
        if box_core and not (self.core_half_width_mm > 0 and self.core_half_length_mm > 0):
            raise ValueError("give both core_half_width_mm and core_half_length_mm (> 0)")
        if box_core and (self.core_half_width_mm > 0.5 * self.width_mm + 1e-9
                         or self.core_half_length_mm > 0.5 * self.length_mm + 1e-9):
            raise ValueError(
                f"the fine rectangle +-{self.core_half_width_mm} x +-{self.core_half_length_mm} mm "
                f"does not fit the {self.width_mm} x {self.length_mm} mm box")
        if self.sector_deg != 360.0 and (self.shape != "disc" or self.sector_deg != 90.0):
            raise ValueError(f"sector_deg must be 360 or 90 (a disc quarter), got {self.sector_deg}")
        if self.top_layer_mm > self.thickness_mm:
            raise ValueError(
                f"top_layer_mm={self.top_layer_mm} exceeds thickness_mm={self.thickness_mm}"
            )
        return self

    @property
    def half_extent_mm(self) -> float:
        """Half of the largest in-plane extent, mm (radius for a disc)."""
        if self.shape == "disc":
            return self.radius_mm
        return 0.5 * max(self.width_mm, self.length_mm)

    def top_height_mm(self, x_mm, y_mm):
        """Rest height z (mm) of the sensing surface above (x, y) in the sensor frame."""
        if self.dome_height_mm == 0:
            return 0.0 * x_mm
        return -self.dome_height_mm * (x_mm**2 + y_mm**2) / self.half_extent_mm**2

    def contains_xy(self, x_mm, y_mm, margin_mm: float = 0.0):
        """True where (x, y) lies inside the pad outline shrunk by ``margin_mm``."""
        if self.shape == "disc":
            inside = x_mm**2 + y_mm**2 <= (self.radius_mm - margin_mm) ** 2
            if self.sector_deg == 90.0:
                inside = inside & (x_mm >= 0) & (y_mm >= 0)
            return inside
        return (abs(x_mm) <= 0.5 * self.width_mm - margin_mm) & (
            abs(y_mm) <= 0.5 * self.length_mm - margin_mm
        )


#: The GelSlim pad of the paper: r 17.5 mm x 3 mm, 5 node layers of 1,075 nodes (5,375 nodes).
GELSLIM_PAD = PadGeometry()
