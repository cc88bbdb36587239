"""Static structure: a residual that is the same in every depth map, wherever the contact is.

A grain of dust on the gel, a scratch in the coating or a dent of compression set adds the same
relief to every map. Small and local, it holds too little of the residual's energy for the
energy tests (a 13 um grain 0.6 mm wide adds 1.7 % to the noise's energy over 40 maps), but it
is the same in every map, so the mean of the maps' residuals shows it above a noise that falls
as one over the square root of the number of maps.

The test, on the residual ``r_s`` (mm) of every sample after the best candidate (the held-out
maps with the named effect; the sensor model's maps when none is named), on the standard grid
(rows: +y down, columns: +x, sensor frame, mm):

* every sample contributes at the pixels of its region of interest (where the maps with the
  candidate are known: the tables' ROI) away from its contact: beyond ``CONTACT_MARGIN``
  contact radii of the pixels the contact presses (its map above a tenth of its peak), where a
  static relief is not pressed flat and where a candidate's leftover error is largest;
* per pixel, the mean residual over the ``n`` samples that contribute there and its standard
  error from the noise, ``sqrt(sum_s v_s) / n`` with ``v_s`` the pixel noise variance (white
  noise: sigma^2 with sigma taken ``SIGMA_SE`` standard errors high; imaged frames: each
  contact's noise realisations at that pixel, their estimation error added the same way), or
  from the samples' own scatter about that mean, ``s / sqrt(n)``, where it is larger: the noise
  is the sensor model's, and where the model lacks the effect it can be too small (a domed
  gel's frames carry 3x the flat model's imaged noise toward the rim); a relief common to
  every map does not add to the scatter;
* z = mean / standard error; a pixel is above the threshold when ``|z|`` exceeds the
  Bonferroni bound of a family-wise false-alarm probability ``FAMILY_ALPHA`` over the pixels
  tested (those with at least ``MIN_SAMPLES`` samples): ``t = Phi^-1(1 - alpha / 2M)``, 5.3 for
  the 12,900 pixels of a 35 mm pad's 128 x 128 map; Bonferroni is conservative for noise that is
  correlated between neighbouring pixels;
* static structure is present when at least ``MIN_PIXELS`` pixels above the threshold touch
  (8-neighbours): a relief on the gel is resolved over several pixels, a lone pixel is a
  camera defect or an outlier of the noise's tails.

The report gives the strongest blob: its centre (sensor frame, mm), its peak mean residual
(um, signed: positive = the measured surface deeper than the model's), its z and its area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt, label
from scipy.stats import norm

#: Family-wise probability that effect-free maps show static structure anywhere.
FAMILY_ALPHA = 1e-3
#: Fewest touching pixels above the threshold that count as a static relief.
MIN_PIXELS = 3
#: Fewest samples a pixel's mean must come from to be tested.
MIN_SAMPLES = 4
#: A sample's pixels within this many contact radii of its pressed pixels are left out.
CONTACT_MARGIN = 1.0
#: The noise's sigma is taken this many standard errors above its estimate.
SIGMA_SE = 2.0


@dataclass
class StaticStructure:
    """Outcome of :func:`static_structure`.

    mean_mm : (H, W) mean residual per pixel (0 where untested); count : (H, W) samples it is
    the mean of; z : (H, W) its z-score (0 where untested); tested : (H, W) bool pixels tested;
    threshold_z : the Bonferroni bound; blobs : per blob above the threshold (strongest first)
    its centre x_mm, y_mm (sensor frame), peak mean residual peak_um, peak |z|, pixels and
    area_mm2."""

    present: bool
    mean_mm: np.ndarray
    count: np.ndarray
    z: np.ndarray
    tested: np.ndarray
    threshold_z: float
    blobs: list

    def summary(self) -> dict:
        """JSON-ready numbers (the strongest blobs, at most 5)."""
        return {"present": self.present, "threshold_z": self.threshold_z,
                "pixels_tested": int(self.tested.sum()),
                "max_abs_z": float(np.abs(self.z).max()) if self.tested.any() else 0.0,
                "blobs": self.blobs[:5]}


def static_structure(residual_mm: np.ndarray, base_mm: np.ndarray, pad_mask: np.ndarray,
                     camera, sigma_mm: float, sigma_se_mm: float = 0.0,
                     noise_var_mm2: np.ndarray | None = None,
                     noise_var_rel_se: float = 0.0,
                     region: np.ndarray | None = None) -> StaticStructure:
    """The static test of the module docstring.

    residual_mm : (N, H, W) measured minus the model's (with the best candidate) maps, mm;
    base_mm : (N, H, W) the sensor model's maps (where each contact presses); pad_mask : (H, W);
    camera : the DepthCamera of the grid; sigma_mm, sigma_se_mm : white pixel noise and the
    standard error of its estimate; noise_var_mm2 : (N, H, W) per-sample pixel noise variance
    (imaged frames: from the contact's realisations; overrides sigma_mm) and noise_var_rel_se
    the relative standard error of the summed variance; region : (N, H, W) bool pixels where
    ``residual_mm`` is known (None: the whole pad).
    """
    r = np.asarray(residual_mm, np.float64)
    n, h, w = r.shape
    pitch = camera.pitch_mm
    use = np.zeros((n, h, w), bool)
    for s in range(n):
        b = base_mm[s]
        top = float(b.max())
        if top <= 0:
            use[s] = pad_mask
            continue
        pressed = (b > 0.1 * top) & pad_mask
        if not pressed.any():
            use[s] = pad_mask
            continue
        a = math.sqrt(pressed.sum() * pitch**2 / math.pi)  # contact radius, mm
        use[s] = pad_mask & (distance_transform_edt(~pressed) * pitch > CONTACT_MARGIN * a)
    if region is not None:
        use &= np.asarray(region, bool)
    count = use.sum(axis=0)
    tested = pad_mask & (count >= MIN_SAMPLES)
    total = np.where(use, r, 0.0).sum(axis=0)
    mean = np.where(tested, total / np.maximum(count, 1), 0.0)
    if noise_var_mm2 is None:
        s_hi = sigma_mm + SIGMA_SE * sigma_se_mm
        var_sum = count * s_hi**2
    else:
        var_sum = np.where(use, noise_var_mm2, 0.0).sum(axis=0) * (
            1.0 + SIGMA_SE * noise_var_rel_se)
    se = np.sqrt(np.maximum(var_sum, 1e-300)) / np.maximum(count, 1)
    # the samples' scatter about the mean, per pixel (n - 1 degrees of freedom)
    sq = np.where(use, (r - mean[None]) ** 2, 0.0).sum(axis=0)
    scatter = np.sqrt(sq / np.maximum(count - 1, 1) / np.maximum(count, 1))
    se = np.maximum(se, scatter)
    z = np.where(tested, mean / se, 0.0)
    m = int(tested.sum())
    t = float(norm.isf(FAMILY_ALPHA / (2.0 * max(m, 1))))
    labels, k = label(tested & (np.abs(z) > t), structure=np.ones((3, 3), bool))
    pix = camera.pixel_centres_mm()
    blobs = []
    for j in range(1, k + 1):
        sel = labels == j
        size = int(sel.sum())
        if size < MIN_PIXELS:
            continue
        zz = np.abs(z[sel])
        i = int(np.argmax(zz))
        wts = zz / zz.sum()
        blobs.append({"x_mm": float(wts @ pix[..., 0][sel]), "y_mm": float(wts @ pix[..., 1][sel]),
                      "peak_um": float(1e3 * mean[sel][i]), "z": float(zz[i]),
                      "pixels": size, "area_mm2": float(size * pitch**2)})
    blobs.sort(key=lambda b: -b["z"])
    return StaticStructure(bool(blobs), mean, count, z, tested, t, blobs)


def describe_blob(blob: dict) -> str:
    """One blob of :attr:`StaticStructure.blobs` in words: where (sensor frame), how high, how
    sure and how large."""
    return (f"x {blob['x_mm']:.2f} mm, y {blob['y_mm']:.2f} mm (sensor frame): "
            f"{blob['peak_um']:+.1f} um mean residual, z {blob['z']:.0f}, "
            f"{blob['area_mm2']:.2f} mm^2")
