"""The fit: bounded nonlinear least squares (``scipy.optimize.least_squares``, trust-region
reflective) of the chosen free parameters on the grey levels of the samples, every other
parameter held at the starting model's value; linear parameters solved in closed form."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from tactile_deploy.calibration.optics_fit.parameters import (
    normalise_model,
    parameter_bounds,
    parameter_paths,
    parameter_vector,
    with_parameters,
)
from tactile_deploy.calibration.optics_fit.samples import ShadingSamples, usable
from tactile_deploy.optics.model import OpticsModel
from tactile_deploy.optics.render import albedo_field, shade_points, shading_basis


@dataclass
class OpticsFit:
    """Result of :func:`fit_optics`."""

    model: OpticsModel
    free: list[str]
    rmse_grey: tuple[float, float, float]
    offsets_grey: np.ndarray
    n_samples: int
    n_evaluations: int
    success: bool
    message: str = ""
    extra: dict = field(default_factory=dict)

def predict(model: OpticsModel, s: ShadingSamples) -> np.ndarray:
    """Model radiance at the samples, (k, 3) float64 grey levels (no noise, no rounding)."""
    if s.albedo is None:
        s.albedo = albedo_field(model, s.xy_mm)
    return shade_points(model, s.uv_px, s.xy_mm, s.z_mm, s.fx, s.fy, albedo=s.albedo)

def _is_linear(path: tuple) -> bool:
    return path[0] == "ambient_grey" or (path[0] == "lights" and path[2] in ("colour_grey",
                                                                             "specular_grey"))

def _linear_solve(model: OpticsModel, s: ShadingSamples, lin_paths, n_frames: int,
                  offsets_on: bool):
    """Best linear parameters (colours, ambient) and frame offsets for fixed geometry.

    Returns ``(values (len(lin_paths),), offsets (n_frames, 3), residual (k, 3))``; colours and
    ambient are kept >= 0, frame 0's offset is 0 (it sets the grey scale).
    """
    from scipy.optimize import lsq_linear

    gain, diffuse, specular = shading_basis(model, s.uv_px, s.xy_mm, s.z_mm, s.fx, s.fy,
                                            albedo=s.albedo)
    pred_fixed = shade_points_from_basis(model, gain, diffuse, specular, exclude=lin_paths)
    sw = np.sqrt(s.weight)
    values = np.zeros(len(lin_paths))
    offsets = np.zeros((n_frames, 3))
    resid = np.empty_like(s.observed)
    frames = np.arange(1, n_frames) if offsets_on else np.arange(0)
    ind = (s.frame[:, None] == frames[None, :]).astype(np.float64)
    for c in range(3):
        cols, which = [], []
        for j, p in enumerate(lin_paths):
            if p[0] == "ambient_grey" and p[1] == c:
                cols.append(gain)
                which.append(j)
            elif p[0] == "lights" and p[3] == c:
                cols.append((diffuse if p[2] == "colour_grey" else specular)[:, p[1]])
                which.append(j)
        a = np.column_stack(cols + [ind]) if (cols or len(frames)) else np.zeros((len(gain), 0))
        b = s.observed[:, c] - pred_fixed[:, c]
        if a.shape[1]:
            # Reduced problem with the same minimiser: R x ~ R^-T A'b, R'R = A'A (Cholesky).
            aw = a * sw[:, None]
            gram = aw.T @ aw
            gram[np.diag_indices_from(gram)] += 1e-9 * np.trace(gram) / len(gram)
            r = np.linalg.cholesky(gram).T
            rhs = np.linalg.solve(r.T, aw.T @ (b * sw))
            lo = np.r_[np.zeros(len(cols)), np.full(len(frames), -np.inf)]
            hi = np.full(a.shape[1], np.inf)
            sol = lsq_linear(r, rhs, bounds=(lo, hi), method="bvls").x
            values[which] = sol[: len(cols)]
            offsets[frames, c] = sol[len(cols):]
            resid[:, c] = a @ sol - b
        else:
            resid[:, c] = -b
    return values, offsets, resid

def shade_points_from_basis(model: OpticsModel, gain, diffuse, specular, exclude=()):
    """Radiance (k, 3) from :func:`shading_basis` terms, leaving out the linear parameters in
    ``exclude`` (paths of :func:`parameter_paths`)."""
    amb = np.array(model.ambient_grey, float)
    col = np.array([lt.colour_grey for lt in model.lights], float)
    spec = np.array([lt.specular_grey for lt in model.lights], float)
    for p in exclude:
        if p[0] == "ambient_grey":
            amb[p[1]] = 0.0
        elif p[2] == "colour_grey":
            col[p[1], p[3]] = 0.0
        else:
            spec[p[1], p[3]] = 0.0
    return gain[:, None] * amb + diffuse @ col + specular @ spec

@dataclass
class SurfaceParameters:
    """Nonlinear parameters of the true surface fitted together with the optics.

    names : their names; x0, lower, upper : (q,) start and bounds; surface(x) -> (z, fx, fy),
    each (k,) for the samples (in their order, before saturated samples are dropped).
    """

    names: list[str]
    x0: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    surface: object

def fit_optics(model0: OpticsModel, samples: ShadingSamples, free: Sequence[str], *,
               frame_offsets_on: bool = True, max_evaluations: int = 400,
               surface: SurfaceParameters | None = None) -> OpticsFit:
    """Least-squares fit of the ``free`` parameters of ``model0`` to ``samples``.

    Variable projection: the radiance is linear in the colours (``colour_grey``,
    ``specular_grey``) and ``ambient_grey``, and in the per-frame offsets; for every trial of the
    other (nonlinear) parameters those are solved exactly by bounded linear least squares
    (colours and ambient >= 0), and ``scipy.optimize.least_squares`` searches the nonlinear
    ones only. Frame 0 of the samples sets the grey scale (offset 0). With ``surface``, the
    true surface has free parameters of its own, searched with the nonlinear optics parameters
    (reported in ``OpticsFit.extra``).
    """
    from scipy.optimize import least_squares

    keep = usable(samples.observed)
    s = ShadingSamples(*(getattr(samples, n)[keep] for n in (
        "uv_px", "xy_mm", "z_mm", "fx", "fy", "observed", "frame", "far", "weight")))
    s.albedo = albedo_field(model0, s.xy_mm)
    n_frames = int(s.frame.max()) + 1
    paths = parameter_paths(model0, free)
    lin = [p for p in paths if _is_linear(p)]
    nonlin = [p for p in paths if not _is_linear(p)]
    sw = np.sqrt(s.weight)[:, None]
    evaluations = [0]
    n_opt = len(nonlin)

    def solve(x):
        m = with_parameters(model0, nonlin, x[:n_opt]) if nonlin else model0
        if surface is not None:
            z, fx, fy = surface.surface(x[n_opt:])
            s.z_mm, s.fx, s.fy = z[keep], fx[keep], fy[keep]
        values, offs, r = _linear_solve(m, s, lin, n_frames, frame_offsets_on)
        evaluations[0] += 1
        return m, values, offs, r

    message, success = "linear parameters only", True
    if nonlin or surface is not None:
        x0 = parameter_vector(model0, nonlin)
        lo, hi = parameter_bounds(nonlin)
        if surface is not None:
            x0 = np.r_[x0, surface.x0]
            lo, hi = np.r_[lo, surface.lower], np.r_[hi, surface.upper]
        x0 = np.clip(x0, lo, hi)
        sol = least_squares(lambda x: (solve(x)[3] * sw).ravel(), x0, bounds=(lo, hi),
                            x_scale="jac", max_nfev=max_evaluations, method="trf")
        x = sol.x
        message, success = str(sol.message), bool(sol.success)
    else:
        x = np.zeros(0)
    m, values, offs, r = solve(x)
    model = normalise_model(with_parameters(m, lin, values, validate=True))
    rmse = tuple(float(v) for v in np.sqrt(np.average(r**2, axis=0, weights=s.weight)))
    extra = {} if surface is None else dict(zip(surface.names, (float(v) for v in x[n_opt:])))
    return OpticsFit(model, list(free), rmse, offs, len(s.z_mm), evaluations[0], success,
                     message, extra)
