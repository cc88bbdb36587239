"""Residual fingerprints: what the gap between measurement and simulation looks like.

The residual of every sample (measured minus simulated depth, mm, standard grid) is summarised
by the properties that separate physical effects:

* **growth with depth**: the signed mean residual inside each contact against the contact's
  depth, fitted as an offset, linear, quadratic or saturating law (the best by AIC), and the
  exponent of the residual's size against depth;
* **position**: the residual's size at the pad's centre against its edge (contacts split at the
  median radius), its slope with the radius, and its first angular harmonic over the pad;
* **indenter**: the residual's size per indenter;
* **where**: the systematic RMS (noise removed) inside the contacts, in a ring around them (1-2
  contact radii), and outside every region a candidate can reach (presence without contact);
* **contact-centred structure**: the mean residual against the distance from the contact centre
  in contact radii, and its dipole (a shift or tilt) and quadrupole (anisotropy) in the ring
  around the contact, with how consistent their direction is from contact to contact;
* **leading modes**: the SVD of the residuals cropped around each contact (41 x 41 px): the
  share of the energy in the first three modes, and the modes themselves (for the report).

RMS values are systematic: ``sqrt(max(mean r^2 - sigma^2, 0))`` with sigma the pixel noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tactile_deploy.calibration.discrepancy.static import StaticStructure

#: Half-size of the contact-centred crops of the leading modes, pixels.
CROP_HALF_PX = 20


@dataclass
class Fingerprint:
    """Summary numbers (``summary``: JSON-ready) and arrays for the report's figures."""

    summary: dict
    depth_mm: np.ndarray           # (N,) contact depth
    radius_mm: np.ndarray          # (N,) distance of the contact from the pad centre
    amplitude_mm: np.ndarray       # (N,) signed mean residual inside the contact
    rms_in_mm: np.ndarray          # (N,) systematic RMS inside the contact
    radial_profile_mm: np.ndarray  # (bins,) mean residual against rho
    rho_edges: np.ndarray          # (bins + 1,) contact radii
    modes: np.ndarray              # (3, 41, 41)
    outside_structure: bool = False
    notes: list = field(default_factory=list)
    static: StaticStructure | None = None  # of the residual after the best candidate


def _systematic(sq_sum: float, count: float, sigma: float) -> float:
    if count <= 0:
        return 0.0
    return math.sqrt(max(sq_sum / count - sigma * sigma, 0.0))


def _growth_law(depth, amp):
    """Best of offset / linear / quadratic / saturating fits of amp(depth) by AIC."""
    n = len(depth)
    fits = {}
    for name, basis in (("offset", np.ones_like(depth)), ("linear", depth),
                        ("quadratic", depth**2)):
        k = float(basis @ amp / max(basis @ basis, 1e-300))
        rss = float(np.sum((amp - k * basis) ** 2))
        fits[name] = (rss, 1, {"coefficient": k})
    best_sat = None
    for d0 in np.geomspace(0.05, 2.0, 40):
        basis = 1.0 - np.exp(-depth / d0)
        k = float(basis @ amp / max(basis @ basis, 1e-300))
        rss = float(np.sum((amp - k * basis) ** 2))
        if best_sat is None or rss < best_sat[0]:
            best_sat = (rss, 2, {"coefficient": k, "depth_scale_mm": float(d0)})
    fits["saturating"] = best_sat
    aic = {k: n * math.log(max(v[0], 1e-300) / n) + 2 * v[1] for k, v in fits.items()}
    best = min(aic, key=aic.get)
    return best, {k: float(v) for k, v in aic.items()}, fits[best][2]


def residual_fingerprint(residual_mm: np.ndarray, base_mm: np.ndarray, centres_mm: np.ndarray,
                         depth_mm: np.ndarray, indenters: list[str], roi_masks: np.ndarray,
                         pad_mask: np.ndarray, sigma_mm: float, camera,
                         outside_noise: tuple[float, float] | None = None) -> Fingerprint:
    """Fingerprint of residuals (N, 128, 128) mm against base maps (N, 128, 128) mm.

    centres_mm : (N, 2) contact centres (sensor frame); depth_mm : (N,) contact depths;
    roi_masks : (N, 128, 128) bool regions a candidate can reach; camera : the DepthCamera;
    outside_noise : (expected sum, standard deviation) of the noise's squared residual outside
    every ROI, mm^2, when the noise is not white (imaged frames); None: white noise of sigma.
    """
    r = np.asarray(residual_mm, np.float64)
    n = len(r)
    s2 = sigma_mm**2
    pix = camera.pixel_centres_mm()  # (H, W, 2)
    pitch = camera.pitch_mm
    amp = np.zeros(n)
    rms_in = np.zeros(n)
    zone = np.zeros((3, 2))  # inside, ring, outside: (sum r^2, count)
    rho_edges = np.linspace(0.0, 3.0, 13)
    prof_sum = np.zeros(len(rho_edges) - 1)
    prof_cnt = np.zeros(len(rho_edges) - 1)
    dipoles, quads = [], []
    crops = np.zeros((n, 2 * CROP_HALF_PX + 1, 2 * CROP_HALF_PX + 1))
    for s in range(n):
        b = base_mm[s]
        top = float(b.max())
        inside = (b > 0.1 * top) & pad_mask if top > 0 else np.zeros_like(pad_mask)
        a = math.sqrt(max(inside.sum(), 1) * pitch**2 / math.pi)
        dist = np.hypot(pix[..., 0] - centres_mm[s, 0], pix[..., 1] - centres_mm[s, 1])
        rho = dist / max(a, pitch)
        ring = (rho >= 1.0) & (rho < 2.0) & pad_mask & ~inside
        outside = pad_mask & ~roi_masks[s]
        for k, m in enumerate((inside, ring, outside)):
            zone[k] += (float(np.sum(r[s][m] ** 2)), float(m.sum()))
        if inside.any():
            amp[s] = float(r[s][inside].mean())
            rms_in[s] = _systematic(float(np.sum(r[s][inside] ** 2)), inside.sum(), sigma_mm)
        ok = pad_mask & (rho < rho_edges[-1])
        idx = np.digitize(rho[ok], rho_edges) - 1
        prof_sum += np.bincount(idx, weights=r[s][ok], minlength=len(prof_sum))[: len(prof_sum)]
        prof_cnt += np.bincount(idx, minlength=len(prof_cnt))[: len(prof_cnt)]
        band = pad_mask & (rho >= 0.5) & (rho < 1.5)
        if band.sum() > 8:
            psi = np.arctan2(pix[..., 1] - centres_mm[s, 1], pix[..., 0] - centres_mm[s, 0])[band]
            basis = np.stack([np.ones_like(psi), np.cos(psi), np.sin(psi), np.cos(2 * psi),
                              np.sin(2 * psi)], axis=1)
            coef = np.linalg.lstsq(basis, r[s][band], rcond=None)[0]
            dipoles.append(coef[1:3])
            quads.append(coef[3:5])
        row = int(round((camera.half_extent_mm - centres_mm[s, 1]) / pitch - 0.5))
        col = int(round((centres_mm[s, 0] + camera.half_extent_mm) / pitch - 0.5))
        padded = np.pad(np.where(pad_mask, r[s], 0.0), CROP_HALF_PX)
        crops[s] = padded[row: row + 2 * CROP_HALF_PX + 1, col: col + 2 * CROP_HALF_PX + 1]

    depth = np.asarray(depth_mm, np.float64)
    radius = np.hypot(centres_mm[:, 0], centres_mm[:, 1])
    law, aic, law_fit = _growth_law(depth, amp)
    big = rms_in > 0
    exponent = (float(np.polyfit(np.log(depth[big]), np.log(rms_in[big]), 1)[0])
                if big.sum() >= 3 and np.ptp(depth[big]) > 0 else float("nan"))
    split = np.median(radius)
    centre_rms = float(np.sqrt(np.mean(rms_in[radius <= split] ** 2))) if n else 0.0
    edge_rms = float(np.sqrt(np.mean(rms_in[radius > split] ** 2))) if (radius > split).any() \
        else centre_rms
    ang = np.arctan2(centres_mm[:, 1], centres_mm[:, 0])
    harm = np.linalg.lstsq(np.stack([np.ones(n), np.cos(ang), np.sin(ang)], 1), amp,
                           rcond=None)[0] if n >= 3 else np.zeros(3)
    per_indenter = {}
    for name in sorted(set(indenters)):
        sel = np.array([i == name for i in indenters])
        per_indenter[name] = float(np.sqrt(np.mean(rms_in[sel] ** 2)))

    def consistency(vecs):
        if not vecs:
            return 0.0, 0.0
        v = np.array(vecs)
        mean = np.linalg.norm(v.mean(0))
        return float(mean), float(mean / max(np.mean(np.linalg.norm(v, axis=1)), 1e-300))

    dip, dip_c = consistency(dipoles)
    quad, quad_c = consistency(quads)
    flat = crops.reshape(n, -1)
    sv = np.linalg.svd(flat, compute_uv=False) if n else np.zeros(1)
    energy = sv**2
    noise_energy = s2 * (np.count_nonzero(flat) if n else 0)
    excess = max(float(energy.sum()) - noise_energy, 1e-300)
    shares = [float(max(e - noise_energy / max(len(energy), 1), 0.0) / excess)
              for e in energy[:3]]
    modes = np.zeros((3, *crops.shape[1:]))
    if n:
        _, _, vt = np.linalg.svd(flat, full_matrices=False)
        for k in range(min(3, len(vt))):
            modes[k] = vt[k].reshape(crops.shape[1:])
    out_sum, out_cnt = zone[2]
    if outside_noise is not None and out_cnt:
        expected, sd = outside_noise
        out_excess = out_sum / max(expected, 1e-300) - 1.0
        out_z = (out_sum - expected) / max(sd, 1e-300)
    else:
        out_excess = out_sum / (s2 * out_cnt) - 1.0 if out_cnt else 0.0
        out_z = out_excess / math.sqrt(2.0 / out_cnt) if out_cnt else 0.0
    outside_structure = bool(out_cnt and out_z > 4.0 and out_excess > 0.02)
    summary = {
        "growth_with_depth": {"law": law, "aic": aic, "fit": law_fit,
                              "exponent": exponent},
        "position": {"centre_rms_mm": centre_rms, "edge_rms_mm": edge_rms,
                     "edge_over_centre": edge_rms / centre_rms if centre_rms > 0 else None,
                     "split_radius_mm": float(split),
                     "slope_mm_per_mm": float(np.polyfit(radius, amp, 1)[0]) if n >= 2 else 0.0,
                     "angular_harmonic_mm": float(np.hypot(harm[1], harm[2])),
                     "angular_direction_deg": float(np.degrees(np.arctan2(harm[2], harm[1])))},
        "indenter_rms_mm": per_indenter,
        "where_rms_mm": {"inside_contact": _systematic(*zone[0], sigma_mm),
                         "ring_1_2_radii": _systematic(*zone[1], sigma_mm),
                         "outside_reach": _systematic(*zone[2], sigma_mm)},
        "without_contact": {"excess": float(out_excess), "z": float(out_z),
                            "present": outside_structure},
        "contact_centred": {"dipole_mm": dip, "dipole_consistency": dip_c,
                            "quadrupole_mm": quad, "quadrupole_consistency": quad_c},
        "leading_modes": {"energy_shares": shares},
    }
    return Fingerprint(summary, depth, radius, amp, rms_in,
                       np.where(prof_cnt > 0, prof_sum / np.maximum(prof_cnt, 1), 0.0),
                       rho_edges, modes, outside_structure)
