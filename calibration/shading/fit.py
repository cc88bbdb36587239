"""Fit the marble shading model (position-dependent binned LUT) to ball presses.

Pipeline (each step a function of this module or of :mod:`.circles`):

1. colour differences ``frame - reference - offset`` with the per-frame illumination offset
   estimated from the non-contact area (:func:`tactile_deploy.imaging.shading.frame_offset`);
2. contact circles: given (labels) or detected, then centres made consistent by a shared colour
   model (:func:`.circles.refine_centres`);
3. training targets: sphere gradients of the **ball's** radius inside a target region around
   each centre, and zero gradient far from the contact (beyond ``far_factor`` contact radii);
   the sunken gel in between has no target, unless the presses carry modelled depth profiles
   (``PressSet.profiles``, e.g. the FEM of the pad: :mod:`.press_profile`), whose slopes it
   then gets, with a lower weight (``ring_stride``);
4. the table: the mean target of each colour bin (saturated channels in a bin of their own),
   smoothed over image position with a Gaussian of ``kernel_sigma_mm`` and stored at nodes
   every ``node_spacing_mm``; where a node has few samples of a bin it falls back to a prior
   (weight ``prior_weight`` samples): the bin's mean over the whole image, or (``prior_model =
   "colour-polynomial"``) a polynomial in colour and position fitted to all samples
   (:mod:`.colour_prior`), which keeps the place's colour-to-slope relation where the steep
   slopes' bins are nearly empty;
5. the target region re-measured on the fitted gradients and the table refitted: first
   ``initial_fraction`` of the given radius, then ``train_fraction`` of the radius where the
   table's radial slope peaks (:func:`.circles.contact_radius_from_gradients` with
   ``plateau_tol=None``; hand-labelled radii are off by several pixels, and a target region
   reaching past the true contact teaches the table wrong slopes). The contact radii reported
   in :class:`ShadingFit` are the contact edges seen by the final table (end of the slope
   plateau);
6. the per-axis weights of the depth integration: the candidate whose integrated training
   presses match their spheres best.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
from scipy import ndimage

from tactile_deploy.imaging.poisson import poisson_solver
from tactile_deploy.imaging.shading import (
    DepthFromShading,
    ShadingHeader,
    ShadingModel,
    colour_bin_index,
    frame_offset,
    node_grid_shape,
    reference_gain,
)

from .circles import (
    ContactNotFoundError,
    contact_radius_from_gradients,
    detect_contact_circle,
    refine_centres,
)
from .colour_prior import ColourPolynomial
from .presses import PressSet
from .targets import sphere_gradients_at


@dataclass(frozen=True)
class ShadingFitConfig:
    """Settings of :func:`fit_shading` (lengths in mm are converted with the sensor's scale)."""

    bins: int = 48                      # colour bins per channel
    colour_min: float = -128.0          # binned colour difference range, grey levels
    colour_max: float = 128.0
    saturation_level: int = 254         # raw value counted as saturated
    node_spacing_mm: float = 2.0        # position grid of the table
    kernel_sigma_mm: float = 1.0        # position smoothing of the table
    prior_sigma_mm: float | None = 3.0  # wider smoothing used where the first has few samples
    prior_weight: float = 1.0           # samples' worth of the prior per node and bin
    prior_model: str = "image-mean"     # "image-mean" or "colour-polynomial" (.colour_prior)
    prior_far_weight: float = 0.1       # weight of the zero-gradient far samples in the polynomial
    prior_position_degree: int = 2      # position dependence of the polynomial's coefficients
    initial_fraction: float = 0.75      # target region / given radius, first fit
    train_fraction: float = 0.9         # target region / radius of the table's steepest slope
    radius_iterations: int = 2          # re-measure radii and refit, times
    centre_iterations: int = 3          # shared-colour-model centre refinement, iterations
    far_factor: float = 3.5             # zero-gradient samples beyond this many contact radii
    far_stride: int = 3                 # subsampling of the far samples, px
    ring_stride: int = 4                # subsampling of the samples with profile targets, px
    reference_gain: bool = True         # bin colour differences x reference_gain(reference)
    offset_inlier_grey: float = 12.0    # see frame_offset
    poisson_weights_x: tuple[float, ...] = (0.02, 0.035, 0.06, 0.1, 0.18, 0.35, 1.0)


@dataclass
class ShadingFit:
    """Result of :func:`fit_shading`: the model and what was learned about the presses.

    circles_input : (N, 3) px circles given or detected.
    circles : (N, 3) px refined centres and the contact edges seen by the final table.
    poisson_scores_um : {weight_x: mean in-sample sphere residual (um)} of the weight choice.
    """

    model: ShadingModel
    circles_input: np.ndarray
    circles: np.ndarray
    colour_model_rms_grey: float
    poisson_scores_um: dict[float, float] = field(default_factory=dict)


# --------------------------------------------------------------------------------- samples
def colour_differences(presses: PressSet, inlier_grey: float = 12.0):
    """Offset-corrected colour differences (N, H, W, 3) float32 and saturation (N, H, W, 3)."""
    ref = presses.reference
    diffs = np.empty(presses.frames.shape, np.float32)
    for i, f in enumerate(presses.frames):
        diffs[i] = f.astype(np.float32) - ref - frame_offset(f, ref, inlier_grey)
    return diffs


def _training_samples(diffs, saturated, circles, radii, ball_radius_px, cfg: ShadingFitConfig,
                      profiles=None, mm_per_px: float = 1.0):
    """(bin index, target (., 2), column, row, far (.,) bool) of the contact, ring and
    far-field samples.

    Inside ``radii`` the sphere of the ball; where a press has a profile
    (:class:`~tactile_deploy.calibration.shading.press_profile.PressProfile`), the ring from there out to
    ``far_factor`` contact radii gets the profile's slope, one pixel in ``ring_stride`` along
    each axis (a pixel there weighs 1 / ring_stride^2 of a contact pixel); beyond it zero
    gradient.
    """
    h, w = diffs.shape[1:3]
    far_r, far_c = np.mgrid[0:h:cfg.far_stride, 0:w:cfg.far_stride]
    keys, targets, cs, rs, fars = [], [], [], [], []
    for i in range(len(diffs)):
        cx, cy, a = circles[i]
        rad = radii[i]
        prof = None if profiles is None else profiles[i]
        reach = cfg.far_factor * a if prof is not None else rad
        r0, r1 = max(int(cy - reach), 0), min(int(cy + reach) + 2, h)
        c0, c1 = max(int(cx - reach), 0), min(int(cx + reach) + 2, w)
        rows, cols = np.mgrid[r0:r1, c0:c1]
        rho = np.hypot(cols - cx, rows - cy)
        m = rho < rad
        far = np.hypot(far_c - cx, far_r - cy) > cfg.far_factor * a
        parts = [(rows[m], cols[m], sphere_gradients_at(cols[m], rows[m], (cx, cy),
                                                        ball_radius_px))]
        if prof is not None:
            ring = ((rho >= rad) & (rho < reach)
                    & (rows % cfg.ring_stride == 0) & (cols % cfg.ring_stride == 0))
            parts.append((rows[ring], cols[ring],
                          prof.image_gradients(cols[ring], rows[ring], (cx, cy), mm_per_px)))
        parts.append((far_r[far], far_c[far], np.zeros((int(far.sum()), 2))))
        for k, (r, c, t) in enumerate(parts):
            keys.append(colour_bin_index(diffs[i][r, c], saturated[i][r, c], cfg.bins,
                                         cfg.colour_min, cfg.colour_max))
            targets.append(t)
            cs.append(c)
            rs.append(r)
            fars.append(np.full(len(r), k == len(parts) - 1))
    return (np.concatenate(keys), np.concatenate(targets), np.concatenate(cs).astype(float),
            np.concatenate(rs).astype(float), np.concatenate(fars))


# --------------------------------------------------------------------------------- table
def fit_table(keys, targets, cols, rows, shape, spacing_px: float, sigma_px: float,
              bins: int, prior_weight: float, prior_sigma_px: float | None = None,
              prior: ColourPolynomial | None = None):
    """Position-dependent table from samples.

    keys : (S,) flat colour-bin indices; targets : (S, 2) image-axis gradients; cols, rows :
    (S,) pixel positions. Where a node has few samples of a bin, the table falls back, with the
    weight of ``prior_weight`` samples, to ``prior`` evaluated at the node and bin if given;
    otherwise to the same estimate with a wider kernel (``prior_sigma_px``, if given) and then
    to the bin's mean over the whole image. Returns (slot_of_bin ((bins+1)^3,) int64, table
    (ny, nx, slots, 2) float32).
    """
    nb = bins + 1
    n_bins = nb ** 3
    cnt = np.bincount(keys, minlength=n_bins).astype(np.float64)
    glob = np.stack([np.bincount(keys, targets[:, k], minlength=n_bins) for k in range(2)], 1)
    ok = cnt > 0
    glob[ok] /= cnt[ok, None]
    # every bin points at the nearest populated bin (in bin units)
    _, ind = ndimage.distance_transform_edt(~ok.reshape(nb, nb, nb), return_indices=True)
    nearest = np.ravel_multi_index(ind, (nb, nb, nb)).ravel()
    populated = np.flatnonzero(ok)
    slot_of = np.full(n_bins, -1, np.int64)
    slot_of[populated] = np.arange(len(populated))
    slot_of_bin = slot_of[nearest]
    n_slots = len(populated)
    # position smoothing: samples -> cells (sparse) -> Gaussian weights to nodes
    h, w = shape
    cell = max(sigma_px / 2.0, 1.0)
    ncx, ncy = int(np.ceil(w / cell)), int(np.ceil(h / cell))
    ci = (np.minimum((rows / cell).astype(int), ncy - 1) * ncx
          + np.minimum((cols / cell).astype(int), ncx - 1))
    slot = slot_of[keys]
    ny, nx = node_grid_shape(shape, spacing_px)
    node_r, node_c = np.meshgrid(np.arange(ny) * spacing_px, np.arange(nx) * spacing_px,
                                 indexing="ij")
    cell_c = (np.arange(ncx) + 0.5) * cell
    cell_r = (np.arange(ncy) + 0.5) * cell
    cc, rr = np.meshgrid(cell_c, cell_r)
    d2 = ((node_c.reshape(-1, 1) - cc.reshape(1, -1)) ** 2
          + (node_r.reshape(-1, 1) - rr.reshape(1, -1)) ** 2)     # (nodes, cells)
    sums = [scipy.sparse.csr_matrix((vals, (ci, slot)), shape=(ncx * ncy, n_slots))
            for vals in (np.ones(len(keys)), targets[:, 0], targets[:, 1])]
    if prior is not None:
        fallback = prior.at_nodes(populated, node_c, node_r)      # (nodes, slots, 2)
        sigmas = [sigma_px]
    else:
        fallback = glob[populated]                                # (slots, 2)
        sigmas = ([prior_sigma_px] if prior_sigma_px else []) + [sigma_px]
    est = fallback
    for sigma in sigmas:
        wn = np.exp(-d2 / (2.0 * sigma ** 2))
        acc = [np.asarray((m.T @ wn.T).T) for m in sums]          # (nodes, slots) each
        den = acc[0] + prior_weight
        est = np.stack([(acc[1] + prior_weight * est[..., 0]) / den,
                        (acc[2] + prior_weight * est[..., 1]) / den], -1)
    table = est
    return slot_of_bin, table.reshape(ny, nx, n_slots, 2).astype(np.float32)


def _build_model(keys, targets, cols, rows, far, shape, presses_n, mm_per_px, ball_radius_mm,
                 cfg: ShadingFitConfig, weights=(1.0, 1.0), metrics=None) -> ShadingModel:
    spacing_px = cfg.node_spacing_mm / mm_per_px
    prior = None
    if cfg.prior_model == "colour-polynomial":
        prior = ColourPolynomial.fit(keys, targets, cols, rows, shape, cfg.bins,
                                     np.where(far, cfg.prior_far_weight, 1.0),
                                     position_degree=cfg.prior_position_degree)
    elif cfg.prior_model != "image-mean":
        raise ValueError(f"prior_model must be 'image-mean' or 'colour-polynomial', got "
                         f"{cfg.prior_model!r}")
    slot_of_bin, table = fit_table(keys, targets, cols, rows, shape, spacing_px,
                                   cfg.kernel_sigma_mm / mm_per_px, cfg.bins, cfg.prior_weight,
                                   cfg.prior_sigma_mm / mm_per_px if cfg.prior_sigma_mm else None,
                                   prior)
    header = ShadingHeader(
        image_height_px=shape[0], image_width_px=shape[1], mm_per_px=mm_per_px,
        ball_radius_mm=ball_radius_mm, bins=cfg.bins, colour_min=cfg.colour_min,
        colour_max=cfg.colour_max, saturation_level=cfg.saturation_level,
        node_spacing_px=spacing_px, n_slots=table.shape[2],
        reference_gain=cfg.reference_gain,
        offset_inlier_grey=cfg.offset_inlier_grey, poisson_weight_x=weights[0],
        poisson_weight_y=weights[1], n_presses=presses_n, fit_metrics=metrics or {})
    return ShadingModel(header, slot_of_bin, table)


# --------------------------------------------------------------------------------- weights
def sphere_residual_um(depth_mm, circle, ball_radius_px: float, mm_per_px: float,
                       region_fraction: float = 0.8) -> float:
    """RMS (um) of depth minus the ball's sphere near ``circle``'s centre, inside
    ``region_fraction`` of its radius, after fitting a vertical offset and a small centre shift
    (linearised). A quick score for choices made during fitting.
    """
    h, w = depth_mm.shape
    cx, cy, a = circle
    rad = region_fraction * a
    r0, r1 = max(int(cy - rad), 0), min(int(cy + rad) + 2, h)
    c0, c1 = max(int(cx - rad), 0), min(int(cx + rad) + 2, w)
    rows, cols = np.mgrid[r0:r1, c0:c1]
    m = np.hypot(cols - cx, rows - cy) < rad
    depth_mm = depth_mm[r0:r1, c0:c1]
    dc = (cols[m] - cx) * mm_per_px
    dr = (rows[m] - cy) * mm_per_px
    r_mm = ball_radius_px * mm_per_px
    q = np.sqrt(np.maximum(r_mm ** 2 - dc ** 2 - dr ** 2, 1e-9))
    sphere = q - r_mm
    a_mat = np.c_[np.ones(m.sum()), dc / q, dr / q]
    res = depth_mm[m] - sphere
    coef = np.linalg.lstsq(a_mat, res, rcond=None)[0]
    return float(np.sqrt(np.mean((res - a_mat @ coef) ** 2)) * 1e3)


def choose_poisson_weights(model: ShadingModel, presses: PressSet, circles, ball_radius_px,
                           candidates, grads=None) -> tuple[float, dict[float, float]]:
    """The x weight (y weight 1) whose integrated presses match their spheres best.

    Scores every candidate (mean :func:`sphere_residual_um` over the presses); the choice is
    the minimum of a parabola in log(weight) through the best candidate and its neighbours
    (clamped to the candidates' range), so that near-ties do not flip between grid values.
    """
    if grads is None:
        runner = DepthFromShading(model, presses.reference)
        grads = [runner.image_gradients(f) for f in presses.frames]
    s = np.float32(model.header.mm_per_px)
    cand = sorted(float(w) for w in candidates)
    scores = {}
    for wx in cand:
        solver = poisson_solver(presses.shape, "dirichlet", (wx, 1.0))
        errs = [sphere_residual_um(solver.integrate(gc * s, gr * s), circles[i], ball_radius_px,
                                   model.header.mm_per_px)
                for i, (gc, gr) in enumerate(grads)]
        scores[wx] = float(np.mean(errs))
    k = int(np.argmin([scores[w] for w in cand]))
    best = cand[k]
    if 0 < k < len(cand) - 1:
        x = np.log([cand[k - 1], cand[k], cand[k + 1]])
        y = np.array([scores[cand[k - 1]], scores[cand[k]], scores[cand[k + 1]]])
        a, b, _ = np.polyfit(x, y, 2)
        if a > 0:
            best = float(np.exp(np.clip(-b / (2 * a), x[0], x[2])))
    return best, scores


# --------------------------------------------------------------------------------- main
def _detect(frame, reference, name: str) -> np.ndarray:
    """:func:`.circles.detect_contact_circle`; its error names the press ``name``."""
    try:
        return detect_contact_circle(frame, reference)
    except ContactNotFoundError as e:
        raise ContactNotFoundError(f"press {name}: {e}") from None


def fit_shading(presses: PressSet, ball_radius_mm: float, mm_per_px: float,
                config: ShadingFitConfig | None = None, circles=None) -> ShadingFit:
    """Fit a :class:`ShadingModel` to ball presses.

    presses : reference and press frames; their ``circles`` (px) are used unless ``circles``
        is given; without either, each press is detected (:func:`.circles.detect_contact_circle`).
    ball_radius_mm : radius of the ball, mm. mm_per_px : sensor-plane scale, mm per pixel.
    """
    cfg = config or ShadingFitConfig()
    if not ball_radius_mm > 0 or not mm_per_px > 0:
        raise ValueError(f"ball_radius_mm and mm_per_px must be > 0, got {ball_radius_mm}, "
                         f"{mm_per_px}")
    if len(presses) < 2:
        raise ValueError(f"need at least 2 presses to fit a shading model, got {len(presses)}")
    r_px = ball_radius_mm / mm_per_px
    if circles is None:
        circles = presses.circles
    if circles is None:
        circles = np.array([_detect(f, presses.reference, n)
                            for f, n in zip(presses.frames, presses.names)])
    circles_in = np.asarray(circles, np.float64).copy()
    if circles_in.shape != (len(presses), 3):
        raise ValueError(f"circles must be ({len(presses)}, 3) px, got {circles_in.shape}")
    if np.any(circles_in[:, 2] >= r_px):
        bad = int(np.argmax(circles_in[:, 2] >= r_px))
        raise ValueError(f"press {presses.names[bad]}: contact radius {circles_in[bad, 2]:.1f} px "
                         f">= ball radius {r_px:.1f} px; check --ball-radius-mm and --mm-per-px")
    diffs = colour_differences(presses, cfg.offset_inlier_grey)
    saturated = presses.frames >= cfg.saturation_level
    circ, rms = refine_centres(diffs, saturated, circles_in, r_px, cfg.centre_iterations)
    if cfg.reference_gain:
        diffs *= reference_gain(presses.reference)
    radii = cfg.initial_fraction * circ[:, 2]
    model = None
    for it in range(cfg.radius_iterations + 1):
        samples = _training_samples(diffs, saturated, circ, radii, r_px, cfg, presses.profiles,
                                    mm_per_px)
        model = _build_model(*samples, presses.shape, len(presses), mm_per_px, ball_radius_mm,
                             cfg)
        if it == cfg.radius_iterations:
            break
        runner = DepthFromShading(model, presses.reference)
        for i, f in enumerate(presses.frames):
            g_col, g_row = runner.image_gradients(f)
            a = contact_radius_from_gradients(g_col, g_row, circ[i, :2], circles_in[i, 2],
                                              plateau_tol=None)
            radii[i] = min(cfg.train_fraction * a, 0.98 * r_px)
    runner = DepthFromShading(model, presses.reference)
    grads = [runner.image_gradients(f) for f in presses.frames]
    for i, g in enumerate(grads):   # contact radii as seen by the final table
        circ[i, 2] = contact_radius_from_gradients(*g, circ[i, :2], circles_in[i, 2])
    # scored like the evaluation: refined centres, 0.8 x the given contact radius
    score_circles = np.c_[circ[:, :2], circles_in[:, 2]]
    wx, scores = choose_poisson_weights(model, presses, score_circles, r_px,
                                        cfg.poisson_weights_x, grads)
    metrics = {"colour_model_rms_grey": rms,
               "in_sample_sphere_rms_um": float(min(scores.values()))}
    header = model.header.model_copy(update={"poisson_weight_x": wx, "poisson_weight_y": 1.0,
                                             "fit_metrics": metrics})
    model = ShadingModel(header, model.slot_of_bin, model.table)
    return ShadingFit(model, circles_in, circ, rms, scores)
