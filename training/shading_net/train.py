"""Train the read-out network of a design and export it (ONNX + model card).

    python -m tactile_deploy.training.shading_net --design gelslim1 --units 8 --presses 1000 --epochs 60 \
        --out exported/gelslim_readout.onnx --overwrite

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
import json
import platform
import time
import zipfile
from dataclasses import asdict
from pathlib import Path

import numpy as np

from tactile_deploy.learning.readout_network import export_onnx, targets

CROP_CELLS = 48
JITTER_CELLS = 8


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
    """Train a :class:`tactile_deploy.learning.readout_network.ReadoutNet` on crops ``x`` (N, 11, h, w), ``y`` (N, 3, h, w);
    loss: mean squared error, the gradient channels weighted by ``gradient_weight`` against
    the depth's 1; returns (network, per-epoch mean losses)."""
    import torch

    from tactile_deploy.learning.readout_network import ReadoutNet

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


def _cache_spec(args) -> dict:
    """What the crops of ``--data-cache`` depend on (stored in it, checked when it is reused)."""
    return {"design": args.design, "units": args.units, "presses": args.presses, "seed": args.seed,
            "crop_cells": CROP_CELLS, "jitter_cells": JITTER_CELLS}


def _check_args(args) -> None:
    """Check every option before any work (:class:`tactile_deploy.training.errors.UsageError`)."""
    from tactile_deploy.training.errors import UsageError

    for option, value, low in (("--units", args.units, 1), ("--presses", args.presses, 1), ("--epochs", args.epochs, 1),
                               ("--width", args.width, 1), ("--seed", args.seed, 0)):
        if value < low:
            raise UsageError(f"{option} must be >= {low}, got {value}")
    if args.threads is not None and args.threads < 1:
        raise UsageError(f"--threads must be >= 1, got {args.threads}")
    if not (np.isfinite(args.gradient_clip) and args.gradient_clip > 0):
        raise UsageError(f"--gradient-clip must be a number > 0 (mm per mm), got {args.gradient_clip}")
    if not (np.isfinite(args.gradient_weight) and args.gradient_weight >= 0):
        raise UsageError(f"--gradient-weight must be a number >= 0, got {args.gradient_weight}")
    from tactile_deploy.sensors.catalog import UnknownSensorError, sensor_config
    from tactile_deploy.sensors.config import SensorConfigError

    try:
        sensor_config(args.design)
    except (UnknownSensorError, SensorConfigError, FileNotFoundError) as e:
        raise UsageError(f"--design: {e}") from None
    out = args.out
    if out.suffix != ".onnx" or out.name.startswith("-"):
        raise UsageError(f"--out {out}: the file name must end in .onnx (its card is written beside it as "
                         f"{out.stem}.json); choose another --out")
    if out.is_dir():
        raise UsageError(f"--out {out} is a folder: give a file name inside it")
    existing = [p for p in (out, out.with_suffix(".json")) if p.exists()]
    if existing and not args.overwrite:
        raise UsageError(f"--out {out}: {' and '.join(map(str, existing))} exist{'s' if len(existing) == 1 else ''}: "
                         "pass --overwrite to replace, or choose another --out")
    cache = args.data_cache
    if cache is not None and cache.exists():
        try:
            with np.load(cache, allow_pickle=False) as z:
                have = json.loads(str(z["spec"])) if "spec" in z.files else None
        except (OSError, ValueError, zipfile.BadZipFile) as e:
            raise UsageError(f"--data-cache {cache} is not a readable crop cache ({type(e).__name__}: {e}); delete "
                             "it (it is made again), or give another --data-cache") from None
        if have is None:
            raise UsageError(f"--data-cache {cache} holds no record of the settings its crops were made with; delete "
                             "it (it is made again), or give another --data-cache")
        want = _cache_spec(args)
        diff = [f"{k}: cache {have.get(k)!r}, now {v!r}" for k, v in want.items() if have.get(k) != v]
        if diff:
            raise UsageError(f"--data-cache {cache} holds crops made with other settings ({'; '.join(diff)}); give "
                             "the same options, delete it (it is made again), or give another --data-cache")


def main(argv=None) -> int:
    from tactile_deploy.imaging import learned_readout as lr_mod

    from .data import DEPTH_RANGE_MM, RADII_MM, unit_presses
    from .family import Tolerances, family_configs

    ap = argparse.ArgumentParser(prog="python -m tactile_deploy.training.shading_net", description=__doc__.splitlines()[0])
    ap.add_argument("--design", default="gelslim1",
                    help="virtual sensor whose design the units share (default: %(default)s)")
    ap.add_argument("--units", type=int, default=8, help="virtual units of the design (default: %(default)s)")
    ap.add_argument("--presses", type=int, default=1000, help="presses per unit (default: %(default)s)")
    ap.add_argument("--epochs", type=int, default=60, help="training epochs (default: %(default)s)")
    ap.add_argument("--width", type=int, default=8, help="base channels of the U-Net (default: %(default)s)")
    ap.add_argument("--seed", type=int, default=5,
                    help="seed of the units, the presses and the training (default: %(default)s)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    ap.add_argument("--gradient-clip", type=float, default=1.0,
                    help="gradient targets clipped to +- this (mm per mm; default: %(default)s)")
    ap.add_argument("--gradient-weight", type=float, default=1.0,
                    help="weight of the gradient channels in the loss, the depth's is 1 (default: %(default)s)")
    ap.add_argument("--data-cache", type=Path, default=None,
                    help="keep the generated crops in this .npz and reuse them when present (only with the same "
                    "--design, --units, --presses and --seed; default: none)")
    ap.add_argument("--out", type=Path, default=Path("exported/gelslim_readout.onnx"),
                    help="ONNX file to write, relative to the current folder (default: %(default)s); its card "
                    "<stem>.json goes beside it")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out and its card")
    args = ap.parse_args(argv)
    _check_args(args)
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

            args.data_cache.parent.mkdir(parents=True, exist_ok=True)
            write_npz(args.data_cache, features=x_all, depth_mm=depth_crops, pitch_mm=pitch,
                      spec=np.array(json.dumps(_cache_spec(args), sort_keys=True)))
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
        "command": "python -m tactile_deploy.training.shading_net " + " ".join(sys.argv[1:] if argv is None else argv),
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
