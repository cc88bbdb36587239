"""Export the adaptation step of a trained bundle for the runtime.

    python -m tactile_deploy.training export-adapt --bundle exported/gelslim_mesh.pt \
        [--onnx exported/gelslim_mesh.onnx] [--out exported/gelslim_mesh_adapt] [--filter vae]

Data flow of :func:`export_step`::

    bundle (training/train.py's model.pt) -> Predictor
      -> AdaptationStep (train mode) --torch.export, dynamic batch--> step.pt2
      -> VAEFilter --torch.onnx (dynamo, opset 18)--> filter.onnx
      -> parameter -> initializer map of the family's fp32 ONNX graph (by value, folded scales found)
      -> checks: fp32 ONNX == step displacement; loaded program == eager; a perturbed
         adaptation written into the ONNX graph == the perturbed step (the runtime's own writer)
      -> card.json, card.md

Why a torch.export program: it is the step's forward and loss as an ATen graph with its weights,
loaded with ``torch.export.load(...).module()`` by the runtime without this package; torch's
autograd and ``torch.optim.Adam`` then run on it as on any module (docs/adaptation.md compares
the alternatives).
"""

from __future__ import annotations

import datetime as _dt
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from tactile_deploy.adapt.card import (
    CARD_FILE,
    CARD_MD,
    FILTER_FILE,
    STEP_FILE,
    AdaptationCard,
    ParameterMapping,
    render_markdown,
)
from tactile_deploy.training.adaptation.step import AdaptationStep, VAEFilter
from tactile_deploy.training.errors import UsageError

DEFAULTS = {"lr": 1e-4, "batch_size": 16.0, "steps": 200.0}


def _sha(path: Path) -> str:
    from tactile_deploy.checksums import file_sha256

    return file_sha256(path)


def fp32_graph_of(family_onnx: Path) -> Path:
    """The fp32 graph of the family model: ``<stem>_fp32.onnx`` beside it, or itself when it has
    no quantised nodes."""
    import onnx

    twin = family_onnx.with_name(family_onnx.stem + "_fp32.onnx")
    if twin.is_file():
        return twin
    model = onnx.load(str(family_onnx))
    if any(n.op_type in ("QuantizeLinear", "DequantizeLinear") for n in model.graph.node):
        raise UsageError(f"{family_onnx} is quantised and its fp32 graph {twin} is missing; export the "
                         "model again (python -m tactile_deploy.training export) or pass --fp32")
    return family_onnx


def map_parameters(step: AdaptationStep, fp32_model) -> list[ParameterMapping]:
    """For each trainable parameter, the initializer of ``fp32_model`` (an onnx ModelProto)
    holding it: same name first, else any initializer of the same values; the first convolution
    carries 1 / depth_scale_mm (folded by the export)."""
    from onnx import numpy_helper

    inits = {i.name: numpy_helper.to_array(i) for i in fp32_model.graph.initializer}
    params = dict(step.named_parameters())
    first_conv = "convs.0.weight"
    out = []
    for name in step.trainable_names():
        p = params[name].detach().cpu().numpy().astype(np.float32)
        scale = 1.0 / float(step.depth_scale_mm) if name == first_conv else 1.0
        candidates = [name] + [k for k in inits if k != name]
        found = None
        for key in candidates:
            a = inits[key]
            for transform, q in (("copy", p), ("transpose", p.T if p.ndim == 2 else None)):
                if q is None or a.shape != q.shape:
                    continue
                if np.allclose(a, q * np.float32(scale), rtol=1e-5, atol=1e-7 * max(1.0, float(np.abs(a).max()))):
                    found = ParameterMapping(parameter=name, initializer=key, transform=transform, scale=scale,
                                             shape=tuple(p.shape))
                    break
            if found:
                break
        if found is None:
            raise UsageError(f"no initializer of the fp32 graph holds parameter {name!r} {p.shape}: the ONNX "
                             "graph was not exported from this bundle; give the --onnx (and --fp32) exported from "
                             "it (python -m tactile_deploy.training export --run RUN), or its --bundle")
        out.append(found)
    return out


def check_inputs(bundle_path: Path, n: int = 16) -> np.ndarray:
    """Depth maps (n, 1, 128, 128) mm for the checks: the run's held-out maps when beside the
    bundle, else smooth synthetic presses (Gaussian bumps of 0.2-1 mm)."""
    held = bundle_path.parent / "heldout.npz"
    if held.is_file():
        with np.load(held) as d:
            return d["depth_mm"][:n, None].astype(np.float32)
    rng = np.random.default_rng(0)
    c = -17.5 + (np.arange(128) + 0.5) * 35.0 / 128
    x, y = np.meshgrid(c, -c)
    maps = []
    for _ in range(n):
        cx, cy = rng.uniform(-8, 8, 2)
        r = rng.uniform(1.5, 4.0)
        maps.append(rng.uniform(0.2, 1.0) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * r * r)))
    return np.stack(maps)[:, None].astype(np.float32) * (np.hypot(x, y) < 17.5)


def _onnx_session(path: Path):
    from tactile_deploy.onnx_runtime.session import make_session

    return make_session(path, providers="cpu")


def export_step(bundle: str | Path, family_onnx: str | Path, out: str | Path, filter_kind: str = "vae",
                fp32_onnx: str | Path | None = None, log=print) -> AdaptationCard:
    """Write the step folder ``out`` (module docstring) for ``bundle`` and its family ONNX model.

    The folder is built beside ``out`` and swapped in at the end (an existing step folder is
    replaced only then, never left half-written); a folder that is not a step folder is refused."""
    import os
    import shutil

    from tactile_deploy.atomic import replace_folder
    from tactile_deploy.training.train import load_bundle

    bundle, family_onnx, out = Path(bundle), Path(family_onnx), Path(out)
    if bundle.is_dir():
        bundle = bundle / "model.pt"
    for option, path in (("--onnx", family_onnx), ("--fp32", fp32_onnx)):
        if path is not None and not Path(path).is_file():
            raise UsageError(f"{option} {path}: no such file; give the graph exported from the bundle "
                             "(python -m tactile_deploy.training export --run RUN)")
    if out.exists() and not (out.is_dir() and ((out / CARD_FILE).is_file() or not any(out.iterdir()))):
        raise UsageError(f"--out {out} exists and is not an adaptation step folder (no {CARD_FILE}), so it is not "
                         "replaced: choose another --out")
    model, meta = load_bundle(bundle)
    fp32 = Path(fp32_onnx) if fp32_onnx is not None else fp32_graph_of(family_onnx)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = out.parent / f".{out.name}.staging-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    try:
        card = _write_step(model, meta, bundle, family_onnx, fp32, staging, out, filter_kind, log)
        replace_folder(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return card


def _write_step(model, meta, bundle: Path, family_onnx: Path, fp32: Path, out: Path, final: Path, filter_kind: str,
                log) -> AdaptationCard:
    """The files of step folder ``final``, written into the folder ``out`` beside it."""
    import onnx

    from tactile_deploy.adapt.step import StepProgram
    from tactile_deploy.adapt.weights import write_adapted_onnx
    from tactile_deploy.atomic import atomic_path, write_json, write_text
    from tactile_deploy.training.export import OPSET, _onnx_export, int8_nodes, run_session

    t0 = time.perf_counter()
    torch.manual_seed(0)
    step = AdaptationStep(model).train()
    fp32_model = onnx.load(str(fp32))
    variant = {p.key: p.value for p in onnx.load(str(family_onnx), load_external_data=False).metadata_props}.get(
        "variant", "unknown")
    pmap = map_parameters(step, fp32_model)
    int8 = int8_nodes(fp32_model) if "-int8" in variant else []

    # 1. the fp32 graph computes the step's displacement
    depth = check_inputs(bundle)
    with torch.no_grad():
        ref = step.displacement(torch.as_tensor(depth)).numpy()
    _, onnx_disp, _ = run_session(_onnx_session(fp32), depth)
    graph_diff = float(np.abs(onnx_disp - ref).max())
    if graph_diff > 1e-4:
        raise UsageError(f"{fp32} differs from the bundle's step by {graph_diff:.3g} mm: it was not exported "
                         f"from {bundle}; give the --onnx (and --fp32) exported from it, or its --bundle")
    log(f"fp32 graph vs step: {graph_diff:.2e} mm")

    # 2. the step program (train mode, dynamic batch) and the filter graph
    batch = torch.export.Dim("batch", min=1, max=4096)
    weight = torch.as_tensor(step.renderer.mask.flip(0).float())
    target = torch.zeros(2, 128, 128)
    example = (torch.as_tensor(depth[:2]), target, weight)
    program = torch.export.export(step, example, dynamic_shapes=({0: batch}, {0: batch}, None))
    with atomic_path(out / STEP_FILE) as tmp:
        torch.export.save(program, str(tmp))
    vae = VAEFilter(model, filter_kind).eval()
    with atomic_path(out / FILTER_FILE) as tmp:
        _onnx_export(vae, torch.as_tensor(depth[:2]), tmp, ["depth"], ["filtered"], optimize=False)
    with torch.no_grad():
        filt_ref = vae(torch.as_tensor(depth)).numpy()
    filt = _onnx_session(out / FILTER_FILE).run(None, {"depth": depth})[0]
    filter_diff = float(np.abs(filt - filt_ref).max())

    def rel(p: Path) -> str:
        import os

        return Path(os.path.relpath(p.resolve(), final.resolve())).as_posix()

    files = {"step": {"path": STEP_FILE, "sha256": _sha(out / STEP_FILE)},
             "filter": {"path": FILTER_FILE, "sha256": _sha(out / FILTER_FILE)},
             "fp32_model": {"path": rel(fp32), "sha256": _sha(fp32)},
             "family_model": {"path": rel(family_onnx), "sha256": _sha(family_onnx)},
             "source_bundle": {"path": rel(bundle), "sha256": _sha(bundle)}}
    pad_n = int(step.displacement_scale_mm.shape[0])
    card_doc = {
        "name": final.name,
        "description": (
            "Self-supervised adaptation step of the image-to-mesh model (Zhu et al., 'Self-Supervised "
            "Adaptation'): the predicted mesh's sensing surface is rendered to a depth map by a "
            "differentiable copy of the simulator's depth camera and matched to the image VAE's "
            "reconstruction of the input, loss = MSE(render(decoder(projection(encoder(I)))), VAE(I)) over "
            "the pixels the sensor sees. One call = forward + loss; the runtime runs autograd and Adam."),
        "sensor_family": "gelslim",
        "mesh_hash": meta["mesh_hash"],
        "n_nodes": pad_n,
        "n_sensing_nodes": int(step.n_plane),
        "files": files,
        "trainable": step.trainable_names(),
        "frozen": ("lean grid mesh decoder (all its parameters), the displacement scales and backplate mask, "
                   "the depth renderer, and the VAE filter (filter.onnx: the image VAE as trained)"),
        "inputs": {
            "depth": "[B, 1, 128, 128] float32, mm pushed in, model grid (row 0 = largest y)",
            "target": "[B, 128, 128] float32, mm: VAE(depth) from filter.onnx (or depth itself: no filter)",
            "weight": "[128, 128] float32 in [0, 1]: pixels the sensor sees (its view on the pad)",
        },
        "outputs": {
            "loss": "[] float32, mm^2: mean over the batch of the weighted pixel MSE",
            "mse": "[B] float32, mm^2: weighted pixel MSE of each map",
            "rendered": "[B, 128, 128] float32, mm: depth map of the predicted mesh",
            "displacement": f"[B, {pad_n}, 3] float32, mm, sensor frame: the predicted mesh",
            "overflow": "[B] int64: triangles whose deformed box exceeded the renderer's pixel budget",
        },
        "parameter_map": [m.model_dump() for m in pmap],
        "int8_nodes": int8,
        "family_variant": variant,
        "depth_scale_mm": float(step.depth_scale_mm),
        "pixels_per_triangle": int(step.renderer.pixels_per_triangle),
        "defaults": DEFAULTS,
        "filter_kind": filter_kind,
        "parity": {"fp32_onnx_vs_step_max_abs_diff_mm": graph_diff,
                   "filter_onnx_vs_torch_max_abs_diff_mm": filter_diff},
        "versions": {
            "torch": torch.__version__, "onnx": onnx.__version__, "opset": str(OPSET),
            "python": platform.python_version(), "training_commit": meta["git"]["commit"],
            "training_dirty": str(meta["git"]["dirty"]).lower(),
            "exported": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        },
    }
    card = AdaptationCard.model_validate(card_doc)
    write_json(out / CARD_FILE, card.model_dump(mode="json"))

    # 3. the runtime's view: loaded program == eager; perturbed weights written into ONNX == eager
    loaded = StepProgram.load(out)
    with torch.no_grad():
        a = loaded(depth, np.zeros((len(depth), 128, 128), np.float32), weight.numpy())
        b = step(torch.as_tensor(depth), torch.zeros(len(depth), 128, 128), weight)
    program_diff = float(max((x.float() - y.float()).abs().max() for x, y in zip(a, b)))
    rng = np.random.default_rng(1)
    perturbed = {n: w + rng.normal(0, 0.2 * (float(np.abs(w).std()) + 1e-6), w.shape).astype(np.float32)
                 for n, w in loaded.weights().items()}
    loaded.load_weights(perturbed)
    with torch.no_grad():
        disp = loaded(depth, np.zeros((len(depth), 128, 128), np.float32), weight.numpy())[3].numpy()
    tmp_onnx = out / ".rewrite_check.onnx"
    try:
        write_adapted_onnx(card, fp32, perturbed, tmp_onnx)
        _, rewritten, _ = run_session(_onnx_session(tmp_onnx), depth)
    finally:
        tmp_onnx.unlink(missing_ok=True)
    rewrite_diff = float(np.abs(rewritten - disp).max())
    moved = float(np.abs(disp - ref).max())
    if rewrite_diff > 1e-4:
        raise ValueError(f"the rewritten ONNX graph differs from the perturbed step by {rewrite_diff:.3g} mm")
    card = AdaptationCard.model_validate(card_doc | {"parity": card_doc["parity"] | {
        "loaded_program_vs_eager_max_abs_diff": program_diff,
        "rewritten_onnx_vs_step_max_abs_diff_mm": rewrite_diff,
        "rewrite_check_displacement_change_mm": moved}})
    write_json(out / CARD_FILE, card.model_dump(mode="json"))
    write_text(out / CARD_MD, render_markdown(card))
    log(f"wrote {final} in {time.perf_counter() - t0:.1f} s: program vs eager {program_diff:.2e}, rewritten ONNX vs "
        f"step {rewrite_diff:.2e} mm (weights moved the mesh by {moved:.3g} mm)")
    return card


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m tactile_deploy.training export-adapt", description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", required=True, help="training bundle (model.pt, or its run folder)")
    ap.add_argument("--onnx", default="exported/gelslim_mesh.onnx",
                    help="the family model exported from it (default: %(default)s, relative to the current folder)")
    ap.add_argument("--fp32", default=None, help="its fp32 graph (default: <onnx stem>_fp32.onnx)")
    ap.add_argument("--out", default=None, help="step folder (default: <onnx stem>_adapt beside the model); an "
                    "existing step folder is replaced once the new one is complete")
    ap.add_argument("--filter", default="vae", choices=["vae", "lean"], help="decoder of the VAE filter")
    args = ap.parse_args(argv)
    onnx_path = Path(args.onnx)
    out = Path(args.out) if args.out else onnx_path.with_name(onnx_path.stem + "_adapt")
    card = export_step(args.bundle, onnx_path, out, args.filter, args.fp32)
    print(json.dumps(card.parity, indent=2))
    return 0
