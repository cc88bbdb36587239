"""A recording of ball presses -> a sensor plugin, in one call (no prompts).

Data flow of :func:`calibrate_recording`::

    --presses DIR (+ --reference, --annotations)   load.load_recording: colour frames, the
                                                    no-contact frame checked or picked
    frames, scale, pad family                       checks.view_mapping: the frames on the
                                                    family's sensing area (camera mapping)
    circles: annotated (axes checked) or detected   checks.check_annotation_axes / detection
    ball radius vs circles                          checks.check_ball_radius
    frames rectified onto the imaging grid          (the runtime's own rectifier)
    shading model fitted (calibrate shading's fit)  tactile_deploy.calibration.shading.fit.fit_shading
    with --readout: the read-out's design checked   readout.load_family_readout, readout.measurable
    against the pad, the grid made its own
    (model-grid cells); it reads the depth
    held-out presses (k-fold)                       tactile_deploy.calibration.shading.evaluate.cross_validate
    plugin folder assembled beside the target, checked by the runtime's loader, renamed into
    place (an existing plugin only with overwrite)

The plugin has no learned mesh model: its meshes come from the pad family's physics lift
(``tactile-deploy run`` says so). With ``readout`` its depth comes from the learned read-out of
the family's design (copied into the plugin), else from the fitted shading model. Its material
is the family's prior (E 0.3 MPa, nu 0.48): without force measurements E is not identifiable;
forces scale with it.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tactile_deploy.calibration.recording.checks import (
    check_annotation_axes,
    check_ball_radius,
    view_edge_extension,
    view_mapping,
)
from tactile_deploy.calibration.recording.errors import PlausibilityError
from tactile_deploy.calibration.recording.load import Recording, load_recording
from tactile_deploy.calibration.recording.readout import (
    MIN_REGION_CELLS,
    ReadoutDepth,
    load_family_readout,
    measurable,
)

#: Material used when no forces were recorded (E is then not identifiable).
PRIOR_E_MPA = 0.3
PRIOR_NU = 0.48
_NAME = r"^[a-z0-9][a-z0-9_\-]*$"


@dataclass
class RecordingCalibration:
    """What :func:`calibrate_recording` did: the plugin, its figures, notes and held-out results."""

    plugin: Path
    metrics: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    held_out: list = field(default_factory=list)


def _target_folder(sensor: str, out: str | os.PathLike | None,
                   plugins_dir: str | os.PathLike | None) -> Path:
    if out is not None and plugins_dir is not None:
        raise PlausibilityError("give either --out (the plugin folder) or --plugins-dir (the "
                                "folder that holds plugin folders), not both")
    if plugins_dir is not None:
        from tactile_deploy.runtime.plugin_dirs import check_plugins_dir

        folder = Path(plugins_dir).expanduser()
        if not folder.exists():  # a first plugin: make the folder of plugins (as mkdir -p)
            folder.mkdir(parents=True)
        return check_plugins_dir(folder) / sensor
    return Path(out) if out is not None else Path(sensor)


def _grid_circles(circles_raw: np.ndarray, camera, mm_per_px: float) -> np.ndarray:
    """Circles (column, row, radius) raw px -> imaging-grid cells (the radius scaled by the
    frames' mm per px over the grid's pitch: kept when the grid has the frames' scale)."""
    from tactile_deploy.imaging.camera_mapping import pixels_to_sensor_mm

    g = camera.grid
    xy = pixels_to_sensor_mm(circles_raw[:, :2], camera)
    col = (xy[:, 0] - g.x_min_mm) / g.pitch_x_mm - 0.5
    row = (g.y_max_mm - xy[:, 1]) / g.pitch_y_mm - 0.5
    return np.c_[col, row, circles_raw[:, 2] * mm_per_px / g.pitch_x_mm]


def _detect_all(rec: Recording) -> np.ndarray:
    from tactile_deploy.calibration.shading.circles import ContactNotFoundError, detect_contact_circle

    out = []
    for f, name in zip(rec.frames, rec.names):
        try:
            out.append(detect_contact_circle(f, rec.reference))
        except ContactNotFoundError as e:
            raise PlausibilityError(
                f"{rec.folder / name}: no contact circle found ({e}); give the circles with "
                "--annotations CSV (img_names,center_x,center_y,radius in px), or remove the "
                "frame") from None
    return np.asarray(out, np.float64)


def calibrate_recording(sensor: str, pad: str, presses: str | os.PathLike, *,
                        ball_radius_mm: float, reference: str | os.PathLike | None = None,
                        annotations: str | os.PathLike | None = None,
                        mm_per_px: float | None = None, out: str | os.PathLike | None = None,
                        plugins_dir: str | os.PathLike | None = None, overwrite: bool = False,
                        folds: int = 5, shallow_presses: bool = False,
                        readout: str | os.PathLike | None = None,
                        say: Callable[[str], None] = print) -> RecordingCalibration:
    """Calibrate a plugin from recorded ball presses (module docstring). ``readout``: a learned
    read-out (.onnx) of the pad family's design, used for depth instead of the fitted shading
    model (:mod:`.readout`). Raises
    :class:`~tactile_deploy.calibration.recording.errors.PlausibilityError`,
    :class:`~tactile_deploy.calibration.shading.presses.PressDataError` or
    :class:`~tactile_deploy.runtime.plugins.PluginError` naming what to fix."""
    from tactile_deploy.calibration.shading.evaluate import cross_validate
    from tactile_deploy.calibration.shading.fit import fit_shading
    from tactile_deploy.calibration.shading.presses import PressSet
    from tactile_deploy.imaging.shading import DepthFromShading
    from tactile_deploy.pad.family import get_family
    from tactile_deploy.runtime.pipeline import Rectifier, rectify_frame, resample_to_grid

    if not re.fullmatch(_NAME, sensor):
        raise PlausibilityError(f"--sensor {sensor!r}: a plugin name is lower case letters, "
                                "digits, '-' and '_', starting with a letter or digit")
    try:
        family = get_family(pad)
    except KeyError as e:
        raise PlausibilityError(f"--pad {pad!r}: {e}") from None
    target = _target_folder(sensor, out, plugins_dir)
    if target.exists() and not overwrite:
        raise PlausibilityError(f"{target} exists: pass --overwrite to replace it, or choose "
                                "another --sensor name or folder")
    if not target.parent.is_dir():
        raise PlausibilityError(f"cannot write the plugin to {target}: folder {target.parent} "
                                "does not exist")
    if mm_per_px is not None and not (math.isfinite(mm_per_px) and mm_per_px > 0):
        raise PlausibilityError(f"--mm-per-px must be a number > 0 (mm per pixel), got {mm_per_px}")
    if folds != 0 and folds < 2:
        raise PlausibilityError(f"--folds must be 0 (no held-out check) or at least 2, got {folds}")
    learned = load_family_readout(readout, family.name)[0] if readout is not None else None

    rec = load_recording(presses, reference, annotations)
    h, w = rec.shape
    notes = []
    if rec.reference_picked:
        notes.append(f"no-contact frame: {rec.reference_path.name} (picked: the smoothest frame "
                     "of the recording)")
    scale_given = mm_per_px is not None
    if mm_per_px is None:
        area = family.sensing_area
        mm_per_px = max(area.width_mm, area.length_mm) / max(w, h)
        notes.append(f"no --mm-per-px: assumed {mm_per_px:.5f} mm per px (the frame's long side "
                     f"spans the {family.name} sensing area's long side); measure it for accuracy")
    camera, turns, view_notes = view_mapping(w, h, mm_per_px, family, scale_given)
    notes += view_notes
    if rec.circles is not None:
        from tactile_deploy.calibration.shading.circles import ContactNotFoundError, detect_contact_circle

        detected = {}
        for i in np.linspace(0, len(rec.frames) - 1, min(8, len(rec.frames))).astype(int):
            try:
                detected[int(i)] = detect_contact_circle(rec.frames[i], rec.reference)
            except ContactNotFoundError:
                pass
        check_annotation_axes(rec.circles, (h, w), rec.names, detected, str(annotations))
        circles_raw = rec.circles
    else:
        circles_raw = _detect_all(rec)
        notes.append(f"contact circles detected in {len(circles_raw)} frames (no --annotations)")
    figures = check_ball_radius(circles_raw, mm_per_px, ball_radius_mm, rec.names, scale_given,
                                shallow_presses)
    if shallow_presses and figures["largest contact radius / ball radius"] < 0.55:
        notes.append("--shallow-presses: the contact circles stay within "
                     f"{figures['largest contact radius / ball radius']:.2f} of the ball's "
                     "radius; depth of steeper contacts than these presses will be read too flat")

    if learned is not None:   # a read-out reads the grid it was trained on: model-grid cells
        from tactile_deploy.imaging.imaging_grid import readout_grid, with_grid

        camera = with_grid(camera, readout_grid(camera))
        notes.append(f"imaging grid: {camera.grid.nx} x {camera.grid.ny} cells of "
                     f"{camera.grid.pitch_x_mm:.4f} mm (the learned read-out's cells)")
        rectifier = Rectifier(camera)    # as the runtime's pipeline rectifies
    else:
        rectifier = Rectifier(camera, supersample=1)
    pitch_mm = camera.grid.pitch_x_mm

    def rect(frame):
        return resample_to_grid(rectify_frame(frame, rectifier), rectifier)

    ref_g = rect(rec.reference)
    press_set = PressSet(ref_g, np.stack([rect(f) for f in rec.frames]), list(rec.names),
                         _grid_circles(circles_raw, camera, mm_per_px))
    say(f"fitting the shading model on {len(press_set)} presses "
        f"({press_set.shape[1]} x {press_set.shape[0]} cells imaging grid, {pitch_mm:.5f} mm per cell)")
    fit = fit_shading(press_set, ball_radius_mm, pitch_mm)
    metrics = {"presses": len(press_set), "mm per px": mm_per_px,
               "in-sample sphere residual (um)": fit.model.header.fit_metrics[
                   "in_sample_sphere_rms_um"], **figures}
    if learned is not None:
        keep = measurable(press_set)
        if not keep.all():
            notes.append(f"{int((~keep).sum())} of {len(keep)} presses cover fewer than "
                         f"{MIN_REGION_CELLS} cells of the read-out's grid within 0.8 contact radii "
                         "(small or cut by the view's edge): left out of the held-out check")
        if keep.sum() < 2:
            raise PlausibilityError(
                f"only {int(keep.sum())} of {len(keep)} presses cover {MIN_REGION_CELLS} cells of the "
                f"learned read-out's grid ({pitch_mm:.3f} mm) within 0.8 contact radii: record "
                "deeper presses away from the view's edges, or leave --readout out")
        press_set = press_set.subset(keep)
        reader = ReadoutDepth(learned, ref_g, camera.grid)
        metrics["depth from"] = f"learned read-out {Path(readout).name}"

        def fitter(train):    # the read-out is not fitted: every press is held out
            return reader
    else:
        metrics["depth from"] = "the fitted shading model"

        def fitter(train):
            return DepthFromShading(fit_shading(train, ball_radius_mm, pitch_mm).model,
                                    train.reference)
    held_out = []
    if folds:
        folds = min(folds, len(press_set))
        say(f"checking on held-out presses ({folds}-fold)")
        held_out = cross_validate(press_set, fitter, ball_radius_mm, pitch_mm, folds)
        shape = np.array([r.shape_um for r in held_out])
        rad = np.array([r.radius_error for r in held_out])
        metrics.update({"held-out shape error mean (um)": float(shape.mean()),
                        "held-out shape error worst (um)": float(shape.max()),
                        "held-out fitted radius error worst (%)": float(100 * np.abs(rad).max()),
                        "held-out fitted radius error mean (%)": float(100 * rad.mean())})
    folder = _write_plugin(sensor, family, target, overwrite, rec, camera, fit, metrics,
                           notes, mm_per_px, ball_radius_mm, turns, learned)
    return RecordingCalibration(folder, metrics, notes, held_out)


def _write_plugin(sensor, family, target: Path, overwrite: bool, rec: Recording, camera, fit,
                  metrics: dict, notes: list[str], mm_per_px: float, ball_radius_mm: float,
                  turns: int, readout=None) -> Path:
    """Assemble the plugin beside ``target``, check it with the runtime's loader, rename it.
    ``readout``: a LearnedReadout, copied into the plugin as ``readout.onnx``."""
    import cv2

    from tactile_deploy.atomic import replace_folder
    from tactile_deploy.imaging.shading import save_shading
    from tactile_deploy.pad.asset import load_pad
    from tactile_deploy.runtime.drift import reference_range
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins import (
        PluginError,
        SensorPlugin,
        validate_plugin,
        write_plugin,
    )
    from tactile_deploy.runtime.predictor import MeshTopology
    from tactile_deploy.runtime.sources.npz import save_clip

    target = target.absolute()
    staging = target.parent / f".{target.name}.partial-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    try:
        save_shading(fit.model, staging / "shading.npz")
        if not cv2.imwrite(str(staging / "reference.png"),
                           np.ascontiguousarray(rec.reference[..., ::-1])):
            raise OSError(f"could not write {staging / 'reference.png'}")
        # the no-contact depth: the other no-contact frames of the recording through the pipeline
        # (none: zero - one frame has no fixed-pattern noise of its own to show)
        if readout is not None:
            shutil.copyfile(readout.path, staging / "readout.onnx")
        extension_mm, extension_notes = view_edge_extension(camera.grid, family.depth_grid)
        notes += extension_notes
        plain = ImagingPipeline(camera, fit.model, rec.reference, None, "keep",
                                depth_grid=family.depth_grid,
                                readout=readout, view_edge_extension_mm=extension_mm)
        if len(rec.no_contact):
            noise = np.mean([plain.frame_to_depth(f) for f in rec.no_contact], axis=0)
        else:
            noise = np.zeros((family.depth_grid.ny, family.depth_grid.nx))
        np.save(staging / "noise_reference.npy", noise.astype(np.float32))
        clip = np.concatenate([rec.reference[None], rec.frames])
        save_clip(staging / "demo.npz", clip, np.arange(len(clip), dtype=np.int64) * 100_000_000,
                  {"sensor": sensor, "made_by": "tactile-deploy calibrate --presses (the "
                   "recording's no-contact frame and presses, 10 fps)"})
        mesh = load_pad(family.name)
        topo = MeshTopology.from_pad(family.name)
        topo.save(staging / "topology.npz")
        prov = {"made_by": "tactile-deploy calibrate --presses (one command, no prompts)",
                "date": _dt.date.today().isoformat(),
                "presses": str(rec.folder.resolve()),
                "reference_frame": str(rec.reference_path.resolve()),
                "ball_radius_mm": f"{ball_radius_mm:g}",
                "mm_per_px": f"{mm_per_px:.6g}",
                "image_quarter_turns": str(turns),
                "figures": "; ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                     for k, v in metrics.items()),
                "notes": " | ".join(notes)}
        all_frames = [rec.reference, *rec.frames, *rec.no_contact]
        fields = {
            "name": sensor,
            "description": f"{sensor}: a {family.name} sensor calibrated from the ball presses "
                           f"of {rec.folder.name}",
            "family": {"name": family.name, "pad": family.name, "pad_version": 1,
                       "mesh_hash": mesh.content_hash},
            "camera": json.loads(camera.model_dump_json()),
            "depth_grid": family.depth_grid.model_dump(),
            "view_edge_extension_mm": round(extension_mm, 6),
            "material": {"E_mpa": PRIOR_E_MPA, "nu": PRIOR_NU,
                         "source": "prior (no forces were recorded, so E is not calibrated: "
                                   "forces scale with it; nu fixed at 0.48)"},
            "default_source": {"kind": "demo"},
            "noise_handling": "subtract",
            "provenance": prov,
            "reference_range": reference_range(all_frames, rec.reference).model_dump(),
        }
        files = {"shading": staging / "shading.npz", "reference_frame": staging / "reference.png",
                 "noise_reference": staging / "noise_reference.npy",
                 "demo_clip": staging / "demo.npz", "topology": staging / "topology.npz"}
        if readout is not None:
            files["readout"] = staging / "readout.onnx"
            prov["readout"] = (f"{readout.path.name} (design {readout.metadata.get('design')}), "
                               "depth gain 1 (no intrusions recorded)")
        write_plugin(staging, fields, files)
        report = validate_plugin(staging)
        if not report.ok:
            raise PluginError("the written plugin does not validate:\n  "
                              + "\n  ".join(report.problems))
        pipeline = ImagingPipeline.from_plugin(SensorPlugin.load(staging))
        depth = pipeline.frame_to_depth(rec.frames[int(np.argmax(fit.circles[:, 2]))])
        metrics["deepest press, plugin depth max (mm)"] = float(depth.max())
        replace_folder(staging, target)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return target
