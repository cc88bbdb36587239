"""Model card of an exported predictor: a strict JSON file and the markdown rendered from it."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from pydantic import Field

from tactile_deploy.fileformat import StrictModel
from tactile_deploy.onnx_runtime.contract import DEPTH_DOC, FRAME, SENSOR_FAMILY

CARD_FORMAT = 1


class PadInfo(StrictModel):
    name: str
    mesh_hash: str = Field(description="sha256 of the frozen pad mesh (vertex order contract).")
    n_nodes: int


class FileInfo(StrictModel):
    onnx: str = Field(description="The shipped graph.")
    onnx_sha256: str
    onnx_mb: float
    reference_fp32: str = Field(description="fp32 graph of the same weights (bit-parity reference).")
    card_json: str


class CardEvaluation(StrictModel):
    """The per-domain evaluation of the card's graph against the physics lift."""

    command: str = Field(description="The command that wrote it (and the report).")
    seed: int = Field(ge=0, description="Seed of the fresh contacts.")
    report: str = Field(description="The evaluation report (tactile_deploy.training.evaluation.EvaluationReport), path in the repository.")
    table: str = Field(description="Markdown table: a row per domain, this graph beside the physics lift, targets.")


class ModelCard(StrictModel):
    format_version: int = CARD_FORMAT
    name: str
    variant: str
    sensor_family: str
    pad: PadInfo
    inputs: dict[str, str]
    outputs: dict[str, str]
    frame: str
    files: FileInfo
    architecture: dict
    training: dict
    heldout_accuracy: dict = Field(description="The shipped graph on held-out contacts (mm).")
    torch_heldout_metrics: dict = Field(description="Training-time evaluation of both decoders (torch, mm).")
    parity: dict = Field(description="onnxruntime vs torch on held-out depth maps (mm).")
    int8_calibration: dict | None = Field(
        None, description="int8 variants: the maps the quantisation was calibrated on ({source, n_maps}); never "
        "the held-out maps of heldout_accuracy.",
    )
    ood: dict = Field(description="What ood_score is and its held-out quantiles (mm): the reconstruction RMSE of the "
                      "ood_score decoder as exported, or the size-normalised score (training/ood_score.py) with its "
                      "fitted statistics.")
    ood_threshold_mm: float = Field(description="ood_score above this (held-out p99) = outside the training range.")
    limitations: list[str]
    intended_use: list[str] = []
    export_seconds: float
    evaluation: CardEvaluation | None = Field(
        None, description="Per-domain evaluation of this graph (python -m tactile_deploy.training evaluate ... --card), when run.",
    )


#: What the exported model is for (rendered in every card).
INTENDED_USE = [
    "Real-time estimate of the deformed volumetric mesh (and, through the runtime's inverse FEM, the "
    "contact forces) of a GelSlim-family pad from its depth map, in robot software: one fixed-cost call "
    "per camera frame, on a CPU thread or a GPU.",
    "Depth maps from the sensor's imaging pipeline (tactile_deploy.runtime), on the model grid; "
    "frames whose ood_score exceeds ood_threshold are outside what the model was trained on.",
    "Not for: pads other than gelslim_v1 (the mesh hash is checked), indentations beyond 1.2 mm, "
    "or measurements that need better than ~0.02 mm per node (see the held-out figures).",
]


def build_card(bundle, variant, out, ref_path, parity, accuracy, ood_threshold, seconds, graph_file=None,
               int8_calibration=None) -> dict:
    """The card of graph ``out`` (its bytes read from ``graph_file``, default ``out``)."""
    cfg = bundle["config"]
    m = bundle["metrics"]
    out = Path(out)
    graph_file = Path(graph_file) if graph_file is not None else out
    card = ModelCard(
        name=out.stem,
        variant=variant,
        sensor_family=SENSOR_FAMILY,
        pad=PadInfo(name="gelslim_v1", mesh_hash=bundle["mesh_hash"], n_nodes=len(bundle["state_dict"]["norm.rest_vertices_mm"])),
        inputs={"depth": DEPTH_DOC},
        outputs={
            "vertices": "[N, 5380, 3] float32, mm, sensor frame, deformed vertex positions",
            "displacement": "[N, 5380, 3] float32, mm, sensor frame, vertices - rest vertices",
            "ood_score": "[N] float32, mm, RMS error of the depth map's reconstruction from the image VAE latent",
        },
        frame=FRAME,
        files=FileInfo(
            onnx=out.name,
            onnx_sha256=hashlib.sha256(graph_file.read_bytes()).hexdigest(),
            onnx_mb=round(graph_file.stat().st_size / 2**20, 3),
            reference_fp32=Path(ref_path).name,
            card_json=out.with_suffix(".json").name,
        ),
        architecture={
            "model": cfg["model"],
            "deployed_path": deployed_path(variant),
        },
        training={
            "commit": bundle["git"]["commit"],
            "dirty": bool(bundle["git"]["dirty"]),
            "data": m["data"],
            "stages": {
                k: cfg[k] for k in ("image_vae", "surface", "mesh_vae", "lean_decoder", "ood_decoder", "projection",
                                    "finetune")
                if cfg.get(k) is not None
            },
            "device": cfg["device"],
        },
        heldout_accuracy=accuracy,
        torch_heldout_metrics={
            name: {k: v for k, v in d["heldout"].items() if k != "ood"} for name, d in m["decoders"].items()
        },
        parity=parity,
        int8_calibration=int8_calibration,
        ood=m["ood_lean"] if variant.endswith("-fastood") else m["ood"],
        ood_threshold_mm=ood_threshold,
        limitations=limitations(cfg, variant),
        intended_use=INTENDED_USE,
        export_seconds=round(float(seconds), 2),
    )
    return card.model_dump(mode="json")


def deployed_path(variant: str) -> str:
    """One line: what the graph of ``variant`` computes."""
    int8 = "-int8" in variant
    if variant.startswith(("surface", "hybrid")):
        path = ("sensing nodes anchored on the measured surface (u_z = -depth where each node has moved) + the "
                "surface decoder's residual (image encoder feature maps at every scale and latent -> convolutional "
                "decoder -> residual displacement of every node)")
        if variant.startswith("hybrid"):
            path += ("; the sensing nodes' lateral displacement from the physics lift of their u_z (the pad's linear "
                     "FEM, one dense product" + (", int8" if int8 else "") + ")")
        precision = " (fp32" + (" but the lateral lift" if int8 else "") + ")"
    else:
        path = "image encoder (mean) -> latent projection -> " + (
            "lean grid decoder" if variant.startswith("lean") else "COMA mesh decoder")
        precision = " (int8 QDQ encoder, projection, image decoder)" if int8 else " (fp32)"
    return (path + precision + ("; ood_score from the lean image decoder" if variant.endswith("-fastood")
                                else "; ood_score from the image VAE decoder"))


def limitations(cfg: dict, variant: str) -> list[str]:
    """What the model does not cover, from its training config."""
    syn = (cfg.get("data") or {}).get("synthetic") or {}
    friction = syn.get("friction", "frictionless")
    trained_laws = [friction] if isinstance(friction, str) else list(friction)
    laws = " + ".join(trained_laws)
    depth = (f"{syn['depth_min_mm']:g}-{syn['depth_max_mm']:g} mm deep" if syn else "as in its dataset")
    faces = syn.get("procedural")
    shapes = "primitive indenters" + (
        f" and {faces['count']:,} procedural pressing faces ({faces['share']:.0%} of the contacts)" if faces else "")
    out = [
        f"Trained on simulated depth maps of {shapes} ({laws} contact, linear-elastic FEM, nu = "
        f"{syn.get('nu', 0.48)}, {depth}); real sensor maps need the self-supervised adaptation step.",
        "The 5,380-node mesh smooths contact features finer than ~2 mm.",
        "Depth maps must follow the camera convention in 'inputs' (mm, row 0 = largest y).",
    ]
    if "frictionless" not in trained_laws:
        out.append("For gels that grip the object (Coulomb friction, sticking contact): a depth map does not show "
                   "whether the gel slid, and on a gel that slides freely this graph's contact patch is far off "
                   "(see the evaluation's frictionless rows); choose the graph by the gel (docs/predictor.md).")
    elif set(trained_laws) == {"frictionless"}:
        out.append("For gels that slide freely on the object (frictionless contact): under Coulomb friction or "
                   "sticking contact the surface moves sideways in a way a depth map does not show (see the "
                   "evaluation's friction rows); choose the graph by the gel (docs/predictor.md).")
    if variant.startswith(("surface", "hybrid")):
        out.append("The sensing nodes follow the depth map: an error of the depth map (read-out, camera view) "
                   "is an error of the mesh where it is, unless it looks like the noise the model was trained "
                   "to remove.")
    else:
        out.append("The latent decoders rebuild the whole pad from 128 numbers: contact patches come out far less "
                   "accurate than from the physics lift (docs/predictor.md, evaluation by domain).")
    return out


def _ood_text(card: dict) -> str:
    """The card's paragraph on ``ood_score``: the exported reconstruction RMSE, or the
    size-normalised score of :mod:`tactile_deploy.training.ood_score`."""
    ood, thr = card["ood"], card["ood_threshold_mm"]
    if "formula" not in ood:
        return ("`ood_score` is the RMS error (mm) of the reconstruction of the input depth map from the image "
                "VAE's mean latent (decoder: see the variant above). Held-out quantiles: "
                + ", ".join(f"{k.split('_')[-1]} {v:.4f} mm" for k, v in ood.items())
                + f". Metadata `ood_threshold` = {thr:.4f} mm (held-out p99): above it a "
                "map is less typical than 99 % of the held-out maps.")
    st = ood["statistics"]
    return (f"`ood_score` ({ood['score']}) is the coarse reconstruction error of the input depth map by the lean image "
            f"decoder (the error averaged over {st['pool_px']} x {st['pool_px']} px blocks), normalised to a contact of "
            f"median size: `{ood['formula']}`, with noise = {st['noise_mm']} mm, b = {st['exponent']:.4f} and "
            f"d_ref = {st['d_ref_mm']:.4f} mm fitted on {st['source']}. Held-out quantiles ({ood['threshold_source']}): "
            f"p50 {ood['score_mm_p50']:.4f} mm, p95 {ood['score_mm_p95']:.4f} mm, p99 {ood['score_mm_p99']:.4f} mm, "
            f"max {ood['score_mm_max']:.4f} mm. Metadata `ood_threshold` = {thr:.4f} mm (held-out p99): above it a "
            "map is less typical than 99 % of the held-out maps. The graph's score equals its float64 re-computation "
            f"from the graph's reconstruction within {ood['graph_vs_numpy_max_abs_diff_mm']:.1e} mm.")


def write_card(card: dict, json_path: Path, md_path: Path) -> None:
    from tactile_deploy.atomic import write_json, write_text

    ModelCard.model_validate(card)
    write_json(json_path, card)
    write_text(md_path, render_markdown(card))


def _metrics_lines(acc: dict) -> list[str]:
    """The figures of training/metrics.py for the shipped graph and the physics lift, as a table."""
    if "metrics" not in acc:
        return []
    rows = [("shipped graph", acc["metrics"])] + ([("physics lift", acc["physics_lift"])] if "physics_lift" in acc else [])
    out = ["", "| method | contact patch RMSE um | deepest node error % (mean, signed / mean abs) | all-node RMSE um |",
           "|---|---|---|---|"]
    for name, m in rows:
        patch = f"{m['contact_patch_rmse_um']:.1f}" if "contact_patch_rmse_um" in m else "-"
        dn = m["deepest_node_error_pct"]
        out.append(f"| {name} | {patch} | {dn['mean']:+.2f} / {dn['mean_abs']:.2f} | {m['all_node_rmse_um']:.1f} |")
    out += ["", "Per-node Euclidean errors (training/metrics.py)."]
    return out


def _evaluation_lines(card: dict) -> list[str]:
    """The per-domain evaluation table, when the card carries one."""
    ev = card.get("evaluation")
    if not ev:
        return []
    return ["", "## Evaluation by domain", "",
            f"`{ev['command']}` (fresh contacts, seed {ev['seed']}; the physics lift beside every figure):", "",
            ev["table"].rstrip()]


def render_markdown(card: dict) -> str:
    acc, par = card["heldout_accuracy"], card["parity"]
    lines = [
        f"# Model card: {card['name']}",
        "",
        f"Image-to-mesh predictor for the **{card['sensor_family']}** pad `{card['pad']['name']}` "
        f"(mesh hash `{card['pad']['mesh_hash'][:16]}...`, {card['pad']['n_nodes']} nodes). "
        f"Variant `{card['variant']}`: {card['architecture']['deployed_path']}.",
        "",
        "## Interface",
        "",
        "| name | description |",
        "|---|---|",
        *[f"| input `{k}` | {v} |" for k, v in card["inputs"].items()],
        *[f"| output `{k}` | {v} |" for k, v in card["outputs"].items()],
        "",
        f"Frame: {card['frame']}.",
        "",
        "## Files",
        "",
        f"- `{card['files']['onnx']}` ({card['files']['onnx_mb']} MiB, sha256 `{card['files']['onnx_sha256'][:16]}...`)",
        *([f"- `{card['files']['reference_fp32']}`: fp32 graph of the same weights"]
          if card["files"]["reference_fp32"] != card["files"]["onnx"] else ["- the graph is fp32 itself (no twin)"]),
        "",
        "## Held-out accuracy (shipped graph)",
        "",
        f"- samples: {acc['n_samples']} (contacts never seen in training)",
        f"- vertex RMSE: {acc['vertex_rmse_mm']:.4f} mm per coordinate; relative displacement error: "
        f"{acc['relative_error']:.3f}; largest node error: {acc['max_error_mm']:.3f} mm",
        *_metrics_lines(acc),
        "",
        "Training-time evaluation (torch, held-out):",
        "",
        "| decoder | vertex RMSE mm | relative error | mesh VAE reconstruction RMSE mm |",
        "|---|---|---|---|",
        *[
            f"| {k} | {v['vertex_rmse_mm']:.4f} | {v['relative_error']:.3f} | "
            + (f"{v['mesh_reconstruction_rmse_mm']:.4f}" if "mesh_reconstruction_rmse_mm" in v else "-") + " |"
            for k, v in card["torch_heldout_metrics"].items()
        ],
        *_evaluation_lines(card),
        "",
        "## Parity",
        "",
        f"- `{par['graph']}` vs torch on {par['n_inputs']} held-out maps: max |difference| "
        f"{par['max_abs_diff_mm']:.2e} mm",
    ]
    if "shipped_vs_fp32_max_abs_diff_mm" in par:
        lines.append(
            f"- shipped int8 graph vs its fp32 graph: max {par['shipped_vs_fp32_max_abs_diff_mm']:.2e} mm, "
            f"RMS {par['shipped_vs_fp32_rms_diff_mm']:.2e} mm"
        )
    if card.get("int8_calibration"):
        cal = card["int8_calibration"]
        lines.append(f"- int8 calibration: {cal['n_maps']} maps, {cal['source']}")
    lines += [
        f"- `ood_score` of `{par['graph']}` vs torch: max {par['ood_max_abs_diff_mm']:.2e} mm",
        "",
        "## Out-of-distribution score",
        "",
        _ood_text(card),
        "",
        "## Training",
        "",
        f"- commit `{card['training']['commit']}`" + (" (uncommitted changes)" if card["training"]["dirty"] else ""),
        f"- data: {json.dumps(card['training']['data']['train']['n_samples'])} training / "
        f"{card['training']['data']['val']['n_samples']} held-out samples, {card['training']['data']['train']['source']}",
        "",
        "## Intended use",
        "",
        *[f"- {x}" for x in card.get("intended_use", [])],
        "",
        "## Limitations",
        "",
        *[f"- {x}" for x in card["limitations"]],
        "",
        "Speed: see `bench/bench_predictor.py` (docs/predictor.md).",
        "",
    ]
    return "\n".join(lines)
