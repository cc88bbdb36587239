"""Adapt a sensor plugin's model to the sensor, from its unlabelled frames.

Data flow of :func:`adapt_plugin` (``tactile-deploy adapt``)::

    frames (a folder, a clip, a camera, the plugin's demo) --plugin's imaging pipeline--> depth (N, 128, 128) mm
      -> split into adaptation / held-out frames (blocks of consecutive frames; at least 5 held out)
      -> targets: VAE(depth) (filter.onnx; or the depth itself without the filter)
      -> step program with the active model's weights (adapted version, else the family model)
      -> Adam steps (progress, live loss)
      -> adapted ONNX (fp32 graph with new initializers; int8 like the family model), parity with
         the step program
      -> held-out label-free RMSE of the models as ``run`` uses them: the start model, the active
         one, the adapted model.onnx
      -> improved (the network's own, fp32, and the written model's beats both)? before/after
         figure, report
         -> plugin version adapted/v<n>, made active in adapted/history.json (atomic; plugin.json untouched;
            tactile_deploy.runtime.plugins.versions)

The label-free RMSE (mm) is the paper's metric: RMS over the held-out maps and the pixels the
sensor sees of rendered mesh minus target. For an ONNX model its meshes are rendered by the
simulator's depth camera (the step's renderer gives the same images: the fp32 twin's figure
equals the step's to ~1e-8 mm).
"""

from __future__ import annotations

import datetime as _dt
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from tactile_deploy.adapt.card import CardError
from tactile_deploy.adapt.report import REPORT_NAME, AdaptationReport
from tactile_deploy.adapt.step import (
    AdaptSettings,
    Evaluation,
    History,
    StepProgram,
    adapt,
    adaptation_target,
    evaluate,
)
from tactile_deploy.adapt.weights import (
    adaptation_metadata,
    read_adapted_weights,
    write_adapted_onnx,
)
from tactile_deploy.atomic import atomic_path, write_json
from tactile_deploy.camera.depth import DepthCamera
from tactile_deploy.onnx_runtime.metadata import write_metadata
from tactile_deploy.onnx_runtime.quantize import quantize_int8
from tactile_deploy.onnx_runtime.session import make_session
from tactile_deploy.pad.asset import load_pad
from tactile_deploy.runtime.pipeline import FrameError, GridResampler, ImagingPipeline
from tactile_deploy.runtime.plugins import MODEL_GRID
from tactile_deploy.runtime.plugins.versions import (
    ADAPTED_DIR,
    add_version,
    check_writable,
    load_history,
    staging_folder,
)
from tactile_deploy.runtime.run import RunOptions
from tactile_deploy.runtime.sources.factory import make_source

#: Parity the adapted fp32 ONNX model must reach against the step program (mm).
PARITY_TOLERANCE_MM = 1e-4
#: Fewest held-out frames the adaptation is judged on.
MIN_HELD_OUT = 5


@dataclass
class AdaptOptions:
    """steps, batch_size, lr: Adam; held_out: share of frames kept aside (in blocks of ``block``
    consecutive frames); use_filter: target VAE(I) (True) or I (False), None: the design's default
    (:func:`tactile_deploy.adapt.step.filters_by_default`: I for the surface-anchored graphs); start: "active"
    (the plugin's active adapted model, else the family's) or "family"; write: create a version
    when the held-out RMSE improved."""

    steps: int = 200
    batch_size: int = 16
    lr: float = 1e-4
    held_out: float = 0.2
    block: int = 10
    use_filter: bool | None = None
    device: str = "cpu"
    seed: int = 0
    start: str = "active"
    write: bool = True


@dataclass
class AdaptResult:
    """before, after: held-out figures of the start model and of the adapted model as ``run``
    uses them (model.onnx: int8 when the family model is); before_fp32, after_fp32: the same of
    the network (the step program); active: the active model's when it is not the start model;
    verdict: why a version was or was not written; report: what ``report.json`` of the version
    holds (also when none was written)."""

    before: Evaluation
    after: Evaluation
    history: History
    n_train: int
    n_held_out: int
    improved: bool
    version: object | None = None
    report: AdaptationReport | None = None
    figure: Path | None = None
    before_fp32: Evaluation | None = None
    after_fp32: Evaluation | None = None
    active: Evaluation | None = None
    verdict: str = ""


def default_step_folder(plugin) -> Path:
    """``<family model stem>_adapt`` beside the plugin's family model."""
    model = plugin.path_of("model")
    return model.with_name(model.stem + "_adapt")


def view_weight(plugin) -> np.ndarray:
    """(128, 128) float32 in [0, 1]: share of each model-grid cell the plugin's camera sees
    (its imaging grid), times the pad's disc."""

    fam = plugin.manifest.family
    pad = load_pad(fam.pad, fam.pad_version)
    disc = DepthCamera().render(pad, pad.vertices).mask.astype(np.float32)
    grid = plugin.manifest.camera.grid
    if grid == MODEL_GRID:
        return disc
    cover = GridResampler(grid, MODEL_GRID)(np.ones((grid.ny, grid.nx), np.float32))
    return (np.clip(cover, 0.0, 1.0) * disc).astype(np.float32)


def collect_depths(plugin, config, from_manifest: bool = False, max_frames: int | None = None,
                   log: Callable[[str], None] = print, max_refused: int | None = None) -> tuple[np.ndarray, dict]:
    """Depth maps (N, 128, 128) float32 mm of the frames of source ``config`` through the
    plugin's imaging pipeline; frames the pipeline refuses are counted and skipped, and
    ``max_refused`` in a row (default: ``tactile-deploy run``'s ``max_bad_frames``) stop it."""

    max_refused = max_refused or RunOptions.max_bad_frames
    pipeline = ImagingPipeline.from_plugin(plugin)
    depths, refused, in_a_row = [], 0, 0
    with make_source(config, plugin, from_manifest=from_manifest) as src:
        if not getattr(src, "finite", True) and max_frames is None:
            raise ValueError(f"{src.name} is a live source: give --max-frames (how many frames to collect)")
        while max_frames is None or len(depths) < max_frames:
            frame = src.read()
            if frame is None:
                break
            try:
                depths.append(pipeline.frame_to_depth(frame.image))
                in_a_row = 0
            except FrameError as e:
                refused, in_a_row = refused + 1, in_a_row + 1
                if refused <= 3:
                    log(f"frame {frame.index} refused: {e}")
                if in_a_row >= max_refused:
                    raise ValueError(
                        f"{src.name}: {in_a_row} frames in a row were refused by the imaging pipeline of plugin "
                        f"{plugin.name!r} ({len(depths)} usable so far); the last, frame {frame.index}: {e}; check "
                        "that the source is this plugin's sensor (`tactile-deploy run` shows its frames)") from None
        name = src.name
    if not depths:
        raise ValueError(f"{name}: no usable frames")
    return np.stack(depths).astype(np.float32), {"source": name, "frames": len(depths), "refused": refused}


def split_blocks(n: int, held_out: float, block: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(adaptation, held-out) frame indices: blocks of ``block`` consecutive frames (neighbouring
    frames of a recording are near copies), a seeded ``held_out`` share of the blocks aside."""
    if n < 2:
        raise ValueError(f"need at least 2 frames to keep some aside, got {n}")
    blocks = np.arange(n) // max(1, block)
    ids = np.unique(blocks)
    if len(ids) < 2:  # too few frames for blocks: hold out single frames
        blocks, ids = np.arange(n), np.arange(n)
    k = min(max(1, int(round(held_out * len(ids)))), len(ids) - 1)
    aside = np.random.default_rng(seed).permutation(ids)[:k]
    is_held = np.isin(blocks, aside)
    return np.flatnonzero(~is_held), np.flatnonzero(is_held)


def check_held_out(n: int, n_held_out: int, held_out: float, block: int) -> None:
    """Refuse to judge an adaptation on fewer than :data:`MIN_HELD_OUT` held-out frames."""
    if n_held_out >= MIN_HELD_OUT:
        return
    need = max(2 * block, -(-(n + 1) // block) * block)  # whole blocks: each held-out block has ``block`` frames
    raise ValueError(f"only {n_held_out} of the {n} frames would be held out (--held-out {held_out:g}, blocks of "
                     f"{block} consecutive frames); the adaptation is judged on at least {MIN_HELD_OUT}: collect at "
                     f"least {need} frames (--max-frames {need}, or more images in --frames)")


def prepare_adaptation(plugin, options: AdaptOptions, step_folder: str | Path | None = None) -> StepProgram:
    """Every check that needs no frames, done before any are collected: the plugin's
    adapted/history.json and its active version, a writable plugin folder (when writing), the
    step (its card, files, the device) and that it belongs to the plugin's family model."""

    load_history(plugin)
    plugin.adapted_model_path()  # the active version: present and unchanged
    if options.write:
        check_writable(plugin)
    folder = Path(step_folder) if step_folder is not None else default_step_folder(plugin)
    if step_folder is None and not folder.is_dir():
        model = plugin.path_of("model")
        bundle = model.with_suffix(".pt")
        how = (f"export it from the model's bundle: `python -m tactile_deploy.training export-adapt --bundle "
               f"{bundle} --onnx {model}`" if bundle.is_file() else
               "export it from the training bundle the model was exported from: `python -m "
               f"tactile_deploy.training export-adapt --bundle MODEL.pt --onnx {model}`")
        raise CardError(f"the plugin's model {model.name} has no adaptation step ({folder} does not exist); "
                        f"{how}, or pass --step FOLDER")
    step = StepProgram.load(folder, options.device)
    step.check_family_model(plugin.verified_path("model"))
    return step


def evaluate_model(model_path: str | Path, pad, depth_mm: np.ndarray, target_mm: np.ndarray, weight: np.ndarray,
                   batch: int = 32) -> Evaluation:
    """Label-free figures of an ONNX model as ``run`` uses it (onnxruntime, CPU): its meshes of
    ``depth_mm`` (N, 128, 128) mm rendered by the depth camera, against ``target_mm`` with the
    step's weighting (``weight`` (128, 128)); rendered kept."""

    session = make_session(model_path, threads=1, providers="cpu")
    d = np.asarray(depth_mm, np.float32)[:, None]
    disp = np.concatenate([session.run(["displacement"], {"depth": d[i:i + batch]})[0] for i in range(0, len(d), batch)])
    cam, rest = DepthCamera(), pad.vertices[: pad.n_plane]
    rendered = np.stack([cam.render(pad, rest + u[: pad.n_plane]).depth_mm for u in disp])
    w = np.asarray(weight, np.float32)
    mse = (((rendered - target_mm) ** 2 * w).sum(axis=(1, 2)) / max(float(w.sum()), 1e-12)).astype(np.float64)
    return Evaluation(float(math.sqrt(mse.mean())), mse, disp, rendered, 0)


def adapt_plugin(plugin, depth_mm: np.ndarray, options: AdaptOptions, step_folder: str | Path | StepProgram | None = None,
                 progress: Callable[[int, float], None] | None = None, log: Callable[[str], None] = print,
                 source: dict | None = None) -> AdaptResult:
    """Adapt ``plugin``'s model on ``depth_mm`` (N, 128, 128) mm (module docstring);
    ``step_folder``: the step folder, or the step :func:`prepare_adaptation` loaded."""
    import shutil
    import tempfile

    t_start = time.perf_counter()
    step = step_folder if isinstance(step_folder, StepProgram) else prepare_adaptation(plugin, options, step_folder)
    card = step.card
    depth = np.asarray(depth_mm, np.float32)
    tr, ho = split_blocks(len(depth), options.held_out, options.block, options.seed)
    check_held_out(len(depth), len(ho), options.held_out, options.block)
    start_model, start_path = "family model", plugin.verified_path("model")
    active = plugin.adapted_model_path()
    if active is not None and options.start == "active":
        fp32 = active.with_name("model_fp32.onnx")
        step.load_weights(read_adapted_weights(card, fp32 if fp32.is_file() else active))
        start_model, start_path = f"adapted model {active.parent.name}", active
    weight = view_weight(plugin)
    fam = plugin.manifest.family
    pad = load_pad(fam.pad, fam.pad_version)
    target, use_filter = adaptation_target(step, depth, options.use_filter)
    log(f"{len(depth)} frames: {len(tr)} to adapt on, {len(ho)} held out; starting from the {start_model}; "
        f"target: {'VAE(depth)' if use_filter else 'depth (no filter)'}")
    before_fp32 = evaluate(step, depth[ho], target[ho], weight)
    settings = AdaptSettings(steps=options.steps, batch_size=options.batch_size, lr=options.lr, seed=options.seed)
    history = adapt(step, depth[tr], target[tr], weight, settings, progress)
    after_fp32 = evaluate(step, depth[ho], target[ho], weight, keep=("displacement",))
    report = {
        "plugin": plugin.name, "source": source or None, "start": start_model, "step": str(step.folder),
        "step_card": {"name": card.name, "sha256": card.files["step"].sha256, "torch": card.versions.get("torch")},
        "frames": {"adapt": int(len(tr)), "held_out": int(len(ho))},
        "settings": {"steps": options.steps, "batch_size": options.batch_size, "lr": options.lr,
                     "use_filter": use_filter, "device": options.device, "seed": options.seed},
        "heldout_rmse_before_fp32_mm": before_fp32.rmse_mm, "heldout_rmse_after_fp32_mm": after_fp32.rmse_mm,
        "train_loss_first_mm2": history.loss_mm2[0], "train_loss_last_mm2": history.loss_mm2[-1],
        "adapt_seconds": history.seconds, "steps_per_s": options.steps / max(history.seconds, 1e-9),
        "renderer_overflow": after_fp32.overflow + before_fp32.overflow,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }

    root = Path(plugin.folder) / ADAPTED_DIR
    made_root = options.write and not root.exists()
    if options.write:
        staging = staging_folder(plugin)
    else:  # measure the written model too, outside the plugin
        scratch = tempfile.TemporaryDirectory(prefix="tactile-deploy-adapt-")
        staging = Path(scratch.name)
    try:
        report.update(_write_models(step, staging, depth[tr], depth[ho], after_fp32.displacement_mm, report))
        before = evaluate_model(start_path, pad, depth[ho], target[ho], weight)
        after = evaluate_model(staging / "model.onnx", pad, depth[ho], target[ho], weight)
        active_eval = None
        if active is not None and active != start_path:
            active_eval = evaluate_model(active, pad, depth[ho], target[ho], weight)
        kind = "int8" if report["int8"] else "fp32"
        report.update({"heldout_rmse_model": f"model.onnx as run uses it ({kind})",
                       "heldout_rmse_before_mm": before.rmse_mm, "heldout_rmse_after_mm": after.rmse_mm})
        if active_eval is not None:
            report["heldout_rmse_active_mm"] = active_eval.rmse_mm
            report["active"] = f"adapted model {active.parent.name}"
        def um(e: Evaluation) -> str:
            return f"{e.rmse_mm * 1e3:.2f} um"

        if not after_fp32.rmse_mm < before_fp32.rmse_mm:
            verdict = (f"the adaptation did not lower the network's held-out error (fp32 twin {um(before_fp32)} -> "
                       f"{um(after_fp32)})")
        elif not after.rmse_mm < before.rmse_mm:
            verdict = (f"the adapted model.onnx ({kind}, {um(after)}) is not better than the {start_model} "
                       f"({um(before)}) on the held-out frames")
        elif active_eval is not None and not after.rmse_mm < active_eval.rmse_mm:
            verdict = (f"the adapted model.onnx ({um(after)}) is not better than the active "
                       f"{report['active']} ({um(active_eval)}) on the same held-out frames")
        else:
            verdict = "improved"
        improved = verdict == "improved"
        report["improved"], report["verdict"] = improved, verdict
        result = AdaptResult(before, after, history, len(tr), len(ho), improved,
                             before_fp32=before_fp32, after_fp32=after_fp32, active=active_eval, verdict=verdict)
        if not (improved and options.write):
            report["seconds"] = time.perf_counter() - t_start
            result.report = AdaptationReport.model_validate(report)
            return result

        meta = adaptation_metadata(card, {k: report[k] for k in (
            "heldout_rmse_before_mm", "heldout_rmse_after_mm", "heldout_rmse_before_fp32_mm",
            "heldout_rmse_after_fp32_mm", "frames", "settings", "created")})
        for name in ("model.onnx", "model_fp32.onnx"):
            if (staging / name).is_file():
                write_metadata(staging / name, meta)
        result.figure = staging / "adaptation.png"
        before_after_figure(depth[ho], target[ho], before.rendered_mm, after.rendered_mm, weight, result.figure,
                            before.rmse_mm, after.rmse_mm)
        report["seconds"] = time.perf_counter() - t_start
        result.report = AdaptationReport.model_validate(report)
        write_json(staging / REPORT_NAME, result.report.model_dump(mode="json", exclude_none=True))
        where = result.report.source.source if result.report.source is not None else "depth maps"
        summary = (f"{len(tr)} + {len(ho)} held-out frames of {where}, "
                   f"{options.steps} steps in {history.seconds:.0f} s on {options.device}")
        result.version = add_version(plugin, staging, {
            "created": report["created"], "heldout_rmse_before_mm": before.rmse_mm,
            "heldout_rmse_after_mm": after.rmse_mm, "summary": summary})
        result.figure = Path(plugin.folder) / result.version.model.rsplit("/", 1)[0] / "adaptation.png"
    finally:
        if not options.write:
            scratch.cleanup()
        elif staging.exists():
            shutil.rmtree(staging)
        if made_root and root.is_dir() and not any(root.iterdir()):
            root.rmdir()  # nothing written: no empty adapted/ either
    return result


def _write_models(step: StepProgram, folder: Path, depth_train: np.ndarray, depth_held: np.ndarray,
                  step_disp: np.ndarray, report: dict) -> dict:
    """Write model.onnx (and model_fp32.onnx when the family graph is int8) into ``folder``;
    check the fp32 graph against the step program's displacements on the held-out maps."""

    card = step.card
    fp32_src = card.path(step.folder, "fp32_model")
    meta = adaptation_metadata(card, {k: report[k] for k in ("heldout_rmse_before_fp32_mm", "heldout_rmse_after_fp32_mm",
                                                              "frames", "settings", "created")})
    int8 = bool(card.int8_nodes)
    fp32_path = folder / ("model_fp32.onnx" if int8 else "model.onnx")
    meta["variant"] = card.family_variant.replace("-int8", "") + "-adapted"
    write_adapted_onnx(card, fp32_src, step.weights(), fp32_path, meta)
    session = make_session(fp32_path, threads=1, providers="cpu")
    d = depth_held[:, None].astype(np.float32)
    onnx_disp = np.concatenate([session.run(["displacement"], {"depth": d[i:i + 32]})[0] for i in range(0, len(d), 32)])
    parity = float(np.abs(onnx_disp - step_disp).max())
    if not parity <= PARITY_TOLERANCE_MM:
        raise RuntimeError(f"the adapted ONNX model differs from the adapted step by {parity:.3g} mm (tolerance "
                           f"{PARITY_TOLERANCE_MM} mm); nothing was written to the plugin")
    out = {"parity_fp32_onnx_vs_step_max_abs_diff_mm": parity, "int8": int8}
    if int8:
        cal = depth_train[np.random.default_rng(0).permutation(len(depth_train))[:256]][:, None]
        quantize_int8(fp32_path, folder / "model.onnx", cal, card.int8_nodes)

        write_metadata(folder / "model.onnx", {"variant": card.family_variant + "-adapted"})
        q = make_session(folder / "model.onnx", threads=1, providers="cpu")
        q_disp = np.concatenate([q.run(["displacement"], {"depth": d[i:i + 32]})[0] for i in range(0, len(d), 32)])
        out["int8_vs_fp32_rms_diff_mm"] = float(np.sqrt(np.mean((q_disp - onnx_disp) ** 2)))
        out["int8_vs_fp32_max_abs_diff_mm"] = float(np.abs(q_disp - onnx_disp).max())
    out.update(_ood_shares(card.path(step.folder, "family_model"), folder / "model.onnx", d))
    return out


def _ood_shares(family: Path, adapted: Path, depth: np.ndarray) -> dict:
    """Share of the held-out maps above the model's ood_threshold, family vs adapted model (the
    adapted encoder feeds the same out-of-distribution decoder)."""

    out = {}
    for key, path in (("family", family), ("adapted", adapted)):
        sess = make_session(path, threads=1, providers="cpu")
        meta = sess.get_modelmeta().custom_metadata_map
        if "ood_threshold" not in meta:
            return {}
        ood = np.concatenate([sess.run(["ood_score"], {"depth": depth[i:i + 32]})[0] for i in range(0, len(depth), 32)])
        out[f"ood_share_above_threshold_{key}"] = float(np.mean(ood > float(meta["ood_threshold"])))
    return out


def before_after_figure(depth, target, before, after, weight, path: Path, rmse_before: float,
                        rmse_after: float, n: int = 4) -> Path:
    """Held-out maps (deepest ``n``): input depth, target, rendered mesh before and after, and
    the two errors inside the sensor's view (mm). Written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pick = np.argsort([-float((t * weight).max()) for t in target])[:n]
    cols = ["input depth I", "target", "rendered before", "rendered after", "error before", "error after"]
    fig, axes = plt.subplots(len(pick), len(cols), figsize=(2.3 * len(cols), 2.3 * len(pick) + 0.6), squeeze=False)
    inside = weight > 0.5
    for r, i in enumerate(pick):
        vmax = max(float(np.abs(target[i]).max()), 0.05)
        imgs = [depth[i], target[i], before[i], after[i], (before[i] - target[i]) * inside, (after[i] - target[i]) * inside]
        for c, img in enumerate(imgs):
            ax = axes[r, c]
            if c < 4:
                ax.imshow(img, cmap="viridis", vmin=-0.1 * vmax, vmax=vmax)
            else:
                ax.imshow(img, cmap="RdBu_r", vmin=-0.5 * vmax, vmax=0.5 * vmax)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=9)
    fig.suptitle(f"held-out label-free RMSE {rmse_before * 1e3:.1f} um -> {rmse_after * 1e3:.1f} um "
                 f"(colour: depth 0 to {vmax:.2f} mm of the last row; errors +-half of it)", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)
    return path


def summary_lines(result: AdaptResult) -> list[str]:
    """What ``tactile-deploy adapt`` prints of ``result`` (its report), one line each."""
    r = result.report
    kind = "int8" if r.int8 else "fp32"
    lines = [
        f"held-out label-free RMSE of model.onnx as `run` uses it ({kind}, {result.n_held_out} frames): "
        f"{result.before.rmse_mm * 1e3:.2f} um ({r.start}) -> {result.after.rmse_mm * 1e3:.2f} um "
        f"({100 * (result.after.rmse_mm / result.before.rmse_mm - 1):+.2f} %)",
    ]
    if result.active is not None:
        lines.append(f"active {r.active} on the same frames: {result.active.rmse_mm * 1e3:.2f} um")
    if result.before_fp32 is not None and result.after_fp32 is not None:
        lines.append(f"network (fp32 twin): {result.before_fp32.rmse_mm * 1e3:.2f} um -> "
                     f"{result.after_fp32.rmse_mm * 1e3:.2f} um"
                     + (f"; int8 vs fp32 mesh: RMS {r.int8_vs_fp32_rms_diff_mm * 1e3:.2f} um, worst "
                        f"{r.int8_vs_fp32_max_abs_diff_mm * 1e3:.1f} um" if r.int8 else ""))
    lines.append(f"adaptation loss: {math.sqrt(r.train_loss_first_mm2) * 1e3:.2f} -> "
                 f"{math.sqrt(r.train_loss_last_mm2) * 1e3:.2f} um RMS over {r.settings.steps} steps, "
                 f"{r.adapt_seconds:.1f} s ({r.steps_per_s:.2f} steps/s)")
    lines.append(f"adapted ONNX (fp32) vs step program: max {r.parity_fp32_onnx_vs_step_max_abs_diff_mm:.2e} mm")
    if r.ood_share_above_threshold_adapted is not None and r.ood_share_above_threshold_family is not None:
        lines.append(f"held-out frames flagged out of distribution: {100 * r.ood_share_above_threshold_family:.0f} % "
                     f"(family model) -> {100 * r.ood_share_above_threshold_adapted:.0f} % (adapted)")
    if r.renderer_overflow:
        lines.append(f"warning: {r.renderer_overflow} triangles exceeded the renderer's pixel budget "
                     "(very large lateral displacements); their pixels may be missing from the loss")
    return lines

