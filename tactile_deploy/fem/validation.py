"""Analytic validation scenarios of the contact FEM (each also a test and a docs figure).

Every scenario builds its own mesh, runs the simulator and returns the FEM figure next to the
closed-form one:

* :func:`uniaxial_patch` — a frictionless rigid plate over the whole sensing surface, bottom on
  rollers: uniform uniaxial compression, force ``E A d / h``, lateral strain ``nu d / h``;
* :func:`confined_patch` — the same with the side wall on rollers: force
  ``E (1 - nu) / ((1 + nu)(1 - 2 nu)) A d / h``;
* :func:`hertz_block` — a rigid paraboloid of radius R on a thick, graded quarter-symmetric
  block (bonded at depth H, frictionless contact): force ``4/3 E/(1 - nu^2) sqrt(R) d^1.5``
  and contact radius ``sqrt(R d)`` (half-space theory; the block's finite depth adds about
  ``0.9 sqrt(R d) / H`` to the force for nu = 0.3, Dimitriadis et al. 2002);
* :func:`refinement_study` — a sphere pressed into pads of decreasing node spacing; the force
  converges and the observed order is reported.

Units: mm, MPa, N.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tactile_deploy.fem.constraints import Supports
from tactile_deploy.fem.material import Material
from tactile_deploy.fem.simulator import ContactSimulator
from tactile_deploy.pad.geometry import PadGeometry
from tactile_deploy.pad.mesh import PadMesh, build_pad_mesh


@dataclass(frozen=True)
class PatchFigures:
    force_n: float
    force_exact_n: float
    lateral_strain: float  # mean radial strain of the side wall (uniaxial) or max |u_r| (confined)
    lateral_strain_exact: float

    @property
    def force_error(self) -> float:
        return self.force_n / self.force_exact_n - 1.0


def uniaxial_patch(
    mesh: PadMesh, E_mpa: float = 0.3, nu: float = 0.45, depth_mm: float = 0.05, **sim_kwargs
) -> PatchFigures:
    """Frictionless plate compression of the whole pad with the bottom on rollers."""
    sim = ContactSimulator(
        mesh, Material(E_mpa=E_mpa, nu=nu), Supports(backplate="rollers"), **sim_kwargs
    )
    res = sim.solve_intrusion(np.full(mesh.n_plane, depth_mm))
    h = mesh.geometry.thickness_mm
    area = mesh.sensing_nodal_areas_mm2().sum()
    v, u = mesh.vertices[mesh.side_nodes], res.displacements_mm[mesh.side_nodes]
    r = np.hypot(v[:, 0], v[:, 1])
    radial_strain = float(np.mean((u[:, 0] * v[:, 0] + u[:, 1] * v[:, 1]) / r**2))
    return PatchFigures(res.force_n, E_mpa * area * depth_mm / h, radial_strain, nu * depth_mm / h)


def confined_patch(
    mesh: PadMesh, E_mpa: float = 0.3, nu: float = 0.45, depth_mm: float = 0.05, **sim_kwargs
) -> PatchFigures:
    """Frictionless plate compression with bottom and side wall on rollers."""
    sim = ContactSimulator(
        mesh, Material(E_mpa=E_mpa, nu=nu), Supports(backplate="rollers", side="rollers"), **sim_kwargs
    )
    res = sim.solve_intrusion(np.full(mesh.n_plane, depth_mm))
    h = mesh.geometry.thickness_mm
    area = mesh.sensing_nodal_areas_mm2().sum()
    modulus = E_mpa * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
    u = res.displacements_mm
    return PatchFigures(
        res.force_n, modulus * area * depth_mm / h, float(np.abs(u[:, :2]).max()), 0.0
    )


@dataclass(frozen=True)
class HertzFigures:
    force_n: float
    force_hertz_n: float
    contact_radius_mm: float
    contact_radius_hertz_mm: float
    n_nodes: int

    @property
    def force_ratio(self) -> float:
        return self.force_n / self.force_hertz_n

    @property
    def radius_ratio(self) -> float:
        return self.contact_radius_mm / self.contact_radius_hertz_mm


def hertz_geometry(
    block_mm: float = 40.0, core_edge_mm: float = 0.1, core_radius_mm: float = 1.3, growth: float = 1.25
) -> PadGeometry:
    """A quarter of a thick cylindrical block, finely meshed near the origin, graded outward and down."""
    n_layers, depth, layer = 0, 0.0, core_edge_mm
    while depth < block_mm:
        depth += layer
        layer *= growth
        n_layers += 1
    return PadGeometry(
        name="hertz_block",
        radius_mm=block_mm,
        thickness_mm=block_mm,
        sector_deg=90.0,
        core_radius_mm=core_radius_mm,
        core_edge_mm=core_edge_mm,
        edge_mm=block_mm / 4,
        edge_growth=growth,
        n_layers=n_layers,
        top_layer_mm=core_edge_mm,
        layer_growth=growth,
    )


def contact_radius_from_pressure(r_mm: np.ndarray, pressure: np.ndarray) -> float:
    """Contact radius (mm) from a Hertz-type pressure profile ``p^2 = p0^2 (1 - r^2/a^2)``.

    Fits ``p^2`` linearly in ``r^2`` over the nodes with ``r < 0.8 * r_edge`` (``r_edge`` =
    outermost loaded node), which avoids the lumped-force bias of the edge ring, and returns the
    zero crossing.
    """
    loaded = pressure > 0
    r_edge = r_mm[loaded].max()
    sel = loaded & (r_mm < 0.8 * r_edge)
    slope, intercept = np.polyfit(r_mm[sel] ** 2, pressure[sel] ** 2, 1)
    return float(math.sqrt(-intercept / slope))


def hertz_block(
    nu: float = 0.3,
    radius_mm: float = 10.0,
    depth_mm: float = 0.1,
    E_mpa: float = 1.0,
    geometry: PadGeometry | None = None,
    formulation: str = "nodal_pressure",
) -> HertzFigures:
    """Frictionless paraboloid indentation of a thick quarter block vs Hertz's half-space solution."""
    geometry = geometry or hertz_geometry()
    mesh = build_pad_mesh(geometry)
    xy = mesh.vertices[mesh.sensing_nodes, :2]
    r = np.hypot(xy[:, 0], xy[:, 1])
    # Only nodes the paraboloid reaches below the rest surface can touch it (Hertz: a < sqrt(2Rd)).
    reach = np.flatnonzero(r < 1.2 * math.sqrt(2.0 * radius_mm * depth_mm))
    sim = ContactSimulator(
        mesh,
        Material(E_mpa=E_mpa, nu=nu),
        formulation=formulation,
        assembly="numpy",
        contact_nodes=reach,
        use_cache=False,
    )
    res = sim.solve_intrusion(depth_mm - r**2 / (2 * radius_mm))
    # A quarter model carries a quarter of the load; nodes on the symmetry planes are shared,
    # so their pressure (force / lumped area of the quarter) is already correct.
    force = 4.0 * res.force_n
    a = contact_radius_from_pressure(r, res.pressure_kpa)
    e_star = E_mpa / (1.0 - nu**2)
    return HertzFigures(
        force_n=force,
        force_hertz_n=4.0 / 3.0 * e_star * math.sqrt(radius_mm) * depth_mm**1.5,
        contact_radius_mm=a,
        contact_radius_hertz_mm=math.sqrt(radius_mm * depth_mm),
        n_nodes=mesh.n_nodes,
    )


@dataclass(frozen=True)
class RefinementFigures:
    edges_mm: tuple[float, ...]
    forces_n: tuple[float, ...]
    extrapolated_force_n: float
    observed_order: float  # p in |F_h - F_0| ~ h^p


def refinement_study(
    edges_mm: tuple[float, ...] = (2.0, 1.4, 1.0),
    sphere_radius_mm: float = 6.0,
    depth_mm: float = 0.6,
    nu: float = 0.45,
    radius_mm: float = 10.0,
    formulation: str = "nodal_pressure",
) -> RefinementFigures:
    """Force of a centred sphere on pads of decreasing node spacing (layers scale with it).

    Three meshes with a constant refinement ratio give the observed order
    ``p = log((F1 - F2) / (F2 - F3)) / log(ratio)`` and a Richardson-extrapolated force.
    """
    forces = []
    for h in edges_mm:
        g = PadGeometry(
            name="refinement",
            radius_mm=radius_mm,
            thickness_mm=3.0,
            edge_mm=h,
            n_layers=max(2, round(3.0 / (0.75 * h))),
        )
        mesh = build_pad_mesh(g)
        sim = ContactSimulator(
            mesh, Material(E_mpa=1.0, nu=nu), formulation=formulation, assembly="numpy", use_cache=False
        )
        xy = mesh.vertices[mesh.sensing_nodes, :2]
        r2 = (xy**2).sum(1)
        R = sphere_radius_mm
        delta = np.where(r2 < R * R, depth_mm - (R - np.sqrt(np.maximum(R * R - r2, 0.0))), -np.inf)
        forces.append(sim.solve_intrusion(delta).force_n)
    f1, f2, f3 = forces[-3:]
    ratio = edges_mm[-3] / edges_mm[-2]
    p = math.log(abs(f1 - f2) / abs(f2 - f3)) / math.log(ratio)
    f0 = f3 + (f3 - f2) / (ratio**p - 1.0)
    return RefinementFigures(tuple(edges_mm), tuple(forces), f0, p)
