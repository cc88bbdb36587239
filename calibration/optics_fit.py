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
:func:`fit_fots` (``python -m calibration.optics_fit`` writes the fitted model, the comparison
table and ``docs/img/optics_real_vs_sim.png``). Their true surface is not measured; it is built
from the hand-labelled contact circles and the known ball (:func:`sphere_press_surface`): the
ball's sphere cap inside the circle and the gel's sinking around it, whose depth at the rim is
``sinking_scale`` times that of an elastic half-space (Hertz), the value being either derived
from our FEM of a flat pad (:func:`fem_sinking_scale`) or fitted with the optics.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tactile_deploy.imaging.camera_mapping import CameraMapping, pixels_to_sensor_mm
from tactile_deploy.optics.model import Light, OpticsModel, Vignetting, simple_camera
from tactile_deploy.optics.render import albedo_field, shade_points, shading_basis

ROOT = Path(__file__).resolve().parent.parent
#: The real ball presses (FOTS project, MIT licence), beside the checkout.
FOTS_FOLDER = ROOT.parent / "shared" / "data" / "real" / "fots_gelsight_ballpress"
#: Ball radius of the FOTS presses, mm, and their image scale, px per mm.
FOTS_BALL_RADIUS_MM = 2.35
FOTS_PX_PER_MM = 19.58
#: Grey level at or above which a channel counts as saturated.
SATURATED_GREY = 254


class OpticsFitError(ValueError):
    """Fit data or parameter names are not usable (the message says which and why)."""


# ----------------------------------------------------------------------------- parameters
_VECTOR_FIELDS = {"colour_grey": 3, "specular_grey": 3, "position_mm": 3}
_BOUNDS = {
    "azimuth_deg": (-math.inf, math.inf), "elevation_deg": (1.0, 89.0),
    "colour_grey": (0.0, 2000.0), "specular_grey": (0.0, 2000.0), "shininess": (1.0, 500.0),
    "falloff_per_mm": (0.0, 2.0), "position_mm": (-100.0, 100.0), "ambient_grey": (0.0, 255.0),
    "k2": (-1.0, 1.0), "k4": (-1.0, 1.0), "exposure_gain": (0.01, 10.0),
}


def _listify(d: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def _model_doc(model: OpticsModel) -> dict:
    return {
        "lights": [_listify(lt.model_dump()) for lt in model.lights],
        "ambient_grey": list(model.ambient_grey),
        "vignetting": model.vignetting.model_dump(),
        "exposure_gain": model.exposure_gain,
    }


def parameter_paths(model: OpticsModel, names: Sequence[str]) -> list[tuple]:
    """Expand parameter names into scalar paths.

    Names: ``ambient_grey``, ``exposure_gain``, ``vignetting.k2``, ``vignetting.k4``,
    ``lights.<i>.<field>`` or ``lights.*.<field>`` with field one of azimuth_deg, elevation_deg,
    colour_grey, specular_grey, shininess, falloff_per_mm, position_mm (vectors expand to their
    components). Returns paths such as ``("lights", 0, "colour_grey", 2)``.
    """
    doc = _model_doc(model)
    out: list[tuple] = []
    for name in names:
        parts = name.split(".")
        if parts[0] == "lights" and len(parts) == 3:
            idx = range(len(model.lights)) if parts[1] == "*" else [int(parts[1])]
            for i in idx:
                if not 0 <= i < len(model.lights) or parts[2] not in doc["lights"][i]:
                    raise OpticsFitError(f"unknown optics parameter {name!r}")
                n = _VECTOR_FIELDS.get(parts[2], 0)
                out += [("lights", i, parts[2], c) for c in range(n)] if n else [
                    ("lights", i, parts[2])]
        elif name == "ambient_grey":
            out += [("ambient_grey", c) for c in range(3)]
        elif name in ("vignetting.k2", "vignetting.k4"):
            out.append(("vignetting", parts[1]))
        elif name == "exposure_gain":
            out.append(("exposure_gain",))
        else:
            raise OpticsFitError(
                f"unknown optics parameter {name!r}; use ambient_grey, exposure_gain, "
                "vignetting.k2, vignetting.k4 or lights.<i|*>.<field>")
    return out


def _get(doc, path):
    node = doc
    for key in path:
        node = node[key]
    return float(node)


def _set(doc, path, value):
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = float(value)


def parameter_vector(model: OpticsModel, paths: Sequence[tuple]) -> np.ndarray:
    """Current values of ``paths`` (see :func:`parameter_paths`), (p,) float64."""
    doc = _model_doc(model)
    return np.array([_get(doc, p) for p in paths])


def with_parameters(model: OpticsModel, paths: Sequence[tuple], values, validate: bool = False
                    ) -> OpticsModel:
    """A copy of ``model`` with ``paths`` set to ``values`` (validated when ``validate``)."""
    doc = _model_doc(model)
    for p, v in zip(paths, values):
        _set(doc, p, v)
    if validate:
        full = model.model_dump()
        full.update(lights=doc["lights"], ambient_grey=doc["ambient_grey"],
                    vignetting=doc["vignetting"], exposure_gain=doc["exposure_gain"])
        full["camera"] = model.camera  # already validated
        return OpticsModel.model_validate(full)
    tup = {k: tuple(v) if isinstance(v, list) else v for k, v in doc.items()}
    lights = tuple(Light.model_construct(**{k: tuple(v) if isinstance(v, list) else v
                                            for k, v in ld.items()}) for ld in doc["lights"])
    return model.model_copy(update={
        "lights": lights, "ambient_grey": tup["ambient_grey"],
        "vignetting": Vignetting.model_construct(**doc["vignetting"]),
        "exposure_gain": doc["exposure_gain"]})


def parameter_bounds(paths: Sequence[tuple]) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = [], []
    for p in paths:
        key = p[2] if p[0] == "lights" else (p[1] if p[0] == "vignetting" else p[0])
        b = _BOUNDS[key]
        if key == "position_mm" and p[3] == 2:
            b = (-100.0, -0.1)  # point lights stay below the sensing surface
        lo.append(b[0])
        hi.append(b[1])
    return np.array(lo), np.array(hi)


def normalise_model(model: OpticsModel) -> OpticsModel:
    """Azimuths wrapped into [0, 360) degrees (the fit leaves them unbounded); validated."""
    lights = tuple(lt.model_copy(update={"azimuth_deg": float(lt.azimuth_deg % 360.0)})
                   for lt in model.lights)
    doc = model.model_dump()
    doc["lights"] = [lt.model_dump() for lt in lights]
    doc["camera"] = model.camera
    return OpticsModel.model_validate(doc)


# ----------------------------------------------------------------------------------- data
@dataclass
class ShadingSamples:
    """Sampled camera pixels with their true surface and observed colour.

    uv_px : (k, 2) raw px; xy_mm : (k, 2) sensor-frame points at rest, mm; z_mm, fx, fy : (k,)
    surface height (mm) and slopes there; observed : (k, 3) float64 grey levels (RGB);
    frame : (k,) int, index of the frame each sample comes from; far : (k,) bool, far-field
    pixels used for the per-frame offsets; weight : (k,) float, least-squares weight.
    """

    uv_px: np.ndarray
    xy_mm: np.ndarray
    z_mm: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    observed: np.ndarray
    frame: np.ndarray
    far: np.ndarray
    weight: np.ndarray
    circle_mm: np.ndarray | None = None
    albedo: np.ndarray | None = None

    def __post_init__(self):
        k = len(self.uv_px)
        for name in ("xy_mm", "z_mm", "fx", "fy", "observed", "frame", "far", "weight"):
            arr = getattr(self, name)
            if len(arr) != k:
                raise OpticsFitError(f"ShadingSamples.{name} has {len(arr)} rows, expected {k}")
        if k == 0:
            raise OpticsFitError("no samples to fit")

    @staticmethod
    def concatenate(parts: Sequence[ShadingSamples]) -> ShadingSamples:
        names = ("uv_px", "xy_mm", "z_mm", "fx", "fy", "observed", "frame", "far", "weight")
        out = ShadingSamples(*(np.concatenate([getattr(p, n) for p in parts]) for n in names))
        if all(p.circle_mm is not None for p in parts):
            out.circle_mm = np.concatenate([p.circle_mm for p in parts])
        return out

    def press_surface(self, sinking_scale: float, ball_radius_mm: float,
                      radius_scale: float = 1.0):
        """``(z, fx, fy)`` of every sample from ``circle_mm`` (:func:`sphere_press_surface`),
        with every contact radius multiplied by ``radius_scale``."""
        z = np.zeros(len(self.z_mm))
        fx, fy = z.copy(), z.copy()
        c = self.circle_mm
        for key in np.unique(c[np.isfinite(c[:, 2])], axis=0):
            sel = np.all(c == key, axis=1)
            a = min(key[2] * radius_scale, 0.98 * ball_radius_mm)
            z[sel], fx[sel], fy[sel] = sphere_press_surface(self.xy_mm[sel], key[:2], a,
                                                            ball_radius_mm, sinking_scale)
        return z, fx, fy


def usable(observed: np.ndarray) -> np.ndarray:
    """(k,) bool: no channel saturated."""
    return np.all(observed < SATURATED_GREY, axis=1)


def frame_offsets(residual: np.ndarray, frame: np.ndarray, far: np.ndarray,
                  n_frames: int) -> np.ndarray:
    """Per-frame, per-channel mean residual over far-field samples: (n_frames, 3) grey levels."""
    out = np.zeros((n_frames, 3))
    for f in range(n_frames):
        sel = (frame == f) & far
        if np.any(sel):
            out[f] = residual[sel].mean(axis=0)
    return out


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


# ------------------------------------------------------------------------------ ball press
def hertz_exterior_shape(r_mm: np.ndarray, a_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Shape of the Hertz (half-space) surface outside a contact of radius a, normalised to 1
    at the rim, and its radial derivative (1/mm): ``phi(r) = u(r) / u(a)`` with
    ``u(r) = (2 a^2 - r^2) asin(a / r) + a sqrt(r^2 - a^2)`` (Johnson, Contact Mechanics, 3.42).
    Valid for r >= a."""
    r = np.maximum(np.asarray(r_mm, np.float64), a_mm)
    root = np.sqrt(np.maximum(r * r - a_mm * a_mm, 0.0))
    asn = np.arcsin(np.clip(a_mm / r, -1.0, 1.0))
    u = (2 * a_mm**2 - r * r) * asn + a_mm * root
    du = -2.0 * r * asn + 2.0 * a_mm * root / r
    ua = 0.5 * math.pi * a_mm**2
    return u / ua, du / ua


def sphere_press_surface(xy_mm: np.ndarray, centre_mm, a_mm: float, ball_radius_mm: float,
                         sinking_scale: float):
    """Surface of a gel pressed by a ball whose contact circle has radius ``a_mm``.

    Inside the circle the gel follows the ball (sphere cap); outside it sinks like the exterior
    of a Hertz contact, with the sinking at the rim ``w_a = sinking_scale * a^2 / (2 R)``
    (``sinking_scale = 1``: elastic half-space, C1 at the rim; 0: no sinking). Tip depth
    ``d = R - sqrt(R^2 - a^2) + w_a``.

    xy_mm : (k, 2) sensor frame. Returns ``(z, dz/dx, dz/dy)``, each (k,) float64 (mm, -, -),
    z = 0 far away, negative pushed in.
    """
    big = float(ball_radius_mm)
    if not 0 < a_mm < big:
        raise OpticsFitError(f"contact radius a_mm={a_mm} must lie in (0, {big}) (ball radius)")
    d = np.asarray(xy_mm, np.float64) - np.asarray(centre_mm, np.float64)
    r = np.hypot(d[:, 0], d[:, 1])
    w_a = sinking_scale * a_mm**2 / (2.0 * big)
    cap_a = big - math.sqrt(big**2 - a_mm**2)
    depth = cap_a + w_a
    inside = r <= a_mm
    rin = np.minimum(r, a_mm)
    root = np.sqrt(big**2 - rin * rin)
    phi, dphi = hertz_exterior_shape(r, a_mm)
    z = np.where(inside, -(depth - (big - root)), -w_a * phi)
    dz_dr = np.where(inside, rin / root, -w_a * dphi)
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(r > 0, d[:, 0] / r, 0.0)
        uy = np.where(r > 0, d[:, 1] / r, 0.0)
    return z, dz_dr * ux, dz_dr * uy


def fem_sinking_scale(depths_mm=(0.6, 0.9, 1.2), ball_radius_mm: float = FOTS_BALL_RADIUS_MM,
                      nu: float = 0.48) -> dict:
    """The sinking around a pressed ball on our flat 3 mm pad, as a ``sinking_scale``.

    For each tip depth, the FEM solution (frictionless, ``nu``) at the sensing nodes is fitted by
    :func:`sphere_press_surface` with the contact radius and the sinking scale free (least
    squares on the nodal heights, nodes within 3 ball radii). Returns the per-depth fits and
    their median scale.
    """
    from scipy.optimize import least_squares

    from tactile_deploy.fem.material import Material
    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.simulation.contact import get_simulator

    sim = get_simulator(Material(nu=nu))
    ball = AnalyticSphere(ball_radius_mm)
    xy = sim.mesh.vertices[sim.mesh.sensing_nodes, :2]
    near = np.hypot(xy[:, 0], xy[:, 1]) < 3.0 * ball_radius_mm
    fits = []
    for d in depths_mm:
        res = sim.solve(ball, ContactPose(depth_mm=float(d)))
        uz = res.displacements_mm[sim.mesh.sensing_nodes, 2][near]

        def resid(p, uz=uz):
            a, s = p
            z, _, _ = sphere_press_surface(xy[near], (0.0, 0.0), a, ball_radius_mm, s)
            return z - uz

        a0 = math.sqrt(ball_radius_mm * d) * 0.9
        sol = least_squares(resid, [min(a0, 0.95 * ball_radius_mm), 0.5],
                            bounds=([0.05, 0.0], [0.99 * ball_radius_mm, 3.0]))
        a, s = sol.x
        fits.append({"depth_mm": float(d), "contact_radius_mm": float(a), "sinking_scale":
                     float(s), "rms_um": float(1e3 * np.sqrt(np.mean(sol.fun**2)))})
    return {"fits": fits, "sinking_scale": float(np.median([f["sinking_scale"] for f in fits]))}


# ------------------------------------------------------------------------------ FOTS data
@dataclass
class PressFrames:
    """Ball presses of one sensor: ``reference`` (H, W, 3) uint8 RGB, ``frames`` (N, H, W, 3)
    uint8 RGB, ``names``, ``circles`` (N, 3) px (column, row, contact radius)."""

    reference: np.ndarray
    frames: np.ndarray
    names: list[str]
    circles: np.ndarray


def read_rgb(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise OpticsFitError(f"{path}: missing or not a readable image")
    return np.ascontiguousarray(img[..., ::-1])


def load_fots(folder: Path = FOTS_FOLDER) -> PressFrames:
    """The FOTS ball presses: background.png, NNNN.png and annotate.csv (circles in px)."""
    folder = Path(folder)
    ann = folder / "annotate.csv"
    if not ann.is_file():
        raise OpticsFitError(f"{ann} not found: the real ball presses must be in {folder} "
                             "(../shared/data beside the checkout)")
    names, circles = [], []
    with open(ann, newline="", encoding="utf-8") as f:
        for line, row in enumerate(csv.DictReader(f), start=2):
            try:
                circles.append([float(row["center_x"]), float(row["center_y"]),
                                float(row["radius"])])
            except (KeyError, TypeError, ValueError):
                raise OpticsFitError(f"{ann}, line {line}: expected numeric center_x, center_y, "
                                     f"radius (px), got {row}") from None
            names.append(row["img_names"].strip())
    reference = read_rgb(folder / "background.png")
    frames = np.stack([read_rgb(folder / n) for n in names])
    if frames.shape[1:] != reference.shape:
        raise OpticsFitError(f"{folder}: press frames are {frames.shape[1:]}, the background "
                             f"{reference.shape}")
    return PressFrames(reference, frames, names, np.array(circles))


def fots_camera(width_px: int = 240, height_px: int = 320) -> CameraMapping:
    """The FOTS sensor's camera: 19.58 px/mm, image centre over the sensor origin, columns
    along +x, rows along -y, no lens distortion (the frames are already rectified)."""
    return simple_camera(width_px, height_px, 1.0 / FOTS_PX_PER_MM)


def press_samples(press: PressFrames, camera: CameraMapping, indices: Sequence[int], *,
                  sinking_scale: float, stride: int = 3, near_factor: float = 3.0,
                  near_stride: int = 1, include_reference: bool = True,
                  far_factor: float = 3.5, ball_radius_mm: float = FOTS_BALL_RADIUS_MM
                  ) -> ShadingSamples:
    """Samples of the presses ``indices`` (and the reference frame as a flat surface, frame 0).

    Contact circles (px) become mm with the camera's mean mm per px at the image centre (a
    distortion-free camera looking straight at the pad, as for the FOTS frames).
    Every ``stride``-th pixel (rows and columns) of each frame, and every ``near_stride``-th
    pixel within ``near_factor`` contact radii of the circle's centre; weights make every
    sample stand for the pixel area it represents. Far-field pixels (for the per-frame offsets):
    beyond ``far_factor`` contact radii.
    """
    h, w = press.reference.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    uv_all = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    xy_all = pixels_to_sensor_mm(uv_all, camera)
    scale = 0.5 * (camera.mm_per_px_x + camera.mm_per_px_y)  # contact radius px -> mm
    grid_sel = ((v % stride == 0) & (u % stride == 0)).ravel()
    near_grid = ((v % near_stride == 0) & (u % near_stride == 0)).ravel()
    parts = []
    items = [(-1, None)] if include_reference else []
    items += [(int(i), press.circles[int(i)]) for i in indices]
    for f, (i, circle) in enumerate(items):
        frame = press.reference if i < 0 else press.frames[i]
        obs = frame.reshape(-1, 3).astype(np.float64)
        if circle is None:
            sel = grid_sel
            z = fx = fy = np.zeros(int(sel.sum()))
            far = np.ones(int(sel.sum()), bool)
            weight = np.full(int(sel.sum()), float(stride * stride))
        else:
            cu, cv, rp = circle
            dist = np.hypot(uv_all[:, 0] - cu, uv_all[:, 1] - cv)
            near = (dist <= near_factor * rp) & near_grid
            sel = grid_sel | near
            centre = pixels_to_sensor_mm(np.array([[cu, cv]]), camera)[0]
            z, fx, fy = sphere_press_surface(xy_all[sel], centre, rp * scale,
                                             ball_radius_mm, sinking_scale)
            far = dist[sel] > far_factor * rp
            weight = np.where(near[sel], float(near_stride**2), float(stride * stride))
        part = ShadingSamples(uv_all[sel], xy_all[sel], z, fx, fy, obs[sel],
                              np.full(int(sel.sum()), f), far, weight)
        circ = [np.nan] * 3 if circle is None else [*centre, circle[2] * scale]
        part.circle_mm = np.tile(np.array(circ, float), (len(z), 1))
        parts.append(part)
    return ShadingSamples.concatenate(parts)


def fots_initial_model(camera: CameraMapping | None = None) -> OpticsModel:
    """Starting point of the FOTS fit: red light from +y, green from -y, blue from -x (as the
    colour changes around a press show), 30 degrees elevation, neutral ambient."""
    cam = camera or fots_camera()
    lights = (
        Light(name="red", azimuth_deg=90.0, elevation_deg=30.0, colour_grey=(120.0, 30.0, 30.0)),
        Light(name="green", azimuth_deg=270.0, elevation_deg=30.0, colour_grey=(30.0, 120.0, 30.0)),
        Light(name="blue", azimuth_deg=180.0, elevation_deg=30.0, colour_grey=(30.0, 30.0, 120.0)),
    )
    return OpticsModel(camera=cam, lights=lights, ambient_grey=(80.0, 80.0, 100.0))


FOTS_FREE = ("ambient_grey", "vignetting.k2", "lights.*.azimuth_deg", "lights.*.elevation_deg",
             "lights.*.colour_grey", "lights.*.falloff_per_mm")


# --------------------------------------------------------------------------- FOTS report
#: Presses the FOTS fit trains on (every fourth); the others are held out.
FOTS_TRAIN = tuple(range(0, 42, 4))


@dataclass
class FotsReport:
    """Outcome of :func:`fit_fots`: the fitted model, the surface parameter, error figures."""

    model: OpticsModel
    sinking_scale: float
    fem: dict
    rows: dict
    train: list[int]
    test: list[int]
    fit: OpticsFit


def _held_out_errors(model: OpticsModel, press: PressFrames, camera, test, sinking_scale):
    """Per-channel RMSE (grey) on the held-out presses: whole frame and within 2 contact radii,
    for the model, the model added to the real reference frame (difference mode) and the real
    reference frame alone (baseline). Per-frame offsets from the far field (> 3.5 radii)."""
    s = press_samples(press, camera, test, sinking_scale=sinking_scale, stride=1,
                      near_factor=2.0, include_reference=False)
    flat = ShadingSamples(s.uv_px, s.xy_mm, np.zeros_like(s.z_mm), np.zeros_like(s.fx),
                          np.zeros_like(s.fy), s.observed, s.frame, s.far, s.weight)
    pred = predict(model, s)
    pred_flat = predict(model, flat)
    _h, w = press.reference.shape[:2]
    idx = (s.uv_px[:, 1] * w + s.uv_px[:, 0]).astype(int)
    ref = press.reference.reshape(-1, 3).astype(np.float64)[idx]
    ok = usable(s.observed)
    circles = press.circles[np.asarray(test)][s.frame]
    near = np.hypot(*(s.uv_px - circles[:, :2]).T) < 2.0 * circles[:, 2]
    out = {}
    for name, p in (("model", pred), ("model on real reference", ref + pred - pred_flat),
                    ("real reference only (baseline)", ref)):
        r = p - s.observed
        off = frame_offsets(r[ok], s.frame[ok], s.far[ok], len(test))
        r = r - off[s.frame]
        out[name] = {
            "frame_rmse_grey": [float(v) for v in np.sqrt((r[ok] ** 2).mean(axis=0))],
            "contact_rmse_grey": [float(v) for v in np.sqrt((r[ok & near] ** 2).mean(axis=0))],
        }
    return out


def fit_fots(press: PressFrames | None = None, train: Sequence[int] = FOTS_TRAIN,
             max_evaluations: int = 400) -> FotsReport:
    """Fit the optics of the FOTS sensor on ``train`` presses (+ its reference frame), with the
    sinking scale of the true surface free, and evaluate on the other presses; also with the
    sinking scale fixed to our FEM's value."""
    press = press or load_fots()
    camera = fots_camera(press.reference.shape[1], press.reference.shape[0])
    test = [i for i in range(len(press.frames)) if i not in set(train)]
    model0 = fots_initial_model(camera)
    samples = press_samples(press, camera, train, sinking_scale=1.0, stride=6, near_factor=2.5,
                            near_stride=3)
    surf = SurfaceParameters(["sinking_scale"], np.array([1.0]), np.array([0.0]),
                             np.array([4.0]),
                             lambda x: samples.press_surface(float(x[0]), FOTS_BALL_RADIUS_MM))
    fit = fit_optics(model0, samples, FOTS_FREE, surface=surf, max_evaluations=max_evaluations)
    scale = fit.extra["sinking_scale"]
    rows = {f"{k} (fitted sinking {scale:.2f})": v for k, v in
            _held_out_errors(fit.model, press, camera, test, scale).items()}
    fem = fem_sinking_scale()
    s_fem = press_samples(press, camera, train, sinking_scale=fem["sinking_scale"], stride=6,
                          near_factor=2.5, near_stride=3)
    fit_fem = fit_optics(model0, s_fem, FOTS_FREE, max_evaluations=max_evaluations)
    rows[f"model (FEM sinking {fem['sinking_scale']:.2f})"] = _held_out_errors(
        fit_fem.model, press, camera, test, fem["sinking_scale"])["model"]
    return FotsReport(fit.model, scale, fem, rows, list(train), test, fit)


def markdown_table(report: FotsReport) -> str:
    lines = [("| prediction of the held-out presses | RMSE whole frame R / G / B | "
             "RMSE within 2 contact radii R / G / B |"), "|---|---|---|"]
    for name, v in report.rows.items():
        f = " / ".join(f"{x:.1f}" for x in v["frame_rmse_grey"])
        c = " / ".join(f"{x:.1f}" for x in v["contact_rmse_grey"])
        lines.append(f"| {name} | {f} | {c} |")
    return "\n".join(lines)


def fots_figure(report: FotsReport, press: PressFrames, path: Path, show=(1, 5, 13)) -> None:
    """Side by side: real held-out presses, simulated (fitted optics, renderer), difference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tactile_deploy.atomic import atomic_path
    from tactile_deploy.optics.render import OpticsRenderer, grid_centres

    model = report.model
    renderer = OpticsRenderer(model)
    x, y = grid_centres(renderer.grid)
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    picks = [report.test[i] for i in show if i < len(report.test)]
    fig, axes = plt.subplots(3, len(picks) + 1, figsize=(2.6 * (len(picks) + 1), 9.6))
    cols = [("reference", None)] + [(press.names[i], i) for i in picks]
    for k, (name, i) in enumerate(cols):
        real = press.reference if i is None else press.frames[i]
        if i is None:
            height = renderer.flat_height()
        else:
            cu, cv, rp = press.circles[i]
            centre = pixels_to_sensor_mm(np.array([[cu, cv]]), model.camera)[0]
            z, _, _ = sphere_press_surface(xy, centre, rp / FOTS_PX_PER_MM, FOTS_BALL_RADIUS_MM,
                                           report.sinking_scale)
            height = z.reshape(x.shape).astype(np.float32)
        sim = renderer.render(height)
        # Same per-frame drift correction as the error figures (far field, > 3.5 radii).
        diff = real.astype(np.float64) - sim
        if i is not None:
            vv, uu = np.mgrid[0:real.shape[0], 0:real.shape[1]]
            far = np.hypot(uu - cu, vv - cv) > 3.5 * rp
            sim = np.clip(sim + diff[far].mean(axis=0), 0, 255).astype(np.uint8)
            diff = real.astype(np.float64) - sim
        rmse = np.sqrt((diff**2).mean(axis=(0, 1)))
        axes[0, k].imshow(real)
        axes[0, k].set_title(f"real {name}", fontsize=8)
        axes[1, k].imshow(sim)
        axes[1, k].set_title("simulated", fontsize=8)
        axes[2, k].imshow(np.clip(128 + 2 * diff, 0, 255).astype(np.uint8))
        axes[2, k].set_title("2 x (real - sim) + 128\nRMSE R/G/B " +
                             "/".join(f"{v:.1f}" for v in rmse), fontsize=8)
        for a in axes[:, k]:
            a.set_xticks([])
            a.set_yticks([])
    fig.suptitle("FOTS GelSight ball presses (held out) vs the fitted optics model", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def fots_sensor_config(report: FotsReport):
    """The ``gelsight_fots`` virtual sensor: the fitted optics with assumed sensor noise, a
    domed gel and the large-deformation effects that set it apart from the GelSlim units."""
    from tactile_deploy.optics.model import SensorNoise
    from tactile_deploy.sensors.config import EffectSpec, VirtualSensorConfig

    optics = report.model.model_copy(update={
        "noise": SensorNoise(read_noise_grey=1.5, conversion_gain_grey_per_e=0.03),
        "blur_sigma_px": 0.5})
    optics = OpticsModel.model_validate(optics.model_dump() | {"camera": optics.camera})
    return VirtualSensorConfig(
        name="gelsight_fots", family="gelsight",
        description=("GelSight-class sensor fitted to the real FOTS ball presses: 240 x 320 px "
                     "portrait frames at 19.58 px/mm, three directional RGB lights from the fit "
                     f"(sinking scale {report.sinking_scale:.2f}), assumed noise; a 0.3 mm dome "
                     "and over-exposure set it apart from the GelSlim units."),
        optics=optics, fps=30.0, seed=3,
        effects=(EffectSpec(name="dome", params={"height_mm": 0.3}),
                 EffectSpec(name="saturation", params={"exposure_factor": 1.15})))


def main(argv=None) -> int:
    import argparse

    from tactile_deploy.sensors.config import SENSOR_DIR, save_sensor_config

    ap = argparse.ArgumentParser(description="Fit the optics model to the real FOTS presses.")
    ap.add_argument("--figure", type=Path, default=ROOT / "docs" / "img" /
                    "optics_real_vs_sim.png")
    ap.add_argument("--sensor", type=Path, default=SENSOR_DIR / "gelsight_fots.json",
                    help="where to write the gelsight_fots virtual sensor")
    ap.add_argument("--no-write", action="store_true", help="print the figures only")
    args = ap.parse_args(argv)
    press = load_fots()
    report = fit_fots(press)
    print(markdown_table(report))
    print(json.dumps({"sinking_scale": report.sinking_scale, "fem": report.fem,
                      "train": report.train, "n_samples": report.fit.n_samples,
                      "evaluations": report.fit.n_evaluations,
                      "train_rmse_grey": report.fit.rmse_grey,
                      "lights": [lt.model_dump() for lt in report.model.lights],
                      "ambient_grey": report.model.ambient_grey,
                      "vignetting": report.model.vignetting.model_dump()}, indent=1))
    if not args.no_write:
        fots_figure(report, press, args.figure)
        save_sensor_config(fots_sensor_config(report), args.sensor)
        print(f"wrote {args.figure} and {args.sensor}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
