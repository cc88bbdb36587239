"""The augmented twin of a trained model, for the ablation (docs/adaptation.md, Table 2a).

    python -m tactile_deploy.training.adaptation.augmented_twin --bundle exported/gelslim_mesh.pt \
        --config training/configs/cpu_adapt_aug.json --out out/predictor/shipped_aug \
        [--projection-epochs 4] [--image-epochs 0]

Data flow of :func:`make_twin`::

    bundle (the shipped model) -> Predictor (its scales kept)
      -> [optional] image VAE continued as a denoising VAE: augmented map in, clean map out
      -> projection trained on the image latents of augmented maps, mesh MSE through the frozen
         lean decoder (the deployed path; the shipped recipe's finetune target)
      -> held-out figures on clean and on augmented maps -> run folder: model.pt, heldout.npz,
         config.json, metrics.json (the layout of a training run, so ``training export`` and
         ``export-adapt`` take it)

Training the shipped model again from scratch with augmentation needs the GPU run
(``training/configs/gpu_paper_aug.json``); on a CPU the twin continues the shipped networks on the
data and augmentation of ``--config`` (its ``data`` and ``augmentation`` sections).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from tactile_deploy.training import distributed
from tactile_deploy.training.config import StageConfig, TrainConfig
from tactile_deploy.training.data import load, split_by_contact
from tactile_deploy.training.train import (
    BUNDLE_FORMAT,
    _augmentation,
    _freeze,
    _Tensors,
    encode_latents,
    evaluate,
    git_commit,
    image_latents,
    image_vae_step,
    load_bundle,
    run_stage,
)


def make_twin(bundle_path: Path, cfg: TrainConfig, out: Path, projection: StageConfig,
              image: StageConfig | None = None, n_eval: int = 512, log=print) -> dict:
    """Write the augmented twin's run folder ``out`` (module docstring); returns its metrics."""
    if cfg.augmentation is None:
        raise ValueError("the config has no augmentation section: the twin would equal the model")
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    device = torch.device("cpu")
    dist = distributed.Dist()
    model, source = load_bundle(bundle_path)
    if model.lean_decoder is None:
        raise ValueError(f"{bundle_path} has no lean decoder (the deployed mesh decoder the twin trains for)")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    data = load(cfg.data)
    tr_idx, va_idx = split_by_contact(data.contact_id, cfg.data.val_fraction, cfg.data.split_seed)
    train_data, val_data = data.subset(tr_idx), data.subset(va_idx)
    log(f"data: {len(train_data)} training / {len(val_data)} held-out maps from {data.source} "
        f"({time.perf_counter() - t0:.0f} s); scales of {bundle_path} kept")
    tr, va = _Tensors(train_data, model, device), _Tensors(val_data, model, device)
    sets = {True: tr, False: va}
    augmented = _augmentation(cfg, model, device, 0)
    mask = model.norm.free_mask
    scale_mm = float(model.norm.displacement_scale_mm.reshape(-1)[0])
    for p in model.parameters():
        p.requires_grad_(False)
    hist = {}
    if image is not None:
        for p in model.image_vae.parameters():
            p.requires_grad_(True)
        hist["image_vae"] = run_stage("image_vae", model.image_vae, image_vae_step(sets, cfg.image_vae.kl_weight, augmented),
                                      tr.n, va.n, image, out, dist, device, cfg.seed, log, float(model.norm.depth_scale_mm))
        _freeze(model.image_vae)
    encode_latents(model, sets.values())
    latents = image_latents(sets, model.image_vae.encoder, augmented)
    for p in model.projection.parameters():
        p.requires_grad_(True)
    deployed = torch.nn.Sequential(model.projection, model.lean_decoder)  # lean decoder frozen

    def step(m, idx, train):
        mse = torch.mean((m(latents(idx, train)) * mask - sets[train].disp[idx]) ** 2)
        return mse, {"loss": mse.detach(), "mse": mse.detach()}

    hist["projection"] = run_stage("projection", deployed, step, tr.n, va.n, projection, out, dist, device, cfg.seed,
                                   log, scale_mm, parameters=list(model.projection.parameters()))
    _freeze(model.projection)
    model.eval()
    model.deploy_decoder = "lean"
    k = min(n_eval, len(val_data))
    held = val_data.subset(np.arange(k))
    rng = torch.Generator().manual_seed(12345)
    from tactile_deploy.training.augment import Augmenter

    aug = Augmenter(cfg.augmentation, cfg.model.image.resolution)
    held_aug = type(held)(aug(torch.as_tensor(held.depth_mm[:, None]), rng)[:, 0].numpy(), held.displacement_mm,
                          held.contact_id, held.indenter, held.source + " (augmented)")
    metrics = {"decoders": {"lean": {"heldout": evaluate(model, held, device),
                                     "heldout_augmented": evaluate(model, held_aug, device)}}}
    model.deploy_decoder = "coma"
    metrics.update(metrics["decoders"]["lean"]["heldout"])
    metrics["data"] = {"train": train_data.summary(), "val": val_data.summary()}
    metrics["twin_of"] = {"bundle": str(bundle_path), "metrics": source["metrics"].get("decoders", {}).get("lean")}
    bundle = {
        "format_version": BUNDLE_FORMAT,
        "config": source["config"],
        "state_dict": {k: v.cpu() for k, v in model.state_dict().items()},
        "mesh_hash": source["mesh_hash"],
        "metrics": metrics | {"ood": source["metrics"]["ood"], "ood_lean": source["metrics"]["ood_lean"]},
        "history": hist,
        "git": git_commit(),
        "created_unix": time.time(),
        "twin": {"of": str(bundle_path), "augmentation": cfg.augmentation.model_dump(mode="json"),
                 "data": cfg.data.model_dump(mode="json"),
                 "image_vae": None if image is None else image.model_dump(mode="json"),
                 "projection": projection.model_dump(mode="json")},
    }
    torch.save(bundle, out / "model.pt")
    from tactile_deploy.atomic import write_json, write_npz

    write_npz(out / "heldout.npz", depth_mm=held.depth_mm, displacement_mm=held.displacement_mm, indenter=held.indenter)
    write_json(out / "config.json", cfg.model_dump(mode="json") | {"run_dir": str(out)})
    from tactile_deploy.training.run_files import training_metrics

    write_json(out / "metrics.json", training_metrics(metrics).model_dump(mode="json", exclude_unset=True))
    lean = metrics["decoders"]["lean"]
    log(f"twin: held-out vertex RMSE {lean['heldout']['vertex_rmse_mm'] * 1e3:.1f} um on clean maps, "
        f"{lean['heldout_augmented']['vertex_rmse_mm'] * 1e3:.1f} um on augmented maps "
        f"({time.perf_counter() - t0:.0f} s)")
    return metrics


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tactile_deploy.training.adaptation.augmented_twin", description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, default=Path("exported/gelslim_mesh.pt"))
    ap.add_argument("--config", type=Path, default=Path("training/configs/cpu_adapt_aug.json"),
                    help="its data and augmentation sections are used")
    ap.add_argument("--out", type=Path, default=Path("out/predictor/shipped_aug"))
    ap.add_argument("--projection-epochs", type=int, default=4)
    ap.add_argument("--image-epochs", type=int, default=0, help="denoising image VAE epochs first (0: keep it)")
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--export", action="store_true", help="then export the ONNX model and the adaptation step")
    args = ap.parse_args(argv)
    cfg = TrainConfig.load(args.config)
    proj = StageConfig(epochs=args.projection_epochs, batch_size=32, lr=args.lr, lr_decay=0.9)
    image = StageConfig(epochs=args.image_epochs, batch_size=32, lr=args.lr, lr_decay=0.9,
                        kl_weight=cfg.image_vae.kl_weight) if args.image_epochs > 0 else None
    metrics = make_twin(args.bundle, cfg, args.out, proj, image)
    if args.export:
        from tactile_deploy.training.adaptation.export import export_step
        from tactile_deploy.training.export import export_run

        onnx = args.out / "gelslim_mesh.onnx"
        export_run(args.out, onnx, overwrite=True)  # the run was just trained again in --out
        export_step(args.out / "model.pt", onnx, args.out / "gelslim_mesh_adapt")
    print(json.dumps(metrics["decoders"]["lean"], indent=1, default=float)[:2000])
    return 0


if __name__ == "__main__":
    from tactile_deploy.training.errors import run_command

    raise SystemExit(run_command(main))
