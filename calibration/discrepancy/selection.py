"""Selecting the missing effect: fits on the response tables, held-out contacts, an information
criterion, a null calibrated on effect-free replicates, look-alikes and pairs.

Data flow of :func:`select_effect`::

    residual of every sample on its contact's ROI (the contact's nuisance projected out)
      -> sufficient statistics per sample: D D^T, D y, y.y (D: the stacked tabulated changes)
    per candidate: fit on all samples (largest drop of the squared residual on the tables)
                   cross-validation by contact groups (K folds): held-out gain, noise units
                   information criterion (BIC) of the all-sample fit
    null: effect-free replicates (white noise of the estimated sigma, or for imaged frames the
          model's own noise realisations, through the same tables and folds) -> the 99th
          percentile of the best candidate's held-out gain
    bootstrap over contact groups: gain intervals, how often each candidate is best, parameter
          intervals (refits)
    excess energy of the residual over the noise (is anything there?), explained fractions
    pairs with the best candidate (a second effect present?)

Gains are ``(SSE_null - SSE_candidate) / sigma^2`` summed over held-out samples: twice the
held-out log-likelihood ratio under white Gaussian noise. A candidate is *significant* when its
gain exceeds the null threshold, its bootstrap interval does not reach below 0 and at least two
contacts gain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from tactile_deploy.calibration.discrepancy.noise import NoiseEstimate
from tactile_deploy.calibration.discrepancy.tables import CandidateTable, ResponseTables

#: Quantile of the effect-free best gain a candidate must exceed.
NULL_QUANTILE = 0.99
#: Excess energy of the residual over the noise that counts as structure: z-score and fraction.
STRUCTURE_Z = 4.0
STRUCTURE_MIN_EXCESS = 0.02
#: A candidate within this bootstrap probability of beating the best is a look-alike.
LOOKALIKE_PROBABILITY = 0.05
#: ... and so is one that explains the excess energy within this share of the best: two effects
#: that the data cannot tell apart differ only by their tables' interpolation error, which is
#: systematic (the same sign on every contact), so the bootstrap alone would call one better.
LOOKALIKE_SHARE = 0.01
#: A second candidate must add this share of the excess energy to count as a second effect.
PAIR_MIN_SHARE = 0.05


@dataclass
class SufficientStats:
    """Per sample: gram (N, R, R) = D D^T, proj (N, R) = D y, energy (N,) = y.y (mm^2),
    dof (N,) residual degrees of freedom (ROI pixels minus nuisance dimensions), groups (N,)
    contact-group labels; blocks: per table the slice of its rows in R; for imaged frames the
    same of the contact's J noise realisations: noise_proj (N, R, J) = D n_j, noise_energy
    (N, J) = n_j.n_j (else None)."""

    gram: np.ndarray
    proj: np.ndarray
    energy: np.ndarray
    dof: np.ndarray
    groups: np.ndarray
    blocks: dict
    noise_proj: np.ndarray | None = None
    noise_energy: np.ndarray | None = None


def sufficient_stats(tables: ResponseTables, measured_mm: np.ndarray, sample_contact: np.ndarray,
                     groups: np.ndarray) -> SufficientStats:
    """Statistics of the samples' residuals ``measured_mm`` (N, 128, 128) against their contacts'
    base maps (``sample_contact`` (N,): index of each sample's contact in ``tables``)."""
    blocks, start = {}, 0
    for t in tables.tables:
        blocks[t.name] = slice(start, start + len(t.node_coords))
        start += len(t.node_coords)
    n = len(sample_contact)
    gram_c, d_c, nproj_c, nenergy_c = [], [], [], []
    for i in range(len(tables.contacts)):
        rows = []
        for t in tables.tables:
            d = t.deltas[i].astype(np.float64)
            rows.append(d if t.usable[i] and t.testable else np.zeros_like(d))
        d = tables.project(i, np.concatenate(rows, axis=0))
        d_c.append(d)
        gram_c.append(d @ d.T)
        if tables.noise_maps is not None:
            nm = tables.noise_maps[i].reshape(len(tables.noise_maps[i]), -1)
            y = tables.project(i, nm[:, tables.roi[i]].astype(np.float64))
            nproj_c.append(d @ y.T)
            nenergy_c.append(np.einsum("jk,jk->j", y, y))
    gram = np.zeros((n, start, start))
    proj = np.zeros((n, start))
    energy = np.zeros(n)
    dof = np.zeros(n)
    noise_proj = noise_energy = None
    if nproj_c:
        noise_proj = np.stack([nproj_c[int(i)] for i in sample_contact])
        noise_energy = np.stack([nenergy_c[int(i)] for i in sample_contact])
    for s in range(n):
        i = int(sample_contact[s])
        roi = tables.roi[i]
        y = np.asarray(measured_mm[s], np.float64).ravel()[roi] - tables.base[i].ravel()[roi]
        y = tables.project(i, y)
        gram[s] = gram_c[i]
        proj[s] = d_c[i] @ y
        energy[s] = float(y @ y)
        q = 0 if tables.nuisance[i] is None else tables.nuisance[i].shape[1]
        dof[s] = len(roi) - q
    return SufficientStats(gram, proj, energy, dof, np.asarray(groups), blocks, noise_proj,
                           noise_energy)


# ------------------------------------------------------------------------------- fitting
class TableFit:
    """Fits of one candidate on summed statistics: the coordinates that most reduce the squared
    residual, ``max_phi 2 w(phi).b - w(phi)^T A w(phi)``, inside the candidate's fit range."""

    def __init__(self, table: CandidateTable, grid_points: int | None = None):
        self.table = table
        p = len(table.axes)
        g = grid_points or (241 if p == 1 else 31)
        axes = [np.linspace(lo, hi, g) for lo, hi in table.bounds]
        self.grid = np.array(np.meshgrid(*axes, indexing="ij")).reshape(p, -1).T
        self.grid_w = table.weights(self.grid)

    def reduction(self, coords, A, b) -> float:
        w = self.table.weights(coords)[0]
        return float(2.0 * w @ b - w @ A @ w)

    def fit(self, A, b, polish: bool = True) -> tuple[np.ndarray, float]:
        W = self.grid_w
        red = 2.0 * W @ b - np.einsum("gi,ij,gj->g", W, A, W)
        k = int(np.argmax(red))
        best = self.grid[k]
        if not polish:
            return best, float(red[k])
        bounds = self.table.bounds
        res = optimize.minimize(lambda x: -self.reduction(x, A, b), best, method="L-BFGS-B",
                                bounds=bounds, options={"maxiter": 50})
        if -res.fun > red[k]:
            return np.asarray(res.x), float(-res.fun)
        return best, float(red[k])


@dataclass
class CandidateStats:
    """Selection numbers of one candidate (gains in noise units, coordinates in its table's)."""

    name: str
    testable: bool
    note: str
    coords: np.ndarray | None = None
    params: dict = field(default_factory=dict)
    intervals: dict = field(default_factory=dict)
    fold_coords: np.ndarray | None = None
    heldout: np.ndarray | None = None  # (N,) held-out drop of the squared residual, mm^2
    gain: float = 0.0
    gain_interval: tuple[float, float] = (0.0, 0.0)
    delta_bic: float = 0.0
    explained: float = 0.0
    best_frequency: float = 0.0
    significant: bool = False


@dataclass
class Selection:
    """Outcome of :func:`select_effect`."""

    candidates: list[CandidateStats]
    noise: NoiseEstimate
    folds: list[np.ndarray]
    null_threshold: float
    null_gains: np.ndarray
    excess: float
    excess_z: float
    structure: bool
    energy: float
    dof: float
    best: str | None
    lookalikes: list[str]
    pair: dict | None

    def stats(self, name: str) -> CandidateStats:
        for c in self.candidates:
            if c.name == name:
                return c
        raise KeyError(name)


def contact_folds(groups: np.ndarray, k: int, seed: int) -> list[np.ndarray]:
    """K boolean test masks over samples, whole contact groups per fold (shuffled by seed)."""
    labels = np.unique(groups)
    if len(labels) < 4:
        raise ValueError(f"held-out selection needs at least 4 distinct contacts, got "
                         f"{len(labels)}; measure more contacts")
    k = min(k, len(labels))
    order = np.random.default_rng(seed).permutation(labels)
    fold_of = {g: j % k for j, g in enumerate(order)}
    f = np.array([fold_of[g] for g in groups])
    return [f == j for j in range(k)]


def _cv(fitter: TableFit, blk: slice, gram, proj, folds, polish=True):
    """Held-out drops (N,) and fold coordinates (K, p)."""
    A_all = gram[:, blk, blk]
    b_all = proj[:, blk]
    red = np.zeros(len(proj))
    coords = []
    A_sum, b_sum = A_all.sum(0), b_all.sum(0)
    for test in folds:
        A = A_sum - A_all[test].sum(0)
        b = b_sum - b_all[test].sum(0)
        phi, _ = fitter.fit(A, b, polish)
        w = fitter.table.weights(phi)[0]
        red[test] = 2.0 * b_all[test] @ w - np.einsum("nij,i,j->n", A_all[test], w, w)
        coords.append(phi)
    return red, np.array(coords)


def select_effect(tables: ResponseTables, stats: SufficientStats, noise: NoiseEstimate,
                  n_folds: int = 5, null_replicates: int = 200, bootstrap: int = 400,
                  param_bootstrap: int = 100, seed: int = 0) -> Selection:
    """Fit, cross-validate and compare every candidate (see the module docstring)."""
    rng = np.random.default_rng(seed)
    sigma2 = noise.sigma_mm**2
    folds = contact_folds(stats.groups, n_folds, seed)
    n_pix = float(stats.dof.sum())
    testable = [t for t in tables.tables if t.testable]
    fitters = {t.name: TableFit(t) for t in testable}
    results: dict[str, CandidateStats] = {}
    for t in tables.tables:
        results[t.name] = CandidateStats(t.name, t.testable, t.note)
    for t in testable:
        blk = stats.blocks[t.name]
        f = fitters[t.name]
        phi, red_all = f.fit(stats.gram[:, blk, blk].sum(0), stats.proj[:, blk].sum(0))
        heldout, fold_coords = _cv(f, blk, stats.gram, stats.proj, folds)
        r = results[t.name]
        r.coords, r.params = phi, t.params(phi)
        r.fold_coords, r.heldout = fold_coords, heldout
        r.gain = float(heldout.sum() / sigma2)
        r.delta_bic = float(-red_all / sigma2 + len(phi) * math.log(max(n_pix, 2.0)))

    # Null: effect-free replicates through the same tables and folds.
    null = _null_gains(tables, stats, testable, fitters, folds, noise, null_replicates, rng)
    threshold = float(np.quantile(null, NULL_QUANTILE)) if len(null) else 0.0

    # Bootstrap over contact groups: gain intervals and how often each candidate is best.
    labels, inverse = np.unique(stats.groups, return_inverse=True)
    names = [t.name for t in testable]
    if names:
        H = np.stack([results[nm].heldout for nm in names], axis=1) / sigma2  # (N, C)
        counts = rng.multinomial(len(labels), np.full(len(labels), 1.0 / len(labels)),
                                 size=bootstrap)
        boot = counts[:, inverse] @ H  # (B, C)
        winner = np.argmax(boot, axis=1)
        for j, nm in enumerate(names):
            r = results[nm]
            r.gain_interval = (float(np.quantile(boot[:, j], 0.025)),
                               float(np.quantile(boot[:, j], 0.975)))
            r.best_frequency = float(np.mean(winner == j))
    energy = float(stats.energy.sum())
    excess = energy / (sigma2 * n_pix) - 1.0
    sd = math.sqrt(2.0 * noise.energy_factor / max(n_pix, 1.0)
                   + (2.0 * noise.se_mm / noise.sigma_mm) ** 2)
    excess_z = excess / sd
    structure = bool(excess_z > STRUCTURE_Z and excess > STRUCTURE_MIN_EXCESS)
    for nm in names:
        r = results[nm]
        r.explained = float(r.gain / (excess * n_pix)) if excess > 0 else 0.0
        # above the null, never below 0 on resampled contacts (0: resamples without a contact
        # that shows it, e.g. no non-round indenter), and gained on at least 2 contacts
        per_group = np.bincount(inverse, weights=r.heldout, minlength=len(labels))
        r.significant = bool(r.gain > threshold and r.gain_interval[0] >= 0
                             and np.sum(per_group > 0) >= 2)

    significant = [nm for nm in names if results[nm].significant]
    best = max(significant, key=lambda nm: results[nm].gain) if significant else None
    lookalikes: list[str] = []
    pair = None
    if best is not None:
        pair = _best_pair(tables, stats, fitters, folds, best, names, results, sigma2, threshold,
                          excess * n_pix)
        # a look-alike explains the same structure as the best: about as well, and adding
        # nothing to it (a candidate that adds is a second effect, not an alternative)
        jb = names.index(best)
        for nm in significant:
            if nm == best or (pair is not None and nm == pair["second"]):
                continue
            beats = np.mean(boot[:, names.index(nm)] >= boot[:, jb])
            close = results[best].explained - results[nm].explained <= LOOKALIKE_SHARE
            if beats >= LOOKALIKE_PROBABILITY or close:
                lookalikes.append(nm)
        _intervals(tables, stats, results[best], fitters[best], counts, inverse,
                   param_bootstrap)
        for nm in lookalikes:
            _intervals(tables, stats, results[nm], fitters[nm], counts, inverse,
                       param_bootstrap)
    order = [t.name for t in tables.tables]
    return Selection([results[nm] for nm in order], noise, folds, threshold, null, excess,
                     excess_z, structure, energy, n_pix, best, lookalikes, pair)


def _null_gains(tables, stats, testable, fitters, folds, noise, replicates, rng) -> np.ndarray:
    """Best held-out gain of every replicate of effect-free data: white noise of sigma, or with
    noise realisations (imaged frames) one of its contact's realisations per sample, with a
    random sign."""
    if not testable or replicates <= 0:
        return np.zeros(0)
    sigma = noise.sigma_mm
    n, R = stats.gram.shape[:2]
    if stats.noise_proj is None:
        vals, vecs = np.linalg.eigh(stats.gram)  # per sample: D D^T = V diag(vals) V^T
        sqrt_roots = vecs * np.sqrt(np.clip(vals, 0.0, None))[:, None, :]  # (N, R, R)
    best = np.zeros(replicates)
    for k in range(replicates):
        if stats.noise_proj is None:
            z = rng.standard_normal((n, R))
            proj = sigma * np.einsum("nij,nj->ni", sqrt_roots, z)
        else:
            j = rng.integers(stats.noise_proj.shape[2], size=n)
            sign = rng.choice((-1.0, 1.0), size=n)
            proj = sign[:, None] * stats.noise_proj[np.arange(n), :, j]
        gains = []
        for t in testable:
            red, _ = _cv(fitters[t.name], stats.blocks[t.name], stats.gram, proj, folds,
                         polish=False)
            gains.append(red.sum() / sigma**2)
        best[k] = max(gains)
    return best


def _intervals(tables, stats, result: CandidateStats, fitter: TableFit, counts, inverse,
               replicates: int) -> None:
    """95 % bootstrap intervals (refits over resampled contact groups) of every parameter."""
    blk = stats.blocks[result.name]
    A_all = stats.gram[:, blk, blk]
    b_all = stats.proj[:, blk]
    t = fitter.table
    informative = np.einsum("nii->n", A_all) > 0
    draws = []
    for c in counts[:replicates]:
        w = c[inverse].astype(np.float64)
        if not np.any(w[informative] > 0):  # no contact that shows the effect
            continue
        phi, _ = fitter.fit(np.einsum("n,nij->ij", w, A_all), w @ b_all)
        draws.append(t.params(phi))
    for key in t.candidate.fitted_params:
        value = result.params[key]
        vals = np.array([d[key] for d in draws])
        if key == "azimuth_deg":  # circular: unwrap around the estimate
            vals = value + (vals - value + 180.0) % 360.0 - 180.0
        result.intervals[key] = (float(np.quantile(vals, 0.025)),
                                 float(np.quantile(vals, 0.975)))


def _best_pair(tables, stats, fitters, folds, best, names, results, sigma2, threshold,
               excess_units):
    """The second candidate that, fitted together with the best (changes added), raises the
    held-out gain most; ``None`` when none raises it by more than the null threshold and
    ``PAIR_MIN_SHARE`` of the excess energy (``excess_units``, noise units)."""
    out = None
    for nm in names:
        if nm == best:
            continue
        red = _pair_cv(fitters[best], fitters[nm], stats.blocks[best], stats.blocks[nm],
                       stats, folds)
        gain = float(red.sum() / sigma2)
        rise = gain - results[best].gain
        if rise > max(threshold, PAIR_MIN_SHARE * excess_units) and (
                out is None or rise > out["rise"]):
            out = {"second": nm, "gain": gain, "rise": rise}
    if out is not None:
        out["coords"] = _pair_fit(fitters[best], fitters[out["second"]], stats.blocks[best],
                                  stats.blocks[out["second"]], stats,
                                  np.ones(len(stats.proj), bool))
    return out


def _pair_fit(fa: TableFit, fb: TableFit, ba: slice, bb: slice, stats, train):
    """Coordinates ``(phi_a, phi_b)`` of the additive two-candidate model fitted on ``train``
    (alternating fits, each candidate given the other's change)."""
    gram, proj = stats.gram, stats.proj
    Aaa = gram[train][:, ba, ba].sum(0)
    Abb = gram[train][:, bb, bb].sum(0)
    Aab = gram[train][:, ba, bb].sum(0)
    pa, pb = proj[train][:, ba].sum(0), proj[train][:, bb].sum(0)
    phi_a = fa.fit(Aaa, pa, polish=False)[0]
    phi_b = fb.fit(Abb, pb, polish=False)[0]
    for k in range(6):
        polish = k == 5
        wa = fa.table.weights(phi_a)[0]
        phi_b = fb.fit(Abb, pb - Aab.T @ wa, polish)[0]
        wb = fb.table.weights(phi_b)[0]
        phi_a = fa.fit(Aaa, pa - Aab @ wb, polish)[0]
    return phi_a, phi_b


def _pair_cv(fa: TableFit, fb: TableFit, ba: slice, bb: slice, stats, folds) -> np.ndarray:
    """Held-out drops of the additive two-candidate model, alternating fits per fold."""
    gram, proj = stats.gram, stats.proj
    red = np.zeros(len(proj))
    for test in folds:
        phi_a, phi_b = _pair_fit(fa, fb, ba, bb, stats, ~test)
        wa, wb = fa.table.weights(phi_a)[0], fb.table.weights(phi_b)[0]
        w = np.zeros(proj.shape[1])
        w[ba] += wa
        w[bb] += wb
        red[test] = 2.0 * proj[test] @ w - np.einsum("nij,i,j->n", gram[test], w, w)
    return red
