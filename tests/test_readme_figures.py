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
    rmse, n = readme(r"shipped int8 graph: ([0-9.]+) mm vertex RMSE on (\d+) fresh contacts")
    evaluation = json.loads((ROOT / "docs" / "results" / "evaluation.json").read_text())
    card = json.loads((ROOT / "exported" / "gelslim_mesh.json").read_text())
    learned = evaluation["domains"]["primitives"]["learned"]
    assert rounded(learned["vertex_rmse_mm"], rmse) == rmse
    on_card = card["heldout_accuracy"]["disjoint_from_int8_calibration"]["seed2024_evaluation"]
    assert rounded(on_card["vertex_rmse_mm"], rmse) == rmse
    assert evaluation["domains"]["primitives"]["n_samples"] == int(n) == on_card["n_samples"]


def test_predictor_latency_is_the_benchmark():
    (ms,) = readme(r"~([0-9.]+) ms on one CPU thread")
    shipped = table_row(section("predictor"), "lean-int8-fastood")
    p50_ms = float(shipped[2])  # decoder, precision, then p50 ms (batch 1)
    assert rounded(p50_ms, ms) == ms, f"README ~{ms} ms, benchmark p50 {p50_ms} ms"


def test_learned_readout_depth_errors_are_the_benchmark():
    in1, in2, edge1, edge2 = readme(
        r"within ([0-9.]+) / ([0-9.]+) um RMS of the true depth near the contact inside the view "
        r"on two sets of new presses and ([0-9.]+) / ([0-9.]+) um near the view's edges")
    bench = virtual_target_line("learned read-out")
    assert (rounded(bench["inside"][0], in1), rounded(bench["inside"][1], in2)) == (in1, in2)
    assert (rounded(bench["edges"][0], edge1), rounded(bench["edges"][1], edge2)) == (edge1, edge2)


def test_learned_readout_worst_edge_press_and_unseen_shapes_are_the_benchmark():
    (worst,) = readme(r"single presses near the edges up to (\d+) um")
    (shapes,) = readme(r"reads unseen shapes to (\d+) um")
    text = section("shading-virtual")
    rows = [line for line in text.splitlines() if line.startswith("| learned read-out of the GelSlim design")]
    assert len(rows) == 2, "expected the read-out's row in both press sets"
    edge_worst = max(float(r.strip().strip("|").split("|")[-2]) for r in rows)
    assert rounded(edge_worst, worst) == worst
    shape_rmse = float(table_row(text, "the learned read-out")[0])
    assert rounded(shape_rmse, shapes) == shapes


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
