"""The differentiable depth renderer of the adaptation step against the simulator's depth camera
(an independent rasteriser: numpy, row spans), its gradient (finite differences), its export."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tactile_deploy.camera.depth import DepthCamera  # noqa: E402
from tactile_deploy.training.adaptation.render import DepthRenderer  # noqa: E402


def _presses(pad, rng, n, lateral_mm):
    """Displacements (n, n_plane, 3) mm of the sensing nodes: Gaussian dents up to 1.2 mm deep
    with radial and random lateral motion up to ``lateral_mm``."""
    xy = pad.vertices[: pad.n_plane, :2]
    out = []
    for _ in range(n):
        c = rng.uniform(-9, 9, 2)
        r = np.hypot(*(xy - c).T)
        bump = np.exp(-((r / rng.uniform(1.5, 4.0)) ** 2))
        u = np.zeros((pad.n_plane, 3))
        u[:, 2] = -rng.uniform(0.3, 1.2) * bump
        u[:, :2] = lateral_mm * ((xy - c) / np.maximum(r, 1e-9)[:, None] + rng.uniform(-1, 1, (pad.n_plane, 2))) * 0.5 * bump[:, None]
        out.append(u)
    return np.array(out)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_renderer_matches_the_depth_camera_within_1um(pad, dtype):
    cam = DepthCamera()
    rng = np.random.default_rng(3)
    u = _presses(pad, rng, 4, lateral_mm=0.15)
    renderer = DepthRenderer.for_pad(pad, dtype=dtype)
    depth, overflow = renderer(torch.as_tensor(u, dtype=dtype))
    assert overflow.tolist() == [0, 0, 0, 0]
    for i in range(len(u)):
        ref = cam.render(pad, pad.vertices[: pad.n_plane] + u[i]).depth_mm
        assert np.abs(depth[i].double().numpy() - ref).max() < 1e-5  # spec 1 um; measured 3e-8 (f64), 5e-7 mm (f32)
        assert ref.max() > 0.25


def test_large_lateral_motion_is_counted_and_rendered_with_a_larger_budget(pad):
    """Displacements that stretch triangles beyond the default pixel budget are reported in
    ``overflow``; with a budget that holds them the depth matches the camera again."""
    cam = DepthCamera()
    u = _presses(pad, np.random.default_rng(4), 2, lateral_mm=1.5)
    small = DepthRenderer.for_pad(pad)
    _, overflow = small(torch.as_tensor(u, dtype=torch.float32))
    assert int(overflow.sum()) > 0
    big = DepthRenderer.for_pad(pad, pixels_per_triangle=160)
    depth, overflow = big(torch.as_tensor(u, dtype=torch.float32))
    assert int(overflow.sum()) == 0
    for i in range(len(u)):
        ref = cam.render(pad, pad.vertices[: pad.n_plane] + u[i]).depth_mm
        assert np.abs(depth[i].numpy() - ref).max() < 1e-3


def test_renderer_gradient_matches_finite_differences():
    """torch.autograd.gradcheck in float64 on a 4 x 4 node patch seen by an 8 x 8 camera:
    the depth is differentiable in all three displacement components."""
    cam = DepthCamera(half_extent_mm=2.0, resolution=8)
    xs = np.array([-1.7, -0.6, 0.5, 1.6])
    xy = np.stack(np.meshgrid(xs, xs + 0.05), -1).reshape(-1, 2)
    rest = np.c_[xy, np.zeros(len(xy))]
    faces = [[a, a + 1, a + 5] for a in (0, 1, 2, 4, 5, 6, 8, 9, 10)] + \
            [[a, a + 5, a + 4] for a in (0, 1, 2, 4, 5, 6, 8, 9, 10)]
    renderer = DepthRenderer(np.array(faces), rest, cam, pixels_per_triangle=16, dtype=torch.float64)
    u = torch.tensor(np.random.default_rng(0).normal(0, 0.08, (2, len(rest), 3)), requires_grad=True)
    depth, _ = renderer(u)
    assert int((depth != 0).sum()) > 40
    assert torch.autograd.gradcheck(lambda x: renderer(x)[0], (u,), eps=1e-6, atol=1e-7)
    # lateral components matter: their gradient is not zero
    depth.sum().backward()
    assert float(u.grad[..., :2].abs().sum()) > 0


def test_renderer_survives_torch_export(pad, tmp_path):
    renderer = DepthRenderer.for_pad(pad)
    batch = torch.export.Dim("batch", min=1, max=64)
    program = torch.export.export(renderer, (torch.zeros(2, pad.n_plane, 3),), dynamic_shapes=({0: batch},))
    torch.export.save(program, str(tmp_path / "r.pt2"))
    loaded = torch.export.load(str(tmp_path / "r.pt2")).module()
    u = torch.as_tensor(_presses(pad, np.random.default_rng(5), 3, 0.1), dtype=torch.float32).requires_grad_(True)
    a = loaded(u)[0]
    b = renderer(u)[0]
    assert torch.equal(a, b)
    (ga,) = torch.autograd.grad(a.square().sum(), u)
    (gb,) = torch.autograd.grad(b.square().sum(), u)
    assert torch.allclose(ga, gb)


def test_renderer_rejects_bad_mesh_arrays_naming_them():
    rest = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match=r"faces must have shape \(t, 3\)"):
        DepthRenderer(np.array([0, 1, 2]), rest)
    with pytest.raises(ValueError, match=r"rest_vertices_mm must have shape \(n, 3\)"):
        DepthRenderer(np.array([[0, 1, 2]]), rest[:, :2])
    with pytest.raises(ValueError, match=r"faces index vertices 0..2, got 0..3"):
        DepthRenderer(np.array([[0, 1, 3]]), rest)
    with pytest.raises(ValueError, match="at least one triangle"):
        DepthRenderer(np.zeros((0, 3), int), rest)
