"""Augmentation of simulated depth maps: each piece against an independent computation or a
planted parameter; the training config keeps today's behaviour without the section."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tactile_deploy.training.augment import Augmenter  # noqa: E402
from tactile_deploy.training.config import AugmentationConfig, TrainConfig  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
OFF = dict(probability=1.0, blur_sigma_mm=(0.0, 0.0), halo_amount=(0.0, 0.0), gain=(1.0, 1.0),
           view_box_probability=0.0, perlin_rms_mm=(0.0, 0.0), pixel_noise_mm=0.0)


def _bumps(n, rng):
    """(n, 128, 128) mm: Gaussian presses near the centre."""
    c = -17.5 + (np.arange(128) + 0.5) * 35 / 128
    x, y = np.meshgrid(c, -c)
    out = [rng.uniform(0.3, 1.0) * np.exp(-((x - a) ** 2 + (y - b) ** 2) / (2 * rng.uniform(1, 3) ** 2))
           for a, b in rng.uniform(-4, 4, (n, 2))]
    return torch.as_tensor(np.array(out), dtype=torch.float32)


def test_configs_without_augmentation_train_as_before():
    from tactile_deploy.training.train import _augmentation

    configs = ROOT / "training" / "configs"
    cfg = TrainConfig.load(configs / "cpu_small.json")
    assert cfg.augmentation is None
    x = torch.rand(2, 1, 128, 128)
    assert _augmentation(cfg, None, "cpu", 0) is None
    # the augmented twins differ in the augmentation section (and the CPU twin in its image VAE epochs)
    for clean, aug in (("gpu_paper", "gpu_paper_aug"), ("cpu_adapt", "cpu_adapt_aug")):
        a = json.loads((configs / f"{clean}.json").read_text())
        b = json.loads((configs / f"{aug}.json").read_text())
        assert TrainConfig.load(configs / f"{aug}.json").augmentation is not None
        b.pop("augmentation")
        if clean == "cpu_adapt":
            assert (a["image_vae"].pop("epochs"), b["image_vae"].pop("epochs")) == (12, 18)
        assert {k: v for k, v in a.items() if k != "run_dir"} == {k: v for k, v in b.items() if k != "run_dir"}


def test_bad_ranges_are_refused_with_the_field_name():
    with pytest.raises(ValueError, match="blur_sigma_mm"):
        AugmentationConfig(blur_sigma_mm=(0.5, 0.1))
    with pytest.raises(ValueError, match="extra"):
        AugmentationConfig(perlin=0.1)


def test_gain_is_a_planted_factor_per_map():
    aug = Augmenter(AugmentationConfig(**(OFF | {"gain": (0.6, 1.3)})))
    x = _bumps(64, np.random.default_rng(0))
    y = aug(x, torch.Generator().manual_seed(1))
    ratio = (y / x.clamp(min=1e-6))[x > 0.05].reshape(-1)
    per_map = [(y[i][x[i] > 0.05] / x[i][x[i] > 0.05]) for i in range(len(x))]
    assert all(float(r.max() - r.min()) < 1e-4 for r in per_map)  # one factor per map
    g = torch.stack([r.mean() for r in per_map])
    assert 0.6 <= float(g.min()) and float(g.max()) <= 1.3 and float(g.max() - g.min()) > 0.3
    assert ratio.numel() > 0


def test_blur_equals_scipy_gaussian_filter():
    from scipy.ndimage import gaussian_filter

    aug = Augmenter(AugmentationConfig(**(OFF | {"blur_sigma_mm": (0.55, 0.55)})))
    x = _bumps(2, np.random.default_rng(1))
    x[:, 60:64, 60:70] += 0.4  # a sharp edge
    y = aug(x, torch.Generator().manual_seed(0)).numpy()
    ref = np.stack([gaussian_filter(m.numpy().astype(np.float64), 0.55 / aug.pitch_mm, mode="constant", truncate=8)
                    for m in x])
    assert np.abs(y - ref).max() < 2e-3 * float(x.max())


def test_halo_keeps_the_volume_and_rings_negative():
    """d + a (d - G(d)) moves depth from the ring into the contact: volume unchanged, a negative
    ring of depth a * G(d) outside a flat contact."""
    aug = Augmenter(AugmentationConfig(**(OFF | {"halo_amount": (0.5, 0.5), "halo_sigma_mm": (1.5, 1.5)})))
    c = -17.5 + (np.arange(128) + 0.5) * 35 / 128
    x_mm, y_mm = np.meshgrid(c, -c)
    punch = torch.as_tensor(((x_mm**2 + y_mm**2) < 9.0) * 0.5, dtype=torch.float32)[None]
    y = aug(punch, torch.Generator().manual_seed(0))[0].numpy()
    assert abs(y.sum() - float(punch.sum())) < 1e-3 * float(punch.sum())
    ring = (np.hypot(x_mm, y_mm) > 3.2) & (np.hypot(x_mm, y_mm) < 4.0)
    assert y[ring].max() < 0 and y.min() < -0.05


def test_perlin_noise_has_the_drawn_rms_and_long_wavelengths():
    aug = Augmenter(AugmentationConfig(**(OFF | {"perlin_rms_mm": (0.02, 0.02)})))
    x = torch.zeros(8, 128, 128)
    n = aug(x, torch.Generator().manual_seed(2)).numpy()
    rms = np.sqrt((n ** 2).mean(axis=(1, 2)))
    np.testing.assert_allclose(rms, 0.02, rtol=1e-4)
    spec = np.abs(np.fft.rfft2(n)) ** 2
    f = np.hypot(*np.meshgrid(np.fft.rfftfreq(128, aug.pitch_mm), np.fft.fftfreq(128, aug.pitch_mm)))
    assert spec[:, f < 1 / 1.5].sum() > 0.9 * spec.sum()  # >90 % of the energy above 1.5 mm wavelength


def test_view_box_cuts_only_maps_whose_contact_stays_visible():
    cfg = AugmentationConfig(**(OFF | {"view_box_probability": 1.0, "view_half_width_mm": (10.0, 10.0),
                                       "view_half_height_mm": (7.0, 7.0), "view_offset_mm": 0.0}))
    aug = Augmenter(cfg)
    x = _bumps(16, np.random.default_rng(3))
    y = aug(x, torch.Generator().manual_seed(0))
    c = -17.5 + (np.arange(128) + 0.5) * 35 / 128
    outside = torch.as_tensor((np.abs(c)[None, :] > 10.0) | (np.abs(c)[:, None] > 7.0))
    cut = [bool((y[i] != x[i]).any()) for i in range(len(x))]
    assert any(cut)
    for i in range(len(x)):
        if cut[i]:
            assert float(y[i][outside].abs().max()) == 0.0
            assert torch.equal(y[i][~outside], x[i][~outside])
            assert float(x[i][~outside].sum()) >= 0.7 * float(x[i].sum())


def test_noise_reference_and_probability(tmp_path):
    ref = np.random.default_rng(4).normal(0, 0.003, (128, 128)).astype(np.float32)
    np.save(tmp_path / "noise.npy", ref)
    aug = Augmenter(AugmentationConfig(**(OFF | {"noise_references": (str(tmp_path / "noise.npy"),),
                                                 "noise_reference_gain": (1.0, 1.0)})))
    x = _bumps(3, np.random.default_rng(5))
    np.testing.assert_allclose((aug(x, torch.Generator().manual_seed(0)) - x).numpy(), ref[None].repeat(3, 0), atol=1e-6)
    never = Augmenter(AugmentationConfig(probability=0.0))
    assert torch.equal(never(x, torch.Generator().manual_seed(0)), x)
    np.save(tmp_path / "bad.npy", np.zeros((64, 64), np.float32))
    with pytest.raises(ValueError, match="bad.npy"):
        Augmenter(AugmentationConfig(noise_references=(str(tmp_path / "bad.npy"),)))


def test_training_hook_augments_in_mm():
    """The training hook works on depth normalised by depth_scale_mm: a planted gain g gives
    g x the normalised map whatever the scale."""
    from tactile_deploy.training.train import _augmentation

    class Norm:
        depth_scale_mm = torch.tensor(0.8)

    class Model:
        norm = Norm()

    cfg = TrainConfig.model_validate({"run_dir": "x", "data": {"synthetic": {"n_samples": 2}},
                                      "augmentation": OFF | {"gain": (1.25, 1.25)}})
    x = _bumps(2, np.random.default_rng(6))[:, None] / 0.8
    y = _augmentation(cfg, Model(), torch.device("cpu"), 0)(x)
    torch.testing.assert_close(y, 1.25 * x, rtol=1e-5, atol=1e-6)
