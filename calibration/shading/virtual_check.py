"""Absolute depth on virtual-sensor ball presses: new presses of known depth, and the error of an
imaging pipeline on them.

Real presses cannot judge absolute depth (hand-drawn circles are good to 2-3 px, and 1 px of
radius moves the implied cap depth by ~100 um); a virtual sensor's can: its frames are shaded from
a surface we keep (``SensorFrame.surface_depth_mm``, area-averaged onto the model grid here).

Presses (sensor frame, mm): ``n_inside`` with the centre at least two contact radii inside the
imaging grid, ``n_edge`` between 1.2 and 1.7 contact radii from one of its edges (left, right,
bottom, top in turn), contact radius ``a = sqrt(2 R d)`` (the rigid ball's footprint at depth
d). Errors: RMSE over the whole model grid, RMSE within ``near_radii`` contact radii of the
centre, and the peak depth error (estimated minus true maximum), um.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class VirtualPresses:
    """New ball presses of a virtual sensor.

    frames : (N, H, W, 3) uint8 RGB raw camera frames. truths : (N, 128, 128) float32 mm, the
    surface they were shaded from on the model grid. centres_mm : (N, 2) sensor frame (the pose
    reached). radii_mm : (N,) rigid contact radius. near_edge : (N,) bool. surfaces_mm : (N,
    ny, nx) float32 mm, the same surfaces on the sensor's optics grid (``surface_grid``, about
    0.04 mm), or None when not kept.
    """

    frames: np.ndarray
    truths: np.ndarray
    centres_mm: np.ndarray
    radii_mm: np.ndarray
    near_edge: np.ndarray
    surfaces_mm: np.ndarray | None = None
    surface_grid: object = None


def virtual_ball_presses(sensor, grid, n_inside: int = 8, n_edge: int = 8, seed: int = 2024,
                         ball_radius_mm: float = 3.0,
                         depth_range_mm: tuple[float, float] = (0.3, 0.8),
                         keep_surfaces: bool = False, depth_grid=None) -> VirtualPresses:
    """Ball presses of ``sensor`` placed on the imaging ``grid`` (module docstring);
    ``keep_surfaces`` also keeps each surface at the optics grid's resolution; ``depth_grid``:
    the grid of the truths (default: the model grid)."""
    from tactile_deploy.imaging.camera_mapping import OutputGrid
    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.runtime.pipeline import GridResampler

    rng = np.random.default_rng([seed, 0x76697274])
    ball = AnalyticSphere(ball_radius_mm)
    to_model = GridResampler(sensor.renderer.grid, depth_grid or OutputGrid())
    frames, truths, centres, radii, edge, surfaces = [], [], [], [], [], []
    for i in range(n_inside + n_edge):
        depth = rng.uniform(*depth_range_mm)
        a = math.sqrt(2 * ball_radius_mm * depth)
        x = rng.uniform(grid.x_min_mm + 2 * a, grid.x_max_mm - 2 * a)
        y = rng.uniform(grid.y_min_mm + 2 * a, grid.y_max_mm - 2 * a)
        if i >= n_inside:
            side, f = (i - n_inside) % 4, rng.uniform(1.2, 1.7) * a
            x = {0: grid.x_min_mm + f, 1: grid.x_max_mm - f}.get(side, x)
            y = {2: grid.y_min_mm + f, 3: grid.y_max_mm - f}.get(side, y)
        out = sensor.press(ball, ContactPose(x_mm=x, y_mm=y, depth_mm=depth),
                           np.random.default_rng([seed, 1, i]))
        r = out.pose_reached
        frames.append(out.frame)
        truths.append(to_model(np.asarray(out.surface_depth_mm, np.float32)))
        if keep_surfaces:
            surfaces.append(np.asarray(out.surface_depth_mm, np.float32))
        centres.append((r.x_mm, r.y_mm))
        radii.append(a)
        edge.append(i >= n_inside)
    return VirtualPresses(np.stack(frames), np.stack(truths), np.array(centres),
                          np.array(radii), np.array(edge),
                          np.stack(surfaces) if keep_surfaces else None,
                          sensor.renderer.grid if keep_surfaces else None)


def near_contact_errors(depths_mm, presses: VirtualPresses, near_radii: float = 1.5,
                        depth_grid=None) -> dict:
    """Per-press errors (um) of depth maps (N, ny, nx) mm on ``depth_grid`` (default: the model
    grid, 128 x 128) against the truth: ``whole`` and ``near`` RMSE, ``peak`` (signed), each an
    (N,) array."""
    from tactile_deploy.imaging.camera_mapping import OutputGrid

    g = depth_grid or OutputGrid()
    x = g.x_min_mm + (np.arange(g.nx) + 0.5) * g.pitch_x_mm
    y = g.y_max_mm - (np.arange(g.ny) + 0.5) * g.pitch_y_mm
    whole, near, peak = [], [], []
    for d, t, c, a in zip(depths_mm, presses.truths, presses.centres_mm, presses.radii_mm):
        m = np.hypot(x[None, :] - c[0], y[:, None] - c[1]) < near_radii * a
        whole.append(np.sqrt(np.mean((d - t) ** 2)) * 1e3)
        near.append(np.sqrt(np.mean((d[m] - t[m]) ** 2)) * 1e3)
        peak.append((float(d.max()) - float(t.max())) * 1e3)
    return {"whole": np.array(whole), "near": np.array(near), "peak": np.array(peak)}


def oracle_weighted_depths(pipeline, presses: VirtualPresses,
                           floor_slope: float = 0.005) -> np.ndarray:
    """Depth maps (N, 128, 128) float32 mm of ``presses`` through ``pipeline`` (an
    :class:`~tactile_deploy.runtime.pipeline.ImagingPipeline`), its shading gradients integrated
    with a weight per pixel and axis of ``1 / (error^2 + floor_slope^2)``, the error being the
    gradient's difference from the truth's (mm per mm, imaging grid): the most a confidence
    weighting of the integration could gain (an oracle: a calibration cannot know the error).
    """
    from tactile_deploy.imaging.camera_mapping import OutputGrid
    from tactile_deploy.runtime.pipeline import (
        GridResampler,
        apply_noise_reference,
        shading_gradients,
        subtract_reference,
        to_model_grid,
    )

    from .weighted_poisson import integrate_weighted

    to_imaging = GridResampler(OutputGrid(), pipeline.camera.grid)
    s = float(pipeline.tables.mm_per_px)
    out = []
    for frame, truth in zip(presses.frames, presses.truths):
        image = pipeline.rectify(frame)
        g_col, g_row = shading_gradients(subtract_reference(image, pipeline.tables), image,
                                         pipeline.tables)
        t_row, t_col = np.gradient(to_imaging(truth).astype(np.float64), s)
        z = integrate_weighted(g_col * s, g_row * s,
                               1.0 / ((g_col - t_col) ** 2 + floor_slope ** 2),
                               1.0 / ((g_row - t_row) ** 2 + floor_slope ** 2))
        depth = to_model_grid(z.astype(np.float32), pipeline.resampler)
        out.append(apply_noise_reference(depth, pipeline.noise_mm, pipeline.noise_handling))
    return np.stack(out)


@dataclass
class ShapePresses:
    """New presses of library indenters (any shape) of a virtual sensor.

    frames : (N, H, W, 3) uint8 RGB raw camera frames. truths : (N, 128, 128) float32 mm on the
    model grid. names : (N,) indenter names (file stems for mesh files).
    """

    frames: np.ndarray
    truths: np.ndarray
    names: np.ndarray


def virtual_shape_presses(sensor, grid, indenters, n: int = 16, seed: int = 99,
                          depth_range_mm: tuple[float, float] = (0.3, 0.8),
                          depth_grid=None, margin_mm: float = 3.0) -> ShapePresses:
    """``n`` presses of ``indenters`` (library names or mesh files) in turn, any rotation, centres
    at least ``margin_mm`` inside the imaging ``grid``; truths on ``depth_grid`` (default: the
    model grid)."""
    from pathlib import Path

    from tactile_deploy.imaging.camera_mapping import OutputGrid
    from tactile_deploy.indenters import ContactPose
    from tactile_deploy.runtime.pipeline import GridResampler
    from tactile_deploy.simulation.contact import ContactError

    rng = np.random.default_rng([seed, 0x73686170])
    names = [str(i) for i in indenters]
    to_model = GridResampler(sensor.renderer.grid, depth_grid or OutputGrid())
    frames, truths, used = [], [], []
    i = 0
    while len(frames) < n:
        name = names[i % len(names)]
        i += 1
        pose = ContactPose(x_mm=rng.uniform(grid.x_min_mm + margin_mm, grid.x_max_mm - margin_mm),
                           y_mm=rng.uniform(grid.y_min_mm + margin_mm, grid.y_max_mm - margin_mm),
                           theta_deg=rng.uniform(0, 360), depth_mm=rng.uniform(*depth_range_mm))
        try:
            out = sensor.press(name, pose, np.random.default_rng([seed, 1, i]))
        except ContactError:
            continue
        frames.append(out.frame)
        truths.append(to_model(np.asarray(out.surface_depth_mm, np.float32)))
        used.append(Path(name).stem)
    return ShapePresses(np.stack(frames), np.stack(truths), np.array(used))


def view_mask(grid, depth_grid=None) -> np.ndarray:
    """(ny, nx) bool: the cells of ``depth_grid`` (default: the model grid, 128 x 128) whose
    centres the camera's imaging ``grid`` covers (where a read-out can see the surface at all)."""
    from tactile_deploy.imaging.camera_mapping import OutputGrid

    g = depth_grid or OutputGrid()
    x = g.x_min_mm + (np.arange(g.nx) + 0.5) * g.pitch_x_mm
    y = g.y_max_mm - (np.arange(g.ny) + 0.5) * g.pitch_y_mm
    return ((x[None, :] > grid.x_min_mm) & (x[None, :] < grid.x_max_mm)
            & (y[:, None] > grid.y_min_mm) & (y[:, None] < grid.y_max_mm))


def contact_region_errors(depths_mm, truths_mm, threshold_mm: float = 0.01,
                          grow_cells: int = 4, view=None) -> dict:
    """Per-press errors (um) of depth maps (N, 128, 128) mm against true ones where the true
    depth exceeds ``threshold_mm``, grown by ``grow_cells`` cells (the contact and its rim):
    ``region`` RMSE, ``whole`` RMSE and ``peak`` (estimated minus true maximum), each (N,);
    with ``view`` (:func:`view_mask`) also ``region_in_view``, the region's RMSE over the cells
    the camera sees (a contact reaching past the view is unknown there to any read-out)."""
    from scipy import ndimage

    region, in_view, whole, peak = [], [], [], []
    for d, t in zip(depths_mm, truths_mm):
        m = ndimage.binary_dilation(t > threshold_mm, iterations=grow_cells)
        region.append(np.sqrt(np.mean((d[m] - t[m]) ** 2)) * 1e3 if m.any() else np.nan)
        if view is not None:
            mv = m & view
            in_view.append(np.sqrt(np.mean((d[mv] - t[mv]) ** 2)) * 1e3 if mv.any() else np.nan)
        whole.append(np.sqrt(np.mean((d - t) ** 2)) * 1e3)
        peak.append((float(d.max()) - float(t.max())) * 1e3)
    out = {"region": np.array(region), "whole": np.array(whole), "peak": np.array(peak)}
    if view is not None:
        out["region_in_view"] = np.array(in_view)
    return out
