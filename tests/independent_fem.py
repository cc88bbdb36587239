"""A rigid sphere or a rigid flat punch pressed into a bonded neo-Hookean layer, solved with
scikit-fem.

An independent reference for the resolved contact solver: it imports numpy, scipy and
scikit-fem only (nothing of ``tactile_deploy``; a test checks that), and is written from the
textbook statement of the problem, not from the product's solver.

Problem (axisymmetric; cylindrical frame (r, z) in mm, z = 0 the layer's rest top surface,
z < 0 inside the layer, the indenter's axis at r = 0):

* a cylindrical layer ``0 <= r <= radius_mm``, ``-thickness_mm <= z <= 0``; its bottom bonded
  (u = 0), its lateral side and top free, u_r = 0 on the axis;
* compressible neo-Hookean material (shear modulus mu, bulk modulus kappa = lambda + 2 mu / 3
  from E (MPa) and nu)::

      W(F) = mu / 2 (J^(-2/3) I1 - 3) + kappa / 2 (J - 1)^2,   I1 = tr(F' F),  J = det F

  with the axisymmetric deformation gradient (displacement u = (u_r, u_z))::

      F = [[1 + du_r/dr, du_r/dz, 0], [du_z/dr, 1 + du_z/dz, 0], [0, 0, (r + u_r) / r]]

  and total energy ``Pi(u) = integral W(F) 2 pi r dr dz`` (N mm);
* :func:`press_sphere`: a rigid frictionless sphere of radius R whose lowest point is at
  z = -depth: its lower surface ``z_s(rho) = R - depth - sqrt(R^2 - rho^2)``. Contact in the
  current configuration: every top-surface node at current position (rho, z) = (r + u_r, u_z)
  keeps the vertical gap ``g = z_s(rho) - z >= 0`` (its gradient is along the sphere's normal,
  so the contact force is normal to the sphere: frictionless);
* :func:`press_punch`: a rigid frictionless circular flat punch of radius a (sharp rim,
  vertical side), its face at z = -depth: every top-surface node stays outside the solid
  rho < a, z > -depth (its face and its side; see there);
* discretisation: quadratic (P2) triangles on a tensor mesh graded towards the contact (the
  sphere: the axis and the top surface; the punch: the rim's corner r = a, z = 0), 4th-order
  quadrature;
* solution: depth raised in equal load steps (each started from the previous increment);
  at each step Newton's method on the Lagrangian with a primal-dual active set (active where
  ``lambda - g > 0``; the active constraints hold in linearised form, the nodal contact forces
  lambda are unknowns of the saddle-point system, the gap's curvature is in the tangent),
  until the active set no longer changes and the Newton step is below the tolerance (mm).
  Checked at the end: the bonded bottom's reaction equals the contact force (to 1e-6), no
  contact force is tensile, no element is inverted.

Returns the total force (N, the indenter pushing the layer along -z) and the deformed top
surface (current r and z of its nodes, mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from skfem import Basis, BilinearForm, ElementTriP2, ElementVector, LinearForm, MeshTri, asm

# Nonzero components (i, j) of the axisymmetric deformation gradient, in this order.
_COMPONENTS = ((0, 0), (0, 1), (1, 0), (1, 1), (2, 2))


@dataclass
class SphereOnLayer:
    """Converged solution: force_n (N), profile_r_mm / profile_z_mm (k,) current positions of
    the top-surface nodes sorted by r, contact_radius_mm (largest current r of a node in
    contact), n_dofs, newton_steps, max_penetration_mm (largest nodal penetration)."""

    force_n: float
    profile_r_mm: np.ndarray
    profile_z_mm: np.ndarray
    contact_radius_mm: float
    n_dofs: int
    newton_steps: int
    max_penetration_mm: float


def graded(h_fine: float, fine_until: float, length: float, growth: float = 1.15) -> np.ndarray:
    """Points 0 .. length (mm): spacing h_fine up to ``fine_until``, then growing geometrically
    by ``growth`` per cell."""
    n = max(int(round(fine_until / h_fine)), 1)
    pts = list(np.linspace(0.0, fine_until, n + 1))
    h = fine_until / n
    while pts[-1] < length:
        h *= growth
        pts.append(pts[-1] + h)
    pts = np.array(pts)
    # stretch the graded part so that the last point lands on ``length``
    tail = pts > fine_until
    pts[tail] = fine_until + (pts[tail] - fine_until) * (length - fine_until) / (pts[-1] - fine_until)
    return pts


def _lame(E: float, nu: float) -> tuple[float, float]:
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def _deformation_gradient(u, r):
    """F (3, 3, ...) from the interpolated displacement u (value (2, ...), grad (2, 2, ...))."""
    g = u.grad
    F = np.zeros((3, 3) + r.shape)
    F[0, 0] = 1 + g[0, 0]
    F[0, 1] = g[0, 1]
    F[1, 0] = g[1, 0]
    F[1, 1] = 1 + g[1, 1]
    F[2, 2] = 1 + u[0] / r
    return F


def stress_and_tangent(F: np.ndarray, mu: float, kappa: float, tangent: bool = True):
    """First Piola stress P (3, 3, ...) and dP/dF (3, 3, 3, 3, ...) of W above (None
    unless ``tangent``)."""
    J = (F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]) * F[2, 2]
    H = np.zeros_like(F)  # F^-T
    det2 = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    H[0, 0] = F[1, 1] / det2
    H[0, 1] = -F[1, 0] / det2
    H[1, 0] = -F[0, 1] / det2
    H[1, 1] = F[0, 0] / det2
    H[2, 2] = 1 / F[2, 2]
    I1 = np.einsum("ij...,ij...->...", F, F)
    Jm = np.cbrt(J) ** -2  # defined for J <= 0 too (an intermediate Newton iterate)
    P = mu * Jm * (F - I1 / 3 * H) + kappa * (J - 1) * J * H
    if not tangent:
        return P, None
    eye = np.eye(3)
    d = np.einsum("im,jn->ijmn", eye, eye)[..., None, None]
    HH = np.einsum("ij...,mn...->ijmn...", H, H)
    HF = np.einsum("ij...,mn...->ijmn...", H, F)
    FH = np.einsum("ij...,mn...->ijmn...", F, H)
    Hx = np.einsum("in...,mj...->ijmn...", H, H)
    A = (mu * Jm * (d - 2 / 3 * HF - 2 / 3 * FH + 2 / 9 * I1 * HH + I1 / 3 * Hx)
         + kappa * ((2 * J - 1) * J * HH - (J - 1) * J * Hx))
    return P, A


def _grad_components(v, r):
    """The five nonzero components of dF for a test/trial field v, in ``_COMPONENTS`` order."""
    return (v.grad[0, 0], v.grad[0, 1], v.grad[1, 0], v.grad[1, 1], v[0] / r)


@BilinearForm
def _tangent_form(u, v, w):
    r = w.x[0]
    gu, gv = _grad_components(u, r), _grad_components(v, r)
    A = np.asarray(w.A)
    out = 0.0
    for a in range(5):
        out = out + gv[a] * sum(A[a * 5 + b] * gu[b] for b in range(5))
    return 2 * math.pi * r * out


@LinearForm
def _residual_form(v, w):
    r = w.x[0]
    gv = _grad_components(v, r)
    P = np.asarray(w.P)
    return 2 * math.pi * r * sum(gv[a] * P[a] for a in range(5))


class Layer:
    """The discretised layer: mesh, P2 basis, boundary conditions, top-surface nodes."""

    def __init__(self, rs: np.ndarray, zs: np.ndarray, E_mpa: float, nu: float):
        """``rs`` (m,) radial grid lines 0 .. the layer's radius, ``zs`` (n,) vertical ones
        -thickness .. 0 (mm, increasing); the mesh is their tensor product, each rectangle
        cut into two triangles."""
        thickness_mm = -float(zs[0])
        self.mesh = MeshTri.init_tensor(rs, zs)
        self.basis = Basis(self.mesh, ElementVector(ElementTriP2()), intorder=4)
        lam, self.mu = _lame(E_mpa, nu)
        self.kappa = lam + 2 * self.mu / 3
        locs = self.basis.doflocs
        comp_r, comp_z = self.basis.split_indices()
        tol = 1e-9
        fixed = np.concatenate([comp_r[np.abs(locs[0, comp_r]) < tol],
                                comp_r[np.abs(locs[1, comp_r] + thickness_mm) < tol],
                                comp_z[np.abs(locs[1, comp_z] + thickness_mm) < tol]])
        self.n = self.basis.N
        self.free = np.setdiff1d(np.arange(self.n), fixed)
        top_r = comp_r[np.abs(locs[1, comp_r]) < tol]
        top_z = comp_z[np.abs(locs[1, comp_z]) < tol]
        top_r = top_r[np.argsort(locs[0, top_r])]
        top_z = top_z[np.argsort(locs[0, top_z])]
        assert np.allclose(locs[0, top_r], locs[0, top_z])
        self.top_r, self.top_z = top_r, top_z
        self.top_rest_r = locs[0, top_r]

    def min_jacobian(self, u: np.ndarray) -> float:
        """Smallest J = det F over the quadrature points."""
        F = _deformation_gradient(self.basis.interpolate(u), self.basis.global_coordinates()[0])
        return float(((F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]) * F[2, 2]).min())

    def forces_and_tangent(self, u: np.ndarray, tangent: bool = True):
        ui = self.basis.interpolate(u)
        r = self.basis.global_coordinates()[0]
        F = _deformation_gradient(ui, r)
        P, A = stress_and_tangent(F, self.mu, self.kappa, tangent)
        P5 = np.stack([P[i, j] for i, j in _COMPONENTS])
        f = asm(_residual_form, self.basis, P=P5)
        if not tangent:
            return f, None
        A5 = np.stack([A[i, j, m, n] for i, j in _COMPONENTS for m, n in _COMPONENTS])
        K = asm(_tangent_form, self.basis, A=A5)
        return f, K.tocsr()


def press_sphere(radius_mm: float = 8.0, thickness_mm: float = 3.0, E_mpa: float = 0.3,
                 nu: float = 0.48, sphere_radius_mm: float = 2.0, depth_mm: float = 1.0,
                 h_fine_mm: float = 0.1, fine_r_mm: float = 3.0, fine_depth_mm: float = 0.6,
                 growth: float = 1.15, steps: int = 20, tol_mm: float = 1e-10) -> SphereOnLayer:
    """Press the sphere ``depth_mm`` into the layer (see the module docstring).

    Contact at the top-surface nodes: the nodal force lambda (N, >= 0) of each active node and
    its linearised gap enter the saddle-point system; the active set is re-chosen after every
    Newton step from ``lambda - g > 0`` (primal-dual active set)."""
    rs = graded(h_fine_mm, fine_r_mm, radius_mm, growth)
    zs = -graded(h_fine_mm, fine_depth_mm, thickness_mm, growth)[::-1]
    lay = Layer(rs, zs, E_mpa, nu)
    R = sphere_radius_mm

    def gap(u, depth, u_start, depth_start):
        rho = lay.top_rest_r + u[lay.top_r]
        inside = rho < R
        root = np.sqrt(np.where(inside, R * R - rho * rho, 1.0))
        # beyond the equator (never reached by a converged surface) the gap continues at the
        # equator's height, so that it stays continuous
        zs = np.where(inside, R - depth - root, R - depth)
        return (zs - u[lay.top_z], np.where(inside, rho / root, 0.0), -np.ones_like(rho),
                np.where(inside, R * R / root**3, 0.0))

    u, lam, _, newton, g = _press(lay, gap, depth_mm, steps, tol_mm, "sphere on layer")
    rho = lay.top_rest_r + u[lay.top_r]
    return SphereOnLayer(
        force_n=float(lam.sum()),
        profile_r_mm=rho,
        profile_z_mm=u[lay.top_z],
        contact_radius_mm=float(rho[lam > 0].max()),
        n_dofs=lay.n,
        newton_steps=newton,
        max_penetration_mm=float(max(-g.min(), 0.0)),
    )


def _press(lay: Layer, gap, depth_mm: float, steps: int, tol_mm: float, label: str):
    """Raise the indenter's depth to ``depth_mm`` in ``steps`` equal load steps; at each,
    Newton's method with a primal-dual active set on the top-surface nodes.

    ``gap(u, depth, u_start, depth_start)`` -> (g, dg/du_r, dg/du_z, d2g/du_r2), each (k,)
    over the top-surface nodes: the gap (mm, >= 0 outside the indenter) and its derivatives
    along the node's displacement; ``u_start`` and ``depth_start`` are the solution and the
    depth of the load step before (zero at the first), which tell a punch which way a node
    inside it came in. Returns (u (n,) mm, the nodal contact forces lambda (k,) N along the gap's
    gradient, their vertical part (k,) N (the force on the layer along -z), Newton steps, the
    final gap (k,) mm), after checking
    that the bonded bottom's reaction equals the contact force (to 1e-6), that no contact
    force is tensile and that no element is inverted."""
    free = lay.free
    u = np.zeros(lay.n)
    lam = np.zeros(len(lay.top_r))
    newton = 0
    u_prev = u.copy()
    for step in range(1, steps + 1):
        depth = depth_mm * step / steps
        u_start, depth_start = u, depth_mm * (step - 1) / steps
        u, u_prev = 2 * u - u_prev, u  # predictor: the previous increment again
        g = gap(u, depth, u_start, depth_start)[0]
        active = (lam - g) > 0
        for it in range(100):
            newton += 1
            f, K = lay.forces_and_tangent(u)
            g, slope, slope_z, curv = gap(u, depth, u_start, depth_start)
            idx = np.flatnonzero(active)
            na = len(idx)
            # tangent of f - C' lam: the gap's curvature along u_r of the active nodes
            diag = np.zeros(lay.n)
            diag[lay.top_r[idx]] = lam[idx] * curv[idx]
            Kt = (K - sp.diags(diag)).tocsr()[free][:, free]
            C = sp.csr_matrix((np.concatenate([slope[idx], slope_z[idx]]),
                               (np.tile(np.arange(na), 2),
                                np.concatenate([lay.top_r[idx], lay.top_z[idx]]))),
                              shape=(na, lay.n))
            Cf = C[:, free]
            res = f[free] - Cf.T @ lam[idx]
            M = sp.bmat([[Kt, -Cf.T], [-Cf, None]], format="csc")
            sol = spla.spsolve(M, np.concatenate([-res, g[idx]]))
            du = np.zeros(lay.n)
            du[free] = sol[: len(free)]
            u = u + du
            new_lam = np.zeros_like(lam)
            new_lam[idx] = lam[idx] + sol[len(free):]
            g = gap(u, depth, u_start, depth_start)[0]
            new_active = (new_lam - g) > 0
            lam = np.where(new_active, np.maximum(new_lam, 0.0), 0.0)
            if np.array_equal(new_active, active) and np.abs(du).max() < tol_mm:
                lam = new_lam
                break
            active = new_active
        else:
            raise RuntimeError(f"{label}: Newton did not converge at depth {depth} mm "
                               f"(last step {np.abs(du).max():.3e} mm)")
    f, _ = lay.forces_and_tangent(u, tangent=False)
    g, _, slope_z, _ = gap(u, depth_mm, u_start, depth_start)
    vertical = -lam * slope_z  # the contact forces' part along -z (N)
    force = float(vertical.sum())
    bottom_z = np.setdiff1d(lay.basis.split_indices()[1], free)
    reaction = float(f[bottom_z].sum())  # internal force at the bonded bottom, +z
    if abs(reaction - force) > 1e-6 * force:
        raise RuntimeError(f"{label}: contact force {force:.9g} N but bottom reaction "
                           f"{reaction:.9g} N")
    if lay.min_jacobian(u) <= 0:
        raise RuntimeError(f"{label}: inverted element (J {lay.min_jacobian(u):.3e})")
    if np.any(lam < 0):
        raise RuntimeError(f"{label}: tensile contact force {lam.min():.3e} N")
    return u, lam, vertical, newton, g


@dataclass
class PunchOnLayer:
    """Converged solution of the flat punch: force_n (N), profile_r_mm / profile_z_mm (k,)
    current positions of the top-surface nodes sorted by rest r, contact_radius_mm (largest
    current r of a node in contact with the face), rim_gap_mm (height above the face of the
    first node beyond the rim, mm), side_nodes (nodes pressed against the punch's side),
    n_dofs, newton_steps, max_penetration_mm (largest nodal penetration of the punch)."""

    force_n: float
    profile_r_mm: np.ndarray
    profile_z_mm: np.ndarray
    contact_radius_mm: float
    rim_gap_mm: float
    side_nodes: int
    n_dofs: int
    newton_steps: int
    max_penetration_mm: float


def graded_about(centre: float, h_min: float, growth: float, length: float,
                 h_max: float) -> np.ndarray:
    """Grid lines 0 .. length (mm) with one at ``centre`` (0 <= centre < length): spacing
    ``h_min`` on either side of it, growing by ``growth`` per cell away from it up to
    ``h_max``; the last cell on each side is stretched to land on 0 and ``length``."""

    def side(extent):
        if extent <= 0:
            return np.zeros(1)
        pts, h = [0.0], h_min
        while pts[-1] < extent:
            pts.append(pts[-1] + h)
            h = min(h * growth, h_max)
        pts = np.array(pts)
        if len(pts) > 2 and extent - pts[-2] < 0.5 * (pts[-1] - pts[-2]):
            pts = np.delete(pts, -2)  # no sliver: merge a short last cell into the one before
        return pts * extent / pts[-1]

    left = centre - side(centre)[::-1]
    right = centre + side(length - centre)
    return np.concatenate([left, right[1:]])


def halved(pts: np.ndarray, times: int = 1) -> np.ndarray:
    """The grid lines ``pts`` with every cell cut in two, ``times`` times."""
    for _ in range(times):
        pts = np.sort(np.concatenate([pts, 0.5 * (pts[1:] + pts[:-1])]))
    return pts


def punch_grid(punch_radius_mm: float, radius_mm: float, thickness_mm: float,
               h_rim_mm: float, growth: float = 1.15, h_max_mm: float = 0.5, refine: int = 0):
    """The tensor grid (rs, zs) of :func:`press_punch`: graded towards the rim's corner
    (r = a, z = 0), with a grid line exactly at r = a; ``refine`` halvings of every cell."""
    rs = graded_about(punch_radius_mm, h_rim_mm, growth, radius_mm, h_max_mm)
    zs = -graded_about(0.0, h_rim_mm, growth, thickness_mm, h_max_mm)[::-1]
    return halved(rs, refine), halved(zs, refine)


def press_punch(radius_mm: float = 8.0, thickness_mm: float = 3.0, E_mpa: float = 0.3,
                nu: float = 0.45, punch_radius_mm: float = 1.0, depth_mm: float = 0.01,
                h_rim_mm: float = 0.002, growth: float = 1.15, h_max_mm: float = 0.5,
                refine: int = 0, steps: int = 1, tol_mm: float = 1e-12) -> PunchOnLayer:
    """Press a rigid frictionless circular flat punch of radius a = ``punch_radius_mm``
    (sharp rim, vertical side) ``depth_mm`` into the layer, its axis at r = 0: the punch is
    the solid rho < a, z > -depth.

    Contact in the current configuration: every top-surface node at (rho, z) = (r + u_r, u_z)
    stays outside that solid: outside it, ``g = max(-depth - z, rho - a) >= 0`` (under the
    face its vertical gap, beside the side its horizontal one); inside it, the one of the two
    that was the larger at the end of the load step before: ``-depth - z`` if the node was
    under the face (the punch came down on it; a node at the rim's corner too), else
    ``rho - a`` (it came in through the side). The gradient is the face's
    or the side's normal: frictionless.
    The mesh is graded towards the rim's corner, where the contact pressure is singular (as
    1 / sqrt(a - r) in the small-strain limit), with a grid line at r = a; the force converges
    with the smallest spacing there, ``h_rim_mm / 2**refine``."""
    a = punch_radius_mm
    rs, zs = punch_grid(a, radius_mm, thickness_mm, h_rim_mm, growth, h_max_mm, refine)
    lay = Layer(rs, zs, E_mpa, nu)
    k = len(lay.top_r)

    def gap(u, depth, u_start, depth_start):
        face = -depth - u[lay.top_z]
        side = lay.top_rest_r + u[lay.top_r] - a
        beside = (lay.top_rest_r + u_start[lay.top_r] - a) > (-depth_start - u_start[lay.top_z])
        outside = (face > 0) | (side > 0)
        on_side = np.where(outside, side > face, beside)
        return (np.where(on_side, side, face), on_side.astype(float),
                np.where(on_side, 0.0, -1.0), np.zeros(k))

    u, lam, vertical, newton, g = _press(lay, gap, depth_mm, steps, tol_mm, "punch on layer")
    rho = lay.top_rest_r + u[lay.top_r]
    z = u[lay.top_z]
    beyond = np.flatnonzero(rho >= a)
    first = beyond[np.argmin(rho[beyond])]
    on_side = (lam > 0) & (rho - a > -depth_mm - z)
    return PunchOnLayer(
        force_n=float(vertical.sum()),
        profile_r_mm=rho,
        profile_z_mm=z,
        contact_radius_mm=float(rho[(lam > 0) & ~on_side].max()),
        rim_gap_mm=float(z[first] + depth_mm),
        side_nodes=int(on_side.sum()),
        n_dofs=lay.n,
        newton_steps=newton,
        max_penetration_mm=float(max(-g.min(), 0.0)),
    )
