"""Diagnostic figures of a camera-mapping fit.

``python -m tactile_deploy.calibration.camera.figure --out docs/img/camera_mapping.png`` regenerates the
documentation figure from virtual-sensor frames (a ChArUco view and a pressed dot grid seen through
a known barrel-distorted camera).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tactile_deploy.calibration.camera.fitting import PlaneFit
from tactile_deploy.atomic import atomic_path
from tactile_deploy.imaging.camera_mapping import (
    rectify,
    sensor_mm_to_pixels,
    undistort_pixels,
)


def _gray(frame: np.ndarray) -> np.ndarray:
    f = np.asarray(frame, dtype=np.float32)
    return f.mean(axis=2) if f.ndim == 3 else f


def draw_fit(axes, fit: PlaneFit, frame: np.ndarray, label: str = "") -> None:
    """Fill three matplotlib axes: detections + residuals, lens displacement, rectified frame."""
    m = fit.mapping
    s = m.fit
    ax0, ax1, ax2 = axes
    gray = _gray(frame)
    ax0.imshow(gray, cmap="gray", interpolation="nearest")
    res_len = np.linalg.norm(fit.residual_px, axis=1)
    gain = 10 ** np.floor(np.log10(60.0 / max(float(res_len.max()), 1e-6)))
    ax0.plot(fit.uv_px[:, 0], fit.uv_px[:, 1], "o", ms=2.5, mfc="none", mec="lime", mew=0.7)
    ax0.quiver(fit.uv_px[:, 0], fit.uv_px[:, 1], gain * fit.residual_px[:, 0],
               gain * fit.residual_px[:, 1], color="red", angles="xy", scale_units="xy", scale=1,
               width=0.004)
    if len(fit.rejected_uv_px):
        ax0.plot(fit.rejected_uv_px[:, 0], fit.rejected_uv_px[:, 1], "x", color="orange", ms=4)
    ax0.set_title(f"{label}{s.n_points} points, residuals x{gain:g}\n"
                  f"RMS {s.rms_px:.3f} px = {1000 * s.rms_mm:.1f} um", fontsize=8)
    ax0.set_xlabel("u (px)", fontsize=7)
    ax0.set_ylabel("v (px)", fontsize=7)

    w, h = m.image_size
    uu, vv = np.meshgrid(np.linspace(0, w - 1, 81), np.linspace(0, h - 1, 61))
    raw = np.stack([uu.ravel(), vv.ravel()], axis=1)
    norm = np.linalg.norm(undistort_pixels(raw, m) - raw, axis=1).reshape(uu.shape)
    ax1.imshow(norm, cmap="viridis", extent=(-0.5, w - 0.5, h - 0.5, -0.5))
    cs = ax1.contour(uu, vv, norm, levels=np.arange(5, norm.max(), 5), colors="white",
                     linewidths=0.5)
    ax1.clabel(cs, fontsize=5, fmt="%g")
    g = m.grid
    edge = np.linspace(0.0, 1.0, 50)
    outline = np.concatenate([
        np.stack([g.x_min_mm + edge * (g.x_max_mm - g.x_min_mm), np.full(50, g.y_min_mm)], 1),
        np.stack([np.full(50, g.x_max_mm), g.y_min_mm + edge * (g.y_max_mm - g.y_min_mm)], 1),
        np.stack([g.x_max_mm - edge * (g.x_max_mm - g.x_min_mm), np.full(50, g.y_max_mm)], 1),
        np.stack([np.full(50, g.x_min_mm), g.y_max_mm - edge * (g.y_max_mm - g.y_min_mm)], 1),
    ])
    uv_outline = sensor_mm_to_pixels(outline, m)
    ax1.plot(uv_outline[:, 0], uv_outline[:, 1], "-", color="red", lw=0.8)
    ax1.set_xlim(-0.5, w - 0.5)
    ax1.set_ylim(h - 0.5, -0.5)
    ax1.set_title(f"lens displacement (px), output grid in red\n"
                  f"{m.mm_per_px_x:.4f} x {m.mm_per_px_y:.4f} mm/px, "
                  f"mirrored={m.image_mirrored}", fontsize=8)
    ax1.set_xlabel("u (px)", fontsize=7)

    ax2.imshow(_gray(rectify(np.asarray(frame), m)), cmap="gray", interpolation="nearest",
               extent=(g.x_min_mm, g.x_max_mm, g.y_min_mm, g.y_max_mm), origin="upper")
    ax2.plot(fit.xy_mm[:, 0], fit.xy_mm[:, 1], ".", ms=1.5, color="lime")
    ax2.set_xlim(g.x_min_mm, g.x_max_mm)
    ax2.set_ylim(g.y_min_mm, g.y_max_mm)
    ax2.set_title(f"rectified {g.ny}x{g.nx}, sensor frame\n(seen from outside the gel)",
                  fontsize=8)
    ax2.set_xlabel("x (mm)", fontsize=7)
    ax2.set_ylabel("y (mm)", fontsize=7)
    for ax in axes:
        ax.tick_params(labelsize=6)


def plot_fit(fit: PlaneFit, frame: np.ndarray, path: str | Path, dpi: int = 90) -> None:
    """Write a one-row diagnostic PNG of ``fit`` on ``frame`` (atomic)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4), constrained_layout=True)
    draw_fit(axes, fit, frame)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)


def make_docs_figure(path: str | Path, dpi: int = 80) -> None:
    """The documentation figure: ChArUco (top) and pressed dots (bottom), virtual sensor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tactile_deploy.calibration.camera.charuco import CharucoBoardSpec, calibrate_charuco
    from tactile_deploy.calibration.camera.dots import calibrate_dots
    from tactile_deploy.calibration.camera.synthetic import (
        VirtualCamera,
        board_to_sensor,
        render_charuco_frame,
        render_dot_press,
    )

    rng = np.random.default_rng(7)
    k = np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]])
    camera = VirtualCamera.from_arrays((640, 480), k, [-0.3, 0.1, 0.0, 0.0, 0.0])
    theta = np.deg2rad(3.0)
    sensor_to_und = np.array([[np.cos(theta) / 0.07, -np.sin(theta) / 0.07, 319.5],
                              [np.sin(theta) / 0.075, np.cos(theta) / 0.075, 239.5],
                              [0.0, 0.0, 1.0]])
    spec = CharucoBoardSpec()
    board_frame = render_charuco_frame(spec, camera, sensor_to_und @ board_to_sensor(spec), rng)
    charuco_fit = calibrate_charuco([board_frame], spec)
    pressed, reference = render_dot_press(camera, sensor_to_und, 2.5, (15, 15), rng)
    dots_fit, _ = calibrate_dots(pressed, reference, 2.5, grid_shape=(15, 15))

    fig, axes = plt.subplots(2, 3, figsize=(11, 6.6), constrained_layout=True, dpi=dpi)
    draw_fit(axes[0], charuco_fit, board_frame, "ChArUco, ")
    draw_fit(axes[1], dots_fit, np.abs(pressed.astype(np.float32) - reference), "pressed dots, ")
    from PIL import Image

    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    plt.close(fig)
    # A 64-colour palette keeps the figure small for the repository.
    img = Image.fromarray(rgb).quantize(colors=64, method=Image.Quantize.MEDIANCUT)
    with atomic_path(path) as tmp:
        img.save(tmp, optimize=True)


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/img/camera_mapping.png"))
    args = parser.parse_args()
    make_docs_figure(args.out)
    print(f"{args.out}: {args.out.stat().st_size / 1024:.0f} KB")
