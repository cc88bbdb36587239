"""Train the read-out network of a design and export it (ONNX + model card).

    python -m training.shading_net --design gelslim1 --units 8 --presses 1000 --epochs 60 \
        --out exported/gelslim_readout.onnx

Data flow: :func:`.family.family_configs` (units of the design) -> :func:`.data.unit_presses`
(features and true depth on each unit's imaging grid) -> 48 x 48-cell crops around each contact
(its deepest cell, jittered by up to 8 cells, inside the grid) -> AdamW with a one-cycle
learning rate, loss: mean squared error of the gradients (mm per mm) and of the depth (in
``DEPTH_UNIT_MM``) -> ONNX (opset 17, dynamic batch and grid size) with the feature contract in
its metadata, and a card (``.json`` beside it) with the data, the settings and the final loss.
"""

from __future__ import annotations

import argparse
import hashlib
import platform
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

CROP_CELLS = 48
JITTER_CELLS = 8


def targets(depth_mm: np.ndarray, pitch_mm: float, gradient_clip: float = 1.0) -> np.ndarray:
    """(N, 3, H, W) float32: depth gradients along image columns and rows (mm per mm, clipped
    to +-``gradient_clip``: the walls of flat punches and prisms are near vertical and would
    dominate the loss) and depth in DEPTH_UNIT_MM, of depth maps (N, H, W) mm (rows along -y)."""
    from .network import DEPTH_UNIT_MM

    g_row, g_col = np.gradient(depth_mm, pitch_mm, axis=(1, 2))
    g = np.clip(np.stack([g_col, g_row], 1), -gradient_clip, gradient_clip)
    return np.concatenate([g, (depth_mm / DEPTH_UNIT_MM)[:, None]], 1).astype(np.float32)


def contact_crops(features: np.ndarray, target: np.ndarray, rng: np.random.Generator,
                  size: int = CROP_CELLS) -> tuple[np.ndarray, np.ndarray]:
    """``size`` x ``size`` crops of features (N, C, H, W) and targets (N, K, H, W) around each
    press's deepest cell (the last target channel is the depth)."""
    n, _, h, w = features.shape
    size_h, size_w = min(size, h), min(size, w)
    fx, tx = [], []
    for k in range(n):
        r, c = np.unravel_index(int(np.argmax(target[k, -1])), (h, w))
        r0 = int(np.clip(r - size_h // 2 + rng.integers(-JITTER_CELLS, JITTER_CELLS + 1), 0, h - size_h))
        c0 = int(np.clip(c - size_w // 2 + rng.integers(-JITTER_CELLS, JITTER_CELLS + 1), 0, w - size_w))
        fx.append(features[k, :, r0:r0 + size_h, c0:c0 + size_w])
        tx.append(target[k, :, r0:r0 + size_h, c0:c0 + size_w])
    return np.stack(fx), np.stack(tx)


def train_network(x: np.ndarray, y: np.ndarray, width: int, epochs: int, seed: int,
                  batch: int = 32, lr: float = 2e-3, gradient_weight: float = 1.0, log=print):
    """Train a :class:`.network.ReadoutNet` on crops ``x`` (N, 11, h, w), ``y`` (N, 3, h, w);
    loss: mean squared error, the gradient channels weighted by ``gradient_weight`` against
    the depth's 1; returns (network, per-epoch mean losses)."""
    import torch

    from .network import ReadoutNet

    torch.manual_seed(seed)
    net = ReadoutNet(width)
    opt = torch.optim.AdamW(net.parameters(), lr, weight_decay=1e-4)
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    steps_per_epoch = max(len(xt) // batch, 1)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=epochs * steps_per_epoch)
    weight = torch.tensor([gradient_weight, gradient_weight, 1.0]).view(1, 3, 1, 1)
    losses = []
    t0 = time.perf_counter()
    for epoch in range(epochs):
        perm = torch.randperm(len(xt))
        total = 0.0
        for i in range(steps_per_epoch):
            idx = perm[i * batch:(i + 1) * batch]
            loss = (((net(xt[idx]) - yt[idx]) ** 2) * weight).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
        losses.append(total / steps_per_epoch)
        log(f"epoch {epoch + 1}/{epochs}: loss {losses[-1]:.3g} ({time.perf_counter() - t0:.0f} s)")
    return net.eval(), losses


def export_onnx(net, out: Path, metadata: dict) -> None:
    """Write ``net`` as the deployed graph (:class:`.network.ExportedReadout`) to ``out``
    atomically, with ``metadata`` as ONNX metadata properties."""
    import onnx
    import torch

    from tactile_deploy.atomic import atomic_path

    from .network import ExportedReadout

    graph = ExportedReadout(net).eval()
    example = torch.zeros(1, 11, 64, 90)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        torch.onnx.export(graph, example, str(tmp), input_names=["features"],
                          output_names=["depth_mm", "gradients"], opset_version=17,
                          dynamic_axes={"features": {0: "batch", 2: "rows", 3: "columns"},
                                        "depth_mm": {0: "batch", 1: "rows", 2: "columns"},
                                        "gradients": {0: "batch", 2: "rows", 3: "columns"}},
                          dynamo=False)
        model = onnx.load(str(tmp))
        for key, value in metadata.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = key, str(value)
        onnx.save(model, str(tmp))


def main(argv=None) -> int:
    from tactile_deploy.imaging import learned_readout as lr_mod

    from .data import DEPTH_RANGE_MM, RADII_MM, unit_presses
    from .family import Tolerances, family_configs

    ap = argparse.ArgumentParser(prog="python -m training.shading_net", description=__doc__.splitlines()[0])
    ap.add_argument("--design", default="gelslim1", help="virtual sensor whose design the units share")
    ap.add_argument("--units", type=int, default=8, help="virtual units of the design")
    ap.add_argument("--presses", type=int, default=1000, help="presses per unit")
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--width", type=int, default=8, help="base channels of the U-Net")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="torch threads")
    ap.add_argument("--gradient-clip", type=float, default=1.0,
                    help="gradient targets clipped to +- this (mm per mm)")
    ap.add_argument("--gradient-weight", type=float, default=1.0,
                    help="weight of the gradient channels in the loss (depth: 1)")
    ap.add_argument("--data-cache", type=Path, default=None,
                    help="keep the generated crops in this .npz and reuse them when present")
    ap.add_argument("--out", type=Path, default=Path("exported/gelslim_readout.onnx"))
    args = ap.parse_args(argv)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    rng = np.random.default_rng(args.seed)
    tol = Tolerances()
    if args.data_cache is not None and args.data_cache.is_file():
        with np.load(args.data_cache) as z:
            x_all, depth_crops, pitch = z["features"], z["depth_mm"], float(z["pitch_mm"])
        print(f"crops from {args.data_cache}", flush=True)
    else:
        xs, ds, simulator = [], [], None
        for u, config in enumerate(family_configs(args.design, args.units, rng, tol)):
            presses, simulator = unit_presses(config, args.presses, rng, simulator)
            x, d = contact_crops(presses.features, presses.depth_mm[:, None], rng)
            xs.append(x)
            ds.append(d[:, 0])
            pitch = presses.pitch_mm
            print(f"unit {u + 1}/{args.units}: {args.presses} presses "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
        x_all, depth_crops = np.concatenate(xs), np.concatenate(ds)
        if args.data_cache is not None:
            from tactile_deploy.atomic import write_npz

            write_npz(args.data_cache, features=x_all, depth_mm=depth_crops, pitch_mm=pitch)
    t_data = time.perf_counter() - t0
    net, losses = train_network(x_all, targets(depth_crops, pitch, args.gradient_clip), args.width,
                                args.epochs, args.seed, gradient_weight=args.gradient_weight,
                                log=lambda m: print(m, flush=True))
    metadata = {"readout_format": lr_mod.READOUT_FORMAT, "feature_version": lr_mod.FEATURE_VERSION,
                "colour_scale_grey": repr(lr_mod.COLOUR_SCALE_GREY),
                "position_scale_mm": repr(lr_mod.POSITION_SCALE_MM), "saturation_level": 254,
                "design": args.design}
    export_onnx(net, args.out, metadata)
    import sys

    card = {
        "model": args.out.name,
        "command": "python -m training.shading_net " + " ".join(sys.argv[1:] if argv is None else argv),
        "sha256": hashlib.sha256(args.out.read_bytes()).hexdigest(),
        "what": "learned read-out: rectified camera frame features -> depth (mm) on the imaging grid "
                "(tactile_deploy/imaging/learned_readout.py describes the inputs and outputs)",
        "design": args.design,
        "family": {"units": args.units, "tolerances": asdict(tol),
                   "seed": args.seed},
        "data": {"presses_per_unit": args.presses, "ball_radii_mm": list(RADII_MM),
                 "library_indenters": "half of the presses: every shape of the indenter library, any rotation",
                 "depth_range_mm": list(DEPTH_RANGE_MM), "crop_cells": CROP_CELLS},
        "training": {"width": args.width, "epochs": args.epochs, "batch": 32, "lr": 2e-3,
                     "gradient_clip": args.gradient_clip, "gradient_weight": args.gradient_weight,
                     "loss_first": losses[0], "loss_last": losses[-1],
                     "parameters": int(sum(p.numel() for p in net.parameters()))},
        "metadata": {k: str(v) for k, v in metadata.items()},
        "versions": {"torch": torch.__version__, "python": platform.python_version()},
        "seconds": {"data": round(t_data, 1), "total": round(time.perf_counter() - t0, 1)},
    }
    from tactile_deploy.atomic import write_json

    write_json(args.out.with_suffix(".json"), card)
    print(f"wrote {args.out} and {args.out.with_suffix('.json')}")
    return 0
