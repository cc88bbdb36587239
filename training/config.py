"""Run configuration of the image-to-mesh predictor (one JSON file per run).

``python -m tactile_deploy.training train --config CONFIG.json``: the file is a :class:`TrainConfig`. Every model
here is strict (unknown keys and NaN/inf refused); field descriptions are the documentation.
Lengths in mm.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from tactile_deploy.fileformat import StrictModel
from tactile_deploy.training.errors import UsageError

FORMAT_VERSION = 1
DEVICE_PATTERN = re.compile(r"cpu|cuda|cuda:\d+|auto")


def check_device(name: str) -> str:
    """``name`` if it is 'cpu', 'cuda', 'cuda:N' or 'auto', else ValueError."""
    if not isinstance(name, str) or not DEVICE_PATTERN.fullmatch(name):
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {name!r}")
    return name


class ImageVAEConfig(StrictModel):
    resolution: int = Field(128, description="Depth map side, pixels (square).")
    widths: tuple[int, ...] = Field((32, 64, 128, 256, 512), description="Channels of the stride-2 convolutions.")
    kernel: int = Field(
        2, ge=2, le=5, description="Convolution kernel size (stride 2); 2 = non-overlapping, 2.4x cheaper than 3."
    )
    hidden: int = Field(128, gt=0, description="Fully connected layer before the latent heads.")
    latent: int = Field(128, gt=0, description="Latent dimension d(z_I).")
    activation: Literal["elu", "relu"] = Field(
        "relu", description="ReLU: onnxruntime fuses it into the convolutions (ELU costs ~3 ns/value)."
    )

    @model_validator(mode="after")
    def _check(self) -> "ImageVAEConfig":
        if self.resolution % 2 ** len(self.widths):
            raise ValueError(
                f"resolution={self.resolution} is not divisible by 2**{len(self.widths)} "
                f"(one halving per width in {self.widths})"
            )
        return self


class MeshVAEConfig(StrictModel):
    channels: tuple[int, ...] = Field((16, 16, 16, 32), description="Encoder features at levels 0..3.")
    cheb_k: tuple[int, ...] = Field((6, 6, 6, 6), description="Chebyshev order K at levels 0..3 (encoder and decoder).")
    factors: tuple[int, ...] = Field((4, 4, 4, 4), description="Node reduction per coarsening level.")
    pooling: Literal["select", "average"] = Field("select", description="Down-sampling of the encoder.")
    latent: int = Field(128, gt=0, description="Latent dimension d(z_M).")
    activation: Literal["elu", "relu"] = "relu"

    @model_validator(mode="after")
    def _check(self) -> "MeshVAEConfig":
        if not len(self.channels) == len(self.cheb_k) == len(self.factors):
            raise ValueError(
                f"channels {self.channels}, cheb_k {self.cheb_k} and factors {self.factors} need one "
                f"entry per level"
            )
        return self


class ProjectionConfig(StrictModel):
    hidden: tuple[int, ...] = Field((256, 512, 256), description="Widths of the fully connected layers.")
    activation: Literal["elu", "relu"] = "relu"


class GridDecoderConfig(StrictModel):
    """The lean deployment decoder (:mod:`tactile_deploy.training.networks.grid_decoder`)."""

    grid: int = Field(64, description="Pixels per side of the in-plane grid (a power of two >= 8).")
    channels: tuple[int, ...] = Field((64, 64, 32, 32), description="Channels at 4x4, 8x8, ... grid/2.")
    half_extent_mm: float = Field(17.5, gt=0, description="The grid spans +-this in x and y, mm.")


class LeanImageDecoderConfig(StrictModel):
    """Small decoder of the image latent whose reconstruction error is the deployed ood_score."""

    channels: tuple[int, ...] = Field(
        (32, 32, 16, 16, 8), description="Channels at 4x4, 8x8, ..., resolution/2 (one per up-sampling step)."
    )


class SurfaceDecoderConfig(StrictModel):
    """The surface-anchored decoder (:mod:`tactile_deploy.training.networks.surface_decoder`): sensing nodes on the
    measured surface, a convolutional residual with skips from every encoder level."""

    channels: tuple[int, ...] = Field(
        (32, 32, 32, 32), description="Decoder channels at 4 x 4, 8 x 8, ...: one per level up to the last "
        "feature grid (4 x 2**(len - 1) pixels a side)."
    )
    conv3x3_at: tuple[int, ...] = Field((8, 16), description="Grid sides (4, 8, ...) that get a 3 x 3 convolution.")
    latent_start: bool = Field(True, description="Add an FC of the image latent to the 4 x 4 start (global context).")
    anchor: Literal["rest", "moved"] = Field(
        "rest", description="Where a sensing node reads the depth map: at its rest (x, y), or where the decoder "
        "moves it (rest + predicted lateral displacement: the depth map shows the surface where it has moved to).",
    )
    half_extent_mm: float = Field(17.5, gt=0, description="The depth map spans +-this in x and y, mm.")
    lateral: Literal["learned", "lift_residual"] = Field(
        "learned", description="The sensing nodes' lateral (x, y) motion: predicted by the decoder (a hybrid "
        "export replaces it by the physics lift's), or the physics lift of their u_z (frictionless, linear) plus "
        "the decoder's residual, in training and in every export (what friction and large strain add to it).",
    )


class ModelConfig(StrictModel):
    image: ImageVAEConfig = Field(default_factory=ImageVAEConfig)
    mesh: MeshVAEConfig = Field(default_factory=MeshVAEConfig)
    projection: ProjectionConfig = Field(default_factory=ProjectionConfig)
    lean_decoder: GridDecoderConfig = Field(default_factory=GridDecoderConfig)
    ood_decoder: LeanImageDecoderConfig = Field(default_factory=LeanImageDecoderConfig)
    surface: SurfaceDecoderConfig | None = Field(
        None, description="The surface-anchored decoder (the deployed one when given; None: the latent decoders only)."
    )


class ProceduralFaces(StrictModel):
    """Random pressing faces beside the named indenters (unseen-shape augmentation).

    The faces are :func:`tactile_deploy.training.shading_net.shapes.random_indenter`'s families
    (flat punches 0.8-18 mm across, holed faces and rings, bars and lines, pins, curved bodies,
    edges and steps reaching beyond the view, raised relief), drawn once from ``seed`` and the
    same on every rank; each contact presses one of them with probability ``share``.
    """

    count: int = Field(gt=0, le=20000, description="Distinct faces in the set.")
    share: float = Field(gt=0, le=1, description="Fraction of the contacts pressed with a procedural face.")
    seed: int = Field(0, ge=0, description="Seed of the faces (not of the poses).")


class SyntheticData(StrictModel):
    """Generate the data with the contact simulator (each rank of a distributed run its own shard)."""

    n_samples: int = Field(gt=0, description="Contacts per rank (with split_over_ranks: over all ranks).")
    split_over_ranks: bool = Field(
        False, description="n_samples is the total of a distributed run: rank r of W makes n_samples // W (+1 for "
        "r < n_samples % W), so 1, 2 or 4 GPUs train on the same amount of data.",
    )
    indenters: tuple[str, ...] | Literal["primitive"] = Field("primitive", description="Names, or all primitives.")
    procedural: ProceduralFaces | None = Field(
        None, description="Add random pressing faces to the indenters (None: the named indenters only)."
    )
    seed: int = Field(0, ge=0, description="Rank r draws from default_rng([seed, r]).")
    depth_min_mm: float = Field(0.2, gt=0)
    depth_max_mm: float = Field(1.2, gt=0)
    radius_max_mm: float = Field(12.0, ge=0, description="Contacts lie within this radius, mm.")
    nu: float = Field(0.48, ge=0, lt=0.5, description="Poisson ratio of the gel.")
    friction: Literal["frictionless", "stick", "coulomb"] | tuple[Literal["frictionless", "stick", "coulomb"], ...] = Field(
        "frictionless", description="Contact law of the simulated presses: the gel slides freely, sticks to the "
        "indenter, or follows Coulomb's law with a coefficient drawn per contact from mu_range; a list of laws makes "
        "a mixture (equal shares: law k for contacts k, k + L, ... on the CPU, for the k-th block of samples in the "
        "batched generator).",
    )
    mu_range: tuple[float, float] = Field(
        (0.3, 1.5), description="Coulomb contact: friction coefficients drawn uniformly from [low, high] per contact."
    )
    gel: Literal["linear", "neo-hookean"] | tuple[Literal["linear", "neo-hookean"], ...] = Field(
        "linear", description="Gel law of the presses: small-strain linear elasticity, or the compressible "
        "neo-Hookean gel at large deformation (frictionless contact only; the hyperelastic effect's solve, "
        "tactile_deploy.sensors.effects.hyperelastic, batched by training/simulation/batched_neo_hookean.py). One "
        "law for every contact law, or one per entry of a friction list (e.g. friction [frictionless, "
        "frictionless] with gel [linear, neo-hookean]: half of the presses each).",
    )
    contact_radius_mm: float | None = Field(
        None, gt=0, description="Only sensing nodes within this radius may touch (faster operators; tests)."
    )
    generator: Literal["cpu", "batched"] = Field(
        "cpu",
        description="'cpu': the CPU contact simulator, one contact at a time; 'batched': the batched "
        "torch simulator on the training device (GPU: tens of thousands of contacts per second).",
    )
    envelope_bank: str | None = Field(
        None,
        description="'batched' only: an .npz of the indenters' envelope grids (EnvelopeBank.save_npz), "
        "for machines without the mesh libraries; its names must match the indenters.",
    )
    formulation: Literal["nodal_pressure", "standard"] = Field(
        "nodal_pressure",
        description="Tet formulation with contact_radius_mm: locking-free nodal pressure, or standard "
        "linear tets (a 5x cheaper factorisation; stiffer near nu = 0.5, for quick tests).",
    )

    @model_validator(mode="after")
    def _check_mu(self) -> "SyntheticData":
        low, high = self.mu_range
        if not 0.0 <= low <= high:
            raise ValueError(f"mu_range must be [low, high] with 0 <= low <= high, got {list(self.mu_range)}")
        laws = (self.friction,) if isinstance(self.friction, str) else tuple(self.friction)
        gels = (self.gel,) if isinstance(self.gel, str) else tuple(self.gel)
        if len(gels) not in (1, len(laws)):
            raise ValueError(f"gel must be one law or one per friction law ({len(laws)}: {list(laws)}), "
                             f"got {len(gels)}: {list(gels)}")
        for law, gel in zip(laws, gels * len(laws) if len(gels) == 1 else gels):
            if gel == "neo-hookean" and law != "frictionless":
                raise ValueError(f"gel 'neo-hookean' is solved with frictionless contact only, got friction "
                                 f"{law!r} for it; pair it with 'frictionless'")
        return self


class DataConfig(StrictModel):
    dataset_dir: str | None = Field(None, description="Folder of a simulated dataset (dataset.json + shards).")
    synthetic: SyntheticData | None = Field(None, description="Or generate the data at start-up.")
    cache_file: str | None = Field(None, description="npz cache of generated data (reused when present).")
    val_fraction: float = Field(0.2, gt=0, lt=1, description="Share of contacts held out (split by contact).")
    split_seed: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _check(self) -> "DataConfig":
        if (self.dataset_dir is None) == (self.synthetic is None):
            raise ValueError("give exactly one of data.dataset_dir and data.synthetic")
        return self


class StageConfig(StrictModel):
    epochs: int = Field(gt=0)
    batch_size: int = Field(32, gt=0)
    lr: float = Field(1e-3, gt=0, description="Adam learning rate.")
    lr_decay: float = Field(0.99, gt=0, le=1, description="Multiplied into the learning rate after every epoch.")
    kl_weight: float = Field(1e-4, ge=0, description="lambda of the VAE stages (loss = MSE + lambda KL).")
    latent_weight: float = Field(
        0.1, ge=0, description="Projection stage: weight of the latent MSE beside the mesh MSE."
    )
    time_budget_s: float | None = Field(
        None, gt=0, description="Stop when one more epoch (as long as the last) would end past this many "
        "seconds of the stage; the first epoch always runs (None: run every epoch). The history records "
        "the epochs run.",
    )


class SurfaceStageConfig(StageConfig):
    """The surface stage: image encoder + surface-anchored decoder end to end on the mesh error,
    with the image VAE's loss beside it so that its reconstruction (ood_score, adaptation filter)
    stays trained."""

    surface_weight: float = Field(1.0, ge=0, description="Extra weight of the sensing layer's nodes in the mesh MSE.")
    contact_weight: float = Field(4.0, ge=0, description="Extra weight of the sensing nodes in contact in the mesh MSE.")
    deepest_weight: float = Field(
        0.0, ge=0, description="Weight of the deepest-node term: per contact, the squared relative error of the "
        "predicted depth at the truth's deepest sensing node, (d_pred - d) / max(d, deepest_floor_mm), averaged over "
        "the batch (the evaluation's deepest-node error, squared; 0: off).",
    )
    deepest_floor_mm: float = Field(
        0.05, gt=0, description="Depth below which the deepest-node term's relative error is taken against this "
        "depth instead, mm (so barely touching contacts do not dominate it).",
    )
    image_weight: float = Field(
        0.1, ge=0, description="Weight of the image VAE loss (its decoder trains too; 0 with train_encoder false)."
    )
    train_encoder: bool = Field(True, description="Train the image encoder with the decoder (else frozen).")
    train_ood_decoder: bool = Field(
        False, description="Train the lean image decoder (the deployed ood_score) in this stage too, on the "
        "reconstruction from the latent mean, with the image VAE's weight (the ood_decoder stage then fine-tunes it).",
    )


class AugmentationConfig(StrictModel):
    """Augmentation of the simulated depth maps (:mod:`tactile_deploy.training.augment`); ranges are (low, high)
    of uniform draws per map. Defaults: the ranges measured on the virtual GelSlim sensors
    (``python -m tactile_deploy.training.adaptation.domain_gap``, docs/adaptation.md)."""

    probability: float = Field(0.8, ge=0, le=1, description="Share of maps augmented (the rest pass clean).")
    blur_sigma_mm: tuple[float, float] = Field((0.0, 0.7), description="Gaussian blur sigma, mm.")
    halo_amount: tuple[float, float] = Field((0.0, 0.6), description="a of d + a (d - G_s(d)): negative ring around contacts.")
    halo_sigma_mm: tuple[float, float] = Field((0.5, 2.0), description="s of the halo's Gaussian, mm.")
    gain: tuple[float, float] = Field((0.6, 1.3), description="Depth scale factor (drawn log-uniform).")
    view_box_probability: float = Field(0.5, ge=0, le=1, description="Share of maps cut to a random camera view box.")
    view_half_width_mm: tuple[float, float] = Field((10.0, 17.5), description="Half-width (x) of the view box, mm.")
    view_half_height_mm: tuple[float, float] = Field((7.0, 17.5), description="Half-height (y) of the view box, mm.")
    view_offset_mm: float = Field(1.0, ge=0, description="The box centre lies within +-this of the pad centre, mm.")
    view_min_visible: float = Field(0.7, ge=0, le=1, description="Cut only maps keeping this share of the contact's volume.")
    perlin_rms_mm: tuple[float, float] = Field((0.0, 0.03), description="RMS of the Perlin noise, mm.")
    perlin_wavelengths_mm: tuple[float, ...] = Field((8.0, 4.0, 2.0), description="Lattice cell of each Perlin octave, mm.")
    noise_references: tuple[str, ...] = Field((), description="Noise reference images (.npy, (R, R) mm: a plugin's noise_reference.npy).")
    noise_reference_gain: tuple[float, float] = Field((-2.0, 2.0), description="Factor of the added noise reference.")
    pixel_noise_mm: float = Field(0.002, ge=0, description="Standard deviation of per-pixel Gaussian noise, mm.")

    @model_validator(mode="after")
    def _check(self) -> "AugmentationConfig":
        for name in ("blur_sigma_mm", "halo_amount", "halo_sigma_mm", "gain", "view_half_width_mm",
                     "view_half_height_mm", "perlin_rms_mm", "noise_reference_gain"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"augmentation.{name}: low {lo} exceeds high {hi}")
        if self.gain[0] <= 0 or min(self.blur_sigma_mm + self.halo_sigma_mm + self.perlin_rms_mm) < 0:
            raise ValueError(f"augmentation: gain must be > 0 and sigmas/RMS >= 0, got gain {self.gain}, "
                             f"blur {self.blur_sigma_mm}, halo {self.halo_sigma_mm}, perlin {self.perlin_rms_mm}")
        return self


class TrainConfig(StrictModel):
    format_version: int = FORMAT_VERSION
    run_dir: str = Field(description="Checkpoints, curves and the exported model go here.")
    device: str = Field("cpu", description="'cpu', 'cuda', 'cuda:1', or 'auto'.")
    seed: int = Field(0, ge=0, description="Initialisation and shuffling seed.")
    threads: int | None = Field(None, gt=0, description="torch intra-op threads (CPU).")
    model: ModelConfig = Field(default_factory=ModelConfig)
    data: DataConfig
    init_weights: str | None = Field(
        None, description="A training bundle (model.pt, or its slim bundle) of the same model whose weights and "
        "data scales start this run (fine-tuning); None: a fresh initialisation from seed.",
    )
    image_vae: StageConfig | None = Field(
        default_factory=lambda: StageConfig(epochs=20),
        description="Pre-train the image VAE alone (None: the surface stage trains it from scratch with the decoder).",
    )
    mesh_vae: StageConfig | None = Field(
        default_factory=lambda: StageConfig(epochs=20),
        description="The mesh VAE (COMA); None: skip it and the latent decoders built on it (lean_decoder, "
        "projection, finetune), for a model with the surface decoder.",
    )
    projection: StageConfig | None = Field(
        default_factory=lambda: StageConfig(epochs=20), description="The latent projection (None: skip; needs mesh_vae)."
    )
    surface: SurfaceStageConfig | None = Field(
        None, description="Train the surface-anchored decoder (model.surface) with the image encoder (None: skip)."
    )
    lean_decoder: StageConfig | None = Field(
        default_factory=lambda: StageConfig(epochs=20),
        description="Train the lean decoder on the frozen mesh encoder's latents (None: skip).",
    )
    ood_decoder: StageConfig | None = Field(
        default_factory=lambda: StageConfig(epochs=20),
        description="Train the lean image decoder (deployed ood_score) on the frozen image encoder (None: skip).",
    )
    augmentation: AugmentationConfig | None = Field(
        None, description="Augment depth maps (image VAE: augmented in, clean out; projection: latents of "
        "augmented maps). None: train on clean maps only.",
    )
    eval_max_samples: int | None = Field(
        10000, gt=0, description="Held-out (and training-probe) samples evaluated at the end (None: all).",
    )
    finetune: StageConfig | None = Field(
        None,
        description="After the projection: train projection + lean decoder together on the mesh MSE of the "
        "image -> mesh path, image encoder frozen (None: skip). Needs lean_decoder.",
    )

    @field_validator("device")
    @classmethod
    def _check_device(cls, v: str) -> str:
        return check_device(v)

    @model_validator(mode="after")
    def _check_stages(self) -> "TrainConfig":
        if self.finetune is not None and (self.lean_decoder is None or self.projection is None):
            raise ValueError("finetune trains the projection and the lean decoder: give both, or set finetune to null")
        if self.mesh_vae is None and (self.lean_decoder is not None or self.projection is not None):
            raise ValueError("lean_decoder and projection decode the mesh VAE's latent: give mesh_vae too, or set "
                             "them to null")
        if (self.surface is None) != (self.model.surface is None):
            raise ValueError("the surface stage trains model.surface: give both, or neither")
        if self.image_vae is None and (self.surface is None or not self.surface.train_encoder
                                       or self.surface.image_weight == 0):
            raise ValueError("without image_vae the image VAE is trained only by the surface stage: give surface "
                             "with train_encoder true and image_weight > 0, or give image_vae")
        if self.mesh_vae is None and self.surface is None:
            raise ValueError("no mesh decoder would be trained: give mesh_vae (and projection) or surface")
        return self

    @staticmethod
    def load(path: str | Path) -> "TrainConfig":
        """The config in the JSON file ``path``; :class:`UsageError` naming the file and each bad field."""
        from tactile_deploy.jsonfile import read_json, validation_error_text

        path = Path(path)
        if not path.is_file():
            raise UsageError(f"config {path} not found{' (it is a folder)' if path.is_dir() else ''}; "
                             "give a TrainConfig JSON file (training/configs/ has examples, docs/predictor.md)")
        doc = read_json(path, UsageError, "a JSON training config")
        if not isinstance(doc, dict):
            raise UsageError(f"{path}: expected a JSON object (a training config), got {type(doc).__name__}")
        try:
            return TrainConfig.model_validate(doc)
        except ValidationError as e:
            raise UsageError(validation_error_text(
                path, e, "training config", "fix these fields; training/config.py describes each")) from None
