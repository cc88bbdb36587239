"""The virtual sensor's own optics as shading knowledge, on virtual-sensor presses.

    python docs/experiments/shading_optics_prior.py [--cache DIR] [--weights 1 4 16 100] [--no-sfs]

Two oracles that know the exact optics of the virtual GelSlim ``gelslim2`` (LED positions and
colours, specular lobes, fall-off, vignetting, camera), which no calibration of a real sensor
knows; each measures how far an optics model could take the shading read-out at its best:

* **Rendered table prior.** The wizard's table falls back, where a node has few samples of a
  colour bin, to a prior (the colour polynomial). Here the prior is rendered from the optics:
  at every table node, the colour difference of a tilted flat patch for a dense set of depth
  gradients (|g| <= 0.75, step 0.01, flat at rest) is binned exactly as the runtime bins a frame
  (reference gain, saturated channels in their own bin), and each bin gets the mean gradient of
  the patches that land in it. The table blends it with the presses' samples at the weight of
  ``w`` samples (``--weights``; a large ``w`` is the rendered table alone).
* **Shape from shading** (``--no-sfs`` skips it). The wizard's depth map is refined around each
  contact (within 2.5 contact radii) by nonlinear least squares on the depth itself: the colours
  the optics predict for the depth's central-difference gradients on the imaging grid, scaled by
  the reference frame over the optics' rest colour (albedo), against the frame's colours
  (offset-corrected; a saturated channel only constrains the prediction from above). The depth
  is one surface, so a pixel whose colour is ambiguous is held by its neighbours' gradients
  (integrability), which the table's per-pixel read cannot use.

Presses and errors as in ``bench/bench_shading.py --only virtual`` (the wizard's 24 presses;
bench set seed 2024, 8 + 8; second set seed 77, 24 + 8; RMSE within 1.5 contact radii, um); the
presses are cached in ``--cache`` (shared with ``shading_sample_read.py`` beside it). The first
oracle swaps the table fit's prior for the rendered one while the script runs (the shading fit
has no such option: this is a measurement, not a calibration path).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]

#: Depth gradients rendered per table node: |g| <= GRADIENT_MAX on a square lattice of GRADIENT_STEP.
GRADIENT_MAX = 0.75
GRADIENT_STEP = 0.01
#: Region refined by the shape-from-shading oracle, contact radii around the press centre.
SFS_REGION_RADII = 2.5


def grid_points_mm(grid, cols, rows) -> np.ndarray:
    """Sensor-frame points (N, 2) mm of imaging-grid pixel coordinates (any shape)."""
    x = grid.x_min_mm + (np.ravel(cols) + 0.5) * grid.pitch_x_mm
    y = grid.y_max_mm - (np.ravel(rows) + 0.5) * grid.pitch_y_mm
    return np.c_[x, y]


def optics_colours(optics, xy_mm, depth_mm, g_x, g_y) -> np.ndarray:
    """Radiance (N, 3) grey levels of the surface at sensor points ``xy_mm`` (N, 2) pushed in
    by ``depth_mm`` (N,) with depth gradients along +x and +y ``g_x``, ``g_y`` (N,): the
    optics' equations (height = -depth, so its slopes are -g)."""
    from tactile_deploy.imaging.camera_mapping import sensor_mm_to_pixels
    from tactile_deploy.optics.render import shade_points

    uv = sensor_mm_to_pixels(xy_mm, optics.camera)
    return shade_points(optics, uv, xy_mm, -np.asarray(depth_mm, float), -np.asarray(g_x, float),
                        -np.asarray(g_y, float))


class RenderedPrior:
    """Table prior rendered from an optics model: ``at_nodes(keys, node_cols, node_rows)`` ->
    (nodes, len(keys), 2) image-axis depth gradients (columns, rows); bins the optics never
    produce at a node take ``fallback``'s value there."""

    def __init__(self, optics, grid, reference_rectified, cfg, fallback):
        from tactile_deploy.imaging.shading import reference_gain

        self.optics, self.grid, self.cfg, self.fallback = optics, grid, cfg, fallback
        self.gain = reference_gain(reference_rectified)
        s = np.arange(-GRADIENT_MAX, GRADIENT_MAX + 1e-9, GRADIENT_STEP)
        gx, gy = np.meshgrid(s, s)
        keep = np.hypot(gx, gy) <= GRADIENT_MAX
        self.g_x, self.g_y = gx[keep], gy[keep]

    def node_bins(self, col: float, row: float):
        """(count, sum of column gradients, sum of row gradients) per flat colour bin at one
        node (imaging-grid px)."""
        from tactile_deploy.imaging.shading import colour_bin_index

        cfg = self.cfg
        n = len(self.g_x)
        xy = np.repeat(grid_points_mm(self.grid, [col], [row]), n + 1, axis=0)
        rad = optics_colours(self.optics, xy, np.zeros(n + 1), np.r_[0.0, self.g_x],
                             np.r_[0.0, self.g_y])
        rad = np.clip(np.rint(rad), 0, self.optics.saturation_grey)
        r = int(np.clip(round(row), 0, self.gain.shape[0] - 1))
        c = int(np.clip(round(col), 0, self.gain.shape[1] - 1))
        diff = (rad[1:] - rad[0]) * self.gain[r, c]
        key = colour_bin_index(diff[None], (rad[1:] >= cfg.saturation_level)[None], cfg.bins,
                               cfg.colour_min, cfg.colour_max)[0]
        nb3 = (cfg.bins + 1) ** 3
        # image columns run along +x, rows along -y
        return (np.bincount(key, minlength=nb3), np.bincount(key, self.g_x, minlength=nb3),
                np.bincount(key, -self.g_y, minlength=nb3))

    def at_nodes(self, keys, node_cols, node_rows) -> np.ndarray:
        out = np.asarray(self.fallback.at_nodes(keys, node_cols, node_rows), np.float64).copy()
        for i, (c, r) in enumerate(zip(np.ravel(node_cols), np.ravel(node_rows))):
            cnt, s_col, s_row = (v[keys] for v in self.node_bins(c, r))
            ok = cnt > 0
            out[i, ok, 0] = s_col[ok] / cnt[ok]
            out[i, ok, 1] = s_row[ok] / cnt[ok]
        return out


@contextlib.contextmanager
def table_prior(make_prior, prior_weight: float):
    """While inside, the shading fit's table takes ``make_prior(fallback)`` as its prior, at
    ``prior_weight`` samples (``fallback``: the prior the fit made, the colour polynomial)."""
    from tactile_deploy.calibration.shading import fit

    original = fit.fit_table

    def fit_table(keys, targets, cols, rows, shape, spacing_px, sigma_px, bins, _weight,
                  prior_sigma_px=None, prior=None):
        return original(keys, targets, cols, rows, shape, spacing_px, sigma_px, bins,
                        prior_weight, prior_sigma_px, make_prior(prior))

    fit.fit_table = fit_table
    try:
        yield
    finally:
        fit.fit_table = original


class ShapeFromShading:
    """Refine an imaging-grid depth map so that the optics' colours match the frame's."""

    def __init__(self, optics, grid, reference_rectified):
        self.optics, self.grid = optics, grid
        self.shape = (grid.ny, grid.nx)
        rows, cols = np.mgrid[0:grid.ny, 0:grid.nx]
        self.xy = grid_points_mm(grid, cols, rows)
        n = len(self.xy)
        rest = optics_colours(optics, self.xy, np.zeros(n), np.zeros(n), np.zeros(n))
        self.reference = reference_rectified.reshape(-1, 3).astype(np.float64)
        self.albedo = self.reference / np.maximum(rest, 1.0)
        self.rest = rest

    def predict(self, depth_mm: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Predicted rectified colours (k, 3) at flat pixels ``idx`` of ``depth_mm`` (ny, nx)."""
        g = self.grid
        g_x = np.gradient(depth_mm, g.pitch_x_mm, axis=1).ravel()[idx]
        g_y = -np.gradient(depth_mm, g.pitch_y_mm, axis=0).ravel()[idx]
        rad = optics_colours(self.optics, self.xy[idx], depth_mm.ravel()[idx], g_x, g_y)
        return self.reference[idx] + (rad - self.rest[idx]) * self.albedo[idx]

    def refine(self, image_u8: np.ndarray, depth_mm: np.ndarray, centre_mm, radius_mm: float,
               saturation_level: int = 254, max_evaluations: int = 30) -> np.ndarray:
        """``depth_mm`` (ny, nx) refined within SFS_REGION_RADII contact radii of ``centre_mm``
        (sensor frame) against the rectified frame ``image_u8`` (ny, nx, 3)."""
        import scipy.sparse
        from scipy.optimize import least_squares

        from tactile_deploy.imaging.shading import frame_offset

        ny, nx = self.shape
        ref_u8 = np.clip(np.rint(self.reference), 0, 255).astype(np.uint8).reshape(ny, nx, 3)
        obs = (image_u8.astype(np.float64) - frame_offset(image_u8, ref_u8, 12.0)).reshape(-1, 3)
        sat = (image_u8 >= saturation_level).reshape(-1, 3)
        rho = np.hypot(self.xy[:, 0] - centre_mm[0], self.xy[:, 1] - centre_mm[1])
        free = np.flatnonzero(rho < SFS_REGION_RADII * radius_mm)
        z = depth_mm.astype(np.float64).ravel().copy()

        def residuals(v):
            zz = z.copy()
            zz[free] = v
            r = self.predict(zz.reshape(ny, nx), free) - obs[free]
            return np.where(sat[free] & (r > 0), 0.0, r).ravel()

        # a pixel's colour depends on its depth and its four neighbours' (central differences)
        pos = np.full(ny * nx, -1)
        pos[free] = np.arange(len(free))
        r0, c0 = np.divmod(free, nx)
        rows, cols = [], []
        for dr, dc in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):
            r1, c1 = r0 + dr, c0 + dc
            inside = (r1 >= 0) & (r1 < ny) & (c1 >= 0) & (c1 < nx)
            j = np.full(len(free), -1)
            j[inside] = pos[r1[inside] * nx + c1[inside]]
            k = np.flatnonzero(j >= 0)
            for ch in range(3):
                rows.append(3 * k + ch)
                cols.append(j[k])
        pattern = scipy.sparse.csr_matrix(
            (np.ones(sum(len(r) for r in rows)), (np.concatenate(rows), np.concatenate(cols))),
            shape=(3 * len(free), len(free)))
        fit = least_squares(residuals, z[free], jac_sparsity=pattern, x_scale=0.05,
                            max_nfev=max_evaluations)
        z[free] = fit.x
        return z.reshape(ny, nx).astype(np.float32)


def forward_mismatch(sfs: ShapeFromShading, pipeline, sensor, new, to_imaging) -> dict:
    """RMS (grey levels) within 0.7 and 0.7-1.3 contact radii of the presses ``new``: colours
    the optics predict on the imaging grid from the true surface against the noise-free frame
    of that surface (``model``), and the noise-free frame against the recorded one
    (``noise``: camera noise and LED drift). Saturated channels left out."""
    r = sensor.renderer
    rest = pipeline.rectify(r.reference_frame(None)).astype(np.float64).reshape(-1, 3)
    recorded_ref = sfs.reference
    out = {"model": {0.7: [], 1.3: []}, "noise": {0.7: [], 1.3: []}}
    for frame, truth, surface, c, a in zip(new.frames, new.truths, new.surfaces_mm,
                                           new.centres_mm, new.radii_mm):
        clean = pipeline.rectify(r.render(r.rest_height_mm - surface, None))
        clean = clean.astype(np.float64).reshape(-1, 3) - rest
        image = pipeline.rectify(frame)
        recorded = image.astype(np.float64).reshape(-1, 3) - recorded_ref
        sat = (image >= 254).reshape(-1, 3)
        rho = np.hypot(sfs.xy[:, 0] - c[0], sfs.xy[:, 1] - c[1]) / a
        for lo, hi in ((0.0, 0.7), (0.7, 1.3)):
            idx = np.flatnonzero((rho >= lo) & (rho < hi))
            pred = sfs.predict(to_imaging(truth).astype(np.float64), idx) - recorded_ref[idx]
            ok = ~sat[idx]
            out["model"][hi].append(np.sqrt(np.mean((pred - clean[idx])[ok] ** 2)))
            out["noise"][hi].append(np.sqrt(np.mean((clean[idx] - recorded[idx])[ok] ** 2)))
    return {k: {hi: float(np.mean(v)) for hi, v in d.items()} for k, d in out.items()}


def summary(errors: dict, new) -> str:
    """``inside mean / worst, near the edges mean`` (um) of near-contact RMSEs."""
    e = errors["near"]
    inside = ~new.near_edge
    return f"{e[inside].mean():.1f} / {e[inside].max():.1f}, {e[~inside].mean():.1f}"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/shading_sample_read"))
    ap.add_argument("--weights", type=float, nargs="+", default=[1.0, 4.0, 16.0, 100.0])
    ap.add_argument("--no-sfs", action="store_true")
    args = ap.parse_args(argv)

    from shading_sample_read import wizard_data
    from tactile_deploy.calibration.shading.fit import fit_shading
    from tactile_deploy.calibration.shading.presses import PressSet
    from tactile_deploy.calibration.shading.virtual_check import near_contact_errors
    from tactile_deploy.runtime.pipeline import (
        ImagingPipeline,
        apply_noise_reference,
        to_model_grid,
    )
    from tactile_deploy.sensors import load_sensor

    t0 = time.perf_counter()
    args.cache.mkdir(parents=True, exist_ok=True)
    data = wizard_data(args.cache)
    d, camera, cfg = data["presses"], data["camera"], data["fit_cfg"]
    grid = camera.grid
    keep = d["keep"]
    presses = PressSet(d["reference_r"], d["rectified"][keep], [str(n) for n in d["names"][keep]],
                       d["circles"][keep], data["profiles"])
    optics = load_sensor("gelslim2").optics

    def pipeline_of(model):
        plain = ImagingPipeline(camera, model, data["reference"], None, "keep")
        noise = np.mean([plain.frame_to_depth(f) for f in data["reference_frames"]], axis=0)
        return ImagingPipeline(camera, model, data["reference"], noise.astype(np.float32),
                               "subtract")

    def row(label, depths_of):
        cells = [summary(near_contact_errors(depths_of(new), new), new)
                 for new in data["sets"].values()]
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)

    print("| read-out | bench set: inside mean / worst, near the edges | second set: the same |")
    print("|---|---|---|")
    wizard = pipeline_of(fit_shading(presses, data["ball_radius_mm"], grid.pitch_x_mm,
                                     cfg).model)
    row("the wizard's table (colour-polynomial prior, weight 1)",
        lambda new: [wizard.frame_to_depth(f) for f in new.frames])
    for w in args.weights:
        def rendered(fallback):
            return RenderedPrior(optics, grid, d["reference_r"], cfg, fallback)
        with table_prior(rendered, w):
            model = fit_shading(presses, data["ball_radius_mm"], grid.pitch_x_mm, cfg).model
        pipe = pipeline_of(model)
        row(f"oracle: prior rendered from the sensor's optics, weight {w:g}",
            lambda new, pipe=pipe: [pipe.frame_to_depth(f) for f in new.frames])
    if not args.no_sfs:
        sfs = ShapeFromShading(optics, grid, wizard.tables.reference_u8)

        def refined(new):
            out = []
            for f, c, a in zip(new.frames, new.centres_mm, new.radii_mm):
                z = sfs.refine(wizard.rectify(f), wizard.imaging_depth(f), c, a,
                               wizard.tables.saturation_level)
                out.append(apply_noise_reference(to_model_grid(z, wizard.resampler),
                                                 wizard.noise_mm, wizard.noise_handling))
            return out
        row("oracle: the wizard's depth refined by shape from shading with the sensor's optics",
            refined)
        from tactile_deploy.imaging.camera_mapping import OutputGrid
        from tactile_deploy.runtime.pipeline import GridResampler

        sensor = load_sensor("gelslim2")
        sensor.prepare()
        m = forward_mismatch(sfs, wizard, sensor, data["sets"]["bench"],
                             GridResampler(OutputGrid(), grid))
        print(f"Colours on the imaging grid, bench set, within 0.7 / 0.7-1.3 contact radii, "
              f"grey levels RMS: the optics' prediction from the true surface vs the "
              f"noise-free frame {m['model'][0.7]:.1f} / {m['model'][1.3]:.1f}; the noise-free "
              f"frame vs the recorded one {m['noise'][0.7]:.1f} / {m['noise'][1.3]:.1f}")
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
