"""Plausibility checks of a ball-press recording against its stated ball, scale and pad.

Each check raises :class:`~tactile_deploy.calibration.recording.errors.PlausibilityError` naming the input that
is wrong, what was found, and what to do:

* :func:`view_mapping`: the frames at ``--mm-per-px`` must fit the pad of the family (a scale in
  px per mm, or one of another camera, spans more than the gel) and cover a useful part of its
  sensing area; it returns the camera mapping that puts the frames on the sensing area (turned
  a quarter when the frames are portrait and the sensing area landscape, or the reverse).
* :func:`check_annotation_axes`: annotated circles with x and y swapped (they leave the image,
  or detection agrees with the swapped circles).
* :func:`check_ball_radius`: a contact circle can never be larger than the ball (a radius too
  small, or a scale too large); circles that imply presses a few micrometres deep (a radius in
  um, or a scale too small); and circles that all stay within half the ball's radius, which is
  what a diameter given as the radius produces (a calibration whose presses are that shallow
  would also only see slopes up to 0.58 and must press deeper).
"""

from __future__ import annotations

import math

import numpy as np

from tactile_deploy.calibration.recording.errors import PlausibilityError

#: Every contact radius below this fraction of the ball radius: a diameter given as the radius.
DIAMETER_RATIO = 0.55
#: Presses implied shallower than this (mm) at the deepest: a radius in the wrong unit.
MIN_IMPLIED_DEPTH_MM = 0.02


# ------------------------------------------------------------------------------- scale and view
def _view_boxes(width_px: int, height_px: int, mm_per_px: float):
    """{quarter turns: (x extent, y extent) mm} of the frame on the sensing surface."""
    w, h = width_px * mm_per_px, height_px * mm_per_px
    return {0: (w, h), 1: (h, w)}


def _fits_outline(family, ex: float, ey: float) -> bool:
    if family.outline == "rectangle":
        return ex <= family.width_mm + 1e-9 and ey <= family.length_mm + 1e-9
    return math.hypot(ex / 2, ey / 2) <= family.radius_mm + 1e-9


def _overlap_fraction(family, ex: float, ey: float) -> float:
    a = family.sensing_area
    ox = max(0.0, min(ex / 2, a.x_max_mm) - max(-ex / 2, a.x_min_mm))
    oy = max(0.0, min(ey / 2, a.y_max_mm) - max(-ey / 2, a.y_min_mm))
    return ox * oy / (ex * ey)


def camera_mapping_for_view(width_px: int, height_px: int, mm_per_px: float,
                            quarter_turns: int):
    """The camera mapping of frames that need no lens correction: centred on the sensor origin
    at ``mm_per_px``; ``quarter_turns`` 0: columns along +x, rows along -y; 1: rows along +x,
    columns along +y (a portrait frame on a landscape sensing area). The imaging grid is the
    frame's pixels in the sensor frame (so rectification only reorders them)."""
    from tactile_deploy.imaging.camera_mapping import OutputGrid, camera_mapping_from_parameters

    s = float(mm_per_px)
    cu, cv = (width_px - 1) / 2.0, (height_px - 1) / 2.0
    if quarter_turns == 0:
        hmat = [[s, 0.0, -s * cu], [0.0, -s, s * cv], [0.0, 0.0, 1.0]]
        nx, ny = width_px, height_px
    elif quarter_turns == 1:
        hmat = [[0.0, s, -s * cv], [s, 0.0, -s * cu], [0.0, 0.0, 1.0]]
        nx, ny = height_px, width_px
    else:
        raise ValueError(f"quarter_turns must be 0 or 1, got {quarter_turns}")
    k = [[float(width_px), 0.0, cu], [0.0, float(width_px), cv], [0.0, 0.0, 1.0]]
    grid = OutputGrid(x_min_mm=-nx * s / 2, x_max_mm=nx * s / 2, y_min_mm=-ny * s / 2,
                      y_max_mm=ny * s / 2, nx=nx, ny=ny)
    return camera_mapping_from_parameters((width_px, height_px), k, np.zeros(5), hmat, grid=grid)


def view_mapping(width_px: int, height_px: int, mm_per_px: float, family,
                 scale_given: bool = True):
    """``(camera mapping, quarter turns, notes)`` of frames at ``mm_per_px`` on ``family``'s
    sensing area (module docstring)."""
    opt = "--mm-per-px" if scale_given else "the scale assumed without --mm-per-px"
    boxes = _view_boxes(width_px, height_px, mm_per_px)
    fitting = [k for k, (ex, ey) in boxes.items() if _fits_outline(family, ex, ey)]
    pad = (f"{family.width_mm} x {family.length_mm} mm" if family.outline == "rectangle"
           else f"{2 * family.radius_mm} mm across")
    ex, ey = boxes[0]
    if not fitting:
        raise PlausibilityError(
            f"{opt} {mm_per_px:g}: the {width_px} x {height_px} px frames would span "
            f"{ex:.1f} x {ey:.1f} mm, more than the whole {family.name} gel ({pad}): the scale "
            f"is too large. --mm-per-px takes millimetres per pixel (19.58 px/mm is "
            f"{1 / 19.58:.5f} mm per px); or --pad names another sensor")
    area = family.sensing_area
    k = max(fitting, key=lambda q: (_overlap_fraction(family, *boxes[q]), -q))
    ex, ey = boxes[k]
    if ex * ey < 0.1 * area.width_mm * area.length_mm:
        raise PlausibilityError(
            f"{opt} {mm_per_px:g}: the frames would span only {ex:.2f} x {ey:.2f} mm of the "
            f"{area.width_mm:g} x {area.length_mm:g} mm sensing area of {family.name}: the scale "
            "is too small (a value in px per mm inverted twice, or in um?); measure it from a "
            "target of known size")
    notes = []
    if k == 1:
        notes.append(f"the frames are {'portrait' if height_px > width_px else 'landscape'} and "
                     f"the {family.name} sensing area {area.width_mm:g} x {area.length_mm:g} mm "
                     "is not: image rows run along +x, columns along +y")
    frac = _overlap_fraction(family, ex, ey)
    if frac < 0.999:
        notes.append(f"the view ({ex:.2f} x {ey:.2f} mm) reaches beyond the sensing area; "
                     f"{100 * (1 - frac):.0f} % of it lies outside the depth grid and is not read")
    return camera_mapping_for_view(width_px, height_px, mm_per_px, k), k, notes


#: The farthest (mm) a contact seen at the edge of the view is carried past it onto the depth grid.
VIEW_EDGE_EXTENSION_MAX_MM = 1.0


def view_edge_extension(imaging_grid, depth_grid) -> tuple[float, list[str]]:
    """``(extension mm, notes)``: the widest strip (mm) of the pad family's ``depth_grid`` that the
    camera's ``imaging_grid`` leaves unseen along any side, at most
    :data:`VIEW_EDGE_EXTENSION_MAX_MM`. The runtime carries the depth at the view's edge across
    that strip (the plugin's ``view_edge_extension_mm``): a contact seen at the edge goes on past
    it, where depth 0 would draw a cliff at the edge of the view."""
    g, d = imaging_grid, depth_grid
    strip = max(0.0, g.x_min_mm - d.x_min_mm, d.x_max_mm - g.x_max_mm,
                g.y_min_mm - d.y_min_mm, d.y_max_mm - g.y_max_mm)
    if strip <= VIEW_EDGE_EXTENSION_MAX_MM:
        return strip, ([f"the view leaves up to {strip:.2f} mm of the depth grid unseen along a "
                        "side; the depth at its edge is carried across it"] if strip > 0 else [])
    return VIEW_EDGE_EXTENSION_MAX_MM, [
        f"the view leaves up to {strip:.2f} mm of the depth grid unseen along a side; the depth at "
        f"its edge is carried {VIEW_EDGE_EXTENSION_MAX_MM:g} mm past it, farther out the depth "
        "is 0"]


# ------------------------------------------------------------------------------- annotations
def check_annotation_axes(circles: np.ndarray, shape_hw: tuple[int, int], names: list[str],
                          detected: dict[int, np.ndarray], annotations: str) -> None:
    """Refuse annotated circles (column, row, radius) px whose x and y are swapped.

    detected : {press index: detected circle} for some presses (may be empty).
    """
    h, w = shape_hw
    c = np.asarray(circles, np.float64)
    inside = (c[:, 0] >= -0.5) & (c[:, 0] <= w - 0.5) & (c[:, 1] >= -0.5) & (c[:, 1] <= h - 0.5)
    inside_sw = ((c[:, 1] >= -0.5) & (c[:, 1] <= w - 0.5) & (c[:, 0] >= -0.5)
                 & (c[:, 0] <= h - 0.5))
    if not inside.all():
        i = int(np.flatnonzero(~inside)[0])
        if inside_sw.all():
            raise PlausibilityError(
                f"--annotations {annotations}: the circle of {names[i]} (center_x {c[i, 0]:g}, "
                f"center_y {c[i, 1]:g}) lies outside the {w} x {h} px frame, and every circle "
                "fits with x and y swapped: center_x is the column (0..width), center_y the row "
                "(0..height); swap the two columns")
        raise PlausibilityError(
            f"--annotations {annotations}: the circle of {names[i]} (center_x {c[i, 0]:g}, "
            f"center_y {c[i, 1]:g}) lies outside the {w} x {h} px frame (columns 0..{w - 1}, "
            f"rows 0..{h - 1}); fix its row")
    if len(detected) >= 3:
        idx = np.array(sorted(detected))
        det = np.array([detected[i][:2] for i in idx])
        d_as = float(np.median(np.hypot(*(det - c[idx, :2]).T)))
        d_sw = float(np.median(np.hypot(*(det - c[idx][:, [1, 0]]).T)))
        radius = float(np.median(c[idx, 2]))
        if inside_sw.all() and d_sw < 0.5 * d_as and d_as > max(5.0, 0.5 * radius):
            raise PlausibilityError(
                f"--annotations {annotations}: the labelled centres lie {d_as:.0f} px from the "
                f"contacts seen in the frames, but {d_sw:.0f} px with x and y swapped: center_x "
                "is the column, center_y the row; swap the two columns")


# ------------------------------------------------------------------------------- ball radius
def check_ball_radius(circles_px: np.ndarray, mm_per_px: float, ball_radius_mm: float,
                      names: list[str], scale_given: bool = True,
                      shallow_presses: bool = False) -> dict:
    """Refuse a ball radius (or scale) that the contact circles contradict (module docstring).
    ``shallow_presses``: the user states the radius is right and the presses shallow (the
    diameter check is skipped). Returns the figures checked: largest contact radius (mm, and
    / R), deepest implied cap (mm)."""
    if not (math.isfinite(ball_radius_mm) and ball_radius_mm > 0):
        raise PlausibilityError(f"--ball-radius-mm must be a number > 0 (mm), got {ball_radius_mm}")
    a = np.asarray(circles_px, np.float64)[:, 2] * mm_per_px
    r = float(ball_radius_mm)
    scale = (f"--mm-per-px {mm_per_px:g}" if scale_given else
             f"the assumed scale {mm_per_px:.4g} mm per px (give --mm-per-px)")
    i = int(np.argmax(a))
    if a[i] >= r:
        raise PlausibilityError(
            f"--ball-radius-mm {r:g}: the contact circle of {names[i]} has a radius of "
            f"{a[i]:.2f} mm ({circles_px[i][2]:.1f} px at {scale}), larger than the ball: a "
            "contact cannot be wider than the ball that makes it. Give the ball's radius in mm "
            "(not in cm), or check the scale")
    cap = r - np.sqrt(r * r - a * a)
    if cap.max() < MIN_IMPLIED_DEPTH_MM:
        raise PlausibilityError(
            f"--ball-radius-mm {r:g}: with contact circles of at most {a.max():.2f} mm, a ball "
            f"of radius {r:g} mm would have pressed at most {1e3 * cap.max():.1f} um deep, far "
            "less than a visible press: is the radius given in micrometres (2.35 mm, not 2350)? "
            f"Or check {scale}")
    ratio = a.max() / r
    if ratio < DIAMETER_RATIO and not shallow_presses:
        raise PlausibilityError(
            f"--ball-radius-mm {r:g}: every contact circle stays within {ratio:.2f} of it (at "
            f"most {a.max():.2f} mm). A contact never exceeds the ball's radius, so that is what "
            f"a DIAMETER given as the radius looks like: if {r:g} mm is the diameter, give "
            f"--ball-radius-mm {r / 2:g}. If the radius is right, the presses are too shallow "
            f"to calibrate (slopes only up to {ratio / math.sqrt(1 - ratio * ratio):.2f}): "
            "press deeper, to contact radii of at least 0.6 of the ball's (or, keeping these "
            "presses, pass --shallow-presses)")
    return {"largest contact radius (mm)": float(a.max()),
            "largest contact radius / ball radius": float(ratio),
            "deepest implied cap (mm)": float(cap.max())}
