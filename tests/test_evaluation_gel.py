"""The evaluation's frictionless domains under the neo-Hookean gel (``evaluate --gel neo-hookean``).

Reference-free check that the truth is what the report says: with ``gel="neo-hookean"`` the
primitives' displacements balance the neo-Hookean gel's internal forces (every free dof but the
contact nodes' z unloaded), with the linear gel they do not; the poses are drawn the same way, so
the same seed presses the same indenter first (later ones differ once a contact that one gel's
solve rejects is redrawn).
"""

from __future__ import annotations

import numpy as np
import pytest

from contact_checks import neo_hookean_imbalance

from tactile_deploy.training.evaluation import DomainUnavailable, markdown_table, simulate_domain


def test_neo_hookean_truth_is_a_neo_hookean_equilibrium_at_the_same_poses():
    linear = simulate_domain("primitives", 2, seed=31)
    neo = simulate_domain("primitives", 2, seed=31, gel="neo-hookean")
    assert neo.indenter[0] == linear.indenter[0]
    # the second pose (parallel lines) does not converge under the neo-Hookean gel: redrawn, and counted
    assert (linear.redrawn, neo.redrawn) == (0, 1) and linear.indenter[1] == "parallel_lines" != neo.indenter[1]
    share = {gel: [neo_hookean_imbalance(u, m) for u, m in zip(d.displacement_mm, d.contact_mask)]
             for gel, d in (("linear", linear), ("neo-hookean", neo))}
    print(f"largest unbalanced force / contact force: {share}")
    assert max(share["neo-hookean"]) < 1e-5     # float32 storage of a 1e-6 mm solve
    assert min(share["linear"]) > 1e-3          # the linear gel's second-order terms are unbalanced
    # the same first press under either gel: the deepest pixels of the two maps within 3 pixels
    a, b = linear.depth_mm[0], neo.depth_mm[0]
    assert np.unravel_index(a.argmax(), a.shape) == pytest.approx(np.unravel_index(b.argmax(), b.shape), abs=3)


def test_friction_domains_have_no_neo_hookean_truth_and_gels_are_checked():
    with pytest.raises(DomainUnavailable, match="frictionless"):
        simulate_domain("coulomb", 1, seed=1, gel="neo-hookean")
    with pytest.raises(DomainUnavailable, match="frictionless"):
        simulate_domain("stick", 1, seed=1, gel="neo-hookean")
    with pytest.raises(ValueError, match="unknown gel 'mooney'"):
        simulate_domain("primitives", 1, seed=1, gel="mooney")


def test_table_names_the_gel_of_the_frictionless_rows():
    m = {"contact_patch_rmse_um": 40.0, "all_node_rmse_um": 10.0, "lift_ratio": 3.0,
         "deepest_node_error_pct": {"mean": 0.5, "mean_abs": 2.0}}
    lift = dict(m, contact_patch_rmse_um=120.0, lift_ratio=1.0)
    row = {"n_samples": 4, "methods": {"model": m, "physics lift": lift}}
    report = {"models": {"model": "x.onnx"}, "gel": "neo-hookean",
              "domains": {"primitives": row, "large_strain": row}}
    table = markdown_table(report)
    assert "| primitives, frictionless, neo-Hookean gel (4) |" in table
    assert "| large strain (neo-Hookean), depth 0.6-1.2 mm (4) |" in table
    assert "neo-Hookean gel" not in markdown_table(dict(report, gel="linear"))
