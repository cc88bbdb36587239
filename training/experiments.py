"""The paper's questions at our scale: latent sizes, KL weights, pre-training vs training from scratch.

``python -m tactile_deploy.training experiments --config CONFIG.json --out DIR [--only latent,kl,scratch]``

Every experiment trains on the same data (``base.data``: generated once, split by contact) with
the same stage settings, and reports the held-out vertex error of the image -> mesh path:

* ``latent``: image VAEs with d(z_I) in ``latent_image``, mesh VAEs with d(z_M) in
  ``latent_mesh`` (paper: 64 / 128 / 256 each), then one projection per pair (COMA decoder);
* ``kl``: image VAEs with lambda_I in ``kl_image_paper`` and mesh VAEs with lambda_M in
  ``kl_mesh_paper`` (paper: {0, 100, 200} x {0, 200, 400, 800}), one projection per pair;
* ``scratch``: the same architecture trained end to end from random weights on the mesh MSE
  (image encoder + projection + COMA decoder, and + lean decoder), against the staged runs.

The paper's lambdas multiply a KL term beside an MSE whose reduction it does not state; we take
its MSE as a **sum** over the map's pixels (16,384) or the mesh's coordinates (16,140) and its KL
as a sum over latent dimensions, so that lambda_paper = kl_weight x n_elements in our reduction
(mean MSE + kl_weight x KL): ``kl_weight = lambda_paper / n_elements``.

Results go to ``DIR/experiments.json`` (:class:`ExperimentsReport`, read back by
:func:`load_experiments`) after every run (atomically), so a stopped job keeps what it finished.
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path
from typing import Callable, Literal

import numpy as np
import torch
from pydantic import Field

from tactile_deploy.atomic import finite_or_null
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.jsonfile import read_model_json
from tactile_deploy.training import distributed
from tactile_deploy.training.config import StageConfig, TrainConfig
from tactile_deploy.training.networks.coarsening import build_hierarchy
from tactile_deploy.training.networks.predictor import Predictor
from tactile_deploy.training.run_files import DataSummary
from tactile_deploy.training.train import (
    _freeze,
    _Tensors,
    encode_latents,
    evaluate,
    image_vae_step,
    mesh_vae_step,
    prepare_data,
    projection_step,
    run_stage,
)


class ExperimentConfig(StrictModel):
    base: TrainConfig = Field(description="Data, stage settings and model of every run (run_dir: scratch space).")
    latent_image: tuple[int, ...] = Field((64, 128, 256), description="d(z_I) of the latent-size grid.")
    latent_mesh: tuple[int, ...] = Field((64, 128, 256), description="d(z_M) of the latent-size grid.")
    kl_image_paper: tuple[float, ...] = Field((0.0, 100.0, 200.0), description="lambda_I, the paper's scale.")
    kl_mesh_paper: tuple[float, ...] = Field((0.0, 200.0, 400.0, 800.0), description="lambda_M, the paper's scale.")
    scratch: StageConfig = Field(description="End-to-end training from random weights.")
    eval_samples: int = Field(5000, gt=0, description="Held-out samples evaluated per run.")

    @staticmethod
    def load(path: str | Path) -> "ExperimentConfig":
        return ExperimentConfig.model_validate(json.loads(Path(path).read_text()))


class ExperimentRun(StrictModel):
    """One result row: the settings of a run and the held-out figures of its image -> mesh path
    (COMA decoder unless ``decoder`` says otherwise; positions in the sensor frame, mm)."""

    group: Literal["latent", "kl", "scratch", "pretrained"] = Field(description="Experiment group.")
    d_image: int = Field(ge=1, description="d(z_I), the image latent size.")
    d_mesh: int = Field(ge=1, description="d(z_M), the mesh latent size.")
    decoder: Literal["coma", "lean"] | None = Field(None, description="Decoder trained end to end "
                                                    "(group scratch only).")
    lambda_image_paper: float | None = Field(None, ge=0, description="lambda_I at the paper's scale (group kl).")
    lambda_mesh_paper: float | None = Field(None, ge=0, description="lambda_M at the paper's scale (group kl).")
    kl_weight_image: float | None = Field(None, ge=0, description="Image VAE kl_weight (mean-MSE reduction).")
    kl_weight_mesh: float | None = Field(None, ge=0, description="Mesh VAE kl_weight (mean-MSE reduction).")
    image_vae_val_rmse_mm: float | None = Field(None, ge=0, description="Image VAE held-out RMSE "
                                                "of its last epoch, mm (staged runs).")
    mesh_vae_val_rmse_mm: float | None = Field(None, ge=0, description="Mesh VAE held-out RMSE of "
                                               "its last epoch, mm (staged runs).")
    seconds: float = Field(ge=0, description="Training time of the run (its VAEs included), s.")
    vertex_rmse_mm: float | None = Field(description="Held-out vertex RMSE, mm (the paper's "
                                         "metric; None: not finite).")
    relative_error: float | None = Field(description="Held-out |pred - true| / |true|.")
    max_error_mm: float | None = Field(description="Largest held-out per-node error, mm.")
    mesh_reconstruction_relative_error: float | None = Field(
        description="The mesh VAE alone, relative error (the floor of the COMA path).")


class ExperimentsData(StrictModel):
    """The data every run trained and was judged on."""

    train: DataSummary = Field(description="The training set.")
    n_eval: int = Field(ge=1, description="Held-out samples evaluated per run.")


class ExperimentsReport(StrictModel):
    """``DIR/experiments.json`` (also ``docs/results/experiments_*.json``): the config and one row
    per finished run."""

    config: ExperimentConfig = Field(description="The experiments' config.")
    runs: list[ExperimentRun] = Field(description="Finished runs, in order.")
    data: ExperimentsData = Field(description="The data.")


class ExperimentsError(ValueError):
    """An experiments.json that is missing or invalid."""


def load_experiments(path: str | Path) -> ExperimentsReport:
    """Read and check an ``experiments.json`` (:class:`ExperimentsError` naming the file, each
    bad field and the value it had)."""
    return read_model_json(path, ExperimentsReport, ExperimentsError, "experiments results",
                           "written by `python -m tactile_deploy.training experiments`; the "
                           "format is experiments.schema.json in training/")


class _ImageToMesh(torch.nn.Module):
    """Normalised depth (N, 1, R, R) -> normalised displacement (N, n, 3): encoder mean, projection, decoder."""

    def __init__(self, encoder, projection, decoder):
        super().__init__()
        self.encoder, self.projection, self.decoder = encoder, projection, decoder

    def forward(self, depth: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.projection(self.encoder(depth)[0]))


class _Runner:
    """Shared data and hierarchy; trains VAEs once per setting and projections per pair."""

    def __init__(self, cfg: ExperimentConfig, out: Path, log: Callable[[str], None]):
        from tactile_deploy.pad.asset import load_pad

        self.cfg, self.out, self.log = cfg, out, log
        self.dist, self.device = distributed.init(cfg.base.device)
        if self.device.type == "cuda":
            torch.backends.cuda.matmul.allow_tf32 = True
            torch.backends.cudnn.allow_tf32 = True
        self.pad = load_pad()
        self.hierarchy = build_hierarchy(self.pad, cfg.base.model.mesh.factors, cfg.base.model.mesh.pooling)
        probe = self.model(cfg.base.model.image.latent, cfg.base.model.mesh.latent)
        self.train_data, val_data, self.scales = prepare_data(cfg.base, probe, self.dist, self.device, log)
        self.val_data = val_data.subset(np.arange(min(len(val_data), cfg.eval_samples)))
        probe.to(self.device)
        self.sets = {True: _Tensors(self.train_data, probe, self.device), False: _Tensors(val_data, probe, self.device)}
        self.mask = probe.norm.free_mask.to(self.device)
        self.scale_mm = float(self.scales.displacement_scale_mm[0])
        self.image_vaes: dict = {}
        self.mesh_vaes: dict = {}
        self.results: dict = {"config": cfg.model_dump(mode="json"), "runs": []}

    def model(self, d_image: int, d_mesh: int) -> Predictor:
        m = self.cfg.base.model
        mc = m.model_copy(update={
            "image": m.image.model_copy(update={"latent": d_image}),
            "mesh": m.mesh.model_copy(update={"latent": d_mesh}),
        })
        torch.manual_seed(self.cfg.base.seed)
        model = Predictor(mc, self.hierarchy, self.pad.vertices, self.pad.backplate_nodes)
        if hasattr(self, "scales"):
            model.norm.set_scales(self.scales.depth_scale_mm, self.scales.displacement_scale_mm)
        return model.to(self.device) if hasattr(self, "device") else model

    def _stage(self, tag: str, name: str, module, step, stage: StageConfig, scale_mm: float) -> tuple[list, float]:
        t0 = time.perf_counter()
        hist = run_stage(
            name, module, step, self.sets[True].n, self.sets[False].n, stage, self.out / "runs" / tag,
            self.dist, self.device, self.cfg.base.seed, self.log, scale_mm,
        )
        return hist, time.perf_counter() - t0

    def image_vae(self, d: int, kl_weight: float):
        key = (d, kl_weight)
        if key not in self.image_vaes:
            model = self.model(d, self.cfg.base.model.mesh.latent)
            stage = self.cfg.base.image_vae.model_copy(update={"kl_weight": kl_weight})
            hist, sec = self._stage(f"image_d{d}_kl{kl_weight:.3g}", "image_vae", model.image_vae,
                                    image_vae_step(self.sets, kl_weight), stage, self.scales.depth_scale_mm)
            self.image_vaes[key] = (copy.deepcopy(model.image_vae.state_dict()), hist[-1], sec)
        return self.image_vaes[key]

    def mesh_vae(self, d: int, kl_weight: float):
        key = (d, kl_weight)
        if key not in self.mesh_vaes:
            model = self.model(self.cfg.base.model.image.latent, d)
            stage = self.cfg.base.mesh_vae.model_copy(update={"kl_weight": kl_weight})
            hist, sec = self._stage(f"mesh_d{d}_kl{kl_weight:.3g}", "mesh_vae", model.mesh_vae,
                                    mesh_vae_step(self.sets, self.mask, kl_weight), stage, self.scale_mm)
            self.mesh_vaes[key] = (copy.deepcopy(model.mesh_vae.state_dict()), hist[-1], sec)
        return self.mesh_vaes[key]

    def staged(self, group: str, d_image: int, d_mesh: int, kl_image: float, kl_mesh: float, **labels) -> None:
        """Pre-trained VAEs (frozen) + projection through the COMA decoder; one result row."""
        img_state, img_last, img_sec = self.image_vae(d_image, kl_image)
        mesh_state, mesh_last, mesh_sec = self.mesh_vae(d_mesh, kl_mesh)
        model = self.model(d_image, d_mesh)
        model.image_vae.load_state_dict(img_state)
        model.mesh_vae.load_state_dict(mesh_state)
        _freeze(model.image_vae)
        _freeze(model.mesh_vae)
        encode_latents(model, self.sets.values())
        tag = f"{group}_i{d_image}_m{d_mesh}_kli{kl_image:.3g}_klm{kl_mesh:.3g}"
        _, sec = self._stage(tag, "projection", model.projection,
                             projection_step(self.sets, model.mesh_vae.decoder, self.mask, self.cfg.base.projection.latent_weight),
                             self.cfg.base.projection, self.scale_mm)
        model.deploy_decoder = "coma"
        self.record(group, model, dict(labels, d_image=d_image, d_mesh=d_mesh, kl_weight_image=kl_image,
                                       kl_weight_mesh=kl_mesh, image_vae_val_rmse_mm=img_last["val_rmse_mm"],
                                       mesh_vae_val_rmse_mm=mesh_last["val_rmse_mm"],
                                       seconds=img_sec + mesh_sec + sec))

    def scratch(self, decoder: str) -> None:
        """Image encoder + projection + decoder from random weights, end to end on the mesh MSE."""
        d_i, d_m = self.cfg.base.model.image.latent, self.cfg.base.model.mesh.latent
        model = self.model(d_i, d_m)
        model.deploy_decoder = decoder
        dec = model.lean_decoder if decoder == "lean" else model.mesh_vae.decoder
        net = _ImageToMesh(model.image_vae.encoder, model.projection, dec)
        sets, mask = self.sets, self.mask

        def step(m, idx, train):
            t = sets[train]
            mse = torch.mean((m(t.depth[idx]) * mask - t.disp[idx]) ** 2)
            return mse, {"loss": mse.detach(), "mse": mse.detach()}

        _, sec = self._stage(f"scratch_{decoder}", "finetune", net, step, self.cfg.scratch, self.scale_mm)
        self.record("scratch", model, {"decoder": decoder, "d_image": d_i, "d_mesh": d_m, "seconds": sec})

    def record(self, group: str, model: Predictor, labels: dict) -> None:
        model.eval()
        ev = evaluate(model, self.val_data, self.device)
        row = {"group": group, **labels, "vertex_rmse_mm": ev["vertex_rmse_mm"],
               "relative_error": ev["relative_error"], "max_error_mm": ev["max_error_mm"],
               "mesh_reconstruction_relative_error": ev["mesh_reconstruction_relative_error"]}
        self.results["runs"].append(row)
        self.log(f"[{group}] {labels}: held-out vertex RMSE {row['vertex_rmse_mm'] * 1e3:.2f} um, "
                 f"relative error {row['relative_error']:.3f}")
        if self.dist.is_main:
            from tactile_deploy.atomic import write_json

            self.results["data"] = {"train": self.train_data.summary(), "n_eval": len(self.val_data)}
            report = ExperimentsReport.model_validate(finite_or_null(self.results))
            write_json(self.out / "experiments.json", report.model_dump(mode="json", exclude_unset=True))


def kl_weight_from_paper(lam: float, n_elements: int) -> float:
    """Our kl_weight (mean-MSE reduction) for the paper's lambda (sum-MSE reduction)."""
    return float(lam) / n_elements


def run_experiments(cfg: ExperimentConfig, out: str | Path, only: tuple[str, ...] = ("latent", "kl", "scratch"),
                    log: Callable[[str], None] = print) -> dict:
    """Run the selected experiment groups; returns (and writes) ``DIR/experiments.json``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    r = _Runner(cfg, out, log)
    base = cfg.base
    n_pixels = base.model.image.resolution ** 2
    n_coords = 3 * len(r.pad.vertices)
    if "latent" in only:
        for d_i in cfg.latent_image:
            for d_m in cfg.latent_mesh:
                r.staged("latent", d_i, d_m, base.image_vae.kl_weight, base.mesh_vae.kl_weight)
    if "kl" in only:
        d_i, d_m = base.model.image.latent, base.model.mesh.latent
        for lam_i in cfg.kl_image_paper:
            for lam_m in cfg.kl_mesh_paper:
                r.staged("kl", d_i, d_m, kl_weight_from_paper(lam_i, n_pixels), kl_weight_from_paper(lam_m, n_coords),
                         lambda_image_paper=lam_i, lambda_mesh_paper=lam_m)
    if "scratch" in only:
        for decoder in ("coma", "lean"):
            r.scratch(decoder)
        d_i, d_m = base.model.image.latent, base.model.mesh.latent
        r.staged("pretrained", d_i, d_m, base.image_vae.kl_weight, base.mesh_vae.kl_weight)
    return r.results
