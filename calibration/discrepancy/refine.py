"""Continuous refinement of a candidate: its table re-centred on its fit until the fit settles.

The first tabulation spans each candidate's realistic range around the sensor model's value, 3
values per coordinate; far from those values (a magnitude beyond the range, a centre that is not
the pad's) the quadratic interpolation misses, and a candidate that is the right effect can
explain only part of the gap. Refinement is a trust-region walk on exact simulations::

    fit the table (all samples)                              -> coordinates phi
    repeat: tabulate again at phi +- step (3 values per coordinate: a grid for two, a star
            beyond; one coordinate: a value added at phi), the coordinates that only mean
            something away from the null joining once phi is away from it
            fit within phi +- 3 steps (the trust region)      -> phi'
            phi' on the region's edge: keep the step (the walk goes on), else shrink it
            (1, 0.5, 0.25, 0.1, 0.04 of the first step)
    until phi moves by less than REFINE_TOLERANCE of a step

so a fit may end anywhere within the effect's validated bounds, however far from where the
walk started.
"""

from __future__ import annotations

import numpy as np

from tactile_deploy.calibration.discrepancy.reproduce import ContactReproducer
from tactile_deploy.calibration.discrepancy.selection import TableFit
from tactile_deploy.calibration.discrepancy.tables import CandidateTable, ResponseTables, recentre_table

#: Steps of the re-centred tables, as fractions of the candidate's first step.
REFINE_SHRINK = (1.0, 0.5, 0.25, 0.1, 0.04)
#: The fit has settled when it moves by less than this share of the candidate's first step.
REFINE_TOLERANCE = 0.01
#: The trust region of a round: this many (current) steps either side of the fit.
TRUST_STEPS = 3.0
#: A fit this close (share of a step) to the trust region's edge keeps the walk going.
EDGE_SHARE = 0.02
#: A re-centred table that can be simulated for fewer than this share of the contacts the
#: previous one could is not taken (the walk stops there).
USABLE_SHARE = 0.8
#: Primary coordinates this far (share of their first step) from the sensor model's value
#: count as away from the null (the refinement coordinates then join the fit).
AWAY_FROM_NULL = 0.05


def fit_stats(tables: ResponseTables, table: CandidateTable, depth: np.ndarray,
              sample_contact: np.ndarray, extra=None) -> tuple[np.ndarray, np.ndarray]:
    """Per sample ``D D^T`` (N, M, M) and ``D y`` (N, M) of one table; ``extra`` (per sample
    ROI vectors or None) is a change already accounted for (subtracted from the residual)."""
    n, m = len(sample_contact), len(table.node_coords)
    A, b = np.zeros((n, m, m)), np.zeros((n, m))
    for s in range(n):
        i = int(sample_contact[s])
        if not table.usable[i]:
            continue
        d = tables.project(i, table.deltas[i].astype(np.float64))
        roi = tables.roi[i]
        y = depth[s].ravel()[roi] - tables.base[i].ravel()[roi]
        if extra is not None:
            y = y - extra[s]
        A[s], b[s] = d @ d.T, d @ tables.project(i, y)
    return A, b


def _away_from_null(table: CandidateTable, coords: np.ndarray) -> bool:
    cand = table.candidate
    for k, name in enumerate(table.coord_names):
        if name in cand.coords and abs(coords[k] - table.centre[k]) > AWAY_FROM_NULL * \
                cand.step(name):
            return True
    return False


def refine_table(repro: ContactReproducer, tables: ResponseTables, table: CandidateTable,
                 depth: np.ndarray, sample_contact: np.ndarray, frames: bool, extra=None,
                 workers: int = 1, max_rounds: int = 8, start=None
                 ) -> tuple[CandidateTable, np.ndarray, int]:
    """The candidate's table re-centred on its all-sample fit until the fit settles (module
    docstring): ``(table, coordinates of the fit, rounds)``. ``start``: the fit to start from
    (default: the table's own fit); ``extra``: a second effect's change, held fixed."""
    cand = table.candidate
    A, b = fit_stats(tables, table, depth, sample_contact, extra)
    coords = np.asarray(start, np.float64) if start is not None else \
        TableFit(table).fit(A.sum(0), b.sum(0))[0]
    full = cand.all_coords(frames)
    level = max(table.refined_level, 0)
    rounds = 0
    for rounds in range(1, max_rounds + 1):
        kept = coords
        names = table.coord_names
        if names != full and _away_from_null(table, coords):
            cur = table.params(coords)
            coords = cand.coords_of(cur, full)
            names = full
        first = np.array([cand.step(nm) for nm in names])
        steps = first * REFINE_SHRINK[level]
        bounds = []
        for k, nm in enumerate(names):
            lo, hi = cand.limited_bounds(nm, {"delta_nu": _nu_limits(repro)})
            reach = TRUST_STEPS * steps[k] if len(names) > 1 else cand.reach(nm)
            bounds.append((max(lo, coords[k] - reach), min(hi, coords[k] + reach)))
        coords = np.clip(coords, [b_[0] for b_ in bounds], [b_[1] for b_ in bounds])
        new_table = recentre_table(repro, tables, table, coords, names, steps, bounds, workers)
        if new_table.usable.sum() < USABLE_SHARE * table.usable.sum():
            # the values around the fit cannot be simulated for most contacts (a view that
            # folds, a solve that does not converge): keep the last table
            coords = kept
            break
        table = new_table
        A, b = fit_stats(tables, table, depth, sample_contact, extra)
        new, _ = TableFit(table).fit(A.sum(0), b.sum(0))
        moved = float(np.max(np.abs(new - coords) / first))
        at_edge = any(
            (new[k] - lo <= EDGE_SHARE * steps[k] and lo > cand.limited_bounds(nm)[0]) or
            (hi - new[k] <= EDGE_SHARE * steps[k] and hi < cand.limited_bounds(nm)[1])
            for k, (nm, (lo, hi)) in enumerate(zip(names, bounds)))
        coords = new
        if moved < REFINE_TOLERANCE and names == table.coord_names and (
                names == full or not _away_from_null(table, coords)):
            break
        if not at_edge:
            level = min(level + 1, len(REFINE_SHRINK) - 1)
    table.refined_level = level
    return table, coords, rounds


def _nu_limits(repro: ContactReproducer) -> tuple[float, float]:
    from tactile_deploy.fem.material import NU_MAX_VALIDATED

    nu0 = repro.sensor.simulator.material.nu
    return (-nu0, NU_MAX_VALIDATED - nu0)
