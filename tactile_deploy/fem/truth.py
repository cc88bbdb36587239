"""Resolved contact of a rigid indenter with the gel: the reference ("truth") solver.

Data flow of :meth:`TruthSolver.solve`::

    indenter + pose --(intrusion footprint)--> refinement region, fine spacing
        --> truth mesh (tactile_deploy.fem.truth_mesh: refined where contact can occur,
            finer where the indenter curves and along a punch's rim)
        --> contact constraints on the continuous surface (below)
        --> semismooth Newton on the contact sets (neo-Hookean or linear gel, Coulomb friction)
        --> TruthSolution (truth-mesh displacements, nodal contact forces, stick/slip)

Contact (sensor frame, mm; the indenter moves only along -z). The indenter is the solid above
its lower surface ``z = -delta(x, y)`` (``delta`` = its intrusion below the rest surface, from
the indenter's envelope); where the envelope ends in a wall (a punch's side), the solid's side
rises vertically along the envelope's outline. Two families of gap constraints ``g >= 0`` keep
the gel's piecewise-linear surface outside it:

* **gel points**: every sensing node p of the truth mesh near the contact, at its *current*
  position: ``g`` its distance to the solid to first order (:func:`solid_gap`: the face's
  normalised vertical gap; beside a wall the horizontal distance to it, below a sharp rim the
  distance to the rim). Its gradient is the solid's normal, so the contact traction is normal
  to the indenter;
* **indenter points**: the indenter's sharp convex features over the contact (cone and pyramid
  tips, edges pointing into the gel): ``g = z_i - z_gel(x_i, y_i)``, the gel's current surface
  height under the point, so a feature between nodes cannot pass through a triangle;
* **the apex** of a sharp tip (a cone's), large deformation: the truth mesh has a sensing node
  there, held at the tip while the tip's force on it lies within the flanks' normal cone
  (:meth:`_Solve._init_vertex`).

``model="linear"`` is the small-strain limit: linear material, gaps along z at the rest
positions. Friction (per sensing node, tangent plane of the indenter at the node): frictionless,
stick (no tangential displacement where in contact), or Coulomb with coefficient mu (traction
``|t_T| <= mu t_N``, slip opposite to the traction). Slip is measured from the rest position
(the indenter pressed straight down; a slide after pressing is measured relative to it).

The complementarity problem is solved exactly to a tolerance (no penalty stiffness remains in
the solution): semismooth Newton on the contact, stick and slip sets (primal-dual active set),
each step solving the tangent system with the active constraints holding exactly in their
linearised form; the sets are re-chosen after each step from the complementarity functions
(:meth:`_Solve._solve_step`). Large deformation: the depth in increments of a tenth of the
thickness (at most ``SolveSettings.tip_step_mm`` under a sharp tip), an increment that fails
halved. docs/fem.md states what is validated against what.

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
from tactile_deploy.fem.hyperelastic import gel_model
from tactile_deploy.fem.material import Material
from tactile_deploy.fem.sparse_solver import SymmetricFactor, nested_dissection_order
from tactile_deploy.fem.truth_mesh import BULK_GROWTH, DEPTH_GROWTH, build_truth_mesh
from tactile_deploy.pad.geometry import PadGeometry
from tactile_deploy.pad.mesh import PadMesh

log = logging.getLogger(__name__)

#: Largest fine spacing of a truth mesh: the depth-camera pixel (35 mm / 128).
H_FINE_MAX_MM = 0.27
#: Fine spacing relative to the equivalent radius of the indenter's footprint.
H_FINE_PER_RADIUS = 1.0 / 10.0
#: Smallest fine spacing.
H_FINE_MIN_MM = 0.05
#: Largest chord sag (mm) of the sensing surface under a curved indenter: where the indenter
#: curves by kappa (1/mm), edges are at most sqrt(8 SAG / kappa) long (sag = h^2 kappa / 8).
CHORD_SAG_MM = 0.003
#: How far inside an indenter's outline (mm) the height of its face at the rim is read.
RIM_PROBE_MM = 0.04
#: An indenter's outline is a wall (a punch's side) where its face there reaches this far
#: (mm) below the rest surface.
RIM_WALL_MM = 0.02
#: Edge length along such a rim, as a fraction of the fine spacing (half of it at the
#: outline's corners); nodes within one such edge of the rim carry no friction.
RIM_SPACING_FRACTION = 1.0 / 3.0
#: Edge length at the outline's corners, relative to the rest of the rim.
RIM_CORNER_FACTOR = 0.5
#: A point of the indenter is a sharp tip where its surface around it (:data:`TIP_PROBE_MM`
#: away) rises by more than this slope: a cone's or a pyramid's apex.
TIP_SLOPE_BREAK = 0.3
#: Radius (mm) at which the flanks around a tip are probed: the envelope's pixel.
TIP_PROBE_MM = 0.025
#: Edge length at a sharp tip, as a fraction of the fine spacing, per gel model: small-strain,
#: a quarter (the chords then follow a cone's flanks); large deformation, a half (before the
#: gel's collapse barrier a quarter's elements below the apex, crushed flat as the tip goes
#: deeper, folded: a 90-degree cone stopped at 0.55 of 0.8 mm; with it a quarter solves at 3.4
#: times the time, the surface's largest penetration 24.3 against 30.3 um, docs/fem.md).
TIP_SIZE_FRACTION = {"linear": 0.25, "neo-hookean": 0.5}
#: A sensing node this close (mm) to a sharp tip's apex is the apex's node.
VERTEX_SNAP_MM = 1e-4


class TruthSolveError(RuntimeError):
    """The nonlinear contact iterations did not converge (message names the figures)."""


class NewtonBudgetError(TruthSolveError):
    """The solve used up :attr:`SolveSettings.max_newton_steps` (no depth increment is retried)."""


@dataclass(frozen=True)
class SolveSettings:
    """Tolerances and limits of the semismooth Newton iterations."""

    penetration_tol_mm: float = 1e-5  # largest penetration at convergence
    force_tol: float = 1e-6  # largest change of a slip force, relative to the total force
    max_iterations: int = 60  # Newton steps per load step
    step_tol: float = 1e-9  # converged when the largest step is below this x depth
    floor_tol: float = 1e-6  # ... or below this x depth and no longer shrinking (round-off floor)
    step_strain: float = 0.1  # load-step depth as a fraction of the pad thickness (large strain)
    # Load steps before the last only carry the solution along: they stop at these looser
    # tolerances (the friction law depends on the total slip, not on the path, so the last
    # step's tolerances alone fix the answer).
    intermediate_step_tol: float = 1e-4  # x depth
    intermediate_force_tol: float = 1e-4
    intermediate_penetration_mm: float = 1e-4
    # Modified Newton: a factorised tangent is reused while the active, stick and slip sets
    # stay the same and each step shrinks to at most this fraction of the one before.
    reuse_contraction: float = 0.8
    anderson_depth: int = 5  # steps remembered when mixing the slip forces
    slide_steps: int = 2  # increments of a tangential slide (after the indenter is pressed)
    max_load_splits: int = 3  # failed depth increments retried as two halves, at most
    # Newton steps of the whole solve (every load step and retry) at most; None: no bound. A
    # bound makes a solve that wanders fail in a known time (benchmarks, batches of contacts).
    max_newton_steps: int | None = None
    # The tangents' direct solver (:class:`SymmetricFactor`): "pardiso" (the pardiso extra),
    # "superlu", or None: PARDISO where installed, else SuperLU.
    linear_solver: str | None = None
    # Depth increments (mm) at most under a sharp tip (a cone's apex; large deformation): the
    # gel below the apex is crushed flat, and a longer increment's first Newton steps fold it.
    tip_step_mm: float = 0.1


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
    ``coverage(xy (k, 2)) -> (signed distance (k,) mm, unit gradient (k, 2))``, optional: the
    signed distance to the edge of the covered region (negative inside). Where it is given, the
    indenter is the solid above ``z = -delta`` bounded by vertical walls along that edge (a
    punch's side), and gaps are distances to that solid (:func:`solid_gap`).
    """

    def __init__(self, fn, step_mm: float = 1e-4, coverage=None):
        self.fn = fn
        self.step = step_mm
        self.coverage = coverage

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
    coverage = None
    if hasattr(indenter, "coverage_distance_mm"):
        coverage = lambda xy: indenter.coverage_distance_mm(xy, pose)  # noqa: E731
    return IntrusionField(lambda xy: indenter.intrusion_mm(xy, pose), coverage=coverage)


def solid_gap(field_: IntrusionField, p: np.ndarray, from_side: np.ndarray | None = None,
              with_side: bool = False):
    """Gap (k,) mm and unit normal (k, 3) of points p (k, 3) (sensor frame, mm) against the
    indenter solid, in the deformed configuration.

    The solid is ``z >= -delta(x, y)`` over the region the indenter covers. The gap is its
    signed distance to first order (negative inside); the normal is the gap's gradient
    (pointing out of the indenter, into the gel):

    * the face: ``g = (-delta - z) / sqrt(1 + |grad delta|^2)``;
    * without ``field_.coverage``: the face wherever the indenter covers the point, +inf
      elsewhere (the indenter is its pressing surface only);
    * with it, the covered region ends in a vertical wall along its outline (a punch's side).
      Beside the outline and above the rim (where face and wall meet): the horizontal distance
      to the wall; below the rim: the distance to the rim (a sharp edge: the normal turns
      from the wall's to the face's). Inside the solid, the wall pushes out sideways only the
      points flagged ``from_side`` (k,) that are nearer the wall than the face (they were
      beside the indenter before: they came in through its side, not by the indenter coming
      down on them); the others are pushed back through the face.

    ``with_side``: also return a mask (k,) of the points beside the indenter (outside its
    outline) or measured against its wall: the ``from_side`` of the next evaluation.
    """
    p = np.asarray(p, np.float64)
    d, grad = field_.with_gradient(p[:, :2])
    norm = np.sqrt(1.0 + (grad**2).sum(1))
    covered = np.isfinite(d)
    gap = np.where(covered, (-d - p[:, 2]) / norm, np.inf)
    normal = np.column_stack([-grad, -np.ones(len(p))]) / norm[:, None]
    if field_.coverage is None or len(p) == 0:
        return (gap, normal, np.zeros(len(p), bool)) if with_side else (gap, normal)
    side_flag = np.zeros(len(p), bool) if from_side is None else np.asarray(from_side, bool)
    sd, away = field_.coverage(p[:, :2])
    beside = sd > 0
    # The outline is the coverage's (a smooth line through the envelope's pixel staircase);
    # near it the face's height is read just inside it, where the intrusion is surely defined.
    fix = (~covered | (sd > -RIM_PROBE_MM)) & np.isfinite(sd)
    if np.any(fix):
        probe = p[fix, :2] - (np.maximum(sd[fix], -RIM_PROBE_MM) + RIM_PROBE_MM)[:, None] * away[fix]
        d_r, grad_r = field_.with_gradient(probe)
        ok = np.isfinite(d_r)
        n_r = np.sqrt(1.0 + (grad_r**2).sum(1))
        gap[fix] = np.where(ok, (-d_r - p[fix, 2]) / n_r, gap[fix])
        normal[fix] = np.where(ok[:, None], np.column_stack([-grad_r, -np.ones(len(d_r))])
                               / n_r[:, None], normal[fix])
        d = d.copy()
        d[fix] = np.where(ok, d_r, d[fix])
    through_side = ~beside & side_flag & (gap < 0) & (-sd < -gap)
    k = np.flatnonzero(beside | through_side)
    side = beside.copy()
    if len(k) == 0:
        return (gap, normal, side) if with_side else (gap, normal)
    s_k, a_k = np.maximum(sd[k], 0.0), away[k]
    dz = p[k, 2] + d[k]  # height above the rim (-inf where the face is unknown)
    below = beside[k] & np.isfinite(dz) & (dz < 0)
    dist = np.hypot(s_k, np.where(below, dz, 0.0))
    n_rim = np.column_stack([s_k[:, None] * a_k, np.where(below, dz, 0.0)])
    n_rim = np.where((dist > 1e-12)[:, None], n_rim / np.maximum(dist, 1e-300)[:, None],
                     np.array([[0.0, 0.0, -1.0]]))
    wall = ~below
    gap[k] = np.where(below, dist, sd[k])
    normal[k] = np.where(below[:, None], n_rim, np.column_stack([a_k, np.zeros(len(k))]))
    side[k] |= wall
    return (gap, normal, side) if with_side else (gap, normal)


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
    bulk_growth : float — 1 + the growth of the truth mesh's edge length per mm of in-plane
        distance from the contact region (:data:`tactile_deploy.fem.truth_mesh.BULK_GROWTH`, 1.2).
    depth_growth : float — the same per mm of depth below the sensing surface
        (:data:`tactile_deploy.fem.truth_mesh.DEPTH_GROWTH`, 1.15): the bulk under the contact
        sets the force of a nearly incompressible gel (a 2 mm ball at 1.0 mm: x1.025 the
        independent FEM's force at 1.2, x1.0175 at 1.15, x1.011 at 1.1; docs/fem.md).
    deviatoric : "face" (default) or "element" — where the gel's deviatoric energy is
        integrated (:mod:`tactile_deploy.fem.hyperelastic`: face-based smoothing cells, or tets,
        which are 2-3 % too stiff on the truth meshes).
    settings : SolveSettings
    """

    def __init__(self, geometry: PadGeometry, material: Material = Material(),
                 model: str = "neo-hookean", supports: Supports = SENSOR_SUPPORTS,
                 h_coarse_mm: float = 2.0, settings: SolveSettings = SolveSettings(),
                 deviatoric: str = "face", bulk_growth: float = BULK_GROWTH,
                 depth_growth: float = DEPTH_GROWTH):
        if model not in ("neo-hookean", "linear"):
            raise ValueError(f"model must be 'neo-hookean' or 'linear', got {model!r}")
        self.geometry = geometry
        self.material = material
        self.model = model
        self.supports = supports
        self.h_coarse_mm = h_coarse_mm
        if not 1.0 < bulk_growth <= 2.0:
            raise ValueError(f"bulk_growth must be in (1, 2] (1 + mm of edge length per mm), got {bulk_growth}")
        if not 1.0 < depth_growth <= 2.0:
            raise ValueError(f"depth_growth must be in (1, 2] (1 + mm of edge length per mm), got {depth_growth}")
        self.bulk_growth = bulk_growth
        self.depth_growth = depth_growth
        self.settings = settings
        self.deviatoric = deviatoric

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
        # around it finer (TIP_SIZE_FRACTION), so their chords follow a cone's flanks.
        sharp = tip_flank_slope(field_, tip, "mean") > TIP_SLOPE_BREAK
        fraction = TIP_SIZE_FRACTION[self.model]
        spots = [(float(tip[0]), float(tip[1]), fraction * h_fine_mm)] if sharp else []
        sizes = np.concatenate([curvature_sizes(field_, pts, h_fine_mm),
                                rim_sizes(field_, pts, h_fine_mm)])
        mesh = build_truth_mesh(self.geometry, region_xy, h_fine_mm, h_coarse_mm=self.h_coarse_mm,
                                growth=self.bulk_growth, depth_growth=self.depth_growth,
                                surface_nodes_xy=tip[None], point_sizes=spots,
                                curvature_sizes=sizes)
        return mesh, h_fine_mm, pts

    def solve(self, indenter, pose, **kwargs) -> TruthSolution:
        """Contact of a library ``indenter`` pressed at ``pose`` (:class:`ContactPose`)."""
        return self.solve_field(indenter_field(indenter, pose), **kwargs)

    def solve_field(self, field_: IntrusionField, mesh: PadMesh | None = None,
                    h_fine_mm: float | None = None, features: np.ndarray | None = None,
                    slide_mm: tuple[float, float] = (0.0, 0.0)) -> TruthSolution:
        """Contact for an intrusion field; ``mesh`` overrides the automatic truth mesh,
        ``features`` (k, 2) adds indenter points (sensor frame, mm) to the constraints.

        ``slide_mm`` (x, y, sensor frame, mm): after pressing, the indenter moved this far
        along the surface (a tangential load, as in Cattaneo-Mindlin). Sticking nodes move with
        it; slipping nodes carry their Coulomb force against the slip. The slide is taken as
        small next to the contact: the intrusion field is the indenter's final place."""
        if mesh is None:
            mesh, h_fine_mm, fp = self.mesh_for(field_, h_fine_mm)
        else:
            fp, _ = footprint(field_, self.geometry, pitch_mm=0.05)
            if h_fine_mm is None:
                h_fine_mm = float(np.sqrt(mesh.sensing_nodal_areas_mm2().min() * 2.0))
        return _Solve(self, mesh, field_, h_fine_mm, fp, features, slide_mm).run()


def curvature_sizes(field_: IntrusionField, fp: np.ndarray, h_fine_mm: float,
                    step_mm: float = 0.02) -> np.ndarray:
    """Edge lengths the indenter's curvature asks for: (k, 3) rows (x, y, size mm) at the
    footprint points ``fp`` (k0, 2) where the largest second derivative of the intrusion
    (along x, y and the diagonals, central differences over ``step_mm``) kappa would make a
    chord of the fine spacing sag by more than :data:`CHORD_SAG_MM` (the steep rim of a ball,
    a rounded edge). Sizes are sqrt(8 sag / kappa), at least :data:`H_FINE_MIN_MM`. Points where
    a difference leaves the indenter (its outline) are skipped: their kink is the edge of
    contact, not a curvature."""
    if len(fp) == 0:
        return np.zeros((0, 3))
    d0 = field_(fp)
    kappa = np.zeros(len(fp))
    for e in (np.array([1.0, 0.0]), np.array([0.0, 1.0]),
              np.array([1.0, 1.0]) / np.sqrt(2), np.array([1.0, -1.0]) / np.sqrt(2)):
        dp, dm = field_(fp + step_mm * e), field_(fp - step_mm * e)
        second = (dp + dm - 2.0 * d0) / step_mm**2
        ok = np.isfinite(second) & (dp > 0) & (dm > 0)
        kappa = np.maximum(kappa, np.where(ok, np.abs(second), 0.0))
    size = np.sqrt(8.0 * CHORD_SAG_MM / np.maximum(kappa, 1e-300))
    need = size < h_fine_mm
    size = np.maximum(size[need], H_FINE_MIN_MM)
    return np.column_stack([fp[need], size])


def rim_sizes(field_: IntrusionField, fp: np.ndarray, h_fine_mm: float,
              pitch_mm: float = 0.05) -> np.ndarray:
    """Edge lengths along the rim of a flat-faced indenter (a punch): (k, 3) rows (x, y, size
    mm) at the footprint points ``fp`` (k0, 2) (a ``pitch_mm`` grid) next to a point the
    indenter does not cover while it reaches more than :data:`RIM_WALL_MM` below the rest
    surface there (a wall, not the gentle edge of a curved contact). The gel folds around the
    rim (strains are singular at its corners): edges there are a third of the fine spacing, a
    sixth at the outline's corners (where less than 45 % of a disc of 2 pitches around the
    point is covered), at least :data:`H_FINE_MIN_MM`."""
    if len(fp) == 0 or field_.coverage is None:
        return np.zeros((0, 3))
    d0 = field_(fp)
    wall = d0 > RIM_WALL_MM
    offsets = pitch_mm * np.array([[1, 0], [-1, 0], [0, 1], [0, -1]], float)
    edge = np.zeros(len(fp), bool)
    for o in offsets:
        edge |= ~np.isfinite(field_(fp + o))
    rim = fp[wall & edge]
    if len(rim) == 0:
        return np.zeros((0, 3))
    ang = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    ring = 2 * pitch_mm * np.stack([np.cos(ang), np.sin(ang)], 1)
    covered = np.mean([np.isfinite(field_(rim + o)) for o in ring], axis=0)
    size = RIM_SPACING_FRACTION * h_fine_mm * np.where(covered < 0.45, RIM_CORNER_FACTOR, 1.0)
    return np.column_stack([rim, np.maximum(size, H_FINE_MIN_MM)])


def tip_flank_slope(field_: IntrusionField, tip: np.ndarray, how: str = "min",
                    probe_mm: float = TIP_PROBE_MM) -> float:
    """How steeply the indenter's surface rises around a point ``tip`` (2,) (sensor frame, mm):
    the drop of the intrusion from ``tip`` to 8 points ``probe_mm`` around it, over
    ``probe_mm``; their minimum (``how="min"``: the gentlest flank, 1 for a 90-degree cone, ~0
    along a wedge's edge or on a smooth apex) or mean (``"mean"``). Uncovered points count as
    flat (0)."""
    ang = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
    ring = np.asarray(tip, float)[None] + probe_mm * np.stack([np.cos(ang), np.sin(ang)], 1)
    drop = (float(field_(np.asarray(tip, float)[None])[0]) - field_(ring)) / probe_mm
    drop = np.where(np.isfinite(drop), drop, 0.0)
    return float(drop.min() if how == "min" else drop.mean())


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
    """One semismooth (primal-dual active-set) Newton solve: the state of its iterations."""

    def __init__(self, solver: TruthSolver, mesh: PadMesh, field_: IntrusionField,
                 h_fine: float, fp: np.ndarray, features, slide_mm=(0.0, 0.0)):
        self.s = solver
        slide = np.asarray(slide_mm, float).reshape(-1)
        if slide.shape != (2,) or not np.all(np.isfinite(slide)):
            raise ValueError(f"slide_mm must be two finite numbers (x, y in mm), got {slide_mm!r}")
        if np.any(slide != 0.0) and solver.material.friction == "frictionless":
            raise ValueError("a slide moves the indenter along the surface: without friction "
                             "it does nothing; use friction 'stick' or 'coulomb'")
        self.slide = np.array([slide[0], slide[1], 0.0])
        self.mesh = mesh
        self.field = field_
        self.h_fine = h_fine
        mat = solver.material
        self.geometric = solver.model != "linear"
        self.gel = gel_model(solver.model, mesh.vertices, mesh.tets, mat.E_mpa, mat.nu,
                             solver.deviatoric)
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
        self._init_vertex(fp)
        pts = feature_points(field_, fp, h_fine, solver.geometry)
        if features is not None:
            pts = np.concatenate([pts, np.asarray(features, float).reshape(-1, 2)])
        # At a sharp tip the apex's node holds the tip itself; the flanks within a fine
        # spacing of it are left to the nodes (as indenter points there, the triangles under
        # them kept changing as the gel slid up the flanks, and the iterations wandered).
        if self.tip >= 0:
            apex = self.mesh.vertices[self.cand_nodes[self.tip], :2]
            pts = pts[np.hypot(*(pts - apex).T) > h_fine] if len(pts) else pts
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
        self.areas = mesh.sensing_nodal_areas_mm2()
        _, shear = mat.lame_mpa
        # Complementarity constants (N/mm): the stiffness of a node's patch of gel.
        self.c_node = shear * self.areas[self.cand_nodes] / h_fine
        self.c_point = shear * h_fine
        self.n_plane = n_plane
        self.friction = mat.friction
        self.mu_f = mat.mu
        self.lift = 0.0  # the indenter raised by this much (mm) during load steps
        self.factorizations = 0
        self.newton_steps = 0
        self.load_splits = 0
        self.beside = np.zeros(len(self.cand_nodes), bool)
        self.tip_pinned = True
        self._cand_index = -np.ones(mesh.n_nodes, np.int64)
        self._cand_index[self.cand_nodes] = np.arange(len(self.cand_nodes))
        self._init_dof_layout()

    def _init_vertex(self, fp: np.ndarray) -> None:
        """The sensing node at a sharp tip (a cone's apex), if the mesh has one there.

        At the apex the indenter's normal is not a direction but a cone (the normals of its
        flanks): a node there is held by the tip (pinned to it) as long as the tip's force on
        it lies within that cone, ``|f_T| <= s f_N`` about the pressing axis with s the
        gentlest flank's slope (:func:`tip_flank_slope`); pushed harder sideways, it leaves
        the apex and slides along a flank like any other node. (Measured as a normal face
        contact at its current position instead, the node's normal flips from flank to flank
        as it moves across the apex by a micrometre: the iterations wandered.) Large
        deformation only: the small-strain model's gaps are vertical at the rest positions."""
        self.tip = -1  # index into cand_nodes of the node at a sharp tip, or -1
        self.tip_slope = 0.0
        self.tip_z = 0.0
        if not self.geometric or len(fp) == 0 or len(self.cand_nodes) == 0:
            return
        tip_xy = deepest_point(self.field, fp, self.s.geometry)
        X = self.mesh.vertices[self.cand_nodes, :2]
        k = int(np.argmin(np.hypot(*(X - tip_xy).T)))
        if np.hypot(*(X[k] - tip_xy)) > VERTEX_SNAP_MM:
            return
        slope = tip_flank_slope(self.field, X[k], "min")
        if slope > TIP_SLOPE_BREAK:
            self.tip, self.tip_slope = k, slope
            self.tip_z = -float(self.field(X[k][None])[0])

    # ------------------------------------------------------------------------ dof layout
    def _init_dof_layout(self):
        """Free coordinates grouped by node, and a fill-reducing order of the nodes."""
        n = self.mesh.n_nodes
        noc = self.dofs.node_of_col
        self.k_node = np.bincount(noc, minlength=n)
        order = np.argsort(noc, kind="stable")
        start = np.concatenate([[0], np.cumsum(self.k_node)[:-1]])
        cols = -np.ones((n, 3), np.int64)
        cols[noc[order], np.arange(len(noc)) - start[noc[order]]] = order
        self.cols = cols
        # Full-space direction of each free coordinate, per node: (n, 3, 3), column a = the
        # direction of the node's a-th coordinate (zero where absent).
        D = np.zeros((n, 3, 3))
        valid = cols >= 0
        D[np.nonzero(valid)[0], :, np.nonzero(valid)[1]] = self.dofs.direction_of_col[cols[valid]]
        self.D = D
        # The stiffness couples nodes that share a nodal patch (two rings of tets).
        tets = self.mesh.tets
        inc = sp.csr_matrix((np.ones(tets.size), (np.repeat(np.arange(len(tets)), 4), tets.ravel())),
                            shape=(len(tets), n))
        ring = (inc.T @ inc).tocsr()
        ring.data[:] = 1.0
        perm = nested_dissection_order(ring @ ring)
        self.node_order = np.arange(n) if perm is None else perm
        self.ordered = perm is not None
        self.T_full = self.dofs.T.tocsr()

    # ------------------------------------------------------------------------ constraints
    def constraints(self, u: np.ndarray) -> _Constraints:
        X = self.mesh.vertices
        nodes = self.cand_nodes
        p = X[nodes] + u[nodes]
        w_n = np.zeros((len(nodes), 3, 3))
        if self.geometric:
            gap_n, w_n[:, 0] = self.node_gaps(p)
            if self.tip >= 0 and self.tip_pinned:
                gap_n[self.tip] = self.tip_z + self.lift - p[self.tip, 2]
                w_n[self.tip, 0] = (0.0, 0.0, -1.0)
        else:
            d = self.field(X[nodes, :2]) - self.lift
            gap_n = np.where(np.isfinite(d), -d - p[:, 2], np.inf)
            w_n[:, 0, 2] = -1.0
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
    def node_gaps(self, p: np.ndarray):
        """Gap (k,) mm and unit normal (k, 3) of deformed sensing-node positions p (k, 3)
        against the indenter at its current height (:func:`solid_gap`)."""
        return solid_gap(self.field, p - np.array([0.0, 0.0, self.lift]), self.beside)

    def at_rim(self, u: np.ndarray) -> np.ndarray:
        """Candidate nodes (nc,) bool within a rim element (:func:`rim_sizes`) of a wall's
        outline (a punch's sharp edge), at their current position. They carry no friction:
        at a sharp edge the normal is a cone, not a direction, and the gel slides round it
        (held there, the elements beside it fold over)."""
        nodes = self.cand_nodes
        if self.field.coverage is None or self.friction == "frictionless":
            return np.zeros(len(nodes), bool)
        xy = self.mesh.vertices[nodes, :2] + (u[nodes, :2] if self.geometric else 0.0)
        sd, _ = self.field.coverage(xy)
        return sd > -RIM_SPACING_FRACTION * self.h_fine

    def note_beside(self, u: np.ndarray) -> None:
        """Flag the candidate nodes that are now beside the indenter (outside its outline, or
        against its wall): if one is inside the solid after the next step, it came in through
        the side."""
        nodes = self.cand_nodes
        p = self.mesh.vertices[nodes] + u[nodes] - np.array([0.0, 0.0, self.lift])
        self.beside = solid_gap(self.field, p, self.beside, with_side=True)[2]

    def indenter_normals(self, u: np.ndarray) -> np.ndarray:
        """Unit normal of the indenter (pointing into the gel) at each sensing node: the
        gradient of the node's gap (-z in the small-strain limit)."""
        n = np.zeros((self.n_plane, 3))
        n[:, 2] = -1.0
        if self.geometric:
            nodes = self.cand_nodes
            n[nodes] = self.node_gaps(self.mesh.vertices[nodes] + u[nodes])[1]
            if self.tip >= 0 and self.tip_pinned:
                n[nodes[self.tip]] = (0.0, 0.0, -1.0)  # the pressing axis
        return n

    def _hold_apex(self, new_stick, new_n, act_n, lam_n, nt) -> None:
        """The node at a sharp tip stays pinned to the apex (``new_stick`` set in place) while
        in contact, unless the tip's force on it leaves the flanks' normal cone
        (``|f_T| > s f_N``): then it is released for good and slides like any other node."""
        k = self.tip
        if k < 0:
            return
        if self.tip_pinned and act_n[k] and lam_n[k] > 0 and nt[k] > self.tip_slope * lam_n[k]:
            self.tip_pinned = False
            log.debug("the apex's node is pushed off the tip (|f_T| %.3g N > %.2f x %.3g N)",
                      nt[k], self.tip_slope, lam_n[k])
        new_stick[k] = new_n[k] and self.tip_pinned

    def friction_bound(self, fn: np.ndarray) -> np.ndarray:
        """Largest tangential force (N) of each candidate node for its normal force fn (N)."""
        if self.friction == "frictionless":
            return np.zeros_like(fn)
        if self.friction == "stick":
            return np.where(fn > 0, np.inf, 0.0)
        return self.mu_f * fn

    def _reduction(self, rows: np.ndarray, rhs: np.ndarray, nrows: np.ndarray):
        """Eliminate the node constraints ``rows`` (k, 3, 3) . du_node = ``rhs`` (k, 3) of the
        candidate nodes (the first ``nrows`` (k,) rows of each are used).

        Returns (E (3n, m) CSR: du = E y + p for the m reduced coordinates y, ordered by the
        fill-reducing node order; p (3n,) the particular increment)."""
        n = self.mesh.n_nodes
        nodes = self.cand_nodes
        con = nrows > 0
        k = self.k_node
        reduced = k.copy()
        p_q = np.zeros(self.dofs.n_free)
        blocks = {}
        cn = nodes[con]
        if len(cn):
            A = np.einsum("kij,kja->kia", rows[con], self.D[cn])  # (c, 3 rows, 3 coords)
            mask = (np.arange(3)[None, :] < nrows[con][:, None]).astype(float)
            A = A * mask[:, :, None]
            # A node's absent coordinates (held by its supports) are pinned by extra rows, so
            # that the null space spans its free coordinates only.
            have = np.arange(3)[None, :] < k[cn][:, None]
            pins = np.eye(3)[None] * (~have)[:, :, None]
            A = np.concatenate([A, pins], axis=1)  # (c, 6, 3)
            U, S, Vt = np.linalg.svd(A, full_matrices=False)
            tol = 1e-10 * np.maximum(S[:, :1], 1e-300)
            r = (S > tol).sum(axis=1)
            Sinv = np.where(S > tol, 1.0 / np.where(S > tol, S, 1.0), 0.0)
            b = np.concatenate([rhs[con] * mask, np.zeros((len(cn), 3))], axis=1)
            pl = np.einsum("kji,kj,klj,kl->ki", Vt, Sinv, U, b, optimize=True)
            pl = np.where(have, pl, 0.0)
            p_q[self.cols[cn][have]] = pl[have]
            reduced[cn] = 3 - r
            blocks = (cn, Vt, r)
        # Reduced coordinates: nodes in the fill-reducing order, each node's consecutively.
        order = self.node_order
        start = np.zeros(n, np.int64)
        start[order] = np.concatenate([[0], np.cumsum(reduced[order])[:-1]])
        m = int(reduced.sum())
        ri, ci, vi = [], [], []
        free_nodes = np.ones(n, bool)
        if len(cn):
            free_nodes[cn] = False
        fn_ = np.flatnonzero(free_nodes)
        for a in range(3):
            sel = fn_[k[fn_] > a]
            ri.append(self.cols[sel, a])
            ci.append(start[sel] + a)
            vi.append(np.ones(len(sel)))
        if len(cn):
            cn, Vt, r = blocks
            # null-space directions: rows r..2 of Vt (in the node's coordinates)
            for j in range(3):
                use = r <= j
                for a in range(3):
                    sel = use & (k[cn] > a)
                    ri.append(self.cols[cn[sel], a])
                    ci.append(start[cn[sel]] + j - r[sel])
                    vi.append(Vt[sel, j, a])
        Zq = sp.csr_matrix((np.concatenate(vi), (np.concatenate(ri), np.concatenate(ci))),
                           shape=(self.dofs.n_free, m))
        E = (self.T_full @ Zq).tocsr()
        return E, self.T_full @ p_q

    # -------------------------------------------------------------------------- iterations
    def run(self) -> TruthSolution:
        """Load steps, each solved to the tolerances: the indenter lowered in equal depth
        increments (large deformation only), then slid along the surface in equal increments
        (a slide only): each step starts from the last one's contact, stick and slip sets."""
        st = self.s.settings
        u = np.zeros((self.mesh.n_nodes, 3))
        depth = max(float(np.max(self.field(self.mesh.vertices[self.cand_nodes, :2]), initial=0.0)),
                    1e-3)
        n_steps = 1
        if self.geometric:
            n_steps = max(1, math.ceil(depth / (st.step_strain * self.s.geometry.thickness_mm)))
            if self.tip >= 0:
                n_steps = max(n_steps, math.ceil(depth / st.tip_step_mm))
        slide = self.slide
        n_slide = st.slide_steps if np.any(slide != 0.0) else 0
        history = []
        state = None
        self.slide = 0.0 * slide
        # Depth increments; one whose Newton steps fail (elements fold, sets cycle) is tried
        # again as two halves, from the last converged step (at most ``max_load_splits``).
        lifts = [depth * (1.0 - k / n_steps) for k in range(1, n_steps + 1)]
        done_lift, splits, i = depth, 0, 0
        while i < len(lifts):
            saved = (u.copy(), None if state is None else
                     {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in state.items()},
                     self.beside.copy(), self.tip_pinned)
            self.lift = lifts[i]
            try:
                u, state = self._solve_step(u, depth, history, state,
                                            final=i == len(lifts) - 1 and n_slide == 0)
            except NewtonBudgetError:
                raise
            except TruthSolveError as err:
                if splits >= st.max_load_splits or not self.geometric:
                    raise
                log.debug("depth increment to %.4f mm failed (%s): halved", lifts[i], err)
                u, state, self.beside, self.tip_pinned = saved
                lifts.insert(i, 0.5 * (done_lift + lifts[i]))
                splits += 1
                self.load_splits = splits
                continue
            done_lift = lifts[i]
            i += 1
        for k in range(1, n_slide + 1):
            self.slide = slide * (k / n_slide)
            u, state = self._solve_step(u, depth, history, state, final=k == n_slide)
        return self._solution(u, state, history)

    def _solve_step(self, u, depth, history, state, final=True):
        """Semismooth Newton for one indenter position: each step solves the tangent system
        with the active contact constraints (and the stick constraints) holding exactly.

        Modified Newton where it pays: while the active, stick and slip sets stay the same and
        the steps keep contracting (the slip forces converge as a fixed point, linearly), the
        last factorised tangent is reused and only the internal forces are re-evaluated. The
        constraints hold exactly on every step either way; the tangent only sets the rate.
        A load step before the last (``final`` False) stops at the looser intermediate
        tolerances."""
        st = self.s.settings
        step_tol = st.step_tol if final else st.intermediate_step_tol
        force_tol = st.force_tol if final else st.intermediate_force_tol
        pen_tol = st.penetration_tol_mm if final else st.intermediate_penetration_mm
        cached = None  # (sets key, factor, stiffness) of the last factorisation in this step
        nc = len(self.cand_nodes)
        c = self.constraints(u)
        if state is None:
            state = {"lam_n": np.zeros(nc), "lam_p": np.zeros(len(self.ind_xy)),
                     "active_n": c.gap[:nc] < 0, "active_p": c.gap[nc:] < 0,
                     "stick": np.zeros(nc, bool), "f_slip": np.zeros((nc, 3)),
                     "f_node": np.zeros((nc, 3))}
        else:
            state["active_n"] = state["active_n"] | (c.gap[:nc] < 0)
            state["active_p"] = state["active_p"] | (c.gap[nc:] < 0)
        if self.tip >= 0 and self.tip_pinned:
            state["stick"][self.tip] = state["active_n"][self.tip]
        prev_step = np.inf
        cut_steps = 0  # consecutive steps cut short because a full one inverts elements
        contraction = np.inf  # last step / the one before
        # Anti-cycling: the (active, stick) sets seen in this load step, and the nodes that may
        # no longer stick (a rim node whose normal force is ~0 can cycle active-slipping ->
        # sticking (tensile) -> released (penetrating) -> active-slipping; it then carries no
        # friction, its bound mu t_N being ~0).
        # A node that still enters and leaves contact once it has lost its friction (at a
        # punch's rim: held, it pulls slightly; released, it penetrates slightly) is kept in
        # contact for the rest of the load step; its small tensile force is reported.
        seen = set()
        no_stick = self.at_rim(u)
        kept = np.zeros(nc, bool)
        mixing = []  # (slip forces in, slip forces out) of the steps since the sets settled
        for it in range(1, st.max_iterations + 1):
            if st.max_newton_steps is not None and self.newton_steps >= st.max_newton_steps:
                raise NewtonBudgetError(
                    f"contact iterations stopped after {self.newton_steps} Newton steps in all "
                    f"(max_newton_steps), the indenter {self.lift:.3g} mm above its final depth")
            self.newton_steps += 1
            if self.geometric:
                self.note_beside(u)
            c = self.constraints(u)
            normals = self.indenter_normals(u)[self.cand_nodes]
            act_n, act_p, stick = state["active_n"], state["active_p"], state["stick"] & state["active_n"]
            # ---- the node constraints: normal (active), tangential (active and sticking)
            rows = np.zeros((nc, 3, 3))
            rhs = np.zeros((nc, 3))
            rows[:, 0] = c.weights[:nc, 0]
            rhs[:, 0] = -c.gap[:nc]
            tang = _tangent_basis(normals)  # (nc, 2, 3)
            rows[:, 1:] = tang
            uc = u[self.cand_nodes] - self.slide  # relative to the indenter's slide
            rhs[:, 1:] = -np.einsum("kij,kj->ki", tang, uc)
            nrows = np.where(act_n, np.where(stick, 3, 1), 0)
            E, p = self._reduction(rows, rhs, nrows)
            # ---- residual and tangent (slip forces are loads of this step)
            sets_key = (act_n.tobytes(), stick.tobytes())
            # (the small-strain tangent depends on the sets alone: always reused)
            reuse = (cached is not None and cached[0] == sets_key
                     and (not self.geometric or contraction <= st.reuse_contraction))
            if reuse:
                f_int, K = self.gel.forces(u), cached[2]
            else:
                f_int, K = self.gel.forces_and_stiffness(u)
            R = f_int.ravel().copy()
            slip = act_n & ~stick
            if self.friction != "frictionless" and np.any(slip):
                nodes = self.cand_nodes[slip]
                R[(3 * nodes[:, None] + np.arange(3)).ravel()] -= state["f_slip"][slip].ravel()
            Kr = None if reuse else (E.T @ K @ E).tocsr()
            rhs_r = -(E.T @ (R + K @ p))
            # ---- active indenter points: Schur complement on their multipliers
            ap = np.flatnonzero(act_p)
            C = None
            if len(ap):
                dofs = (3 * c.nodes[nc + ap][:, :, None] + np.arange(3)).reshape(len(ap), 9)
                C = sp.csr_matrix((c.weights[nc + ap].reshape(len(ap), 9).ravel(),
                                   (np.repeat(np.arange(len(ap)), 9), dofs.ravel())),
                                  shape=(len(ap), 3 * self.mesh.n_nodes))
                Cr = (C @ E).toarray()
                keep = np.linalg.norm(Cr, axis=1) > 1e-8 * np.linalg.norm(C.toarray(), axis=1)
                # A point whose three corners are all held by active node constraints cannot
                # move: where it penetrates, those node constraints are released next step
                # (the point holds the triangle below the indenter's feature instead).
                held = ap[~keep]
                ap, C, Cr = ap[keep], C[keep], Cr[keep]
            else:
                held = ap
            if reuse:
                factor = cached[1]
            else:
                factor = SymmetricFactor(Kr, ordered=self.ordered, backend=st.linear_solver)
                self.factorizations += 1
                cached = (sets_key, factor, K)
            y = factor.solve(rhs_r)
            mu_p = np.zeros(len(ap))
            if len(ap):
                Y = factor.solve(Cr.T)
                S = Cr @ Y
                b = -c.gap[nc + ap] - C @ p - Cr @ y
                mu_p = np.linalg.solve(S, b)
                y = y + Y @ mu_p
            du = E @ y + p
            # ---- contact forces from the linearised residual
            r_lin = R + K @ du
            if len(ap):
                r_lin -= C.T @ mu_p
            f_node = r_lin.reshape(-1, 3)[self.cand_nodes]
            lam_n = np.where(act_n, np.einsum("ki,ki->k", f_node, normals), 0.0)
            f_T = f_node - lam_n[:, None] * normals
            f_T = np.where(stick[:, None], f_T, np.where(slip[:, None], state["f_slip"], 0.0))
            lam_p = np.zeros(len(self.ind_xy))
            lam_p[ap] = mu_p
            # ---- step (halved while elements invert)
            t = 1.0
            dU = du.reshape(-1, 3)
            while self.geometric and not np.isfinite(self.gel.energy(u + t * dU)):
                t *= 0.5
                if t < 1e-4:
                    raise TruthSolveError("every step inverts elements of the truth mesh")
            cut_steps = cut_steps + 1 if t <= 1.0 / 32.0 else 0
            if cut_steps >= 3:
                raise TruthSolveError("elements of the truth mesh fold: three steps in a row "
                                      "cut to 1/32 or less")
            u = u + t * dU
            # ---- new active, stick and slip sets (complementarity functions)
            c = self.constraints(u)
            new_n = (lam_n - self.c_node * c.gap[:nc]) > 0
            new_p = (lam_p - self.c_point * c.gap[nc:]) > 0
            stuck = held[c.gap[nc + held] < -st.penetration_tol_mm] if len(held) else held
            if len(stuck):
                release = self._cand_index[c.nodes[nc + stuck].ravel()]
                new_n[release[release >= 0]] = False
                new_p[stuck] = True
            normals = self.indenter_normals(u)[self.cand_nodes]
            bound = self.friction_bound(np.maximum(lam_n, 0.0))
            rel = u[self.cand_nodes] - self.slide  # slip relative to the indenter
            uT = rel - np.einsum("ki,ki->k", rel, normals)[:, None] * normals
            tau = f_T - self.c_node[:, None] * uT
            tau -= np.einsum("ki,ki->k", tau, normals)[:, None] * normals
            nt = np.linalg.norm(tau, axis=1)
            new_stick = new_n & (nt <= bound) & (bound > 0) & ~no_stick
            self._hold_apex(new_stick, new_n, act_n, lam_n, nt)
            key = (new_n.tobytes(), new_p.tobytes(), new_stick.tobytes())
            if key in seen:  # a cycle: the nodes that just changed their sets stop sticking
                kept |= (new_n != act_n) & no_stick
                new_n |= kept
                no_stick |= (new_n != act_n) | (new_stick != stick)
                new_stick &= ~no_stick
                self._hold_apex(new_stick, new_n, act_n, lam_n, nt)
            seen.add(key)
            f_slip = np.where((new_n & ~new_stick & ~no_stick)[:, None],
                              np.where(np.isfinite(bound), bound, 0.0)[:, None] * tau
                              / np.maximum(nt, 1e-300)[:, None], 0.0)
            scale = max(float(np.abs(lam_n).sum() + np.abs(lam_p).sum()), 1e-300)
            slip_change = float(np.abs(f_slip - state["f_slip"]).max(initial=0.0)) / scale
            same = (np.array_equal(new_n, act_n) and np.array_equal(new_p, state["active_p"])
                    and np.array_equal(new_stick, stick))
            # With the sets fixed the slip forces are a fixed point x -> g(x) (their loads give
            # the tractions that give them back), contracting by 0.6-0.9 a step: Anderson mixing
            # over the last few steps takes it to its limit in a few.
            if same:
                mixing.append((state["f_slip"], f_slip))
                f_slip = _anderson(mixing[-st.anderson_depth:])
            else:
                mixing.clear()
            step = float(np.abs(dU).max()) * t
            pen = float(max(0.0, -c.gap.min())) if len(c.gap) else 0.0
            history.append((self.newton_steps, pen, step))
            log.debug("lift %.4f mm, step %d: |du| %.3g mm, t %.2g, active %d+%d, stick %d, "
                      "penetration %.3g um, slip change %.2g", self.lift, it, step, t,
                      int(new_n.sum()), int(new_p.sum()), int(new_stick.sum()), pen * 1e3,
                      slip_change)
            state.update(lam_n=lam_n, lam_p=lam_p, active_n=new_n, active_p=new_p,
                         stick=new_stick, f_slip=f_slip, f_node=np.where(new_n[:, None], f_T, 0.0),
                         no_stick=no_stick.copy(), kept=kept.copy())
            # The small-strain model's equations and constraints are linear in u: a step taken
            # with the active, stick and slip sets that it then reproduces is the exact
            # solution (one more step would only measure the factorisation's round-off).
            small = (not self.geometric or step <= step_tol * depth
                     or (step <= st.floor_tol * depth and step >= 0.5 * prev_step))
            if same and t == 1.0 and small and slip_change <= force_tol and pen <= pen_tol:
                return u, state
            contraction = step / prev_step if prev_step > 0 else np.inf
            prev_step = step
        raise TruthSolveError(
            f"contact iterations did not converge in {st.max_iterations} Newton steps (indenter "
            f"{self.lift:.3g} mm above its final depth): last step {step:.3g} mm, penetration "
            f"{pen * 1e3:.3g} um, active sets changing: {not same}")

    def _solution(self, u, state, history) -> TruthSolution:
        n_plane = self.n_plane
        nc = len(self.cand_nodes)
        c = self.constraints(u)
        normals = self.indenter_normals(u)
        # Active sets are final: a multiplier is > c g, with |g| at round-off (clipped at 0).
        # (a node kept in contact against cycling may pull slightly: its force is kept)
        kept = state.get("kept", np.zeros(nc, bool))
        lam_n = np.where(state["active_n"], np.where(kept, state["lam_n"],
                                                     np.maximum(state["lam_n"], 0.0)), 0.0)
        forces = np.zeros((n_plane, 3))
        nodes = self.cand_nodes
        forces[nodes] = lam_n[:, None] * normals[nodes] + state["f_node"]
        fn = np.zeros(n_plane)
        fn[nodes] = lam_n
        node_fn = fn.copy()
        lam_p = np.maximum(state["lam_p"], 0.0)
        if len(lam_p):
            fp = lam_p[:, None, None] * c.weights[nc:]  # (q, 3 corners, 3)
            np.add.at(forces, c.nodes[nc:].ravel(), fp.reshape(-1, 3))
            np.add.at(fn, c.nodes[nc:].ravel(), (lam_p[:, None] * c.share[nc:]).ravel())
        in_contact = fn > 1e-12 * max(fn.max(initial=0.0), 1e-300)
        sticking = np.zeros(n_plane, bool)
        if self.friction == "stick":
            sticking = in_contact.copy()
        elif self.friction == "coulomb":
            sticking[nodes] = state["stick"]
            sticking &= in_contact
        if self.friction != "frictionless":
            sticking[nodes[state.get("no_stick", np.zeros(nc, bool))]] = False
        return TruthSolution(
            mesh=self.mesh, displacements_mm=u, contact_forces_n=forces, normal_force_n=fn,
            in_contact=in_contact, sticking=sticking, force_n=float(-forces[:, 2].sum()),
            tangential_force_n=forces[:, :2].sum(0),
            max_penetration_mm=float(max(0.0, -c.gap.min())) if len(c.gap) else 0.0,
            iterations=self.newton_steps,
            info={"history": history, "n_nodes": self.mesh.n_nodes,
                  "factorizations": self.factorizations,
                  "load_splits": self.load_splits,
                  "newton_steps": self.newton_steps,
                  "n_constraints": len(c.gap), "h_fine_mm": self.h_fine,
                  # complementarity, per constraint: a sensing node's own normal force (N) and
                  # the feature points' gaps (mm) and forces (N)
                  "node_normal_force_n": node_fn, "point_gap_mm": c.gap[nc:].copy(),
                  # sensing nodes the anti-cycling rule left without friction (rim nodes whose
                  # normal force is ~0; reported as slipping)
                  "frictionless_nodes": nodes[state.get("no_stick", np.zeros(nc, bool))
                                              & state["active_n"]],
                  "point_force_n": np.asarray(lam_p, float).copy(),
                  # sensing nodes kept in contact against cycling, and the largest tensile
                  # force among them (N; 0 when none pulls)
                  "kept_nodes": nodes[kept & state["active_n"]],
                  "kept_tension_n": float(max(0.0, -lam_n[kept].min(initial=0.0))),
                  # the sensing node held at a sharp tip's apex (-1: none, or pushed off it)
                  "apex_node": int(nodes[self.tip]) if self.tip >= 0 and self.tip_pinned else -1},
        )


def _anderson(pairs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Anderson mixing (type II) of a fixed point x = g(x): ``pairs`` are the last (x_k, g(x_k))
    (arrays of one shape), oldest first. Returns the next x: g(x_k) less the combination of
    earlier differences that best cancels the residual g(x_k) - x_k (least squares)."""
    g_k = pairs[-1][1]
    if len(pairs) < 2:
        return g_k
    F = np.stack([(g - x).ravel() for x, g in pairs], axis=1)
    G = np.stack([g.ravel() for _, g in pairs], axis=1)
    dF, dG = np.diff(F, axis=1), np.diff(G, axis=1)
    gamma = np.linalg.lstsq(dF, F[:, -1], rcond=None)[0]
    return (G[:, -1] - dG @ gamma).reshape(g_k.shape)


def _tangent_basis(normals: np.ndarray) -> np.ndarray:
    """Two unit vectors (k, 2, 3) spanning the plane normal to each unit normal (k, 3)."""
    a = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = a - np.einsum("ki,ki->k", a, normals)[:, None] * normals
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return np.stack([t1, t2], axis=1)


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
