"""Response tables: each candidate's effect on each contact's depth map, tabulated exactly at a
few parameter values and interpolated between them.

For every contact the sensor model's map (the *base*) is simulated once, and for every candidate
the map at each of its tabulated values (3 per fitted coordinate: a 3 x 3 grid for two, a
*star* for three or more: the middle value and one either side along each coordinate). A
candidate's change of the map at any coordinates ``phi`` is the quadratic Lagrange interpolation
of the tabulated changes (tensor product on a grid; on a star the sum of the changes along each
coordinate, an additive model that the refinement re-centres until it is exact at the fit)::

    sim(phi) - base  ~=  sum_k w_k(phi) (sim(node_k) - base)

Maps are those of :meth:`ContactReproducer.depth_map`: a candidate that changes only the view or
the read-out reuses the contact's FEM solution. :func:`recentre_table` tabulates a candidate
again around a fit (:mod:`tactile_deploy.calibration.discrepancy.refine`).

Everything is kept on each contact's region of interest (ROI): the pad pixels where the base map
or any tabulated change exceeds ``ROI_THRESHOLD_MM``, dilated by ``ROI_DILATE_PX``; outside it
every candidate predicts the same map. Fits, cross-validation and the bootstrap then run on these
tables alone (:mod:`tactile_deploy.calibration.discrepancy.selection`); the selected effect is re-simulated
exactly.

With measured frames (the reproducer has an imaging path, :mod:`tactile_deploy.calibration.discrepancy.imaging`)
every tabulated map is an imaged map: the base, the candidates' values (optical ones included:
the variant's frame through the calibrated pipeline, no view; read-out ones: the imaged map with
the read-out applied) and the exact re-simulations;
the ROI starts from the FEM surface's change (an imaged map is nowhere exactly flat), and each
contact keeps noise realisations of its imaged base (``noise_maps``).

Contacts estimated from their maps carry the contact itself as base parameters: the change of
the map per unit change of x, y, depth (and theta) spans a nuisance subspace that is projected out
of the residual and of every candidate's changes (a linearised joint fit of the contact).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import binary_dilation

from tactile_deploy.calibration.discrepancy.candidates import Candidate, lagrange_weights
from tactile_deploy.calibration.discrepancy.reproduce import ContactReproducer, is_round
from tactile_deploy.fem.material import NU_MAX_VALIDATED
from tactile_deploy.indenters import ContactPose
from tactile_deploy.sensors.config import EffectSpec
from tactile_deploy.sensors.effects import effect_class

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

    current : the effect's parameters in the sensor model (null and ``fixed`` values when it
    has none); coord_names : the fitted coordinates; centre : (p,) their value in the sensor
    model; axes : per coordinate (nodes, (fit_lo, fit_hi)); design : "grid" (tensor product of
    the axes' nodes, M = 3^p, or one axis with more nodes) or "star" (the middle node and one
    node either side along each axis, M = 2p + 1: an additive quadratic model, for p >= 3);
    node_coords : (M, p); deltas : per contact an (M, n_roi) float32 array of map changes (mm)
    against the base; forces : (n_contacts, M) N; usable : (n_contacts,) bool (False: not
    applicable or a tabulated value failed; the candidate then predicts no change there); note :
    why it is not testable, or "".
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
    coord_names: tuple = ()
    design: str = "grid"
    #: steps of the last re-centring (index into refine.REFINE_SHRINK), -1 = not re-centred
    refined_level: int = -1

    def __post_init__(self):
        if not self.coord_names:
            self.coord_names = tuple(self.candidate.coords)

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
        """Interpolation weights (m, M) at coordinates (m, p): tensor quadratic Lagrange (a
        single coordinate with more than 3 nodes uses the 3 nodes nearest to each point), or
        the star design's additive quadratic model."""
        c = np.atleast_2d(np.asarray(coords, np.float64))
        if c.shape[1] == 1 and len(self.axes[0][0]) > 3:
            nodes = self.axes[0][0]
            w = np.zeros((len(c), len(nodes)))
            for j, t in enumerate(c[:, 0]):
                near = np.sort(np.argsort(np.abs(nodes - t), kind="stable")[:3])
                w[j, near] = lagrange_weights(nodes[near], t)[0]
            return w
        per_axis = [lagrange_weights(self.axes[k][0], c[:, k]) for k in range(c.shape[1])]
        if self.design == "star":
            p = c.shape[1]
            w = np.zeros((len(c), 2 * p + 1))
            w[:, 0] = 1.0 - p
            for k, lw in enumerate(per_axis):
                w[:, 0] += lw[:, 1]
                w[:, 1 + 2 * k] = lw[:, 0]
                w[:, 2 + 2 * k] = lw[:, 2]
            return w
        w = per_axis[0]
        for extra in per_axis[1:]:
            w = (w[:, :, None] * extra[:, None, :]).reshape(len(c), -1)
        return w

    def params(self, coords) -> dict[str, float]:
        return self.candidate.params_of(coords, self.current, self.coord_names)

    def spec(self, coords) -> EffectSpec:
        return EffectSpec(name=self.candidate.effect, params=self.params(coords))

    @property
    def fitted_params(self) -> tuple[str, ...]:
        return self.candidate.fitted_params(self.coord_names)


def design_nodes(axes) -> tuple[str, np.ndarray]:
    """(design, node coordinates (M, p)) of per-coordinate 3-node axes: a tensor grid for up
    to two coordinates, a star beyond."""
    if len(axes) <= 2:
        return "grid", np.array(list(itertools.product(*[a[0] for a in axes])))
    mid = np.array([a[0][1] for a in axes])
    rows = [mid]
    for k, a in enumerate(axes):
        for j in (0, 2):
            r = mid.copy()
            r[k] = a[0][j]
            rows.append(r)
    return "star", np.array(rows)


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

    def subset(self, index) -> ResponseTables:
        """The tables of the contacts ``index`` (ints), in that order."""
        idx = [int(i) for i in index]
        tables = [dataclasses.replace(t, deltas=[t.deltas[i] for i in idx], forces=t.forces[idx],
                                      usable=t.usable[idx]) for t in self.tables]
        return ResponseTables([self.contacts[i] for i in idx], self.base[idx],
                              self.base_force[idx], [self.roi[i] for i in idx],
                              [self.nuisance[i] for i in idx], tables,
                              None if self.noise_maps is None else self.noise_maps[idx])

    def project(self, i: int, values: np.ndarray) -> np.ndarray:
        """Remove contact i's nuisance subspace from ``values`` (..., n_roi)."""
        q = self.nuisance[i]
        if q is None:
            return values
        return values - (values @ q) @ q.T


def _limits(repro: ContactReproducer) -> dict:
    """Narrower coordinate bounds from the sensor model (the Poisson ratio's validated range)."""
    nu0 = repro.sensor.simulator.material.nu
    return {"delta_nu": (-nu0, NU_MAX_VALIDATED - nu0)}


def _plans(repro: ContactReproducer, candidates: list[Candidate]):
    """Per candidate: (candidate, current params, centre, axes, design, node coords, specs,
    which node is the current value)."""
    sensor_effects = repro.sensor.config.effects
    plans = []
    for cand in candidates:
        current = cand.current(sensor_effects)
        centre = cand.coords_of(current)
        axes = cand.axes(centre, _limits(repro))
        design, node_coords = design_nodes(axes) if all(len(a[0]) == 3 for a in axes) else (
            "grid", np.array(list(itertools.product(*[a[0] for a in axes]))))
        specs = [EffectSpec(name=cand.effect, params=cand.params_of(nc, current))
                 for nc in node_coords]
        is_centre = np.all(np.isclose(node_coords, centre[None, :], atol=1e-12), axis=1)
        plans.append((cand, current, centre, axes, design, node_coords, specs, is_centre))
    return plans


def _skip(cand: Candidate, c: Contact) -> bool:
    """Whether the candidate predicts nothing for this contact."""
    return (cand.needs_commanded and c.estimated) or (cand.needs_non_round
                                                      and is_round(c.indenter))


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
    for cand, current, centre, axes, design, node_coords, specs, is_centre in plans:
        m = len(specs)
        maps = np.repeat(base[None], m, axis=0)
        f = np.full(m, base_force)
        ok = True
        if not _skip(cand, c):
            try:
                for k, spec in enumerate(specs):
                    if is_centre[k]:
                        continue
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
        return st["fn"](st["repro"], st["items"][i], st["args"])


def _map_contacts(repro: ContactReproducer, fn, items: list, args, progress=None,
                  workers: int = 1) -> list:
    """``[fn(repro, item, args) for item in items]``, in ``workers`` forked processes (each one
    thread; the simulator's operators are shared copy-on-write) when there are several."""
    if workers > 1 and len(items) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        repro.sensor.simulator.prepare()
        _WORKER_STATE.update(repro=repro, items=items, args=args, fn=fn)
        try:
            with ProcessPoolExecutor(min(workers, len(items)),
                                     mp_context=mp.get_context("fork")) as pool:
                out = []
                for res in pool.map(_worker, range(len(items)), chunksize=1):
                    out.append(res)
                    if progress is not None:
                        progress(1)
                return out
        finally:
            _WORKER_STATE.clear()
    out = []
    for item in items:
        out.append(fn(repro, item, args))
        if progress is not None:
            progress(1)
    return out


def tabulate(repro: ContactReproducer, contacts: list[Contact], candidates: list[Candidate],
             progress=None, workers: int = 1) -> ResponseTables:
    """Simulate the base and every candidate's tabulated values for every contact.

    progress(k) is called after each contact. workers > 1 splits the contacts over that many
    forked processes.
    """
    plans = _plans(repro, candidates)
    if workers > 1:
        for cand in candidates:  # shared operators built once, before the workers fork
            effect_class(cand.effect).prepare(repro.sensor.simulator)
    per = _map_contacts(repro, _tabulate_contact, contacts, plans, progress, workers)
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
    for cand, current, centre, axes, design, node_coords, specs, is_centre in plans:
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
                                     np.stack([p["forces"][cand.name] for p in per]), use, note,
                                     tuple(cand.coords), design))
    noise_maps = None if repro.imaging is None else np.stack([p["noise"] for p in per])
    return ResponseTables(contacts, base, base_force, rois, nuisance, tables,
                          noise_maps=noise_maps)


def _contact_node_maps(repro: ContactReproducer, item, args):
    """One contact's changes (len(specs), n_roi) float32 and forces at ``specs``; ok False when
    a value failed."""
    c, base, base_force, roi, use = item
    cand, specs = args
    maps = np.repeat(base[None], len(specs), axis=0)
    forces = np.full(len(specs), base_force)
    ok = use
    if use and not _skip(cand, c):
        try:
            for k, spec in enumerate(specs):
                maps[k], forces[k] = repro.depth_map(c.indenter, c.pose, repro.variant(spec))
        except TABULATION_ERRORS:
            ok = False
            maps[:] = base
            forces[:] = base_force
    d = (maps - base[None]).reshape(len(specs), -1)[:, roi]
    return d.astype(np.float32), forces, ok


def _node_maps(repro: ContactReproducer, tables: ResponseTables, table: CandidateTable,
               specs: list[EffectSpec], usable: np.ndarray, workers: int = 1):
    """Changes (per contact (len(specs), n_roi) float32) and forces (n, len(specs)) of the
    candidate at ``specs`` against the base maps; contacts that fail become unusable."""
    items = [(c, tables.base[i], tables.base_force[i], tables.roi[i], bool(usable[i]))
             for i, c in enumerate(tables.contacts)]
    if workers > 1 and not table.candidate.cheap:
        effect_class(table.candidate.effect).prepare(repro.sensor.simulator)
    # cheap candidates (a view or read-out of the cached FEM map) are not worth a process pool
    out = _map_contacts(repro, _contact_node_maps, items, (table.candidate, specs), None,
                        1 if table.candidate.cheap else workers)
    deltas = [o[0] for o in out]
    forces = np.stack([o[1] for o in out])
    usable[:] = [o[2] for o in out]
    return deltas, forces


def recentre_table(repro: ContactReproducer, tables: ResponseTables, table: CandidateTable,
                   coords, names: tuple[str, ...], steps, bounds, workers: int = 1
                   ) -> CandidateTable:
    """The candidate tabulated around ``coords`` (values of coordinates ``names``; the rest of
    the effect's parameters kept from ``table``): same contacts and ROIs, changes still against
    the base maps. One coordinate that the table has too gets a node at ``coords`` added to its
    nodes (interpolation then uses the 3 nearest); otherwise 3 nodes per coordinate at
    ``coords +- steps`` (a grid for two, a star beyond), fit range ``bounds``."""
    cand = table.candidate
    coords = np.asarray(coords, np.float64).ravel()
    usable = table.usable.copy()
    current = dict(table.current)
    if tuple(names) == tuple(table.coord_names) and len(names) == 1:
        nodes = table.axes[0][0]
        axes = [(nodes, tuple(bounds[0]))]
        if np.min(np.abs(nodes - coords[0])) < 1e-9 * max(1.0, np.ptp(nodes)):
            return dataclasses.replace(table, axes=axes)
        spec = EffectSpec(name=cand.effect, params=cand.params_of(coords, current, names))
        new, f = _node_maps(repro, tables, table, [spec], usable, workers)
        order = np.argsort(np.append(nodes, coords[0]), kind="stable")
        deltas = [np.concatenate([d, e], axis=0)[order] for d, e in zip(table.deltas, new)]
        forces = np.concatenate([table.forces, f], axis=1)[:, order]
        axes = [(np.append(nodes, coords[0])[order], tuple(bounds[0]))]
        return dataclasses.replace(table, axes=axes, node_coords=axes[0][0][:, None],
                                   deltas=deltas, forces=forces, usable=usable & table.usable)
    axes = []
    for k, name in enumerate(names):
        lo_hard, hi_hard = cand.limited_bounds(name, _limits(repro))
        c, h = float(coords[k]), float(steps[k])
        lo, hi = c - h, c + h
        if lo < lo_hard:  # keep three distinct nodes inside the bounds
            lo, c, hi = lo_hard, lo_hard + h, lo_hard + 2 * h
        elif hi > hi_hard:
            lo, c, hi = hi_hard - 2 * h, hi_hard - h, hi_hard
        axes.append((np.array([lo, c, hi]), (float(bounds[k][0]), float(bounds[k][1]))))
    design, node_coords = design_nodes(axes)
    specs = [EffectSpec(name=cand.effect, params=cand.params_of(nc, current, names))
             for nc in node_coords]
    deltas, forces = _node_maps(repro, tables, table, specs, usable, workers)
    centre = cand.coords_of(cand.current(repro.sensor.config.effects), tuple(names))
    return CandidateTable(cand, current, centre, axes, node_coords, deltas, forces,
                          usable & table.usable, table.note, tuple(names), design)
