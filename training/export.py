"""ONNX export of the trained predictor: one graph depth (mm) -> vertices and displacement (mm).

Data flow of :func:`export_run`::

    run_dir/model.pt -> Predictor -> deploy module of the chosen variant (fold scales, restructure)
      -> torch.onnx.export (dynamo, opset 18, dynamic batch) [-> int8 QDQ quantisation]
      -> metadata (units, frames, mesh hash, training commit, dataset, ood_threshold)
      -> parity on held-out depth maps -> model card (JSON + markdown)

Every graph follows docs/onnx_contract.md: input ``depth`` [N, 1, 128, 128] float32 mm; outputs
``vertices`` and ``displacement`` [N, 5380, 3] float32 mm (sensor frame) and ``ood_score`` [N]:
the RMS difference (mm) between the depth map and the image VAE's reconstruction of it from its
mean latent. The metadata's ``ood_threshold`` is the 99th percentile of that score on held-out
(in-distribution) maps: above it a map is less typical than 99 % of them.

Variants (``VARIANTS``):

* ``naive``: the training modules as they are (COMA decoder, Chebyshev recursions as Gather tables);
* ``fused``: the same function restructured (:mod:`tactile_deploy.training.fused`), exact to float rounding;
* ``lean``: image encoder + projection + the lean grid decoder (:mod:`tactile_deploy.training.networks.grid_decoder`);
* ``*-fastood``: ``ood_score`` from the lean image decoder (:class:`LeanImageDecoder`, trained on
  the frozen image encoder) instead of the symmetric VAE decoder, which is half of the lean graph's
  time; the metadata's ``ood_threshold`` is then that decoder's held-out p99;
* ``*-int8``: a variant with the image encoder, the projection and the image decoder (the
  ``ood_score`` branch) in int8 (static QDQ, calibrated on training depth maps; onnxruntime fuses
  them into integer kernels); the mesh decoder stays fp32. int8 graphs are checked against their
  fp32 graph by accuracy, not bit parity.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from tactile_deploy.onnx_runtime.contract import mesh_model_metadata
from tactile_deploy.onnx_runtime.metadata import write_metadata
from tactile_deploy.onnx_runtime.quantize import quantize_int8, quantize_int8_dynamic
from tactile_deploy.onnx_runtime.session import make_session
from tactile_deploy.training.errors import UsageError
from tactile_deploy.training.networks.predictor import Predictor
from tactile_deploy.training.networks.surface_decoder import compose_surface

VARIANTS = ("naive", "fused", "lean", "lean-fastood", "fused-int8", "lean-int8", "lean-int8-fastood",
            "surface", "surface-fastood", "surface-int8", "surface-int8-fastood",
            "hybrid", "hybrid-fastood", "hybrid-int8", "hybrid-int8-fastood")
#: Variants of the latent decoders and of the surface-anchored decoder (``hybrid``: its sensing
#: nodes' lateral displacement from the physics lift of their u_z).
LATENT_VARIANTS = VARIANTS[:7]
SURFACE_VARIANTS = VARIANTS[7:]
#: The variant written to the shipped file (best accuracy/speed pair, see bench/bench_predictor.py).
SHIPPED_VARIANT = "hybrid-int8-fastood"
OPSET = 18
OUTPUTS = ["vertices", "displacement", "ood_score"]


# ----------------------------------------------------------------------------------------- graphs
class PixelShuffleUp(nn.Module):
    """A stride-2, kernel-2 transposed convolution written as a 1 x 1 convolution to 4 C_out
    channels and a pixel shuffle (ONNX DepthToSpace, CRD). Same numbers; the 1 x 1 convolution
    quantises to an integer kernel, while onnxruntime de-quantises ConvTranspose weights per call.

    y[o, 2i + a, 2j + b] = sum_c x[c, i, j] W[c, o, a, b] + bias[o]
    """

    def __init__(self, deconv: nn.ConvTranspose2d):
        super().__init__()
        c_in, c_out = deconv.in_channels, deconv.out_channels
        self.conv = nn.Conv2d(c_in, 4 * c_out, 1)
        with torch.no_grad():
            # conv output channel o * 4 + a * 2 + b (pixel_shuffle's order)
            self.conv.weight.copy_(deconv.weight.permute(1, 2, 3, 0).reshape(4 * c_out, c_in, 1, 1))
            bias = deconv.bias if deconv.bias is not None else torch.zeros(c_out)
            self.conv.bias.copy_(bias.repeat_interleave(4))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.pixel_shuffle(self.conv(x), 2)


#: Transposed convolutions with at least this many weights become :class:`PixelShuffleUp`: there
#: int8 weights save memory traffic, while on wide, few-channel outputs DepthToSpace costs more
#: than an fp32 ConvTranspose.
PIXEL_SHUFFLE_MIN_WEIGHTS = 65536


def rewrite_transposed_convs(module: nn.Module, min_weights: int = PIXEL_SHUFFLE_MIN_WEIGHTS) -> nn.Module:
    """Replace kernel-2, stride-2 ConvTranspose2d layers (no padding) with at least ``min_weights``
    weights in ``module`` by :class:`PixelShuffleUp` (in place); returns ``module``."""
    for name, child in module.named_children():
        if (
            isinstance(child, nn.ConvTranspose2d)
            and child.kernel_size == (2, 2) and child.stride == (2, 2)
            and child.padding == (0, 0) and child.output_padding == (0, 0)
            and child.groups == 1 and child.dilation == (1, 1)
            and child.weight.numel() >= min_weights
        ):
            setattr(module, name, PixelShuffleUp(child))
        else:
            rewrite_transposed_convs(child, min_weights)
    return module


class DeployGraph(nn.Module):
    """depth (N, 1, R, R) mm -> (vertices (N, n, 3) mm, displacement (N, n, 3) mm, ood_score (N,) mm).

    Folded scales (exact up to float rounding): 1 / depth_scale into the first convolution
    (conv(x / s) = (W / s) * x + b) and depth_scale into the image decoder's last layer.
    """

    def __init__(self, model: Predictor, decoder: nn.Module, out_scale: torch.Tensor | None, ood: str = "vae"):
        super().__init__()
        enc = copy.deepcopy(model.image_vae.encoder)
        img_dec = copy.deepcopy(model.ood_decoder if ood == "lean" else model.image_vae.decoder)
        s = model.norm.depth_scale_mm.detach()
        with torch.no_grad():
            enc.convs[0].weight.div_(s)
            last = img_dec.deconvs[-1]
            last.weight.mul_(s)
            last.bias.mul_(s)
        self.convs, self.fc, self.mu = enc.convs, enc.fc, enc.mu
        self.image_decoder = rewrite_transposed_convs(img_dec)
        self.projection = copy.deepcopy(model.projection)
        self.decoder = rewrite_transposed_convs(decoder)
        self.register_buffer("rest", model.norm.rest_vertices_mm.clone())
        if out_scale is None:
            self.out_scale = None
        else:
            self.register_buffer("out_scale", out_scale)

    def forward(self, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        z_image = self.mu(self.fc(self.convs(depth)))
        d = self.decoder(self.projection(z_image))
        if self.out_scale is not None:
            d = d * self.out_scale
        recon = self.image_decoder(z_image)
        ood = torch.sqrt(torch.mean((recon - depth) ** 2, dim=(1, 2, 3)))
        return self.rest + d, d, ood


class SurfaceDeployGraph(nn.Module):
    """The surface-anchored path as one graph: depth (N, 1, R, R) mm -> (vertices, displacement
    (N, n, 3) mm, ood_score (N,) mm) (:mod:`tactile_deploy.training.networks.surface_decoder`).

    Folded: 1 / depth_scale into the first convolution, the displacement scale into the decoder's
    1 x 1 head (channel 3 * layer + axis), depth_scale into the image decoder's last layer. The
    anchor reads the depth map in mm (one Gather of 4 pixels per sensing node).
    """

    def __init__(self, model: Predictor, ood: str = "lean", lateral: nn.Module | None = None):
        super().__init__()
        self.lateral = lateral
        self.lateral_adds = model.lateral_adds  # the lift under the decoder's lateral residual, not instead
        enc = copy.deepcopy(model.image_vae.encoder)
        img_dec = copy.deepcopy(model.ood_decoder if ood == "lean" else model.image_vae.decoder)
        s = model.norm.depth_scale_mm.detach()
        dec = copy.deepcopy(model.surface_decoder)
        # head channel s * (3 * free layers) + 3 * layer + axis carries axis `axis`
        scale = model.norm.displacement_scale_mm.detach().repeat(dec.n_free_layers * dec.sub**2)
        with torch.no_grad():
            enc.convs[0].weight.div_(s)
            last = img_dec.deconvs[-1]
            last.weight.mul_(s)
            last.bias.mul_(s)
            dec.head.weight.mul_(scale[:, None])
            dec.head.bias.mul_(scale)
        self.convs, self.fc, self.mu = enc.convs, enc.fc, enc.mu
        self.image_decoder = rewrite_transposed_convs(img_dec)
        self.decoder = dec
        self.anchor = copy.deepcopy(model.anchor)
        self.moved = model.cfg.surface.anchor == "moved"
        self.register_buffer("rest", model.norm.rest_vertices_mm.clone())

    def forward(self, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        maps = []
        h = depth
        for layer in self.convs:
            h = layer(h)
            if not isinstance(layer, nn.Conv2d):
                maps.append(h)
        z_image = self.mu(self.fc(h))
        # mm (scale folded into the head); the lateral lift: the physics lift of the sensing surface's u_z
        d = compose_surface(self.decoder(maps, z_image), depth, self.anchor, self.moved, None, self.lateral,
                            self.lateral_adds)
        recon = self.image_decoder(z_image)
        ood = torch.sqrt(torch.mean((recon - depth) ** 2, dim=(1, 2, 3)))
        return self.rest + d, d, ood


def lateral_lift_of(model: Predictor):
    """The lateral physics lift of the model's pad at its training data's Poisson ratio (the model's
    own where it was trained with it, ``surface.lateral = "lift_residual"``)."""
    if model.lateral_lift is not None and model.lateral_adds:
        return model.lateral_lift
    from tactile_deploy.training.networks.lift import LateralLift

    return LateralLift.for_pad(getattr(model, "nu", 0.48))


def variant_parts(variant: str) -> tuple[str, bool, str]:
    """(base "naive" | "fused" | "lean", int8?, ood decoder "vae" | "lean") of a variant name."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; known: {', '.join(VARIANTS)}")
    base = variant.split("-")[0]
    return base, "-int8" in variant, "lean" if variant.endswith("-fastood") else "vae"


def fp32_twin(variant: str) -> str:
    """The variant with the same graph in fp32 (itself for fp32 variants)."""
    base, _, ood = variant_parts(variant)
    return base + ("-fastood" if ood == "lean" else "")


def deploy_module(model: Predictor, variant: str) -> nn.Module:
    """The fp32 torch module exported for ``variant`` (int8 variants start from their fp32 base)."""
    base, _, ood = variant_parts(variant)
    model = model.eval()
    if base in ("surface", "hybrid"):
        if not hasattr(model, "surface_decoder"):
            raise UsageError(f"variant {variant!r} needs a model with the surface decoder (model.surface in its "
                             f"config); this one has the latent decoders only: choose one of {', '.join(LATENT_VARIANTS)}")
        if base == "surface" and model.lateral_adds:
            raise UsageError(f"variant {variant!r} drops the lateral physics lift, but this model's decoder was "
                             f"trained on top of it (surface.lateral = 'lift_residual'): export a hybrid variant "
                             f"({', '.join(v for v in VARIANTS if v.startswith('hybrid'))})")
        return SurfaceDeployGraph(model, ood, lateral_lift_of(model) if base == "hybrid" else None).eval()
    scale_mask = (model.norm.displacement_scale_mm * model.norm.free_mask).detach().clone()
    if base == "naive":
        dec = copy.deepcopy(model.mesh_vae.decoder)
        dec.graphs.set_use_tables(True)
        return DeployGraph(model, dec, scale_mask, ood).eval()
    if base == "fused":
        from tactile_deploy.training.fused import FusedComaDecoder

        return DeployGraph(model, FusedComaDecoder(model.mesh_vae.decoder), scale_mask, ood).eval()
    if base == "lean":
        dec = copy.deepcopy(model.lean_decoder)
        last = dec.net[-1]
        scale = model.norm.displacement_scale_mm.detach()
        # channel 3 * layer + axis carries axis `axis`: fold the per-axis scale into the layer.
        s = scale.repeat(dec.n_free_layers)
        with torch.no_grad():
            last.weight.mul_(s[None, :, None, None])
            last.bias.mul_(s)
        return DeployGraph(model, dec, None, ood).eval()
    raise ValueError(f"unknown variant {variant!r}; known: {', '.join(VARIANTS)}")


# ----------------------------------------------------------------------------------------- export
def _onnx_export(
    module: nn.Module, example: torch.Tensor, path: Path, inputs: list[str], outputs: list[str], optimize: bool = True
) -> None:
    batch = torch.export.Dim("batch", min=1, max=4096)
    path.parent.mkdir(parents=True, exist_ok=True)
    prog = torch.onnx.export(
        module, (example,), dynamo=True, opset_version=OPSET, input_names=inputs, output_names=outputs,
        dynamic_shapes=({0: batch},), optimize=optimize, verbose=False,
    )
    prog.save(str(path))


#: Modules (paths inside :class:`DeployGraph`) whose Conv / Gemm / MatMul become int8. Not the
#: first convolution (one input channel: the int8 kernel is slower than fp32 there) and not the
#: mesh decoders (small, and where quantisation error reaches the vertices directly: 3x the RMS
#: deviation of all other layers together on the CPU run).
INT8_MODULES = ("convs.", "fc.", "projection.", "image_decoder.")
INT8_EXCLUDE = ("convs.0",)


def node_module_path(node) -> str:
    """Module path (e.g. ``projection.net.2``) the dynamo exporter recorded for an ONNX node."""
    meta = {p.key: p.value for p in node.metadata_props}
    parts = meta.get("namespace", "").split("/")
    return parts[-2].split(":")[0] if len(parts) >= 2 else ""


#: For the hybrid graphs: only the lateral physics lift, a 2.3 M-weight product that int8 makes ~3x
#: faster, quantised dynamically (each call's range of u_z: a static range calibrated on training
#: contacts saturated the lift's output on large novel presses, up to 1.6 mm at a node); their
#: convolutions and fully connected layers stay fp32 (static int8 of the encoder's, calibrated on
#: training maps, changed the out-of-distribution score of novel presses up to 2.6x). The surface
#: graphs (no lateral lift) quantise as the latent ones.
INT8_MODULES_HYBRID = ("lateral",)


def int8_nodes(model, variant: str | None = None) -> list[str]:
    """Names of the nodes :func:`quantise` turns into int8 for ``variant`` (default: the graph's
    ``variant`` metadata): INT8_MODULES_HYBRID for the hybrid graphs, else INT8_MODULES but
    INT8_EXCLUDE."""
    if variant is None:
        variant = {p.key: p.value for p in model.metadata_props}.get("variant", "")
    surface = variant.startswith("hybrid")
    prefixes = INT8_MODULES_HYBRID if surface else INT8_MODULES
    inits = {i.name for i in model.graph.initializer}
    out = []
    for n in model.graph.node:
        weighted = n.op_type in ("Conv", "Gemm") or (n.op_type == "MatMul" and n.input[1] in inits)
        path = node_module_path(n)
        chosen = any(path == p.rstrip(".") or path.startswith(p if p.endswith(".") else p + ".") for p in prefixes)
        if weighted and chosen and (surface or not any(path == e or path.startswith(e + ".") for e in INT8_EXCLUDE)):
            out.append(n.name)
    return out


def quantise(fp32_path: Path, out_path: Path, calibration: np.ndarray, input_name: str = "depth",
             variant: str = "") -> None:
    """int8 quantisation of :func:`int8_nodes` of ``variant``: dynamic for the hybrid graphs
    (:func:`tactile_deploy.onnx_runtime.quantize.quantize_int8_dynamic`: s8 per-channel weights,
    each call's activation range), else static (:func:`tactile_deploy.onnx_runtime.quantize.quantize_int8`:
    u8 activations, s8 per-channel weights, MinMax calibration on ``calibration`` (K, 1, R, R) mm).
    Everything else stays fp32."""
    import onnx

    nodes = int8_nodes(onnx.load(str(fp32_path)), variant)
    if not nodes:
        raise RuntimeError(f"{fp32_path}: no node to quantise (module paths missing from the export?)")
    if is_dynamic_int8(variant):
        quantize_int8_dynamic(fp32_path, out_path, nodes, keep_metadata=False)
    else:
        quantize_int8(fp32_path, out_path, calibration, nodes, input_name, keep_metadata=False)


def is_dynamic_int8(variant: str) -> bool:
    """Whether an int8 ``variant`` is quantised dynamically (no calibration maps): the hybrid graphs."""
    return variant.startswith("hybrid") and "-int8" in variant


def run_session(session, depth_mm: np.ndarray, batch: int = 32) -> tuple[np.ndarray, ...]:
    outs = [session.run(None, {"depth": depth_mm[i : i + batch].astype(np.float32)}) for i in range(0, len(depth_mm), batch)]
    return tuple(np.concatenate([o[k] for o in outs]) for k in range(len(outs[0])))


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def export_variant(
    model: Predictor, variant: str, path: str | Path, calibration: np.ndarray | None = None, optimize: bool = True
) -> Path:
    """Write the ONNX graph of ``variant`` (no metadata) and return its path.

    ``optimize``: run the exporter's graph optimiser (constant folding, ~8 s); onnxruntime
    optimises again at load, so both give the same numbers."""
    path = Path(path)
    example = torch.zeros(2, 1, model.cfg.image.resolution, model.cfg.image.resolution)
    module = deploy_module(model, variant)
    if variant_parts(variant)[1]:
        if calibration is None and not is_dynamic_int8(variant):
            raise ValueError(f"variant {variant!r} needs calibration depth maps")
        fp32 = path.with_name(path.stem + ".fp32.tmp.onnx")
        _onnx_export(module, example, fp32, ["depth"], OUTPUTS, optimize)
        try:
            quantise(fp32, path, calibration, variant=variant)
        finally:
            fp32.unlink(missing_ok=True)
            Path(str(fp32) + ".data").unlink(missing_ok=True)
    else:
        _onnx_export(module, example, path, ["depth"], OUTPUTS, optimize)
    return path


@torch.no_grad()
def torch_reference(model: Predictor, variant: str, depth_mm: np.ndarray, batch: int = 32):
    """(displacement (K, n, 3) mm, ood_score (K,) mm) of the eager fp32 torch model of ``variant``
    (``variant`` may also be a decoder family, "coma" or "lean", with the VAE's ood_score)."""
    before, before_lift = model.deploy_decoder, model.lateral_lift
    base = variant.split("-")[0]
    model.deploy_decoder = {"lean": "lean", "surface": "surface", "hybrid": "surface"}.get(base, "coma")
    if base == "hybrid":
        model.use_lateral_lift(lateral_lift_of(model))
    ood = variant_parts(variant)[2] if variant in VARIANTS else "vae"
    disp, oods = [], []
    try:
        for i in range(0, len(depth_mm), batch):
            x = torch.as_tensor(depth_mm[i : i + batch])
            disp.append(model(x)[1].numpy())
            oods.append(model.image_reconstruction_rmse(x, ood).numpy())
    finally:
        model.deploy_decoder = before
        model.use_lateral_lift(before_lift)
    return np.concatenate(disp), np.concatenate(oods)


def export_files(out: str | Path) -> list[Path]:
    """The files of an export to ``out``: the graph, its fp32 twin ``<stem>_fp32.onnx`` (int8
    variants), the model card ``<stem>.json`` and ``<stem>.md``."""
    out = Path(out)
    return [out, out.with_name(out.stem + "_fp32.onnx"), out.with_suffix(".json"), out.with_suffix(".md")]


def check_export(run_dir: str | Path, out: str | Path, variant: str, overwrite: bool = False) -> None:
    """Check a run export before any work (:class:`UsageError` naming the option and what to do):
    a known variant, a run folder with model.pt and heldout.npz, an ``.onnx`` --out whose files
    (:func:`export_files`) are replaced only with ``overwrite``."""
    run_dir, out = Path(run_dir), Path(out)
    if variant not in VARIANTS:
        raise UsageError(f"--variant {variant!r} is not a variant; choose one of {', '.join(VARIANTS)}")
    if not run_dir.is_dir():
        raise UsageError(f"--run {run_dir}: no such folder; give the run_dir of a training run")
    for name in ("model.pt", "heldout.npz"):
        if not (run_dir / name).is_file():
            raise UsageError(f"--run {run_dir} holds no {name}: give a finished training run (python -m tactile_deploy.training "
                             "train --config CONFIG.json writes both)")
    if out.suffix != ".onnx" or out.name.startswith("-"):
        raise UsageError(f"--out {out}: the file name must end in .onnx (its card is written beside it as "
                         f"{out.stem}.json and .md); choose another --out")
    if out.is_dir():
        raise UsageError(f"--out {out} is a folder: give a file name inside it")
    if out.parent.exists() and not out.parent.is_dir():
        raise UsageError(f"--out {out}: {out.parent} is not a folder; choose another --out")
    existing = [p for p in export_files(out) if p.exists()]
    if existing and not overwrite:
        raise UsageError(f"--out {out}: {', '.join(str(p) for p in existing)} exist"
                         f"{'s' if len(existing) == 1 else ''}: pass --overwrite to replace the set, or choose "
                         "another --out")


def heldout_seed(held) -> int | None:
    """The generator seed of a run's heldout.npz written by ``python -m tactile_deploy.training heldout`` (None:
    the held-out split of the training data)."""
    if "seed" in held:
        return int(held["seed"])
    if "source" in held:
        import re

        m = re.search(r"seed=(\d+)", str(held["source"]))
        return int(m.group(1)) if m else None
    return None


def export_run(
    run_dir: str | Path, out: str | Path, variant: str | None = None, n_parity: int = 128, optimize: bool = True,
    overwrite: bool = False, bundle_path: str | Path | None = None,
) -> dict:
    """Export a trained run: the shipped graph ``out``, the fp32 graph of the same weights
    (``<stem>_fp32.onnx``, when the shipped one is int8) and the model card (``<stem>.json``,
    ``<stem>.md``). Returns the card.

    ``bundle_path``: the weights to export (default ``run_dir/model.pt``; e.g. its slim bundle, so
    that the committed bundle and graph agree). Existing files of the set are replaced only with
    ``overwrite``. Everything is written to
    temporary names beside ``out`` and renamed into place at the end: an interrupted export
    leaves the previous set as it was."""
    import os

    from tactile_deploy.training.card import build_card, write_card
    from tactile_deploy.training.train import load_bundle

    run_dir, out = Path(run_dir), Path(out)
    variant = variant or SHIPPED_VARIANT
    check_export(run_dir, out, variant, overwrite)
    _, is_int8, ood = variant_parts(variant)
    model, bundle = load_bundle(Path(bundle_path) if bundle_path is not None else run_dir / "model.pt")
    with np.load(run_dir / "heldout.npz") as held:
        depth = held["depth_mm"][:, None].astype(np.float32)
        true = held["displacement_mm"]
        contact = held["contact_mask"] if "contact_mask" in held.files else None
        held_seed = heldout_seed(held)
    t0 = time.perf_counter()
    calibration, calibration_info = None, None
    if is_int8 and not is_dynamic_int8(variant):
        from tactile_deploy.training.config import TrainConfig

        calibration, calibration_info = calibration_maps(TrainConfig.model_validate(bundle["config"]), heldout_seed=held_seed)
    fp32_variant = fp32_twin(variant)
    final = export_files(out)
    ref_path = final[1] if variant != fp32_variant else out
    writes = [out, *([ref_path] if ref_path != out else []), final[2], final[3]]
    tmp = {p: p.with_name(f".{p.stem}.{os.getpid()}.partial{p.suffix}") for p in writes}
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        export_variant(model, variant, tmp[out], calibration, optimize)
        if ref_path != out:
            export_variant(model, fp32_variant, tmp[ref_path], optimize=optimize)

        # parity of the fp32 graph with torch, int8 against fp32, accuracy of the shipped graph
        k = min(n_parity, len(depth))
        ref_disp, ref_ood = torch_reference(model, variant, depth[:k])
        _, fp32_disp, fp32_ood = run_session(make_session(tmp[ref_path], providers="cpu"), depth[:k])
        parity = {
            "graph": ref_path.name,
            "n_inputs": k,
            "max_abs_diff_mm": float(np.abs(fp32_disp - ref_disp).max()),
            "ood_max_abs_diff_mm": float(np.abs(fp32_ood - ref_ood).max()),
        }
        _, final_disp, final_ood = run_session(make_session(tmp[out], providers="cpu"), depth)
        if ref_path != out:
            parity["shipped_vs_fp32_max_abs_diff_mm"] = float(np.abs(final_disp[:k] - fp32_disp).max())
            parity["shipped_vs_fp32_rms_diff_mm"] = float(np.sqrt(np.mean((final_disp[:k] - fp32_disp) ** 2)))
            parity["shipped_vs_fp32_ood_max_abs_diff_mm"] = float(np.abs(final_ood[:k] - fp32_ood).max())
        err = (final_disp - true).astype(np.float64)
        from tactile_deploy.training.evaluation import physics_lift
        from tactile_deploy.training.metrics import mesh_metrics

        accuracy = {
            "n_samples": int(len(depth)),
            "vertex_rmse_mm": float(np.sqrt(np.mean(err**2))),
            "relative_error": float(np.linalg.norm(err) / np.linalg.norm(true)),
            "max_error_mm": float(np.linalg.norm(err, axis=-1).max()),
            "ood_score_p99_mm": float(np.quantile(final_ood, 0.99)),
            "metrics": mesh_metrics(final_disp, true, contact, model.n_plane),
            "physics_lift": mesh_metrics(physics_lift(depth[:, 0]), true, contact, model.n_plane),
        }
        ood_threshold = float(bundle["metrics"]["ood_lean" if ood == "lean" else "ood"]["recon_rmse_mm_p99"])

        def card_now() -> dict:
            return build_card(bundle, variant, out, ref_path, parity, accuracy, ood_threshold,
                              time.perf_counter() - t0, graph_file=tmp[out], int8_calibration=calibration_info)

        props = card_metadata(card_now())
        for p in {out, ref_path}:
            write_metadata(tmp[p], props | {"variant": variant if p == out else fp32_variant},
                           replace=True, producer="tactile-deploy training")
        card = card_now()
        write_card(card, tmp[final[2]], tmp[final[3]])
        with _signals_held():  # the new set into place (the twin of an older int8 export goes), not half
            for p in writes:
                os.replace(tmp[p], p)
            if ref_path == out:
                final[1].unlink(missing_ok=True)
    finally:
        for t in tmp.values():
            t.unlink(missing_ok=True)
    return card


@contextlib.contextmanager
def _signals_held():
    """Hold SIGINT and SIGTERM back (delivered on exit) where the platform allows it."""
    import signal

    held = {signal.SIGINT, signal.SIGTERM}
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def calibration_maps(cfg, n: int = 256, heldout_seed: int | None = None) -> tuple[np.ndarray, dict]:
    """Depth maps (n, 1, R, R) mm of the training distribution for int8 calibration, never the
    held-out maps used for accuracy, and where they came from ({"source", "n_maps"}): ``n`` maps
    of the training split of the run's dataset folder, or ``n`` fresh contacts of its synthetic
    generator (another seed than the training one and ``heldout_seed``, simulated on the CPU).
    A dataset folder that cannot be read is a :class:`UsageError`."""
    from tactile_deploy.training.data import fresh_contacts, load, split_by_contact

    if cfg.data.synthetic is not None:
        spec = cfg.data.synthetic
        seed = spec.seed + 1_000
        if seed == heldout_seed:
            seed += 1_000
        maps = fresh_contacts(spec, n, seed).depth_mm[:, None].astype(np.float32)
        held = f"seed {heldout_seed}" if heldout_seed is not None else "the split of the training data"
        return maps, {"source": f"fresh contacts of the run's synthetic generator, seed {seed} (training: seed "
                                f"{spec.seed}; held-out maps: {held})", "n_maps": len(maps)}
    try:
        data = load(cfg.data)
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(
            f"int8 calibration reads training maps from the run's data.dataset_dir {cfg.data.dataset_dir}, which "
            f"cannot be read ({e}); put the dataset back there, or export an fp32 variant "
            f"(--variant {fp32_twin(SHIPPED_VARIANT)})"
        ) from None
    tr, _ = split_by_contact(data.contact_id, cfg.data.val_fraction, cfg.data.split_seed)
    rng = np.random.default_rng(0)
    pick = rng.choice(tr, size=min(n, len(tr)), replace=False)
    return data.depth_mm[pick][:, None].astype(np.float32), {
        "source": f"training split of {cfg.data.dataset_dir} (data.split_seed {cfg.data.split_seed}; no held-out contact)",
        "n_maps": len(pick)}


def card_metadata(card: dict) -> dict[str, str]:
    """ONNX metadata_props: the contract's entries (checked by the runtime at load) and where the
    model comes from."""
    return mesh_model_metadata(card["pad"]["name"], card["pad"]["mesh_hash"], card["pad"]["n_nodes"],
                               card["ood_threshold_mm"]) | {
        "training_commit": card["training"]["commit"],
        "training_dirty": str(card["training"]["dirty"]).lower(),
        "dataset": json.dumps(card["training"]["data"], sort_keys=True),
        "ood_calibration": json.dumps(card["ood"], sort_keys=True),
        "variant_accuracy": json.dumps(card["heldout_accuracy"], sort_keys=True),
        "model_card": card["files"]["card_json"],
    }
