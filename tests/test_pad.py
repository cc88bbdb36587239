"""The pad mesh: size, determinism and frozen hash, quality, node sets, parametric shapes, export."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from tactile_deploy.pad import asset as asset_mod
from tactile_deploy.pad.geometry import PadGeometry
from tactile_deploy.pad.mesh import build_pad_mesh, content_hash
from tactile_deploy.pad.meshing import signed_volumes
from tactile_deploy.pad.quality import quality_report


def test_node_count_matches_the_paper_within_3_percent(pad):
    assert abs(pad.n_nodes - 5415) / 5415 <= 0.03
    assert pad.n_plane * 5 == pad.n_nodes


def test_regenerated_mesh_equals_the_frozen_asset(pad):
    fresh = asset_mod.regenerate_shipped("gelslim")
    np.testing.assert_allclose(fresh.vertices, pad.vertices, atol=1e-9)
    np.testing.assert_array_equal(fresh.tets, pad.tets)
    assert fresh.content_hash == pad.content_hash == asset_mod.load_pad_card().content_hash


def test_quality_no_inverted_or_sliver_tets(pad):
    q = quality_report(pad.vertices, pad.tets)
    print(q)
    assert q.n_inverted == 0 and q.n_slivers == 0
    assert q.min_dihedral_deg > 25.0 and q.worst_aspect_ratio < 2.0
    card = asset_mod.load_pad_card()
    assert card.min_dihedral_deg == pytest.approx(q.min_dihedral_deg, abs=1e-3)


def test_node_sets_lie_on_their_surfaces(pad):
    v = pad.vertices
    assert np.allclose(v[pad.backplate_nodes, 2], -3.0)
    assert np.allclose(v[pad.sensing_nodes, 2], 0.0)
    np.testing.assert_allclose(np.hypot(v[pad.side_nodes, 0], v[pad.side_nodes, 1]), 17.5)
    # every node on z = 0 is a sensing node, every node at r = R a side node
    assert set(np.flatnonzero(np.isclose(v[:, 2], 0.0))) == set(pad.sensing_nodes)
    assert set(np.flatnonzero(np.isclose(np.hypot(v[:, 0], v[:, 1]), 17.5))) == set(pad.side_nodes)


def test_boundary_surface_is_closed_and_encloses_the_tets(pad):
    import trimesh

    surface = trimesh.Trimesh(pad.vertices, pad.boundary_faces, process=False)
    assert surface.is_watertight
    assert surface.volume == pytest.approx(signed_volumes(pad.vertices, pad.tets).sum(), rel=1e-10)
    # the polygonal disc is within 0.1 % of the cylinder's volume
    assert surface.volume == pytest.approx(np.pi * 17.5**2 * 3.0, rel=1e-3)


def test_modified_asset_is_refused(tmp_path, monkeypatch):
    for suffix in (".npz", ".json"):
        shutil.copy(asset_mod.ASSET_DIR / f"gelslim_v1{suffix}", tmp_path / f"gelslim_v1{suffix}")
    with np.load(tmp_path / "gelslim_v1.npz") as d:
        arrays = dict(d)
    arrays["vertices"][10, 2] += 1e-3
    np.savez(tmp_path / "gelslim_v1.npz", **arrays)
    monkeypatch.setattr(asset_mod, "ASSET_DIR", tmp_path)
    monkeypatch.setattr(asset_mod, "_LOADED", {})
    with pytest.raises(ValueError, match="content hash"):
        asset_mod.load_pad("gelslim")


def test_content_hash_ignores_last_bit_noise_but_not_changes(pad):
    h = content_hash(pad.vertices, pad.tets)
    assert content_hash(pad.vertices * (1 + 1e-15), pad.tets) == h
    moved = pad.vertices.copy()
    moved[0, 0] += 1e-5
    assert content_hash(moved, pad.tets) != h


@pytest.mark.parametrize(
    "geometry",
    [
        PadGeometry(name="box", shape="box", width_mm=30, length_mm=20, edge_mm=1.0, n_layers=3),
        PadGeometry(name="dome", radius_mm=12, dome_height_mm=0.8, edge_mm=1.0, n_layers=3),
    ],
)
def test_other_pads_are_a_config_change(geometry):
    mesh = build_pad_mesh(geometry)
    q = quality_report(mesh.vertices, mesh.tets)
    assert q.ok, str(q)
    top = mesh.vertices[mesh.sensing_nodes]
    np.testing.assert_allclose(top[:, 2], geometry.top_height_mm(top[:, 0], top[:, 1]), atol=1e-12)
    assert np.allclose(mesh.vertices[mesh.backplate_nodes, 2], -geometry.thickness_mm)
    assert quality_report(mesh.vertices, mesh.tets).n_inverted == 0
    assert build_pad_mesh(geometry).content_hash == mesh.content_hash  # deterministic


def test_bad_geometry_is_refused():
    with pytest.raises(ValueError, match="dome_height_mm"):
        PadGeometry(dome_height_mm=3.5)


def test_export_volume_and_surface_round_trip(pad, tmp_path):
    import meshio
    import trimesh

    from tactile_deploy.pad.export import export_surface, export_volume

    deformed = pad.vertices.copy()
    deformed[pad.sensing_nodes, 2] -= 0.1
    for name in ("pad.vtu", "pad.msh"):
        export_volume(pad, tmp_path / name, deformed)
        back = meshio.read(tmp_path / name)
        np.testing.assert_allclose(back.points, deformed, atol=1e-9)
        np.testing.assert_array_equal(back.cells_dict["tetra"], pad.tets)
    vtu = meshio.read(tmp_path / "pad.vtu")
    assert vtu.point_data["set_sensing"].sum() == pad.n_plane
    np.testing.assert_allclose(vtu.point_data["displacement_mm"][pad.sensing_nodes, 2], -0.1)
    export_surface(pad, tmp_path / "pad.stl")
    assert trimesh.load(tmp_path / "pad.stl").is_watertight
    with pytest.raises(ValueError, match="format"):
        export_volume(pad, tmp_path / "pad.xyz")
    assert not list(tmp_path.glob(".*partial*"))  # nothing half-written left behind


def test_exported_glb_is_in_metres_and_y_up_as_gltf_says(pad, tmp_path):
    """glTF: metres, +y up. Read back by trimesh (its glTF loader, not our writer), the pad's
    sensing face (sensor z = 0, the top) must be the highest y, and the 35 mm disc must span
    0.035 in x and in z."""
    import trimesh

    from tactile_deploy.pad.export import export_surface

    export_surface(pad, tmp_path / "pad.glb")
    back = trimesh.load(tmp_path / "pad.glb", force="mesh")
    lo, hi = back.bounds
    np.testing.assert_allclose(hi - lo, [0.035, 0.003, 0.035], atol=2e-4)
    top_mm = pad.vertices[:, 2].max()
    np.testing.assert_allclose(hi[1], top_mm * 1e-3, atol=1e-9)
    np.testing.assert_allclose(lo[1], pad.vertices[:, 2].min() * 1e-3, atol=1e-9)
