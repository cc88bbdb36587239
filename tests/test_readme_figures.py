"""The figures the README quotes are the ones the benchmarks and evaluations wrote.

Each figure is read from the README's text and from its source (a section of BENCHMARKS.md
written by `tactile-deploy bench`, a committed result under docs/results/, or the model card),
and must equal the source rounded as the README rounds it. A rerun benchmark that changes a
figure makes this test fail until the README says the new one.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _text(path: Path) -> str:
    """The file's text with every run of whitespace (line breaks included) as one space."""
    return re.sub(r"\s+", " ", path.read_text(encoding="utf-8"))


README = _text(ROOT / "README.md")
BENCHMARKS = (ROOT / "BENCHMARKS.md").read_text(encoding="utf-8")


def readme(pattern: str) -> tuple[str, ...]:
    """The groups of ``pattern`` in the README (it must be there: the sentence was rewritten
    otherwise, and this test with it)."""
    m = re.search(pattern, README)
    assert m, f"README no longer says {pattern!r}: update the README or this test"
    return m.groups()


def section(name: str) -> str:
    """A ``<!-- bench:NAME -->`` section of BENCHMARKS.md."""
    m = re.search(rf"<!-- bench:{name} -->(.*?)<!-- /bench:{name} -->", BENCHMARKS, re.S)
    assert m, f"BENCHMARKS.md has no section {name!r}"
    return m.group(1)


def table_row(text: str, first_cell: str) -> list[str]:
    """The cells after the first of the table row whose first cell starts with ``first_cell``."""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0].startswith(first_cell):
            return cells[1:]
    raise AssertionError(f"no table row starting with {first_cell!r}")


def rounded(value: float, like: str) -> str:
    """``value`` with as many decimals as the README's ``like``."""
    decimals = len(like.split(".")[1]) if "." in like else 0
    return f"{value:.{decimals}f}"


def virtual_target_line(which: str) -> dict:
    """The machine-written target line of ``bench shading --only virtual`` for ``which``."""
    text = section("shading-virtual")
    m = re.search(rf"the {re.escape(which)}: new presses, seed 2024: ([0-9.]+) um mean inside the "
                  rf"view \(worst [0-9.]+\), ([0-9.]+) um near its edges; second set, seed 77: "
                  rf"([0-9.]+) um mean inside the view \(worst [0-9.]+\), ([0-9.]+) um near its "
                  r"edges", text)
    assert m, f"no target line for {which!r} in BENCHMARKS.md"
    inside1, edge1, inside2, edge2 = (float(v) for v in m.groups())
    return {"inside": (inside1, inside2), "edges": (edge1, edge2)}


def test_predictor_headline_is_the_evaluation_and_the_model_card():
    """The README's contact-patch headline, the physics lift beside it, is the committed
    evaluation report's, and the shipped model's card carries the same report's table."""
    import hashlib

    (n, patch, lift_patch, deep, lift_deep, all_nodes, lift_all, unseen, lift_unseen, neo, lift_neo) = readme(
        r"on (\d+) fresh frictionless contacts of the linear-elastic gel it was trained on: the shipped graph's "
        r"contact patch is ([0-9.]+) um RMS against "
        r"([0-9.]+) um for the physics lift, its deepest node ([-+0-9.]+) % against ([-+0-9.]+) % \(all nodes: "
        r"([0-9.]+) against ([0-9.]+) um\); on the shared STL shapes it never saw ([0-9.]+) against ([0-9.]+) um "
        r"\(docs/results/evaluation.json\); on the same kind of contacts of the neo-Hookean gel \(large "
        r"deformation\) ([0-9.]+) um against ([0-9.]+) um \(docs/results/evaluation_neo_hookean_truth.json\)")
    neo_report = json.loads((ROOT / "docs" / "results" / "evaluation_neo_hookean_truth.json").read_text())
    assert neo_report["gel"] == "neo-hookean" and neo_report["models"]["shipped"] == "exported/gelslim_mesh.onnx"
    neo_prim = neo_report["domains"]["primitives"]["methods"]
    assert rounded(neo_prim["shipped"]["contact_patch_rmse_um"], neo) == neo
    assert rounded(neo_prim["physics lift"]["contact_patch_rmse_um"], lift_neo) == lift_neo
    evaluation = json.loads((ROOT / "docs" / "results" / "evaluation.json").read_text())
    card = json.loads((ROOT / "exported" / "gelslim_mesh.json").read_text())
    assert evaluation["models"]["shipped"] == "exported/gelslim_mesh.onnx"
    shipped_bytes = (ROOT / evaluation["models"]["shipped"]).read_bytes()
    assert hashlib.sha256(shipped_bytes).hexdigest() == card["files"]["onnx_sha256"], "the card is of another graph"
    prim, shapes = evaluation["domains"]["primitives"], evaluation["domains"]["unseen_shapes"]
    assert prim["n_samples"] == int(n)
    model, lift = prim["methods"]["shipped"], prim["methods"]["physics lift"]
    assert rounded(model["contact_patch_rmse_um"], patch) == patch
    assert rounded(lift["contact_patch_rmse_um"], lift_patch) == lift_patch
    assert rounded(model["deepest_node_error_pct"]["mean"], deep) == deep.lstrip("+")
    assert rounded(lift["deepest_node_error_pct"]["mean"], lift_deep) == lift_deep.lstrip("+")
    assert rounded(model["all_node_rmse_um"], all_nodes) == all_nodes
    assert rounded(lift["all_node_rmse_um"], lift_all) == lift_all
    assert rounded(shapes["methods"]["shipped"]["contact_patch_rmse_um"], unseen) == unseen
    assert rounded(shapes["methods"]["physics lift"]["contact_patch_rmse_um"], lift_unseen) == lift_unseen
    assert card["evaluation"]["report"] == "docs/results/evaluation.json"
    assert f"| **{patch}** / {lift_patch} | {deep} / {lift_deep} | {all_nodes} / {lift_all} |" in card["evaluation"]["table"]


def test_predictor_limits_are_the_evaluation():
    stick, stick_lift, strain, strain_lift = readme(
        r"is ([0-9.]+) um RMS off on the contact patch under sticking contact \(the physics lift: ([0-9.]+) um\) and "
        r"([0-9.]+) um under large strain \(lift: ([0-9.]+) um\)")
    domains = json.loads((ROOT / "docs" / "results" / "evaluation.json").read_text())["domains"]
    for dom, model, lift in (("stick", stick, stick_lift), ("large_strain", strain, strain_lift)):
        methods = domains[dom]["methods"]
        assert rounded(methods["shipped"]["contact_patch_rmse_um"], model) == model
        assert rounded(methods["physics lift"]["contact_patch_rmse_um"], lift) == lift


def test_predictor_latency_is_the_benchmark():
    ms, verdict, latent, alone = readme(
        r"~([0-9.]+) ms on one CPU thread interleaved with the other designs \(target 1 ms: ([a-z ]+) in this run, "
        r"where the previous latent graph took ([0-9.]+) ms[;)].*?, ([0-9.]+) ms alone")
    text = section("predictor")
    shipped = table_row(text, "**hybrid-int8-fastood (shipped)**")
    p50_ms = float(shipped[1])  # precision, then p50 ms (batch 1)
    assert rounded(p50_ms, ms) == ms, f"README ~{ms} ms, benchmark p50 {p50_ms} ms"
    assert verdict == ("met" if p50_ms <= 1.0 else "not met"), (verdict, p50_ms)
    assert rounded(float(table_row(text, "latent (previous shipped)")[1]), latent) == latent
    m = re.search(r"The same graph alone \(.*?\): p50 ([0-9.]+) ms", text)
    assert m and rounded(float(m.group(1)), alone) == alone


def test_real_ball_adaptation_figures_are_the_benchmark():
    ball0, ball1, cap0, cap1, lift, lift_cap, ball_vae, cap_vae = readme(
        r"brings the sensing surface's error against the ball from ([0-9.]+) to ([0-9.]+) um RMS \(contact depth "
        r"([-+0-9.]+) % -> ([-+0-9.]+) %; the physics lift: ([0-9.]+) um, ([-+0-9.]+) %\); towards the image VAE's "
        r"reconstruction \(the paper's target, `adapt --filter`\) its label-free error falls too but the\s+surface "
        r"leaves the ball \(([0-9.]+) um, ([-+0-9.]+) %\)")
    text = section("predictor-real")
    before, after, vae, physics = (table_row(text, name) for name in (
        "shipped model", "adapted (fp32)", "adapted towards VAE(I) (fp32)", "physics lift"))
    assert (before[0], after[0], vae[0], physics[0]) == (ball0, ball1, ball_vae, lift)
    assert tuple(r[1].split(" /")[0] for r in (before, after, vae, physics)) == (cap0, cap1, cap_vae, lift_cap)
    assert float(after[2]) < float(before[2])  # label-free error against its target fell


def test_learned_readout_depth_errors_are_the_benchmark():
    in1, in2, edge1, edge2 = readme(
        r"within ([0-9.]+) / ([0-9.]+) um RMS of the true depth near the contact inside the view "
        r"on two sets of new presses and ([0-9.]+) / ([0-9.]+) um near the view's edges")
    bench = virtual_target_line("learned read-out")
    assert (rounded(bench["inside"][0], in1), rounded(bench["inside"][1], in2)) == (in1, in2)
    assert (rounded(bench["edges"][0], edge1), rounded(bench["edges"][1], edge2)) == (edge1, edge2)


def test_learned_readout_worst_edge_press_and_unseen_shapes_are_the_benchmark():
    (worst,) = readme(r"single presses near the edges up to (\d+) um")
    shapes, in_view = readme(r"reads unseen shapes to (\d+) um near the contact \((\d+) um within the view\)")
    text = section("shading-virtual")
    rows = [line for line in text.splitlines() if line.startswith("| learned read-out of the GelSlim design")]
    assert len(rows) == 2, "expected the read-out's row in both press sets"
    edge_worst = max(float(r.strip().strip("|").split("|")[-2]) for r in rows)
    assert rounded(edge_worst, worst) == worst
    cells = table_row(text, "the learned read-out")
    assert (rounded(float(cells[0]), shapes), rounded(float(cells[2]), in_view)) == (shapes, in_view)


def test_family_figures_are_the_benchmarks():
    (lift_ms,) = readme(r"lift, (\d+) ms per frame on the Mini's 10,716-node pad")
    assert re.search(rf"physics lift {lift_ms} ms \(", section("recording-real"))
    figures = readme(
        r"both meet the depth targets on two samples each: DIGIT balls ([0-9.]+) / ([0-9.]+) um inside\s+"
        r"the view, ([0-9.]+) / ([0-9.]+) um near its edges, unseen shapes ([0-9.]+) / ([0-9.]+) um; the GelSight "
        r"Mini, whose\s+LED layout is not published and is assumed, balls ([0-9.]+) / ([0-9.]+) um "
        r"inside the view, ([0-9.]+) / ([0-9.]+)\s+um near its edges \(target 20 um\) and "
        r"unseen shapes ([0-9.]+) / ([0-9.]+) um \(target 30 um\)")
    text = section("families")
    for family, readme_figures in (("digit", figures[:6]), ("gelsight_mini", figures[6:])):
        cells = [line.strip().strip("|").split("|") for line in text.splitlines()
                 if line.startswith(f"| {family} | learned read-out")]
        assert len(cells) == 1, family
        row = [c.strip() for c in cells[0]]
        # inside, second inside, edges, second edges, shapes (16), shapes (48)
        second_inside, second_edges = (part.strip().split(" ")[0] for part in row[4].split("/"))
        bench = [row[2].split(" ")[0], second_inside, row[3].split(" ")[0], second_edges,
                 row[6].split(" ")[0], row[7].split(" ")[0]]
        assert bench == list(readme_figures), (family, bench, readme_figures)
    for family in ("digit", "gelsight_mini"):   # the README's verdict: every target met
        row = [line for line in text.splitlines() if line.startswith(f"| {family} | learned read-out")][0]
        assert ("balls 20 um (both samples): met, edges 20 um (both samples): met, "
                "shapes 30 um (both samples): met") in row, family


def test_shading_model_depth_errors_are_the_benchmark():
    in1, in2, lo, hi = readme(r"meets the target inside the view \(([0-9.]+) / ([0-9.]+) um\) but "
                              r"is (\d+)-(\d+) um near its edges")
    bench = virtual_target_line("wizard's shading model")
    assert (rounded(bench["inside"][0], in1), rounded(bench["inside"][1], in2)) == (in1, in2)
    edges = sorted(bench["edges"])
    assert (rounded(edges[0], lo), rounded(edges[1], hi)) == (lo, hi)


@pytest.fixture(scope="module")
def adaptation_rows():
    return json.loads((ROOT / "docs" / "results" / "adaptation_tables.json").read_text())["rows"]


def _gain(row: dict) -> float:
    return row["before"]["label_free_rmse_mm"] / row["after"]["label_free_rmse_mm"]


def test_adaptation_gains_are_the_tables(adaptation_rows):
    lo, hi, paper = readme(r"lowers the paper's label-free error only ([0-9.]+)-([0-9.]+)x "
                           r"\(paper: ([0-9.]+)x\)")
    virtual = [_gain(r) for name, r in adaptation_rows.items()
               if name.startswith("clean: ") and "-> gelslim" in name]
    assert len(virtual) >= 3
    assert (rounded(min(virtual), lo), rounded(max(virtual), hi)) == (lo, hi), (
        f"the clean model's gains on the virtual sensors span {min(virtual):.3f}-{max(virtual):.3f}x")
    assert paper == "4.75"  # the paper's Table 2, not ours
    (real,) = readme(r"halves it \(([0-9.]+)x\)")
    assert rounded(_gain(adaptation_rows["clean: sim -> real-balls"]), real) == real


def test_adaptation_label_free_errors_are_the_tables(adaptation_rows):
    virtual, sim = readme(r"label-free ([0-9.]+) um against ([0-9.]+) um in simulation")
    gelslim1 = 1e3 * adaptation_rows["clean: sim -> gelslim1"]["before"]["label_free_rmse_mm"]
    simulated = 1e3 * adaptation_rows["sim-prim (clean)"]["before"]["label_free_rmse_mm"]
    assert (rounded(gelslim1, virtual), rounded(simulated, sim)) == (virtual, sim)


def test_virtual_sensor_frame_time_is_the_benchmark():
    (ms,) = readme(r"take about (\d+) ms at 640 x 480 on one CPU thread")
    renderer = float(table_row(section("optics"), "renderer, whole frame changed")[0])
    assert rounded(renderer, ms) == ms


def test_neo_hookean_graph_figures_are_its_evaluation():
    """The README's figures for the graph trained on the neo-Hookean gel (not shipped) are its
    committed evaluation reports' (neo-Hookean truth; the linear truth's primitives)."""
    prim, unseen, noisy, strain, linear = readme(
        r"alone reads frictionless primitives to ([0-9.]+) um, unseen shapes ([0-9.]+), noisy maps "
        r"([0-9.]+) and large\s+strain ([0-9.]+) um, 2.9-3.4x better than the physics lift, but not to the "
        r"30 / 50 um targets, and the\s+linear gel's contacts to ([0-9.]+) um")
    results = ROOT / "docs" / "results"
    neo = json.loads((results / "evaluation_neo_hookean_truth_x2.json").read_text())
    lin = json.loads((results / "evaluation_neo_hookean_finetune_x2.json").read_text())
    assert neo["gel"] == "neo-hookean" and lin["gel"] == "linear"
    for dom, figure in (("primitives", prim), ("unseen_shapes", unseen), ("noisy", noisy), ("large_strain", strain)):
        methods = neo["domains"][dom]["methods"]
        assert rounded(methods["nh_x2"]["contact_patch_rmse_um"], figure) == figure
        assert methods["physics lift"]["contact_patch_rmse_um"] / methods["nh_x2"]["contact_patch_rmse_um"] >= 2.85
    assert rounded(lin["domains"]["primitives"]["methods"]["nh_x2"]["contact_patch_rmse_um"], linear) == linear
