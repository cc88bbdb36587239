"""The JSON files of a training run folder: ``metrics.json`` (:class:`TrainingMetrics`) and
``history.json`` (:class:`TrainingHistory`), built by :func:`tactile_deploy.training.train.train`
(and ``metrics.json`` of the augmented twin, :mod:`tactile_deploy.training.adaptation.augmented_twin`)
and read back by :func:`load_training_metrics` and :func:`load_training_history`.

Positions and displacements are in the sensor frame (origin at the centre of the sensing
surface, z up out of the gel); errors in mm or um as the field names say. ``*_mse`` of the
history are mean squared errors of normalised quantities (divided by the run's scales), not mm^2;
``*_rmse_mm`` and ``*_contact_patch_rmse_um`` are the same errors in mm / um. Errors of the
readers name the file, each bad field, the rule it breaks and the value it had.
"""

from __future__ import annotations

import os

from pydantic import Field

from tactile_deploy.atomic import finite_or_null
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_model_json
from tactile_deploy.training.metrics import MeshMetrics



class TrainingRunFileError(ValueError):
    """A training run's metrics.json or history.json that is missing or invalid."""


class OodQuantiles(StrictModel):
    """Quantiles of the image reconstruction RMSE (mm) on in-distribution depth maps: the
    calibration of the out-of-distribution score (its threshold is ``recon_rmse_mm_p99``)."""

    recon_rmse_mm_p50: float = Field(ge=0, description="Median, mm.")
    recon_rmse_mm_p95: float = Field(ge=0, description="95th percentile, mm.")
    recon_rmse_mm_p99: float = Field(ge=0, description="99th percentile, mm.")
    recon_rmse_mm_max: float = Field(ge=0, description="Largest, mm.")


class EvaluationFigures(StrictModel):
    """Figures of the image-to-mesh path on a set of contacts (:func:`tactile_deploy.training.train.evaluate`)."""

    n_samples: int = Field(ge=0, description="Depth maps evaluated.")
    vertex_rmse_mm: float = Field(ge=0, description="RMS over samples, nodes and axes of predicted "
                                  "- true vertex positions, mm (the paper's metric).")
    relative_error: float = Field(ge=0, description="|pred - true| / |true| of the displacements over the set.")
    max_error_mm: float = Field(ge=0, description="Largest per-node Euclidean error, mm.")
    mesh_metrics: MeshMetrics = Field(description="Per-node figures (tactile_deploy.training.metrics).")
    ood: OodQuantiles = Field(description="By the image VAE's decoder.")
    ood_lean: OodQuantiles = Field(description="By the lean image decoder (the deployed ood_score).")
    mesh_reconstruction_rmse_mm: float | None = Field(
        None, ge=0, description="The mesh VAE alone (true mesh -> latent mean -> decoder), mm: the "
        "floor the image-to-mesh path can reach with this decoder (None: no mesh VAE).")
    mesh_reconstruction_relative_error: float | None = Field(
        None, ge=0, description="The same as a relative error.")


class DecoderFigures(StrictModel):
    """Figures of one decoder of the run."""

    heldout: EvaluationFigures = Field(description="On the held-out contacts.")
    train: EvaluationFigures | None = Field(None, description="On as many training contacts.")
    heldout_augmented: EvaluationFigures | None = Field(
        None, description="On the held-out maps augmented (augmented twin only).")
    note: str | None = Field(None, description="What the figures are of.")


class ScalesRecord(StrictModel):
    """The run's normalisation (:class:`tactile_deploy.training.data.Scales`)."""

    depth_scale_mm: float = Field(gt=0, description="Mean over samples of the largest depth, mm.")
    displacement_scale_mm: list[float] = Field(min_length=3, max_length=3,
                                               description="RMS displacement over free nodes (x, y, z), mm.")


class DataSummary(StrictModel):
    """A data set of the run (:meth:`tactile_deploy.training.data.ContactData.summary`)."""

    source: str = Field(description="Where the samples came from.")
    n_samples: int = Field(ge=0, description="Samples (depth map + mesh).")
    n_contacts: int = Field(ge=0, description="Distinct presses.")
    indenters: dict[str, int] = Field(description="Samples by indenter.")
    max_depth_mm: float = Field(ge=0, description="Deepest depth of the set, mm.")


class DataSplit(StrictModel):
    """The training and held-out sets (split by contact)."""

    train: DataSummary
    val: DataSummary


class TwinOf(StrictModel):
    """The run an augmented twin was made from."""

    bundle: str = Field(description="model.pt of the source run.")
    metrics: DecoderFigures | None = Field(None, description="The source run's lean decoder figures "
                                           "(None: it had none).")


class TrainingMetrics(EvaluationFigures):
    """``RUN/metrics.json``: the held-out figures of the deployed decoder (top level), those of
    every decoder, the scales and the data."""

    decoders: dict[str, DecoderFigures] = Field(
        description="By decoder: coma, lean (after finetune when there is one), lean_staged (before "
        "it), surface.")
    scales: ScalesRecord | None = Field(None, description="The run's normalisation (not in an "
                                        "augmented twin's, which keeps its source's).")
    data: DataSplit = Field(description="The data sets.")
    twin_of: TwinOf | None = Field(None, description="Augmented twin only: its source run.")


class EpochRecord(StrictModel):
    """One epoch of a stage. ``train_*`` over the training batches, ``val_*`` over the held-out
    ones; which ``*_mse`` a stage has depends on its loss (None/absent: not part of it)."""

    epoch: int = Field(ge=1, description="Epoch number, from 1.")
    lr: float = Field(ge=0, description="Learning rate of the epoch.")
    seconds: float = Field(ge=0, description="Time of the epoch (training + validation), s.")
    stage_seconds: float = Field(ge=0, description="Time of the stage so far, s.")
    train_seconds: float = Field(ge=0, description="Time of the training loop of the epoch, s.")
    samples_per_s: float | None = Field(None, description="Training samples of all ranks per second "
                                        "of this rank's training loop.")
    train_loss: float | None = Field(description="Loss (the stage's objective) (None: not finite, the stage diverged).")
    val_loss: float | None = Field(description="Loss on the held-out set (None: not finite, the stage diverged).")
    train_mse: float | None = Field(ge=0, description="MSE of the stage's output, normalised (None: not finite, the stage diverged).")
    val_mse: float | None = Field(ge=0, description="The same, held out (None: not finite, the stage diverged).")
    train_rmse_mm: float | None = Field(ge=0, description="sqrt(train_mse) in mm (None: not finite, the stage diverged).")
    val_rmse_mm: float | None = Field(ge=0, description="sqrt(val_mse) in mm (None: not finite, the stage diverged).")
    train_kl: float | None = Field(None, description="KL term of a VAE stage.")
    val_kl: float | None = Field(None, description="The same, held out.")
    train_latent_mse: float | None = Field(None, ge=0, description="Latent MSE of the projection.")
    val_latent_mse: float | None = Field(None, ge=0, description="The same, held out.")
    train_contact_mse: float | None = Field(None, ge=0, description="MSE per axis of the sensing "
                                            "nodes in contact, normalised.")
    val_contact_mse: float | None = Field(None, ge=0, description="The same, held out.")
    train_contact_patch_rmse_um: float | None = Field(None, ge=0, description="Per-node Euclidean "
                                                      "RMS over the contact patch, um.")
    val_contact_patch_rmse_um: float | None = Field(None, ge=0, description="The same, held out.")
    train_deepest_rel: float | None = Field(None, ge=0, description="Mean squared relative depth error of "
                                            "each contact's deepest sensing node (surface stage, where its "
                                            "term is on; training/train.py deepest_node_term).")
    val_deepest_rel: float | None = Field(None, ge=0, description="The same, held out.")
    train_image_mse: float | None = Field(None, ge=0, description="Image VAE MSE (surface stage).")
    val_image_mse: float | None = Field(None, ge=0, description="The same, held out.")
    train_ood_image_mse: float | None = Field(None, ge=0, description="Lean image decoder MSE.")
    val_ood_image_mse: float | None = Field(None, ge=0, description="The same, held out.")


class TrainingHistory(StrictModel):
    """``RUN/history.json``: the epochs of each stage that ran, in order (a stage that did not
    run is absent)."""

    image_vae: list[EpochRecord] | None = Field(None, description="Image VAE.")
    surface: list[EpochRecord] | None = Field(None, description="Image encoder + surface-anchored decoder.")
    mesh_vae: list[EpochRecord] | None = Field(None, description="Mesh VAE.")
    lean_decoder: list[EpochRecord] | None = Field(None, description="Lean deployment decoder.")
    ood_decoder: list[EpochRecord] | None = Field(None, description="Out-of-distribution image decoder.")
    projection: list[EpochRecord] | None = Field(None, description="Latent projection.")
    finetune: list[EpochRecord] | None = Field(None, description="Projection + lean decoder end to end.")


def _load(path, model, what: str):
    return read_model_json(path, model, TrainingRunFileError, f"training {what}",
                           "written by `python -m tactile_deploy.training train`; the format "
                           "is in training/training_*.schema.json",
                           expected=f"a training run's {what}")


def load_training_metrics(path: str | os.PathLike) -> TrainingMetrics:
    """Read and check a run's ``metrics.json``."""
    return _load(path, TrainingMetrics, "metrics")


def load_training_history(path: str | os.PathLike) -> TrainingHistory:
    """Read and check a run's ``history.json`` (also ``docs/results/*.history.json``)."""
    return _load(path, TrainingHistory, "history")


def training_metrics(metrics: dict) -> TrainingMetrics:
    """The metrics of a run as the model (non-finite numbers as None, as the file writes them);
    write it with ``model_dump(mode="json", exclude_unset=True)`` (the fields it was given)."""
    return TrainingMetrics.model_validate(finite_or_null(metrics))


def training_history(history: dict) -> TrainingHistory:
    """The history of a run as the model (non-finite numbers as None, as the file writes them);
    write it with ``model_dump_json(indent=1, exclude_unset=True)``."""
    return TrainingHistory.model_validate(finite_or_null(history))
