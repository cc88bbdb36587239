"""Batched torch contact path against the CPU simulator (the reference) and independent methods.

CPU torch, float64. Every batched result is compared with ``ContactSimulator`` +
``DepthCamera.render`` (same physics, numpy/scipy code), the dense-Cholesky operators with a
sparse LU solve, the envelope sampling with ``torch.nn.functional.grid_sample``.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

torch = pytest.importorskip("torch")

from tactile_deploy.camera.depth import DepthCamera  # noqa: E402
from tactile_deploy.training.simulation.depth_torch import TorchDepthCamera, TriangleRasterizer  # noqa: E402
from tactile_deploy.training.simulation.batched import (  # noqa: E402
    BatchedContact,
    BatchedContactSimulator,
    EnvelopeBank,
    compute_operators_torch,
    contact_columns,
    poses_tensor,
)
from tactile_deploy.fem.contact import ContactSolveError  # noqa: E402
from tactile_deploy.fem.elasticity import assemble_stiffness_numpy  # noqa: E402
from tactile_deploy.fem.material import Material  # noqa: E402
from tactile_deploy.fem.simulator import ContactSimulator  # noqa: E402
from tactile_deploy.indenters import ContactPose, get_indenter  # noqa: E402
from tactile_deploy.pad.geometry import PadGeometry  # noqa: E402
from tactile_deploy.pad.mesh import build_pad_mesh  # noqa: E402
from tactile_deploy.raster import rasterize_triangles  # noqa: E402

# Spheres, a flat punch, lines, dots, an analytic sphere and novel objects.
INDENTERS = ("sphere_r2", "sphere_r4", "flat_punch", "parallel_lines", "triangle_prism",
             "dot_array", "analytic_sphere_r3", "gear", "coin", "key_bit")
# A 10 mm pad (347 sensing nodes): its operators take a second or two on the CPU.
SMALL = PadGeometry(name="small", radius_mm=10.0, edge_mm=1.0)


@pytest.fixture(scope="module")
def bank():
    return EnvelopeBank.from_indenters([get_indenter(n) for n in INDENTERS])


def random_poses(rng, n, radius_mm, depth_mm=(0.2, 1.2)):
    r = radius_mm * np.sqrt(rng.random(n))
    phi = 2 * np.pi * rng.random(n)
    return [ContactPose(x_mm=float(r[i] * np.cos(phi[i])), y_mm=float(r[i] * np.sin(phi[i])),
                        theta_deg=float(360 * rng.random()),
                        depth_mm=float(rng.uniform(*depth_mm))) for i in range(n)]


def assert_matches_cpu(cpu: ContactSimulator, batched, bank, index, poses):
    cam = DepthCamera()
    res = batched.solve(bank, torch.as_tensor(index), poses_tensor(poses))
    for i, pose in enumerate(poses):
        try:
            ref = cpu.solve(get_indenter(INDENTERS[index[i]]), pose)
        except ContactSolveError:  # the CPU path gives up: the batched path flags the sample
            assert not res.solved[i] and torch.isnan(res.displacements_mm[i]).all()
            continue
        assert res.solved[i]
        delta = res.intrusion_mm[i].numpy()
        np.testing.assert_array_equal(np.isfinite(delta), np.isfinite(ref.intrusion_mm))
        fin = np.isfinite(delta)
        np.testing.assert_allclose(delta[fin], ref.intrusion_mm[fin], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(res.contact_mask[i].numpy(), ref.contact_mask)
        np.testing.assert_allclose(res.contact_forces_n[i].numpy(), ref.contact_forces_n,
                                   rtol=0, atol=1e-10 * max(1.0, np.abs(ref.contact_forces_n).max()))
        np.testing.assert_allclose(res.displacements_mm[i].numpy(), ref.displacements_mm,
                                   rtol=0, atol=1e-10)
        assert float(res.force_n[i]) == pytest.approx(ref.force_n, rel=1e-10, abs=1e-12)
        depth_ref = cam.render(cpu.mesh, ref.vertices_mm).depth_mm  # float32
        np.testing.assert_allclose(res.depth_mm[i].numpy(), depth_ref, rtol=0, atol=1e-6)
    return res


# ----------------------------------------------------------------------------- operators
@pytest.fixture(scope="module")
def small_mesh():
    return build_pad_mesh(SMALL)


_SMALL_CPU: dict = {}


def small_cpu(mesh, friction) -> ContactSimulator:
    """CPU simulator of the small pad (nu = 0.48), operators computed once per module."""
    if friction not in _SMALL_CPU:
        sim = ContactSimulator(mesh, Material(nu=0.48, friction=friction), assembly="numpy",
                               use_cache=False)
        sim.prepare()
        _SMALL_CPU[friction] = sim
    return _SMALL_CPU[friction]


@pytest.mark.parametrize("friction", ["frictionless", "stick"])
def test_operators_by_dense_cholesky_equal_the_cpu_operators(small_mesh, friction):
    material = Material(nu=0.48, friction=friction)
    block = 1 if friction == "frictionless" else 3
    C, G = compute_operators_torch(small_mesh, material.nu, block)
    cpu = small_cpu(small_mesh, friction)
    C_cpu, G_cpu = cpu.compliance, cpu.greens
    C, G = C.numpy(), G.numpy()
    assert np.abs(C - C_cpu).max() <= 1e-10 * np.abs(C_cpu).max()
    # The CPU stores G in float32: equal to its rounding.
    assert np.abs(G - G_cpu).max() <= 1e-6 * np.abs(G_cpu).max()
    # Independent float64 check of G: a few columns by a sparse LU solve of the reduced system.
    cols, dofs = contact_columns(small_mesh, block)
    K = assemble_stiffness_numpy(small_mesh.vertices, small_mesh.tets, 1.0, material.nu,
                                 "nodal_pressure")
    Kq = sp.csc_matrix(dofs.T.T @ K @ dofs.T)
    lu = spla.splu(Kq)
    for j in (0, len(cols.ravel()) // 2, len(cols.ravel()) - 1):
        e = np.zeros(Kq.shape[0])
        e[cols.ravel()[j]] = 1.0
        u = (dofs.T @ lu.solve(e)).reshape(-1, 3)
        assert np.abs(G[j] - u).max() <= 1e-10 * np.abs(u).max()


# ----------------------------------------------------------------------------- intrusion
def test_envelope_bank_equals_the_indenters(pad, bank):
    rng = np.random.default_rng(3)
    xy = pad.vertices[: pad.n_plane, :2]
    index = np.arange(len(INDENTERS)).repeat(3)
    poses = random_poses(rng, len(index), 10.0, (0.5, 3.9))
    got = bank.intrusion_mm(torch.as_tensor(index), poses_tensor(poses),
                            torch.as_tensor(xy)).numpy()
    for i, pose in enumerate(poses):
        ref = get_indenter(INDENTERS[index[i]]).intrusion_mm(xy, pose)
        np.testing.assert_array_equal(np.isfinite(got[i]), np.isfinite(ref))
        np.testing.assert_allclose(got[i][np.isfinite(ref)], ref[np.isfinite(ref)], rtol=0,
                                   atol=1e-12)


def test_envelope_bank_snaps_the_footprint_edge_like_the_cpu(bank):
    """Points on (and within 1e-7 pixel of) the pixel line at a flat punch's wall."""
    k = INDENTERS.index("flat_punch")
    grid = get_indenter("flat_punch").envelope_grid()
    finite = np.isfinite(grid.heights_mm)
    iy = grid.ny // 2
    ix = int(np.flatnonzero(finite[iy])[-1])  # last finite pixel of the middle row
    x = grid.x0_mm + ix * grid.pitch_mm + np.array([0.0, 1e-7, -1e-7, 3e-6]) * grid.pitch_mm
    q = np.stack([x, np.full(4, grid.y0_mm + iy * grid.pitch_mm)], axis=1)
    got = bank.envelope_mm(torch.full((1,), k), torch.as_tensor(q)[None]).numpy()[0]
    np.testing.assert_array_equal(got, get_indenter("flat_punch").envelope_mm(q))
    assert np.isfinite(got[:3]).all() and np.isinf(got[3])


def test_envelope_bank_equals_grid_sample(bank):
    """Independent method: the grid_sample recipe documented on EnvelopeGrid (float64)."""
    import torch.nn.functional as F

    rng = np.random.default_rng(5)
    for name in ("sphere_r4", "gear", "dot_array"):
        grid = get_indenter(name).envelope_grid()
        q = rng.uniform(-9, 9, (4000, 2))
        h = torch.tensor(grid.finite_heights_mm(), dtype=torch.float64)[None, None]
        uv = torch.as_tensor(grid.normalized_coordinates(q))[None, None]
        e = F.grid_sample(h, uv, mode="bilinear", padding_mode="border", align_corners=True)[0, 0, 0]
        e = torch.where(e > grid.max_relief_mm, torch.inf, e).numpy()
        got = bank.envelope_mm(torch.full((1,), INDENTERS.index(name)),
                               torch.as_tensor(q)[None]).numpy()[0]
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(e))
        np.testing.assert_allclose(got[np.isfinite(e)], e[np.isfinite(e)], rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- depth camera
def _deformations(mesh, rng, n):
    xy = mesh.vertices[: mesh.n_plane, :2]
    out = []
    for s in range(n):
        c = rng.uniform(-9, 9, 2)
        r = np.hypot(*(xy - c).T)
        bump = np.exp(-((r / 3.0) ** 2))
        u = np.zeros((mesh.n_plane, 3))
        u[:, 2] = -1.3 * bump
        u[:, :2] = 1.5 * rng.uniform(-1, 1, (mesh.n_plane, 2)) * bump[:, None] * (s % 2)
        u[:, :2] += 0.8 * (xy - c) / np.maximum(r, 1e-9)[:, None] * bump[:, None]
        out.append(u)
    steep = np.zeros((mesh.n_plane, 3))
    steep[np.argmin(np.hypot(*xy.T)), 2] = -12.0  # a deep narrow dimple: |grad z| > 10
    out.append(steep)
    return np.array(out)


def test_torch_depth_camera_equals_depth_camera(pad):
    cam = DepthCamera()
    U = _deformations(pad, np.random.default_rng(0), 3)
    depth = TorchDepthCamera(pad, cam, dtype=torch.float64).render_displacements(torch.as_tensor(U))
    for i, u in enumerate(U):
        ref = cam.render(pad, pad.vertices[: pad.n_plane] + u)
        np.testing.assert_allclose(depth[i].numpy(), ref.depth_mm, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(TorchDepthCamera(pad, cam).image_mask().numpy(),
                                  cam.render(pad, pad.vertices).mask)
    depth32 = TorchDepthCamera(pad, cam, dtype=torch.float32).render_displacements(
        torch.as_tensor(U, dtype=torch.float32))
    assert (depth32.double() - depth).abs().max() < 1e-5


def test_rasterizer_face_index_and_barycentric_reproduce_z(pad):
    cam = DepthCamera()
    u = _deformations(pad, np.random.default_rng(1), 1)[:1]
    rest = pad.vertices[: pad.n_plane]
    r = TriangleRasterizer(pad.sensing_faces, rest, cam.grid).rasterize(
        torch.as_tensor(u), return_face_index=True, return_barycentric=True)
    v = rest + u[0]
    tri = v[pad.sensing_faces]
    ref = rasterize_triangles(tri, cam.grid, reduce="min", return_face_index=True)
    z, face, bary = r.z_mm[0].numpy(), r.face_index[0].numpy(), r.barycentric[0].numpy()
    hit = face >= 0
    np.testing.assert_array_equal(hit, ref.face_index >= 0)
    np.testing.assert_allclose(z[hit], ref.z_mm[hit], rtol=0, atol=1e-12)
    interp = (bary[hit] * tri[face[hit], :, 2]).sum(axis=1)
    np.testing.assert_allclose(interp, z[hit], rtol=0, atol=1e-12)
    # Where the winners differ, both triangles give the same z (a shared edge or vertex).
    assert np.mean(face[hit] == ref.face_index[hit]) > 0.99


# ----------------------------------------------------------------------------- contact
def test_frictionless_batch_equals_the_cpu_simulator(small_mesh, bank):
    cpu = small_cpu(small_mesh, "frictionless")
    rng = np.random.default_rng(11)
    batched = BatchedContactSimulator(small_mesh, cpu.material, dtype=torch.float64,
                                      operators=(cpu.compliance, cpu.greens))
    index = np.concatenate([np.arange(len(INDENTERS)), rng.integers(len(INDENTERS), size=4)])
    poses = random_poses(rng, len(index), 5.0)
    assert_matches_cpu(cpu, batched, bank, index, poses)


def test_stick_batch_equals_the_cpu_simulator(small_mesh, bank):
    cpu = small_cpu(small_mesh, "stick")
    batched = BatchedContactSimulator(small_mesh, cpu.material, dtype=torch.float64,
                                      operators=(cpu.compliance, cpu.greens))
    rng = np.random.default_rng(12)
    index = np.array([0, 1, 2, 3, 5, 6, 7, 8])
    poses = random_poses(rng, len(index), 4.0)
    res = assert_matches_cpu(cpu, batched, bank, index, poses)
    assert res.contact_forces_n[..., :2].abs().max() > 0  # tangential forces act


def test_host_fallback_is_counted_and_exact(small_mesh, bank):
    cpu_sim = small_cpu(small_mesh, "frictionless")
    batched = BatchedContactSimulator(small_mesh, cpu_sim.material, dtype=torch.float64,
                                      operators=(cpu_sim.compliance, cpu_sim.greens),
                                      max_active_nodes=12)
    index = np.array([INDENTERS.index("sphere_r2"), INDENTERS.index("coin")])
    poses = [ContactPose(x_mm=1.0, y_mm=-2.0, theta_deg=0.0, depth_mm=0.3),
             ContactPose(x_mm=-1.0, y_mm=0.5, theta_deg=40.0, depth_mm=0.8)]
    res = batched.solve(bank, torch.as_tensor(index), poses_tensor(poses))
    assert res.stats["contact_host_fallback"] == {"active_set_too_large": 1}
    for i, pose in enumerate(poses):
        ref = cpu_sim.solve(get_indenter(INDENTERS[index[i]]), pose)
        np.testing.assert_allclose(res.displacements_mm[i].numpy(), ref.displacements_mm,
                                   rtol=0, atol=1e-10)
        np.testing.assert_array_equal(res.contact_mask[i].numpy(), ref.contact_mask)


def test_unsettled_iterations_take_the_cpu_fallbacks(small_mesh, bank):
    """With one active-set step allowed, contacts that need more take the CPU path's way out:
    Lawson-Hanson for frictionless contact, a flagged failure for sticking contact; float32
    failures are first solved again in float64 on the device."""
    rng = np.random.default_rng(21)
    index = torch.as_tensor(rng.integers(len(INDENTERS), size=12))
    poses = poses_tensor(random_poses(rng, len(index), 3.0))
    cpu_sim = small_cpu(small_mesh, "frictionless")
    sim = BatchedContactSimulator(cpu_sim.mesh, cpu_sim.material, dtype=torch.float64,
                                  operators=(cpu_sim.compliance, cpu_sim.greens))
    delta = sim.intrusion(bank, index, poses)
    C64 = torch.as_tensor(cpu_sim.compliance)
    for contact in (BatchedContact(C64, 1, max_iter=1),
                    BatchedContact(C64.float(), 1, C64=C64, max_iter=1)):
        forces, _, stats = contact.solve(delta)
        assert stats.host_fallback.get("not_settled", 0) >= 1 and not stats.unsolved
        single = contact.C.dtype == torch.float32
        if single:
            assert stats.escalated_to_float64 >= 1
        for i in range(len(index)):
            ref = cpu_sim.surface_forces(delta[i].numpy())
            np.testing.assert_allclose(forces[i].double().numpy(), ref, rtol=0,
                                       atol=(1e-5 if single else 1e-9) * np.abs(ref).max())
    stick = small_cpu(small_mesh, "stick")
    sim = BatchedContactSimulator(small_mesh, stick.material, dtype=torch.float64,
                                  operators=(stick.compliance, stick.greens))
    delta = sim.intrusion(bank, index, poses)
    forces, _, stats = BatchedContact(torch.as_tensor(stick.compliance), 3, max_iter=1).solve(delta)
    assert stats.unsolved and torch.isnan(forces[stats.unsolved]).all()


def test_no_contact_gives_zero_fields(small_mesh, bank):
    cpu_sim = small_cpu(small_mesh, "frictionless")
    batched = BatchedContactSimulator(cpu_sim.mesh, cpu_sim.material, dtype=torch.float64,
                                      operators=(cpu_sim.compliance, cpu_sim.greens))
    off_pad = ContactPose(x_mm=30.0, y_mm=0.0, theta_deg=0.0, depth_mm=0.5)
    res = batched.solve(bank, torch.zeros(1, dtype=torch.int64), poses_tensor([off_pad]))
    assert res.stats["samples_in_contact"] == 0
    assert res.displacements_mm.abs().max() == 0 and res.depth_mm.abs().max() == 0


def test_float32_batch_agrees_with_float64(small_mesh, bank):
    cpu_sim = small_cpu(small_mesh, "frictionless")
    rng = np.random.default_rng(13)
    index = rng.integers(len(INDENTERS), size=8)
    poses = poses_tensor(random_poses(rng, len(index), 5.0))
    ops = (cpu_sim.compliance, cpu_sim.greens)
    r64 = BatchedContactSimulator(cpu_sim.mesh, cpu_sim.material, dtype=torch.float64,
                                  operators=ops).solve(bank, torch.as_tensor(index), poses)
    r32 = BatchedContactSimulator(cpu_sim.mesh, cpu_sim.material, dtype=torch.float32,
                                  operators=ops).solve(bank, torch.as_tensor(index), poses)
    assert (r32.displacements_mm.double() - r64.displacements_mm).abs().max() < 1e-4
    assert (r32.depth_mm.double() - r64.depth_mm).abs().max() < 1e-4
    mismatch = (r32.contact_mask != r64.contact_mask).sum().item()
    assert mismatch <= 2  # nodes at the contact edge with ~zero force may flip in float32


def test_package_imports_without_torch():
    code = ("import sys; sys.modules['torch'] = None; import tactile_deploy, "
            "tactile_deploy.fem.simulator, tactile_deploy.camera.depth, tactile_deploy.indenters")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_coulomb_batch_equals_the_cpu_simulator(small_mesh, bank):
    """Per-sample friction coefficients, from frictionless to sticking, in one batch: forces,
    contact and stick sets and depth as CoulombSimulator's (its Newton steps on the host)."""
    from tactile_deploy.fem.coulomb import CoulombSimulator

    stick = small_cpu(small_mesh, "stick")
    batched = BatchedContactSimulator(small_mesh, Material(nu=0.48, friction="coulomb", mu=0.5),
                                      dtype=torch.float64, operators=(stick.compliance, stick.greens))
    rng = np.random.default_rng(13)
    index = np.array([0, 1, 2, 3, 5, 6, 7, 8, 1, 0])
    mu = np.array([0.0, 0.3, 0.5, 0.8, 1.0, 1.5, 0.4, 0.7, 5.0, 0.6])
    poses = random_poses(rng, len(index), 4.0)
    res = batched.solve(bank, torch.as_tensor(index), poses_tensor(poses), mu=torch.as_tensor(mu))
    cam = DepthCamera()
    n_slip = 0
    for i, pose in enumerate(poses):
        cpu = CoulombSimulator.sharing(stick, Material(nu=0.48, friction="coulomb", mu=float(mu[i])))
        ref = cpu.solve(get_indenter(INDENTERS[index[i]]), pose)
        assert res.solved[i]
        scale = max(1.0, np.abs(ref.contact_forces_n).max())
        np.testing.assert_allclose(res.contact_forces_n[i].numpy(), ref.contact_forces_n, rtol=0, atol=1e-9 * scale)
        np.testing.assert_array_equal(res.contact_mask[i].numpy(), ref.contact_mask)
        np.testing.assert_array_equal(res.stick_mask[i].numpy(), ref.stick_mask)
        np.testing.assert_allclose(res.displacements_mm[i].numpy(), ref.displacements_mm, rtol=0, atol=1e-10)
        depth_ref = cam.render(cpu.mesh, ref.vertices_mm).depth_mm
        np.testing.assert_allclose(res.depth_mm[i].numpy(), depth_ref, rtol=0, atol=1e-6)
        n_slip += int((ref.contact_mask & ~ref.stick_mask).sum())
    assert n_slip > 0  # partial slip occurs in the batch
    # the frictionless limit: mu = 0 is the frictionless simulator's contact (one dof per node)
    free = small_cpu(small_mesh, "frictionless").solve(get_indenter(INDENTERS[index[0]]), poses[0])
    assert float(res.contact_forces_n[0, :, :2].abs().max()) == 0.0
    np.testing.assert_allclose(res.displacements_mm[0].numpy(), free.displacements_mm, rtol=0, atol=1e-10)


def test_coulomb_host_fallback_is_counted_and_exact(small_mesh, bank):
    """Samples with more nodes in contact than the device may take go to the CPU solver."""
    stick = small_cpu(small_mesh, "stick")
    mat = Material(nu=0.48, friction="coulomb", mu=0.6)
    poses = poses_tensor(random_poses(np.random.default_rng(14), 3, 3.0, depth_mm=(0.6, 0.9)))
    index = torch.tensor([1, 2, 0])
    ref = BatchedContactSimulator(small_mesh, mat, dtype=torch.float64, operators=(stick.compliance, stick.greens))
    small = BatchedContactSimulator(small_mesh, mat, dtype=torch.float64, operators=(stick.compliance, stick.greens),
                                    max_active_nodes=4)
    a, b = ref.solve(bank, index, poses), small.solve(bank, index, poses)
    assert a.stats["n_contact_fallback"] == 0 and b.stats["contact_host_fallback"] == {"active_set_too_large": 3}
    np.testing.assert_allclose(b.contact_forces_n.numpy(), a.contact_forces_n.numpy(), rtol=0, atol=1e-10)
    np.testing.assert_array_equal(b.stick_mask.numpy(), a.stick_mask.numpy())


def test_batched_generator_draws_coulomb_coefficients(small_mesh, monkeypatch):
    """The batched data generator with Coulomb contact: with mu_range (0, 0) every sample is the
    frictionless generator's sample of the same seed (the poses are drawn before the coefficients);
    with mu 0.8 the gel is held and the samples differ."""
    import tactile_deploy.pad.asset as asset
    from tactile_deploy.training.config import SyntheticData
    from tactile_deploy.training.data import generate_batched

    monkeypatch.setattr(asset, "load_pad", lambda *a, **k: small_mesh)
    spec = SyntheticData(n_samples=12, seed=3, indenters=("sphere_r4", "cube_corner"), radius_max_mm=3.0,
                         depth_min_mm=0.3, depth_max_mm=0.8, generator="batched")
    free = generate_batched(spec)
    zero = generate_batched(spec.model_copy(update={"friction": "coulomb", "mu_range": (0.0, 0.0)}))
    held = generate_batched(spec.model_copy(update={"friction": "coulomb", "mu_range": (0.8, 0.8)}))
    np.testing.assert_allclose(zero.displacement_mm, free.displacement_mm, rtol=0, atol=1e-6)
    np.testing.assert_allclose(zero.depth_mm, free.depth_mm, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(held.indenter, free.indenter)
    lateral = np.abs(held.displacement_mm[:, : small_mesh.n_plane, :2] - free.displacement_mm[:, : small_mesh.n_plane, :2])
    assert lateral.max() > 0.01  # mm: friction holds the surface where frictionless contact lets it slide


def test_concatenated_bank_with_procedural_faces_equals_the_indenters(pad):
    """EnvelopeBank.concat of named indenters and procedural faces (grids of another pitch)
    samples each as its own numpy envelope does (EnvelopeGrid.sample_mm: another code path)."""
    from tactile_deploy.training.config import ProceduralFaces, SyntheticData
    from tactile_deploy.training.data import procedural_faces

    spec = SyntheticData(n_samples=1, procedural=ProceduralFaces(count=4, share=0.5, seed=11))
    faces = procedural_faces(spec)
    for f, again in zip(faces, procedural_faces(spec), strict=True):  # the same faces on every call (rank)
        np.testing.assert_array_equal(f.envelope_grid().heights_mm, again.envelope_grid().heights_mm)
    assert all(f.name.startswith("procedural_") for f in faces)
    named = [get_indenter(n) for n in ("analytic_sphere_r3", "flat_punch")]
    bank = EnvelopeBank.concat([EnvelopeBank.from_indenters(named), EnvelopeBank.from_indenters(faces)])
    indenters = named + faces
    rng = np.random.default_rng(8)
    xy = pad.vertices[: pad.n_plane, :2]
    index = np.arange(len(indenters)).repeat(2)
    poses = random_poses(rng, len(index), 6.0, (0.3, 1.2))
    got = bank.intrusion_mm(torch.as_tensor(index), poses_tensor(poses), torch.as_tensor(xy)).numpy()
    for i, pose in enumerate(poses):
        ref = indenters[index[i]].intrusion_mm(xy, pose)
        np.testing.assert_array_equal(np.isfinite(got[i]), np.isfinite(ref))
        np.testing.assert_allclose(got[i][np.isfinite(ref)], ref[np.isfinite(ref)], rtol=0, atol=1e-12)
    assert all(np.isfinite(got[i]).any() for i in range(len(index)))  # every face reaches the pad


def test_batched_generator_presses_procedural_faces(small_mesh, monkeypatch):
    """With procedural faces at share 1 every contact presses one of them; at share 0.5 both kinds
    occur; without them the draws are those of the named indenters alone."""
    import tactile_deploy.pad.asset as asset
    from tactile_deploy.training.config import ProceduralFaces, SyntheticData
    from tactile_deploy.training.data import generate_batched

    monkeypatch.setattr(asset, "load_pad", lambda *a, **k: small_mesh)
    spec = SyntheticData(n_samples=16, seed=3, indenters=("sphere_r4", "cube_corner"), radius_max_mm=3.0,
                         depth_min_mm=0.3, depth_max_mm=0.8, generator="batched")
    named = generate_batched(spec)
    assert set(named.indenter) <= {"sphere_r4", "cube_corner"}
    only = generate_batched(spec.model_copy(update={"procedural": ProceduralFaces(count=5, share=1.0)}))
    assert all(n.startswith("procedural_") for n in only.indenter)
    assert only.contact_mask.any(axis=1).all() and only.depth_mm.max() > 0.2
    half = generate_batched(spec.model_copy(update={"procedural": ProceduralFaces(count=5, share=0.5)}))
    kinds = {n.startswith("procedural_") for n in half.indenter}
    assert kinds == {True, False}
