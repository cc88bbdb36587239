"""Compare read-out networks on presses of a unit none of them was trained on.

    python -m tactile_deploy.training.shading_net.validate A.onnx B.onnx ... [--sensor gelslim2] [--presses 60]
        [--seed 20261126] [--cache PRESSES.npz]

Presses of the virtual sensor ``--sensor`` (another unit of the design than the training family's),
drawn as in training (:func:`.data.unit_presses`): a quarter balls, three quarters procedural
faces (:mod:`.shapes`), none of the indenter library's shapes and none of the shared meshes, so
that choosing a network here leaves the shared meshes unseen for the benchmark. Each network
reads the presses' features on the unit's imaging grid as the runtime does (in windows when its
metadata names ``window_cells``; no camera mapping, depth gain 1); the
error is the depth RMSE (um) over the contact and its rim (true depth > 10 um, grown by 4
cells), mean and worst per kind.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def region_rmse_um(depth_mm: np.ndarray, truth_mm: np.ndarray, threshold_mm: float = 0.01,
                   grow_cells: int = 4) -> float:
    """RMSE (um) of ``depth_mm`` against ``truth_mm`` (H, W) where the truth exceeds
    ``threshold_mm``, grown by ``grow_cells`` cells; NaN where it exceeds it nowhere (a press
    that left no contact inside the grid)."""
    from scipy import ndimage

    m = ndimage.binary_dilation(truth_mm > threshold_mm, iterations=grow_cells)
    if not m.any():
        return float("nan")
    return float(np.sqrt(np.mean((depth_mm[m] - truth_mm[m]) ** 2)) * 1e3)


def main(argv=None) -> int:
    from tactile_deploy.imaging.learned_readout import LearnedReadout
    from tactile_deploy.sensors.catalog import sensor_config

    from .data import PressMix, UnitPresses, unit_presses

    ap = argparse.ArgumentParser(prog="python -m tactile_deploy.training.shading_net.validate",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("onnx", type=Path, nargs="+", help="read-out networks (.onnx)")
    ap.add_argument("--sensor", default="gelslim2", help="virtual unit (default: %(default)s)")
    ap.add_argument("--presses", type=int, default=60, help="presses (default: %(default)s)")
    ap.add_argument("--seed", type=int, default=20261126, help="seed (default: %(default)s)")
    ap.add_argument("--cache", type=Path, default=None,
                    help="keep the presses in this .npz and reuse them when present")
    args = ap.parse_args(argv)
    fields = ("images", "offsets", "reference", "xy_mm", "depth_mm", "pitch_mm", "kinds")
    if args.cache is not None and args.cache.is_file():
        with np.load(args.cache, allow_pickle=False) as z:
            presses = UnitPresses(*(z[f] for f in fields))
    else:
        presses, _ = unit_presses(sensor_config(args.sensor), args.presses,
                                  np.random.default_rng(args.seed), None, PressMix(0.25, 0.0, 0.75))
        if args.cache is not None:
            np.savez_compressed(args.cache, **{f: np.asarray(getattr(presses, f)) for f in fields})
    features = presses.features
    for path in args.onnx:
        readout = LearnedReadout(path)
        errors = {}
        for f, t, kind in zip(features, presses.depth_mm, presses.kinds):
            errors.setdefault(str(kind), []).append(region_rmse_um(readout.depth_mm(f), t))
        print(f"{path.name}: " + "; ".join(
            f"{kind} {np.nanmean(e):.1f} um mean, {np.nanmax(e):.0f} worst "
            f"({int(np.isfinite(e).sum())} presses with a contact in the grid)"
            for kind, e in sorted(errors.items(), reverse=True)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
