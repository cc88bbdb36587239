"""Response tables: each candidate's effect on each contact's depth map, tabulated exactly at a
few parameter values and interpolated between them.

For every contact the sensor model's map (the *base*) is simulated once, and for every candidate
the map at each of its tabulated values (3 per fitted coordinate, a 3 x 3 grid for two). A
candidate's change of the map at any coordinates ``phi`` is the quadratic (tensor) Lagrange
interpolation of the tabulated changes::

    sim(phi) - base  ~=  sum_k L_k(phi) (sim(node_k) - base)

Everything is kept on each contact's region of interest (ROI): the pad pixels where the base map
or any tabulated change exceeds ``ROI_THRESHOLD_MM``, dilated by ``ROI_DILATE_PX``; outside it
every candidate predicts the same map. Fits, cross-validation and the bootstrap then run on these
tables alone (:mod:`tactile_deploy.calibration.discrepancy.selection`); the selected effect is re-simulated
exactly.

With measured frames (the reproducer has an imaging path, :mod:`tactile_deploy.calibration.discrepancy.imaging`)
every tabulated map is an imaged map: the base, the candidates' values (optical ones included:
the variant's frame through the calibrated pipeline, no view warp) and the exact re-simulations;
the ROI starts from the FEM surface's change (an imaged map is nowhere exactly flat), and each
contact keeps noise realisations of its imaged base (``noise_maps``).

Contacts estimated from their maps carry the contact itself as base parameters: the change of
the map per unit change of x, y, depth (and theta) spans a nuisance subspace that is projected out
of the residual and of every candidate's changes (a linearised joint fit of the contact).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import binary_dilation

from tactile_deploy.calibration.discrepancy.candidates import Candidate, lagrange_weights
from tactile_deploy.calibration.discrepancy.reproduce import ContactReproducer, is_round
from tactile_deploy.calibration.discrepancy.view_warp import ViewWarp
from tactile_deploy.fem.material import NU_MAX_VALIDATED
from tactile_deploy.indenters import ContactPose
from tactile_deploy.sensors.config import EffectSpec

#: A map change smaller than this (mm) is outside the region of interest.
ROI_THRESHOLD_MM = 1e-4
#: Dilation of the region of interest, pixels.
ROI_DILATE_PX = 2

#: Exceptions that make one tabulated value unavailable for one contact (too deep after the
#: effect, off the pad, a large-strain solve that does not converge, a ratio out of range).
TABULATION_ERRORS = (ValueError, RuntimeError)


@dataclass
class Contact:
    """A contact to reproduce: indenter name, pose (sensor frame), whether it was estimated."""

    indenter: str
    pose: ContactPose
    estimated: bool = False

    @property
    def key(self):
        p = self.pose
        return (self.indenter, p.x_mm, p.y_mm, p.theta_deg, p.depth_mm, self.estimated)


@dataclass
class CandidateTable:
    """One candidate's tabulated changes.

    centre : (p,) coordinates of the sensor model's current value; axes : per coordinate
    (nodes (3,), (fit_lo, fit_hi)); node_coords : (M, p), M = 3^p; deltas : per contact an
    (M, n_roi) float32 array of map changes (mm) against the base (zeros at the current value);
    forces : (n_contacts, M) N; usable : (n_contacts,) bool (False: not applicable or a tabulated
    value failed; the candidate then predicts no change there); note : why it is not testable,
    or "".
    """

    candidate: Candidate
    current: dict
    centre: np.ndarray
    axes: list
    node_coords: np.ndarray
    deltas: list
    forces: np.ndarray
    usable: np.ndarray
    note: str = ""

    @property
    def name(self) -> str:
        return self.candidate.name

    @property
    def testable(self) -> bool:
        return not self.note

    @property
    def bounds(self) -> list[tuple[float, float]]:
        return [a[1] for a in self.axes]

    def weights(self, coords) -> np.ndarray:
        """Interpolation weights (m, M) at coordinates (m, p): tensor quadratic Lagrange; a
        single coordinate with more than 3 nodes uses the 3 nodes nearest to each point."""
        c = np.atleast_2d(np.asarray(coords, np.float64))
        if c.shape[1] == 1 and len(self.axes[0][0]) > 3:
            nodes = self.axes[0][0]
            w = np.zeros((len(c), len(nodes)))
            for j, t in enumerate(c[:, 0]):
                near = np.sort(np.argsort(np.abs(nodes - t), kind="stable")[:3])
                w[j, near] = lagrange_weights(nodes[near], t)[0]
            return w
        per_axis = [lagrange_weights(self.axes[k][0], c[:, k]) for k in range(c.shape[1])]
        w = per_axis[0]
        for extra in per_axis[1:]:
            w = (w[:, :, None] * extra[:, None, :]).reshape(len(c), -1)
        return w

    def params(self, coords) -> dict[str, float]:
        return self.candidate.params_of(coords, self.current)

    def spec(self, coords) -> EffectSpec:
        return EffectSpec(name=self.candidate.effect, params=self.params(coords))


@dataclass
class ResponseTables:
    """Base maps and candidate tables of a list of contacts (see the module docstring).

    base : (n, 128, 128) float64 mm; base_force : (n,) N; roi : per contact flat pixel indices;
    nuisance : per contact an orthonormal (n_roi, q) basis of the contact's own changes, or None
    for commanded contacts; tables : per candidate; noise_maps : (n, J, 128, 128) float32 mm,
    for measured frames: noise realisations of each imaged base map (the residual's noise), else
    None (maps are the FEM's; the noise is estimated from the residual).
    """

    contacts: list[Contact]
    base: np.ndarray
    base_force: np.ndarray
    roi: list
    nuisance: list
    tables: list[CandidateTable] = field(default_factory=list)
    noise_maps: np.ndarray | None = None

    def table(self, name: str) -> CandidateTable:
        for t in self.tables:
            if t.name == name:
                return t
        raise KeyError(name)

    def project(self, i: int, values: np.ndarray) -> np.ndarray:
        """Remove contact i's nuisance subspace from ``values`` (..., n_roi)."""
        q = self.nuisance[i]
        if q is None:
            return values
        return values - (values @ q) @ q.T


def _plans(repro: ContactReproducer, candidates: list[Candidate]):
    """Per candidate: (candidate, current params, centre, axes, node coords, specs, view warps
    or None, which node is the current value)."""
    sensor_effects = repro.sensor.config.effects
    nu0 = repro.sensor.simulator.material.nu
    limits = {"delta_nu": (-nu0, NU_MAX_VALIDATED - nu0)}
    plans = []
    for cand in candidates:
        current = cand.current(sensor_effects)
        centre = cand.coords_of(current)
        axes = cand.axes(centre, limits)
        node_coords = np.array(list(itertools.product(*[a[0] for a in axes])))
        specs = [EffectSpec(name=cand.effect, params=cand.params_of(nc, current))
                 for nc in node_coords]
        warps = None
        if cand.route == "view" and repro.imaging is None:
            cal = repro.sensor.optics.camera
            warps = [ViewWarp(cal, repro.variant(s).optics.camera, repro.camera) for s in specs]
        is_centre = np.all(np.isclose(node_coords, centre[None, :], atol=1e-12), axis=1)
        plans.append((cand, current, centre, axes, node_coords, specs, warps, is_centre))
    return plans


def _tabulate_contact(repro: ContactReproducer, c: Contact, plans) -> dict:
    """Base map, ROI and every candidate's changes on it for one contact."""
    base, base_force = repro.depth_map(c.indenter, c.pose)
    noise = None
    if repro.imaging is None:
        changed = np.abs(base) > ROI_THRESHOLD_MM
    else:
        changed = np.abs(repro.surface_map(c.indenter, c.pose)[0]) > ROI_THRESHOLD_MM
        noise = repro.noise_maps(c.indenter, c.pose, base)
    per_cand, forces, usable = {}, {}, {}
    for cand, current, centre, axes, node_coords, specs, warps, is_centre in plans:
        m = len(specs)
        maps = np.repeat(base[None], m, axis=0)
        f = np.full(m, base_force)
        ok = True
        skip = ((cand.needs_commanded and c.estimated)
                or (cand.needs_non_round and is_round(c.indenter)))
        if not skip:
            try:
                for k, spec in enumerate(specs):
                    if is_centre[k]:
                        continue
                    if warps is not None:
                        maps[k] = warps[k](base)
                    else:
                        maps[k], f[k] = repro.depth_map(c.indenter, c.pose, repro.variant(spec))
            except TABULATION_ERRORS:
                ok = False
                maps[:] = base
                f[:] = base_force
        else:
            ok = not (cand.needs_commanded and c.estimated)
        delta = maps - base[None]
        changed |= np.any(np.abs(delta) > ROI_THRESHOLD_MM, axis=0)
        per_cand[cand.name], forces[cand.name], usable[cand.name] = delta, f, ok
    roi = np.flatnonzero(binary_dilation(changed, iterations=ROI_DILATE_PX) & repro.pad_mask)
    deltas = {name: d.reshape(len(d), -1)[:, roi].astype(np.float32)
              for name, d in per_cand.items()}
    return {"base": base, "base_force": base_force, "roi": roi, "deltas": deltas,
            "forces": forces, "usable": usable, "noise": noise}


_WORKER_STATE: dict = {}


def _worker(i: int) -> dict:
    from threadpoolctl import threadpool_limits

    st = _WORKER_STATE
    with threadpool_limits(1):
        return _tabulate_contact(st["repro"], st["contacts"][i], st["plans"])


def tabulate(repro: ContactReproducer, contacts: list[Contact], candidates: list[Candidate],
             progress=None, workers: int = 1) -> ResponseTables:
    """Simulate the base and every candidate's tabulated values for every contact.

    progress(k) is called after each contact. workers > 1 splits the contacts over that many
    forked processes (each one thread; the simulator's operators are shared copy-on-write).
    """
    n = len(contacts)
    plans = _plans(repro, candidates)
    if workers > 1 and n > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        repro.sensor.simulator.prepare()
        _WORKER_STATE.update(repro=repro, contacts=contacts, plans=plans)
        try:
            with ProcessPoolExecutor(workers, mp_context=mp.get_context("fork")) as pool:
                per = []
                for out in pool.map(_worker, range(n), chunksize=1):
                    per.append(out)
                    if progress is not None:
                        progress(1)
        finally:
            _WORKER_STATE.clear()
    else:
        per = []
        for c in contacts:
            per.append(_tabulate_contact(repro, c, plans))
            if progress is not None:
                progress(1)
    base = np.stack([p["base"] for p in per])
    base_force = np.array([p["base_force"] for p in per])
    rois = [p["roi"] for p in per]

    nuisance = []
    for i, c in enumerate(contacts):
        if not c.estimated:
            nuisance.append(None)
            continue
        jac = repro.pose_jacobian(c.indenter, c.pose, rois[i])
        q, r = np.linalg.qr(jac)
        keep = np.abs(np.diag(r)) > 1e-9 * max(1.0, np.abs(np.diag(r)).max())
        nuisance.append(q[:, keep])

    tables = []
    for cand, current, centre, axes, node_coords, specs, warps, is_centre in plans:
        use = np.array([p["usable"][cand.name] for p in per], bool)
        note = ""
        if cand.needs_commanded and not any(not c.estimated for c in contacts):
            note = ("not testable: it moves the contact itself, and every contact was estimated "
                    "from its map; give the commanded contacts")
        elif cand.needs_non_round and all(is_round(c.indenter) for c in contacts):
            note = ("not testable: only indenters that are not bodies of revolution show it; "
                    "press a non-round indenter (e.g. cylinder_side, cube_edge)")
        elif not use.any():
            note = "not testable: its tabulated values could not be simulated for any contact"
        tables.append(CandidateTable(cand, current, centre, axes, node_coords,
                                     [p["deltas"][cand.name] for p in per],
                                     np.stack([p["forces"][cand.name] for p in per]), use, note))
    noise_maps = None if repro.imaging is None else np.stack([p["noise"] for p in per])
    return ResponseTables(contacts, base, base_force, rois, nuisance, tables,
                          noise_maps=noise_maps)


def _node_maps(repro: ContactReproducer, tables: ResponseTables, table: CandidateTable,
               specs: list[EffectSpec], usable: np.ndarray):
    """Changes (per contact (len(specs), n_roi) float32) and forces (n, len(specs)) of the
    candidate at ``specs`` against the base maps; contacts that fail become unusable."""
    cand = table.candidate
    warps = None
    if cand.route == "view" and repro.imaging is None:
        cal = repro.sensor.optics.camera
        warps = [ViewWarp(cal, repro.variant(s).optics.camera, repro.camera) for s in specs]
    deltas, forces = [], np.zeros((len(tables.contacts), len(specs)))
    for i, c in enumerate(tables.contacts):
        base = tables.base[i]
        maps = np.repeat(base[None], len(specs), axis=0)
        forces[i] = tables.base_force[i]
        if usable[i] and not (cand.needs_non_round and is_round(c.indenter)):
            try:
                for k, spec in enumerate(specs):
                    if warps is not None:
                        maps[k] = warps[k](base)
                    else:
                        maps[k], forces[i, k] = repro.depth_map(c.indenter, c.pose,
                                                                repro.variant(spec))
            except TABULATION_ERRORS:
                usable[i] = False
                maps[:] = base
        d = (maps - base[None]).reshape(len(specs), -1)[:, tables.roi[i]]
        deltas.append(d.astype(np.float32))
    return deltas, forces


def refine_table(repro: ContactReproducer, tables: ResponseTables, table: CandidateTable, coords,
                 shrink: float = 0.5) -> CandidateTable:
    """The candidate's table made accurate near ``coords`` (same contacts, ROIs, fit range;
    changes still against the base maps): one coordinate gets a node at ``coords`` added to its
    nodes (interpolation then uses the 3 nearest), two get a new 3 x 3 grid around ``coords``
    with node offsets scaled by ``shrink``."""
    import dataclasses

    cand = table.candidate
    coords = np.asarray(coords, np.float64).ravel()
    usable = table.usable.copy()
    if len(coords) == 1:
        nodes = table.axes[0][0]
        if np.min(np.abs(nodes - coords[0])) < 1e-9 * max(1.0, np.ptp(nodes)):
            return table
        spec = EffectSpec(name=cand.effect, params=cand.params_of(coords, table.current))
        new, f = _node_maps(repro, tables, table, [spec], usable)
        order = np.argsort(np.append(nodes, coords[0]), kind="stable")
        deltas = [np.concatenate([d, e], axis=0)[order] for d, e in zip(table.deltas, new)]
        forces = np.concatenate([table.forces, f], axis=1)[:, order]
        axes = [(np.append(nodes, coords[0])[order], table.axes[0][1])]
        node_coords = axes[0][0][:, None]
        return CandidateTable(cand, table.current, table.centre, axes, node_coords, deltas,
                              forces, usable & table.usable, table.note)
    narrow = dataclasses.replace(cand, node_offsets=tuple(
        (lo * shrink, hi * shrink) for lo, hi in cand.node_offsets))
    nu0 = repro.sensor.simulator.material.nu
    limits = {"delta_nu": (-nu0, NU_MAX_VALIDATED - nu0)}
    axes = [(n, b) for (n, _), b in zip(narrow.axes(coords, limits), table.bounds)]
    node_coords = np.array(list(itertools.product(*[a[0] for a in axes])))
    specs = [EffectSpec(name=cand.effect, params=cand.params_of(nc, table.current))
             for nc in node_coords]
    deltas, forces = _node_maps(repro, tables, table, specs, usable)
    return CandidateTable(cand, table.current, table.centre, axes, node_coords, deltas, forces,
                          usable, table.note)
