"""Procedural indenters for the read-out's training: random pressing faces of many kinds and sizes.

A ball calibrates slopes; what a read-out meets on a robot is flats with edges, lines, rings,
dots, corners, holes and curved parts from a fraction of a millimetre to the width of the view.
:func:`random_indenter` draws one such face as a height map (the envelope: height of the
pressing surface above its lowest point, mm, indenter frame) and wraps it as an
:class:`~tactile_deploy.indenters.base.Indenter` with that envelope on a grid
(:class:`GridIndenter`); the virtual sensor presses it like any other indenter (only its
intrusion and footprint are used).

Families (:data:`FAMILIES`), each with its sizes drawn per indenter:

==============  ===============================================================================
``flat``        flat punch: disc, ellipse, rectangle, rounded rectangle or regular polygon,
                0.8-18 mm across, sharp or filleted edge (radius up to 1.2 mm), the face flat,
                tilted by up to 2 degrees or gently domed
``holed``       the same with one to four holes (discs or polygons), or a ring (annulus)
``lines``       one to seven flat or rounded bars 0.3-3 mm wide, 3-22 mm long, parallel, crossed
                or fanned
``dots``        pins with round or flat tips, 0.2-1.6 mm in radius, on a grid or scattered
``curved``      sphere, ellipsoid, cylinder on its side, cone, pyramid, torus, knife edge (wedge)
``edge``        a large flat with one straight or curved edge, or a step between two levels,
                reaching beyond the view
``relief``      a flat carrying raised relief: waves, bumps, letters-like strokes
==============  ===============================================================================

Heights are in mm, positions in the indenter frame (origin at the face's centre); the shapes'
extent is at most 24 mm so that they fit the pad.
"""

from __future__ import annotations

import math

import numpy as np

from tactile_deploy.indenters.base import DEFAULT_MAX_RELIEF_MM, EnvelopeGrid, Indenter

#: Pitch (mm) of the envelope grids.
PITCH_MM = 0.03
#: Shape families and their share of the draws.
FAMILIES = {"flat": 0.2, "holed": 0.15, "lines": 0.15, "dots": 0.12, "curved": 0.18,
            "edge": 0.1, "relief": 0.1}
#: Largest half-extent of a shape, mm.
MAX_HALF_EXTENT_MM = 12.0


class GridIndenter(Indenter):
    """An indenter given by its envelope on a grid (no mesh).

    name : short name. heights_mm : (ny, nx) float envelope, mm, at pixel centres
        ``((ix - (nx - 1) / 2) pitch, (iy - (ny - 1) / 2) pitch)`` of the indenter frame;
        ``+inf`` outside the footprint; its minimum is moved to 0. pitch_mm : pixel pitch, mm.
    """

    def __init__(self, name: str, heights_mm: np.ndarray, pitch_mm: float = PITCH_MM,
                 max_relief_mm: float = DEFAULT_MAX_RELIEF_MM):
        super().__init__(None, name, "procedural", pitch_mm=pitch_mm, max_relief_mm=max_relief_mm,
                         cache_dir=None)
        h = np.asarray(heights_mm, np.float64)
        finite = np.isfinite(h)
        if h.ndim != 2 or not finite.any():
            raise ValueError(f"indenter {name!r}: heights_mm must be a 2-D map with a footprint")
        h = h - h[finite].min()
        h = np.where(finite & (h <= max_relief_mm), h, np.inf).astype(np.float32)
        h = np.pad(h, 1, constant_values=np.inf)          # outermost pixels outside
        h.flags.writeable = False
        ny, nx = h.shape
        self._grid = EnvelopeGrid(h, -(nx - 1) / 2 * pitch_mm, -(ny - 1) / 2 * pitch_mm,
                                  float(pitch_mm), float(max_relief_mm))

    @property
    def content_hash(self) -> str:
        import hashlib

        return hashlib.sha256(self._grid.heights_mm.tobytes()).hexdigest()

    def _load_or_build_grid(self) -> EnvelopeGrid:
        return self._grid


# ------------------------------------------------------------------------------ 2-D geometry
def _frame(half_mm: float, pitch: float = PITCH_MM):
    """(x, y) (ny, nx) mm of a square grid covering +-half_mm."""
    n = int(math.ceil(2 * half_mm / pitch)) + 1
    c = (np.arange(n) - (n - 1) / 2) * pitch
    return np.meshgrid(c, c)


def _polygon_sdf(x, y, vertices) -> np.ndarray:
    """Signed distance (mm, negative inside) of points to a closed polygon (k, 2)."""
    v = np.asarray(vertices, np.float64)
    p = np.stack([x, y], -1)
    d = np.full(x.shape, np.inf)
    inside = np.zeros(x.shape, bool)
    for i in range(len(v)):
        a, b = v[i], v[(i + 1) % len(v)]
        e = b - a
        t = np.clip(((p - a) @ e) / (e @ e), 0.0, 1.0)
        d = np.minimum(d, np.linalg.norm(p - a - t[..., None] * e, axis=-1))
        cond = (a[1] > y) != (b[1] > y)
        xin = a[0] + (y - a[1]) * e[0] / np.where(e[1] == 0, 1e-12, e[1])
        inside ^= cond & (x < xin)
    return np.where(inside, -d, d)


def _outline_sdf(rng, x, y, size_mm: float) -> np.ndarray:
    """Signed distance to a random outline about ``size_mm`` across, centred."""
    kind = rng.choice(["disc", "ellipse", "rectangle", "rounded", "polygon"])
    r = size_mm / 2
    if kind == "disc":
        return np.hypot(x, y) - r
    if kind == "ellipse":
        b = r * rng.uniform(0.3, 0.9)
        # first-order distance: level set scaled by the gradient's length
        f = np.sqrt((x / r) ** 2 + (y / b) ** 2)
        g = np.sqrt((x / r ** 2) ** 2 + (y / b ** 2) ** 2)
        return (f - 1.0) * f / np.maximum(g, 1e-9)
    if kind in ("rectangle", "rounded"):
        w, h = r, r * rng.uniform(0.25, 1.0)
        c = rng.uniform(0.1, 0.5) * min(w, h) if kind == "rounded" else 0.0
        qx, qy = np.abs(x) - (w - c), np.abs(y) - (h - c)
        return np.hypot(np.maximum(qx, 0), np.maximum(qy, 0)) + np.minimum(np.maximum(qx, qy), 0) - c
    n = int(rng.integers(3, 9))
    phase = rng.uniform(0, 2 * math.pi)
    ang = phase + 2 * math.pi * np.arange(n) / n + rng.uniform(-0.25, 0.25, n) * (2 * math.pi / n)
    rad = r * rng.uniform(0.75, 1.0, n)
    return _polygon_sdf(x, y, np.c_[rad * np.cos(ang), rad * np.sin(ang)])


def _edge_profile(rng, sdf: np.ndarray) -> np.ndarray:
    """Height (mm) near the edge of a flat face from its signed distance: sharp, or a fillet
    of radius up to 1.2 mm, or a 45 degree chamfer; +inf outside."""
    inside = -sdf
    style = rng.choice(["sharp", "fillet", "chamfer"], p=[0.45, 0.4, 0.15])
    h = np.zeros_like(sdf)
    if style == "fillet":
        rf = rng.uniform(0.1, 1.2)
        d = np.clip(rf - inside, 0.0, rf)
        h = rf - np.sqrt(np.maximum(rf * rf - d * d, 0.0))
    elif style == "chamfer":
        c = rng.uniform(0.1, 0.6)
        h = np.clip(c - inside, 0.0, c)
    return np.where(sdf <= 0, h, np.inf)


def _face(rng, x, y) -> np.ndarray:
    """Height of a flat face's surface: flat, tilted by up to 2 degrees, or gently domed."""
    kind = rng.choice(["flat", "tilted", "domed"], p=[0.5, 0.3, 0.2])
    if kind == "tilted":
        t = math.tan(math.radians(rng.uniform(0.2, 2.0)))
        a = rng.uniform(0, 2 * math.pi)
        return t * (x * math.cos(a) + y * math.sin(a))
    if kind == "domed":
        rc = rng.uniform(30.0, 300.0)
        return (x * x + y * y) / (2 * rc)
    return np.zeros_like(x)


# ------------------------------------------------------------------------------ families
def _flat(rng):
    size = float(np.exp(rng.uniform(math.log(0.8), math.log(18.0))))
    x, y = _frame(size / 2 + 0.3)
    sdf = _outline_sdf(rng, x, y, size)
    return _edge_profile(rng, sdf) + _face(rng, x, y)


def _holed(rng):
    size = float(np.exp(rng.uniform(math.log(3.0), math.log(18.0))))
    x, y = _frame(size / 2 + 0.3)
    if rng.random() < 0.35:             # ring (annulus) of any width
        r_out = size / 2
        r_in = r_out * rng.uniform(0.3, 0.85)
        sdf = np.maximum(np.hypot(x, y) - r_out, r_in - np.hypot(x, y))
    else:
        sdf = _outline_sdf(rng, x, y, size)
        for _ in range(int(rng.integers(1, 5))):
            hr = size * rng.uniform(0.06, 0.3)
            cx, cy = rng.uniform(-0.3, 0.3, 2) * size
            hole = _outline_sdf(rng, x - cx, y - cy, 2 * hr)
            sdf = np.maximum(sdf, -hole)
    return _edge_profile(rng, sdf) + _face(rng, x, y)


def _bar(x, y, x0, y0, angle, length, width, rounded: bool) -> np.ndarray:
    """Height of one bar (flat or with a round top), +inf outside."""
    c, s = math.cos(angle), math.sin(angle)
    u = (x - x0) * c + (y - y0) * s
    v = -(x - x0) * s + (y - y0) * c
    inside = (np.abs(u) <= length / 2) & (np.abs(v) <= width / 2)
    if rounded:
        rr = width / 2
        h = rr - np.sqrt(np.maximum(rr * rr - v * v, 0.0))
    else:
        h = np.zeros_like(x)
    return np.where(inside, h, np.inf)


def _lines(rng):
    n = int(rng.integers(1, 8))
    width = float(np.exp(rng.uniform(math.log(0.3), math.log(3.0))))
    length = rng.uniform(3.0, 22.0)
    pitch = width + rng.uniform(0.4, 4.0)
    layout = rng.choice(["parallel", "crossed", "fan"], p=[0.6, 0.25, 0.15])
    rounded = bool(rng.random() < 0.4)
    half = min(MAX_HALF_EXTENT_MM, 0.5 * math.hypot(length, n * pitch) + 0.5)
    x, y = _frame(half)
    h = np.full(x.shape, np.inf)
    base = rng.uniform(0, math.pi)
    for k in range(n):
        off = (k - (n - 1) / 2) * pitch
        if layout == "parallel":
            ang, x0, y0 = base, -off * math.sin(base), off * math.cos(base)
        elif layout == "crossed":
            ang = base + (math.pi / 2 if k % 2 else 0.0)
            x0, y0 = rng.uniform(-1, 1, 2) * min(3.0, pitch)
        else:
            ang, x0, y0 = base + (k - (n - 1) / 2) * rng.uniform(0.1, 0.5), 0.0, 0.0
        h = np.minimum(h, _bar(x, y, x0, y0, ang, length, width, rounded))
    return h


def _dots(rng):
    r = float(np.exp(rng.uniform(math.log(0.2), math.log(1.6))))
    flat_tip = bool(rng.random() < 0.35)
    if rng.random() < 0.6:
        nx, ny = int(rng.integers(1, 6)), int(rng.integers(1, 6))
        pitch = 2 * r + rng.uniform(0.5, 4.0)
        pts = [((i - (nx - 1) / 2) * pitch, (j - (ny - 1) / 2) * pitch)
               for i in range(nx) for j in range(ny)]
    else:
        n = int(rng.integers(2, 12))
        spread = rng.uniform(2.0, 9.0)
        pts = [tuple(p) for p in rng.uniform(-spread, spread, (n, 2))]
    pts = np.array(pts)
    half = min(MAX_HALF_EXTENT_MM, float(np.abs(pts).max()) + r + 0.3)
    x, y = _frame(half)
    h = np.full(x.shape, np.inf)
    for px, py in pts:
        d = np.hypot(x - px, y - py)
        tip = np.zeros_like(d) if flat_tip else r - np.sqrt(np.maximum(r * r - d * d, 0.0))
        tip = tip + rng.uniform(0.0, 0.04)            # pins of slightly different lengths
        h = np.minimum(h, np.where(d <= r, tip, np.inf))
    return h


def _curved(rng):
    kind = rng.choice(["sphere", "ellipsoid", "cylinder", "cone", "pyramid", "torus", "wedge"])
    if kind in ("sphere", "ellipsoid"):
        a = float(np.exp(rng.uniform(math.log(0.8), math.log(10.0))))
        b = a * (rng.uniform(0.3, 1.0) if kind == "ellipsoid" else 1.0)
        c = b
        half = min(MAX_HALF_EXTENT_MM, a)
        x, y = _frame(half)
        q = 1.0 - (x / a) ** 2 - (y / b) ** 2
        return np.where(q > 0, c * (1.0 - np.sqrt(np.maximum(q, 0.0))), np.inf)
    if kind == "cylinder":
        rc = float(np.exp(rng.uniform(math.log(0.5), math.log(8.0))))
        length = rng.uniform(3.0, 22.0)
        x, y = _frame(min(MAX_HALF_EXTENT_MM, 0.5 * math.hypot(length, 2 * rc)))
        return np.where((np.abs(x) <= length / 2) & (np.abs(y) < rc),
                        rc - np.sqrt(np.maximum(rc * rc - y * y, 0.0)), np.inf)
    if kind == "cone":
        half_angle = math.radians(rng.uniform(30.0, 80.0))
        rb = rng.uniform(1.5, 9.0)
        x, y = _frame(rb)
        rho = np.hypot(x, y)
        tip = rng.uniform(0.0, 0.8)                    # rounded tip radius
        h = rho / math.tan(half_angle)
        if tip > 0:
            h = np.where(rho < tip * math.cos(half_angle),
                         tip - np.sqrt(np.maximum(tip * tip - rho * rho, 0.0)), h)
        return np.where(rho <= rb, h, np.inf)
    if kind == "pyramid":
        n = int(rng.integers(3, 7))
        slope = math.tan(math.radians(rng.uniform(10.0, 60.0)))
        rb = rng.uniform(1.5, 9.0)
        x, y = _frame(rb)
        ang = rng.uniform(0, 2 * math.pi) + 2 * math.pi * np.arange(n) / n
        h = np.max([(x * math.cos(a) + y * math.sin(a)) for a in ang], axis=0) * slope
        return np.where(h <= rb * slope * math.cos(math.pi / n), np.maximum(h, 0.0), np.inf)
    if kind == "torus":
        big = rng.uniform(1.5, 8.0)
        small = rng.uniform(0.3, min(2.5, big * 0.8))
        x, y = _frame(big + small)
        d = np.hypot(np.hypot(x, y) - big, 0.0)
        return np.where(d < small, small - np.sqrt(np.maximum(small * small - d * d, 0.0)), np.inf)
    # wedge: a knife edge of some opening angle, possibly rounded, along x
    slope = math.tan(math.radians(rng.uniform(5.0, 60.0)))
    length = rng.uniform(3.0, 22.0)
    width = rng.uniform(1.0, 10.0)
    rt = rng.uniform(0.0, 1.0)
    x, y = _frame(min(MAX_HALF_EXTENT_MM, 0.5 * math.hypot(length, width)))
    h = np.abs(y) * slope
    if rt > 0:
        yc = rt * slope / math.sqrt(1 + slope * slope)
        h = np.where(np.abs(y) < yc, rt - np.sqrt(np.maximum(rt * rt - y * y, 0.0)), h)
        h = h - h.min()
    return np.where((np.abs(x) <= length / 2) & (np.abs(y) <= width / 2), h, np.inf)


def _edge(rng):
    x, y = _frame(MAX_HALF_EXTENT_MM)
    a = rng.uniform(0, 2 * math.pi)
    u = x * math.cos(a) + y * math.sin(a)
    offset = rng.uniform(-6.0, 2.0)
    if rng.random() < 0.3:                              # a curved edge: a large disc's rim
        rc = rng.uniform(8.0, 40.0)
        sdf = np.hypot(u - offset + rc, x * math.sin(a) - y * math.cos(a)) - rc
    else:
        sdf = u - offset
    h = _edge_profile(rng, sdf) + _face(rng, x, y) * 0.5
    if rng.random() < 0.3:                              # a step: a second, higher level
        step = rng.uniform(0.1, 0.6)
        h = np.where(np.isfinite(h) & (u < offset - rng.uniform(2.0, 8.0)), h + step, h)
    return h


def _relief(rng):
    size = rng.uniform(6.0, 20.0)
    x, y = _frame(size / 2 + 0.3)
    sdf = _outline_sdf(rng, x, y, size)
    base = rng.uniform(0.15, 0.6)                       # the plate stands this far back
    kind = rng.choice(["waves", "bumps", "strokes"])
    if kind == "waves":
        lam = rng.uniform(1.2, 5.0)
        amp = rng.uniform(0.1, base)
        a = rng.uniform(0, math.pi)
        raise_ = amp * 0.5 * (1 + np.cos(2 * math.pi * (x * math.cos(a) + y * math.sin(a)) / lam))
    elif kind == "bumps":
        raise_ = np.zeros_like(x)
        for _ in range(int(rng.integers(1, 8))):
            c = rng.uniform(-0.35, 0.35, 2) * size
            s = rng.uniform(0.4, 2.0)
            raise_ = np.maximum(raise_, rng.uniform(0.1, base)
                                * np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2) / (2 * s * s)))
    else:
        raise_ = np.zeros_like(x)
        for _ in range(int(rng.integers(1, 5))):
            bar = _bar(x, y, *(rng.uniform(-0.3, 0.3, 2) * size), rng.uniform(0, math.pi),
                       rng.uniform(2.0, size * 0.8), rng.uniform(0.3, 1.5), bool(rng.random() < 0.5))
            raise_ = np.where(np.isfinite(bar), base - bar.clip(0, base), raise_)
    return np.where(sdf <= 0, base - raise_, np.inf)


_BUILDERS = {"flat": _flat, "holed": _holed, "lines": _lines, "dots": _dots, "curved": _curved,
             "edge": _edge, "relief": _relief}


def random_indenter(rng: np.random.Generator, family: str | None = None) -> GridIndenter:
    """One procedural indenter (module docstring); ``family`` None draws it by :data:`FAMILIES`."""
    if family is None:
        names = list(FAMILIES)
        family = str(rng.choice(names, p=np.array([FAMILIES[n] for n in names])))
    if family not in _BUILDERS:
        raise ValueError(f"unknown shape family {family!r}; known: {sorted(_BUILDERS)}")
    return GridIndenter(f"procedural_{family}", _BUILDERS[family](rng))
