"""``fem.json``: the gel material fitted by the FEM step of the wizard and by ``calibrate fem``
(E from forces, nu from depth maps), read back by the plugin step and the benchmarks."""

from __future__ import annotations

import os

from pydantic import Field

from tactile_deploy.atomic import write_json
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_model_json


class FemResultError(ValueError):
    """``fem.json`` is missing, not JSON or not a valid FEM result (the message says which field)."""


class FemResult(StrictModel):
    """The fitted (or prior) material and how well the FEM reproduces the contacts. ``None``:
    not measured or not identifiable (the notes say why)."""

    E_mpa: float | None = Field(gt=0, description="Young's modulus, MPa (None: not identifiable "
                                "without forces).")
    nu: float = Field(ge=0.0, lt=0.5, description="Poisson's ratio.")
    source: str = Field("", description="Where the values come from (fit, prior).")
    nu_std: float | None = Field(None, ge=0, description="Bootstrap spread of nu.")
    E_std_mpa: float | None = Field(None, ge=0, description="Bootstrap spread of E, MPa.")
    nu_note: str = Field("", description="How nu was found.")
    E_note: str = Field("", description="How E was found.")
    friction: str | None = Field(None, description="Friction law of the fit (frictionless, stick).")
    friction_note: str = Field("", description="How the friction law was chosen.")
    depth_gap_um: float | None = Field(None, ge=0, description="RMS depth-map gap at the optimum, um.")
    depth_offset_mm: float | None = Field(None, description="Fitted zero offset of the rig's "
                                          "depth, mm (None: not fitted).")
    method: str | None = Field(None, description="Optimiser of nu (brent, cem).")
    evaluations: int | None = Field(None, ge=0, description="FEM evaluations of the fit.")
    n_contacts: int | None = Field(None, ge=0, description="Contacts fitted.")
    forces_measured_n: list[float] = Field(default_factory=list,
                                           description="Rig forces of the contacts, N.")
    forces_fitted_n: list[float] = Field(default_factory=list,
                                         description="FEM forces at the fitted material, N.")


def write_fem_result(path: str | os.PathLike, result: FemResult) -> None:
    """Write ``fem.json`` atomically."""
    write_json(path, result.model_dump(mode="json"))


def read_fem_result(path: str | os.PathLike) -> FemResult:
    """Read and validate ``fem.json`` (:class:`FemResultError` names the file and field)."""
    return read_model_json(
        path, FemResult, FemResultError, "FEM result",
        "the format is described by calibration/fem_fit/fem_result.schema.json",
        expected="a JSON FEM result",
        missing=f"{path} is missing: redo the FEM step (or `calibrate fem --out`)")
