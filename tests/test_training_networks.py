"""Networks, the fused decoder, the lean decoder's read-out, the split and the configs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydantic
import pytest

torch = pytest.importorskip("torch")

from tactile_deploy.training.config import GridDecoderConfig, ImageVAEConfig, MeshVAEConfig, TrainConfig  # noqa: E402
from tactile_deploy.training.data import contact_ids, split_by_contact  # noqa: E402
from tactile_deploy.training.networks.coarsening import build_hierarchy  # noqa: E402
from tactile_deploy.training.networks.grid_decoder import GridDecoder  # noqa: E402
from tactile_deploy.training.networks.image_vae import ImageVAE  # noqa: E402
from tactile_deploy.training.networks.mesh_vae import MeshVAE  # noqa: E402


@pytest.fixture(scope="module")
def hierarchy(pad):
    return build_hierarchy(pad)


@pytest.mark.parametrize("kernel", [2, 3, 4])
def test_image_vae_shapes(kernel):
    vae = ImageVAE(ImageVAEConfig(kernel=kernel))
    recon, mu, logvar = vae(torch.zeros(2, 1, 128, 128))
    assert recon.shape == (2, 1, 128, 128) and mu.shape == logvar.shape == (2, 128)
    convs = [m for m in vae.encoder.convs if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [32, 64, 128, 256, 512]


def test_mesh_vae_shapes_and_paper_sizes(hierarchy):
    vae = MeshVAE(MeshVAEConfig(), hierarchy)
    recon, mu, _ = vae(torch.zeros(3, 5380, 3))
    assert recon.shape == (3, 5380, 3) and mu.shape == (3, 128)
    assert [c.weight.shape[2] for c in vae.encoder.convs] == [16, 16, 16, 32]
    assert all(c.k == 6 for c in vae.encoder.convs)


def test_fused_decoder_is_the_same_function(hierarchy):
    """Restructured (folded, dense coarse levels, layered fine levels) = the training decoder."""
    from tactile_deploy.training.fused import FusedComaDecoder

    torch.manual_seed(0)
    vae = MeshVAE(MeshVAEConfig(), hierarchy)
    with torch.no_grad():
        for conv in vae.decoder.convs:
            conv.bias.normal_(0, 0.1)
    fused = FusedComaDecoder(vae.decoder)
    z = torch.randn(4, 128)
    with torch.no_grad():
        ref, out = vae.decoder(z), fused(z)
    assert ref.abs().max() > 0.1
    torch.testing.assert_close(out, ref, atol=2e-5, rtol=0)


def test_grid_decoder_reads_the_pixel_under_each_node(pad):
    lv0 = pad.vertices[: pad.n_plane]
    dec = GridDecoder(GridDecoderConfig(), 128, lv0[:, :2], 5).eval()
    z = torch.randn(2, 128)
    with torch.no_grad():
        grid = dec.grid_features(z).numpy()  # (2, 12, 64, 64)
        out = dec(z).numpy()  # (2, 5380, 3)
    # pixel k covers [-17.5 + k p, -17.5 + (k + 1) p), rows along +y
    edges = -17.5 + np.arange(65) * (35.0 / 64)
    col = np.searchsorted(edges, lv0[:, 0], side="right") - 1
    row = np.searchsorted(edges, lv0[:, 1], side="right") - 1
    col, row = np.clip(col, 0, 63), np.clip(row, 0, 63)
    for layer in range(4):
        for axis in range(3):
            np.testing.assert_array_equal(
                out[:, layer * 1076 : (layer + 1) * 1076, axis], grid[:, 3 * layer + axis, row, col]
            )
    assert np.all(out[:, 4 * 1076 :] == 0.0)  # backplate layer is bonded


def test_grid_decoder_refuses_a_grid_that_merges_nodes(pad):
    with pytest.raises(ValueError, match="several pad nodes in one pixel"):
        GridDecoder(GridDecoderConfig(grid=32, channels=(32, 32, 32)), 128, pad.vertices[:1076, :2], 5)


def test_split_by_contact_keeps_every_press_on_one_side():
    rng = np.random.default_rng(0)
    n_contacts = 50
    ind = np.repeat(rng.choice(["a", "b", "c"], n_contacts), 3)  # 3 depths per press
    x = np.repeat(rng.uniform(-10, 10, n_contacts), 3)
    y = np.repeat(rng.uniform(-10, 10, n_contacts), 3)
    t = np.repeat(rng.uniform(0, 360, n_contacts), 3)
    cid = contact_ids(ind, x, y, t)
    assert len(np.unique(cid)) == n_contacts
    tr, va = split_by_contact(cid, 0.2, seed=1)
    assert not set(cid[tr]) & set(cid[va])
    assert len(np.unique(cid[va])) == 10 and len(tr) + len(va) == 3 * n_contacts
    tr2, va2 = split_by_contact(cid, 0.2, seed=1)
    np.testing.assert_array_equal(va, va2)


def test_configs_refuse_inconsistent_input():
    with pytest.raises(pydantic.ValidationError, match="one entry per level"):
        MeshVAEConfig(channels=(16, 16, 32), cheb_k=(6, 6, 6, 6), factors=(4, 4, 4))
    with pytest.raises(pydantic.ValidationError, match="not divisible"):
        ImageVAEConfig(resolution=100)
    with pytest.raises(pydantic.ValidationError, match="exactly one of"):
        TrainConfig(run_dir="x", data={"val_fraction": 0.2})
    with pytest.raises(pydantic.ValidationError, match="Extra inputs"):
        TrainConfig(run_dir="x", data={"dataset_dir": "d"}, learning_rate=1.0)


def test_shipped_configs_load():
    """Every config shipped in training/configs validates against the schema it is read with."""
    from tactile_deploy.training.experiments import ExperimentConfig

    root = Path(__file__).resolve().parents[1] / "training" / "configs"
    files = sorted(root.glob("*.json"))
    assert len(files) >= 5
    for f in files:
        if f.name.startswith("experiments"):
            ExperimentConfig.load(f)
        else:
            TrainConfig.load(f)
    stick = TrainConfig.load(root / "gpu_h100_stick.json")
    assert stick.data.synthetic.friction == "stick"
    with pytest.raises(pydantic.ValidationError, match="frictionless"):
        TrainConfig(run_dir="x", data={"synthetic": {"n_samples": 8, "friction": "slip"}})
