"""The adaptation's ``report.json`` (:class:`AdaptationReport`), kept in each adapted version
(``PLUGIN/adapted/vN/report.json``), and its reader (:func:`load_adaptation_report`).

:func:`tactile_deploy.adapt.workflow.adapt_plugin` builds the report through the model (also
when nothing is written: ``--dry-run`` or no improvement) and writes it with the version. The
held-out figures are the label-free RMSE (mm) of the paper: RMS over the held-out depth maps
and the pixels the sensor sees of rendered mesh minus target (target: VAE(depth), or the depth
itself with ``use_filter`` off). Errors of the reader name the file, each bad field, the rule it
breaks and the value it had.
"""

from __future__ import annotations

import os

from pydantic import Field, field_validator

from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_model_json

REPORT_NAME = "report.json"


class AdaptationReportError(ValueError):
    """An adaptation report that is missing or invalid (the message names file and field)."""


class FrameSourceRecord(StrictModel):
    """Where the frames came from (``tactile-deploy adapt --frames/--source``)."""

    source: str = Field(description="Name of the frame source (folder, clip, camera, demo).")
    frames: int = Field(ge=0, description="Frames the imaging pipeline turned into depth maps.")
    refused: int = Field(ge=0, description="Frames the imaging pipeline refused (skipped).")


class StepCardRecord(StrictModel):
    """The adaptation step the model was adapted with (its card: ``card.json``)."""

    name: str = Field(description="Name of the step (its card's name).")
    sha256: str = Field(description="sha256 of the step program (step.pt2).")
    torch: str | None = Field(description="torch version the step was exported with.")


class FrameCounts(StrictModel):
    """How the frames were split (blocks of consecutive frames)."""

    adapt: int = Field(ge=1, description="Frames the model was adapted on.")
    held_out: int = Field(ge=1, description="Frames kept aside to judge it.")


class AdaptSettingsRecord(StrictModel):
    """The settings of the adaptation (``tactile-deploy adapt`` options)."""

    steps: int = Field(ge=1, description="Adam steps.")
    batch_size: int = Field(ge=1, description="Depth maps per step.")
    lr: float = Field(ge=0, description="Adam learning rate (0: the weights stay as they are).")
    use_filter: bool = Field(description="Target VAE(depth) (True) or the depth itself (False).")
    device: str = Field(description="torch device the steps ran on.")
    seed: int = Field(description="Seed of the split and the batches.")


class AdaptationReport(StrictModel):
    """``PLUGIN/adapted/vN/report.json``: what an adaptation did and measured (``tactile-deploy
    adapt``). RMSE in mm (label-free, held-out frames); losses in mm^2; times in s."""

    plugin: str = Field(description="Name of the plugin adapted.")
    source: FrameSourceRecord | None = Field(
        None, description="Where the frames came from; None: depth maps given directly.")
    start: str = Field(description="Model the adaptation started from ('family model' or "
                       "'adapted model vN').")
    step: str = Field(description="Folder of the adaptation step.")
    step_card: StepCardRecord = Field(description="The step's card.")
    frames: FrameCounts = Field(description="Frames adapted on and held out.")
    settings: AdaptSettingsRecord = Field(description="Settings of the adaptation.")
    heldout_rmse_before_fp32_mm: float = Field(
        ge=0, description="Held-out RMSE of the network (fp32 step program) before, mm.")
    heldout_rmse_after_fp32_mm: float = Field(
        ge=0, description="Held-out RMSE of the network (fp32 step program) after, mm.")
    train_loss_first_mm2: float = Field(ge=0, description="Adaptation loss of the first step, mm^2.")
    train_loss_last_mm2: float = Field(ge=0, description="Adaptation loss of the last step, mm^2.")
    adapt_seconds: float = Field(ge=0, description="Time of the Adam steps, s.")
    steps_per_s: float = Field(ge=0, description="Adam steps per second.")
    renderer_overflow: int = Field(
        ge=0, description="Triangles beyond the renderer's pixel budget (their pixels may be "
        "missing from the loss).")
    created: str = Field(description="When the adaptation ran (ISO 8601, UTC).")
    parity_fp32_onnx_vs_step_max_abs_diff_mm: float = Field(
        ge=0, description="Largest |displacement| difference of the adapted fp32 ONNX graph and "
        "the step program on the held-out maps, mm.")
    int8: bool = Field(description="model.onnx is int8 (as the family model is).")
    int8_vs_fp32_rms_diff_mm: float | None = Field(
        None, ge=0, description="RMS displacement difference int8 vs fp32 graph, mm (int8 only).")
    int8_vs_fp32_max_abs_diff_mm: float | None = Field(
        None, ge=0, description="Largest displacement difference int8 vs fp32 graph, mm (int8 only).")
    ood_share_above_threshold_family: float | None = Field(
        None, ge=0, le=1, description="Share of held-out maps above the family model's "
        "out-of-distribution threshold (None: the model has none).")
    ood_share_above_threshold_adapted: float | None = Field(
        None, ge=0, le=1, description="The same of the adapted model.")
    heldout_rmse_model: str = Field(description="Which graph the next figures are of.")
    heldout_rmse_before_mm: float = Field(
        ge=0, description="Held-out RMSE of the start model as `run` uses it, mm.")
    heldout_rmse_after_mm: float = Field(
        ge=0, description="Held-out RMSE of the adapted model.onnx as `run` uses it, mm.")
    heldout_rmse_active_mm: float | None = Field(
        None, ge=0, description="Held-out RMSE of the active adapted model when it is not the "
        "start model, mm.")
    active: str | None = Field(None, description="The active adapted model ('adapted model vN') "
                               "when it is not the start model.")
    improved: bool = Field(description="The adapted model beat the start (and the active) model.")
    verdict: str = Field(description="'improved', or why no version was written.")
    seconds: float = Field(ge=0, description="Time of the whole adaptation, s.")

    @field_validator("source", mode="before")
    @classmethod
    def _empty_source(cls, v):
        """Reports written before the source was recorded hold ``{}``: no source."""
        return None if v == {} else v


def load_adaptation_report(path: str | os.PathLike) -> AdaptationReport:
    """Read and check an adaptation's ``report.json`` (:class:`AdaptationReportError` naming the
    file, each bad field and the value it had)."""
    return read_model_json(path, AdaptationReport, AdaptationReportError, "adaptation report",
                           "written by `tactile-deploy adapt`; the format is "
                           "adaptation_report.schema.json in tactile_deploy/adapt/",
                           expected="an adaptation report")
