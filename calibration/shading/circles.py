"""Contact circles of ball presses: detection (OpenCV) and refinement from the data.

Circles are ``(column, row, radius)`` in image pixels. Three steps, each usable on its own:

* :func:`detect_contact_circle` finds a press without labels: the colour difference to the
  reference (illumination offset removed) is smoothed, thresholded (Otsu), the largest blob is
  kept, and a circle is fitted robustly to the ridge of the colour change along rays from the
  blob's centre. Rays that leave the image are dropped, so contacts cut by the border still fit.
* :func:`refine_centres` moves every centre so that one smooth colour model, shared by all
  presses, explains the colours inside the contacts best: colour = polynomial in the sphere's
  surface normal (cubic) whose coefficients vary smoothly (quadratically) over the image. Hand
  labels (good to 2-3 px) and detections (biased by the uneven colour response) become
  mutually consistent. A common shift of all centres cannot be seen in the colours alone; it is
  kept at the mean of the input circles.
* :func:`contact_radius_from_gradients` puts the contact edge where the radial slope of a
  reconstructed gradient field peaks: inside the contact the slope of the sphere grows with the
  radius, outside the gel bends back towards the flat far field.
"""

from __future__ import annotations

import numpy as np

from tactile_deploy.imaging.shading import frame_offset


class ContactNotFoundError(ValueError):
    """No contact could be found in a frame."""


def difference_image(frame, reference, inlier_grey: float = 12.0) -> np.ndarray:
    """``frame - reference - offset`` (H, W, 3) float32, grey levels (offset: frame_offset)."""
    off = frame_offset(frame, reference, inlier_grey)
    return frame.astype(np.float32) - reference.astype(np.float32) - off


# --------------------------------------------------------------------------------- detection
def _fit_circle_irls(pts: np.ndarray, iterations: int = 10) -> tuple[np.ndarray, float]:
    """Algebraic circle fit with Huber-like reweighting; returns ((col, row, r), scatter px)."""
    w = np.ones(len(pts))
    sol = None
    scatter = 0.0
    for _ in range(iterations):
        a = np.c_[pts[:, 0], pts[:, 1], np.ones(len(pts))]
        b = (pts ** 2).sum(1)
        s = np.linalg.lstsq(a * w[:, None], b * w, rcond=None)[0]
        cx, cy = s[0] / 2, s[1] / 2
        r = float(np.sqrt(max(s[2] + cx * cx + cy * cy, 1e-12)))
        res = np.hypot(pts[:, 0] - cx, pts[:, 1] - cy) - r
        scatter = 1.4826 * float(np.median(np.abs(res))) + 1e-6
        w = 1.0 / np.maximum(1.0, np.abs(res) / (2.0 * scatter))
        sol = np.array([cx, cy, r])
    return sol, scatter


def detect_contact_circle(frame, reference, smooth_px: float = 1.5, n_rays: int = 90,
                          min_radius_px: float = 4.0) -> np.ndarray:
    """Contact circle (column, row, radius) px of one press, without labels.

    frame, reference : (H, W, 3) uint8 RGB.
    Raises ContactNotFoundError when no blob of at least ``min_radius_px`` stands out.
    """
    import cv2
    from scipy.ndimage import map_coordinates

    diff = difference_image(frame, reference)
    smooth = cv2.GaussianBlur(diff, (0, 0), smooth_px)
    mag = np.linalg.norm(smooth, axis=-1)
    # pixel noise from the high-pass residual (robust), grey levels
    noise = 1.4826 * float(np.median(np.abs(diff - smooth))) + 1e-3
    peak = float(mag.max())
    if peak < 10.0 * noise:
        raise ContactNotFoundError(f"no contact: largest colour change {peak:.1f} grey levels is "
                                   f"below 10 x the pixel noise ({noise:.2f})")
    m8 = np.clip(mag * (255.0 / peak), 0, 255).astype(np.uint8)
    _, bw = cv2.threshold(m8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    bw = cv2.morphologyEx(bw, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    n, _labels, stats, cent = cv2.connectedComponentsWithStats(bw)
    if n < 2:
        raise ContactNotFoundError("no contact: nothing above the Otsu threshold")
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    r0 = float(np.sqrt(stats[k, cv2.CC_STAT_AREA] / np.pi))
    if r0 < min_radius_px:
        raise ContactNotFoundError(f"no contact: largest blob has radius {r0:.1f} px < "
                                   f"{min_radius_px} px")
    c0 = cent[k]
    h, w = mag.shape
    for _ in range(2):
        th = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
        rad = np.arange(0.3 * r0, 1.6 * r0, 0.25)
        xs = c0[0] + rad[None] * np.cos(th)[:, None]
        ys = c0[1] + rad[None] * np.sin(th)[:, None]
        inside = (xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1)
        prof = map_coordinates(mag, [ys, xs], order=1, mode="nearest")
        prof[~inside] = -np.inf
        k = np.argmax(prof, axis=1)
        # keep rays whose ridge lies inside the image and is not at the search limit
        ok = inside[np.arange(n_rays), k] & (k > 0) & (k < len(rad) - 1) \
            & inside[np.arange(n_rays), np.minimum(k + 4, len(rad) - 1)]
        if ok.sum() < 8:
            raise ContactNotFoundError(f"no contact: only {int(ok.sum())} of {n_rays} rays "
                                       "found a ridge inside the image")
        pts = np.c_[xs[np.arange(n_rays), k][ok], ys[np.arange(n_rays), k][ok]]
        circ, _ = _fit_circle_irls(pts)
        c0, r0 = circ[:2], circ[2]
    if not (r0 >= min_radius_px and np.all(np.isfinite(circ))):
        raise ContactNotFoundError(f"no contact: fitted radius {r0:.1f} px")
    return circ


# --------------------------------------------------------------------------------- refinement
def _normal_basis(ux, uy):
    """Cubic polynomial basis (N, 10) of the normal's in-plane components and its derivatives."""
    o = np.ones_like(ux)
    z = np.zeros_like(ux)
    b = np.stack([o, ux, uy, ux * ux, ux * uy, uy * uy, ux ** 3, ux * ux * uy, ux * uy * uy,
                  uy ** 3], -1)
    bx = np.stack([z, o, z, 2 * ux, uy, z, 3 * ux * ux, 2 * ux * uy, uy * uy, z], -1)
    by = np.stack([z, z, o, z, ux, 2 * uy, z, ux * ux, 2 * ux * uy, 3 * uy * uy], -1)
    return b, bx, by


def _position_basis(cols, rows, shape):
    h, w = shape
    x = (cols - w / 2.0) / (0.5 * max(h, w))
    y = (rows - h / 2.0) / (0.5 * max(h, w))
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], -1)


class ColourNormalModel:
    """Colour difference (3,) as a smooth function of surface normal and image position.

    colour = sum_k,l C[k, l] * B_k(n_col, n_row) * P_l(column, row), B cubic in the normal's
    in-plane components (n = (pixel - centre) / R for a sphere), P quadratic in position.
    Fitted by linear least squares on unsaturated pixels inside the contacts.
    """

    def __init__(self, shape: tuple[int, int]):
        self.shape = shape
        self.coef = None

    def _design(self, ux, uy, cols, rows):
        b, _, _ = _normal_basis(ux, uy)
        p = _position_basis(cols, rows, self.shape)
        return (b[:, :, None] * p[:, None, :]).reshape(len(ux), -1)

    def fit(self, ux, uy, cols, rows, colours) -> float:
        """Fit to samples (N,) and colours (N, 3); returns the RMS residual, grey levels."""
        a = self._design(ux, uy, cols, rows)
        ata = a.T @ a + 1e-6 * np.eye(a.shape[1])
        self.coef = np.linalg.solve(ata, a.T @ colours)
        return float(np.sqrt(np.mean((colours - a @ self.coef) ** 2)))

    def predict_with_derivatives(self, ux, uy, cols, rows):
        """Colour (N, 3) and its derivatives along the normal's two components, (N, 3) each."""
        b, bx, by = _normal_basis(ux, uy)
        p = _position_basis(cols, rows, self.shape)
        c = self.coef.reshape(10, p.shape[1], 3)
        cp = np.einsum("klc,nl->nkc", c, p)
        return (np.einsum("nk,nkc->nc", b, cp), np.einsum("nk,nkc->nc", bx, cp),
                np.einsum("nk,nkc->nc", by, cp))


def _contact_samples(diff, saturated, circle, fraction, stride):
    h, w = diff.shape[:2]
    cx, cy, a = circle
    r = fraction * a
    r0, r1 = max(int(cy - r), 0), min(int(cy + r) + 1, h)
    c0, c1 = max(int(cx - r), 0), min(int(cx + r) + 1, w)
    rows, cols = np.mgrid[r0:r1:stride, c0:c1:stride]
    keep = (np.hypot(cols - cx, rows - cy) < r) & ~saturated[rows, cols].any(-1)
    rows = rows[keep].astype(np.float64)
    cols = cols[keep].astype(np.float64)
    return cols, rows, diff[rows.astype(int), cols.astype(int)].astype(np.float64)


def refine_centres(diffs, saturated, circles, ball_radius_px: float, iterations: int = 3,
                   fraction: float = 0.75, stride: int = 2) -> tuple[np.ndarray, float]:
    """Centres made consistent with one shared :class:`ColourNormalModel`.

    diffs : (N, H, W, 3) float32 colour differences (offset removed), grey levels.
    saturated : (N, H, W, 3) bool, saturated channels (left out).
    circles : (N, 3) px initial circles; radii are kept; pixels within ``fraction`` of the
        initial radius (around the initial centre) are used.
    Returns (refined circles (N, 3), RMS colour residual of the last model fit, grey levels).
    The mean centre is kept equal to the mean of the input centres.
    """
    circles = np.asarray(circles, np.float64)
    n = len(circles)
    shape = diffs.shape[1:3]
    samples = [_contact_samples(diffs[i], saturated[i], circles[i], fraction, stride)
               for i in range(n)]
    centres = circles[:, :2].copy()
    model = ColourNormalModel(shape)
    rms = float("nan")
    for _ in range(iterations):
        ux = np.concatenate([(s[0] - centres[i, 0]) / ball_radius_px
                             for i, s in enumerate(samples)])
        uy = np.concatenate([(s[1] - centres[i, 1]) / ball_radius_px
                             for i, s in enumerate(samples)])
        rms = model.fit(ux, uy, np.concatenate([s[0] for s in samples]),
                        np.concatenate([s[1] for s in samples]),
                        np.concatenate([s[2] for s in samples]))
        new = centres.copy()
        for i, (cols, rows, col) in enumerate(samples):
            c = centres[i].copy()
            for _gn in range(3):  # Gauss-Newton on the centre
                f, fx, fy = model.predict_with_derivatives((cols - c[0]) / ball_radius_px,
                                                           (rows - c[1]) / ball_radius_px,
                                                           cols, rows)
                jx = -fx.ravel() / ball_radius_px
                jy = -fy.ravel() / ball_radius_px
                res = (col - f).ravel()
                jtj = np.array([[jx @ jx, jx @ jy], [jx @ jy, jy @ jy]]) + 1e-9 * np.eye(2)
                step = np.linalg.solve(jtj, np.array([jx @ res, jy @ res]))
                step = np.clip(step, -2.0, 2.0)
                c += step
                if np.abs(step).max() < 0.01:
                    break
            new[i] = c
        new += circles[:, :2].mean(0) - new.mean(0)
        centres = new
    out = circles.copy()
    out[:, :2] = centres
    return out, rms


def radial_slope_profile(g_col, g_row, centre, max_radius_px: float, step_px: float = 1.0):
    """Mean radial slope (outward descent of depth) in rings around ``centre``.

    Returns (ring radii (M,) px, mean slope (M,) dimensionless, NaN for empty rings).
    """
    h, w = g_col.shape
    r0, r1 = max(int(centre[1] - max_radius_px), 0), min(int(centre[1] + max_radius_px) + 2, h)
    c0, c1 = max(int(centre[0] - max_radius_px), 0), min(int(centre[0] + max_radius_px) + 2, w)
    g_col = g_col[r0:r1, c0:c1]
    g_row = g_row[r0:r1, c0:c1]
    cols = np.arange(c0, c1)[None, :] - centre[0]
    rows = np.arange(r0, r1)[:, None] - centre[1]
    rho = np.hypot(cols, rows)
    slope = -(g_col * cols + g_row * rows) / np.maximum(rho, 1e-6)
    m = rho < max_radius_px
    ring = (rho[m] / step_px).astype(int)
    nr = int(np.ceil(max_radius_px / step_px))
    cnt = np.bincount(ring, minlength=nr)[:nr]
    s = np.bincount(ring, slope[m], minlength=nr)[:nr]
    with np.errstate(invalid="ignore", divide="ignore"):
        prof = s / cnt
    return (np.arange(nr) + 0.5) * step_px, prof


def contact_radius_from_gradients(g_col, g_row, centre, radius_guess_px: float,
                                  search=(0.7, 1.4), plateau_tol: float | None = 0.03) -> float:
    """Contact radius px from the ring-averaged radial slope (1 px rings, 3-ring smoothing).

    The profile is searched in ``search`` x ``radius_guess_px`` for its maximum. With
    ``plateau_tol`` (the contact edge), the radius is the outer edge of the last ring, going
    outwards from the maximum, whose slope is within ``plateau_tol`` of it: a table that has
    not seen slopes as steep as the contact edge's flattens the profile just inside the edge,
    and the end of that plateau is the edge. With ``plateau_tol=None`` it is the location of
    the maximum itself (parabola through the largest ring and its neighbours), which lies at
    or inside that plateau.
    """
    radii, prof = radial_slope_profile(g_col, g_row, centre, search[1] * radius_guess_px + 2)
    prof = np.convolve(np.nan_to_num(prof, nan=-np.inf), np.ones(3) / 3.0, mode="same")
    lo = int(search[0] * radius_guess_px)
    hi = len(prof) - 2
    if hi <= lo + 1:
        return float(radius_guess_px)
    k = lo + int(np.argmax(prof[lo:hi]))
    if plateau_tol is None:
        a, b, c = prof[k - 1], prof[k], prof[k + 1]
        den = a - 2 * b + c
        shift = 0.5 * (a - c) / den if np.isfinite(den) and den < 0 else 0.0
        return float(radii[k] + np.clip(shift, -0.5, 0.5))
    peak = prof[k]
    while k + 1 < hi and prof[k + 1] >= (1.0 - plateau_tol) * peak:
        k += 1
    return float(radii[k] + 0.5)
