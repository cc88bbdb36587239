"""The card of an exported adaptation step: what it updates, what it takes, how its weights map
onto the family's ONNX model, and the versions it was made with.

An adaptation step folder (``exported/gelslim_mesh_adapt/`` for the GelSlim family model
``exported/gelslim_mesh.onnx``) holds::

    card.json     this card (strict JSON, :class:`AdaptationCard`)
    card.md       the same, for people
    step.pt2      the step as a torch.export program (train mode; forward + loss)
    filter.onnx   the image VAE as a noise filter (onnxruntime): depth -> VAE(depth)

The step program's parameters named in ``trainable`` are the image encoder and the latent
projection; everything else in it (the mesh decoder, the renderer) is frozen. ``parameter_map``
says, for each trainable parameter, which initializer of the family's fp32 ONNX graph holds it
and with which scale folded in, so that the runtime writes the adapted ONNX model by replacing
those initializers (no training code, no re-export).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError

from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_json

CARD_FORMAT = 1
CARD_FILE = "card.json"
CARD_MD = "card.md"
STEP_FILE = "step.pt2"
FILTER_FILE = "filter.onnx"



class CardError(ValueError):
    """An adaptation step folder or card is missing, invalid, or does not match a model."""


class FileEntry(StrictModel):
    path: str = Field(description="Path relative to the step folder (POSIX separators).")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="sha256 of the file's bytes.")


class ParameterMapping(StrictModel):
    """ONNX initializer = transform(parameter) * scale (scale: a constant folded at export)."""

    parameter: str = Field(description="Name of the step program's trainable parameter.")
    initializer: str = Field(description="Name of the initializer in the fp32 ONNX graph.")
    transform: Literal["copy", "transpose"] = Field(description="'transpose' for 2-D weights stored transposed.")
    scale: float = Field(1.0, description="Factor folded into the initializer (e.g. 1 / depth_scale_mm).")
    shape: tuple[int, ...] = Field(description="Shape of the parameter.")


class AdaptationCard(StrictModel):
    """``card.json`` of an adaptation step folder."""

    format_version: Literal[1] = CARD_FORMAT
    name: str
    description: str
    sensor_family: str
    mesh_hash: str = Field(description="Pad mesh the step's meshes follow (the family model's).")
    n_nodes: int
    n_sensing_nodes: int
    files: dict[str, FileEntry] = Field(description="step, filter, fp32_model (the graph whose "
                                        "initializers are replaced), family_model (the shipped graph), source_bundle (the training bundle "
                                        "both were exported from).")
    trainable: list[str] = Field(description="Parameters the step updates (encoder and projection).")
    frozen: str = Field(description="What stays fixed during adaptation.")
    inputs: dict[str, str]
    outputs: dict[str, str]
    parameter_map: list[ParameterMapping]
    int8_nodes: list[str] = Field(description="Nodes of the fp32 graph the shipped int8 graph quantises "
                                  "(empty when the shipped graph is fp32).")
    family_variant: str = Field(description="Export variant of the family model.")
    depth_scale_mm: float
    pixels_per_triangle: int = Field(description="Fixed pixel budget per triangle of the renderer.")
    defaults: dict[str, float] = Field(description="Suggested lr, batch_size, steps.")
    filter_kind: Literal["vae", "lean"] = Field(description="Image decoder of the noise filter.")
    parity: dict[str, float] = Field(description="Checks at export (mm).")
    versions: dict[str, str] = Field(description="torch, onnx, opset, training commit, date.")

    def path(self, folder: Path, key: str) -> Path:
        """Absolute path of file ``key`` of the card in ``folder``."""
        if key not in self.files:
            raise CardError(f"{folder / CARD_FILE}: no file entry {key!r} (has {sorted(self.files)})")
        return (Path(folder) / self.files[key].path).resolve()


def load_card(folder: str | os.PathLike) -> AdaptationCard:
    """Read and validate ``folder/card.json``."""
    path = Path(folder) / CARD_FILE
    if not path.is_file():
        raise CardError(f"{path} not found: an adaptation step folder holds {CARD_FILE}, {STEP_FILE} and "
                        f"{FILTER_FILE}; export one with `python -m tactile_deploy.training export-adapt --bundle MODEL.pt`")
    doc = read_json(path, CardError, "a JSON step card")
    if not isinstance(doc, dict) or doc.get("format_version") != CARD_FORMAT:
        got = doc.get("format_version") if isinstance(doc, dict) else type(doc).__name__
        raise CardError(f"{path}: field 'format_version' must be {CARD_FORMAT}, got {got!r}")
    try:
        return AdaptationCard.model_validate(doc)
    except ValidationError as e:
        bad = "; ".join(f"field '{'.'.join(map(str, err['loc']))}': {err['msg']}" for err in e.errors())
        raise CardError(f"{path}: invalid adaptation card: {bad}") from None


def render_markdown(card: AdaptationCard) -> str:
    """The card as markdown (card.md)."""
    rows = [f"| `{k}` | {v} |" for k, v in card.inputs.items()]
    outs = [f"| `{k}` | {v} |" for k, v in card.outputs.items()]
    return "\n".join([
        f"# Adaptation step: {card.name}",
        "",
        card.description,
        "",
        "## What it updates",
        "",
        f"- trainable ({len(card.trainable)} tensors): " + ", ".join(f"`{n}`" for n in card.trainable),
        f"- frozen: {card.frozen}",
        "",
        "## Inputs and outputs of `step.pt2`",
        "",
        "| input | description |",
        "|---|---|",
        *rows,
        "",
        "| output | description |",
        "|---|---|",
        *outs,
        "",
        f"`filter.onnx`: depth [N, 1, 128, 128] mm -> `filtered` [N, 128, 128] mm, the image VAE's "
        f"reconstruction (decoder: {card.filter_kind}), the adaptation target.",
        "",
        "## Files",
        "",
        *[f"- {k}: `{v.path}` (sha256 `{v.sha256[:16]}...`)" for k, v in card.files.items()],
        "",
        "## ONNX re-export",
        "",
        f"The adapted model is the fp32 graph `{card.files['fp32_model'].path}` with "
        f"{len(card.parameter_map)} initializers replaced (initializer = transform(parameter) x scale); "
        + ("folded scales: " + ", ".join(f"`{m.parameter}` x {m.scale:.6g}" for m in card.parameter_map if m.scale != 1.0)
           if any(m.scale != 1.0 for m in card.parameter_map) else "no folded scales")
        + f". The family model is `{card.family_variant}`"
        + (f"; {len(card.int8_nodes)} nodes are re-quantised to int8 on the adaptation frames." if card.int8_nodes else "."),
        "",
        "## Checks at export",
        "",
        *[f"- {k}: {v:.3g}" for k, v in card.parity.items()],
        "",
        "## Versions",
        "",
        *[f"- {k}: {v}" for k, v in card.versions.items()],
        "",
        "Defaults: " + ", ".join(f"{k} {v:g}" for k, v in card.defaults.items()) + ".",
        "",
    ])
