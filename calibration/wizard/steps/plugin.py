"""Step 6, plugin: the plugin folder (validated by the runtime's loader) with its calibration
report, written atomically."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from tactile_deploy.calibration.shading.readout_finetune import FinetuneUnavailable
from tactile_deploy.calibration.wizard.context import Context, Outcome, StepError
from tactile_deploy.calibration.wizard.figures import plugin_figure
from tactile_deploy.calibration.wizard.report import write_report
from tactile_deploy.calibration.wizard.unit_readout import finetune_readout_on_presses, readout_gain
from tactile_deploy.calibration.wizard.work_data import (load_camera, load_fitted_material, load_npz,
                                                         load_reference, write_png)
from tactile_deploy.atomic import replace_folder
from tactile_deploy.imaging.learned_readout import LearnedReadout, ReadoutError
from tactile_deploy.imaging.shading import load_shading
from tactile_deploy.pad.topology import MeshTopology
from tactile_deploy.runtime.pipeline import ImagingPipeline
from tactile_deploy.runtime.plugins import SensorPlugin, validate_plugin, write_plugin
from tactile_deploy.runtime.sources.video import write_video
from tactile_deploy.shipped import model_path


def default_model() -> Path:
    """The shipped family model (``gelslim_mesh.onnx``)."""
    return model_path("gelslim_mesh.onnx")


def step_plugin(ctx: Context) -> Outcome:
    """Write the plugin folder (validated by the runtime's loader) with its report, atomically:
    everything goes to a hidden folder beside the target, which is renamed into place last."""

    out = Path(ctx.out)
    ours = ctx.state.plugin_written == str(out.resolve())
    if out.exists() and not (ctx.overwrite or ours):
        raise StepError(f"{out} exists: pass --overwrite to replace it, or choose another --out")
    if not out.parent.is_dir():
        raise StepError(f"--out: folder {out.parent} does not exist")
    model = Path(ctx.model_path or ctx.config.model or default_model())
    if not model.is_file():
        raise StepError(f"the family model {model} does not exist: pass --model PATH (an ONNX "
                        "model exported by `python -m tactile_deploy.training export`)")
    tmp = (out.parent / f".{out.name}.partial-{os.getpid()}").resolve()
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        manifest, notes = _build_plugin(ctx, tmp, model)
        report = validate_plugin(tmp)
        if not report.ok:
            raise StepError("the written plugin does not validate:\n  "
                            + "\n  ".join(report.problems))
        plugin = SensorPlugin.load(tmp)
        pipeline = ImagingPipeline.from_plugin(plugin)
        d = load_npz(ctx.work, "presses.npz")
        i = int(np.argmax(d["planned_mm"][:, 2])) if len(d["planned_mm"]) else 0
        depth = pipeline.frame_to_depth(d["raw"][i])
        fig = plugin_figure(ctx.work.figures / "plugin.png", d["raw"][i], depth,
                            manifest.depth_grid)
        size_mb = sum(p.stat().st_size for p in tmp.rglob("*") if p.is_file()) / 1e6
        metrics = {"plugin": str(out), "checks passed": len(report.checked),
                   "size (MB)": size_mb,
                   "deepest press, plugin depth max (mm)": float(depth.max())}
        write_report(ctx, tmp / "calibration", {"plugin": metrics}, [fig])
        replace_folder(tmp, out)
        ctx.state.plugin_written = str(out.resolve())
        ctx.work.save(ctx.state)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    notes.append(f"report: {out / 'calibration' / 'report.html'}")
    notes.append(f"use it: tactile-deploy run --sensor {out}")
    return Outcome(metrics, [fig], notes)


def _build_plugin(ctx: Context, folder: Path, model: Path):
    """Files and manifest of the plugin in ``folder``; returns (manifest, notes)."""

    cfg = ctx.config
    camera = load_camera(ctx.work)
    ref, ref_frames = load_reference(ctx.work)
    shading = load_shading(ctx.work.path("shading.npz"))
    shutil.copyfile(ctx.work.path("shading.npz"), folder / "shading.npz")
    write_png(folder / "reference.png", ref)
    d = load_npz(ctx.work, "presses.npz")
    material = load_fitted_material(ctx.work)
    readout, tune_note = None, None
    if cfg.readout is not None:

        try:
            readout = LearnedReadout(cfg.readout)
        except ReadoutError as e:
            raise StepError(f"config field 'readout': {e}") from None
        if cfg.readout_steps > 0:
            readout, tune_note = _finetune_readout(ctx, camera, shading, ref, ref_frames,
                                                   readout, d, material, folder)
    plain = ImagingPipeline(camera, shading, ref, None, "keep", readout=readout)
    noise = np.mean([plain.frame_to_depth(f) for f in ref_frames], axis=0).astype(np.float32)
    gain, gain_note = 1.0, None
    if readout is not None:
        gain, gain_note = readout_gain(camera, shading, ref, noise, readout, d, material)
        if tune_note is not None:
            gain_note = f"{gain_note}; {tune_note}"
        noise = noise * np.float32(gain)
    np.save(folder / "noise_reference.npy", noise)
    demo = np.concatenate([ref_frames[:4], d["raw"][d["keep"]]])
    write_video(folder / "demo.avi", demo, fps=10.0, fourcc="MJPG")
    topo = MeshTopology.from_pad(cfg.family)
    topo.save(folder / "topology.npz")
    if cfg.copy_model:
        shutil.copyfile(model, folder / model.name)
        model = folder / model.name
    steps = ctx.state.steps
    prov = {"made_by": "tactile-deploy calibrate (the calibration wizard)",
            "date": ctx.state.started[:10], "source": ctx.state.source,
            "rig": ctx.state.rig or "none (hand presses)",
            "report": "calibration/report.html"}
    for name in ("camera", "shading", "fem"):
        if name in steps:
            prov[f"{name}_figures"] = "; ".join(
                f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                for k, v in steps[name].metrics.items())
    fields = {
        "name": ctx.sensor,
        "description": cfg.description or f"{ctx.sensor}, calibrated from {ctx.state.source}",
        "family": {"name": cfg.family, "pad": cfg.family, "pad_version": 1,
                   "mesh_hash": topo.mesh_hash},
        "camera": json.loads(camera.model_dump_json()),
        "material": {"E_mpa": material.E_mpa, "nu": material.nu, "source": material.source},
        "default_source": _default_source(ctx),
        "noise_handling": "subtract",
        "provenance": prov,
    }
    if readout is not None:
        fields["readout_depth_gain"] = gain
        prov["readout"] = gain_note
    files = {"model": model, "shading": folder / "shading.npz",
             "reference_frame": folder / "reference.png",
             "noise_reference": folder / "noise_reference.npy", "demo_clip": folder / "demo.avi",
             "topology": folder / "topology.npz"}
    if readout is not None:
        files["readout"] = readout.path.resolve()
    manifest = write_plugin(folder, fields, files)
    return manifest, [f"model: {'copied into the plugin' if cfg.copy_model else model}"]


def _finetune_readout(ctx: Context, camera, shading, ref, ref_frames, readout, d, material,
                      folder: Path):
    """:func:`finetune_readout_on_presses` in the plugin step, its progress on the UI."""
    ctx.ui.say(f"fine-tuning the learned read-out on {int(d['keep'].sum())} presses "
               f"({ctx.config.readout_steps} steps)")

    def log(step, steps, loss, seconds):
        ctx.ui.say(f"  step {step}/{steps}: loss {loss:.3g} ({seconds:.0f} s)")

    try:
        return finetune_readout_on_presses(ctx.config, camera, shading, ref, ref_frames, readout,
                                           d, material, folder / "readout.onnx", ctx.sensor, log)
    except FinetuneUnavailable as e:
        raise StepError(str(e)) from None


def _default_source(ctx: Context) -> dict:
    src = getattr(ctx.station, "source_config", None)
    if src is not None and src.kind == "camera":
        return src.model_dump()
    sensor = getattr(getattr(ctx.station, "sensor", None), "name", None)
    if sensor is not None:
        return {"kind": "virtual", "sensor": sensor}
    return {"kind": "demo"}
