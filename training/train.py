"""Training of the predictor: image VAE, mesh VAE, then the latent projection with both frozen.

Data flow of :func:`train`::

    config -> data of this rank -> split by contact (80/20) -> scales from the training part
      -> stage "image_vae"    (MSE + lambda_I KL on normalised depth; with ``augmentation``: augmented in, clean out)
      -> stage "mesh_vae"     (MSE + lambda_M KL on normalised displacement)
      -> stage "lean_decoder" (optional: the deployment decoder, MSE from z ~ q(z | mesh), VAEs frozen)
      -> stage "ood_decoder"  (optional: small decoder of the frozen image latent, for ood_score)
      -> stage "projection"   (mesh MSE through the frozen COMA decoder + latent MSE; VAEs frozen;
                               with ``augmentation``: latents of augmented maps)
      -> held-out evaluation of both decoders, OOD calibration
      -> run_dir/model.pt, heldout.npz, metrics.json, history.json (their formats:
         tactile_deploy.training.run_files), learning_curves.png

Every stage uses Adam (``lr``) with the learning rate multiplied by ``lr_decay`` after each epoch,
checkpoints after every epoch (``run_dir/checkpoints/<stage>.pt``) and resumes from there: a
finished stage is skipped when the same run is started again. A run folder trained with other
settings is refused (:func:`check_resume`); ``config.json`` is written once the config is accepted.
"""

from __future__ import annotations

import json
import subprocess
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from tactile_deploy.atomic import atomic_path, write_json, write_npz, write_text
from tactile_deploy.safe_torch import load_torch_file
from tactile_deploy.training import distributed
from tactile_deploy.training.config import StageConfig, TrainConfig
from tactile_deploy.training.data import ContactData, Scales, check_data, compute_scales, load, split_by_contact
from tactile_deploy.training.errors import UsageError
from tactile_deploy.training.networks.coarsening import build_hierarchy
from tactile_deploy.training.networks.image_vae import vae_loss
from tactile_deploy.training.networks.predictor import Predictor

BUNDLE_FORMAT = 1
STAGES = ("image_vae", "mesh_vae", "lean_decoder", "projection", "ood_decoder", "finetune", "surface")
#: Settings that may change when a run is started again: they change neither the data nor any
#: trained weight. A stage's ``epochs`` and ``time_budget_s`` may also change while the stage is
#: not complete, and every setting of a stage not started yet.
RESUME_FREE = ("run_dir", "device", "threads", "eval_max_samples", "data.cache_file", "data.synthetic.envelope_bank")


def git_commit(repo: Path | None = None) -> dict:
    """{'commit': sha or 'unknown', 'dirty': bool} of the repository holding this package; a copy
    of the tree without its git history (a GPU machine's) names its commit in the environment
    variable TRAINING_SOURCE_COMMIT (sha, with a "+dirty" suffix when the copy had changes)."""
    import os

    given = os.environ.get("TRAINING_SOURCE_COMMIT")
    if given:
        sha, _, flag = given.partition("+")
        return {"commit": sha, "dirty": flag == "dirty", "recorded": "TRAINING_SOURCE_COMMIT"}
    repo = repo or Path(__file__).resolve().parents[1]
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True).stdout.strip()
        dirty = bool(
            subprocess.run(
                ["git", "status", "--porcelain", "--", "training"], cwd=repo, capture_output=True, text=True, check=True
            ).stdout.strip()
        )
    except (OSError, subprocess.CalledProcessError):
        return {"commit": "unknown", "dirty": True}
    return {"commit": sha, "dirty": dirty}


def build_model(cfg: TrainConfig) -> Predictor:
    from tactile_deploy.pad.asset import load_pad

    pad = load_pad()
    hierarchy = build_hierarchy(pad, cfg.model.mesh.factors, cfg.model.mesh.pooling)
    model = Predictor(cfg.model, hierarchy, pad.vertices, pad.backplate_nodes)
    # the gel's Poisson ratio of the training data: the lateral physics lift of hybrid exports uses it
    model.nu = cfg.data.synthetic.nu if cfg.data.synthetic is not None else 0.48
    if model.lateral_adds:  # the lift is the decoder's lateral prior, in training and in every export
        from tactile_deploy.training.networks.lift import LateralLift

        model.use_lateral_lift(LateralLift.for_pad(model.nu))
    return model


class _Tensors:
    """The rank's data as normalised tensors on the training device; ``contact`` (N, m) bool, the
    sensing nodes in contact (None when the data do not say)."""

    def __init__(self, data: ContactData, model: Predictor, device: torch.device):
        norm = model.norm
        self.depth = torch.as_tensor(data.depth_mm[:, None]).to(device) / norm.depth_scale_mm.to(device)
        disp = torch.as_tensor(data.displacement_mm).to(device)
        self.disp = norm.to(device).normalise_displacement(disp) * norm.free_mask.to(device)
        self.contact = None if data.contact_mask is None else torch.as_tensor(data.contact_mask).to(device)
        self.n = len(data)


class SurfaceTrainer(torch.nn.Module):
    """The modules the surface stage trains, as one module (for DistributedDataParallel):
    normalised depth (B, 1, R, R) -> (normalised displacement (B, n, 3), image VAE reconstruction,
    mu, logvar). The anchor reads the depth in mm (``x * depth_scale``)."""

    def __init__(self, model: Predictor, ood: bool = False):
        super().__init__()
        self.ood_decoder = model.ood_decoder if ood else None
        self.encoder = model.image_vae.encoder
        self.surface_decoder = model.surface_decoder
        self.image_decoder = model.image_vae.decoder
        self.anchor = model.anchor  # buffers only
        self.register_buffer("depth_scale_mm", model.norm.depth_scale_mm.detach().clone(), persistent=False)
        self.register_buffer("scale_mm", model.norm.displacement_scale_mm.detach().clone(), persistent=False)
        self.moved = model.cfg.surface.anchor == "moved"
        # the lateral physics lift where the decoder is trained on top of it (surface.lateral = "lift_residual")
        self.lateral = model.lateral_lift if model.lateral_adds else None

    def forward(self, x: torch.Tensor, sample: bool):
        from tactile_deploy.training.networks.surface_decoder import compose_surface

        maps, _ = self.encoder.feature_maps(x)
        h = self.encoder.fc(maps[-1])
        mu, logvar = self.encoder.mu(h), self.encoder.logvar(h)
        pred = compose_surface(self.surface_decoder(maps, mu), x * self.depth_scale_mm, self.anchor, self.moved,
                               self.scale_mm, self.lateral, lateral_adds=True)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if sample else mu
        lean = self.ood_decoder(mu) if self.ood_decoder is not None else None
        return pred, self.image_decoder(z), mu, logvar, lean


def surface_step(sets: dict, mask: torch.Tensor, n_plane: int, stage, augmented: Callable | None = None,
                 z_scale_mm: float = 1.0):
    """Step of the surface stage: weighted mesh MSE of the surface-anchored path (every free node 1,
    + ``surface_weight`` on the sensing layer, + ``contact_weight`` on its nodes in contact) +
    ``deepest_weight`` x the deepest node's squared relative depth error (:func:`deepest_node_term`) +
    ``image_weight`` x the image VAE loss (augmented map in, clean map out). Metrics: ``mse`` (of
    normalised displacements, all nodes and axes), ``contact_mse`` (per axis, sensing nodes in
    contact), ``deepest_rel`` (mean squared relative depth error of the deepest node, where the term is on),
    ``image_mse``. ``z_scale_mm``: the displacement scale of the z axis (normalised -> mm)."""

    def step(m, idx, train):
        t = sets[train]
        x = t.depth[idx]
        pred, recon, mu, logvar, lean = m(augmented(x) if train and augmented is not None else x, train)
        err2 = ((pred - t.disp[idx]) ** 2 * mask).sum(-1)  # (B, n)
        w = torch.ones_like(err2)
        w[:, :n_plane] += stage.surface_weight
        contact = t.contact[idx] if t.contact is not None else None
        if contact is not None:
            w[:, :n_plane] += stage.contact_weight * contact
        mse = err2.mean() / 3
        loss = (w * err2).mean() / 3
        metrics = {"mse": mse.detach()}
        if stage.deepest_weight > 0:
            rel2 = deepest_node_term(pred, t.disp[idx], n_plane, stage.deepest_floor_mm / z_scale_mm)
            loss = loss + stage.deepest_weight * rel2
            metrics["deepest_rel"] = rel2.detach()
        if contact is not None:
            metrics["contact_mse"] = ((err2[:, :n_plane] * contact).sum() / contact.sum().clamp(min=1) / 3).detach()
        if stage.image_weight > 0:
            image_loss, image_terms = vae_loss(x, recon, mu, logvar, stage.kl_weight)
            loss = loss + stage.image_weight * image_loss
            metrics["image_mse"] = image_terms["mse"]
            if lean is not None:
                lean_mse = torch.mean((lean - x) ** 2)
                loss = loss + stage.image_weight * lean_mse
                metrics["ood_image_mse"] = lean_mse.detach()
        metrics["loss"] = loss.detach()
        return loss, metrics

    return step


def deepest_node_term(pred: torch.Tensor, true: torch.Tensor, n_plane: int, floor: float) -> torch.Tensor:
    """Mean over the batch of ((d_pred - d) / max(d, floor))^2 at each contact's deepest sensing node.

    pred, true : (B, n, 3) displacements (z out of the gel; any one scale for both), sensing layer first
    (n_plane nodes); d = -true z of the node with the largest -true z, d_pred = -pred z there; floor in
    the same units. The evaluation's deepest-node error (training/metrics.py) as a fraction, squared."""
    depth = -true[:, :n_plane, 2]
    k = depth.argmax(dim=1)
    rows = torch.arange(len(k), device=k.device)
    d = depth[rows, k]
    d_pred = -pred[rows, k, 2]
    return (((d_pred - d) / d.clamp(min=floor)) ** 2).mean()


def _batches(n: int, batch: int, rng: np.random.Generator | None, n_batches: int | None = None):
    order = rng.permutation(n) if rng is not None else np.arange(n)
    chunks = [order[i : i + batch] for i in range(0, n, batch)]
    return chunks if n_batches is None else chunks[:n_batches]


def run_stage(
    name: str,
    module: torch.nn.Module,
    step: Callable[[torch.nn.Module, np.ndarray, bool], tuple[torch.Tensor, dict]],
    n_train: int,
    n_val: int,
    stage: StageConfig,
    run_dir: Path,
    dist: distributed.Dist,
    device: torch.device,
    seed: int,
    log: Callable[[str], None],
    rmse_scale_mm: float,
    parameters: list[torch.nn.Parameter] | None = None,
) -> list[dict]:
    """Train ``module`` with ``step(module, batch_indices, train) -> (loss, metrics)``; return history.

    ``metrics`` holds detached 0-d tensors (at least ``loss`` and ``mse``, the MSE of normalised
    values), summed on the device and read once per epoch; ``rmse_mm = sqrt(mse) * rmse_scale_mm``.
    ``parameters``: what the optimiser updates (default: the module's trainable parameters).
    """
    ckpt = run_dir / "checkpoints" / f"{name}.pt"
    wrapped = distributed.wrap(module, dist, device)
    params = parameters if parameters is not None else [p for p in module.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=stage.lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=stage.lr_decay)
    history: list[dict] = []
    start = 0
    if ckpt.exists():
        state = load_torch_file(ckpt, map_location=device)
        module.load_state_dict(state["module"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        history, start = state["history"], state["epoch"]
        if start >= stage.epochs or state.get("stopped_by_time_budget", False):
            log(f"[{name}] complete in {ckpt}, skipped")
            return history
        log(f"[{name}] resuming after epoch {start}")
    n_batches = distributed.reduce_min(-(-n_train // stage.batch_size), dist, device)
    n_val_batches = distributed.reduce_min(-(-n_val // stage.batch_size), dist, device)
    t_stage = time.perf_counter()

    def _accumulate(sums: dict, metrics: dict, weight: int) -> None:
        for k, v in metrics.items():
            sums[k] = sums.get(k, 0.0) + torch.as_tensor(v, dtype=torch.float64, device=device) * weight

    for epoch in range(start, stage.epochs):
        t0 = time.perf_counter()
        module.train()
        rng = np.random.default_rng([seed, dist.rank, STAGES.index(name), epoch])
        sums: dict[str, torch.Tensor] = {}
        count = 0
        for idx in _batches(n_train, stage.batch_size, rng, n_batches):
            loss, metrics = step(wrapped, idx, True)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            _accumulate(sums, metrics, len(idx))
            count += len(idx)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        train_seconds = time.perf_counter() - t0
        module.eval()
        vsums: dict[str, torch.Tensor] = {}
        vcount = 0
        with torch.no_grad():
            for idx in _batches(n_val, stage.batch_size, None, n_val_batches):
                _, metrics = step(wrapped, idx, False)
                _accumulate(vsums, metrics, len(idx))
                vcount += len(idx)
        keys = sorted(sums)
        tot = distributed.reduce_sum(np.array([float(sums[k]) for k in keys] + [count]), dist, device)
        vtot = distributed.reduce_sum(np.array([float(vsums[k]) for k in keys] + [vcount]), dist, device)
        rec = {"epoch": epoch + 1, "lr": opt.param_groups[0]["lr"], "seconds": time.perf_counter() - t0}
        rec.update({f"train_{k}": tot[i] / tot[-1] for i, k in enumerate(keys)})
        rec.update({f"val_{k}": vtot[i] / max(vtot[-1], 1) for i, k in enumerate(keys)})
        for part in ("train", "val"):
            rec[f"{part}_rmse_mm"] = float(np.sqrt(max(rec[f"{part}_mse"], 0.0))) * rmse_scale_mm
            if f"{part}_contact_mse" in rec:  # per-node Euclidean RMS over the contact patch (training/metrics.py)
                rec[f"{part}_contact_patch_rmse_um"] = float(np.sqrt(max(3 * rec[f"{part}_contact_mse"], 0.0))) * rmse_scale_mm * 1e3
        elapsed = time.perf_counter() - t_stage
        rec["stage_seconds"] = elapsed
        rec["train_seconds"] = train_seconds
        # training samples of all ranks per second of this rank's training loop (validation excluded)
        rec["samples_per_s"] = float(tot[-1]) / train_seconds if train_seconds > 0 else None
        history.append(rec)
        sched.step()
        # stop when one more epoch like the last would end past the budget
        over_budget = stage.time_budget_s is not None and elapsed + rec["seconds"] > stage.time_budget_s
        log(
            f"[{name}] epoch {epoch + 1}/{stage.epochs} train loss {rec['train_loss']:.4g} "
            f"val loss {rec['val_loss']:.4g} val RMSE {rec['val_rmse_mm'] * 1e3:.2f} um"
            + (f", contact patch {rec['val_contact_patch_rmse_um']:.1f} um" if "val_contact_patch_rmse_um" in rec else "")
            + f" ({rec['seconds']:.1f} s, {rec['samples_per_s']:.0f} samples/s)"
            + (f"; time budget of {stage.time_budget_s:g} s reached" if over_budget else "")
        )
        if dist.is_main:
            ckpt.parent.mkdir(parents=True, exist_ok=True)
            state = {
                "module": module.state_dict(), "optimizer": opt.state_dict(),
                "scheduler": sched.state_dict(), "history": history, "epoch": epoch + 1,
                "stopped_by_time_budget": over_budget,
            }
            with atomic_path(ckpt) as tmp:
                torch.save(state, tmp)
        if distributed.reduce_sum(np.array([float(over_budget)]), dist, device)[0] > 0:  # all ranks stop together
            break
    return history


def prepare_data(cfg: TrainConfig, model: Predictor, dist: distributed.Dist, device: torch.device,
                 log: Callable[[str], None]) -> tuple[ContactData, ContactData, Scales]:
    """This rank's data split by contact, and the data scales (set on ``model``, same on every rank)."""
    t0 = time.perf_counter()
    data = load(cfg.data, dist.rank, dist.world, device)
    log(f"data: {len(data)} samples from {data.source} ({time.perf_counter() - t0:.1f} s)")
    tr_idx, va_idx = split_by_contact(data.contact_id, cfg.data.val_fraction, cfg.data.split_seed)
    train_data, val_data = data.subset(tr_idx), data.subset(va_idx)
    del data  # the split holds copies; free the host memory of the full set
    scales = compute_scales(train_data, model.norm.free_mask.cpu().numpy()[:, 0])
    if dist.active:  # every rank uses the same scales
        s = distributed.reduce_sum(np.array([scales.depth_scale_mm, *scales.displacement_scale_mm]), dist, device) / dist.world
        scales = type(scales)(float(s[0]), tuple(float(v) for v in s[1:]))
    model.norm.set_scales(scales.depth_scale_mm, scales.displacement_scale_mm)
    return train_data, val_data, scales


def image_vae_step(sets: dict, kl_weight: float, augmented: Callable | None = None):
    """Step of the image VAE stage on ``sets`` ({True: training, False: held-out} :class:`_Tensors`);
    with ``augmented`` (normalised depth -> augmented copy) a denoising VAE: augmented in, clean out."""

    def step(m, idx, train):
        x = sets[train].depth[idx]
        recon, mu, logvar = m(augmented(x) if train and augmented is not None else x, sample=train)
        return vae_loss(x, recon, mu, logvar, kl_weight)

    return step


def mesh_vae_step(sets: dict, mask: torch.Tensor, kl_weight: float):
    """Step of the mesh VAE stage (normalised displacements; backplate nodes masked)."""

    def step(m, idx, train):
        x = sets[train].disp[idx]
        recon, mu, logvar = m(x, sample=train)
        return vae_loss(x, recon * mask, mu, logvar, kl_weight)

    return step


def image_latents(sets: dict, encoder: torch.nn.Module | None = None, augmented: Callable | None = None):
    """``latents(idx, train)`` -> image latent means (B, L): the cached ones, or with ``augmented``
    those of augmented training maps through the frozen ``encoder``."""

    def latents(idx, train):
        t = sets[train]
        if train and augmented is not None:
            with torch.no_grad():
                return encoder(augmented(t.depth[idx]))[0]
        return t.z_image[idx]

    return latents


def projection_step(sets: dict, decoder: torch.nn.Module, mask: torch.Tensor, latent_weight: float,
                    latents: Callable | None = None):
    """Step of the projection stage: mesh MSE through the frozen ``decoder`` + latent MSE
    (image latents from ``latents``, default the cached clean ones)."""
    latents = latents or image_latents(sets)

    def step(m, idx, train):
        t = sets[train]
        z = m(latents(idx, train))
        mse = torch.mean((decoder(z) * mask - t.disp[idx]) ** 2)
        lat = torch.mean((z - t.z_mesh[idx]) ** 2)
        loss = mse + latent_weight * lat
        return loss, {"loss": loss.detach(), "mse": mse.detach(), "latent_mse": lat.detach()}

    return step


@torch.no_grad()
def encode_latents(model: Predictor, tensors, mesh: bool = True) -> None:
    """Cache the frozen encoders' latents on each :class:`_Tensors`: z_image, and with ``mesh``
    z_mesh, z_mesh_logvar."""
    for t in tensors:
        t.z_image = torch.cat([model.image_vae.encoder(t.depth[i])[0] for i in _batches(t.n, 256, None)])
        if not mesh:
            continue
        enc = [model.mesh_vae.encoder(t.disp[i]) for i in _batches(t.n, 256, None)]
        t.z_mesh = torch.cat([e[0] for e in enc])
        t.z_mesh_logvar = torch.cat([e[1] for e in enc])


def _differences(old, new, prefix: str = ""):
    """(dotted key, old value, new value) of every difference of two JSON documents (a section
    present on one side only is one difference)."""
    if isinstance(old, dict) and isinstance(new, dict):
        for k in list(old) + [k for k in new if k not in old]:
            yield from _differences(old.get(k), new.get(k), f"{prefix}.{k}" if prefix else k)
    elif old != new:
        yield prefix, old, new


def _stage_progress(run_dir: Path) -> dict[str, tuple[int, bool]]:
    """{stage: (epochs run, stopped by its time budget)} of the stages with a checkpoint in ``run_dir``."""
    out = {}
    for name in STAGES:
        ckpt = run_dir / "checkpoints" / f"{name}.pt"
        if ckpt.is_file():
            state = load_torch_file(ckpt, map_location="cpu")
            out[name] = (int(state["epoch"]), bool(state.get("stopped_by_time_budget", False)))
    return out


def check_resume(cfg: TrainConfig, run_dir: Path) -> None:
    """Refuse to start ``cfg`` in a run folder trained with other settings (:class:`UsageError`
    naming each differing field): a run resumes only with the same model, data and seed and the
    same settings of every stage already started, but ``epochs`` and ``time_budget_s`` of a stage
    not complete (never fewer epochs than it has run); :data:`RESUME_FREE` may always change."""
    from pydantic import ValidationError

    from tactile_deploy.jsonfile import read_json, validation_error_text

    if run_dir.exists() and not run_dir.is_dir():
        raise UsageError(f"run_dir {run_dir} is a file, not a folder: choose another run_dir")
    progress = _stage_progress(run_dir)
    trained = bool(progress) or (run_dir / "model.pt").exists()
    saved_path = run_dir / "config.json"
    way_out = f"choose another run_dir, or delete {run_dir} to train from scratch"
    if not saved_path.is_file():
        if trained:
            raise UsageError(f"run_dir {run_dir} holds trained weights but no config.json, so it cannot be "
                             f"resumed: {way_out}")
        return
    if not trained:  # nothing was trained yet: any setting may change
        return
    doc = read_json(saved_path, UsageError, "the run's saved training config")
    try:
        saved = TrainConfig.model_validate(doc)
    except ValidationError as e:
        raise UsageError(validation_error_text(saved_path, e, "saved training config",
                                               f"the run cannot be resumed: {way_out}")) from None
    problems = []
    for key, was_value, value in _differences(saved.model_dump(mode="json"), cfg.model_dump(mode="json")):
        if key in RESUME_FREE:
            continue
        top, _, field = key.partition(".")
        was = f"run {json.dumps(was_value)}, config {json.dumps(value)}"
        if top in STAGES:
            if top not in progress:
                continue  # the stage has not started: its settings are free
            run, stopped = progress[top]
            stage = getattr(saved, top)
            complete = stopped or (stage is not None and run >= stage.epochs)
            if field in ("epochs", "time_budget_s") and not complete:
                if field == "epochs" and value < run:
                    problems.append(f"{key}: {was}, but {run} epochs have run")
                continue
            state = "complete" if complete else f"started ({run} epochs run)"
            problems.append(f"{key}: {was} (stage {top} is {state})")
        else:
            problems.append(f"{key}: {was}")
    if problems:
        raise UsageError(
            f"run_dir {run_dir} holds a run trained with other settings ({saved_path}): " + "; ".join(problems)
            + f". A run resumes only with the same model, data and seed and the same settings of its started "
            f"stages (epochs and time_budget_s of an unfinished stage may change): {way_out}"
        )


def _remove_partials(run_dir: Path) -> None:
    """Delete temporary files an interrupted write left in ``run_dir`` (never read)."""
    for pattern in (".*.partial*", "checkpoints/.*.partial*", "checkpoints/*.partial"):
        for p in run_dir.glob(pattern):
            if p.is_file():
                p.unlink(missing_ok=True)


def _freeze(module: torch.nn.Module) -> None:
    module.eval()
    for p in module.parameters():
        p.requires_grad_(False)


def train(cfg: TrainConfig, log: Callable[[str], None] = print) -> dict:
    """Run all stages of ``cfg``; returns the metrics (also written to ``run_dir/metrics.json``)."""
    dist, device = distributed.init(cfg.device)
    if not dist.is_main:
        log = lambda message: None  # noqa: E731 - rank 0 reports for all
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    if device.type == "cuda":  # TF32 matrix units: ~3e-4 relative rounding, far below the training noise
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    run_dir = Path(cfg.run_dir)
    check_resume(cfg, run_dir)
    check_data(cfg.data, dist.rank, dist.world)
    if cfg.init_weights is not None and not Path(cfg.init_weights).is_file():  # before minutes of data
        raise UsageError(f"init_weights: {cfg.init_weights} is not a file; give a training bundle (model.pt) or "
                         "set init_weights to null")
    if dist.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        _remove_partials(run_dir)
        write_text(run_dir / "config.json", json.dumps(cfg.model_dump(mode="json"), indent=2))
    torch.manual_seed(cfg.seed)
    model = build_model(cfg)

    train_data, val_data, scales = prepare_data(cfg, model, dist, device, log)
    if cfg.init_weights is not None:
        scales = start_from(model, cfg, log)
    model.to(device)
    tr, va = _Tensors(train_data, model, device), _Tensors(val_data, model, device)
    sets = {True: tr, False: va}
    scale_mm = float(scales.displacement_scale_mm[0])
    mask = model.norm.free_mask
    augmented = _augmentation(cfg, model, device, dist.rank)

    # -- stage 1: image VAE ------------------------------------------------------------------
    hist = {}
    if cfg.image_vae is not None:
        hist["image_vae"] = run_stage(
            "image_vae", model.image_vae, image_vae_step(sets, cfg.image_vae.kl_weight, augmented), tr.n, va.n,
            cfg.image_vae, run_dir, dist, device, cfg.seed, log, scales.depth_scale_mm,
        )

    # -- stage 1b (optional): image encoder + surface-anchored decoder end to end ------------
    if cfg.surface is not None:
        if tr.contact is None and cfg.surface.contact_weight > 0:
            log("[surface] the data carry no contact masks: contact_weight is not applied")
        trainer = SurfaceTrainer(model, ood=cfg.surface.train_ood_decoder and cfg.surface.image_weight > 0)
        if not cfg.surface.train_encoder:
            for p in model.image_vae.encoder.parameters():
                p.requires_grad_(False)
        if cfg.surface.image_weight == 0:  # the VAE's own heads are then unused
            for p in [*model.image_vae.decoder.parameters(), *model.image_vae.encoder.logvar.parameters()]:
                p.requires_grad_(False)
        hist["surface"] = run_stage(
            "surface", trainer, surface_step(sets, mask, model.anchor.m, cfg.surface, augmented,
                                             float(model.norm.displacement_scale_mm[2])), tr.n, va.n,
            cfg.surface, run_dir, dist, device, cfg.seed, log, scale_mm,
        )
        _freeze(model.surface_decoder)

    # -- stage 2: mesh VAE -------------------------------------------------------------------
    _freeze(model.image_vae)
    if cfg.mesh_vae is not None:
        model.image_vae.train(False)
        hist["mesh_vae"] = run_stage(
            "mesh_vae", model.mesh_vae, mesh_vae_step(sets, mask, cfg.mesh_vae.kl_weight), tr.n, va.n, cfg.mesh_vae,
            run_dir, dist, device, cfg.seed, log, scale_mm,
        )

    # -- VAEs frozen from here on ----------------------------------------------------------
    _freeze(model.mesh_vae)
    encode_latents(model, sets.values(), mesh=cfg.mesh_vae is not None)

    # -- stage 3 (optional): lean deployment decoder on the same latent space ---------------
    s4 = cfg.lean_decoder
    if s4 is not None:

        def lean_step(m, idx, train):
            t = sets[train]
            z = t.z_mesh[idx]
            if train:  # the mesh VAE decoder's training distribution: z ~ q(z | mesh)
                z = z + torch.randn_like(z) * torch.exp(0.5 * t.z_mesh_logvar[idx])
            mse = torch.mean((m(z) * mask - t.disp[idx]) ** 2)
            return mse, {"loss": mse.detach(), "mse": mse.detach()}

        hist["lean_decoder"] = run_stage(
            "lean_decoder", model.lean_decoder, lean_step, tr.n, va.n, s4, run_dir, dist, device, cfg.seed, log,
            scale_mm,
        )
        _freeze(model.lean_decoder)

    # -- stage 3b (optional): lean image decoder for the deployed ood_score ------------------
    s5 = cfg.ood_decoder
    if s5 is not None:
        for t in (tr, va):
            with torch.no_grad():
                t.z_image_logvar = torch.cat([model.image_vae.encoder(t.depth[i])[1] for i in _batches(t.n, 256, None)])

        def ood_step(m, idx, train):
            t = sets[train]
            z = t.z_image[idx]
            if train:
                z = z + torch.randn_like(z) * torch.exp(0.5 * t.z_image_logvar[idx])
            mse = torch.mean((m(z) - t.depth[idx]) ** 2)
            return mse, {"loss": mse.detach(), "mse": mse.detach()}

        hist["ood_decoder"] = run_stage(
            "ood_decoder", model.ood_decoder, ood_step, tr.n, va.n, s5, run_dir, dist, device, cfg.seed, log,
            scales.depth_scale_mm,
        )
        _freeze(model.ood_decoder)

    # -- stage 4: latent projection through the frozen mesh decoder -------------------------
    latents = image_latents(sets, model.image_vae.encoder, augmented)
    if cfg.projection is not None:
        hist["projection"] = run_stage(
            "projection", model.projection,
            projection_step(sets, model.mesh_vae.decoder, mask, cfg.projection.latent_weight, latents),
            tr.n, va.n, cfg.projection, run_dir, dist, device, cfg.seed, log, scale_mm,
        )

    # -- evaluation, OOD calibration ---------------------------------------------------------
    model.eval()
    decoders = (("coma", "lean") if s4 is not None else ("coma",)) if cfg.projection is not None else ()
    if cfg.surface is not None:
        decoders = decoders + ("surface",)
    n_eval = len(val_data) if cfg.eval_max_samples is None else min(len(val_data), cfg.eval_max_samples)
    val_eval = val_data.subset(np.arange(n_eval))
    train_probe = train_data.subset(np.arange(min(len(train_data), n_eval)))
    metrics = {"decoders": {}}
    for name in decoders:
        model.deploy_decoder = name
        metrics["decoders"][name] = {
            "heldout": evaluate(model, val_eval, device),
            "train": evaluate(model, train_probe, device),
        }

    # -- stage 5 (optional): projection + lean decoder end to end, image encoder frozen -------
    s6 = cfg.finetune
    if s6 is not None:
        joint = torch.nn.Sequential(model.projection, model.lean_decoder)  # z_I -> normalised displacement
        for p in joint.parameters():
            p.requires_grad_(True)

        def finetune_step(m, idx, train):
            t = sets[train]
            pred = m(latents(idx, train)) * mask
            mse = torch.mean((pred - t.disp[idx]) ** 2)
            return mse, {"loss": mse.detach(), "mse": mse.detach()}

        hist["finetune"] = run_stage(
            "finetune", joint, finetune_step, tr.n, va.n, s6, run_dir, dist, device, cfg.seed, log, scale_mm
        )
        _freeze(joint)
        model.eval()
        # the COMA figures above are those of the staged (paper) path; the projection is now tuned
        # for the lean decoder, so the deployed lean path is evaluated again
        metrics["decoders"]["coma"]["note"] = "staged path, before finetune (the projection was then tuned for the lean decoder)"
        metrics["decoders"]["lean_staged"] = metrics["decoders"]["lean"]
        model.deploy_decoder = "lean"
        metrics["decoders"]["lean"] = {
            "heldout": evaluate(model, val_eval, device),
            "train": evaluate(model, train_probe, device),
            "note": "after finetune (projection + lean decoder end to end)",
        }
    model.deploy_decoder = "surface" if cfg.surface is not None else "coma"
    metrics.update(metrics["decoders"][model.deploy_decoder]["heldout"])
    metrics["scales"] = asdict(scales)
    metrics["data"] = {"train": train_data.summary(), "val": val_data.summary()}
    log(
        f"held-out: vertex RMSE {metrics['vertex_rmse_mm']:.4f} mm, relative error "
        f"{metrics['relative_error']:.3f}, max error {metrics['max_error_mm']:.3f} mm"
    )
    if dist.is_main:
        bundle = {
            "format_version": BUNDLE_FORMAT,
            "config": cfg.model_dump(mode="json"),
            "state_dict": {k: v.cpu() for k, v in model.state_dict().items()},
            "mesh_hash": model.mesh_vae.graphs.hierarchy.mesh_hash,
            "metrics": metrics,
            "history": hist,
            "git": git_commit(),
            "created_unix": time.time(),
        }
        with atomic_path(run_dir / "model.pt") as tmp:
            torch.save(bundle, tmp)
        n_keep = min(len(val_data), 512)
        write_npz(
            run_dir / "heldout.npz", depth_mm=val_data.depth_mm[:n_keep],
            displacement_mm=val_data.displacement_mm[:n_keep], indenter=val_data.indenter[:n_keep],
            **({} if val_data.contact_mask is None else {"contact_mask": val_data.contact_mask[:n_keep]}),
        )
        from tactile_deploy.training.run_files import training_history, training_metrics

        write_json(run_dir / "metrics.json", training_metrics(metrics).model_dump(mode="json", exclude_unset=True))
        write_text(run_dir / "history.json", training_history(hist).model_dump_json(indent=1, exclude_unset=True) + "\n")
        plot_curves(hist, run_dir / "learning_curves.png")
    distributed.barrier(dist)
    return metrics


def _augmentation(cfg: TrainConfig, model: Predictor, device: torch.device, rank: int):
    """x (B, 1, R, R) normalised depth -> augmented copy; None without ``cfg.augmentation``."""
    if cfg.augmentation is None:
        return None
    from tactile_deploy.training.augment import Augmenter

    aug = Augmenter(cfg.augmentation, cfg.model.image.resolution, device=device)
    generator = torch.Generator(device=device).manual_seed(cfg.seed * 1000 + rank + 1)
    scale = model.norm.depth_scale_mm.to(device)
    return lambda x: aug(x * scale, generator) / scale


@torch.no_grad()
def evaluate(model: Predictor, data: ContactData, device: torch.device, batch: int = 256) -> dict:
    """Held-out figures (of this rank's held-out contacts in a distributed run) of the image-to-mesh path (mm, sensor frame) and the OOD calibration.

    vertex_rmse_mm: RMS over samples, nodes and axes of predicted - true vertex positions (the
    paper's metric); relative_error: ||pred - true|| / ||true|| of the displacements over the set;
    mesh_reconstruction_*: the same for the mesh VAE alone (true mesh -> latent mean -> decoder),
    the floor the image-to-mesh path can reach with this decoder.
    ood / ood_lean: quantiles of the reconstruction RMSE (mm) on these in-distribution maps, by
    the image VAE's decoder / the lean image decoder (the deployed ood_score).
    """
    from tactile_deploy.training.metrics import mesh_metrics

    model.eval()
    err2 = true2 = rec_err2 = 0.0
    max_err = 0.0
    recon, recon_lean, preds = [], [], []
    n = 0
    coma_trained = model.deploy_decoder in ("coma", "lean")
    for i in range(0, len(data), batch):
        depth = torch.as_tensor(data.depth_mm[i : i + batch, None]).to(device)
        true = torch.as_tensor(data.displacement_mm[i : i + batch]).to(device)
        _, disp = model(depth)
        preds.append(disp.cpu().numpy())
        e = (disp - true).double()
        if coma_trained:
            z_true = model.mesh_vae.encoder(model.norm.normalise_displacement(true))[0]
            er = (model.decode_displacement(z_true) - true).double()
            rec_err2 = rec_err2 + float((er**2).sum())
        err2 += float((e**2).sum())
        true2 += float((true.double() ** 2).sum())
        max_err = max(max_err, float(e.norm(dim=-1).max()))
        recon.append(model.image_reconstruction_rmse(depth).cpu().numpy())
        recon_lean.append(model.image_reconstruction_rmse(depth, "lean").cpu().numpy())
        n += e.numel()
    rec = np.concatenate(recon)
    rec_lean = np.concatenate(recon_lean)
    n_plane = model.n_plane
    out = {
        "n_samples": len(data),
        "vertex_rmse_mm": float(np.sqrt(err2 / n)),
        "relative_error": float(np.sqrt(err2 / true2)),
        "max_error_mm": max_err,
        "mesh_metrics": mesh_metrics(np.concatenate(preds), data.displacement_mm, data.contact_mask, n_plane),
        "ood": {
            "recon_rmse_mm_p50": float(np.quantile(rec, 0.5)),
            "recon_rmse_mm_p95": float(np.quantile(rec, 0.95)),
            "recon_rmse_mm_p99": float(np.quantile(rec, 0.99)),
            "recon_rmse_mm_max": float(rec.max()),
        },
        "ood_lean": {
            "recon_rmse_mm_p50": float(np.quantile(rec_lean, 0.5)),
            "recon_rmse_mm_p95": float(np.quantile(rec_lean, 0.95)),
            "recon_rmse_mm_p99": float(np.quantile(rec_lean, 0.99)),
            "recon_rmse_mm_max": float(rec_lean.max()),
        },
    } | ({
        "mesh_reconstruction_rmse_mm": float(np.sqrt(rec_err2 / n)),
        "mesh_reconstruction_relative_error": float(np.sqrt(rec_err2 / true2)),
    } if coma_trained else {})
    return out


def plot_curves(history: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(history), figsize=(4.2 * len(history), 3.4))
    for ax, (name, hist) in zip(np.atleast_1d(axes), history.items()):
        if not hist:
            continue
        ep = [h["epoch"] for h in hist]
        ax.semilogy(ep, [h["train_rmse_mm"] for h in hist], label="train")
        ax.semilogy(ep, [h["val_rmse_mm"] for h in hist], label="held-out")
        ax.set_title(name)
        ax.set_xlabel("epoch")
        ax.set_ylabel("RMSE, mm" + (" (depth)" if name in ("image_vae", "ood_decoder") else " (displacement)"))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def start_from(model: Predictor, cfg: TrainConfig, log: Callable[[str], None]):
    """Load ``cfg.init_weights`` into ``model`` (weights and the data scales, which replace the
    ones just computed from this run's data); returns those scales. The bundle's model settings must
    be this run's."""
    start, bundle = load_bundle(cfg.init_weights)
    theirs = TrainConfig.model_validate(bundle["config"]).model.model_dump(mode="json")
    if theirs != cfg.model.model_dump(mode="json"):
        raise UsageError(f"init_weights {cfg.init_weights}: trained with model settings {theirs}, this run has "
                         f"{cfg.model.model_dump(mode='json')}; start from a bundle of the same model")
    model.load_state_dict(start.state_dict())
    scales = Scales(float(model.norm.depth_scale_mm), tuple(float(v) for v in model.norm.displacement_scale_mm))
    log(f"weights and data scales from {cfg.init_weights} (depth scale {scales.depth_scale_mm:.4f} mm)")
    return scales


def load_bundle(path: str | Path, device: str = "cpu") -> tuple[Predictor, dict]:
    """Rebuild the trained predictor from ``model.pt`` (checks the pad mesh hash)."""
    if not Path(path).is_file():
        raise UsageError(f"training bundle {path} not found; train a run first (python -m tactile_deploy.training train "
                         "--config CONFIG.json) or give its model.pt")
    try:
        bundle = load_torch_file(path, map_location=device)
    except Exception as e:  # torch raises several types for damaged or foreign files
        raise UsageError(f"{path}: not a training bundle (torch cannot read it: {type(e).__name__}: {e}); give "
                         "the model.pt of a training run") from None
    if not isinstance(bundle, dict) or bundle.get("format_version") != BUNDLE_FORMAT:
        got = bundle.get("format_version") if isinstance(bundle, dict) else type(bundle).__name__
        raise UsageError(f"{path}: bundle format {got} is not {BUNDLE_FORMAT}; give the model.pt of a training "
                         "run of this version")
    cfg = TrainConfig.model_validate(bundle["config"])
    model = build_model(cfg)
    if model.mesh_vae.graphs.hierarchy.mesh_hash != bundle["mesh_hash"]:
        raise UsageError(
            f"{path} was trained on pad mesh {bundle['mesh_hash'][:12]}..., the shipped pad is "
            f"{model.mesh_vae.graphs.hierarchy.mesh_hash[:12]}...; retrain for this pad"
        )
    state = bundle["state_dict"]
    if "slim" in bundle:  # weights of the trained modules only, maybe in a narrower float type
        state = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
        missing, unexpected = model.load_state_dict(state, strict=False)
        kept = trained_prefixes(cfg)
        wrong = [k for k in missing if k.startswith(kept)] + list(unexpected)
        if wrong:
            raise UsageError(f"{path}: a slim bundle that does not match its config ({len(wrong)} tensors missing or "
                             f"unexpected, e.g. {wrong[0]}); make it again (python -m tactile_deploy.training slim-bundle)")
    else:
        model.load_state_dict(state)
    model.eval()
    return model, bundle


def trained_prefixes(cfg: TrainConfig) -> tuple[str, ...]:
    """State-dict prefixes of the modules ``cfg`` trains (and the data scales, ``norm.``)."""
    out = ["norm.", "image_vae."]
    if cfg.surface is not None:
        out.append("surface_decoder.")
    if cfg.ood_decoder is not None:
        out.append("ood_decoder.")
    if cfg.mesh_vae is not None:
        out.append("mesh_vae.")
    if cfg.lean_decoder is not None:
        out.append("lean_decoder.")
    if cfg.projection is not None:
        out.append("projection.")
    return tuple(out)


def slim_bundle(src: str | Path, out: str | Path, dtype: str = "float16") -> dict:
    """Write the bundle ``src`` keeping only the weights of the modules its config trains, those
    (not the data scales and rest mesh, ``norm.``) stored as ``dtype``; returns its summary. A model
    loaded from it computes with the rounded weights in float32: export from it, so that graph and
    bundle agree."""
    if dtype not in ("float16", "float32"):
        raise UsageError(f"--dtype must be float16 or float32, got {dtype!r}")
    model, bundle = load_bundle(src)
    cfg = TrainConfig.model_validate(bundle["config"])
    keep = trained_prefixes(cfg)
    torch_dtype = getattr(torch, dtype)
    state = {k: (v.to(torch_dtype) if v.is_floating_point() and not k.startswith("norm.") else v).clone()
             for k, v in model.state_dict().items() if k.startswith(keep)}
    import hashlib

    slim = dict(bundle)
    slim["state_dict"] = state
    slim["slim"] = {"dtype": dtype, "modules": list(keep),
                    "source_sha256": hashlib.sha256(Path(src).read_bytes()).hexdigest()}
    with atomic_path(Path(out)) as tmp:
        torch.save(slim, tmp)
    n = sum(v.numel() for v in state.values())
    return {"tensors": len(state), "numbers": int(n), "bytes": Path(out).stat().st_size, "dtype": dtype}
