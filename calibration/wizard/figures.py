"""The pictures the wizard shows after each step (PNG, written atomically).

Image axes: frames are shown as the camera or the imaging grid sees them (row 0 at the top);
circles are (column, row, radius) px; depths in mm (positive into the gel), residuals in um.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tactile_deploy.atomic import atomic_path

DPI = 80


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    plt = _plt()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=DPI)
    plt.close(fig)
    return path


def reference_figure(path: Path, reference: np.ndarray, frames: np.ndarray) -> Path:
    """The reference frame and the per-pixel noise of the frames averaged into it (grey)."""
    plt = _plt()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(9, 3.4), constrained_layout=True)
    a0.imshow(reference)
    a0.set_title(f"reference frame (mean of {len(frames)})", fontsize=9)
    std = frames.astype(np.float32).std(axis=0).mean(axis=-1) if len(frames) > 1 else (
        np.zeros(reference.shape[:2]))
    im = a1.imshow(std, cmap="magma")
    fig.colorbar(im, ax=a1, label="frame-to-frame std (grey)")
    a1.set_title("camera noise per pixel", fontsize=9)
    for a in (a0, a1):
        a.tick_params(labelsize=7)
    return _save(fig, path)


def crop_figure(path: Path, reference: np.ndarray, grid_px: tuple[int, int, int, int]) -> Path:
    """The reference frame with the crop used as imaging grid."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 4), constrained_layout=True)
    ax.imshow(reference)
    x0, y0, w, h = grid_px
    ax.add_patch(plt.Rectangle((x0 - 0.5, y0 - 0.5), w, h, fill=False, ec="lime", lw=1.2))
    ax.set_title("imaging grid: the crop (no lens correction)", fontsize=9)
    return _save(fig, path)


def circles_figure(path: Path, frames: np.ndarray, circles: np.ndarray, names, keep,
                   rig_centres: np.ndarray | None = None, max_panels: int = 24) -> Path:
    """Rectified press frames with their contact circles (green; dropped presses red) and the
    rig's commanded centres (white crosses)."""
    plt = _plt()
    n = min(len(frames), max_panels)
    cols = min(6, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(1.9 * cols, 1.55 * rows + 0.3),
                             squeeze=False, constrained_layout=True)
    t = np.linspace(0, 2 * np.pi, 73)
    for k, ax in enumerate(axes.ravel()):
        ax.axis("off")
        if k >= n:
            continue
        ax.imshow(frames[k], interpolation="nearest")
        cx, cy, r = circles[k]
        colour = "lime" if keep[k] else "red"
        if np.all(np.isfinite(circles[k])):
            ax.plot(cx + r * np.cos(t), cy + r * np.sin(t), "-", color=colour, lw=0.9)
            ax.plot(cx, cy, "+", color=colour, ms=5)
        if rig_centres is not None and np.all(np.isfinite(rig_centres[k])):
            ax.plot(*rig_centres[k], "x", color="white", ms=4, mew=0.8)
        ax.set_title(f"{k + 1}: {names[k]}" + ("" if keep[k] else " (dropped)"), fontsize=6.5)
    fig.suptitle("contact circles on the imaging grid (green: used; white x: where the rig "
                 "pressed)" if rig_centres is not None else
                 "contact circles on the imaging grid (green: used; red: dropped)", fontsize=8)
    return _save(fig, path)


def shading_figure(path: Path, depths, circles, names, spheres, pitch_mm: float,
                   ball_radius_mm: float) -> Path:
    """Per press (rows): reconstructed depth map, the row through the fitted centre against the
    ball's sphere, and the residual to that sphere inside 0.8 x the contact radius (um)."""
    plt = _plt()
    n = len(depths)
    fig, axes = plt.subplots(n, 3, figsize=(10, 2.3 * n), squeeze=False,
                             constrained_layout=True)
    for row in range(n):
        d, (cx, cy, a), sph = depths[row], circles[row], spheres[row]
        a0, a1, a2 = axes[row]
        im = a0.imshow(d, cmap="viridis")
        fig.colorbar(im, ax=a0, label="depth (mm)")
        a0.set_title(names[row], fontsize=8)
        ccol, crow = sph.centre_px
        x = (np.arange(d.shape[1]) - ccol) * pitch_mm
        line = d[int(np.clip(round(crow), 0, d.shape[0] - 1))]
        sphere = sph.apex_mm - (ball_radius_mm - np.sqrt(np.maximum(
            ball_radius_mm ** 2 - x ** 2, 0.0)))
        near = np.abs(x) < 0.95 * ball_radius_mm
        a1.plot(x, line, "-", color="tab:blue", lw=1.3, label="reconstruction")
        a1.plot(x[near], sphere[near], "k--", lw=1.0, label=f"sphere R = {ball_radius_mm:g} mm")
        band = 0.8 * a * pitch_mm
        a1.axvspan(-band, band, color="0.9", zorder=0)
        a1.set_xlim(-3 * a * pitch_mm, 3 * a * pitch_mm)
        a1.set_ylim(min(-0.05, float(line.min()) - 0.02), sph.apex_mm + 0.1)
        a1.set_xlabel("x from the fitted centre (mm)", fontsize=7)
        a1.set_ylabel("depth (mm)", fontsize=7)
        a1.legend(fontsize=6, loc="upper left")
        a1.set_title(f"shape error {sph.rms_um:.1f} um", fontsize=8)
        rows, cols = np.mgrid[0:d.shape[0], 0:d.shape[1]]
        rho = np.hypot((cols - ccol) * pitch_mm, (rows - crow) * pitch_mm)
        m = np.hypot(cols - cx, rows - cy) < 0.8 * a
        res = np.full(d.shape, np.nan)
        sph_map = sph.apex_mm - (ball_radius_mm - np.sqrt(np.maximum(ball_radius_mm ** 2
                                                                     - rho ** 2, 0.0)))
        res[m] = (d - sph_map)[m] * 1e3
        r0, r1 = max(int(cy - 1.5 * a), 0), int(cy + 1.5 * a) + 2
        c0, c1 = max(int(cx - 1.5 * a), 0), int(cx + 1.5 * a) + 2
        lim = max(float(np.nanmax(np.abs(res))) if np.any(m) else 1.0, 1.0)
        im = a2.imshow(res[r0:r1, c0:c1], cmap="coolwarm", vmin=-lim, vmax=lim,
                       extent=(c0 - 0.5, min(c1, d.shape[1]) - 0.5,
                               min(r1, d.shape[0]) - 0.5, r0 - 0.5))
        fig.colorbar(im, ax=a2, label="depth - sphere (um)")
        a2.set_title("residual inside 0.8 x contact radius", fontsize=8)
        for ax in (a0, a1, a2):
            ax.tick_params(labelsize=6)
    return _save(fig, path)


def cross_validation_figure(path: Path, results, ball_radius_mm: float, pitch_mm: float) -> Path:
    """Held-out shape error and fitted radius of every press against its distance from the
    image centre (cross-validation)."""
    plt = _plt()
    dist = np.array([r.centre_distance_px for r in results]) * pitch_mm
    shape = np.array([r.shape_um for r in results])
    radius = np.array([r.radius_mm for r in results])
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(9, 3.0), constrained_layout=True)
    a0.plot(dist, shape, "o", ms=4)
    a0.axhline(20, color="0.5", ls="--", lw=0.8)
    a0.set_xlabel("distance from the image centre (mm)", fontsize=8)
    a0.set_ylabel("held-out shape error (um)", fontsize=8)
    a1.plot(dist, radius, "o", ms=4)
    a1.axhline(ball_radius_mm, color="k", lw=0.8)
    for f in (0.95, 1.05):
        a1.axhline(f * ball_radius_mm, color="0.5", ls="--", lw=0.8)
    a1.set_xlabel("distance from the image centre (mm)", fontsize=8)
    a1.set_ylabel("fitted sphere radius (mm)", fontsize=8)
    for ax in (a0, a1):
        ax.tick_params(labelsize=7)
    fig.suptitle("cross-validated presses (each reconstructed by a model that never saw it)",
                 fontsize=9)
    return _save(fig, path)


def fem_figure(path: Path, curve, nu: float, forces_measured, forces_fitted) -> Path:
    """Depth-map gap against nu (the search), and measured against simulated forces."""
    plt = _plt()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(9, 3.0), constrained_layout=True)
    if curve:
        c = np.array(sorted(curve))
        a0.plot(c[:, 0], c[:, 1] * 1e3, "o-", ms=3)
    a0.axvline(nu, color="tab:red", lw=0.9, label=f"nu = {nu:.3f}")
    a0.set_xlabel("Poisson ratio nu", fontsize=8)
    a0.set_ylabel("depth-map gap RMS (um)", fontsize=8)
    a0.legend(fontsize=7)
    if len(forces_measured):
        fm, fs = np.asarray(forces_measured), np.asarray(forces_fitted)
        a1.plot(fm, fs, "o", ms=4)
        top = float(max(fm.max(), fs.max())) * 1.05
        a1.plot([0, top], [0, top], "k--", lw=0.8)
        a1.set_xlabel("measured force (N)", fontsize=8)
        a1.set_ylabel("FEM force at the fitted E (N)", fontsize=8)
    else:
        a1.text(0.5, 0.5, "no forces measured:\nE is not identifiable", ha="center",
                va="center", fontsize=9)
        a1.axis("off")
    for ax in (a0, a1):
        ax.tick_params(labelsize=7)
    return _save(fig, path)


def plugin_figure(path: Path, frame: np.ndarray, depth_mm: np.ndarray, grid) -> Path:
    """A press frame and the depth the written plugin makes of it on the model grid."""
    plt = _plt()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(9, 3.4), constrained_layout=True)
    a0.imshow(frame)
    a0.set_title("camera frame", fontsize=9)
    im = a1.imshow(depth_mm, cmap="viridis", extent=(grid.x_min_mm, grid.x_max_mm,
                                                     grid.y_min_mm, grid.y_max_mm))
    fig.colorbar(im, ax=a1, label="depth (mm)")
    a1.set_title("the plugin's depth on the model grid (sensor frame)", fontsize=9)
    a1.set_xlabel("x (mm)", fontsize=8)
    a1.set_ylabel("y (mm)", fontsize=8)
    return _save(fig, path)
