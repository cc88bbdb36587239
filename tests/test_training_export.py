"""Export modules against the trained predictor (torch only; the ONNX round trip is in
test_training_pipeline.py): rewrites and folded scales must not change the function."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tactile_deploy.training.config import DataConfig, SyntheticData, TrainConfig  # noqa: E402
from tactile_deploy.training.export import PixelShuffleUp, deploy_module, rewrite_transposed_convs  # noqa: E402


@pytest.fixture(scope="module")
def model():
    from tactile_deploy.training.train import build_model

    torch.manual_seed(1)
    m = build_model(TrainConfig(run_dir="unused", data=DataConfig(synthetic=SyntheticData(n_samples=1)))).eval()
    m.norm.set_scales(0.6, (0.05, 0.07, 0.04))  # distinct per-axis scales: folding must keep them apart
    with torch.no_grad():
        for conv in m.mesh_vae.decoder.convs:
            conv.bias.normal_(0, 0.1)
    return m


@pytest.fixture(scope="module")
def depth():
    yy, xx = np.mgrid[0:128, 0:128]
    d = np.stack([np.clip(0.8 - ((yy - cy) ** 2 + (xx - cx) ** 2) / 150.0, 0, None) for cy, cx in [(40, 60), (80, 90)]])
    return torch.as_tensor(d[:, None], dtype=torch.float32)


@pytest.mark.parametrize("c_in,c_out", [(3, 5), (64, 32)])
def test_pixel_shuffle_equals_transposed_conv(c_in, c_out):
    deconv = torch.nn.ConvTranspose2d(c_in, c_out, 2, stride=2)
    x = torch.randn(2, c_in, 5, 7)
    torch.testing.assert_close(PixelShuffleUp(deconv)(x), deconv(x), atol=1e-5, rtol=0)


def test_rewrite_only_touches_large_stride2_kernel2_layers():
    seq = torch.nn.Sequential(
        torch.nn.ConvTranspose2d(256, 128, 2, stride=2),  # 131k weights: rewritten
        torch.nn.ConvTranspose2d(128, 8, 2, stride=2),  # 4k weights: kept
        torch.nn.ConvTranspose2d(128, 256, 3, stride=2),  # kernel 3: kept
    )
    rewrite_transposed_convs(seq)
    assert isinstance(seq[0], PixelShuffleUp)
    assert isinstance(seq[1], torch.nn.ConvTranspose2d) and isinstance(seq[2], torch.nn.ConvTranspose2d)


@pytest.mark.parametrize("variant,decoder", [("naive", "coma"), ("fused", "coma"), ("lean", "lean")])
def test_deploy_modules_compute_the_predictor(model, depth, variant, decoder):
    module = deploy_module(model, variant)
    model.deploy_decoder = decoder
    try:
        with torch.no_grad():
            v_ref, d_ref = model(depth)
            ood_ref = model.image_reconstruction_rmse(depth)
            v, d, ood = module(depth)
    finally:
        model.deploy_decoder = "coma"
    assert d_ref.abs().max() > 1e-3
    torch.testing.assert_close(d, d_ref, atol=1e-6, rtol=1e-4)
    torch.testing.assert_close(v, v_ref, atol=1e-5, rtol=0)
    torch.testing.assert_close(ood, ood_ref, atol=1e-6, rtol=1e-4)
    assert torch.all(d[:, -1076:] == 0)  # the bonded backplate layer never moves
