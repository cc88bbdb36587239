"""Augmentation of simulated depth maps towards what a sensor's imaging pipeline delivers.

The paper ("Image Augmentations") adds Perlin noise and a real sensor's noise reference image to
the synthetic depth maps. The virtual GelSlim sensors show what else separates a plugin's depth
map from the simulator's (``python -m tactile_deploy.training.adaptation.domain_gap``, docs/adaptation.md):
shading and integration blur the contact (Gaussian sigma 0.1-0.7 mm), scale its depth (gain
0.57-1.31), leave a negative halo around it (down to -0.1 to -0.4 mm) and a low-frequency drift
(RMS 2-30 um), and the camera sees only part of the pad (depth 0 outside its view). Data flow of
:func:`augment` (every step drawn per map, depth in mm on the model grid)::

    depth (B, R, R) mm
      -> blur          Gaussian G_b, b ~ U(blur_sigma_mm)                          (shading smooths)
      -> halo          d + a (d - G_s(d)), a ~ U(halo_amount), s ~ U(halo_sigma_mm) (integration ring)
                       (blur and halo are one linear filter, applied by FFT)
      -> gain          x g, log g ~ U(log gain)                                   (depth scale error)
      -> view box      0 outside a random box, when the contact stays visible     (camera field)
      -> Perlin noise  gradient noise, octaves of perlin_wavelengths_mm, RMS ~ U(perlin_rms_mm)
      -> reference     + c x noise reference image, c ~ U(noise_reference_gain)   (paper)
      -> pixel noise   Gaussian, sigma pixel_noise_mm
    augmented depth (B, R, R) mm

Each map is augmented with probability ``probability`` (the others pass unchanged). The image
VAE learns to reconstruct the *clean* map from the augmented one (a denoising VAE: its output is
the adaptation target, the paper's noise filter); the projection is trained on latents of
augmented maps. Frames: image rows (row 0 = largest y), pixel pitch ``pitch_mm``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from tactile_deploy.training.config import AugmentationConfig

#: Perlin maps computed once per :class:`Augmenter`, PERLIN_MARGIN pixels larger than the map
#: (crops at random offsets).
PERLIN_BANK = 256
PERLIN_MARGIN = 64


class Augmenter:
    """Draws augmentations of batches of depth maps (see module docstring)."""

    def __init__(self, cfg: AugmentationConfig, resolution: int = 128, half_extent_mm: float = 17.5,
                 device="cpu"):
        self.cfg = cfg
        self.resolution = int(resolution)
        self.pitch_mm = 2.0 * half_extent_mm / resolution
        self.half_extent_mm = float(half_extent_mm)
        self.device = torch.device(device)
        refs = []
        for path in cfg.noise_references:
            a = np.load(path, allow_pickle=False)
            if a.shape != (resolution, resolution) or not np.all(np.isfinite(a)):
                raise ValueError(f"augmentation.noise_references: {path} must be a finite ({resolution}, "
                                 f"{resolution}) depth map in mm (a plugin's noise_reference.npy), got {a.shape}")
            refs.append(torch.as_tensor(a, dtype=torch.float32))
        self.references = torch.stack(refs).to(self.device) if refs else None
        c = -half_extent_mm + (np.arange(resolution) + 0.5) * self.pitch_mm
        self.x_mm = torch.as_tensor(c, dtype=torch.float32, device=self.device)  # columns
        self.y_mm = torch.as_tensor(-c, dtype=torch.float32, device=self.device)  # rows (row 0 = largest y)
        # FFT size: the map plus 3 sigma of the widest Gaussian as zero padding (no wrap-around)
        sigma_max = max(cfg.blur_sigma_mm[1], cfg.halo_sigma_mm[1])
        self.fft_size = resolution + 2 * int(math.ceil(3.0 * sigma_max / self.pitch_mm / 2.0))
        f = torch.fft.fftfreq(self.fft_size, d=self.pitch_mm, device=self.device)  # cycles per mm
        fr = torch.fft.rfftfreq(self.fft_size, d=self.pitch_mm, device=self.device)
        self.freq2 = (f[:, None] ** 2 + fr[None, :] ** 2).float()
        #: Bank of unit-RMS Perlin maps (B, R, R), drawn with a random symmetry and shift.
        self.perlin_bank = self._perlin_bank(PERLIN_BANK) if cfg.perlin_rms_mm[1] > 0 else None

    def __call__(self, depth_mm: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Augmented copy of ``depth_mm`` (B, R, R) or (B, 1, R, R), mm."""
        return augment(depth_mm, self, generator)

    # -- pieces ------------------------------------------------------------------------------
    def transfer(self, sigma_mm: torch.Tensor) -> torch.Tensor:
        """Transfer function (B, n, n // 2 + 1) of Gaussians of per-map sigma (B,) mm."""
        return torch.exp(-2.0 * math.pi**2 * sigma_mm[:, None, None] ** 2 * self.freq2)

    def filter(self, depth: torch.Tensor, transfer: torch.Tensor) -> torch.Tensor:
        """(B, R, R) filtered by ``transfer`` (FFT with zero padding: no wrap-around)."""
        r, n = self.resolution, self.fft_size
        return torch.fft.irfft2(torch.fft.rfft2(depth, s=(n, n)) * transfer, s=(n, n))[:, :r, :r]

    def _perlin_bank(self, n: int) -> torch.Tensor:
        g = torch.Generator(device=self.device).manual_seed(0x5045524C)
        side = self.resolution + PERLIN_MARGIN
        total = torch.zeros(n, side, side, device=self.device)
        for wl in self.cfg.perlin_wavelengths_mm:
            total = total + wl * _perlin_octave(n, side, wl / self.pitch_mm, self.device, g)
        return total

    def perlin(self, b: int, generator: torch.Generator | None) -> torch.Tensor:
        """(B, R, R) gradient noise, unit RMS per map: octaves of ``perlin_wavelengths_mm`` with
        amplitudes proportional to their wavelengths (a random crop of a map of the bank, randomly
        flipped and transposed)."""
        k = torch.randint(len(self.perlin_bank), (b,), device=self.device, generator=generator)
        r = self.resolution
        i0, j0 = (int(v) for v in torch.randint(PERLIN_MARGIN + 1, (2,), generator=generator, device=self.device))
        maps = self.perlin_bank[k, i0:i0 + r, j0:j0 + r]
        maps = maps / maps.pow(2).mean(dim=(1, 2), keepdim=True).sqrt().clamp(min=1e-12)
        flip = torch.randint(8, (b,), device=self.device, generator=generator)
        maps = torch.where((flip & 1).bool()[:, None, None], maps.flip(1), maps)
        maps = torch.where((flip & 2).bool()[:, None, None], maps.flip(2), maps)
        return torch.where((flip & 4).bool()[:, None, None], maps.transpose(1, 2), maps)


def _uniform(b, lo_hi, device, generator) -> torch.Tensor:
    lo, hi = lo_hi
    return lo + (hi - lo) * torch.rand(b, device=device, generator=generator)


def _perlin_octave(b: int, r: int, cell_px: float, device, generator) -> torch.Tensor:
    """(B, r, r) Perlin gradient noise with lattice cells of ``cell_px`` pixels, random offset."""
    n = int(math.ceil(r / cell_px)) + 2
    angle = 2.0 * math.pi * torch.rand(b, n, n, device=device, generator=generator)
    grad = torch.stack([torch.cos(angle), torch.sin(angle)], dim=-1)  # (B, n, n, 2)
    offset = torch.rand(b, 2, device=device, generator=generator)  # lattice shift, cells
    p = (torch.arange(r, device=device, dtype=torch.float32) + 0.5) / cell_px
    py = p[None, :, None] + offset[:, 0, None, None]  # (B, r, 1)
    px = p[None, None, :] + offset[:, 1, None, None]  # (B, 1, r)
    iy, ix = py.floor().long(), px.floor().long()
    fy, fx = py - iy, px - ix
    bi = torch.arange(b, device=device)[:, None, None]

    def corner(dy, dx):
        g = grad[bi, iy + dy, ix + dx]  # (B, r, r, 2)
        return g[..., 0] * (fy - dy) + g[..., 1] * (fx - dx)

    def fade(t):
        return t * t * t * (t * (6.0 * t - 15.0) + 10.0)

    wy, wx = fade(fy), fade(fx)
    top = corner(0, 0) * (1 - wx) + corner(0, 1) * wx
    bottom = corner(1, 0) * (1 - wx) + corner(1, 1) * wx
    return top * (1 - wy) + bottom * wy


def augment(depth_mm: torch.Tensor, aug: Augmenter, generator: torch.Generator | None = None) -> torch.Tensor:
    """Augmented copy of depth maps (B, R, R) or (B, 1, R, R), mm (module docstring)."""
    cfg = aug.cfg
    shape = depth_mm.shape
    d = depth_mm.reshape(-1, aug.resolution, aug.resolution).to(aug.device, torch.float32)
    b = d.shape[0]
    dev = aug.device
    active = torch.rand(b, device=dev, generator=generator) < cfg.probability
    out = d
    if cfg.blur_sigma_mm[1] > 0 or cfg.halo_amount[1] > 0:  # one linear filter: blur, then halo
        h = aug.transfer(_uniform(b, cfg.blur_sigma_mm, dev, generator))
        a = _uniform(b, cfg.halo_amount, dev, generator)[:, None, None]
        out = aug.filter(out, h * ((1.0 + a) - a * aug.transfer(_uniform(b, cfg.halo_sigma_mm, dev, generator))))
    if cfg.gain != (1.0, 1.0):
        log_g = _uniform(b, (math.log(cfg.gain[0]), math.log(cfg.gain[1])), dev, generator)
        out = out * torch.exp(log_g)[:, None, None]
    if cfg.view_box_probability > 0:
        out = _view_box(out, d, aug, generator)
    if cfg.perlin_rms_mm[1] > 0:
        out = out + _uniform(b, cfg.perlin_rms_mm, dev, generator)[:, None, None] * aug.perlin(b, generator)
    if aug.references is not None:
        k = torch.randint(len(aug.references), (b,), device=dev, generator=generator)
        c = _uniform(b, cfg.noise_reference_gain, dev, generator)[:, None, None]
        out = out + c * aug.references[k]
    if cfg.pixel_noise_mm > 0:
        out = out + cfg.pixel_noise_mm * torch.randn(out.shape, device=dev, generator=generator)
    out = torch.where(active[:, None, None], out, d)
    return out.reshape(shape).to(depth_mm.device)


def _view_box(out: torch.Tensor, clean: torch.Tensor, aug: Augmenter, generator) -> torch.Tensor:
    """Zero outside a random axis-aligned box (half-widths from ``view_half_width_mm`` /
    ``view_half_height_mm``, centre within ``view_offset_mm``), for maps drawn with probability
    ``view_box_probability`` whose contact keeps ``view_min_visible`` of its volume in the box."""
    cfg = aug.cfg
    b = out.shape[0]
    dev = aug.device
    hw = _uniform(b, cfg.view_half_width_mm, dev, generator)[:, None, None]
    hh = _uniform(b, cfg.view_half_height_mm, dev, generator)[:, None, None]
    cx = _uniform(b, (-cfg.view_offset_mm, cfg.view_offset_mm), dev, generator)[:, None, None]
    cy = _uniform(b, (-cfg.view_offset_mm, cfg.view_offset_mm), dev, generator)[:, None, None]
    inside = ((aug.x_mm[None, None, :] - cx).abs() <= hw) & ((aug.y_mm[None, :, None] - cy).abs() <= hh)
    pos = clean.clamp(min=0.0)
    visible = (pos * inside).sum(dim=(1, 2)) / pos.sum(dim=(1, 2)).clamp(min=1e-12)
    use = (torch.rand(b, device=dev, generator=generator) < cfg.view_box_probability) & (visible >= cfg.view_min_visible)
    return torch.where(use[:, None, None] & ~inside, torch.zeros_like(out), out)
