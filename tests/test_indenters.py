"""Indenters: pose maps, envelopes against closed forms, the library, the shared STL set, errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pydantic
import pytest

from tactile_deploy.indenters import (
    AnalyticParaboloid,
    AnalyticSphere,
    ContactPose,
    Indenter,
    get_indenter,
    indenter_to_sensor,
    library_entry,
    list_indenters,
    load_indenter,
    sensor_to_indenter_xy,
)
from tactile_deploy.raster import RasterGrid, rasterize_triangles

SHARED_INDENTERS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "indenters"
PITCH = 0.025
# Facets of curved library surfaces deviate at most this much from the true surface (normal).
FACET_NORMAL_ERROR_MM = 2e-3


@pytest.fixture(autouse=True, scope="module")
def _private_cache(tmp_path_factory):
    """Keep the on-disk envelope cache of this module in a temporary folder."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TACTILE_DEPLOY_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))
        yield


def _shared_stls() -> list[Path]:
    if not SHARED_INDENTERS.is_dir():
        raise FileNotFoundError(
            f"shared indenter set not found at {SHARED_INDENTERS.resolve()}: the tests need "
            f"../shared/data/indenters next to the repository"
        )
    files = sorted(SHARED_INDENTERS.glob("*.stl"))
    if len(files) != 16:
        raise FileNotFoundError(f"expected 16 STL files in {SHARED_INDENTERS}, found {len(files)}")
    return files


# ---- pose ---------------------------------------------------------------------------------------


def test_sensor_to_indenter_by_hand():
    pose = ContactPose(x_mm=2.0, y_mm=-1.0, theta_deg=90.0, depth_mm=0.5)
    # Rotated 90 degrees counter-clockwise: the indenter's +x axis points along sensor +y.
    p = np.array([[2.0, -1.0], [2.0, 0.0], [1.0, -1.0], [4.0, -1.0], [3.0, 1.0]])
    q_expected = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, -2.0], [2.0, -1.0]])
    np.testing.assert_allclose(sensor_to_indenter_xy(p, pose), q_expected, atol=1e-12)
    pose30 = ContactPose(x_mm=0.0, y_mm=0.0, theta_deg=30.0)
    q = sensor_to_indenter_xy([[math.cos(math.radians(30)), math.sin(math.radians(30))]], pose30)
    np.testing.assert_allclose(q, [[1.0, 0.0]], atol=1e-12)
    # indenter_to_sensor inverts it, and lowers z by the depth.
    back = indenter_to_sensor(np.c_[q_expected, np.full(5, 0.2)], pose)
    np.testing.assert_allclose(back, np.c_[p, np.full(5, 0.2 - 0.5)], atol=1e-12)


def test_contact_pose_is_strict():
    with pytest.raises(pydantic.ValidationError):
        ContactPose(x_mm=0.0, depth=1.0)  # unknown field
    with pytest.raises(pydantic.ValidationError):
        ContactPose(depth_mm=float("nan"))
    with pytest.raises(pydantic.ValidationError):
        ContactPose(theta_deg="90")
    pose = ContactPose(depth_mm=1)
    assert pose.depth_mm == 1.0
    with pytest.raises(pydantic.ValidationError):
        pose.depth_mm = 2.0  # frozen


def test_rotation_direction_with_an_elongated_indenter():
    key = get_indenter("key_bit")  # blade along the indenter x axis, cuts up to 1.8 mm deep
    pose = ContactPose(x_mm=1.0, y_mm=2.0, theta_deg=90.0, depth_mm=0.5)
    along_sensor_y = np.array([[1.0, 2.0 + 6.4], [1.0, 2.0 - 10.0]])  # shoulders at x = 6.4, -10
    along_sensor_x = np.array([[1.0 + 6.4, 2.0], [1.0 - 10.0, 2.0]])
    np.testing.assert_allclose(key.intrusion_mm(along_sensor_y, pose), 0.5, atol=1e-9)
    assert np.all(key.intrusion_mm(along_sensor_x, pose) == -np.inf)


def test_mesh_in_sensor_frame_agrees_with_intrusion():
    # Independent route: move the mesh with a rigid transform and rasterise its lower surface
    # in the sensor frame; intrusion must be minus that surface's height.
    ind = get_indenter("hex_bolt_head")
    pose = ContactPose(x_mm=-3.0, y_mm=4.0, theta_deg=17.0, depth_mm=0.8)
    moved = ind.mesh_in_sensor_frame(pose)
    assert moved.vertices[:, 2].min() == pytest.approx(-0.8, abs=1e-12)
    grid = RasterGrid(-9.5, -2.5, 0.1, 131, 131)
    lower = rasterize_triangles(moved.triangles, grid, reduce="min").z_mm
    pts = grid.pixel_centres_mm().reshape(-1, 2)
    delta = ind.intrusion_mm(pts, pose).reshape(grid.ny, grid.nx)
    both = np.isfinite(delta) & (lower < 4.0 - 0.8 - 0.05)
    assert both.sum() > 5000
    # The chamfer has slope tan(30 deg); bilinear sampling of its kinked rim errs <= slope * pitch.
    np.testing.assert_allclose(delta[both], -lower[both], atol=0.6 * PITCH)
    np.testing.assert_allclose(np.median(np.abs(delta[both] + lower[both])), 0.0, atol=1e-6)


# ---- analytic indenters ---------------------------------------------------------------------------


def test_analytic_envelopes_by_hand():
    s = AnalyticSphere(5.0)
    q = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, -4.0], [5.0, 0.0], [6.0, 1.0]])
    np.testing.assert_allclose(s.envelope_mm(q), [0.0, 1.0, 2.0, np.inf, np.inf])
    assert s.footprint_radius_mm == pytest.approx(math.sqrt(4.0 * 6.0))  # h = 4 at r^2 = h(2R-h)
    small = AnalyticSphere(2.0)
    assert small.footprint_radius_mm == 2.0
    p = AnalyticParaboloid(10.0, max_relief_mm=1.0)
    np.testing.assert_allclose(p.envelope_mm([[2.0, 0.0], [0.0, 4.0], [5.0, 0.0]]), [0.2, 0.8, np.inf])
    assert p.footprint_radius_mm == pytest.approx(math.sqrt(20.0))
    pose = ContactPose(x_mm=1.0, y_mm=1.0, depth_mm=1.5)
    np.testing.assert_allclose(s.intrusion_mm([[4.0, 1.0], [1.0, 1.0], [9.0, 9.0]], pose), [0.5, 1.5, -np.inf])
    assert s.mesh.vertices[:, 2].min() == 0.0
    assert s.mesh.extents == pytest.approx([10.0, 10.0, 10.0], abs=1e-3)


def test_analytic_grid_reproduces_exact_envelope():
    for ind, curvature in ((AnalyticSphere(6.0), 1.0 / 6.0 * 27.0), (AnalyticParaboloid(8.0), 1.0 / 8.0)):
        rng = np.random.default_rng(0)
        q = rng.uniform(-7.0, 7.0, (20000, 2))
        exact = ind.envelope_mm(q)
        grid = ind.envelope_grid().sample_mm(q)
        both = np.isfinite(exact) & np.isfinite(grid)
        # Disagreement about the footprint only within two pixels of its edge.
        rim = ind.footprint_radius_mm
        r = np.hypot(q[:, 0], q[:, 1])
        assert np.all((np.isfinite(exact) == np.isfinite(grid)) | (np.abs(r - rim) < 2 * PITCH))
        # Bilinear interpolation error <= (h_xx + h_yy) p^2 / 8 <= curvature p^2 / 4, plus float32.
        np.testing.assert_allclose(grid[both], exact[both], atol=curvature * PITCH**2 / 4 + 1e-6)


@pytest.mark.parametrize("radius", [2.0, 4.0, 6.0])
def test_mesh_sphere_envelope_within_facet_error(radius):
    mesh_sphere = get_indenter(f"sphere_r{radius:g}")
    exact = AnalyticSphere(radius)
    rng = np.random.default_rng(1)
    q = rng.uniform(-radius, radius, (40000, 2))
    r = np.hypot(q[:, 0], q[:, 1])
    e_exact = exact.envelope_mm(q)
    e_mesh = mesh_sphere.envelope_mm(q)
    inner = r < 0.9 * radius
    inner &= np.isfinite(e_exact) & (e_exact < exact.max_relief_mm - 0.05)
    cos_slope = np.sqrt(radius**2 - r[inner] ** 2) / radius
    curvature = 1.0 / (radius * cos_slope**3)  # largest second derivative of the cap
    err = e_mesh[inner] - e_exact[inner]
    # Facets lie inside the sphere: the mesh envelope is never below the exact one.
    assert err.min() > -1e-6
    assert np.all(err <= FACET_NORMAL_ERROR_MM / cos_slope + curvature * PITCH**2 / 4 + 1e-6)
    assert abs(np.median(err)) < 2e-3


def test_envelope_grid_sampling_matches_torch_grid_sample():
    import torch

    F = torch.nn.functional
    for name in ("gear", "sphere_r4", "analytic_sphere_r3"):
        ind = get_indenter(name)
        g = ind.envelope_grid()
        rng = np.random.default_rng(2)
        q = rng.uniform(-12.0, 12.0, (5000, 2))
        q[:500] = np.round(q[:500] / PITCH) * PITCH  # exactly on pixel centres
        h = torch.tensor(g.finite_heights_mm(), dtype=torch.float64)[None, None]
        uv = torch.as_tensor(g.normalized_coordinates(q))[None, None]
        e = F.grid_sample(h, uv, mode="bilinear", padding_mode="border", align_corners=True)[0, 0, 0]
        e = torch.where(e > g.max_relief_mm, torch.inf, e).numpy()
        ref = g.sample_mm(q)
        assert np.isfinite(ref).sum() > 200
        # Only on a pixel line at the footprint edge may rounding decide between in and out.
        uv_px = (q - [g.x0_mm, g.y0_mm]) / g.pitch_mm
        on_line = np.any(np.abs(uv_px - np.round(uv_px)) < 1e-6, axis=1)
        agree = np.isfinite(e) == np.isfinite(ref)
        assert np.all(agree | on_line) and agree.sum() >= len(q) - 3
        both = np.isfinite(e) & np.isfinite(ref)
        np.testing.assert_allclose(e[both], ref[both], atol=1e-9)
        if name != "analytic_sphere_r3":
            np.testing.assert_array_equal(ref, ind.envelope_mm(q))


def test_intrusion_input_errors():
    ind = AnalyticSphere(3.0, max_relief_mm=2.0)
    with pytest.raises(ValueError, match=r"depth_mm=2.5 exceeds max_relief_mm=2.0"):
        ind.intrusion_mm(np.zeros((3, 2)), ContactPose(depth_mm=2.5))
    with pytest.raises(ValueError, match=r"points_xy_sensor_mm must have shape \(k, 2\)"):
        ind.intrusion_mm(np.zeros((3, 3)), ContactPose(depth_mm=1.0))
    with pytest.raises(TypeError, match="ContactPose"):
        ind.intrusion_mm(np.zeros((3, 2)), {"depth_mm": 1.0})
    with pytest.raises(ValueError, match="radius_mm must be > 0"):
        AnalyticSphere(-1.0)


def test_indenter_construction_errors():
    import trimesh

    plate = trimesh.creation.box(extents=[150.0, 150.0, 2.0])
    with pytest.raises(ValueError, match="'plate': pitch_mm must be > 0, got 0.0"):
        Indenter(plate, "plate", pitch_mm=0.0)
    with pytest.raises(TypeError, match="mesh must be a trimesh.Trimesh, got ndarray"):
        Indenter(np.zeros((3, 3)), "points")
    # A 150 mm flat plate would need a 6,000 x 6,000 grid at 0.025 mm: refused with advice.
    with pytest.raises(ValueError, match=r"'plate'.*6005 x 6005 envelope grid.*larger pitch_mm"):
        Indenter(plate, "plate", cache_dir=None).envelope_grid()
    coarse = Indenter(plate, "plate", cache_dir=None, pitch_mm=0.5).envelope_grid()
    assert np.all(coarse.heights_mm[2:-2, 2:-2] == 0.0)


# ---- the procedural library ---------------------------------------------------------------------


def test_library_has_enough_distinct_shapes():
    primitives, novel = list_indenters("primitive"), list_indenters("novel")
    assert len(primitives) >= 16 and len(novel) >= 6
    assert list_indenters() == primitives + novel
    with pytest.raises(ValueError, match="kind must be one of"):
        list_indenters("tool")


@pytest.mark.parametrize("name", list_indenters())
def test_library_indenter_is_valid_and_fits_the_pad(name):
    ind = get_indenter(name)
    mesh = ind.mesh
    assert ind.kind == library_entry(name).kind
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert all(part.volume > 0 for part in mesh.split(only_watertight=False))
    assert mesh.vertices[:, 2].min() == 0.0
    lo, hi = mesh.bounds
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-12)
    heights = ind.envelope_grid().heights_mm
    finite = np.isfinite(heights)
    assert abs(heights[finite].min()) < 1e-9  # the envelope reaches the lowest point
    assert finite.sum() * PITCH**2 > 0.3  # a pressing surface of some area (mm^2)
    assert ind.footprint_radius_mm <= 12.0  # pressing surface within 12 mm of the origin
    assert np.hypot(mesh.vertices[:, 0], mesh.vertices[:, 1]).max() < 17.5  # whole body on the pad
    # Deterministic: built again, the mesh is identical.
    again = Indenter(library_entry(name).build(), name, ind.kind)
    assert again.content_hash == ind.content_hash


def _cube_corner_height(q):
    # Faces through the lowest corner have outward normals -R e_i, with R mapping (1,1,1) to z.
    import trimesh

    rot = trimesh.geometry.align_vectors([-1.0, -1.0, -1.0], [0.0, 0.0, -1.0])[:3, :3]
    normals = -rot.T  # rows: outward normals of the three faces at the corner
    return np.max(-(q @ normals[:, :2].T) / normals[:, 2], axis=1)


CLOSED_FORMS = {
    # name: (envelope h(q) in the indenter frame, region where it holds, slope bound)
    "cone": (lambda q: np.hypot(q[:, 0], q[:, 1]), lambda q: np.hypot(*q.T) < 3.9, 1.0),
    "pyramid": (lambda q: np.abs(q).max(axis=1), lambda q: np.abs(q).max(axis=1) < 3.9, 1.0),
    "flat_punch": (lambda q: 0 * q[:, 0], lambda q: np.hypot(*q.T) < 2.9, 0.0),
    "cylinder_side": (lambda q: 3 - np.sqrt(9 - q[:, 0] ** 2), lambda q: (np.abs(q[:, 0]) < 2.6) & (np.abs(q[:, 1]) < 6.9), 2.0),
    "torus": (lambda q: 1.2 - np.sqrt(np.maximum(1.44 - (np.hypot(*q.T) - 4) ** 2, 0)), lambda q: np.abs(np.hypot(*q.T) - 4) < 1.0, 1.7),
    "wave": (lambda q: 0.4 * (1 - np.cos(2 * np.pi * q[:, 0] / 3)), lambda q: np.abs(q).max(axis=1) < 5.9, 0.9),
    "cube_edge": (lambda q: np.abs(q[:, 0]), lambda q: (np.abs(q[:, 0]) < 3.9) & (np.abs(q[:, 1]) < 3.9), 1.0),
    "cube_corner": (_cube_corner_height, lambda q: np.hypot(*q.T) < 2.4, 1.5),
}


@pytest.mark.parametrize("name", sorted(CLOSED_FORMS))
def test_library_envelope_matches_closed_form(name):
    h, region, slope = CLOSED_FORMS[name]
    ind = get_indenter(name)
    rng = np.random.default_rng(3)
    q = rng.uniform(-8.0, 8.0, (60000, 2))
    q = q[region(q)]
    exact = h(q)
    got = ind.envelope_mm(q)
    assert np.all(np.isfinite(got))
    err = np.abs(got - exact)
    # Away from kinks the error is facet error plus interpolation; within a pixel of a kink
    # (apex, ridge, crest) bilinear sampling cuts the corner by at most slope * pitch.
    assert err.max() <= FACET_NORMAL_ERROR_MM * 3 + slope * PITCH
    assert np.quantile(err, 0.9) <= FACET_NORMAL_ERROR_MM * 3


# ---- the shared STL set (independent test set) -------------------------------------------------


@pytest.mark.parametrize("index", range(16))
def test_shared_stl_loads_feature_down(index):
    import trimesh

    path = _shared_stls()[index]
    ind = load_indenter(path, pressing_face="top")
    raw = trimesh.load(path, force="mesh")
    assert ind.kind == "file" and ind.name == path.stem
    # Turned over: the file's top (the feature) is now the lowest point, the base 20 mm up.
    assert ind.mesh.vertices[:, 2].max() == pytest.approx(np.ptp(raw.vertices[:, 2]), abs=1e-9)
    # Footprint within 1 mm of relief, against bounds from the file's vertices (independent of
    # the rasteriser): it lies within the hull of the facets that reach that band, contains the
    # hull of the vertices inside the band when the feature is convex, and is far smaller than
    # the 16 x 16 mm base.
    from scipy.spatial import ConvexHull

    g = ind.envelope_grid()
    area = np.sum(g.heights_mm <= 1.0) * PITCH**2
    z_top = raw.vertices[:, 2].max()
    near = raw.vertices[:, 2] >= z_top - 1.0
    touching = raw.faces[near[raw.faces].any(axis=1)]
    outer = ConvexHull(raw.vertices[np.unique(touching), :2]).volume
    assert 0 < area <= outer * 1.01 + 0.5
    assert area < 0.8 * 16 * 16
    if path.stem in ("cylinder", "hexagon", "triangle", "prism", "flat_slab", "sphere", "sphere2", "cone"):
        inner = ConvexHull(raw.vertices[near, :2]).volume
        assert area >= inner * 0.97 - 0.2


def test_shared_sphere_matches_its_fitted_radius():
    # The sphere's relief at the edge of the 1 mm footprint gives R = (a^2 + 1) / 2 for a
    # footprint radius a; the envelope must follow that cap R - sqrt(R^2 - r^2).
    ind = load_indenter(_shared_stls()[[p.stem for p in _shared_stls()].index("sphere")])
    g = ind.envelope_grid()
    a = math.sqrt(np.sum(g.heights_mm <= 1.0) * PITCH**2 / math.pi)
    radius = (a * a + 1.0) / 2.0
    r = np.linspace(0.0, 0.9 * a, 50)
    q = np.c_[r, np.zeros_like(r)]
    np.testing.assert_allclose(ind.envelope_mm(q), radius - np.sqrt(radius**2 - r**2), atol=0.03)


# ---- loading, registry and cache ---------------------------------------------------------------


def _cone_stl(path: Path, scale: float = 1.0) -> Path:
    import trimesh

    cone = trimesh.creation.cone(radius=3.0, height=4.0, sections=64)  # apex up at z = 4
    cone.apply_scale(scale)
    cone.export(path)
    return path


def test_pressing_face_top_turns_the_file_over(tmp_path):
    path = _cone_stl(tmp_path / "cone_up.stl")
    top = load_indenter(path, pressing_face="top")
    bottom = load_indenter(path, pressing_face="bottom", name="base_down")
    assert bottom.name == "base_down"
    # Apex first: envelope = (4 / 3) r; base first: a flat disc.
    np.testing.assert_allclose(top.envelope_mm([[0.0, 0.0], [1.5, 0.0]]), [0.0, 2.0], atol=0.01)
    np.testing.assert_allclose(bottom.envelope_mm([[0.0, 0.0], [1.5, 0.0]]), [0.0, 0.0], atol=1e-9)
    metres = load_indenter(_cone_stl(tmp_path / "cone_m.stl", 1e-3), scale_to_mm=1000.0)
    np.testing.assert_allclose(metres.envelope_mm([[1.5, 0.0]]), [2.0], atol=0.01)


def test_load_errors_name_file_and_expectation(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.stl does not exist"):
        load_indenter(tmp_path / "nope.stl")
    (tmp_path / "a.step").write_text("solid")
    with pytest.raises(ValueError, match=r"a.step: expected a mesh file with suffix .stl, .obj, .ply, found '.step'"):
        load_indenter(tmp_path / "a.step")
    (tmp_path / "empty.stl").write_bytes(b"")
    with pytest.raises(ValueError, match="empty.stl: file is empty"):
        load_indenter(tmp_path / "empty.stl")
    (tmp_path / "junk.obj").write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match="junk.obj: expected a triangle mesh"):
        load_indenter(tmp_path / "junk.obj")
    (tmp_path / "points.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    )
    with pytest.raises(ValueError, match="points.ply: expected a triangle mesh"):
        load_indenter(tmp_path / "points.ply")
    metres = _cone_stl(tmp_path / "metres.stl", 1e-3)
    with pytest.raises(ValueError, match=r"metres.stl: largest extent is 0.006 mm .* between 0.2 and 300 mm.*scale_to_mm"):
        load_indenter(metres)
    with pytest.raises(ValueError, match="pressing_face must be one of"):
        load_indenter(metres, pressing_face="side")
    with pytest.raises(ValueError, match="scale_to_mm must be a finite number > 0"):
        load_indenter(metres, scale_to_mm=0.0)


def test_get_indenter_by_name_analytic_name_and_path(tmp_path):
    s = get_indenter("analytic_sphere_r5")
    assert isinstance(s, AnalyticSphere) and s.radius_mm == 5.0 and s.kind == "analytic"
    p = get_indenter("analytic_paraboloid_r2p5")
    assert isinstance(p, AnalyticParaboloid) and p.radius_mm == 2.5
    assert get_indenter("analytic_sphere_r2.35").radius_mm == 2.35
    assert get_indenter("gear") is get_indenter("gear")  # built once
    f = get_indenter(_cone_stl(tmp_path / "cone.stl"))
    assert f.kind == "file" and f.name == "cone"
    with pytest.raises(ValueError, match=r"unknown indenter 'spehre_r2'.*sphere_r2, sphere_r4"):
        get_indenter("spehre_r2")


def test_envelope_grid_disk_cache(tmp_path, monkeypatch, caplog):
    mesh = library_entry("ring").build()
    first = Indenter(mesh, "ring", cache_dir=tmp_path)
    g1 = first.envelope_grid()
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1 and not list(tmp_path.glob(".*partial*"))
    second = Indenter(mesh, "ring", cache_dir=tmp_path)
    monkeypatch.setattr(Indenter, "_build_grid", lambda self: pytest.fail("grid was rebuilt"))
    g2 = second.envelope_grid()
    np.testing.assert_array_equal(g1.heights_mm, g2.heights_mm)
    assert (g1.x0_mm, g1.y0_mm, g1.pitch_mm) == (g2.x0_mm, g2.y0_mm, g2.pitch_mm)
    # A different pitch is a different cache entry; a damaged file is rebuilt, not trusted.
    monkeypatch.undo()
    files[0].write_bytes(b"damaged")
    third = Indenter(mesh, "ring", cache_dir=tmp_path)
    np.testing.assert_array_equal(third.envelope_grid().heights_mm, g1.heights_mm)
    assert "ignoring unreadable envelope cache" in caplog.text
    Indenter(mesh, "ring", cache_dir=tmp_path, pitch_mm=0.05).envelope_grid()
    assert len(list(tmp_path.glob("*.npz"))) == 2


# ---- tools ----------------------------------------------------------------------------------------


def test_contact_sheet_draws_pressing_surfaces(tmp_path):
    from PIL import Image

    from tactile_deploy.indenters.contact_sheet import envelope_image, render_contact_sheet

    # Panels: 0.125 mm pixels over +-12.5 mm; the ring (radii 2.5-4 mm) is hollow, the punch not.
    ring = envelope_image(get_indenter("ring"), relief_mm=1.0, pixels=201)
    punch = envelope_image(get_indenter("flat_punch"), relief_mm=1.0, pixels=201)
    assert ring.mask[100, 100] and not punch.mask[100, 100] and punch[100, 100] == 0.0
    assert ring[100, 100 + 26] == 0.0  # 3.25 mm to the right
    assert np.sum(~ring.mask) * 0.125**2 == pytest.approx(np.pi * (4.0**2 - 2.5**2), rel=0.05)
    out = render_contact_sheet(tmp_path / "sheet.png", names=["flat_punch", "ring"], columns=2,
                               pixels_per_panel=60)
    assert Image.open(out).size[0] > 200


def test_benchmark_runs_at_small_settings():
    from tactile_deploy.indenters.benchmark import run

    results = run(small=True)
    assert set(results) >= {"raster_10k_min", "raster_pad_max", "intrusion_1100"}
    assert all(r["min_ms"] > 0 for r in results.values())


def _polygon_signed_distance(q: np.ndarray, corners: np.ndarray):
    """Signed distance (k,) of points q (k, 2) to a convex polygon (corners (m, 2) in
    counter-clockwise order), negative inside, and the outward unit gradient (k, 2)."""
    best = np.full(len(q), np.inf)
    grad = np.zeros((len(q), 2))
    inside = np.ones(len(q), bool)
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        ab = b - a
        t = np.clip((q - a) @ ab / (ab @ ab), 0.0, 1.0)
        diff = q - (a + t[:, None] * ab)
        dist = np.linalg.norm(diff, axis=1)
        closer = dist < best
        best = np.where(closer, dist, best)
        grad = np.where(closer[:, None], diff / np.maximum(dist, 1e-300)[:, None], grad)
        inside &= ab[0] * (q[:, 1] - a[1]) - ab[1] * (q[:, 0] - a[0]) > 0
    return np.where(inside, -best, best), np.where(inside[:, None], -grad, grad)


def test_coverage_distance_follows_a_punch_outline():
    """The hexagonal punch's outline (a wall in the resolved solver) against the hexagon
    itself: the signed distance from its corners (read from the indenter's mesh, not from the
    rasterised envelope) at 4,000 points within 0.15 mm of the rim, at a rotated pose."""
    from scipy.spatial import ConvexHull

    ind = get_indenter("hexagon")
    pose = ContactPose(x_mm=1.0, y_mm=-0.5, theta_deg=37.0, depth_mm=0.3)
    v = np.asarray(ind.mesh.vertices)
    face = v[np.abs(v[:, 2] - v[:, 2].min()) < 1e-9, :2]
    corners = face[ConvexHull(face).vertices]  # counter-clockwise, indenter frame
    rng = np.random.default_rng(3)
    radius = rng.uniform(2.8, 3.7, 20000)
    angle = rng.uniform(0.0, 2 * math.pi, 20000)
    q = np.stack([radius * np.cos(angle), radius * np.sin(angle)], 1)
    ref, ref_grad = _polygon_signed_distance(q, corners)
    keep = np.abs(ref) < 0.15
    q, ref, ref_grad = q[keep][:4000], ref[keep][:4000], ref_grad[keep][:4000]
    c, s = math.cos(math.radians(pose.theta_deg)), math.sin(math.radians(pose.theta_deg))
    p = np.stack([c * q[:, 0] - s * q[:, 1] + pose.x_mm, s * q[:, 0] + c * q[:, 1] + pose.y_mm], 1)
    dist, grad = ind.coverage_distance_mm(p, pose)
    err = dist - ref
    pitch = ind.envelope_grid().pitch_mm
    assert np.abs(err).max() <= pitch  # the rasterised staircase is within a pixel of the line
    assert np.abs(err).mean() <= 0.3 * pitch
    ref_grad_sensor = np.stack([c * ref_grad[:, 0] - s * ref_grad[:, 1],
                                s * ref_grad[:, 0] + c * ref_grad[:, 1]], 1)
    cosine = np.einsum("ki,ki->k", grad, ref_grad_sensor)
    # the corners of the hexagon (120 degrees) turn the gradient; along the edges it is the
    # edge's normal
    assert np.median(cosine) > math.cos(math.radians(3.0))
    assert np.mean(cosine > math.cos(math.radians(15.0))) > 0.95
    # the sign agrees with where the envelope is defined (the cells whose four corner pixels
    # are inside the hexagon: up to a pixel's diagonal inside it), away from the staircase
    finite = np.isfinite(ind.intrusion_mm(p, pose))
    clear = np.abs(ref) > 1.5 * pitch
    assert np.array_equal(finite[clear], (dist < 0)[clear])


def test_analytic_coverage_distance_is_exact():
    ball = AnalyticSphere(2.0)
    pose = ContactPose(x_mm=0.5, y_mm=0.2, theta_deg=10.0, depth_mm=0.5)
    p = np.array([[0.5, 0.2 + 2.5], [0.5 + 1.0, 0.2], [0.5, 0.2]])
    dist, grad = ball.coverage_distance_mm(p, pose)
    np.testing.assert_allclose(dist, [0.5, -1.0, -2.0], atol=1e-12)
    np.testing.assert_allclose(grad[:2], [[0.0, 1.0], [1.0, 0.0]], atol=1e-12)
