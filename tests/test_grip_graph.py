"""The shipped graph for gels that grip (`exported/gelslim_mesh_grip.onnx`) against the contact FEM.

A depth map does not show whether the gel slid on the object: the frictionless graph
(`gelslim_mesh.onnx`) and the graph trained on Coulomb and sticking contact read the same map
into different lateral motion of the sensing surface. Here both read fresh contacts simulated by
the project's FEM (`training/evaluation.py`'s domains, a seed no training run uses), and each must
be the better one on the contact law it was trained for, by the margins the evaluation measured
on 256 contacts per domain (docs/predictor.md): sticking contact 26.7 against 279.2 um on the
contact patch; frictionless 21.0 against 216.4 um.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
GRIP = ROOT / "exported" / "gelslim_mesh_grip.onnx"
SHIPPED = ROOT / "exported" / "gelslim_mesh.onnx"


def test_grip_graph_keeps_the_contract_and_its_card(pad):
    from tactile_deploy.checksums import file_sha256
    from tactile_deploy.onnx_runtime.contract import check_model_contract

    check_model_contract(GRIP, pad.content_hash, pad.n_nodes)
    card = json.loads(GRIP.with_suffix(".json").read_text())
    assert card["files"]["onnx_sha256"] == file_sha256(GRIP)
    # trained on the friction laws it is for, and its card says which gel it is for
    assert "coulomb + stick contact" in card["limitations"][0]
    assert any("gels that grip" in line for line in card["limitations"])
    report = json.loads((ROOT / card["evaluation"]["report"]).read_text())
    rows = {d: report["domains"][d]["methods"]["grip"]["contact_patch_rmse_um"] for d in ("coulomb", "stick", "primitives")}
    assert rows["coulomb"] <= 50 and rows["stick"] <= 50 and rows["primitives"] > 100


@pytest.mark.slow
@pytest.mark.parametrize("domain, better, worse", [("stick", GRIP, SHIPPED), ("primitives", SHIPPED, GRIP)])
def test_each_graph_is_right_on_its_own_contact_law(pad, domain, better, worse):
    from tactile_deploy.training.evaluation import onnx_displacements, simulate_domain
    from tactile_deploy.training.metrics import mesh_metrics

    data = simulate_domain(domain, 8, seed=31)
    patch = {}
    for path in (better, worse):
        pred = onnx_displacements(path, data.depth_mm)
        patch[path.name] = mesh_metrics(pred, data.displacement_mm, data.contact_mask, pad.n_plane)["contact_patch_rmse_um"]
    print(domain, patch)
    assert patch[better.name] <= 45.0, patch
    assert patch[worse.name] >= 4.0 * patch[better.name], patch


def test_friction_domains_on_unseen_shapes_press_the_shared_meshes_under_coulomb_friction(shared_data, pad):
    """The evaluation's extra domains for gels that grip (run only when named): `unseen_shapes_coulomb`
    presses the shared STL indenters, `noisy_coulomb` adds the sensor noise to Coulomb contacts."""
    from tactile_deploy.training.evaluation import ALL_DOMAINS, DOMAINS, simulate_domain

    assert "unseen_shapes_coulomb" not in DOMAINS and "unseen_shapes_coulomb" in ALL_DOMAINS
    shared = shared_data / "indenters"
    data = simulate_domain("unseen_shapes_coulomb", 3, seed=5, shared_dir=shared)
    stems = {p.stem for p in shared.glob("*.stl")}
    assert set(data.indenter) <= stems and len(data.depth_mm) == 3
    noisy = simulate_domain("noisy_coulomb", 2, seed=5)
    clean_like = simulate_domain("coulomb", 2, seed=5)
    assert noisy.depth_mm.shape == clean_like.depth_mm.shape
    # the image corners lie outside the pad's disc: 0 in a clean map, the 10 um white noise in a noisy one
    corner = np.s_[:, :8, :8]
    assert np.all(clean_like.depth_mm[corner] == 0) and np.std(noisy.depth_mm[corner]) > 0.005
    with pytest.raises(ValueError, match="unknown domain"):
        simulate_domain("coulomb_everything", 1, seed=5)


def test_card_says_which_gel_a_graph_is_for_from_its_training_laws():
    """The card's limitation line: a graph trained without frictionless contact is for gels that
    grip, one trained on frictionless contact only for gels that slide, a mixture of both neither."""
    from tactile_deploy.training.card import limitations

    def lines(friction):
        cfg = {"data": {"synthetic": {"friction": friction, "depth_min_mm": 0.2, "depth_max_mm": 1.2}}}
        text = " ".join(limitations(cfg, "surface-fastood"))
        return "gels that grip the object" in text, "gels that slide freely" in text

    assert lines(["coulomb", "stick"]) == (True, False)
    assert lines("stick") == (True, False)
    assert lines("frictionless") == (False, True)
    assert lines(["frictionless", "stick"]) == (False, False)
