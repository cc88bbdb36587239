"""Resolved contact of a rigid indenter with the gel: the reference ("truth") solver.

Data flow of :meth:`TruthSolver.solve`::

    indenter + pose --(intrusion footprint)--> refinement region, fine spacing
        --> truth mesh (tactile_deploy.fem.truth_mesh: refined where contact can occur)
        --> contact constraints on the continuous surface (below)
        --> augmented-Lagrangian Newton solve (neo-Hookean or linear gel, Coulomb friction)
        --> TruthSolution (truth-mesh displacements, nodal contact forces, stick/slip)

Contact (sensor frame, mm; the indenter moves only along -z). The indenter's lower surface is
``z = -delta(x, y)`` (``delta`` = its intrusion below the rest surface, from the indenter's
envelope). Two families of gap constraints ``g >= 0`` keep the gel's piecewise-linear surface
below it everywhere:

* **gel points**: every sensing node p of the truth mesh near the contact,
  ``g = -delta(p_x, p_y) - p_z`` at its *current* position (its gradient is the indenter's
  normal, so the contact traction is normal to the indenter);
* **indenter points**: the indenter's surface sampled over the contact (every envelope pixel on
  a sharp convex feature such as a cone tip, an edge or a punch rim, and a grid at a third of the
  fine spacing elsewhere): ``g = z_i - z_gel(x_i, y_i)``, the gel's current surface height under
  the point, so a feature between nodes cannot pass through a triangle.

``model="linear"`` is the small-strain limit: linear material, gaps along z at the rest
positions. Friction (per sensing node, tangent plane of the indenter at the node): frictionless,
stick (no tangential displacement where in contact), or Coulomb with coefficient mu (traction
``|t_T| <= mu t_N``, slip opposite to the traction). Slip is measured from the rest position
(one load step, the indenter pressed straight down).

The complementarity problem is solved exactly to a tolerance (no penalty stiffness remains in
the solution): an augmented Lagrangian with multipliers updated after each Newton step
(``lambda <- max(0, lambda - rho g)``; friction: ``t <- proj(t - rho_T u_T)`` onto the Coulomb
disc), Newton on the augmented energy with a backtracking line search, until the largest
penetration, the largest change of the multipliers and the force residual are below their
tolerances.

Units: mm, MPa, N. The solution is computed at the given E (forces scale with E).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from tactile_deploy.fem.constraints import SENSOR_SUPPORTS, Supports, build_dof_map
from tactile_deploy.fem.hyperelastic import InvertedElementError, gel_model
from tactile_deploy.fem.material import Material
from tactile_deploy.fem.sparse_solver import SparseCholesky
from tactile_deploy.fem.truth_mesh import build_truth_mesh
from tactile_deploy.pad.geometry import PadGeometry
from tactile_deploy.pad.mesh import PadMesh

log = logging.getLogger(__name__)

#: Largest fine spacing of a truth mesh: the depth-camera pixel (35 mm / 128).
H_FINE_MAX_MM = 0.27
#: Fine spacing relative to the equivalent radius of the indenter's footprint.
H_FINE_PER_RADIUS = 1.0 / 10.0
#: Smallest fine spacing.
H_FINE_MIN_MM = 0.05


class TruthSolveError(RuntimeError):
    """The nonlinear contact iterations did not converge (message names the figures)."""


@dataclass(frozen=True)
class SolveSettings:
    """Tolerances and limits of the augmented-Lagrangian Newton iterations."""

    penetration_tol_mm: float = 1e-5  # largest penetration at convergence
    force_tol: float = 1e-6  # largest change of a nodal contact force, of the total force
    max_iterations: int = 60  # multiplier updates
    max_newton: int = 8  # Newton steps per multiplier update
    step_tol: float = 1e-9  # Newton converged when the largest step is below this x depth
    rho_factor: float = 3000.0  # multiplier-update stiffness relative to mu * area / edge
    step_strain: float = 0.1  # load-step depth as a fraction of the pad thickness (large strain)
    pcg_rtol: float = 1e-12  # relative residual of the preconditioned CG solves
    pcg_max: int = 150  # CG iterations before the preconditioner is factored afresh
    precond_bulk: float = 0.15  # bulk term of the preconditioner, fraction of the bulk modulus


@dataclass
class TruthSolution:
    """Resolved contact on the truth mesh.

    mesh : PadMesh, the truth mesh (sensor frame, mm)
    displacements_mm : (n, 3) float64
    contact_forces_n : (n_plane, 3) float64, force of the indenter on each sensing node, N
    normal_force_n : (n_plane,) float64, its component along the indenter normal (>= 0), N
    in_contact : (n_plane,) bool, sensing nodes touching the indenter
    sticking : (n_plane,) bool, nodes in contact whose friction is below mu times the normal
        force (all contact nodes for ``stick``, none for ``frictionless``)
    force_n : float, total force pressing the pad along -z (compression > 0), N
    tangential_force_n : (2,) float64, total x, y force of the indenter on the gel, N
    max_penetration_mm : float, largest penetration over all constraint points
    iterations : int
    info : dict, solver figures
    """

    mesh: PadMesh
    displacements_mm: np.ndarray
    contact_forces_n: np.ndarray
    normal_force_n: np.ndarray
    in_contact: np.ndarray
    sticking: np.ndarray
    force_n: float
    tangential_force_n: np.ndarray
    max_penetration_mm: float
    iterations: int
    info: dict = field(default_factory=dict)

    @property
    def vertices_mm(self) -> np.ndarray:
        return self.mesh.vertices + self.displacements_mm

    def pressure_kpa(self) -> np.ndarray:
        """Normal contact pressure at the sensing nodes, (n_plane,) kPa (lumped areas)."""
        return 1e3 * self.normal_force_n / self.mesh.sensing_nodal_areas_mm2()


# --------------------------------------------------------------------------------- geometry
class IntrusionField:
    """The indenter's intrusion ``delta(x, y)`` (mm) below the rest surface and its gradient.

    ``fn(xy (k, 2)) -> (k,)`` mm, -inf where the indenter does not cover the point.
    """

    def __init__(self, fn, step_mm: float = 1e-4):
        self.fn = fn
        self.step = step_mm

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        return np.asarray(self.fn(np.asarray(xy, np.float64)), np.float64)

    @np.errstate(invalid="ignore")
    def with_gradient(self, xy: np.ndarray):
        """(delta (k,), grad (k, 2)) by central differences (one-sided at a footprint edge)."""
        xy = np.asarray(xy, np.float64)
        d = self(xy)
        h = self.step
        grad = np.zeros((len(xy), 2))
        for c in range(2):
            e = np.zeros(2)
            e[c] = h
            dp, dm = self(xy + e), self(xy - e)
            g = (dp - dm) / (2 * h)
            g = np.where(np.isfinite(dp) & ~np.isfinite(dm), (dp - d) / h, g)
            g = np.where(~np.isfinite(dp) & np.isfinite(dm), (d - dm) / h, g)
            grad[:, c] = np.where(np.isfinite(g), g, 0.0)
        return d, grad


def indenter_field(indenter, pose) -> IntrusionField:
    """Intrusion field of a library indenter (``tactile_deploy.indenters``) at ``pose``."""
    return IntrusionField(lambda xy: indenter.intrusion_mm(xy, pose))


def footprint(field_: IntrusionField, geometry: PadGeometry, pitch_mm: float = 0.05,
              centre_xy=(0.0, 0.0), radius_mm: float | None = None):
    """Points (k, 2) of a ``pitch_mm`` grid where the indenter reaches below the rest surface,
    and their intrusion (k,) mm. Searched within ``radius_mm`` of ``centre_xy`` (default: the
    whole pad)."""
    half = geometry.half_extent_mm
    cx, cy = centre_xy
    r = half if radius_mm is None else radius_mm
    xs = np.arange(max(cx - r, -half), min(cx + r, half) + pitch_mm, pitch_mm)
    ys = np.arange(max(cy - r, -half), min(cy + r, half) + pitch_mm, pitch_mm)
    pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    pts = pts[geometry.contains_xy(pts[:, 0], pts[:, 1])]
    d = field_(pts)
    inside = d > 0
    return pts[inside], d[inside]


def fine_spacing(footprint_area_mm2: float) -> float:
    """Fine spacing (mm) of a truth mesh for a footprint of this area."""
    radius = math.sqrt(max(footprint_area_mm2, 0.0) / math.pi)
    return float(np.clip(H_FINE_PER_RADIUS * radius, H_FINE_MIN_MM, H_FINE_MAX_MM))


# ------------------------------------------------------------------------------ locating
def locate_in_triangles(points_xy: np.ndarray, tri_xy: np.ndarray, k: int = 12):
    """Triangle index (q,) and barycentric coordinates (q, 3) of points in a planar
    triangulation given by its corner positions ``tri_xy`` (t, 3, 2). A point outside every
    triangle gets the nearest one (coordinates then extrapolate)."""
    centroids = tri_xy.mean(axis=1)
    k = min(k, len(tri_xy))
    _, cand = cKDTree(centroids).query(points_xy, k=k)
    cand = cand.reshape(len(points_xy), k)
    a, b, c = tri_xy[cand, 0], tri_xy[cand, 1], tri_xy[cand, 2]  # (q, k, 2)
    v0, v1 = b - a, c - a
    v2 = points_xy[:, None, :] - a
    det = v0[..., 0] * v1[..., 1] - v0[..., 1] * v1[..., 0]
    l1 = (v2[..., 0] * v1[..., 1] - v2[..., 1] * v1[..., 0]) / det
    l2 = (v0[..., 0] * v2[..., 1] - v0[..., 1] * v2[..., 0]) / det
    bary = np.stack([1.0 - l1 - l2, l1, l2], axis=-1)
    worst = bary.min(axis=-1)
    best = np.argmax(worst, axis=1)
    rows = np.arange(len(points_xy))
    return cand[rows, best], bary[rows, best]


# ------------------------------------------------------------------------------- the solver
@dataclass
class _Constraints:
    """Linearised gap constraints: gap (c,), nodes (c, 3) sensing-node indices, weights
    (c, 3, 3) dgap/du per node and component, node_share (c, 3) weight of each node in the
    normal force (sums to 1)."""

    gap: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    share: np.ndarray


class TruthSolver:
    """Resolved large-deformation frictional contact on per-contact truth meshes.

    Parameters
    ----------
    geometry : PadGeometry — the pad (disc or box, flat), bonded to the backplate.
    material : Material — E (MPa), nu, mu and the friction law.
    model : "neo-hookean" (default) or "linear" (small-strain limit).
    supports : Supports — how the pad is held (default: bonded backplate, free sides).
    h_coarse_mm : float — largest in-plane spacing of the truth mesh.
    settings : SolveSettings
    """

    def __init__(self, geometry: PadGeometry, material: Material = Material(),
                 model: str = "neo-hookean", supports: Supports = SENSOR_SUPPORTS,
                 h_coarse_mm: float = 2.0, settings: SolveSettings = SolveSettings()):
        if model not in ("neo-hookean", "linear"):
            raise ValueError(f"model must be 'neo-hookean' or 'linear', got {model!r}")
        self.geometry = geometry
        self.material = material
        self.model = model
        self.supports = supports
        self.h_coarse_mm = h_coarse_mm
        self.settings = settings

    # -------------------------------------------------------------------------- meshing
    def mesh_for(self, field_: IntrusionField, h_fine_mm: float | None = None,
                 region_xy: np.ndarray | None = None) -> tuple[PadMesh, float, np.ndarray]:
        """Truth mesh for a contact: (mesh, fine spacing mm, footprint points (k, 2))."""
        pts, _ = footprint(field_, self.geometry, pitch_mm=0.05)
        if len(pts) == 0:
            raise ValueError("the indenter does not reach below the rest surface anywhere on "
                             "the pad: press deeper or move it onto the pad")
        if h_fine_mm is None:
            h_fine_mm = fine_spacing(len(pts) * 0.05**2)
        if region_xy is None:
            # The fine region: the footprint grown by 3 fine spacings (lateral slide, rim).
            margin = max(3.0 * h_fine_mm, 0.3)
            region_xy = _dilate(pts, margin, h_fine_mm)
        tip = deepest_point(field_, pts, self.geometry)
        # A sharp tip (the intrusion bends by more than 0.3 in slope across it): triangles
        # around it a quarter of the fine spacing, so their chords follow a cone's flanks.
        probe = 0.025
        ring = tip + probe * np.array([[1, 0], [-1, 0], [0, 1], [0, -1]])
        sharp = float(field_(tip[None])[0] - np.mean(field_(ring))) > 0.3 * probe
        spots = [(float(tip[0]), float(tip[1]), 0.25 * h_fine_mm)] if sharp else []
        mesh = build_truth_mesh(self.geometry, region_xy, h_fine_mm, h_coarse_mm=self.h_coarse_mm,
                                surface_nodes_xy=tip[None], point_sizes=spots)
        return mesh, h_fine_mm, pts

    def solve(self, indenter, pose, **kwargs) -> TruthSolution:
        """Contact of a library ``indenter`` pressed at ``pose`` (:class:`ContactPose`)."""
        return self.solve_field(indenter_field(indenter, pose), **kwargs)

    def solve_field(self, field_: IntrusionField, mesh: PadMesh | None = None,
                    h_fine_mm: float | None = None, features: np.ndarray | None = None
                    ) -> TruthSolution:
        """Contact for an intrusion field; ``mesh`` overrides the automatic truth mesh,
        ``features`` (k, 2) adds indenter points (sensor frame, mm) to the constraints."""
        if mesh is None:
            mesh, h_fine_mm, fp = self.mesh_for(field_, h_fine_mm)
        else:
            fp, _ = footprint(field_, self.geometry, pitch_mm=0.05)
            if h_fine_mm is None:
                h_fine_mm = float(np.sqrt(mesh.sensing_nodal_areas_mm2().min() * 2.0))
        return _Solve(self, mesh, field_, h_fine_mm, fp, features).run()


def deepest_point(field_: IntrusionField, fp: np.ndarray, geometry: PadGeometry,
                  pitch_mm: float = 0.005) -> np.ndarray:
    """The sensor-frame point (2,) mm where the indenter reaches deepest (a cone's tip), found
    on the footprint grid ``fp`` and refined on a ``pitch_mm`` grid around it. The truth mesh
    puts a node there, so that a tip rests on a node rather than inside a triangle."""
    d = field_(fp)
    best = fp[int(np.argmax(d))]
    step = float(np.min(np.abs(np.diff(np.unique(fp[:, 0]))))) if len(np.unique(fp[:, 0])) > 1 else 0.05
    xs = best[0] + np.arange(-step, step + pitch_mm / 2, pitch_mm)
    ys = best[1] + np.arange(-step, step + pitch_mm / 2, pitch_mm)
    grid = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    grid = grid[geometry.contains_xy(grid[:, 0], grid[:, 1], margin_mm=0.05)]
    if len(grid) == 0:
        return best
    return grid[int(np.argmax(field_(grid)))]


def _dilate(points: np.ndarray, margin: float, pitch: float) -> np.ndarray:
    """Points of a ``pitch`` grid within ``margin`` of ``points`` (k, 2)."""
    lo, hi = points.min(0) - margin, points.max(0) + margin
    xs = np.arange(lo[0], hi[0] + pitch, pitch)
    ys = np.arange(lo[1], hi[1] + pitch, pitch)
    grid = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    d, _ = cKDTree(points).query(grid, distance_upper_bound=margin)
    return grid[np.isfinite(d)]


def feature_points(field_: IntrusionField, fp: np.ndarray, h_fine: float,
                   geometry: PadGeometry, pitch_mm: float = 0.025) -> np.ndarray:
    """Points (k, 2) mm of the indenter's sharp convex features over its footprint ``fp``
    (cone and pyramid tips, edges, punch rims): where the intrusion, sampled on a ``pitch_mm``
    grid, bends by more than 0.3 in slope between neighbours, thinned to ``h_fine / 2`` apart.
    Smooth parts need none (the fine mesh follows them within its sag)."""
    if len(fp) == 0:
        return np.zeros((0, 2))
    lo, hi = fp.min(0), fp.max(0)
    xs = np.arange(lo[0] - pitch_mm, hi[0] + 2 * pitch_mm, pitch_mm)
    ys = np.arange(lo[1] - pitch_mm, hi[1] + 2 * pitch_mm, pitch_mm)
    X, Y = np.meshgrid(xs, ys)
    D = field_(np.stack([X.ravel(), Y.ravel()], 1)).reshape(X.shape)
    covered = np.isfinite(D)
    D = np.where(covered, D, -1e3)
    c = D[1:-1, 1:-1]
    # Only features inside the footprint (a tip, an edge pointing into the gel); its outline (a
    # punch's rim, where the indenter's wall rises vertically) is left to the sensing nodes:
    # constraining a triangle across it would drag the gel below the indenter's face.
    inner = np.ones_like(c, dtype=bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inner &= covered[1 + dy: covered.shape[0] - 1 + dy, 1 + dx: covered.shape[1] - 1 + dx]
    kink = np.zeros_like(c, dtype=bool)
    diag = pitch_mm * math.sqrt(2.0)
    for a, b, spacing in ((D[1:-1, :-2], D[1:-1, 2:], pitch_mm), (D[:-2, 1:-1], D[2:, 1:-1], pitch_mm),
                          (D[:-2, :-2], D[2:, 2:], diag), (D[:-2, 2:], D[2:, :-2], diag)):
        kink |= (2 * c - a - b) > 0.3 * spacing
    kink &= (c > 0) & inner
    pts = np.stack([X[1:-1, 1:-1][kink], Y[1:-1, 1:-1][kink]], 1)
    depth = c[kink]
    pts = pts[geometry.contains_xy(pts[:, 0], pts[:, 1])]
    if len(pts) == 0:
        return pts
    # Thin out, deepest first, so that a tip keeps its lowest point.
    order = np.argsort(-depth[: len(pts)], kind="stable")
    pts = pts[order]
    tree = cKDTree(pts)
    keep = np.ones(len(pts), bool)
    for i in range(len(pts)):
        if keep[i]:
            near = tree.query_ball_point(pts[i], 0.5 * h_fine)
            keep[near] = False
            keep[i] = True
    return pts[keep]


class _Solve:
    """One augmented-Lagrangian Newton solve (state of the iterations)."""

    def __init__(self, solver: TruthSolver, mesh: PadMesh, field_: IntrusionField,
                 h_fine: float, fp: np.ndarray, features):
        self.s = solver
        self.mesh = mesh
        self.field = field_
        self.h_fine = h_fine
        mat = solver.material
        self.geometric = solver.model != "linear"
        self.gel = gel_model(solver.model, mesh.vertices, mesh.tets, mat.E_mpa, mat.nu)
        self.dofs = _dof_map(mesh, solver.supports)
        n_plane = mesh.n_plane
        X = mesh.vertices[:n_plane]
        # Candidate sensing nodes: near the footprint.
        if len(fp):
            dist, _ = cKDTree(fp).query(X[:, :2])
        else:
            dist = np.full(n_plane, np.inf)
        reach = 3.0 * h_fine + 0.5
        self.cand_nodes = np.flatnonzero(dist < reach)
        pts = feature_points(field_, fp, h_fine, solver.geometry)
        if features is not None:
            pts = np.concatenate([pts, np.asarray(features, float).reshape(-1, 2)])
        self.ind_xy = pts
        self.ind_z = -field_(pts) if len(pts) else np.zeros(0)
        keep = np.isfinite(self.ind_z)
        self.ind_xy, self.ind_z = self.ind_xy[keep], self.ind_z[keep]
        # Surface triangles that can hold an indenter point.
        tri = mesh.plane_triangles
        tri_centroid = X[tri].mean(axis=1)[:, :2]
        if len(fp):
            dt, _ = cKDTree(fp).query(tri_centroid)
        else:
            dt = np.full(len(tri), np.inf)
        self.cand_tris = tri[dt < reach + 2 * h_fine]
        areas = mesh.sensing_nodal_areas_mm2()
        self.areas = areas
        lam_, mu_ = mat.lame_mpa
        top = h_fine  # the edge length under the contact
        self.rho_node = solver.settings.rho_factor * mu_ * areas / top  # N/mm per node
        self.rho_point = solver.settings.rho_factor * mu_ * h_fine**2 / top
        self.n_plane = n_plane
        self.lam_node = np.zeros(n_plane)
        self.lam_point = np.zeros(len(self.ind_xy))
        self.t_T = np.zeros((n_plane, 3))  # tangential traction multipliers (friction)
        self.friction = mat.friction
        self.mu_f = mat.mu
        self.lift = 0.0  # the indenter raised by this much (mm) during load steps
        self._factor = None
        self._M0 = None
        self.factorizations = 0
        self.pcg_iterations = 0

    # ------------------------------------------------------------------------ constraints
    def constraints(self, u: np.ndarray) -> _Constraints:
        X = self.mesh.vertices
        nodes = self.cand_nodes
        p = X[nodes] + u[nodes]
        xy = p[:, :2] if self.geometric else X[nodes, :2]
        d, grad = self.field.with_gradient(xy)
        d = d - self.lift
        covered = np.isfinite(d)
        gap_n = np.where(covered, -d - p[:, 2], np.inf)
        w_n = np.zeros((len(nodes), 3, 3))
        w_n[:, 0, 2] = -1.0
        if self.geometric:
            w_n[:, 0, :2] = -grad
        nodes_n = np.stack([nodes, nodes, nodes], 1)
        share_n = np.array([[1.0, 0.0, 0.0]]).repeat(len(nodes), 0)
        # Indenter points against the gel's current surface.
        tris = self.cand_tris
        if len(self.ind_xy) and len(tris):
            P = X[tris] + u[tris]  # (t, 3, 3)
            locate_xy = P[:, :, :2] if self.geometric else X[tris][:, :, :2]
            which, bary = locate_in_triangles(self.ind_xy, locate_xy)
            corners = tris[which]
            z_gel = np.einsum("qa,qa->q", bary, P[which, :, 2])
            gap_p = self.ind_z + self.lift - z_gel
            w_p = np.zeros((len(which), 3, 3))
            w_p[:, :, 2] = -bary
            if self.geometric:
                slope = _triangle_slopes(P[which])  # (q, 2)
                w_p[:, :, :2] = bary[:, :, None] * slope[:, None, :]
            share_p = np.clip(bary, 0.0, None)
            share_p /= share_p.sum(1, keepdims=True)
        else:
            gap_p = np.zeros(0)
            w_p = np.zeros((0, 3, 3))
            corners = np.zeros((0, 3), np.int64)
            share_p = np.zeros((0, 3))
        return _Constraints(
            gap=np.concatenate([gap_n, gap_p]),
            nodes=np.concatenate([nodes_n, corners]),
            weights=np.concatenate([w_n, w_p]),
            share=np.concatenate([share_n, share_p]),
        )

    # -------------------------------------------------------------------------- pieces
    def multipliers(self):
        return np.concatenate([self.lam_node[self.cand_nodes], self.lam_point])

    def rho(self):
        return np.concatenate([self.rho_node[self.cand_nodes],
                               np.full(len(self.ind_xy), self.rho_point)])

    def set_multipliers(self, lam):
        k = len(self.cand_nodes)
        self.lam_node[:] = 0.0
        self.lam_node[self.cand_nodes] = lam[:k]
        self.lam_point = lam[k:]

    def normal_forces(self, c: _Constraints, lam: np.ndarray) -> np.ndarray:
        """Normal contact force carried by each sensing node, (n_plane,) N."""
        fn = np.zeros(self.n_plane)
        np.add.at(fn, c.nodes.ravel(), (lam[:, None] * c.share).ravel())
        return fn

    def indenter_normals(self, u: np.ndarray) -> np.ndarray:
        """Unit normal of the indenter (pointing into the gel, -z side) at each sensing node."""
        X = self.mesh.vertices[: self.n_plane]
        n = np.zeros((self.n_plane, 3))
        n[:, 2] = -1.0
        if self.geometric:
            nodes = self.cand_nodes
            xy = X[nodes, :2] + u[nodes, :2]
            d, grad = self.field.with_gradient(xy)
            v = np.column_stack([-grad, -np.ones(len(nodes))])
            n[nodes] = v / np.linalg.norm(v, axis=1, keepdims=True)
        return n

    def friction_bound(self, fn: np.ndarray) -> np.ndarray:
        if self.friction == "frictionless":
            return np.zeros_like(fn)
        if self.friction == "stick":
            return np.where(fn > 0, np.inf, 0.0)
        return self.mu_f * fn

    # -------------------------------------------------------------------------- merit
    def merit(self, u, lam, rho, bound, normals):
        """Augmented energy for fixed multipliers; +inf where an element inverts."""
        e = self.gel.energy(u)
        if not np.isfinite(e):
            return np.inf
        c = self.constraints(u)
        a = np.maximum(0.0, lam - rho * c.gap)
        e += float(np.sum((a**2 - lam**2) / (2 * rho)))
        if self.friction != "frictionless":
            e += self._friction_energy(u, bound, normals)
        return e

    def _tangential(self, u, normals):
        P = np.eye(3)[None] - normals[:, :, None] * normals[:, None, :]
        uT = np.einsum("nij,nj->ni", P, u[: self.n_plane])
        return P, uT

    def _friction_energy(self, u, bound, normals):
        _, uT = self._tangential(u, normals)
        rho = self.rho_node[:, None]
        tau = self.t_T - rho * uT
        nt = np.linalg.norm(tau, axis=1)
        b = bound
        stick = nt <= b
        e = np.where(stick, nt**2, 2 * np.where(np.isfinite(b), b, 0) * nt - np.where(np.isfinite(b), b, 0) ** 2)
        e = e - np.sum(self.t_T**2, axis=1)
        return float(np.sum(e / (2 * self.rho_node)))

    # -------------------------------------------------------------------------- Newton
    def gradient_and_hessian(self, u, lam, rho, bound, normals):
        f_int, K_mat = self.gel.forces_and_stiffness(u)
        K = sp.csr_matrix(K_mat.shape)
        c = self.constraints(u)
        a = np.maximum(0.0, lam - rho * c.gap)
        n3 = 3 * self.mesh.n_nodes
        dofs = (3 * c.nodes[:, :, None] + np.arange(3)[None, None, :]).reshape(len(c.gap), 9)
        w = c.weights.reshape(len(c.gap), 9)
        grad = f_int.ravel().copy()
        np.add.at(grad, dofs.ravel(), (-a[:, None] * w).ravel())
        act = a > 0
        if np.any(act):
            da, wa = dofs[act], w[act] * np.sqrt(rho[act])[:, None]
            rows = np.repeat(np.arange(int(act.sum())), 9)
            G = sp.csr_matrix((wa.ravel(), (rows, da.ravel())), shape=(int(act.sum()), n3))
            K = K + (G.T @ G)
        if self.friction != "frictionless":
            P, uT = self._tangential(u, normals)
            rho_n = self.rho_node
            tau = self.t_T - rho_n[:, None] * uT
            nt = np.linalg.norm(tau, axis=1)
            stick = nt <= bound
            scale = np.where(stick, 1.0, np.where(nt > 0, bound / np.maximum(nt, 1e-300), 0.0))
            scale = np.where(np.isfinite(scale), scale, 1.0)
            t = tau * scale[:, None]
            node_dofs = 3 * np.arange(self.n_plane)[:, None] + np.arange(3)
            grad[node_dofs.ravel()] -= np.einsum("nij,nj->ni", P, t).ravel()
            that = tau / np.maximum(nt, 1e-300)[:, None]
            blocks = rho_n[:, None, None] * np.where(
                stick[:, None, None], P, scale[:, None, None] * (P - that[:, :, None] * that[:, None, :]))
            rows = np.repeat(node_dofs, 3, axis=1).ravel()
            cols = np.tile(node_dofs, (1, 3)).ravel()
            K = K + sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(n3, n3))
        return grad, (K_mat, K.tocsr()), c, a

    def _preconditioner_base(self) -> sp.csr_matrix:
        """Narrow-stencil stand-in for the material stiffness: linear tets with the bulk term
        per element at ``precond_bulk`` of the bulk modulus (the locking-free stiffness's wide
        stencil makes its own factor ~10x dearer; this one is spectrally close)."""
        if self._M0 is None:
            from tactile_deploy.fem.elasticity import (
                _scatter_element_matrices,
                element_stiffness,
                shape_gradients,
            )

            lam, mu = self.s.material.lame_mpa
            kappa = lam + 2.0 * mu / 3.0
            g, V = shape_gradients(self.mesh.vertices, self.mesh.tets)
            ke = element_stiffness(g, V, -2.0 * mu / 3.0 + self.s.settings.precond_bulk * kappa, mu)
            M = _scatter_element_matrices(ke, self.mesh.tets, self.mesh.n_nodes)
            T = self.dofs.T
            self._M0 = (T.T @ M @ T).tocsr()
        return self._M0

    def _linear_solve(self, Kq: sp.csr_matrix, b: np.ndarray, extra_q: sp.csr_matrix) -> np.ndarray:
        """Solve ``Kq x = b`` by conjugate gradients, preconditioned by the Cholesky factor of
        the narrow-stencil stiffness plus this step's contact and friction terms (kept while
        CG converges within ``pcg_max`` iterations, refactored otherwise)."""
        import scipy.sparse.linalg as spla

        st = self.s.settings
        for attempt in range(2):
            if self._factor is None or attempt == 1:
                M = self._preconditioner_base() + extra_q
                self._factor = SparseCholesky(M)
                self.factorizations += 1
            P = spla.LinearOperator(Kq.shape, matvec=self._factor.solve, dtype=float)
            count = [0]

            def cb(_):
                count[0] += 1

            x, info = spla.cg(Kq, b, rtol=st.pcg_rtol, atol=0.0, maxiter=st.pcg_max, M=P,
                              callback=cb)
            self.pcg_iterations += count[0]
            if info == 0 and np.all(np.isfinite(x)):
                return x
        # CG did not converge with a fresh preconditioner: the tangent is indefinite (large
        # compression); a direct solve of the shifted system still gives a descent step.
        diag = sp.diags(Kq.diagonal())
        for shift in (0.0, 1e-3, 1e-2, 1e-1, 1.0):
            try:
                return SparseCholesky(Kq + shift * diag if shift else Kq).solve(b)
            except ValueError:
                continue
        raise TruthSolveError("Newton matrix not positive definite even when shifted")

    def _newton_step(self, u, lam, rho, bound, normals):
        """One Newton step with line search on the augmented energy (multipliers fixed).
        Returns (new u, step length, relative force residual before the step)."""
        T = self.dofs.T
        grad, (K_mat, K_extra), _, _ = self.gradient_and_hessian(u, lam, rho, bound, normals)
        gq = T.T @ grad
        extra_q = (T.T @ K_extra @ T).tocsr()
        Kq = (T.T @ K_mat @ T).tocsr() + extra_q
        step = self._linear_solve(Kq, -gq, extra_q)
        du = (T @ step).reshape(-1, 3)
        m0 = self.merit(u, lam, rho, bound, normals)
        slope = float(gq @ step)
        t = 1.0
        while True:
            m1 = self.merit(u + t * du, lam, rho, bound, normals)
            if np.isfinite(m1) and m1 <= m0 + 1e-4 * t * slope + 1e-13 * abs(m0):
                break
            t *= 0.5
            if t < 1e-6:
                break
        return u + t * du, t, float(np.abs(gq).max()), float(np.abs(du).max())

    def run(self) -> TruthSolution:
        """Load steps (the indenter lowered in equal depth increments, large deformation only),
        each solved to the tolerances."""
        st = self.s.settings
        u = np.zeros((self.mesh.n_nodes, 3))
        depth = max(float(np.max(self.field(self.mesh.vertices[self.cand_nodes, :2]), initial=0.0)),
                    1e-3)
        n_steps = 1
        if self.geometric:
            n_steps = max(1, math.ceil(depth / (st.step_strain * self.s.geometry.thickness_mm)))
        history = []
        for k in range(1, n_steps + 1):
            self.lift = depth * (1.0 - k / n_steps)
            u, c, lam, it = self._solve_step(u, depth, history)
        return self._solution(u, c, lam, it, history)

    def _solve_step(self, u, depth, history):
        st = self.s.settings
        rho = self.rho()
        normals = self.indenter_normals(u)
        fn = self.normal_forces(self.constraints(u), self.multipliers())
        newton = 0
        for it in range(1, st.max_iterations + 1):
            lam = self.multipliers()
            bound = self.friction_bound(fn)
            for _ in range(st.max_newton):  # minimise the augmented energy for these multipliers
                u, t, res, du_max = self._newton_step(u, lam, rho, bound, normals)
                newton += 1
                if t == 1.0 and du_max <= st.step_tol * depth:
                    break
            c = self.constraints(u)
            lam_new = np.maximum(0.0, lam - rho * c.gap)
            self.set_multipliers(lam_new)
            fn_new = self.normal_forces(c, lam_new)
            if self.friction != "frictionless":
                normals = self.indenter_normals(u)
                P, uT = self._tangential(u, normals)
                tau = self.t_T - self.rho_node[:, None] * uT
                nt = np.linalg.norm(tau, axis=1)
                b = self.friction_bound(fn_new)
                scale = np.where(nt <= b, 1.0, b / np.maximum(nt, 1e-300))
                self.t_T = tau * scale[:, None]
            total = max(float(fn_new.sum()), 1e-300)
            pen = float(max(0.0, -c.gap.min())) if len(c.gap) else 0.0
            change = float(np.abs(fn_new - fn).max()) / total
            fn = fn_new
            history.append((newton, pen, change))
            log.debug("step lift %.4f mm, update %d: %d Newton steps, penetration %.3g um, force "
                      "change %.2g, factorizations %d, PCG %d", self.lift, it, newton, pen * 1e3,
                      change, self.factorizations, self.pcg_iterations)
            if pen <= st.penetration_tol_mm and change <= st.force_tol:
                return u, c, lam_new, it
        raise TruthSolveError(
            f"contact iterations did not converge in {st.max_iterations} multiplier updates "
            f"({newton} Newton steps, indenter {self.lift:.3g} mm above its final depth): "
            f"penetration {pen * 1e3:.3g} um, nodal force change {change:.2g} of the total")

    def _solution(self, u, c, lam, it, history) -> TruthSolution:
        n_plane = self.n_plane
        f = np.zeros(3 * self.mesh.n_nodes)
        dofs = (3 * c.nodes[:, :, None] + np.arange(3)[None, None, :]).reshape(len(c.gap), 9)
        np.add.at(f, dofs.ravel(), (lam[:, None] * c.weights.reshape(len(c.gap), 9)).ravel())
        forces = f.reshape(-1, 3)[:n_plane].copy()
        normals = self.indenter_normals(u)
        if self.friction != "frictionless":
            P, _ = self._tangential(u, normals)
            forces += np.einsum("nij,nj->ni", P, self.t_T)
        fn = self.normal_forces(c, lam)
        in_contact = fn > 1e-12 * max(fn.max(), 1e-300)
        if self.friction == "stick":
            sticking = in_contact.copy()
        elif self.friction == "frictionless":
            sticking = np.zeros(n_plane, bool)
        else:
            tn = np.linalg.norm(self.t_T, axis=1)
            sticking = in_contact & (tn < (1.0 - 1e-6) * self.mu_f * fn)
        return TruthSolution(
            mesh=self.mesh, displacements_mm=u, contact_forces_n=forces, normal_force_n=fn,
            in_contact=in_contact, sticking=sticking, force_n=float(-forces[:, 2].sum()),
            tangential_force_n=forces[:, :2].sum(0),
            max_penetration_mm=float(max(0.0, -c.gap.min())) if len(c.gap) else 0.0,
            iterations=it,
            info={"history": history, "n_nodes": self.mesh.n_nodes,
                  "factorizations": self.factorizations, "pcg_iterations": self.pcg_iterations,
                  "n_constraints": len(c.gap), "h_fine_mm": self.h_fine},
        )


def _dof_map(mesh: PadMesh, supports: Supports):
    """The free-coordinate map of ``mesh``; for the sensor's supports (bonded backplate, free
    sides) a plain selection of the free nodes' x, y, z, built directly."""
    if supports != SENSOR_SUPPORTS:
        return build_dof_map(mesh, supports)
    from tactile_deploy.fem.constraints import DofMap

    n = mesh.n_nodes
    free = np.setdiff1d(np.arange(n), mesh.backplate_nodes)
    rows = (3 * free[:, None] + np.arange(3)).ravel()
    T = sp.csr_matrix((np.ones(len(rows)), (rows, np.arange(len(rows)))), shape=(3 * n, len(rows)))
    return DofMap(T=T, node_of_col=np.repeat(free, 3),
                  direction_of_col=np.tile(np.eye(3), (len(free), 1)),
                  z_col=np.full(n, -1), xy_cols=np.full((n, 2), -1))


def _triangle_slopes(P: np.ndarray) -> np.ndarray:
    """Gradient (dz/dx, dz/dy) of the plane through each triangle (q, 3, 3), (q, 2)."""
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    nrm = np.cross(e1, e2)
    nz = np.where(np.abs(nrm[:, 2]) > 1e-300, nrm[:, 2], 1e-300)
    return np.column_stack([-nrm[:, 0] / nz, -nrm[:, 1] / nz])


def surface_penetration(sol: TruthSolution, field_: IntrusionField, pitch_mm: float = 0.01,
                        geometric: bool = True) -> tuple[float, np.ndarray]:
    """Penetration of the indenter into the gel's continuous (piecewise-linear) surface, mm.

    Checked at every point of a ``pitch_mm`` grid over the indenter's footprint (the gel's
    deformed surface height under the point against the indenter's) and at every deformed
    sensing node (against the indenter above it). Returns (largest penetration, the points'
    penetrations (k,)). ``geometric=False`` measures in the rest positions (small strain).
    """
    mesh = sol.mesh
    fp, _ = footprint(field_, mesh.geometry, pitch_mm=pitch_mm)
    X = mesh.vertices[: mesh.n_plane]
    P = X + sol.displacements_mm[: mesh.n_plane]
    tri = mesh.plane_triangles
    out = [np.zeros(1)]
    if len(fp):
        near = cKDTree(fp).query(X[:, :2], distance_upper_bound=1.0)[0] < np.inf
        tris = tri[near[tri].any(axis=1)]
        loc = P[tris][:, :, :2] if geometric else X[tris][:, :, :2]
        which, bary = locate_in_triangles(fp, loc)
        z_gel = np.einsum("qa,qa->q", bary, P[tris[which]][:, :, 2])
        inside = bary.min(axis=1) > -1e-9
        out.append(np.where(inside, z_gel + field_(fp), -np.inf))
    xy = P[:, :2] if geometric else X[:, :2]
    d = field_(xy)
    out.append(np.where(np.isfinite(d), P[:, 2] + d, -np.inf))
    pen = np.concatenate(out)
    return float(max(pen.max(), 0.0)), pen
