"""Our procedural indenter library and the registry that finds indenters by name or path.

Every shape is built deterministically with trimesh in the indenter frame (mm, pressing face
down, lowest point z = 0, origin at the bounding-box centre in x, y) and fits a 35 mm pad: its
pressing surface lies within 12 mm of the origin. Curved surfaces are faceted to a chord error of
at most 1 um (:data:`tactile_deploy.indenters.shapes.FACET_ERROR_MM`); on doubly curved surfaces
(spheres, ellipsoid, torus) a triangle can sit up to 2 um inside the true surface (measured along
the normal), so the envelope there is up to ``2 um / cos(slope)`` too high. The screw thread's
crest and root corners are rounded over one axial sample (P/16 = 0.08 mm). Shapes assembled from several parts (pins on a backing plate, ...) are unions of
closed, possibly overlapping parts.

Kinds: ``"primitive"`` (geometric shapes) and ``"novel"`` (household and industrial objects, for
testing generalisation). Names of analytic indenters, ``analytic_sphere_r<R>`` and
``analytic_paraboloid_r<R>`` (R in mm, e.g. ``analytic_sphere_r2.35``), and mesh file paths are
accepted by :func:`get_indenter` too.
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from tactile_deploy.indenters import shapes as S
from tactile_deploy.indenters.base import (
    DEFAULT_MAX_RELIEF_MM,
    DEFAULT_PITCH_MM,
    AnalyticParaboloid,
    AnalyticSphere,
    Indenter,
)
from tactile_deploy.indenters.loading import load_indenter

KINDS = ("primitive", "novel")
MESH_SUFFIXES = (".stl", ".obj", ".ply")


@dataclass(frozen=True)
class LibraryEntry:
    """One procedural indenter: its kind, a one-line description and its mesh builder."""

    name: str
    kind: str
    description: str
    build: Callable[[], object]


_LIBRARY: dict[str, LibraryEntry] = {}


def _register(kind: str, description: str):
    def wrap(build):
        name = build.__name__.lstrip("_")
        _LIBRARY[name] = LibraryEntry(name, kind, description, build)
        return build

    return wrap


def _rotate(mesh, angle_rad: float, axis, point=(0.0, 0.0, 0.0)):
    import trimesh

    mesh.apply_transform(trimesh.transformations.rotation_matrix(angle_rad, axis, point))
    return mesh


def _lying_prism(section_xz, length_y_mm: float):
    """Convex prism whose cross-section (n, 2) lies in the x-z plane, extruded along y."""
    s = np.asarray(section_xz, dtype=np.float64)
    half = 0.5 * length_y_mm
    pts = [np.c_[s[:, 0], np.full(len(s), y), s[:, 1]] for y in (-half, half)]
    return S.convex_solid(np.concatenate(pts))


# ---- primitives ---------------------------------------------------------------------------------


@_register("primitive", "sphere, radius 2 mm")
def _sphere_r2():
    return S.sphere(2.0)


@_register("primitive", "sphere, radius 4 mm")
def _sphere_r4():
    return S.sphere(4.0)


@_register("primitive", "sphere, radius 6 mm")
def _sphere_r6():
    return S.sphere(6.0)


@_register("primitive", "ellipsoid, semi-axes 5 x 2.5 x 2.5 mm, long axis along x")
def _ellipsoid():
    return S.ellipsoid((5.0, 2.5, 2.5))


@_register("primitive", "flat circular punch, radius 3 mm")
def _flat_punch():
    return S.disc_prism(3.0, 0.0, 6.0)


@_register("primitive", "flat square punch, 6 x 6 mm")
def _square_punch():
    return S.box([-3.0, -3.0, 0.0], [3.0, 3.0, 6.0])


@_register("primitive", "cylinder lying on its side, radius 3 mm, 14 mm long along y")
def _cylinder_side():
    return _rotate(S.disc_prism(3.0, -7.0, 7.0), 0.5 * math.pi, [1, 0, 0])


@_register("primitive", "cube edge: 8 mm cube with an edge (along y) down")
def _cube_edge():
    return _rotate(S.box([-4.0] * 3, [4.0] * 3), 0.25 * math.pi, [0, 1, 0])


@_register("primitive", "cube corner: 6 mm cube with a corner down (body diagonal vertical)")
def _cube_corner():
    import trimesh

    cube = S.box([-3.0] * 3, [3.0] * 3)
    cube.apply_transform(trimesh.geometry.align_vectors([-1.0, -1.0, -1.0], [0.0, 0.0, -1.0]))
    return cube


@_register("primitive", "cone, apex down, 90 degree apex angle, base radius 5 mm")
def _cone():
    return S.revolved([[0.0, 0.0], [5.0, 5.0], [0.0, 5.0]], S.sections_for(5.0))


@_register("primitive", "square pyramid, apex down, base 8 x 8 mm, height 4 mm")
def _pyramid():
    base = [[x, y, 4.0] for x in (-4.0, 4.0) for y in (-4.0, 4.0)]
    return S.convex_solid(np.array(base + [[0.0, 0.0, 0.0]]))


@_register("primitive", "triangular prism lying edge down (knife edge along y), side 6 mm, 12 mm long")
def _triangle_prism():
    tri = S.regular_polygon(3, 6.0 / math.sqrt(3.0), -0.5 * math.pi)  # a vertex straight down
    return _lying_prism(tri, 12.0)


@_register("primitive", "hexagonal prism lying edge down, across corners 7 mm, 12 mm long along y")
def _hex_prism():
    return _lying_prism(S.regular_polygon(6, 3.5, -0.5 * math.pi), 12.0)


@_register("primitive", "flat equilateral-triangle punch, side 7 mm")
def _triangle():
    return S.convex_prism(S.regular_polygon(3, 7.0 / math.sqrt(3.0), 0.5 * math.pi), 0.0, 5.0)


@_register("primitive", "flat hexagonal punch, across corners 7 mm")
def _hexagon():
    return S.convex_prism(S.regular_polygon(6, 3.5), 0.0, 5.0)


@_register("primitive", "torus lying flat, major radius 4 mm, tube radius 1.2 mm")
def _torus():
    import trimesh

    return trimesh.creation.torus(
        major_radius=4.0, minor_radius=1.2,
        major_sections=S.sections_for(5.2), minor_sections=S.sections_for(1.2),
    )


@_register("primitive", "flat ring punch, radii 2.5 to 4 mm")
def _ring():
    phi = 2.0 * math.pi * np.arange(S.sections_for(4.0)) / S.sections_for(4.0)
    return S.prism(*S.polar_region(phi, 4.0, 2.5), 0.0, 5.0)


@_register("primitive", "3 x 3 round-tipped pins (radius 0.6 mm, pitch 2.5 mm) on a plate")
def _dot_array():
    r = 0.6
    a = np.linspace(-0.5 * math.pi, 0.0, 33)
    profile = np.concatenate([np.c_[r * np.cos(a), r * (1.0 + np.sin(a))], [[r, 4.0], [0.0, 4.0]]])
    profile[0, 0] = 0.0
    pins = []
    for x in (-2.5, 0.0, 2.5):
        for y in (-2.5, 0.0, 2.5):
            pin = S.revolved(profile, S.sections_for(r))
            pin.apply_translation([x, y, 0.0])
            pins.append(pin)
    return S.union(pins + [S.box([-4.0, -4.0, 3.8], [4.0, 4.0, 5.8])])


@_register("primitive", "three parallel flat ridges 0.8 mm wide, 12 mm long, 2.5 mm apart")
def _parallel_lines():
    ridges = [S.box([x - 0.4, -6.0, 0.0], [x + 0.4, 6.0, 3.0]) for x in (-2.5, 0.0, 2.5)]
    return S.union(ridges + [S.box([-4.0, -7.0, 2.8], [4.0, 7.0, 4.8])])


@_register("primitive", "cross of two flat bars 12 x 1.2 mm")
def _cross():
    bars = [S.box([-6.0, -0.6, 0.0], [6.0, 0.6, 3.0]), S.box([-0.6, -6.0, 0.0], [0.6, 6.0, 3.0])]
    return S.union(bars + [S.box([-7.0, -7.0, 2.8], [7.0, 7.0, 4.8])])


@_register("primitive", "corrugated surface, wavelength 3 mm, 0.8 mm deep, 12 x 12 mm")
def _wave():
    x = np.linspace(-6.0, 6.0, 481)
    y = np.array([-6.0, 6.0])
    h = 0.4 * (1.0 - np.cos(2.0 * math.pi * x / 3.0))
    return S.heightfield_solid(x, y, np.broadcast_to(h, (2, len(x))), 3.0)


# ---- novel objects ------------------------------------------------------------------------------


@_register("novel", "hex bolt head (M8, 13 mm across flats) with a 30 degree chamfer, top down")
def _hex_bolt_head():
    across_flats, height, r_face = 13.0, 5.3, 6.1
    corners = S.regular_polygon(6, across_flats / math.sqrt(3.0))
    t = np.linspace(0.0, 1.0, 97)[:-1]
    outline = np.concatenate([c0 + t[:, None] * (c1 - c0) for c0, c1 in zip(corners, np.roll(corners, -1, 0))])
    z = np.maximum(np.hypot(outline[:, 0], outline[:, 1]) - r_face, 0.0) * math.tan(math.radians(30.0))
    n = S.sections_for(r_face)
    face = S.regular_polygon(n, r_face)
    points = np.concatenate([np.c_[outline, z], np.c_[face, np.zeros(n)], np.c_[corners, np.full(6, height)]])
    return S.convex_solid(points)


@_register("novel", "spur gear lying flat: 16 teeth, tip radius 9 mm, 2.5 mm bore")
def _gear():
    teeth, r_tip, r_root, r_bore = 16, 9.0, 7.6, 2.5
    period = 2.0 * math.pi / teeth
    step = 2.0 * math.pi / S.sections_for(r_tip)
    phis, radii = [], []

    def arc(a0, a1, r):
        k = max(1, math.ceil((a1 - a0) / step))
        a = a0 + (a1 - a0) * np.arange(k) / k
        phis.append(a)
        radii.append(np.full(k, r))

    for i in range(teeth):
        a = i * period
        arc(a, a + 0.30 * period, r_root)  # root land, then flank (a chord) up to the tip
        arc(a + 0.42 * period, a + 0.68 * period, r_tip)
        arc(a + 0.80 * period, a + period, r_root)
    phi = np.concatenate(phis)
    return S.prism(*S.polar_region(phi, np.concatenate(radii), np.full(len(phi), r_bore)), 0.0, 4.0)


@_register("novel", "coin face down: 20 mm disc, raised rim and a raised five-point star")
def _coin():
    n = S.sections_for(10.0)
    phi = 2.0 * math.pi * np.arange(n) / n
    rim = S.prism(*S.polar_region(phi, 10.0, 9.2), 0.0, 0.3)
    body = S.disc_prism(10.0, 0.15, 1.8)
    star_phi = 0.5 * math.pi + math.pi * np.arange(10) / 5
    star_r = np.where(np.arange(10) % 2 == 0, 4.5, 1.9)
    star = S.prism(*S.polar_region(star_phi, star_r), 0.06, 0.3)
    return S.union([rim, body, star])


@_register("novel", "key blade edge down: 22 mm bitting with five V cuts 0.4-1.8 mm deep")
def _key_bit():
    x, z = [-11.0], [0.0]
    for centre, depth in zip((-8.0, -4.0, 0.0, 4.0, 8.0), (0.4, 1.4, 0.8, 1.8, 1.0)):
        x += [centre - depth - 0.2, centre - 0.2, centre + 0.2, centre + depth + 0.2]
        z += [0.0, depth, depth, 0.0]
    x += [9.6, 11.0]
    z += [0.0, 2.4]
    x = np.array(x)
    return S.xz_profile_solid(x, np.array(z), np.full(len(x), 7.0), 2.2)


@_register("novel", "USB-A plug face: 12 x 4.5 mm metal shell, plastic tongue recessed 0.6 mm")
def _usb_a_plug():
    w, h, t = 6.0, 2.25, 0.3
    shell = [
        S.box([-w, -h, 0.0], [w, -h + t, 6.2]), S.box([-w, h - t, 0.0], [w, h, 6.2]),
        S.box([-w, -h, 0.0], [-w + t, h, 6.2]), S.box([w - t, -h, 0.0], [w, h, 6.2]),
    ]
    tongue = S.box([-5.1, 0.0, 0.6], [5.1, h - 0.2, 6.2])
    overmould = S.box([-8.0, -4.5, 6.0], [8.0, 4.5, 16.0])
    return S.union(shell + [tongue, overmould])


@_register("novel", "threaded rod (M8 x 1.25) lying along x, 14 mm long; crests rounded over P/16")
def _screw_thread():
    import trimesh

    pitch, r_major, length = 1.25, 4.0, 14.0
    sections = S.sections_for(r_major)
    r_minor = r_major - 5.0 / 16.0 * pitch * math.tan(math.radians(60.0))
    x = np.linspace(-0.5 * length, 0.5 * length, round(length / pitch * 16) + 1)
    phi = 2.0 * math.pi * np.arange(sections) / sections
    u = np.mod(x[:, None] / pitch - phi[None, :] / (2.0 * math.pi), 1.0)
    d = np.minimum(u, 1.0 - u)  # distance (in pitches) from the crest centre line
    r = np.interp(d, [0.0, 1 / 16, 6 / 16, 0.5], [r_major, r_major, r_minor, r_minor])
    v = np.stack([np.broadcast_to(x[:, None], r.shape), r * np.cos(phi), r * np.sin(phi)], axis=-1)
    nx, s = r.shape
    idx = np.arange(nx * s).reshape(nx, s)
    a, b = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    c, d_ = b + s, a + s
    faces = [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d_, c], -1).reshape(-1, 3)]
    ends = nx * s + np.arange(2)
    faces += [np.stack([np.full(s, ends[0]), idx[0], np.roll(idx[0], -1)], 1),
              np.stack([np.full(s, ends[1]), np.roll(idx[-1], -1), idx[-1]], 1)]
    vertices = np.concatenate([v.reshape(-1, 3), [[x[0], 0.0, 0.0], [x[-1], 0.0, 0.0]]])
    return S.closed_solid(trimesh.Trimesh(vertices, np.concatenate(faces), process=True), "thread")


@_register("novel", "2 x 2 toy brick upside down: four studs 4.8 mm across on an 8 mm grid")
def _brick_studs():
    studs = []
    for x in (-4.0, 4.0):
        for y in (-4.0, 4.0):
            stud = S.disc_prism(2.4, 0.0, 1.8)
            stud.apply_translation([x, y, 0.0])
            studs.append(stud)
    return S.union(studs + [S.box([-7.9, -7.9, 1.7], [7.9, 7.9, 11.3])])


@_register("novel", "crimped bottle cap, open side down: 21 flutes, 22 mm across, 0.3 mm wall")
def _bottle_cap():
    n = 21 * 48  # flute curvature ~1.8 / mm: chord error <= 1 um
    phi = 2.0 * math.pi * np.arange(n) / n
    outer = 10.6 + 0.45 * np.cos(21.0 * phi)
    skirt = S.prism(*S.polar_region(phi, outer, outer - 0.3), 0.0, 5.0)
    top = S.prism(*S.polar_region(phi, outer), 4.8, 5.1)
    return S.union([skirt, top])


# ---- registry -----------------------------------------------------------------------------------

_ANALYTIC = re.compile(r"^analytic_(sphere|paraboloid)_r(\d+(?:[.p]\d+)?)$")


def list_indenters(kind: str | None = None) -> list[str]:
    """Names of the library indenters, primitives first; ``kind``: "primitive" or "novel"."""
    if kind is not None and kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS} or None, got {kind!r}")
    return [name for name, e in _LIBRARY.items() if kind is None or e.kind == kind]


def library_entry(name: str) -> LibraryEntry:
    """The library entry (kind, description, builder) of ``name``."""
    if name not in _LIBRARY:
        raise ValueError(_unknown(name))
    return _LIBRARY[name]


def get_indenter(
    name_or_path: str | Path,
    *,
    pressing_face: str = "top",
    pitch_mm: float = DEFAULT_PITCH_MM,
    max_relief_mm: float = DEFAULT_MAX_RELIEF_MM,
) -> Indenter:
    """An indenter by library name, analytic name or mesh file path.

    * library name (:func:`list_indenters`): built once and shared (do not modify its mesh);
    * ``analytic_sphere_r<R>`` / ``analytic_paraboloid_r<R>``: R in mm (``2.35`` or ``2p35``);
    * a path to an .stl/.obj/.ply file in mm: loaded with :func:`load_indenter` and
      ``pressing_face`` ("top": the feature is the top of the file, as in the shared set).
    """
    text = str(name_or_path)
    if isinstance(name_or_path, Path) or text.lower().endswith(MESH_SUFFIXES) or "/" in text:

        return load_indenter(text, pressing_face=pressing_face, pitch_mm=pitch_mm,
                             max_relief_mm=max_relief_mm)
    return _get_named(text, float(pitch_mm), float(max_relief_mm))


@functools.lru_cache(maxsize=None)
def _get_named(name: str, pitch_mm: float, max_relief_mm: float) -> Indenter:
    m = _ANALYTIC.match(name)
    if m:
        radius = float(m.group(2).replace("p", "."))
        cls = AnalyticSphere if m.group(1) == "sphere" else AnalyticParaboloid
        return cls(radius, pitch_mm=pitch_mm, max_relief_mm=max_relief_mm)
    entry = library_entry(name)
    return Indenter(entry.build(), entry.name, entry.kind, pitch_mm=pitch_mm,
                    max_relief_mm=max_relief_mm)


def _unknown(name: str) -> str:
    return (
        f"unknown indenter {name!r}: expected a library name, analytic_sphere_r<R> or "
        f"analytic_paraboloid_r<R> (R in mm), or a path to an .stl/.obj/.ply file. "
        f"Library indenters: {', '.join(_LIBRARY)}"
    )
