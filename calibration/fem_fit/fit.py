"""Fit the FEM's material parameters (nu, E, friction law) to measured contacts.

Data flow of :func:`fit_fem_parameters`::

    measured depth maps (+ forces, + commanded contacts when known)
      -> contact of each map: given, or estimated (maximum-displacement point, refined by fitting)
      -> nu: minimise the depth-map gap between measurement and simulation
             (cross-entropy search as in the paper, or bounded Brent search: it is 1-D)
      -> contacts re-estimated at that nu, nu refitted
      -> E from the forces: closed-form least squares (forces scale with E, displacements do not)
      -> friction law: the fit repeated with sticking contact, compared against the noise
      -> bootstrap over contacts: standard errors and identifiability verdicts

What is identifiable: under displacement control the displacement field does not depend on E, so
**E is not identifiable from depth maps alone**: it comes from measured forces, and without them
the result says so. nu changes how the gel bulges around a contact and is identified from depth
maps. A finite Coulomb mu is not part of the model (frictionless or sticking contact); the fit
reports which law the data prefers and whether the difference rises above the noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, optimize

from tactile_deploy.calibration.fem_fit.operator_bank import OperatorBank
from tactile_deploy.camera.depth import DepthCamera
from tactile_deploy.indenters import ContactPose, get_indenter


@dataclass
class MatchedContact:
    """One measured contact.

    depth_mm : (H, W) float, mm pushed in, on the camera's grid (row 0 = largest y)
    indenter : library name or mesh path
    pose : the commanded contact, or None (estimated from the map)
    force_n : measured total normal force (N), or None
    """

    depth_mm: np.ndarray
    indenter: str
    pose: ContactPose | None = None
    force_n: float | None = None


@dataclass
class FemFitResult:
    nu: float
    nu_std: float
    E_mpa: float | None
    E_std_mpa: float | None
    E_note: str
    friction: str
    friction_note: str
    method: str
    evaluations: int
    rmse_mm: float  # depth-map gap at the optimum, over pad pixels
    poses: list[ContactPose] = field(default_factory=list)
    nu_note: str = ""
    depth_offset_mm: float | None = None  # fitted offset of the given contacts' depths, mm
    objective_curve: list[tuple[float, float]] = field(default_factory=list)


def render_contact(bank: OperatorBank, nu: float, camera: DepthCamera, indenter, pose: ContactPose):
    """Simulated depth map (H, W) mm and force at E = 1 (N) of ``indenter`` at ``pose``."""
    mesh = bank.mesh
    xy = mesh.vertices[mesh.sensing_nodes, :2]
    delta = indenter.intrusion_mm(xy, pose) + mesh.vertices[mesh.sensing_nodes, 2]
    u, force = bank.sensing_response(nu, delta)
    image = camera.render(mesh, mesh.vertices[: mesh.n_plane] + u)
    return image.depth_mm.astype(np.float64), force


def _gap(bank, nu, camera, contact, indenter, pose) -> np.ndarray:
    sim, _ = render_contact(bank, nu, camera, indenter, pose)
    return (sim - contact.depth_mm)[camera_mask(camera, bank)]


def camera_mask(camera: DepthCamera, bank: OperatorBank) -> np.ndarray:
    return camera._rest(bank.mesh)[1]


def estimate_pose(
    bank: OperatorBank,
    nu: float,
    camera: DepthCamera,
    contact: MatchedContact,
    start: ContactPose | None = None,
) -> ContactPose:
    """The contact that reproduces a measured map: maximum-displacement point, then least squares.

    x, y and depth are refined; theta is taken from ``start`` (or 0, or the best of 12 angles for
    indenters that are not round).
    """
    indenter = get_indenter(contact.indenter)
    round_shape = _is_round(indenter)
    if start is None:
        # the maximum-displacement region (paper), located by its depth-weighted centroid so that
        # flat-topped contacts (a plateau of maxima) start at their centre
        smooth = ndimage.gaussian_filter(contact.depth_mm, 1.0)
        top = smooth > 0.5 * smooth.max()
        centres = camera.pixel_centres_mm()
        w = smooth[top]
        x0, y0 = (float(v) for v in (centres[top] * w[:, None]).sum(0) / w.sum())
        d0 = float(contact.depth_mm.max())
        thetas = [0.0] if round_shape else list(np.arange(0.0, 360.0, 15.0))
        best = None
        for t in thetas:
            pose = ContactPose(x_mm=x0, y_mm=y0, theta_deg=t, depth_mm=max(d0, 1e-3))
            cost = float(np.sum(_gap(bank, nu, camera, contact, indenter, pose) ** 2))
            if best is None or cost < best[0]:
                best = (cost, pose)
        start = best[1]

    def pose_of(p):
        theta = start.theta_deg if round_shape else p[3]
        return ContactPose(x_mm=p[0], y_mm=p[1], theta_deg=theta, depth_mm=max(p[2], 1e-4))

    def residual(p):
        return _gap(bank, nu, camera, contact, indenter, pose_of(p))

    p0 = np.array([start.x_mm, start.y_mm, start.depth_mm] + ([] if round_shape else [start.theta_deg]))
    scale = [0.3, 0.3, 0.05] + ([] if round_shape else [5.0])
    # the gap is piecewise smooth (pixels, mesh nodes): restart from shifted starts, keep the best
    best = None
    for shift in ((0.0, 0.0), (0.3, 0.0), (0.0, 0.3), (-0.3, -0.3)):
        q0 = p0.copy()
        q0[:2] += shift
        sol = optimize.least_squares(residual, q0, x_scale=scale, diff_step=2e-2, max_nfev=60)
        if best is None or sol.cost < best.cost:
            best = sol
    return pose_of(best.x)


def _is_round(indenter) -> bool:
    return indenter.name.startswith(("sphere", "analytic", "flat_punch", "ring", "torus")) or indenter.name in (
        "sphere", "sphere2", "cylinder", "cylinder_shell", "torus", "cone"
    )


def unit_force_n(bank: OperatorBank, nu: float, indenter, pose: ContactPose) -> float:
    """Total normal force (N) of ``indenter`` at ``pose`` for E = 1 MPa (no depth map)."""
    mesh = bank.mesh
    xy = mesh.vertices[mesh.sensing_nodes, :2]
    delta = indenter.intrusion_mm(xy, pose) + mesh.vertices[mesh.sensing_nodes, 2]
    return bank.sensing_response(nu, delta)[1]


def fit_depth_offset_mm(bank: OperatorBank, nu: float, contacts, poses,
                        bounds_mm: tuple[float, float] = (-0.15, 0.15)) -> float:
    """Common offset (mm, positive: the contacts went deeper than given) of the contacts' depths
    that, with the best E, explains the measured forces best (relative residuals).

    F_i = E * F1(pose_i deepened by the offset), F1 the FEM force at E = 1 MPa: E scales every
    force alike while an offset changes shallow presses relatively more than deep ones, so both
    are identifiable from presses of several depths.
    """
    fm = np.array([c.force_n for c in contacts], np.float64)
    indenters = [get_indenter(c.indenter) for c in contacts]

    def cost(off):
        f1 = np.array([unit_force_n(bank, nu, ind, p.model_copy(
            update={"depth_mm": max(p.depth_mm + off, 1e-4)})) for ind, p in zip(indenters, poses)])
        q = f1 / fm
        e = q.sum() / (q @ q)
        return float(np.sum((e * q - 1.0) ** 2))

    res = optimize.minimize_scalar(cost, bounds=bounds_mm, method="bounded", options={"xatol": 2e-4})
    return float(res.x)


def depth_objective(bank, nu, camera, contacts, poses) -> float:
    """Root-mean-square depth-map gap (mm) over all contacts' pad pixels at ``nu``."""
    total, count = 0.0, 0
    for c, pose in zip(contacts, poses):
        g = _gap(bank, nu, camera, c, get_indenter(c.indenter), pose)
        total += float(np.sum(g * g))
        count += g.size
    return math.sqrt(total / count)


def _minimise_nu(objective, lo, hi, method: str, seed: int):
    """Returns (nu, value, evaluations, curve)."""
    curve: list[tuple[float, float]] = []

    def f(nu):
        v = objective(float(nu))
        curve.append((float(nu), v))
        return v

    if hi - lo < 1e-9:  # one operator node: nu is fixed there
        return float(lo), f(lo), 1, curve

    if method == "brent":
        res = optimize.minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": 2e-4})
        return float(res.x), float(res.fun), len(curve), curve
    if method == "cem":  # cross-entropy method, as in the paper
        rng = np.random.default_rng(seed)
        mean, std = 0.5 * (lo + hi), 0.5 * (hi - lo)
        best = (None, np.inf)
        for _ in range(8):
            samples = np.clip(rng.normal(mean, std, 12), lo, hi)
            values = np.array([f(s) for s in samples])
            elite = samples[np.argsort(values)[:4]]
            if values.min() < best[1]:
                best = (float(samples[np.argmin(values)]), float(values.min()))
            mean, std = float(elite.mean()), max(float(elite.std()), 1e-4)
            if std < 5e-4:
                break
        return best[0], best[1], len(curve), curve
    raise ValueError(f"method must be 'cem' or 'brent', got {method!r}")


def fit_fem_parameters(
    contacts: list[MatchedContact],
    bank: OperatorBank,
    camera: DepthCamera | None = None,
    method: str = "brent",
    stick_bank: OperatorBank | None = None,
    bootstrap: int = 20,
    seed: int = 0,
    fit_depth_offset: bool = False,
) -> FemFitResult:
    """Fit nu (and E from forces, and the friction law when ``stick_bank`` is given).

    fit_depth_offset : the given contacts' depths share an unknown offset (a rig's touch-off
        error): fit it from the forces with E (:func:`fit_depth_offset_mm`), correct those
        contacts, refit nu. Needs forces at given contacts of several depths.
    """
    if not contacts:
        raise ValueError("no contacts to fit")
    camera = camera or DepthCamera()
    lo, hi = bank.nu_range
    nu0 = 0.5 * (lo + hi)
    poses = [c.pose if c.pose is not None else estimate_pose(bank, nu0, camera, c) for c in contacts]
    nu, value, evals, curve = _minimise_nu(lambda n: depth_objective(bank, n, camera, contacts, poses), lo, hi, method, seed)
    # contacts that were estimated are re-estimated at the fitted nu, then nu is refitted
    if any(c.pose is None for c in contacts):
        poses = [c.pose if c.pose is not None else estimate_pose(bank, nu, camera, c, start=p) for c, p in zip(contacts, poses)]
        nu, value, more, curve2 = _minimise_nu(lambda n: depth_objective(bank, n, camera, contacts, poses), lo, hi, method, seed)
        evals += more
        curve = curve2  # the objective at the final contacts

    depth_offset = None
    poses0 = list(poses)
    given = [i for i, c in enumerate(contacts) if c.pose is not None and c.force_n is not None]
    if fit_depth_offset and len(given) >= 3:
        given_poses = [poses[i] for i in given]
        for _ in range(2):  # offset at this nu, nu at the corrected contacts, twice
            depth_offset = fit_depth_offset_mm(bank, nu, [contacts[i] for i in given], given_poses)
            poses = [p.model_copy(update={"depth_mm": p.depth_mm + depth_offset})
                     if c.pose is not None else p for c, p in zip(contacts, poses0)]
            nu, value, more, curve2 = _minimise_nu(lambda n: depth_objective(bank, n, camera, contacts, poses), lo, hi, method, seed)
            evals += more
            curve = curve2  # the objective at the final contacts

    # bootstrap over contacts (Brent, poses fixed): the spread of nu (none when nu is fixed)
    rng = np.random.default_rng(seed)
    nus = []
    for _ in range(bootstrap if hi - lo >= 1e-9 else 0):
        idx = rng.integers(len(contacts), size=len(contacts))
        sub_c = [contacts[i] for i in idx]
        sub_p = [poses[i] for i in idx]
        nus.append(_minimise_nu(lambda n: depth_objective(bank, n, camera, sub_c, sub_p), lo, hi, "brent", seed)[0])
    nu_std = float(np.std(nus)) if nus else float("nan")
    nu_note = (f"fixed at {lo:g}: the operator bank has one node (give several to fit it)"
               if hi - lo < 1e-9 else f"fitted in [{lo:g}, {hi:g}] ({method})")

    # E from forces: F_measured = E * F(E = 1)
    with_force = [(c, p) for c, p in zip(contacts, poses) if c.force_n is not None]
    if with_force:
        f1 = np.array([render_contact(bank, nu, camera, get_indenter(c.indenter), p)[1] for c, p in with_force])
        fm = np.array([c.force_n for c, _ in with_force])
        if not np.all(f1 > 0):
            i = [k for k, c in enumerate(contacts) if c.force_n is not None][int(np.argmin(f1 > 0))]
            raise ValueError(f"contact {i + 1} has a measured force but its FEM contact gives no "
                             "force (the indenter does not reach the gel there): E cannot be "
                             "fitted; check that contact's position and depth")
        E = float(fm @ f1 / (f1 @ f1))
        ratios = fm / f1
        E_std = float(np.std([np.mean(ratios[rng.integers(len(ratios), size=len(ratios))]) for _ in range(200)]))
        E_note = f"from {len(with_force)} measured forces" + (
            f", with a fitted depth offset of {depth_offset * 1e3:+.1f} um" if depth_offset is not None
            else "")
    else:
        E, E_std = None, None
        E_note = (
            "not identifiable from this data: with depth maps alone (displacement control) the "
            "displacement field does not depend on E; measure forces"
        )

    friction, friction_note = bank.friction, "only one contact law was tried"
    if stick_bank is not None:
        nu_s, value_s, more, _ = _minimise_nu(lambda n: depth_objective(stick_bank, n, camera, contacts, poses), lo, hi, "brent", seed)
        evals += more
        # the fits differ meaningfully when the gap changes by more than the bootstrap spread
        # of the objective itself
        spread = float(np.std([depth_objective(bank, nu, camera, [contacts[i] for i in rng.integers(len(contacts), size=len(contacts))],
                                               [poses[i] for i in rng.integers(len(contacts), size=len(contacts))])
                               for _ in range(5)])) if len(contacts) > 1 else 0.0
        better, worse = ("stick", "frictionless") if value_s < value else ("frictionless", "stick")
        gain = abs(value - value_s)
        if gain > max(0.02 * min(value, value_s), 1e-6) and gain > 0.1 * spread:
            friction = better
            friction_note = (
                f"{better} contact fits better than {worse} (depth gap {min(value, value_s) * 1e3:.2f} vs "
                f"{max(value, value_s) * 1e3:.2f} um); mu itself is not identifiable with these two laws"
            )
            if better == "stick":
                nu, value = nu_s, value_s
        else:
            friction_note = (
                "not identifiable from this data: frictionless and sticking contact fit equally well "
                f"({value * 1e3:.2f} vs {value_s * 1e3:.2f} um)"
            )
    return FemFitResult(
        nu=nu, nu_std=nu_std, E_mpa=E, E_std_mpa=E_std, E_note=E_note, friction=friction,
        friction_note=friction_note, method=method, evaluations=evals, rmse_mm=value,
        poses=poses, objective_curve=curve, nu_note=nu_note, depth_offset_mm=depth_offset,
    )
