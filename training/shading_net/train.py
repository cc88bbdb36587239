"""Train the read-out network of a design and export it (ONNX + model card).

    python -m tactile_deploy.training.shading_net --design gelslim1 --units 8 --presses 1000 --epochs 60 \
        --out exported/gelslim_readout.onnx --overwrite

Data flow: :func:`.family.family_configs` (units of the design) -> :func:`.data.unit_presses`
(8-bit rectified frames and true depth on each unit's imaging grid: balls, the indenter library
and procedural faces, ``--mix``; each unit draws its presses from its own seed, so ``--workers``
processes make the same crops as one) -> ``--crop`` x ``--crop``-cell crops around each contact (its
deepest cell, jittered by up to 8 cells, inside the grid; :mod:`.crops`) -> :mod:`.fitting`:
AdamW with a one-cycle learning rate, loss: mean squared error of the gradients (mm per mm) and
of the depth (in ``DEPTH_UNIT_MM``) -> ONNX (opset 17, dynamic batch and grid size) with the
feature contract in its metadata, and a card (``.json`` beside it, :class:`.card.ReadoutCard`)
with the data, the settings and the final loss.

The crops can be trained elsewhere (a GPU machine without OpenCV or pydantic):
``--data-only --data-cache CROPS.npz`` writes them and stops; ``python -m
tactile_deploy.training.shading_net.fitting --crops CROPS.npz --weights-out W.pt`` trains there; ``--weights
W.pt`` (with the same data options) exports those weights with their card here.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from tactile_deploy.learning.readout_network import export_onnx

#: Default side of the training crops, cells: the imaging grid's height on the GelSlim designs
#: (64 cells, 17.5 mm), so that contacts up to the view's size are seen whole.
CROP_CELLS = 64
#: Default shares of the presses: balls, the indenter library, procedural faces.
MIX = (0.35, 0.15, 0.5)


def _cache_spec(args) -> dict:
    """What the crops of ``--data-cache`` depend on (stored in it, checked when it is reused)."""
    from .crops import JITTER_CELLS

    return {"design": args.design, "units": args.units, "presses": args.presses, "seed": args.seed,
            "crop_cells": args.crop, "jitter_cells": JITTER_CELLS, "mix": list(args.mix),
            "imaging_grid": "whole box of model-grid cells", "unit_seeds": UNIT_SEEDS}


#: How each unit's presses are seeded (recorded in a crop file; older files drew every unit's
#: presses from one stream and are made again).
UNIT_SEEDS = "numpy SeedSequence(seed).spawn(units)"

#: Shared with the worker processes (fork): the units and the pad's simulator, built once.
_UNITS: dict = {}


def _unit_crops(u: int):
    """Crops of unit ``u`` of ``_UNITS`` (run in a worker process or in this one)."""
    from .crops import contact_crops
    from .data import unit_presses

    rng = np.random.default_rng(_UNITS["seeds"][u])
    presses, _ = unit_presses(_UNITS["configs"][u], _UNITS["presses"], rng, _UNITS["simulator"], _UNITS["mix"])
    return contact_crops(presses, rng, _UNITS["crop"])


def generate_crops(design: str, units: int, presses: int, seed: int, mix, crop: int, workers: int = 1,
                   log=print):
    """Training crops of ``units`` virtual units of ``design``, ``presses`` each
    (:class:`.crops.Crops`, units in order). The units are drawn from ``seed``; unit ``u``'s
    presses and crops from the ``u``-th child of ``SeedSequence(seed)``, so the result does not
    depend on ``workers`` (processes forked after the pad's FEM operators are built, one unit
    each at a time)."""
    import multiprocessing
    import time
    from concurrent.futures import ProcessPoolExecutor

    from tactile_deploy.sensors.virtual import VirtualSensor

    from .crops import Crops
    from .data import PressMix
    from .family import Tolerances, family_configs

    t0 = time.perf_counter()
    configs = list(family_configs(design, units, np.random.default_rng(seed), Tolerances()))
    simulator = VirtualSensor(configs[0]).simulator
    simulator.prepare()
    _UNITS.update(configs=configs, seeds=np.random.SeedSequence(seed).spawn(units), presses=presses,
                  simulator=simulator, mix=PressMix(*mix), crop=crop)
    parts, pool = [], None
    try:
        if workers > 1:
            pool = ProcessPoolExecutor(min(workers, units), mp_context=multiprocessing.get_context("fork"))
        for u, part in enumerate((pool.map if pool else map)(_unit_crops, range(units))):
            parts.append(part)
            log(f"unit {u + 1}/{units}: {presses} presses ({time.perf_counter() - t0:.0f} s)")
    finally:
        if pool is not None:
            pool.shutdown()
        _UNITS.clear()
    return Crops.concatenate(parts)


def _check_args(args) -> None:
    """Check every option before any work (:class:`tactile_deploy.training.errors.UsageError`)."""
    from tactile_deploy.training.errors import UsageError

    for option, value, low in (("--units", args.units, 1), ("--presses", args.presses, 1), ("--epochs", args.epochs, 1),
                               ("--width", args.width, 1), ("--seed", args.seed, 0)):
        if value < low:
            raise UsageError(f"{option} must be >= {low}, got {value}")
    if args.threads is not None and args.threads < 1:
        raise UsageError(f"--threads must be >= 1, got {args.threads}")
    if args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    if args.device is not None:
        import torch

        try:
            torch.device(args.device)
        except RuntimeError:
            raise UsageError(f"--device must be a torch device such as cpu or cuda, got {args.device!r}") from None
    if not (np.isfinite(args.gradient_clip) and args.gradient_clip > 0):
        raise UsageError(f"--gradient-clip must be a number > 0 (mm per mm), got {args.gradient_clip}")
    if not (np.isfinite(args.gradient_weight) and args.gradient_weight >= 0):
        raise UsageError(f"--gradient-weight must be a number >= 0, got {args.gradient_weight}")
    from tactile_deploy.sensors.catalog import UnknownSensorError, sensor_config
    from tactile_deploy.sensors.config import SensorConfigError

    try:
        design = sensor_config(args.design)
    except (UnknownSensorError, SensorConfigError, FileNotFoundError) as e:
        raise UsageError(f"--design: {e}") from None
    if args.out is None:
        args.out = Path("exported") / f"{design.pad}_readout.onnx"
    out = args.out
    if not args.data_only:   # --data-only writes no model
        if out.suffix != ".onnx" or out.name.startswith("-"):
            raise UsageError(f"--out {out}: the file name must end in .onnx (its card is written beside it as "
                             f"{out.stem}.json); choose another --out")
        if out.is_dir():
            raise UsageError(f"--out {out} is a folder: give a file name inside it")
        existing = [p for p in (out, out.with_suffix(".json")) if p.exists()]
        if existing and not args.overwrite:
            raise UsageError(f"--out {out}: {' and '.join(map(str, existing))} exist{'s' if len(existing) == 1 else ''}: "
                             "pass --overwrite to replace, or choose another --out")
    if args.crop < 8:
        raise UsageError(f"--crop must be >= 8 cells, got {args.crop}")
    if len(args.mix) != 3 or min(args.mix) < 0 or abs(sum(args.mix) - 1.0) > 1e-6:
        raise UsageError(f"--mix must be three shares >= 0 (balls, library, procedural) that sum to 1, "
                         f"got {args.mix}")
    if args.data_only and args.data_cache is None:
        raise UsageError("--data-only needs --data-cache (where the crops are written)")
    if args.weights is not None and not args.weights.is_file():
        raise UsageError(f"--weights {args.weights} not found: give the .pt written by "
                         "python -m tactile_deploy.training.shading_net.fitting")
    cache = args.data_cache
    if cache is not None and cache.exists():
        from .crops import CropFileError, read_spec

        try:
            have = read_spec(cache)
        except CropFileError as e:
            raise UsageError(f"--data-cache: {e}; delete it (it is made again), or give another "
                             "--data-cache") from None
        if have is None:
            raise UsageError(f"--data-cache {cache} holds no record of the settings its crops were made with; delete "
                             "it (it is made again), or give another --data-cache")
        want = _cache_spec(args)
        diff = [f"{k}: cache {have.get(k)!r}, now {v!r}" for k, v in want.items() if have.get(k) != v]
        if diff:
            raise UsageError(f"--data-cache {cache} holds crops made with other settings ({'; '.join(diff)}); give "
                             "the same options, delete it (it is made again), or give another --data-cache")


def _mix(text: str) -> tuple[float, float, float]:
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three numbers separated by commas, got {text!r}") from None


def main(argv=None) -> int:
    from tactile_deploy.imaging import learned_readout as lr_mod

    from .crops import load_crops, save_crops
    from .data import DEPTH_RANGE_MM, RADII_MM
    from .family import Tolerances
    from .fitting import fit_network

    ap = argparse.ArgumentParser(prog="python -m tactile_deploy.training.shading_net", description=__doc__.splitlines()[0])
    ap.add_argument("--design", default="gelslim1",
                    help="virtual sensor whose design the units share (default: %(default)s)")
    ap.add_argument("--units", type=int, default=8, help="virtual units of the design (default: %(default)s)")
    ap.add_argument("--presses", type=int, default=1000, help="presses per unit (default: %(default)s)")
    ap.add_argument("--mix", type=_mix, default=MIX,
                    help="shares of balls, library shapes and procedural faces (default: 0.35,0.15,0.5)")
    ap.add_argument("--crop", type=int, default=CROP_CELLS,
                    help="side of the training crops, cells (default: %(default)s)")
    ap.add_argument("--epochs", type=int, default=60, help="training epochs (default: %(default)s)")
    ap.add_argument("--width", type=int, default=8, help="base channels of the U-Net (default: %(default)s)")
    ap.add_argument("--seed", type=int, default=5,
                    help="seed of the units, the presses and the training (default: %(default)s)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    ap.add_argument("--workers", type=int, default=1,
                    help="processes that make the presses, one unit each at a time; the crops do not depend on it "
                    "(default: %(default)s)")
    ap.add_argument("--device", default=None,
                    help="torch device of the training, e.g. cpu or cuda (default: cuda when there is one)")
    ap.add_argument("--gradient-clip", type=float, default=1.0,
                    help="gradient targets clipped to +- this (mm per mm; default: %(default)s)")
    ap.add_argument("--gradient-weight", type=float, default=1.0,
                    help="weight of the gradient channels in the loss, the depth's is 1 (default: %(default)s)")
    ap.add_argument("--data-cache", type=Path, default=None,
                    help="keep the generated crops in this .npz and reuse them when present (only with the same "
                    "--design, --units, --presses, --mix, --crop and --seed; default: none)")
    ap.add_argument("--data-only", action="store_true",
                    help="write the crops to --data-cache and stop (to train them elsewhere)")
    ap.add_argument("--weights", type=Path, default=None,
                    help="export these weights (.pt of python -m tactile_deploy.training.shading_net.fitting) instead of training")
    ap.add_argument("--out", type=Path, default=None,
                    help="ONNX file to write, relative to the current folder (default: "
                    "exported/<the design's pad>_readout.onnx); its card <stem>.json goes beside it")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out and its card")
    args = ap.parse_args(argv)
    _check_args(args)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    tol = Tolerances()
    if args.data_cache is not None and args.data_cache.is_file():
        crops = load_crops(args.data_cache)
        print(f"crops from {args.data_cache}", flush=True)
    else:
        crops = generate_crops(args.design, args.units, args.presses, args.seed, args.mix, args.crop, args.workers,
                               log=lambda m: print(m, flush=True))
        if args.data_cache is not None:
            save_crops(args.data_cache, crops, _cache_spec(args))
            print(f"wrote {len(crops)} crops to {args.data_cache} "
                  f"({args.data_cache.stat().st_size / 2 ** 20:.1f} MiB)", flush=True)
    t_data = time.perf_counter() - t0
    if args.data_only:
        return 0
    if args.weights is not None:
        from tactile_deploy.learning.readout_network import ReadoutNet
        from tactile_deploy.safe_torch import load_torch_file

        saved = load_torch_file(args.weights)
        trained = saved["settings"]
        net = ReadoutNet(int(trained["width"]))
        net.load_state_dict(saved["state_dict"])
        net.eval()
        losses = list(saved["losses"])
        train_info = {**trained, "seconds": round(float(saved["seconds"]), 1),
                      "weights_from": args.weights.name}
    else:
        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
        net, losses = fit_network(crops, args.width, args.epochs, args.seed,
                                  gradient_clip=args.gradient_clip,
                                  gradient_weight=args.gradient_weight, device=device,
                                  log=lambda m: print(m, flush=True))
        train_info = {"width": args.width, "epochs": args.epochs, "batch": 32, "lr": 2e-3,
                      "gradient_clip": args.gradient_clip, "gradient_weight": args.gradient_weight,
                      "seed": args.seed, "device": device, "seconds": round(time.perf_counter() - t0 - t_data, 1)}
        if device.startswith("cuda"):
            train_info["device_name"] = torch.cuda.get_device_name(torch.device(device))
    metadata = {"readout_format": lr_mod.READOUT_FORMAT, "feature_version": lr_mod.FEATURE_VERSION,
                "colour_scale_grey": repr(lr_mod.COLOUR_SCALE_GREY),
                "position_scale_mm": repr(lr_mod.POSITION_SCALE_MM), "saturation_level": 254,
                "design": args.design, "window_cells": str(args.crop)}
    export_onnx(net, args.out, metadata)
    import sys

    kinds, counts = np.unique(crops.kinds, return_counts=True)
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
                 "mix": {"balls": args.mix[0], "library": args.mix[1], "procedural": args.mix[2]},
                 "presses_by_kind": {str(k): int(c) for k, c in zip(kinds, counts)},
                 "library_indenters": "every shape of the indenter library, any rotation",
                 "procedural": "training/shading_net/shapes.py: flats, holed flats and rings, lines, dots, "
                               "curved parts, edges beyond the view, relief; 0.2-24 mm, any rotation",
                 "depth_range_mm": list(DEPTH_RANGE_MM), "crop_cells": args.crop},
        "training": {**train_info, "loss_first": losses[0], "loss_last": losses[-1],
                     "parameters": int(sum(p.numel() for p in net.parameters()))},
        "metadata": {k: str(v) for k, v in metadata.items()},
        "versions": {"torch": torch.__version__, "python": platform.python_version()},
        "seconds": {"data": round(t_data, 1), "total": round(time.perf_counter() - t0, 1)},
    }
    from tactile_deploy.atomic import write_json
    from tactile_deploy.training.shading_net.card import ReadoutCard

    write_json(args.out.with_suffix(".json"), ReadoutCard.model_validate(card).model_dump(mode="json", exclude_none=True))
    print(f"wrote {args.out} and {args.out.with_suffix('.json')}")
    return 0
