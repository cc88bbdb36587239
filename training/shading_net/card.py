"""The card of a learned read-out network (``exported/gelslim_readout.json`` beside its ONNX
graph): :class:`ReadoutCard`, built by ``python -m tactile_deploy.training.shading_net`` and read
back by :func:`load_readout_card`, which also checks that the graph it names is the one beside it
(sha256). Errors name the file, each bad field, the rule it breaks and the value it had.

The runtime reads the graph's own metadata (:mod:`tactile_deploy.imaging.learned_readout`), not
the card; the card is for the people who use or retrain the read-out.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from pydantic import Field, ValidationError

from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_json, validation_error_text


class ReadoutCardError(ValueError):
    """A read-out card that is missing, invalid, or names another graph."""


class ReadoutFamilyRecord(StrictModel):
    """The units of the design the crops were rendered with."""

    units: int = Field(ge=1, description="Virtual sensor units drawn around the design.")
    tolerances: dict[str, float] = Field(
        description="Half-widths of the draws around the design (training/shading_net/family.py "
        "Tolerances: led_xy_mm, led_z_mm in mm; the others relative factors).")
    seed: int = Field(description="Seed of the draws and the presses.")


class PressMixRecord(StrictModel):
    """Shares of the presses (sum 1)."""

    balls: float = Field(ge=0, le=1, description="Share of ball presses.")
    library: float = Field(ge=0, le=1, description="Share of the indenter library's shapes.")
    procedural: float = Field(ge=0, le=1, description="Share of procedural faces.")


class ReadoutDataRecord(StrictModel):
    """The presses the crops were cut from."""

    presses_per_unit: int = Field(ge=1, description="Presses rendered for each unit.")
    ball_radii_mm: list[float] = Field(description="Radii of the ball indenters, mm.")
    mix: PressMixRecord | None = Field(None, description="Shares of the press kinds (cards "
                                       "before the mix was an option: half balls, half library).")
    presses_by_kind: dict[str, int] | None = Field(None, description="Crops of each press kind.")
    library_indenters: str = Field(description="Which shapes of the indenter library were pressed.")
    procedural: str | None = Field(None, description="The procedural faces pressed.")
    depth_range_mm: list[float] = Field(min_length=2, max_length=2,
                                        description="Press depth range [min, max], mm.")
    crop_cells: int = Field(ge=1, description="Side of a training crop, grid cells.")


class FitSettingsRecord(StrictModel):
    """Settings of the fit (:mod:`tactile_deploy.training.shading_net.fitting`)."""

    width: int = Field(ge=1, description="Channels of the network's first layer.")
    epochs: int = Field(ge=1, description="Epochs over the crops.")
    batch: int = Field(ge=1, description="Crops per step.")
    lr: float = Field(gt=0, description="Peak learning rate (one-cycle AdamW).")
    gradient_clip: float = Field(gt=0, description="Gradient targets clipped to +- this, mm/mm.")
    gradient_weight: float = Field(ge=0, description="Weight of the gradient channels in the loss.")
    seed: int | None = Field(None, description="Seed of the fit (weights trained elsewhere).")
    device: str | None = Field(None, description="torch device of the fit.")
    device_name: str | None = Field(None, description="Name of the device (GPU name or 'cpu').")
    init: FitInitRecord | None = Field(None, description="The weights the fit started from, and "
                                       "how they were trained.")


class FitInitRecord(FitSettingsRecord):
    """Weights a fit started from (``fitting --init``) and their own settings."""

    weights: str = Field(description="File name of the starting weights.")


FitSettingsRecord.model_rebuild()


class ReadoutTrainingRecord(FitSettingsRecord):
    """The fit and its result."""

    loss_first: float = Field(ge=0, description="Loss of the first epoch (mean squared error of "
                              "the depth in DEPTH_UNIT_MM and the gradients).")
    loss_last: float = Field(ge=0, description="Loss of the last epoch (as loss_first).")
    parameters: int = Field(ge=1, description="Parameters of the network.")
    seconds: float | None = Field(None, ge=0, description="Time of the fit, s (weights trained "
                                  "elsewhere).")
    weights_from: str | None = Field(None, description="File of the weights exported (trained "
                                     "elsewhere); None: trained by this command.")


class ReadoutCard(StrictModel):
    """``<stem>.json`` beside a learned read-out graph ``<stem>.onnx``: what it is, the data and
    the settings it was trained with, its final loss."""

    model: str = Field(description="File name of the ONNX graph, beside the card.")
    command: str = Field(description="The command that made it.")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="sha256 of the graph.")
    what: str = Field(description="What the network computes.")
    design: str = Field(description="Virtual sensor design it was trained for.")
    family: ReadoutFamilyRecord = Field(description="The units the crops came from.")
    data: ReadoutDataRecord = Field(description="The presses.")
    training: ReadoutTrainingRecord = Field(description="The fit.")
    metadata: dict[str, str] = Field(description="The graph's metadata (the feature contract).")
    versions: dict[str, str] = Field(description="torch and python versions.")
    seconds: dict[str, float] = Field(description="Time of the data and of the whole command, s.")


def load_readout_card(path: str | os.PathLike) -> ReadoutCard:
    """Read and check a read-out card, and that the graph it names beside it has its sha256
    (:class:`ReadoutCardError` naming the file, field, expected and actual value)."""
    path = Path(path)
    if not path.is_file():
        raise ReadoutCardError(f"read-out card {path} not found")
    doc = read_json(path, ReadoutCardError, "a learned read-out card")
    try:
        card = ReadoutCard.model_validate(doc)
    except ValidationError as e:
        raise ReadoutCardError(validation_error_text(
            path, e, "learned read-out card", "written by `python -m "
            "tactile_deploy.training.shading_net`; the format is readout_card.schema.json in "
            "training/shading_net/")) from None
    graph = path.parent / card.model
    if not graph.is_file():
        raise ReadoutCardError(f"{path}: field 'model': the graph {graph} is not there")
    digest = hashlib.sha256(graph.read_bytes()).hexdigest()
    if digest != card.sha256:
        raise ReadoutCardError(f"{path}: field 'sha256': expected the sha256 of {graph}, "
                               f"{digest}, got {card.sha256}")
    return card
