"""Layer-aware coarsening and the graph operators of the mesh networks, against independent
references: linear-field reproduction, dense scipy/numpy products, autograd through tables."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

torch = pytest.importorskip("torch")

from tactile_deploy.training.networks.coarsening import build_hierarchy  # noqa: E402
from tactile_deploy.training.networks.graph import ChebConv, SparseMap  # noqa: E402


@pytest.fixture(scope="module")
def hierarchy(pad):
    return build_hierarchy(pad)


def test_levels_are_nested_layered_meshes(hierarchy, pad):
    assert hierarchy.node_counts == (5380, 1345, 335, 85, 20)
    assert hierarchy.mesh_hash == pad.content_hash
    for fine, coarse in zip(hierarchy.levels[:-1], hierarchy.levels[1:]):
        assert set(coarse.plane_index) <= set(fine.plane_index)
        assert coarse.n_layers == 5
        # same depths on every level, node = layer * m + k
        z = coarse.vertices_mm[:, 2].reshape(5, coarse.n_plane)
        np.testing.assert_allclose(z, np.linspace(0.0, -3.0, 5)[:, None] * np.ones((1, coarse.n_plane)), atol=1e-12)
        assert len(np.unique(coarse.tets)) == coarse.n_nodes  # every node used by a tet


def test_upsampling_is_a_partition_of_unity_exact_at_kept_nodes(hierarchy):
    for l, up in enumerate(hierarchy.up):
        w = up.matrix()
        np.testing.assert_allclose(np.asarray(w.sum(axis=1)).ravel(), 1.0, atol=1e-12)
        assert (up.weight >= 0).all()
        # down (select) then up returns the kept nodes' values exactly
        x = np.random.default_rng(l).normal(size=hierarchy.levels[l].n_nodes)
        coarse = hierarchy.down[l].apply(x)
        np.testing.assert_allclose(hierarchy.up[l].apply(coarse)[hierarchy.down[l].index[:, 0]], coarse, atol=1e-12)


def test_upsampling_reproduces_linear_fields_inside_the_coarse_disc(hierarchy):
    """Barycentric weights interpolate any affine field exactly where the fine point lies inside
    the coarse polygon; rim points projected onto a chord are off by at most the chord's sag."""
    for l, up in enumerate(hierarchy.up):
        fine, coarse = hierarchy.levels[l], hierarchy.levels[l + 1]
        f = lambda p: 0.3 * p[:, 0] - 1.7 * p[:, 1] + 2.0 * p[:, 2] + 0.5  # noqa: E731
        err = np.abs(up.apply(f(coarse.vertices_mm)) - f(fine.vertices_mm))
        r = np.hypot(fine.vertices_mm[:, 0], fine.vertices_mm[:, 1])
        # largest chord of the coarse rim: sag = R (1 - cos(pi / n_rim))
        n_rim = int(np.sum(np.abs(np.hypot(*coarse.plane_xy_mm.T) - 17.5) < 1e-9))
        sag = 17.5 * (1 - np.cos(np.pi / n_rim))
        inside = r < 17.5 - sag - 1e-9
        assert err[inside].max() < 1e-9
        assert err.max() <= np.hypot(0.3, 1.7) * sag + 1e-9


def test_smooth_field_survives_one_level(hierarchy, pad):
    """The documented reconstruction figure: a 30 mm-wavelength field loses < 5 % at level 1."""
    p = pad.vertices
    f = np.cos(p[:, 0] / 6.0) * np.sin(p[:, 1] / 5.0) * (p[:, 2] + 3.0) / 3.0
    rel = np.linalg.norm(hierarchy.down_up(f, 1) - f) / np.linalg.norm(f)
    assert rel < 0.05


def test_chebyshev_operator_spectrum_in_unit_interval(hierarchy):
    for lv in hierarchy.levels[2:]:
        a = lv.chebyshev_operator.matrix().toarray()
        np.testing.assert_allclose(a, a.T, atol=1e-12)
        ev = np.linalg.eigvalsh(a)
        assert ev.min() >= -1 - 1e-9 and ev.max() <= 1 + 1e-9
        assert ev.max() == pytest.approx(1.0, abs=1e-6)  # lambda_max scaled exactly to 2


def test_sparse_map_paths_agree_with_scipy_and_autograd(hierarchy):
    table = hierarchy.levels[1].chebyshev_operator
    dense = table.matrix()
    op = SparseMap(table)
    x = torch.randn(table.n_in, 3, 4, dtype=torch.float32, requires_grad=True)
    y_sparse = op(x)
    ref = (dense @ x.detach().numpy().reshape(table.n_in, -1)).reshape(-1, 3, 4)
    np.testing.assert_allclose(y_sparse.detach().numpy(), ref, atol=1e-5)
    g = torch.randn_like(y_sparse)
    (grad_sparse,) = torch.autograd.grad(y_sparse, x, g)
    op.use_tables = True
    (grad_tables,) = torch.autograd.grad(op(x), x, g)
    np.testing.assert_allclose(grad_sparse.numpy(), grad_tables.numpy(), atol=1e-5)


@pytest.mark.parametrize("c_in,c_out,k", [(3, 16, 6), (16, 3, 6), (16, 16, 2), (5, 4, 1)])
def test_chebconv_matches_dense_polynomial(hierarchy, c_in, c_out, k):
    lv = hierarchy.levels[2]
    conv = ChebConv(c_in, c_out, k, SparseMap(lv.chebyshev_operator))
    x = torch.randn(lv.n_nodes, 2, c_in)
    with torch.no_grad():
        y = conv(x).numpy()
    a = lv.chebyshev_operator.matrix().toarray()
    t = [np.eye(len(a)), a]
    while len(t) < k:
        t.append(2 * a @ t[-1] - t[-2])
    w = conv.weight.detach().numpy()
    ref = sum(np.einsum("ij,jbc,cd->ibd", t[i], x.numpy(), w[i]) for i in range(k)) + conv.bias.detach().numpy()
    np.testing.assert_allclose(y, ref, atol=2e-5)


def test_layered_blocks_reproduce_the_operator(hierarchy):
    from tactile_deploy.training.fused import layered_blocks

    lv = hierarchy.levels[0]
    op = lv.chebyshev_operator.matrix()
    index, blocks = layered_blocks(lv, op)
    x = np.random.default_rng(1).normal(size=(lv.n_nodes, 2))
    xl = x.reshape(5, lv.n_plane, 2).transpose(1, 0, 2)  # (m, layer, c)
    g = xl[index].reshape(lv.n_plane, -1, 2)  # (m, W * 5, c)
    y = np.einsum("mlk,mkc->mlc", blocks, g).transpose(1, 0, 2).reshape(lv.n_nodes, 2)
    np.testing.assert_allclose(y, op @ x, atol=1e-12)
    assert index.shape[1] <= 8  # rows gathered per in-plane point: 8 vs 17 per node


def test_refuses_a_box_pad():
    from tactile_deploy.pad.geometry import PadGeometry
    from tactile_deploy.pad.mesh import build_pad_mesh

    box = build_pad_mesh(PadGeometry(shape="box", width_mm=10, length_mm=10, edge_mm=2.0))
    with pytest.raises(ValueError, match="full disc"):
        build_hierarchy(box)
