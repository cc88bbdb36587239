"""Two reference methods that public tactile-sensor tools use, for side-by-side comparison.

* :func:`fit_rgb_table`: a 3-D table indexed by the binned RGB difference to the reference
  frame, holding the mean gradient of the training pixels in each bin (empty bins take the
  nearest filled bin). No illumination-offset correction, no saturation handling, no position
  dependence.
* :func:`fit_mlp`: a small per-pixel multilayer perceptron from (R, G, B, column, row) to the
  gradient, trained with Adam on the contact pixels and a sample of far-field pixels.

Both train on the same targets as the main method (sphere of the ball's radius inside 0.8 x
the given contact radius, zero gradient far from the contact; the given circles are used as
they are) and integrate depth with the isotropic Poisson solver (zero depth at the image
border), as those tools do. The MLP needs torch (``pip install tactile-deploy[train]``); it is
imported when the MLP is fitted, and predictions run in numpy.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from tactile_deploy.imaging.poisson import poisson_solver

from .presses import PressSet
from .targets import sphere_gradients_at


def _target_pixels(presses: PressSet, ball_radius_px: float, fraction: float = 0.8,
                   far_factor: float = 3.5, far_stride: int = 3):
    """Per press: (rows, cols, targets (., 2)) of contact pixels and zero-target far pixels."""
    if presses.circles is None:
        raise ValueError("reference methods need contact circles (labels or detections)")
    h, w = presses.shape
    rows, cols = np.mgrid[0:h, 0:w]
    grid = np.zeros((h, w), bool)
    grid[::far_stride, ::far_stride] = True
    out = []
    for cx, cy, a in presses.circles:
        rho = np.hypot(cols - cx, rows - cy)
        inside = rho < min(fraction * a, 0.98 * ball_radius_px)
        far = (rho > far_factor * a) & grid
        r = np.concatenate([rows[inside], rows[far]])
        c = np.concatenate([cols[inside], cols[far]])
        t = np.concatenate([sphere_gradients_at(cols[inside], rows[inside], (cx, cy),
                                                ball_radius_px), np.zeros((far.sum(), 2))])
        out.append((r, c, t))
    return out


class _GradientPredictor:
    """Common tail: image-axis gradients -> depth (mm) with the isotropic Poisson solver."""

    def __init__(self, reference, mm_per_px: float):
        self.reference = reference
        self.mm_per_px = float(mm_per_px)
        self._solver = poisson_solver(reference.shape[:2], "dirichlet", (1.0, 1.0))

    def image_gradients(self, frame):  # pragma: no cover - overridden
        raise NotImplementedError

    def depth(self, frame) -> np.ndarray:
        """Depth map (H, W) float32, mm, positive into the gel."""
        g_col, g_row = self.image_gradients(frame)
        s = np.float32(self.mm_per_px)
        return self._solver.integrate(g_col * s, g_row * s)


class RGBTable(_GradientPredictor):
    """3-D RGB-difference lookup table (see module docstring)."""

    def __init__(self, reference, mm_per_px, lut, bins, lo, hi):
        super().__init__(reference, mm_per_px)
        self.lut, self.bins, self.lo, self.hi = lut, bins, lo, hi
        self._ref = reference.astype(np.float32)

    def _index(self, diff):
        q = np.clip(((diff - self.lo) * (self.bins / (self.hi - self.lo))).astype(np.int64),
                    0, self.bins - 1)
        return (q[..., 0] * self.bins + q[..., 1]) * self.bins + q[..., 2]

    def image_gradients(self, frame):
        g = self.lut[self._index(frame.astype(np.float32) - self._ref)]
        return g[..., 0], g[..., 1]


def fit_rgb_table(presses: PressSet, ball_radius_mm: float, mm_per_px: float, bins: int = 64,
                  lo: float = -128.0, hi: float = 128.0) -> RGBTable:
    """Fit the RGB-difference table (``bins`` per channel over [lo, hi) grey levels)."""
    r_px = ball_radius_mm / mm_per_px
    ref = presses.reference.astype(np.float32)
    table = RGBTable(presses.reference, mm_per_px, None, bins, lo, hi)
    keys, targets = [], []
    for f, (r, c, t) in zip(presses.frames, _target_pixels(presses, r_px)):
        keys.append(table._index(f[r, c].astype(np.float32) - ref[r, c]))
        targets.append(t)
    keys = np.concatenate(keys)
    targets = np.concatenate(targets)
    n = bins ** 3
    cnt = np.bincount(keys, minlength=n)
    lut = np.stack([np.bincount(keys, targets[:, k], minlength=n) for k in range(2)], 1)
    ok = cnt > 0
    lut[ok] /= cnt[ok, None]
    _, ind = ndimage.distance_transform_edt(~ok.reshape(bins, bins, bins), return_indices=True)
    table.lut = lut[np.ravel_multi_index(ind, (bins,) * 3).ravel()].astype(np.float32)
    return table


class PixelMLP(_GradientPredictor):
    """Per-pixel MLP (R, G, B, column, row) -> gradient, evaluated in numpy."""

    def __init__(self, reference, mm_per_px, weights):
        super().__init__(reference, mm_per_px)
        self.weights = weights  # [(W (in, out), b (out,)), ...], tanh between layers
        h, w = reference.shape[:2]
        rows, cols = np.mgrid[0:h, 0:w]
        self._pos = np.stack([cols / (w - 1) - 0.5, rows / (h - 1) - 0.5], -1).reshape(-1, 2)

    @staticmethod
    def features(rgb, pos):
        return np.concatenate([rgb.astype(np.float32) / 127.5 - 1.0, pos], -1).astype(np.float32)

    def image_gradients(self, frame):
        x = self.features(frame.reshape(-1, 3), self._pos)
        for k, (w, b) in enumerate(self.weights):
            x = x @ w + b
            if k < len(self.weights) - 1:
                np.tanh(x, out=x)
        g = x.reshape(*frame.shape[:2], 2)
        return g[..., 0], g[..., 1]


def fit_mlp(presses: PressSet, ball_radius_mm: float, mm_per_px: float, hidden: int = 32,
            steps: int = 800, batch: int = 1024, lr: float = 3e-3, seed: int = 0) -> PixelMLP:
    """Train the per-pixel MLP (two tanh hidden layers of ``hidden`` units) with Adam.

    Runs on one CPU thread (faster than two for this size): ~1 s for 800 steps of 1024 pixels.
    """
    try:
        import torch
    except ImportError as e:  # pragma: no cover - environment dependent
        raise ImportError("the MLP reference method needs torch: pip install "
                          "'tactile-deploy[train]'") from e
    r_px = ball_radius_mm / mm_per_px
    h, w = presses.shape
    xs, ts = [], []
    for f, (r, c, t) in zip(presses.frames, _target_pixels(presses, r_px)):
        pos = np.stack([c / (w - 1) - 0.5, r / (h - 1) - 0.5], -1)
        xs.append(PixelMLP.features(f[r, c], pos))
        ts.append(t.astype(np.float32))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        gen = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)
        x = torch.from_numpy(np.concatenate(xs))
        t = torch.from_numpy(np.concatenate(ts))
        net = torch.nn.Sequential(torch.nn.Linear(5, hidden), torch.nn.Tanh(),
                                  torch.nn.Linear(hidden, hidden), torch.nn.Tanh(),
                                  torch.nn.Linear(hidden, 2))
        opt = torch.optim.Adam(net.parameters(), lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
        for _ in range(steps):
            idx = torch.randint(0, len(x), (batch,), generator=gen)
            loss = torch.mean((net(x[idx]) - t[idx]) ** 2)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        layers = [m for m in net if isinstance(m, torch.nn.Linear)]
        weights = [(m.weight.detach().numpy().T.copy(), m.bias.detach().numpy().copy())
                   for m in layers]
    finally:
        torch.set_num_threads(threads)
    return PixelMLP(presses.reference, mm_per_px, weights)
