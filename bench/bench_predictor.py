"""Image-to-mesh predictor: the designs side by side, accuracy where the contact is and speed on
one CPU thread.

    python bench/bench_predictor.py [--shipped exported/gelslim_mesh.onnx] [--bundle exported/gelslim_mesh.pt]
        [--latent exported/baselines/gelslim_mesh_latent.onnx] [--n 256] [--rounds 300]
        [--variants surface-fastood] [--json results.json]
        [--small] [--no-write]
    (or: tactile-deploy bench predictor)

Designs (each one ONNX graph of the contract: depth [N, 1, 128, 128] mm -> vertices,
displacement [N, 5380, 3] mm, ood_score [N]):

* **latent**: the previous shipped graph (``--latent``): image encoder -> latent projection -> lean
  grid decoder, int8; rebuilds the whole pad from 128 numbers;
* **physics lift**: no learning: the depth map read at every sensing node's rest position, the
  pad's linear FEM for the rest (one dense 16,140 x 1,076 product, fp32; built here from the pad's
  operators, :class:`tactile_deploy.training.networks.lift.LiftGraph`); and, for accuracy only, the reference lift
  that reads the map where the nodes have moved (3 passes, numpy; the "physics lift" of every
  evaluation);
* **surface**: sensing nodes anchored on the measured surface + the convolutional residual of the
  committed bundle (``--bundle``), lateral motion learned;
* **hybrid** (shipped): the same, the sensing nodes' lateral motion from the physics lift of
  their anchored u_z; int8 only in that product (``hybrid-int8-fastood``): the committed graph
  (``--shipped``) as it is, and its committed fp32 twin.

``--variants`` exports further variants of the committed bundle here (default: the surface design).

Accuracy (:func:`tactile_deploy.training.metrics.mesh_metrics`, per-node Euclidean errors): contact patch RMSE,
deepest-node error (mean of |.| in % and signed mean), all-node RMSE, on fresh frictionless contacts
of the training indenters (``--n``, seed 3003) and of the shared STL indenters never trained on
(``--n`` / 2); the OOD AUROC of ``ood_score`` separating those primitives from 256 contacts of the
library's novel indenters (1 = perfect, 0.5 = chance; the physics lift has no score). The shipped
graph's ``ood_score`` is the size-normalised score of :mod:`tactile_deploy.training.ood_score`; the
``*-fastood`` variants exported here get the same nodes with the shipped graph's statistics; the
previous shipped graph keeps its own (the reconstruction RMSE).

Speed: p50 / p95 of one call at batch 1 and the time per mesh at batch 8, onnxruntime with 1
intra-op thread, all designs and the torch eager model of the shipped variant (the surface modules,
fp32, 1 thread) interleaved round by round, so a busy machine slows them alike; ratios to the
previous shipped graph measured in the same run. Results go to BENCHMARKS.md (section
``predictor``) unless ``--small`` or ``--no-write``.

``--small`` builds an untrained surface model (random weights) and synthetic presses and runs two
variants with few rounds: a check that the benchmark works, in about a minute; its accuracy columns
are meaningless. Target: p50 <= 1 ms per mesh at batch 1 for the shipped graph.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

TARGET_P50_MS = 1.0
BENCH_SEED = 3003
DEFAULT_VARIANTS = "surface-fastood"


def _small_model():
    """Untrained small surface-anchored model and synthetic presses (for --small)."""
    import numpy as np
    import torch

    from tactile_deploy.training.config import DataConfig, ModelConfig, SurfaceStageConfig, SyntheticData, TrainConfig
    from tactile_deploy.training.train import build_model

    cfg = TrainConfig(run_dir="unused", data=DataConfig(synthetic=SyntheticData(n_samples=1)),
                      model=ModelConfig(image={"widths": (16, 32, 64, 128, 128)}, surface={"anchor": "moved"}),
                      surface=SurfaceStageConfig(epochs=1), image_vae=None, mesh_vae=None, lean_decoder=None,
                      projection=None, finetune=None)
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    model.norm.set_scales(0.6, (0.05, 0.05, 0.05))
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:128, 0:128]
    depth = np.zeros((16, 128, 128), np.float32)
    for i in range(16):
        cy, cx, r = rng.uniform(30, 98), rng.uniform(30, 98), rng.uniform(5, 15)
        depth[i] = np.clip(0.8 * (1 - ((yy - cy) ** 2 + (xx - cx) ** 2) / r**2), 0, None)
    n = model.norm.rest_vertices_mm.shape[0]
    mask = np.zeros((16, model.n_plane), bool)
    mask[:, :10] = True
    data = {"primitives": (depth, np.zeros((16, n, 3), np.float32), mask)}
    return model, {"metrics": {}, "config": cfg.model_dump(mode="json")}, data, depth[:8]


def auroc(inside, outside) -> float:
    """Area under the ROC curve of a score meant to be larger ``outside`` (Mann-Whitney U)."""
    import numpy as np
    from scipy.stats import rankdata

    ranks = rankdata(np.concatenate([inside, outside]))
    n_in, n_out = len(inside), len(outside)
    return float((ranks[n_in:].sum() - n_out * (n_out + 1) / 2) / (n_in * n_out))


def _domains(n: int, shared: Path):
    """{name: (depth (N, R, R) mm, displacement (N, n, 3) mm, contact mask)} and the novel maps."""
    import numpy as np

    from tactile_deploy.indenters import list_indenters
    from tactile_deploy.training.config import SyntheticData
    from tactile_deploy.training.data import fresh_contacts
    from tactile_deploy.training.evaluation import simulate_domain

    out = {}
    for name, count in (("primitives", n), ("unseen_shapes", max(1, n // 2))):
        d = simulate_domain(name, count, BENCH_SEED, shared)
        out[name] = (d.depth_mm, d.displacement_mm, d.contact_mask)
    novel = SyntheticData(n_samples=1, indenters=tuple(list_indenters("novel")), seed=11)
    ood = fresh_contacts(novel, 256, 12).depth_mm.astype(np.float32)
    return out, ood


def main(argv=None) -> int:
    import numpy as np
    import torch

    from tactile_deploy.onnx_runtime.session import make_session
    from tactile_deploy.training.export import VARIANTS, export_variant, run_session, torch_reference
    from tactile_deploy.training.metrics import mesh_metrics

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default=str(ROOT / "exported" / "gelslim_mesh.pt"), help="training bundle (model.pt)")
    ap.add_argument("--shipped", default=str(ROOT / "exported" / "gelslim_mesh.onnx"),
                    help="the shipped graph, measured as committed (and its fp32 twin <stem>_fp32.onnx when present)")
    ap.add_argument("--latent", default=str(ROOT / "exported" / "baselines" / "gelslim_mesh_latent.onnx"),
                    help="the previous shipped (latent-decoder) graph, for comparison (skipped when missing)")
    ap.add_argument("--n", type=int, default=256, help="fresh frictionless contacts of the training indenters")
    ap.add_argument("--shared", default=str(ROOT.parent / "shared" / "data" / "indenters"),
                    help="folder of the shared STL indenters (never trained on)")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    ap.add_argument("--rounds", type=int, default=300)
    ap.add_argument("--variants", default=DEFAULT_VARIANTS,
                    help="other variants exported here from --bundle (comma-separated; '' for none)")
    ap.add_argument("--json", help="also write the results to this JSON file")
    ap.add_argument("--small", action="store_true", help="untrained model, 2 variants, few rounds")
    args = ap.parse_args(argv)

    torch.set_num_threads(1)
    variants = [v for v in args.variants.split(",") if v]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
    rounds = args.rounds
    if args.small:
        model, bundle, data, calib = _small_model()
        variants, rounds, ood_maps = ["surface-fastood", "surface-int8-fastood"], min(rounds, 20), None
    else:
        from tactile_deploy.training.train import load_bundle

        model, bundle = load_bundle(args.bundle)
        if not Path(args.shared).is_dir():
            ap.error(f"--shared {args.shared}: no such folder (the STL indenters never trained on)")
        data, ood_maps = _domains(args.n, Path(args.shared))
        calib = None
        if any("-int8" in v for v in variants):  # maps of the training distribution, never the ones measured here
            from tactile_deploy.training.config import TrainConfig
            from tactile_deploy.training.export import calibration_maps

            calib, _ = calibration_maps(TrainConfig.model_validate(bundle["config"]), heldout_seed=BENCH_SEED)

    tmp = Path(tempfile.mkdtemp(prefix="bench_predictor_"))
    designs = {}  # name -> {"session", "kind", "precision", "file_mb"}
    latent = Path(args.latent)
    if not args.small and latent.is_file():
        designs["latent (previous shipped)"] = {"path": latent, "kind": "latent", "precision": "int8"}
    elif not args.small:
        print(f"{latent} not found: the latent design is left out", file=sys.stderr)
    shipped_variant = variants[0] if args.small else None
    if not args.small:
        from tactile_deploy.onnx_runtime.metadata import read_metadata
        from tactile_deploy.training.export import fp32_twin

        shipped = Path(args.shipped)
        if not shipped.is_file():
            ap.error(f"--shipped {shipped}: no such file (the shipped graph, exported/gelslim_mesh.onnx)")
        shipped_variant = read_metadata(shipped).get("variant", "")
        if shipped_variant not in VARIANTS:
            ap.error(f"--shipped {shipped}: its metadata names no known variant (got {shipped_variant!r})")
        designs[f"{shipped_variant} (shipped)"] = {"path": shipped, "kind": shipped_variant.split("-")[0],
                                                   "variant": shipped_variant,
                                                   "precision": "int8" if "-int8" in shipped_variant else "fp32"}
        twin = shipped.with_name(shipped.stem + "_fp32.onnx")
        if twin.is_file() and twin != shipped:
            designs[f"{fp32_twin(shipped_variant)} (its fp32 twin)"] = {
                "path": twin, "kind": shipped_variant.split("-")[0], "variant": fp32_twin(shipped_variant),
                "precision": "fp32"}
        import torch.onnx

        from tactile_deploy.training.export import OUTPUTS, _onnx_export
        from tactile_deploy.training.networks.lift import LiftGraph

        path = tmp / "lift.onnx"
        _onnx_export(LiftGraph.for_pad(getattr(model, "nu", 0.48)).eval(), torch.zeros(2, 1, 128, 128), path,
                     ["depth"], OUTPUTS, optimize=False)
        designs["physics lift, one graph"] = {"path": path, "kind": "lift", "precision": "fp32"}
    ood_stats = None  # the shipped graph's size-normalised ood_score, given to the variants exported here
    if not args.small:
        from tactile_deploy.training.ood_score import statistics_of

        ood_stats = statistics_of(Path(args.shipped))
    for v in variants:
        t0 = time.perf_counter()
        path = export_variant(model, v, tmp / f"{v}.onnx", calib[:, None] if calib is not None and calib.ndim == 3
                              else calib, optimize=True)
        if ood_stats is not None and v.endswith("-fastood"):
            import onnx

            from tactile_deploy.training.ood_score import append_score

            onnx.save(append_score(onnx.load(str(path)), ood_stats), str(path))
        kind = v.split("-")[0]
        designs[v] = {
            "path": path, "kind": kind, "variant": v, "precision": "int8" if "-int8" in v else "fp32"}
        print(f"exported {v} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    for d in designs.values():
        d["session"] = make_session(d["path"], threads=1, providers="cpu")
        d["file_mb"] = sum(p.stat().st_size for p in (Path(d["path"]), Path(str(d["path"]) + ".data")) if p.is_file()) / 2**20

    # -- accuracy --------------------------------------------------------------------------------
    n_plane = model.n_plane
    rows = {}
    for name, d in designs.items():
        rows[name] = {"kind": d["kind"], "precision": d["precision"], "file_mb": d["file_mb"], "domains": {}}
        for dom, (depth, true, mask) in data.items():
            _, disp, ood = run_session(d["session"], depth[:, None].astype(np.float32))
            rows[name]["domains"][dom] = mesh_metrics(disp, true, mask, n_plane)
            if dom == "primitives" and ood_maps is not None and d["kind"] != "lift":
                rows[name]["ood_auroc"] = auroc(ood, run_session(d["session"], ood_maps[:, None])[2])
    if not args.small:
        from tactile_deploy.training.evaluation import physics_lift

        rows["physics lift (reference: 3 passes, numpy)"] = {"kind": "lift", "precision": "fp64", "file_mb": None,
            "domains": {dom: mesh_metrics(physics_lift(depth), true, mask, n_plane)
                        for dom, (depth, true, mask) in data.items()}}
    depth0 = data["primitives"][0][:, None].astype(np.float32)
    ref = torch_reference(model, shipped_variant, depth0[:64])[0]
    for name, d in designs.items():
        if d.get("variant"):
            rows[name]["max_diff_vs_torch_mm"] = float(np.abs(run_session(d["session"], depth0[:64])[1] - ref).max()) \
                if d["variant"].split("-")[0] == shipped_variant.split("-")[0] else None

    # -- speed: interleaved rounds ----------------------------------------------------------------
    from tactile_deploy.training.export import deploy_module

    eager = deploy_module(model, shipped_variant.replace("-int8", "")).eval()
    k = len(depth0)
    inputs = [depth0[i % k: i % k + 1] for i in range(16)]
    batch8 = np.concatenate([depth0[i % k: i % k + 1] for i in range(8)])
    names = list(designs) + ["torch eager (" + shipped_variant.replace("-int8", "") + ")"]
    t1 = {n: [] for n in names}
    t8 = {n: [] for n in names}

    def call(n, x):
        if n.startswith("torch"):
            with torch.no_grad():
                eager(torch.as_tensor(x))
        else:
            designs[n]["session"].run(None, {"depth": x})

    for n in names:  # warm-up
        for x in inputs[:5]:
            call(n, x)
        call(n, batch8)
    for r in range(rounds):
        for n in names:
            x = inputs[r % len(inputs)]
            t0 = time.perf_counter_ns()
            call(n, x)
            t1[n].append((time.perf_counter_ns() - t0) / 1e6)
        if r % 10 == 0:
            for n in names:
                t0 = time.perf_counter_ns()
                call(n, batch8)
                t8[n].append((time.perf_counter_ns() - t0) / 1e6 / 8)
    # the shipped graph alone: back-to-back calls, as `run` calls it frame after frame, with no
    # other design's weights (the physics lift's graph holds 66 MiB) pushed through the caches between
    alone = {}
    for n in names:
        if n.endswith("(shipped)"):
            for x in inputs[:5]:
                call(n, x)
            times = []
            for r in range(rounds):
                t0 = time.perf_counter_ns()
                call(n, inputs[r % len(inputs)])
                times.append((time.perf_counter_ns() - t0) / 1e6)
            alone[n] = (float(np.percentile(times, 50)), float(np.percentile(times, 95)))
    base_name = "latent (previous shipped)" if "latent (previous shipped)" in t1 else names[0]
    base = float(np.percentile(t1[base_name], 50))
    for n in names:
        rows.setdefault(n, {"kind": "torch", "precision": "fp32", "file_mb": None, "domains": {}})
        rows[n].update(p50_ms=float(np.percentile(t1[n], 50)), p95_ms=float(np.percentile(t1[n], 95)),
                       per_mesh_batch8_ms=float(np.percentile(t8[n], 50)), vs_base=float(np.percentile(t1[n], 50)) / base)
        if n in alone:
            rows[n]["p50_alone_ms"], rows[n]["p95_alone_ms"] = alone[n]

    text = table(rows, base_name, rounds, {d: len(v[0]) for d, v in data.items()}, args.small)
    print(text)
    if not args.small and not args.no_write:
        from bench.report import machine_line, write_section

        write_section("predictor", "## Image-to-mesh predictor (`tactile-deploy bench predictor`)\n\n"
                      f"{machine_line()}; model {Path(args.bundle).name}.\n\n" + text)
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "rounds": rounds}, indent=1))
    return 0


def table(rows: dict, base_name: str, rounds: int, counts: dict, small: bool) -> str:
    """The designs table (markdown) and the lines that read it."""
    def f(v, fmt):
        return "-" if v is None else format(v, fmt)

    lines = [
        f"Designs, one onnxruntime / torch thread; {rounds} interleaved rounds; accuracy on {counts.get('primitives', 0)} "
        f"fresh frictionless contacts of the training indenters and {counts.get('unseen_shapes', 0)} of the shared STL "
        "indenters (never trained on): per-node Euclidean errors (training/metrics.py), deepest node as mean |error| "
        f"(signed mean) in %; target p50 <= {TARGET_P50_MS} ms (shipped graph)" + (" (--small: untrained model, "
                                                                                    "accuracy meaningless)" if small else "") + ".",
        "",
        "| design | precision | p50 ms (batch 1) | p95 ms | ms/mesh (batch 8) | vs previous shipped | contact patch um "
        "| deepest node % | all nodes um | unseen: contact patch um | unseen: deepest node % | OOD AUROC | file MiB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        p = r["domains"].get("primitives", {})
        u = r["domains"].get("unseen_shapes", {})

        def dn(m):
            if not m:
                return "-"
            d = m["deepest_node_error_pct"]
            return f"{d['mean_abs']:.1f} ({d['mean']:+.1f})"

        label = f"**{name}**" if "(shipped)" in name else name
        lines.append(
            f"| {label} | {r['precision']} | {f(r.get('p50_ms'), '.3f')} | {f(r.get('p95_ms'), '.3f')} "
            f"| {f(r.get('per_mesh_batch8_ms'), '.3f')} | {f(r.get('vs_base'), '.2f')} "
            f"| {f(p.get('contact_patch_rmse_um'), '.1f')} | {dn(p)} | {f(p.get('all_node_rmse_um'), '.1f')} "
            f"| {f(u.get('contact_patch_rmse_um'), '.1f')} | {dn(u)} | {f(r.get('ood_auroc'), '.3f')} "
            f"| {f(r.get('file_mb'), '.1f')} |")
    lines += ["", f"`vs previous shipped`: p50 over the p50 of `{base_name}` in the same run."]
    shipped = [r for name, r in rows.items() if name.endswith("(shipped)") and r.get("p50_ms") is not None]
    if shipped:
        p50 = shipped[0]["p50_ms"]
        lines.append(f"Shipped graph p50 at batch 1, interleaved with the other designs: {p50:.3f} ms, "
                     f"target <= {TARGET_P50_MS} ms: "
                     + ("met" if p50 <= TARGET_P50_MS else "**not met**") + " in this run.")
        if shipped[0].get("p50_alone_ms") is not None:
            a50, a95 = shipped[0]["p50_alone_ms"], shipped[0]["p95_alone_ms"]
            lines.append(f"The same graph alone ({rounds} back-to-back calls at batch 1, one thread, as "
                         f"`run` calls it frame after frame, no other graph between): p50 {a50:.3f} ms, "
                         f"p95 {a95:.3f} ms: " + ("met" if a50 <= TARGET_P50_MS else "**not met**")
                         + ". Interleaved, every other design's weights (the physics lift's graph "
                         "holds 66 MiB) pass through the caches between two calls; in the `run` loop "
                         "the imaging stages do (BENCHMARKS.md `runtime`, its `model` stage).")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
