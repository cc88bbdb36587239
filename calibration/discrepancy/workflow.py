"""The discrepancy workflow, top to bottom: which effect is missing from a sensor model.

Data flow of :func:`find_discrepancy`::

    measured samples (depth maps, or RGB frames through the sensor plugin's imaging pipeline)
      -> contacts: commanded, or estimated from the maps            (reproduce.py)
      -> base maps of the sensor model + every candidate's tabulated changes   (tables.py)
         (for frames: the model's frames through the same pipeline, with noise realisations:
         imaging.py)
      -> pixel noise from the residual's Laplacian, the realisations, or as given  (noise.py)
      -> residual fingerprint                                         (fingerprint.py)
      -> candidates that explain a good part of the gap: their tables re-centred on their
         fits until the fits settle (any magnitude within the effect's bounds)   (refine.py)
      -> fits, held-out gains by contact, BIC, effect-free null, bootstrap     (selection.py)
      -> the best candidate refined further, then re-simulated exactly on held-out contacts:
         gap before -> after                                          (verify_effect)
      -> structure common to every map, away from the contacts, in the residual after the
         best candidate (a static relief no candidate explains)        (static.py)
      -> look-alikes: the experiment that tells them apart            (experiment.py)
      -> verdict: effect / ambiguous / unexplained / none             (verdict.py)
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from tactile_deploy.calibration.discrepancy.candidates import candidate_library
from tactile_deploy.calibration.discrepancy.experiment import distinguishing_experiment
from tactile_deploy.calibration.discrepancy.fingerprint import Fingerprint, residual_fingerprint
from tactile_deploy.calibration.discrepancy.imaging import FrameImaging
from tactile_deploy.calibration.discrepancy.measured import MeasuredData, MeasuredDataError
from tactile_deploy.calibration.discrepancy.noise import (
    NoiseEstimate,
    estimate_noise,
    known_noise,
    noise_from_realisations,
)
from tactile_deploy.calibration.discrepancy.refine import fit_stats, refine_table
from tactile_deploy.calibration.discrepancy.reproduce import ContactReproducer
from tactile_deploy.calibration.discrepancy.selection import (
    STRUCTURE_MIN_EXCESS,
    STRUCTURE_Z,
    Selection,
    TableFit,
    excess_energy,
    select_effect,
    sufficient_stats,
)
from tactile_deploy.calibration.discrepancy.static import (
    StaticStructure,
    describe_blob,
    static_structure,
)
from tactile_deploy.calibration.discrepancy.tables import (
    Contact,
    ResponseTables,
    tabulate,
)
from tactile_deploy.calibration.discrepancy.verdict import CandidateReport, DiscrepancyVerdict, finite
from tactile_deploy.sensors.config import EffectSpec
from tactile_deploy.sensors.virtual import VirtualSensor

#: Share of the residual's excess energy over the noise that the named effect must remove
#: (held-out, exact), or that it removes together with a second candidate (tables): below it
#: the structure is reported as unexplained. 0.75 = the systematic gap halved.
EXPLAIN_MIN = 0.75
#: Before the selection, candidates whose all-sample fit removes at least this share of the
#: residual's excess energy are refined, the best first: REFINE_CANDIDATES of them, and further
#: ones, down the list, while none of those refined removes EXPLAIN_MIN of it (a candidate with
#: large-deformation solves only when it is the best).
REFINE_MIN_SHARE = 0.2
REFINE_CANDIDATES = 4
#: With measured frames every refined value is an imaged map (a rendered frame through the
#: pipeline, 6 noise draws): the best two candidates are refined before the selection, further
#: ones only while neither explains the gap. An imaged dome's change grows much faster than its
#: height (the shading of the sagging rim): its first table, quadratic through -0.25, 0 and
#: 0.5 mm, fits a 0.3 mm dome at 0.1 mm, 6th of the candidates behind a zero offset and a depth
#: scale that explain half of the gap each; refined, it explains 96 %.
REFINE_CANDIDATES_FRAMES = 2
#: Rounds of re-centring at most (depth maps, measured frames).
REFINE_ROUNDS = 8
REFINE_ROUNDS_FRAMES = 3


@dataclass
class DiscrepancyOptions:
    """folds : K of the grouped cross-validation; null_replicates : effect-free replicates;
    bootstrap : resamples of contact groups (gains), param_bootstrap : refits (intervals);
    candidates : names to consider (None: the whole library); plugin : sensor plugin whose
    imaging pipeline turns measured frames into depth (default: the sensor's name); pipeline :
    that pipeline itself (an object with ``frame_to_depth``; overrides ``plugin``); workers :
    processes that tabulate the contacts' responses; refine : re-centre the tables of the
    candidates that explain a good part of the gap before the selection."""

    folds: int = 5
    null_replicates: int = 200
    bootstrap: int = 400
    param_bootstrap: int = 100
    seed: int = 0
    candidates: tuple[str, ...] | None = None
    plugin: str | None = None
    pipeline: object | None = None
    workers: int = 1
    refine: bool = True


@dataclass
class Verification:
    """The named effect re-simulated exactly: parameters fitted on all samples (after a second
    tabulation around the first fit), and held-out maps with the effect."""

    spec: EffectSpec
    params: dict
    intervals: dict
    after_mm: np.ndarray          # (N, 128, 128) held-out maps with the effect
    energy_after: np.ndarray      # (N,) squared residual on each ROI, mm^2
    force_after_n: np.ndarray     # (N,)


@dataclass
class DiscrepancyResult:
    """Everything the verdict and the report come from."""

    verdict: DiscrepancyVerdict
    measured: MeasuredData
    depth_mm: np.ndarray
    tables: ResponseTables
    sample_contact: np.ndarray
    noise: NoiseEstimate
    fingerprint: Fingerprint
    selection: Selection
    verification: Verification | None
    gap_before_mm: np.ndarray      # (N,) per sample, systematic
    gap_after_mm: np.ndarray | None
    timings_s: dict = field(default_factory=dict)


def _stage(progress, description: str, total: int):
    if progress is None:
        return contextlib.nullcontext(lambda n=1: None)
    return progress(description, total)


def measured_depth_maps(measured: MeasuredData, opts: DiscrepancyOptions, sensor_name: str):
    """(N, 128, 128) mm depth of the samples and the imaging pipeline that made them from the
    measured frames (None for measured maps)."""
    if measured.depth_mm is not None:
        return measured.depth_mm.astype(np.float64), None
    from tactile_deploy.runtime.pipeline import FrameError, ImagingPipeline
    from tactile_deploy.runtime.plugins import PluginError, SensorPlugin

    name = opts.plugin or sensor_name
    try:
        pipeline = opts.pipeline or ImagingPipeline.from_plugin(SensorPlugin.load(name))
        return np.stack([pipeline.frame_to_depth(f) for f in measured.frames]).astype(
            np.float64), pipeline
    except (PluginError, FrameError) as e:
        raise MeasuredDataError(f"{measured.source}: the frames cannot be turned into depth with "
                                f"plugin {name!r}: {e}; give --plugin, or depth maps") from None


def reproducer(sensor: VirtualSensor, pipeline, opts: DiscrepancyOptions) -> ContactReproducer:
    """The contact reproducer: FEM maps, or imaged maps when ``pipeline`` made the measured
    maps from frames."""
    return ContactReproducer(sensor, None if pipeline is None
                             else FrameImaging(pipeline, seed=opts.seed))


def reproduce_contacts(repro: ContactReproducer, measured: MeasuredData, depth: np.ndarray,
                       progress=None) -> tuple[list[Contact], np.ndarray]:
    """Unique contacts of the samples (commanded, or estimated per sample) and each sample's
    index into them."""
    contacts, index, seen = [], np.zeros(measured.n, np.int64), {}
    with _stage(progress, "reproducing contacts", measured.n) as advance:
        for s in range(measured.n):
            pose = measured.pose(s)
            c = (Contact(measured.indenter[s], pose) if pose is not None else
                 Contact(measured.indenter[s], repro.estimate_pose(measured.indenter[s],
                                                                   depth[s]), True))
            key = c.key if not c.estimated else ("estimated", s)
            if key not in seen:
                seen[key] = len(contacts)
                contacts.append(c)
            index[s] = seen[key]
            advance(1)
    return contacts, index


def prepare_tables(sensor: VirtualSensor, measured: MeasuredData,
                   options: DiscrepancyOptions | None = None, progress=None) -> ResponseTables:
    """The response tables of ``measured``'s contacts (reusable for other data of the same
    commanded contacts: pass them to :func:`find_discrepancy`)."""
    opts = options or DiscrepancyOptions()
    depth, pipeline = measured_depth_maps(measured, opts, sensor.name)
    repro = reproducer(sensor, pipeline, opts)
    contacts, _ = reproduce_contacts(repro, measured, depth, progress)
    with _stage(progress, "tabulating candidate responses", len(contacts)) as advance:
        return tabulate(repro, contacts, candidate_library(opts.candidates), advance,
                        opts.workers)


def find_discrepancy(sensor: VirtualSensor, measured: MeasuredData,
                     options: DiscrepancyOptions | None = None,
                     tables: ResponseTables | None = None, progress=None) -> DiscrepancyResult:
    """Which effect is missing from ``sensor`` given ``measured`` (module docstring)."""
    opts = options or DiscrepancyOptions()
    timings = {}
    t0 = time.perf_counter()
    depth, pipeline = measured_depth_maps(measured, opts, sensor.name)
    repro = reproducer(sensor, pipeline, opts)
    contacts, sample_contact = reproduce_contacts(repro, measured, depth, progress)
    timings["contacts"] = time.perf_counter() - t0
    if tables is None:
        with _stage(progress, "tabulating candidate responses", len(contacts)) as advance:
            tables = tabulate(repro, contacts, candidate_library(opts.candidates), advance,
                              opts.workers)
    elif (tables.noise_maps is not None) != (pipeline is not None):
        raise ValueError("the response tables were made for "
                         f"{'frames' if tables.noise_maps is not None else 'depth maps'}, the "
                         "measured data are not; prepare them with prepare_tables for these data")
    elif [c.key for c in tables.contacts] != [c.key for c in contacts]:
        raise ValueError("the response tables were made for other contacts; prepare them with "
                         "prepare_tables for these data")
    timings["tables"] = time.perf_counter() - t0 - timings["contacts"]

    t1 = time.perf_counter()
    base = tables.base[sample_contact]
    residual = depth - base
    stats = sufficient_stats(tables, depth, sample_contact, measured.contact_id)
    noise = _noise(stats, measured, residual, repro, opts)
    refined = {}
    if opts.refine:
        # the caller's tables are shared between datasets: refine a copy of the list
        tables = dataclasses.replace(tables, tables=list(tables.tables))
        with _stage(progress, "refining the candidates that explain part of the gap",
                    REFINE_CANDIDATES) as advance:
            refined = refine_candidates(repro, tables, stats, noise, depth, sample_contact,
                                        pipeline is not None, opts.workers, advance)
        if refined:
            stats = sufficient_stats(tables, depth, sample_contact, measured.contact_id)
    timings["refine"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    roi_masks = np.zeros((measured.n, 128, 128), bool)
    for s in range(measured.n):
        roi_masks[s].ravel()[tables.roi[sample_contact[s]]] = True
    centres = np.array([[tables.contacts[i].pose.x_mm, tables.contacts[i].pose.y_mm]
                        for i in sample_contact])
    depths = np.array([tables.contacts[i].pose.depth_mm for i in sample_contact])
    fingerprint = residual_fingerprint(residual, base, centres, depths, measured.indenter,
                                       roi_masks, repro.pad_mask, noise.sigma_mm, repro.camera,
                                       _outside_noise(tables, sample_contact, roi_masks,
                                                      repro.pad_mask))
    selection = select_effect(tables, stats, noise, opts.folds, opts.null_replicates,
                              opts.bootstrap, opts.param_bootstrap, opts.seed)
    timings["selection"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    verification = None
    if selection.best is not None:
        with _stage(progress, f"re-simulating {selection.best} on held-out contacts",
                    len(tables.contacts)) as advance:
            verification = verify_effect(repro, tables, selection, depth, sample_contact,
                                         measured, opts, advance)
    timings["verification"] = time.perf_counter() - t2
    fingerprint.static = static_test(tables, sample_contact, depth, verification, noise, repro,
                                     roi_masks)
    fingerprint.summary["static_structure"] = fingerprint.static.summary()
    timings["static"] = time.perf_counter() - t2 - timings["verification"]
    sigma2 = noise.sigma_mm**2
    gap_before = np.sqrt(np.maximum(stats.energy / np.maximum(stats.dof, 1) - sigma2, 0.0))
    gap_after = None
    if verification is not None:
        gap_after = np.sqrt(np.maximum(verification.energy_after / np.maximum(stats.dof, 1)
                                       - sigma2, 0.0))
    t3 = time.perf_counter()
    verdict = decide(sensor, measured, tables, selection, fingerprint, verification, stats,
                     repro, sample_contact)
    timings["verdict"] = time.perf_counter() - t3
    timings["total"] = time.perf_counter() - t0
    return DiscrepancyResult(verdict, measured, depth, tables, sample_contact, noise,
                             fingerprint, selection, verification, gap_before, gap_after,
                             timings)


def _noise(stats, measured: MeasuredData, residual: np.ndarray, repro: ContactReproducer,
           opts: DiscrepancyOptions) -> NoiseEstimate:
    """The pixel noise: from the imaged maps' realisations, given with the data, or estimated
    from the residual."""
    if stats.noise_energy is not None:
        noise = noise_from_realisations(stats.noise_energy, stats.dof, opts.seed)
        if measured.noise_mm is not None:
            noise = dataclasses.replace(known_noise(measured.noise_mm),
                                        energy_factor=noise.energy_factor)
        return noise
    if measured.noise_mm is not None:
        return known_noise(measured.noise_mm)
    return estimate_noise(residual, repro.pad_mask, opts.seed)


def refine_candidates(repro: ContactReproducer, tables: ResponseTables, stats, noise,
                      depth: np.ndarray, sample_contact: np.ndarray, frames: bool,
                      workers: int = 1, advance=None) -> dict[str, int]:
    """Re-centre (in ``tables``) the tables of the candidates whose all-sample fit removes at
    least ``REFINE_MIN_SHARE`` of the residual's excess energy, when there is structure beyond
    the noise, the best first: ``REFINE_CANDIDATES`` (``REFINE_CANDIDATES_FRAMES``), then one
    by one while no refined table removes ``EXPLAIN_MIN`` of it: ``{name: rounds}``."""
    excess, z, n_pix = excess_energy(stats, noise)
    if not (z > STRUCTURE_Z and excess > STRUCTURE_MIN_EXCESS):
        return {}
    units = excess * n_pix * noise.sigma_mm**2  # mm^2
    reductions = []
    for t in tables.tables:
        if not t.testable:
            continue
        blk = stats.blocks[t.name]
        _, red = TableFit(t).fit(stats.gram[:, blk, blk].sum(0), stats.proj[:, blk].sum(0))
        reductions.append((red, t.name))
    reductions.sort(reverse=True)
    first = REFINE_CANDIDATES_FRAMES if frames else REFINE_CANDIDATES
    out = {}
    explained = 0.0  # the largest share of the excess a refined table removes (all samples)
    for rank, (red, name) in enumerate(reductions):
        if red < REFINE_MIN_SHARE * units or (rank >= first and explained >= EXPLAIN_MIN):
            break
        table = tables.table(name)
        if table.candidate.route == "nonlinear" and rank:
            continue
        new, _, rounds = refine_table(repro, tables, table, depth, sample_contact, frames,
                                      workers=workers, max_rounds=REFINE_ROUNDS_FRAMES if frames
                                      else REFINE_ROUNDS)
        tables.tables[tables.tables.index(table)] = new
        out[name] = rounds
        A, b = fit_stats(tables, new, depth, sample_contact)
        explained = max(explained, TableFit(new).fit(A.sum(0), b.sum(0))[1] / units)
        if advance is not None:
            advance(1)
    return out


def _outside_noise(tables: ResponseTables, sample_contact: np.ndarray, roi_masks: np.ndarray,
                   pad_mask: np.ndarray):
    """(expected sum, standard deviation) of the noise's squared residual outside every
    sample's ROI, from the noise realisations (imaged frames), mm^2; None without them."""
    if tables.noise_maps is None:
        return None
    mean = var = 0.0
    for s, i in enumerate(sample_contact):
        out = pad_mask & ~roi_masks[s]
        draws = tables.noise_maps[int(i)][:, out].astype(np.float64)  # (J, pixels outside)
        e = np.einsum("jk,jk->j", draws, draws)
        mean += float(e.mean())
        var += float(e.var(ddof=1))
    return mean, math.sqrt(var)


def static_test(tables: ResponseTables, sample_contact: np.ndarray, depth: np.ndarray,
                verification: Verification | None, noise: NoiseEstimate,
                repro: ContactReproducer, roi_masks: np.ndarray) -> StaticStructure:
    """Structure common to every map (static.py) in the residual after the best candidate:
    the held-out maps with the named effect, or the sensor model's maps when none is named, on
    each sample's region of interest ``roi_masks`` (N, H, W) (where those maps are the
    candidate's). With imaged frames each sample's pixel noise variance comes from its
    contact's noise realisations."""
    base = tables.base[sample_contact]
    after = base if verification is None else verification.after_mm
    var = None
    rel_se = 0.0
    if tables.noise_maps is not None:
        per_contact = np.stack([np.asarray(m, np.float64).var(axis=0, ddof=1)
                                for m in tables.noise_maps])
        var = per_contact[sample_contact]
        j = min(len(m) for m in tables.noise_maps)
        rel_se = math.sqrt(2.0 / max(len(sample_contact) * (j - 1), 1))
    return static_structure(depth - after, base, repro.pad_mask, repro.camera, noise.sigma_mm,
                            noise.se_mm, var, rel_se, roi_masks)


def _second_change(tables: ResponseTables, selection: Selection, sample_contact):
    """Per sample ROI change of the second effect of a pair at its joint fit (tables), or
    None without a pair."""
    if not selection.pair:
        return None
    t = tables.table(selection.pair["second"])
    w = t.weights(selection.pair["coords"][1])[0]
    return [w @ t.deltas[int(i)].astype(np.float64) for i in sample_contact]


#: A tabulated value this close to a fold's fit (share of the fit range) stands for its exact
#: re-simulation.
REUSE_TOLERANCE = 0.002


def verify_effect(repro: ContactReproducer, tables: ResponseTables, selection: Selection,
                  depth: np.ndarray, sample_contact: np.ndarray, measured: MeasuredData,
                  opts: DiscrepancyOptions, advance) -> Verification:
    """Tabulate the best candidate again around its fit until the fit settles, refit (all
    samples and per fold), and re-simulate every sample exactly with the parameters fitted
    without its fold."""
    best = selection.stats(selection.best)
    table = tables.table(best.name)
    # contacts where the candidate predicts something; a refined node that fails to simulate
    # (e.g. a neo-Hookean solve beyond the fit) leaves them out of the refined table only
    predicts = table.usable.copy()
    # with a second effect present, the named one is fitted jointly (the second's change, from
    # the tables, held at its joint fit)
    extra = _second_change(tables, selection, sample_contact)
    coords = best.coords if extra is None else selection.pair["coords"][0]
    frames = repro.imaging is not None
    table, coords, _ = refine_table(repro, tables, table, depth, sample_contact, frames, extra,
                                    opts.workers, start=coords,
                                    max_rounds=REFINE_ROUNDS_FRAMES if frames else REFINE_ROUNDS)
    A, b = fit_stats(tables, table, depth, sample_contact, extra)
    span = np.array([hi - lo for lo, hi in table.bounds])
    fitter = TableFit(table)
    n = len(sample_contact)
    coords, _ = fitter.fit(A.sum(0), b.sum(0))
    params = table.params(coords)
    labels, inverse = np.unique(measured.contact_id, return_inverse=True)
    rng = np.random.default_rng([opts.seed, 0x76657269])
    draws = []
    informative = np.einsum("nii->n", A) > 0
    for c in rng.multinomial(len(labels), np.full(len(labels), 1.0 / len(labels)),
                             size=opts.param_bootstrap):
        w = c[inverse].astype(np.float64)
        if not np.any(w[informative] > 0):  # no contact that shows the effect
            continue
        phi, _ = fitter.fit(np.einsum("n,nij->ij", w, A), w @ b)
        draws.append(table.params(phi))
    intervals = {}
    # no resample at all when the refined table could not be simulated anywhere (e.g. a lens
    # distortion that is not invertible over the image at the fit): no interval then
    for key in table.fitted_params if draws else ():
        value = params[key]
        vals = np.array([d[key] for d in draws])
        period = {"azimuth_deg": 360.0, "axis_deg": 180.0}.get(key)
        if period:
            vals = value + (vals - value + period / 2) % period - period / 2
        intervals[key] = (float(np.quantile(vals, 0.025)), float(np.quantile(vals, 0.975)))

    after = tables.base[sample_contact].copy()
    energy_after = np.zeros(n)
    force_after = np.zeros(n)
    cache = {}
    for test in selection.folds:
        train = ~test
        phi, _ = fitter.fit(A[train].sum(0), b[train].sum(0))
        # a tabulated value within REUSE_TOLERANCE of the fold's fit is its exact simulation
        near = np.flatnonzero(np.all(np.abs(table.node_coords - phi) <= REUSE_TOLERANCE * span,
                                     axis=1))
        spec = table.spec(phi)
        for s in np.flatnonzero(test):
            i = int(sample_contact[s])
            roi = tables.roi[i]
            key = (i, tuple(np.round(phi, 12)))
            if key not in cache:
                c = tables.contacts[i]
                base = tables.base[i].ravel()[roi]
                if not predicts[i]:  # the candidate predicts no change there
                    sim, f = base, tables.base_force[i]
                elif len(near) and table.usable[i]:
                    sim, f = base + table.deltas[i][near[0]], table.forces[i, near[0]]
                else:
                    try:
                        full, f = repro.depth_map(c.indenter, c.pose, repro.variant(spec))
                        sim = full.ravel()[roi]
                    except (ValueError, RuntimeError):
                        sim, f = base, tables.base_force[i]
                cache[key] = (sim, f)
                advance(1)
            sim, f = cache[key]
            if extra is not None:
                sim = sim + extra[s]
            after[s].ravel()[roi] = sim
            force_after[s] = f
            r = tables.project(i, depth[s].ravel()[roi] - sim)
            energy_after[s] = float(r @ r)
    return Verification(table.spec(coords), params, intervals, after, energy_after, force_after)


def _force_summary(sensor, measured, tables, sample_contact, verification) -> dict:
    fm = measured.force_n
    ok = np.isfinite(fm) & (fm > 0)
    if not ok.any():
        return {}
    E = sensor.config.material.E_mpa
    f0 = tables.base_force[sample_contact][ok]
    out = {"n_forces": int(ok.sum()),
           "gap_before_fraction": float(np.sqrt(np.mean(((fm[ok] - f0) / fm[ok]) ** 2))),
           "E_before_mpa": float(E * (fm[ok] @ f0) / max(f0 @ f0, 1e-300))}
    if verification is not None:
        f1 = verification.force_after_n[ok]
        out["gap_after_fraction"] = float(np.sqrt(np.mean(((fm[ok] - f1) / fm[ok]) ** 2)))
        out["E_after_mpa"] = float(E * (fm[ok] @ f1) / max(f1 @ f1, 1e-300))
    return out


def _static_text(static: StaticStructure) -> str:
    b = static.blobs[0]
    more = f" (and {len(static.blobs) - 1} more)" if len(static.blobs) > 1 else ""
    return (f"a static relief common to every map at {describe_blob(b)} (threshold z "
            f"{static.threshold_z:.1f}){more}")


def decide(sensor, measured, tables, selection: Selection, fingerprint: Fingerprint,
           verification: Verification | None, stats, repro, sample_contact) -> DiscrepancyVerdict:
    """The verdict from the selection, the exact verification and the fingerprint."""
    sigma2 = selection.noise.sigma_mm**2
    dof = selection.dof
    excess_energy = selection.energy - sigma2 * dof
    gap_before = math.sqrt(max(selection.energy / dof - sigma2, 0.0))
    static = fingerprint.static
    static_present = static is not None and static.present
    reports = []
    for c in selection.candidates:
        t = tables.table(c.name)
        reports.append(CandidateReport(
            name=c.name, kind=t.candidate.kind, testable=c.testable, note=c.note,
            parameters={k: float(v) for k, v in c.params.items()},
            intervals={k: (float(a), float(b)) for k, (a, b) in c.intervals.items()},
            heldout_gain=c.gain, gain_interval=c.gain_interval, delta_bic=c.delta_bic,
            explained_fraction=c.explained, best_frequency=c.best_frequency,
            significant=c.significant))
    est = sum(c.estimated for c in tables.contacts)
    contacts = "commanded" if est == 0 else "estimated" if est == len(tables.contacts) else "mixed"
    common = dict(noise_mm=selection.noise.sigma_mm, noise_source=selection.noise.source,
                  noise_energy_factor=selection.noise.energy_factor, excess=selection.excess,
                  excess_z=selection.excess_z, null_threshold=selection.null_threshold,
                  force=_force_summary(sensor, measured, tables, sample_contact, verification),
                  candidates=reports, fingerprint=finite(fingerprint.summary), sensor=sensor.name,
                  n_samples=measured.n, n_contacts=len(tables.contacts), contacts=contacts,
                  gap_before_mm=gap_before)
    best = selection.best
    if best is None:
        if selection.structure or fingerprint.outside_structure:
            where = ("outside every contact's reach" if fingerprint.outside_structure
                     and not selection.structure else "in the contact regions")
            msg = (f"structure beyond the noise {where} (excess {selection.excess:.3f}, "
                   f"z {selection.excess_z:.0f}) that no candidate explains"
                   + (f"; {_static_text(static)}" if static_present else "")
                   + "; see the fingerprint")
            return DiscrepancyVerdict(verdict="unexplained", message=msg, **common)
        if static_present:
            msg = f"{_static_text(static)}, which no candidate explains; see the fingerprint"
            return DiscrepancyVerdict(verdict="unexplained", message=msg, **common)
        return DiscrepancyVerdict(verdict="none", message="the residual is consistent with the "
                                  "noise: nothing is missing from the model", **common)
    bs = selection.stats(best)
    energy_after = float(verification.energy_after.sum())
    gap_after = math.sqrt(max(energy_after / dof - sigma2, 0.0))
    explained = (selection.energy - energy_after) / excess_energy if excess_energy > 0 else 0.0
    x_after = energy_after / (sigma2 * dof) - 1.0
    z_after = x_after / math.sqrt(2.0 * selection.noise.energy_factor / dof
                                  + (2 * selection.noise.se_mm / selection.noise.sigma_mm) ** 2)
    remaining = bool(z_after > STRUCTURE_Z and x_after > STRUCTURE_MIN_EXCESS) or static_present
    second = selection.pair["second"] if selection.pair else None
    # with a second effect, gap_after and explained are those of both together (the named
    # effect re-simulated exactly, the second from the tables): apply the first, run again
    named = dict(effect=best, parameters=verification.params, intervals=verification.intervals,
                 gap_after_mm=gap_after, explained_fraction=explained,
                 confidence=bs.best_frequency, remaining_structure=remaining or bool(second),
                 second_effect=second)
    if explained < EXPLAIN_MIN:
        partial = f" (together with {second})" if second else ""
        msg = (f"structure beyond the noise that no candidate explains: the best, {best}"
               f"{partial}, removes only {100 * explained:.0f} % of it on held-out contacts; "
               "see the fingerprint")
        return DiscrepancyVerdict(verdict="unexplained", message=msg,
                                  **{**named, "second_effect": None}, **common)
    if selection.lookalikes:
        specs = {best: verification.spec}
        for nm in selection.lookalikes:
            st = selection.stats(nm)
            specs[nm] = tables.table(nm).spec(st.coords)
        exp = distinguishing_experiment(repro, specs, selection.noise.sigma_mm)
        msg = (f"{best} or look-alikes {', '.join(selection.lookalikes)} explain the gap "
               f"about equally well")
        return DiscrepancyVerdict(verdict="ambiguous", message=msg,
                                  ambiguous_with=list(selection.lookalikes),
                                  experiment=exp.get("text"), **named, **common)
    both = f" together with a second effect, {second} (apply {best}, run again)" if second \
        else ""
    msg = (f"{best}{both} explains {100 * explained:.0f} % of the held-out gap's structure "
           f"({gap_before * 1e3:.2f} -> {gap_after * 1e3:.2f} um)"
           + (f"; besides, {_static_text(static)}, which no candidate explains"
              if static_present else ""))
    return DiscrepancyVerdict(verdict="effect", message=msg, **named, **common)
