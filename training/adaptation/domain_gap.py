"""What separates a sensor's depth maps from the simulator's: measured on the virtual sensors.

For every press of a virtual domain (:mod:`tactile_deploy.training.adaptation.domains`) the plugin's depth map
``est`` is compared with the clean simulated depth map ``true`` of the same contact, inside the
sensor's view:

* **blur and gain**: the Gaussian blur sigma (mm) and gain g that best explain ``est`` as
  ``g * blur(true)`` (least squares; sigma on a 0.05 mm grid);
* **residual**: what remains, ``est - g * blur(true)``: its RMS, its low-frequency part (a
  Gaussian of 2 mm: the shading/integration drift the Perlin noise stands for), its most negative
  value within 3 mm of the contact (the integration halo);
* **view**: the share of the true contact's volume (positive depth) outside the camera's view
  (the depth map is 0 there).

    python -m tactile_deploy.training.adaptation.domain_gap --domains gelslim1 gelslim2 [--work out/adapt/domains]

prints a markdown table (docs/adaptation.md) of the 10th, 50th and 90th percentiles, which set
the ranges of :class:`tactile_deploy.training.config.AugmentationConfig`.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import gaussian_filter

from tactile_deploy.camera.depth import DepthCamera

PITCH_MM = DepthCamera().pitch_mm
SIGMAS_MM = np.arange(0.0, 0.81, 0.05)


def fit_blur_gain(est: np.ndarray, true: np.ndarray, weight: np.ndarray) -> tuple[float, float, float]:
    """(sigma_mm, gain, residual RMS mm) of ``est ~ gain * blur_sigma(true)`` over ``weight``."""
    best = (0.0, 1.0, np.inf)
    w = weight.astype(np.float64)
    for s in SIGMAS_MM:
        b = gaussian_filter(true.astype(np.float64), s / PITCH_MM) if s > 0 else true.astype(np.float64)
        den = float((w * b * b).sum())
        if den <= 0:
            continue
        g = float((w * b * est).sum()) / den
        r = float(np.sqrt((w * (est - g * b) ** 2).sum() / w.sum()))
        if r < best[2]:
            best = (float(s), g, r)
    return best


def measure(domain) -> dict[str, np.ndarray]:
    """Per-press figures of one domain (arrays of length N)."""
    w = domain.weight
    inside = w > 0.5
    out = {k: [] for k in ("sigma_mm", "gain", "residual_rms_mm", "lowfreq_rms_mm", "halo_mm",
                           "peak_ratio", "outside_view")}
    for est, true in zip(domain.depth_mm, domain.true_depth_mm):
        pos = np.maximum(true, 0.0)
        vol = float(pos.sum())
        if true.max() < 0.05 or vol <= 0:
            continue
        s, g, r = fit_blur_gain(est, true, w)
        b = gaussian_filter(true.astype(np.float64), s / PITCH_MM) if s > 0 else true
        res = (est - g * b) * inside
        low = gaussian_filter(res, 2.0 / PITCH_MM)
        near = gaussian_filter((true > 0.02).astype(float), 3.0 / PITCH_MM) > 0.01
        out["sigma_mm"].append(s)
        out["gain"].append(g)
        out["residual_rms_mm"].append(r)
        out["lowfreq_rms_mm"].append(float(np.sqrt((low[inside] ** 2).mean())))
        out["halo_mm"].append(float(min(res[near & inside].min(initial=0.0), 0.0)))
        out["peak_ratio"].append(float(est[inside].max() / true.max()))
        out["outside_view"].append(float(pos[~inside].sum() / vol))
    return {k: np.array(v) for k, v in out.items()}


def table(results: dict[str, dict[str, np.ndarray]]) -> str:
    rows = ["| quantity | " + " | ".join(f"{n} p10 / p50 / p90" for n in results) + " |",
            "|---|" + "---|" * len(results)]
    names = {"sigma_mm": "blur sigma, mm", "gain": "gain", "residual_rms_mm": "residual RMS, mm",
             "lowfreq_rms_mm": "low-frequency residual RMS, mm", "halo_mm": "halo (most negative residual within 3 mm of the contact), mm",
             "peak_ratio": "peak depth / true peak depth", "outside_view": "share of the contact volume outside the view"}
    for key, label in names.items():
        cells = []
        for r in results.values():
            q = np.quantile(r[key], [0.1, 0.5, 0.9])
            cells.append(" / ".join(f"{v:.3g}" for v in q))
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    n = " / ".join(str(len(r["gain"])) for r in results.values())
    return "\n".join(rows) + f"\n\n(presses with a true peak above 0.05 mm: {n})\n"


def main(argv=None) -> int:
    from tactile_deploy.training.adaptation.domains import load_or_make

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--domains", nargs="+", default=["gelslim1", "gelslim2"])
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default="out/adapt/domains")
    args = ap.parse_args(argv)
    results = {name: measure(load_or_make(name, args.n, args.seed, args.work)) for name in args.domains}
    print(table(results))
    return 0


if __name__ == "__main__":
    from tactile_deploy.training.errors import run_command

    raise SystemExit(run_command(main))
