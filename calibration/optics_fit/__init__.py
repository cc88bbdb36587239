"""Fit the parameters of an RGB optics model to camera frames of surfaces of known shape.

Model: :class:`tactile_deploy.optics.OpticsModel`, evaluated by
:func:`tactile_deploy.optics.render.shade_points` at sampled camera pixels. Data: frames, and for
every sampled pixel the true surface there (height z, slopes dz/dx, dz/dy, sensor frame). Fit:
bounded nonlinear least squares (``scipy.optimize.least_squares``, trust-region reflective) on the
grey levels of the chosen free parameters, every other parameter held at the starting model's
value. Saturated pixels (any channel >= 254) are left out: they only say "at least".

Per-frame drift: real sensors drift by tens of grey levels between frames (LED warm-up,
auto-exposure). With ``frame_offsets=True`` each frame gets a per-channel grey-level offset,
solved in closed form at every step as the mean residual over that frame's far-field pixels
(``ShadingSamples.far``, away from any contact); the offsets are reported, not part of the model.

The real GelSight-class presses in ``../shared/data/real/fots_gelsight_ballpress`` are fitted by
:func:`fit_fots` (``python -m tactile_deploy.calibration.optics_fit`` writes the fitted model, the comparison
table and ``docs/img/optics_real_vs_sim.png``). Their true surface is not measured; it is built
from the hand-labelled contact circles and the known ball (:func:`sphere_press_surface`): the
ball's sphere cap inside the circle and the gel's sinking around it, whose depth at the rim is
``sinking_scale`` times that of an elastic half-space (Hertz), the value being either derived
from our FEM of a flat pad (:func:`fem_sinking_scale`) or fitted with the optics.

Modules: :mod:`.parameters` (free parameters by name, bounds), :mod:`.samples` (sampled pixels
and their true surface), :mod:`.press_surface` (the surface of a ball press), :mod:`.fit`
(:func:`fit_optics`), :mod:`.fots` (the real FOTS presses and :func:`fit_fots`).
"""

from __future__ import annotations

from tactile_deploy.calibration.optics_fit.fit import OpticsFit, SurfaceParameters, fit_optics, predict
from tactile_deploy.calibration.optics_fit.fots import (
    FOTS_BALL_RADIUS_MM,
    FOTS_FOLDER,
    FOTS_PX_PER_MM,
    FotsReport,
    PressFrames,
    fem_sinking_scale,
    fit_fots,
    fots_camera,
    fots_initial_model,
    load_fots,
    press_samples,
)
from tactile_deploy.calibration.optics_fit.parameters import (
    OpticsFitError,
    parameter_bounds,
    parameter_paths,
    parameter_vector,
    with_parameters,
)
from tactile_deploy.calibration.optics_fit.press_surface import hertz_exterior_shape, sphere_press_surface
from tactile_deploy.calibration.optics_fit.samples import SATURATED_GREY, ShadingSamples, frame_offsets, usable

__all__ = [
    "FOTS_BALL_RADIUS_MM", "FOTS_FOLDER", "FOTS_PX_PER_MM", "SATURATED_GREY", "FotsReport",
    "OpticsFit", "OpticsFitError", "PressFrames", "ShadingSamples", "SurfaceParameters",
    "fem_sinking_scale", "fit_fots", "fit_optics", "fots_camera", "fots_initial_model",
    "frame_offsets", "hertz_exterior_shape", "load_fots", "parameter_bounds", "parameter_paths",
    "parameter_vector", "predict", "press_samples", "sphere_press_surface", "usable",
    "with_parameters",
]
