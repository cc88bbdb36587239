"""Marble shading model on the real GelSight ball presses: accuracy of three methods side by
side, and speed of the applied model; absolute depth on virtual-sensor presses.

    python bench/bench_shading.py [--small] [--figure docs/img/shading_real.png] [--only real|virtual]

Measures, in one run on this machine:

* grouped 7-fold cross-validation over the 42 presses of
  ``../shared/data/real/fots_gelsight_ballpress`` (every press held out once, same folds for
  all methods): shape error (RMS residual to the sphere of the ball's known radius, centre and
  offset free, inside 0.8 x the labelled contact radius), fitted ball radius (radius free too)
  against 2.35 mm, and that split by the distance of the press from the image centre;
* speed of the applied model on a 240 x 320 frame (offset, colour lookup, Poisson), of the
  Poisson solve alone (240 x 320 and 128 x 128) and of the calibration on all 42 presses.

``main()`` prints both as markdown and writes them, with the targets, as the ``shading`` section of
BENCHMARKS.md (``bench/report.py``). ``--small`` runs 3 folds and a shorter MLP training
(seconds; a smoke test: nothing is written).

Virtual-sensor presses (the ``shading-virtual`` section; absolute depth, which the real presses
cannot judge): the calibration wizard on ``virtual:gelslim2`` with the simulated rig (24 ball
presses), then the shading model fitted on its presses: without targets for the sunken gel
around the contacts, with them (the ball press solved by the FEM of the pad) and the table's
former fallback (the colour bin's whole-image mean, 32 bins), and as the wizard fits it now
(FEM targets, the colour-polynomial fallback, 24 bins); each run through the runtime's imaging
pipeline on two sets of new presses (:mod:`tactile_deploy.calibration.shading.virtual_check`): the bench set (8
at least two contact radii inside the view, 8 within 1.2-1.7 contact radii of its edges) and a
larger second set with another seed (24 inside, 8 near the edges), so that a setting is not
judged on 8 presses alone; beside them the integration of the presses' true gradients, i.e.
what the zero-depth border of the integration costs by itself, and the wizard's model integrated
with a weight per pixel from its gradients' true error (an oracle: the most that weighting the
integration by the table's confidence could gain).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

DATA = ROOT / ".." / "shared" / "data" / "real" / "fots_gelsight_ballpress"
SHARED = ROOT.parent / "shared" / "data"
BALL_RADIUS_MM = 2.35
MM_PER_PX = 1 / 19.58


def load():
    from tactile_deploy.calibration.shading.presses import load_presses

    if not (DATA / "annotate.csv").is_file():
        raise SystemExit(f"real ball-press data not found at {DATA.resolve()} (see "
                         "../shared/data/README.md)")
    return load_presses(DATA / "background.png", DATA, DATA / "annotate.csv")


def _median_ms(fn, n: int) -> tuple[float, float]:
    """Median wall time and median process CPU time of one call, ms (the CPU time is what the
    call costs when the machine is shared with other work)."""
    import numpy as np

    fn()
    wall, cpu = [], []
    for _ in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall) * 1e3), float(np.median(cpu) * 1e3)


def accuracy(presses, folds: int = 7, mlp_steps: int = 800):
    """Cross-validated comparison (:func:`tactile_deploy.calibration.shading.compare.compare_methods`)."""
    from tactile_deploy.calibration.shading.compare import compare_methods

    return compare_methods(presses, BALL_RADIUS_MM, MM_PER_PX, folds=folds, mlp_steps=mlp_steps,
                           workers=2)


def speed(presses, n: int = 50) -> dict[str, tuple[float, float]]:
    """(wall, CPU) median times of the runtime steps (ms) and of the calibration (s)."""
    import numpy as np

    from tactile_deploy.calibration.shading.baselines import fit_rgb_table
    from tactile_deploy.calibration.shading.fit import fit_shading
    from tactile_deploy.imaging.poisson import poisson_solver
    from tactile_deploy.imaging.shading import DepthFromShading, frame_offset

    t0, c0 = time.perf_counter(), time.process_time()
    fit = fit_shading(presses, BALL_RADIUS_MM, MM_PER_PX)
    calib_s = (time.perf_counter() - t0, time.process_time() - c0)
    run = DepthFromShading(fit.model, presses.reference)
    frame = presses.frames[0]
    rng = np.random.default_rng(0)
    g = rng.standard_normal((2, 320, 240)).astype(np.float32)
    g128 = rng.standard_normal((2, 128, 128)).astype(np.float32)
    s320 = poisson_solver((320, 240), "dirichlet", (0.05, 1.0))
    s128 = poisson_solver((128, 128), "dirichlet", (1.0, 1.0))
    table = fit_rgb_table(presses, BALL_RADIUS_MM, MM_PER_PX)
    return {
        "frame offset": _median_ms(lambda: frame_offset(frame, presses.reference), n),
        "colour -> gradients (incl. offset)": _median_ms(lambda: run.image_gradients(frame), n),
        "frame -> depth (gradients + Poisson)": _median_ms(lambda: run.depth(frame), n),
        "Poisson 240 x 320": _median_ms(lambda: s320.integrate(g[0], g[1]), n),
        "Poisson 128 x 128": _median_ms(lambda: s128.integrate(g128[0], g128[1]), n),
        "reference RGB table frame -> depth": _median_ms(lambda: table.depth(frame), n),
        "calibration on 42 presses (s)": calib_s,
    }


def figure(presses, path: Path, fold: int = 0, folds: int = 7, mlp_steps: int = 800) -> None:
    """Held-out reconstructions of four presses of one fold vs the fitted sphere (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from tactile_deploy.calibration.shading.compare import METHOD_NAMES, method_fitters
    from tactile_deploy.calibration.shading.evaluate import fit_sphere
    from tactile_deploy.atomic import atomic_path

    n = len(presses)
    held = np.flatnonzero(np.arange(n) % folds == fold)
    dist = np.hypot(presses.circles[held, 0] - 119.5, presses.circles[held, 1] - 159.5)
    show = held[np.argsort(dist)][[0, 2, len(held) - 2, len(held) - 1]]
    train = presses.subset(np.arange(n) % folds != fold)
    predictors = {k: f(train) for k, f in method_fitters(BALL_RADIUS_MM, MM_PER_PX,
                                                          mlp_steps=mlp_steps).items()}
    colours = {"lut": "tab:blue", "rgb_table": "tab:orange", "mlp": "tab:green"}
    fig, axes = plt.subplots(len(show), 3, figsize=(10.0, 2.3 * len(show)),
                             gridspec_kw={"width_ratios": [0.8, 1.6, 1.6]})
    for row, i in enumerate(show):
        cx, cy, a = presses.circles[i]
        half = int(1.5 * a)
        sl = (slice(max(int(cy) - half, 0), int(cy) + half),
              slice(max(int(cx) - half, 0), int(cx) + half))
        axes[row, 0].imshow(presses.frames[i][sl])
        axes[row, 0].set_title(f"{presses.names[i]} (held out)", fontsize=8)
        axes[row, 0].axis("off")
        band = 0.8 * a * MM_PER_PX
        for key, pred in predictors.items():
            d = pred.depth(presses.frames[i])
            sph = fit_sphere(d, presses.circles[i], MM_PER_PX, BALL_RADIUS_MM)
            ccol, crow = sph.centre_px
            x = (np.arange(d.shape[1]) - ccol) * MM_PER_PX
            line = d[round(crow)]
            sphere = sph.apex_mm - (BALL_RADIUS_MM - np.sqrt(np.maximum(
                BALL_RADIUS_MM ** 2 - x ** 2, 0.0)))
            inside = np.abs(x) <= band
            label = f"{METHOD_NAMES[key].split(' (')[0].replace('reference: ', '')}"
            if key == "lut":
                ax = axes[row, 1]
                ax.plot(x, line, color=colours[key], lw=1.4, label="reconstruction")
                ax.plot(x[np.abs(x) < 2.2], sphere[np.abs(x) < 2.2], "k--", lw=1.0,
                        label="fitted sphere, R = 2.35 mm")
                ax.axvspan(-band, band, color="0.92", zorder=0)
                ax.set_xlim(-2.4 * a * MM_PER_PX, 2.4 * a * MM_PER_PX)
                ax.set_ylim(-0.1, sph.apex_mm + 0.15)
                ax.set_ylabel("depth (mm)", fontsize=8)
                ax.legend(fontsize=7, loc="upper left")
                ax.set_title(f"{METHOD_NAMES[key]}", fontsize=8)
            axes[row, 2].plot(x[inside], 1e3 * (line - sphere)[inside], color=colours[key],
                              lw=1.2, label=f"{label}: shape error {sph.rms_um:.0f} um")
        axes[row, 2].axhline(0, color="k", lw=0.6)
        axes[row, 2].set_ylim(-150, 150)
        axes[row, 2].set_ylabel("depth - sphere (um)", fontsize=8)
        axes[row, 2].legend(fontsize=6.5, loc="lower center")
        axes[row, 2].set_title("residual to the fitted sphere, inside 0.8 x contact radius",
                               fontsize=8)
        for ax in axes[row, 1:]:
            ax.tick_params(labelsize=7)
            ax.set_xlabel("x from the fitted centre (mm)", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=72)
    plt.close(fig)


def markdown(presses, comp, folds: int, timings: dict) -> str:
    """The BENCHMARKS.md section: the three methods side by side, the targets, the speeds."""
    from bench.report import machine_line
    from tactile_deploy.calibration.shading.compare import METHOD_NAMES
    from tactile_deploy.calibration.shading.evaluate import markdown_table

    ours = comp.summaries["lut"]
    worst_radius = max(abs(r.radius_error) for r in comp.results["lut"])
    checks = [("shape error mean <= 20 um", ours.shape_mean_um <= 20.0,
               f"{ours.shape_mean_um:.1f} um"),
              ("shape error worst <= 40 um", ours.shape_worst_um <= 40.0,
               f"{ours.shape_worst_um:.1f} um"),
              ("fitted radius within 5 % for every press", worst_radius <= 0.05,
               f"worst {100 * worst_radius:.1f} %"),
              ("... in the edge half too", ours.radius_error_worst_edge <= 0.05,
               f"worst {100 * ours.radius_error_worst_edge:.1f} %")]
    base = timings["reference RGB table frame -> depth"][1]
    lines = [
        "## Marble shading model on real ball presses (`tactile-deploy bench shading`)",
        "",
        (f"{machine_line()}. Data: `../shared/data/real/fots_gelsight_ballpress` ({len(presses)} "
        f"presses of a 4.70 mm ball, 240 x 320 px, 19.58 px/mm). Grouped {folds}-fold "
        "cross-validation (press i in fold i mod k; same folds, labelled circles and evaluation "
        "for the three methods). Shape error: RMS residual to the sphere of the ball's radius "
        "(centre and offset free) inside 0.8 x the labelled contact radius; fitted radius: the "
        "same fit with the radius free; centre/edge: the halves nearest to / farthest from the "
        "image centre."),
        "",
        markdown_table({METHOD_NAMES[k]: v for k, v in comp.summaries.items()}),
        "",
        "| target (ours) | measured | met |",
        "|---|---:|---|",
        *[f"| {name} | {value} | {'yes' if ok else '**no**'} |" for name, ok, value in checks],
        "",
        "Cross-validation wall time (the methods in two processes): "
        + ", ".join(f"{METHOD_NAMES[k].split(' (')[0]} {v:.1f} s" for k, v in
                    comp.seconds.items()) + ".",
        "",
        ("| step (one 240 x 320 frame, one thread; medians) | wall | CPU | CPU vs the reference "
        "RGB table's frame -> depth |"),
        "|---|---:|---:|---:|",
    ]
    for k, (wall, cpu) in timings.items():
        unit = "s" if k.endswith("(s)") else "ms"
        ratio = "" if unit == "s" else f"{cpu / base:.2f} x"
        lines.append(f"| {k.replace(' (s)', '')} | {wall:.2f} {unit} | {cpu:.2f} {unit} | "
                     f"{ratio} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------- virtual presses
#: Wizard settings of the virtual-sensor comparison (24 presses; the FEM step at one nu, for
#: the rig's zero offset that calibrates the learned read-out's depth gain; 800 steps for the
#: fine-tuned read-out's row, an option: the wizard's default is 0).
VIRTUAL_WIZARD = {"description": "bench", "reference": {"n_frames": 6}, "camera": {"n_frames": 1},
                  "presses": {"n_presses": 24}, "shading": {"folds": 0, "ring_targets": "none"},
                  "fem": {"nu_grid": [0.48], "bootstrap": 0}, "readout_steps": 800,
                  "rig": {"approach_step_mm": 0.2, "approach_clearance_mm": 0.4}}
VIRTUAL_SENSOR = "gelslim2"
#: Floor of the oracle weights 1 / (gradient error^2 + floor^2), mm per mm (0.005-0.01 is best).
ORACLE_FLOOR_SLOPE = 0.005


def run_virtual_wizard(config, folder: Path) -> tuple[dict, object, object, object]:
    """The calibration wizard on ``virtual:VIRTUAL_SENSOR`` with the simulated rig, its work
    in ``folder`` (an existing ``work/presses.npz`` there is reused): ``(presses npz as a dict,
    camera mapping, rectified reference, reference frames)``."""
    import numpy as np
    from rich.console import Console

    from tactile_deploy.calibration.wizard.state import WorkFolder
    from tactile_deploy.calibration.wizard.work_data import load_camera, load_reference
    from tactile_deploy.calibration.wizard.ui import AutoUI
    from tactile_deploy.calibration.wizard.wizard import EXIT_OK, run_wizard

    folder.mkdir(parents=True, exist_ok=True)
    work = WorkFolder(folder / "work")
    if not work.path("presses.npz").is_file():
        code = run_wizard("bench", source=f"virtual:{VIRTUAL_SENSOR}", rig="simulated",
                          gauge=None, config=config, out=folder / "bench", work=work.folder,
                          ui=AutoUI(Console(quiet=True)))
        if code != EXIT_OK:
            raise SystemExit(f"the wizard failed on virtual:{VIRTUAL_SENSOR} (exit code {code})")
    with np.load(work.path("presses.npz")) as z:
        d = {k: z[k] for k in z.files}
    reference, reference_frames = load_reference(work)
    return d, load_camera(work), reference, reference_frames


def virtual_accuracy(small: bool = False) -> dict:
    """Depth errors (um, per press) of the variants on new virtual-sensor presses (module
    docstring), and the wizard's settings."""
    import tempfile
    from dataclasses import replace

    import numpy as np

    from tactile_deploy.calibration.fem_fit.result import read_fem_result
    from tactile_deploy.calibration.shading.fit import fit_shading
    from tactile_deploy.calibration.shading.presses import PressSet
    from tactile_deploy.calibration.shading.readout_gain import readout_depth_gain
    from tactile_deploy.calibration.shading.virtual_check import (
        contact_region_errors,
        near_contact_errors,
        oracle_weighted_depths,
        virtual_ball_presses,
        virtual_shape_presses,
    )
    from tactile_deploy.calibration.wizard.config import shading_fit_config, wizard_config_from_dict
    from tactile_deploy.calibration.wizard.press_data import press_profiles
    from tactile_deploy.calibration.wizard.unit_readout import finetune_readout_on_presses
    from tactile_deploy.calibration.wizard.work_data import rectifier_for
    from tactile_deploy.imaging.camera_mapping import OutputGrid
    from tactile_deploy.imaging.learned_readout import LearnedReadout
    from tactile_deploy.imaging.poisson import poisson_solver
    from tactile_deploy.runtime.pipeline import GridResampler, ImagingPipeline
    from tactile_deploy.sensors import load_sensor

    doc = dict(VIRTUAL_WIZARD)
    if small:
        doc["presses"] = {"n_presses": 12}
    config = wizard_config_from_dict(doc, "bench_shading.VIRTUAL_WIZARD")
    with tempfile.TemporaryDirectory() as tmp:
        d, camera, reference, reference_frames = run_virtual_wizard(config, Path(tmp))
        material = read_fem_result(Path(tmp) / "work" / "fem.json")
    keep = d["keep"]
    pitch = camera.grid.pitch_x_mm
    fit_cfg = shading_fit_config(config.shading)
    before_cfg = replace(fit_cfg, bins=32, prior_model="image-mean")
    presses = PressSet(d["reference_r"], d["rectified"][keep],
                       [str(n) for n in d["names"][keep]], d["circles"][keep])
    profiles = press_profiles(config, d, camera, fit_cfg.far_factor)
    sensor = load_sensor(VIRTUAL_SENSOR)
    sensor.prepare()
    sets = {"bench": virtual_ball_presses(sensor, camera.grid, *((4, 4) if small else (8, 8)))}
    if not small:
        sets["second"] = virtual_ball_presses(sensor, camera.grid, 24, 8, seed=77)
    novel = sorted((SHARED / "indenters").glob("*.stl"))
    if not novel:
        raise SystemExit(f"no indenter STL files in {SHARED / 'indenters'}: the shapes check needs "
                         "../shared/data beside the checkout")
    shapes = virtual_shape_presses(sensor, camera.grid, novel, 8 if small else 16)
    out = {"presses": int(keep.sum()), "sets": sets, "errors": {}, "bins": fit_cfg.bins,
           "readout_steps": config.readout_steps,
           "shapes": shapes, "shape_errors": {},
           "camera": camera_position_error_mm(camera, sensor.optics.camera)}
    # the same presses rectified by the virtual camera's own mapping (same imaging grid)
    exact = sensor.optics.camera.model_copy(update={"grid": camera.grid})
    rectify = rectifier_for(exact)
    exact_presses = PressSet(rectify(reference), np.stack([rectify(f) for f in d["raw"][keep]]),
                             presses.names, presses.circles, profiles)
    readout = LearnedReadout(READOUT_PATH) if READOUT_PATH.is_file() else None
    variants = (("none", camera, presses, None, before_cfg, None),
                ("fem", camera, presses, profiles, before_cfg, None),
                ("fem, colour prior", camera, presses, profiles, fit_cfg, None),
                ("fem, colour prior, exact camera", exact, exact_presses, profiles, fit_cfg, None),
                ("learned read-out", camera, presses, profiles, fit_cfg, readout),
                ("learned read-out, fine-tuned", camera, presses, profiles, fit_cfg, readout))
    fitted = {}   # the learned read-out's pipeline takes the wizard's model, fitted once
    tuned_dir = tempfile.TemporaryDirectory()
    for key, cam, prs, prof, cfg, ro in variants:
        if key.startswith("learned read-out") and ro is None:
            continue
        prs.profiles = prof
        fit_key = (id(cam), id(prs), id(prof), cfg)
        if fit_key not in fitted:
            fitted[fit_key] = fit_shading(prs, config.presses.ball_radius_mm, pitch, cfg).model
        model = fitted[fit_key]
        if key == "learned read-out, fine-tuned":   # as the wizard's plugin step does
            ro, out["readout_finetune"] = finetune_readout_on_presses(
                config, cam, model, reference, reference_frames, ro, d, material,
                Path(tuned_dir.name) / "readout.onnx", VIRTUAL_SENSOR)
        plain = ImagingPipeline(cam, model, reference, None, "keep", readout=ro)
        noise = np.mean([plain.frame_to_depth(f) for f in reference_frames], axis=0)
        pipeline = ImagingPipeline(cam, model, reference, noise.astype(np.float32), "subtract",
                                   readout=ro)
        if ro is not None:   # the unit's depth gain, as the wizard calibrates it
            gain, _ = readout_depth_gain(pipeline, d["raw"][keep], d["tip_mm"][keep, 2],
                                         material.depth_offset_mm or 0.0)
            out["readout_gain" if ro is readout else "finetuned_gain"] = gain
            out["rig_offset_um"] = 1e3 * (material.depth_offset_mm or 0.0)
            pipeline = ImagingPipeline(cam, model, reference, gain * noise.astype(np.float32),
                                       "subtract", readout=ro, readout_gain=gain)
        out["errors"][key] = {
            name: near_contact_errors([pipeline.frame_to_depth(f) for f in new.frames], new)
            for name, new in sets.items()}
        if key in ("fem, colour prior", "learned read-out", "learned read-out, fine-tuned"):
            out["shape_errors"][key] = contact_region_errors(
                [pipeline.frame_to_depth(f) for f in shapes.frames], shapes.truths)
        if key == "fem, colour prior":
            wizard_pipeline = pipeline
    tuned_dir.cleanup()   # the fine-tuned read-out is loaded; its file is not needed any more
    # the most a per-pixel confidence weighting of the integration could gain
    out["errors"]["oracle weights"] = {
        name: near_contact_errors(oracle_weighted_depths(wizard_pipeline, new,
                                                         ORACLE_FLOOR_SLOPE), new)
        for name, new in sets.items()}
    # the true gradients on the imaging grid, integrated with the zero border
    to_imaging = GridResampler(OutputGrid(), camera.grid)
    to_model = GridResampler(camera.grid, OutputGrid())
    solver = poisson_solver((camera.grid.ny, camera.grid.nx), "dirichlet", (1.0, 1.0))
    out["errors"]["true gradients"] = {}
    for name, new in sets.items():
        ideal = []
        for t in new.truths:
            d_row, d_col = np.gradient(to_imaging(t).astype(np.float64))
            ideal.append(to_model(solver.integrate(d_col, d_row)))
        out["errors"]["true gradients"][name] = near_contact_errors(ideal, new)
    return out


def camera_position_error_mm(fitted, true) -> dict:
    """Distance (mm, sensing plane) between where two camera mappings sample the raw frame for
    each cell of ``fitted``'s imaging grid: mean, mean over the 8 cells next to the grid's edges,
    max."""
    import numpy as np

    from tactile_deploy.imaging.camera_mapping import build_remap

    a = np.asarray(build_remap(fitted), np.float64)
    b = np.asarray(build_remap(true.model_copy(update={"grid": fitted.grid})), np.float64)
    e = np.hypot(*(a - b)) * fitted.mm_per_px_x
    band = np.zeros(e.shape, bool)
    band[:8] = band[-8:] = True
    band[:, :8] = band[:, -8:] = True
    return {"mean": float(e.mean()), "edge_band": float(e[band].mean()), "max": float(e.max())}


VIRTUAL_NAMES = {
    "none": "no targets around the contact, image-mean fallback, 32 bins",
    "fem": "targets around the contact from the FEM of the pad, image-mean fallback, 32 bins",
    "fem, colour prior": "the same targets, colour-polynomial fallback, {bins} bins (the "
                         "wizard's shading model)",
    "fem, colour prior, exact camera": "the same, presses rectified by the virtual camera's own "
                                       "mapping instead of the fitted one",
    "oracle weights": "the wizard's default model, its gradients integrated with a weight per "
                      "pixel from their true error, 1 / (error^2 + 0.005^2) (an oracle: the most "
                      "a confidence-weighted integration could gain)",
    "learned read-out": "learned read-out of the GelSlim design (`exported/gelslim_readout.onnx`, "
                        "trained on balls and the indenter library's shapes pressed into virtual "
                        "units of gelslim1's design, never on this unit), "
                        "with the wizard's camera mapping, reference frame and depth gain "
                        "({readout_gain:.3f}, from its presses and the rig's zero offset "
                        "{rig_offset_um:.1f} um): the wizard's default with a `readout`, and "
                        "how the shipped plugins read frames",
    "learned read-out, fine-tuned": "the same read-out fine-tuned on this unit by the wizard "
                                    "(an option, `readout_steps` {readout_steps}: "
                                    "{readout_finetune}), "
                                    "depth gain {finetuned_gain:.3f}",
    "true gradients": "reference: the true gradients integrated (zero border)"}
#: The learned read-out of the virtual sensor's design (training/shading_net).
READOUT_PATH = Path(__file__).resolve().parent.parent / "exported" / "gelslim_readout.onnx"
VIRTUAL_SETS = {"bench": "new presses, seed 2024", "second": "second set, seed 77"}


#: Variants compared on other shapes and against the target, and their names there.
SHAPE_ROW_NAMES = {"fem, colour prior": "the wizard's shading model",
                   "learned read-out": "the learned read-out",
                   "learned read-out, fine-tuned": "the learned read-out fine-tuned on the unit"}


def variant_name(key: str, res: dict) -> str:
    """A variant's row name in BENCHMARKS.md, with the run's settings filled in."""
    return VIRTUAL_NAMES[key].format(
        bins=res["bins"], readout_gain=res.get("readout_gain", 1.0),
        rig_offset_um=res.get("rig_offset_um", 0.0), finetuned_gain=res.get("finetuned_gain", 1.0),
        readout_steps=res.get("readout_steps", 0),
        readout_finetune=res.get("readout_finetune", "").split(" (")[0])


def target_verdict(errors: dict, sets: dict) -> str:
    """Each set's mean near-contact RMSE inside the view and near its edges against 20 um."""
    parts, inside_met, edge_met = [], [], []
    for name, new in sets.items():
        e = errors[name]["near"]
        inside, edge = e[~new.near_edge].mean(), e[new.near_edge].mean()
        parts.append(f"{VIRTUAL_SETS[name]}: {inside:.1f} um mean inside the view (worst "
                     f"{e[~new.near_edge].max():.1f}), {edge:.1f} um near its edges")
        inside_met.append(bool(inside <= 20.0))
        edge_met.append(bool(edge <= 20.0))

    def verdict(met):
        return ("met on every set" if all(met) else "**not met** on " + ", ".join(
            VIRTUAL_SETS[name] for name, ok in zip(sets, met) if not ok))
    return ("; ".join(parts) + f". Inside the view: {verdict(inside_met)}. Near its edges: "
            f"{verdict(edge_met)}.")


def virtual_markdown(res: dict) -> str:
    """The ``shading-virtual`` section of BENCHMARKS.md."""
    import numpy as np

    from bench.report import machine_line

    sets = res["sets"]
    counts = ", ".join(f"{VIRTUAL_SETS[k]}: {int((~v.near_edge).sum())} presses at least two "
                       f"contact radii inside the view and {int(v.near_edge.sum())} within "
                       "1.2-1.7 contact radii of its edges" for k, v in sets.items())
    lines = [
        "## Absolute depth on virtual-sensor ball presses (`tactile-deploy bench shading`)",
        "",
        (f"{machine_line()}. The calibration wizard on `virtual:{VIRTUAL_SENSOR}` with the "
        f"simulated rig ({res['presses']} presses of a 3 mm ball, 0.3-0.9 mm), the shading "
        "model fitted on its presses as stated, the runtime's imaging pipeline on new presses "
        f"(0.3-0.8 mm deep; {counts}) against the surface their frames were shaded from (model "
        "grid). RMSE within 1.5 contact radii (a = sqrt(2 R d)), peak: estimated minus true "
        "maximum depth, whole: the whole model grid; um."),
    ]
    for name, new in sets.items():
        inside, edge = ~new.near_edge, new.near_edge
        lines += [
            "", f"{VIRTUAL_SETS[name].capitalize()}:", "",
            ("| shading model | inside: RMSE near, mean | worst | mean abs peak | whole-frame mean "
            "| near the edges: RMSE near, mean | worst | mean abs peak |"),
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for key, per_set in res["errors"].items():
            e = per_set[name]
            lines.append(
                f"| {variant_name(key, res)} | "
                f"{e['near'][inside].mean():.1f} | "
                f"{e['near'][inside].max():.1f} | {np.abs(e['peak'][inside]).mean():.0f} | "
                f"{e['whole'][inside].mean():.1f} | {e['near'][edge].mean():.1f} | "
                f"{e['near'][edge].max():.1f} | {np.abs(e['peak'][edge]).mean():.0f} |")
    shapes = res["shapes"]
    lines += ["", (f"Other shapes: {len(shapes.names)} presses of the shared indenter meshes "
                   f"(`../shared/data/indenters`: {', '.join(sorted(set(shapes.names)))}; shapes "
                   "neither the shading calibration nor the read-out's training saw; any rotation, "
                   "0.3-0.8 mm deep, centres 3 mm inside the view, seed 99) against the true "
                   "surface: RMSE where the true depth exceeds 10 um, grown by 4 cells (the "
                   "contact and its rim), um:"), "",
              "| read-out | contact region RMSE, mean | worst | mean abs peak | whole-frame mean |",
              "|---|---:|---:|---:|---:|"]
    for key, e in res["shape_errors"].items():
        label = SHAPE_ROW_NAMES[key]
        lines.append(f"| {label} | {np.nanmean(e['region']):.1f} | {np.nanmax(e['region']):.1f} | "
                     f"{np.abs(e['peak']).mean():.0f} | {e['whole'].mean():.1f} |")
    cam = res["camera"]
    lines += ["", (f"The fitted camera mapping samples the frame {cam['mean']:.2f} mm from where the "
              f"virtual camera's does on average over the imaging grid, {cam['edge_band']:.2f} mm "
              f"in the band of 8 cells along its edges, {cam['max']:.2f} mm at most.")]
    for key, what in SHAPE_ROW_NAMES.items():
        if key in res["errors"]:
            lines += ["", f"Target: absolute depth RMSE <= 20 um on virtual-sensor presses "
                      f"(within 1.5 contact radii), {what}: " + target_verdict(res["errors"][key], sets)]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--small", action="store_true", help="3 folds, short MLP training "
                        "(nothing written to BENCHMARKS.md)")
    parser.add_argument("--figure", type=Path, help="write the held-out figure (PNG) here")
    parser.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    parser.add_argument("--only", choices=("real", "virtual"), help="run one part")
    args = parser.parse_args(argv)

    if args.only != "real":
        text = virtual_markdown(virtual_accuracy(args.small))
        print(text)
        if not args.no_write and not args.small:
            from bench.report import write_section

            write_section("shading-virtual", text)
            print("\nwrote the shading-virtual section of BENCHMARKS.md\n")
        if args.only == "virtual":
            return
    presses = load()
    folds, steps = (3, 200) if args.small else (7, 800)
    comp = accuracy(presses, folds, steps)
    timings = speed(presses, 10 if args.small else 50)
    text = markdown(presses, comp, folds, timings)
    print(text)
    if not args.no_write and not args.small:
        from bench.report import write_section

        write_section("shading", text)
        print("\nwrote the shading section of BENCHMARKS.md")
    if args.figure:
        figure(presses, args.figure, mlp_steps=steps)
        print(f"\nwrote {args.figure}")


if __name__ == "__main__":
    main()
