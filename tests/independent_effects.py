"""Effects of real tactile sensors in their textbook form, made without the product's effect code.

The discrepancy workflow is judged on data it did not make itself: this module applies each
effect the way an outside tool would, from the clean output of ``tactile-deploy simulate`` (depth
maps of commanded contacts on the standard grid, no effects) and, for the effects that change
the contact or the material, from clean simulations at other poses or materials, asked for
through a caller-supplied function. It imports only numpy, scipy and OpenCV (a test checks
that): nothing of ``tactile_deploy`` or ``calibration``.

Grid: 128 x 128 pixels over +-17.5 mm; pixel (row i, column j) has its centre at
``x = -17.5 + (j + 0.5) p``, ``y = 17.5 - (i + 0.5) p`` (p = 35 / 128 mm; row 0 = largest y);
depth in mm pushed in (> 0).

Effects (textbook forms):

* ``radial_map``: the map distorted radially about a centre c: a point at ``x_u`` is shown at
  ``x_d = c + (x_u - c) (1 + k r_u^2)``, r_u = |x_u - c| / 17.5 mm (the map resampled);
* ``radial_image``: the camera image distorted: a camera calibrated with the plugin's mapping
  (intrinsics K, distortion, homography H from undistorted pixels to mm) whose lens has k1
  more; each map point p is the image pixel the calibrated mapping gives, the surface point
  there is found with the real lens (OpenCV's ``projectPoints`` / ``undistortPoints``), and the
  depth is what a pipeline integrating the surface's slopes over the calibrated grid reports
  (Frankot-Chellappa);
* ``pixel_scale``: millimetres per pixel off by ``1 + s`` along the image columns and/or rows
  (the map at p shows the surface at ``diag(1 + s_x, 1 + s_y) p``), either resampled or
  integrated from slopes;
* ``gain_gradient``: depth times ``1 + g0 + g_x x + g_y y``;
* ``blur``: a Gaussian of ``sigma_mm`` (OpenCV ``GaussianBlur``);
* ``saturation``: slope magnitudes clipped at ``max_slope`` and re-integrated (Frankot-Chellappa);
* ``zero_offset``, ``depth_scale``, ``position_offset``, ``rotation_offset``: the rig reaches
  ``depth + offset``, ``depth (1 + s)``, ``(x + dx, y + dy)``, ``theta + dtheta`` while the
  commanded contact is recorded (clean simulations at the reached poses);
* ``dome``: a gel whose surface sags ``h (r / 17.5)^2`` at radius r (either sign): the gap
  between indenter and gel grows by the sag under every point of the indenter, so a clean
  simulation of the indenter's mesh with its pressing face moved away from the gel by the sag
  there (the binary STL rewritten, large triangles subdivided first) is the domed contact;
* ``poisson``: the gel's Poisson ratio off (a clean simulation at another ratio);
* ``friction``: the gel sticks to the indenter (a clean simulation with sticking contact);
* out of every library: ``banding`` (periodic stripes over the whole pad) and ``dust`` (a
  particle under the membrane: a fixed bump that is there with or without contact).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

N_PX = 128
HALF_MM = 17.5
PITCH_MM = 2 * HALF_MM / N_PX
_c = -HALF_MM + (np.arange(N_PX) + 0.5) * PITCH_MM
#: (128, 128) sensor-frame x and y of the pixel centres, mm.
X_MM, Y_MM = np.meshgrid(_c, _c[::-1])
#: Pixels on the 17.5 mm pad.
PAD = np.hypot(X_MM, Y_MM) <= HALF_MM


@dataclass(frozen=True)
class Contact:
    """A commanded contact: indenter (library name or mesh path), pose (sensor frame, mm,
    degrees), depth into the gel (mm)."""

    indenter: str
    x_mm: float
    y_mm: float
    theta_deg: float
    depth_mm: float


# ------------------------------------------------------------------------------- helpers
def resample(depth: np.ndarray, qx: np.ndarray, qy: np.ndarray) -> np.ndarray:
    """The map at pad points (qx, qy) mm (bilinear, 0 outside), (128, 128)."""
    col = ((qx + HALF_MM) / PITCH_MM - 0.5).astype(np.float32)
    row = ((HALF_MM - qy) / PITCH_MM - 0.5).astype(np.float32)
    return cv2.remap(np.asarray(depth, np.float32), col, row, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0).astype(np.float64)


def slopes(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dz/dx, dz/dy) of a map, mm/mm, central differences (x along columns, y along -rows)."""
    z = np.asarray(depth, np.float64)
    return np.gradient(z, axis=1) / PITCH_MM, -np.gradient(z, axis=0) / PITCH_MM


def integrate(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Frankot-Chellappa: the surface (128, 128) mm whose central-difference slopes best match
    (gx, gy) mm/mm (least squares in the Fourier domain, periodic), level: the pad's rim 0."""
    g_col = np.asarray(gx, np.float64) * PITCH_MM
    g_row = -np.asarray(gy, np.float64) * PITCH_MM
    w_col = 2 * np.pi * np.fft.fftfreq(N_PX)[None, :]
    w_row = 2 * np.pi * np.fft.fftfreq(N_PX)[:, None]
    d_col, d_row = 1j * np.sin(w_col), 1j * np.sin(w_row)
    denom = np.abs(d_col) ** 2 + np.abs(d_row) ** 2
    num = np.conj(d_col) * np.fft.fft2(g_col) + np.conj(d_row) * np.fft.fft2(g_row)
    spec = np.where(denom > 1e-12, num / np.where(denom > 1e-12, denom, 1.0), 0.0)
    z = np.real(np.fft.ifft2(spec))
    rim = PAD & (np.hypot(X_MM, Y_MM) > HALF_MM - 1.5)
    return z - np.median(z[rim])


def _view(depth: np.ndarray, qx: np.ndarray, qy: np.ndarray, integrated: bool) -> np.ndarray:
    """The map at p showing the surface at q(p): resampled, or its slopes at q(p) integrated
    over the p grid (a pipeline reading slopes)."""
    if not integrated:
        return resample(depth, qx, qy)
    gx, gy = slopes(depth)
    return integrate(resample(gx, qx, qy), resample(gy, qx, qy))


# ---------------------------------------------------------------------------- optical
def radial_map(depth, k: float, centre_mm=(0.0, 0.0)) -> np.ndarray:
    """``radial_map`` of the module docstring (k: relative displacement at 17.5 mm)."""
    cx, cy = centre_mm
    dx, dy = X_MM - cx, Y_MM - cy
    ux, uy = dx.copy(), dy.copy()
    for _ in range(50):  # undistorted point of every displayed point: fixed point
        f = 1.0 + k * (ux * ux + uy * uy) / HALF_MM**2
        ux, uy = dx / f, dy / f
    return resample(depth, cx + ux, cy + uy)


def _camera_arrays(camera: dict):
    k = camera["intrinsics"]
    K = np.array([[k["fx_px"], 0.0, k["cx_px"]], [0.0, k["fy_px"], k["cy_px"]], [0, 0, 1.0]])
    d = camera["distortion"]
    dist = np.array([d["k1"], d["k2"], d["p1"], d["p2"], d["k3"]], np.float64)
    H = np.array(camera["homography_px_to_mm"], np.float64)
    return K, dist, H


def radial_image_points(k1: float, camera: dict) -> tuple[np.ndarray, np.ndarray]:
    """Surface points (qx, qy) mm that a pipeline calibrated on ``camera`` (a camera-mapping
    JSON dict) shows at each map pixel when the lens has ``k1`` more distortion."""
    K, dist, H = _camera_arrays(camera)
    p = np.stack([X_MM.ravel(), Y_MM.ravel(), np.ones(X_MM.size)], axis=1)
    und = p @ np.linalg.inv(H).T
    und = und[:, :2] / und[:, 2:3]  # undistorted px, calibrated camera
    norm = np.stack([(und[:, 0] - K[0, 2]) / K[0, 0], (und[:, 1] - K[1, 2]) / K[1, 1],
                     np.ones(len(und))], axis=1)
    raw, _ = cv2.projectPoints(norm.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    real = dist.copy()
    real[0] += k1
    und_real = cv2.undistortPoints(raw, K, real, P=K,
                                   criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                             100, 1e-12)).reshape(-1, 2)
    # where the real lens cannot be inverted (far outside the frame) the point stays where it is
    back, _ = cv2.projectPoints(np.concatenate([(und_real - K[:2, 2]) / np.diag(K)[:2],
                                                np.ones((len(und_real), 1))], axis=1
                                               ).reshape(-1, 1, 3),
                                np.zeros(3), np.zeros(3), K, real)
    ok = np.linalg.norm(back.reshape(-1, 2) - raw.reshape(-1, 2), axis=1) < 1e-3
    q = np.concatenate([und_real, np.ones((len(und_real), 1))], axis=1) @ H.T
    q = np.where(ok[:, None], q[:, :2] / q[:, 2:3], p[:, :2])
    return q[:, 0].reshape(X_MM.shape), q[:, 1].reshape(X_MM.shape)


def radial_image(depth, k1: float, camera: dict) -> np.ndarray:
    """``radial_image`` of the module docstring."""
    qx, qy = radial_image_points(k1, camera)
    return _view(depth, qx, qy, integrated=True)


def pixel_scale(depth, s_x: float, s_y: float, integrated: bool) -> np.ndarray:
    """``pixel_scale`` of the module docstring."""
    return _view(depth, (1.0 + s_x) * X_MM, (1.0 + s_y) * Y_MM, integrated)


def gain_gradient(depth, g0: float, g_x: float, g_y: float) -> np.ndarray:
    return np.asarray(depth, np.float64) * (1.0 + g0 + g_x * X_MM + g_y * Y_MM)


def blur(depth, sigma_mm: float) -> np.ndarray:
    s = sigma_mm / PITCH_MM
    return cv2.GaussianBlur(np.asarray(depth, np.float64), (0, 0), s, s,
                            borderType=cv2.BORDER_REPLICATE)


def saturation(depth, max_slope: float) -> np.ndarray:
    z = np.asarray(depth, np.float64)
    gx, gy = slopes(z)
    mag = np.hypot(gx, gy)
    factor = np.minimum(1.0, max_slope / np.maximum(mag, 1e-300))
    return z + integrate(gx * (factor - 1.0), gy * (factor - 1.0))


def banding(depth, amplitude_mm: float, period_mm: float, angle_deg: float,
            phase: float) -> np.ndarray:
    a = math.radians(angle_deg)
    s = X_MM * math.cos(a) + Y_MM * math.sin(a)
    return np.asarray(depth, np.float64) + np.where(
        PAD, amplitude_mm * np.sin(2 * np.pi * s / period_mm + phase), 0.0)


def dust(depth, height_mm: float, x_mm: float, y_mm: float, width_mm: float) -> np.ndarray:
    bump = height_mm * np.exp(-((X_MM - x_mm) ** 2 + (Y_MM - y_mm) ** 2) / (2 * width_mm**2))
    return np.asarray(depth, np.float64) + np.where(PAD, bump, 0.0)


# -------------------------------------------------------------------------- the dome
def read_stl(path) -> np.ndarray:
    """Triangles (m, 3, 3) mm of a binary STL file."""
    data = Path(path).read_bytes()
    (m,) = struct.unpack("<I", data[80:84])
    if len(data) != 84 + 50 * m:
        raise ValueError(f"{path}: not a binary STL file ({len(data)} bytes for {m} triangles)")
    rec = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    return np.frombuffer(data, rec, count=m, offset=84)["v"].astype(np.float64)


def write_stl(path, triangles: np.ndarray) -> None:
    tri = np.asarray(triangles, np.float64)
    rec = np.zeros(len(tri), np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)),
                                       ("attr", "<u2")]))
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    rec["n"] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    rec["v"] = tri
    Path(path).write_bytes(b"\0" * 80 + struct.pack("<I", len(tri)) + rec.tobytes())


def subdivide(triangles: np.ndarray, max_edge_mm: float, keep) -> np.ndarray:
    """Triangles split in four (edge midpoints) until every edge of those ``keep(tri)`` selects
    is at most ``max_edge_mm``."""
    tri = np.asarray(triangles, np.float64)
    for _ in range(12):
        edge = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
        split = (edge > max_edge_mm) & keep(tri)
        if not split.any():
            return tri
        t = tri[split]
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        new = np.concatenate([np.stack(q, axis=1) for q in
                              ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
        tri = np.concatenate([tri[~split], new])
    return tri


def domed_mesh(src, dst, contact: Contact, height_mm: float, relief_mm: float = 2.5) -> float:
    """Write to ``dst`` the indenter mesh ``src`` (binary STL, pressing face the top of the
    file) whose pressing face is moved away from the gel by the sag of a domed gel under it at
    ``contact``; returns the depth to simulate it at (the loader puts the new lowest point at
    z = 0).

    Frames (as documented for mesh indenters): the file is turned over, ``(x, y, z) -> (x, -y,
    -z)``, its x, y bounding-box centre put at the origin and its lowest point at z = 0; the
    contact's pose maps indenter points to the sensor frame, ``p = R(theta) q + (x, y)``."""
    tri = read_stl(src)
    v = tri.reshape(-1, 3)
    cx = 0.5 * (v[:, 0].min() + v[:, 0].max())
    cy = 0.5 * (v[:, 1].min() + v[:, 1].max())
    top = v[:, 2].max()
    # only the part near the pressing face needs the sag's curvature
    tri = subdivide(tri, 0.4, lambda t: np.min(top - t[:, :, 2], axis=1) < relief_mm)
    v = tri.reshape(-1, 3).copy()
    qx, qy = v[:, 0] - cx, -(v[:, 1] - cy)
    c, s = math.cos(math.radians(contact.theta_deg)), math.sin(math.radians(contact.theta_deg))
    px, py = contact.x_mm + c * qx - s * qy, contact.y_mm + s * qx + c * qy
    sag = height_mm * (px * px + py * py) / HALF_MM**2
    z_ind = top - v[:, 2]
    lowest = float(np.min(z_ind + sag))
    v[:, 2] -= sag  # the face moves away from the gel (up in the indenter frame)
    write_stl(dst, v.reshape(-1, 3, 3))
    return contact.depth_mm - lowest


def domed_contacts(contacts: list[Contact], height_mm: float, workdir) -> list[Contact]:
    """The contacts with every indenter mesh rewritten for a domed gel (:func:`domed_mesh`)."""
    out = []
    for k, c in enumerate(contacts):
        if not str(c.indenter).lower().endswith(".stl"):
            raise ValueError(f"the dome is made by rewriting indenter meshes: {c.indenter!r} is "
                             "not an STL file")
        dst = Path(workdir) / f"domed_{k:03d}_{Path(c.indenter).stem}.stl"
        depth = domed_mesh(c.indenter, dst, c, height_mm)
        out.append(Contact(str(dst), c.x_mm, c.y_mm, c.theta_deg, depth))
    return out


# ------------------------------------------------------------------ contact and material
def reached_contacts(contacts: list[Contact], effect: str, params: dict) -> list[Contact]:
    """The contacts the rig really makes when the commanded ones are ``contacts``."""
    out = []
    for c in contacts:
        x, y, t, d = c.x_mm, c.y_mm, c.theta_deg, c.depth_mm
        if effect == "zero_offset":
            d = d + params["offset_mm"]
        elif effect == "depth_scale":
            d = d * (1.0 + params["scale"])
        elif effect == "position_offset":
            x, y = x + params["dx_mm"], y + params["dy_mm"]
        elif effect == "rotation_offset":
            t = t + params["dtheta_deg"]
        else:
            raise ValueError(f"{effect!r} does not move the contact")
        out.append(Contact(c.indenter, x, y, t, d))
    return out


#: Effects applied to the map (name -> function of (depth, params, camera)).
MAP_EFFECTS = {
    "radial_map": lambda d, p, cam: radial_map(d, p["k"], (p["cx_mm"], p["cy_mm"])),
    "radial_image": lambda d, p, cam: radial_image(d, p["k1"], cam),
    "pixel_scale_iso": lambda d, p, cam: pixel_scale(d, p["s"], p["s"], p["integrated"] > 0),
    "pixel_scale_axis": lambda d, p, cam: pixel_scale(d, p["s_x"], p["s_y"], p["integrated"] > 0),
    "gain_gradient": lambda d, p, cam: gain_gradient(d, p["g0"], p["g_x"], p["g_y"]),
    "blur": lambda d, p, cam: blur(d, p["sigma_mm"]),
    "saturation": lambda d, p, cam: saturation(d, p["max_slope"]),
    "banding": lambda d, p, cam: banding(d, p["amplitude_mm"], p["period_mm"], p["angle_deg"],
                                         p["phase"]),
    "dust": lambda d, p, cam: dust(d, p["height_mm"], p["x_mm"], p["y_mm"], p["width_mm"]),
}
#: Effects that change where the contact is.
POSE_EFFECTS = ("zero_offset", "depth_scale", "position_offset", "rotation_offset")
#: Effects that change the gel (simulated clean with another material or contact law).
MATERIAL_EFFECTS = ("poisson", "friction")
#: The effects the discrepancy library is expected to name (-> the candidate's name) and those
#: it must call unexplained.
EXPECTED = {"radial_map": "lens_distortion", "radial_image": "lens_distortion",
            "pixel_scale_iso": "pixel_scale", "pixel_scale_axis": "pixel_scale",
            "gain_gradient": "gain_gradient", "blur": "blur", "saturation": "shading_saturation",
            "zero_offset": "zero_offset", "depth_scale": "depth_scale",
            "position_offset": "position_offset", "rotation_offset": "rotation_offset",
            "dome": "dome", "poisson": "poisson_drift", "friction": "friction",
            "banding": "unexplained", "dust": "unexplained"}


def draw(effect: str, rng: np.random.Generator) -> dict:
    """Parameters of ``effect`` at random from what real sensors show (either sign where both
    occur; magnitudes well clear of zero so that the effect is there to be found)."""
    def signed(lo, hi):
        return float(rng.uniform(lo, hi) * rng.choice((-1.0, 1.0)))

    if effect == "radial_map":  # 5-16 % at the rim, centre within 1.5 mm of the pad's
        return {"k": signed(0.05, 0.16), "cx_mm": float(rng.uniform(-1.5, 1.5)),
                "cy_mm": float(rng.uniform(-1.5, 1.5))}
    if effect == "radial_image":
        return {"k1": signed(0.08, 0.25)}
    if effect == "pixel_scale_iso":  # the most common calibration error: 3-8 %
        return {"s": signed(0.03, 0.08), "integrated": float(rng.integers(2))}
    if effect == "pixel_scale_axis":  # one image axis against the other: 2-5 %
        s = signed(0.02, 0.05)
        along_x = rng.integers(2) == 1
        return {"s_x": s if along_x else 0.0, "s_y": 0.0 if along_x else s,
                "integrated": float(rng.integers(2))}
    if effect == "gain_gradient":  # 10-30 % across a 15 mm view
        a = rng.uniform(0.0, 2 * np.pi)
        g = rng.uniform(0.007, 0.02)
        return {"g0": float(rng.uniform(-0.05, 0.05)), "g_x": float(g * np.cos(a)),
                "g_y": float(g * np.sin(a))}
    if effect == "blur":
        return {"sigma_mm": float(rng.uniform(0.15, 0.4))}
    if effect == "saturation":
        return {"max_slope": float(rng.uniform(0.3, 0.5))}
    if effect == "zero_offset":
        return {"offset_mm": signed(0.01, 0.05)}
    if effect == "depth_scale":
        return {"scale": signed(0.02, 0.06)}
    if effect == "position_offset":
        r, a = rng.uniform(0.1, 0.3), rng.uniform(0.0, 2 * np.pi)
        return {"dx_mm": float(r * np.cos(a)), "dy_mm": float(r * np.sin(a))}
    if effect == "rotation_offset":
        return {"dtheta_deg": signed(2.0, 5.0)}
    if effect == "dome":
        return {"height_mm": signed(0.1, 0.4)}
    if effect == "poisson":
        return {"delta_nu": float(rng.uniform(-0.03, -0.01))}
    if effect == "friction":
        return {"law": 1.0}
    if effect == "banding":
        return {"amplitude_mm": float(rng.uniform(0.004, 0.012)),
                "period_mm": float(rng.uniform(1.5, 4.0)),
                "angle_deg": float(rng.uniform(0.0, 180.0)),
                "phase": float(rng.uniform(0.0, 2 * np.pi))}
    if effect == "dust":
        return {"height_mm": float(rng.uniform(0.01, 0.03)), "x_mm": float(rng.uniform(-5, 5)),
                "y_mm": float(rng.uniform(-5, 5)), "width_mm": float(rng.uniform(0.5, 1.0))}
    raise ValueError(f"unknown effect {effect!r}")


def measured_maps(effect: str, params: dict, contacts: list[Contact], clean: np.ndarray,
                  simulate, camera: dict | None, noise_mm: float,
                  rng: np.random.Generator, workdir: Path | None = None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Depth maps (N, 128, 128) mm with ``effect`` and white pixel noise on the pad, and the
    forces (N,) N of contacts the effect changes (None: the clean ones).

    clean : (N, 128, 128) clean maps of ``contacts``. simulate(contacts, material) -> (maps,
    forces): clean simulations (NaN maps for contacts it could not make) (``material``: None, ``{"delta_nu": ...}`` or ``{"friction":
    "stick"}``). camera : the plugin's camera-mapping JSON dict (for ``radial_image``).
    workdir : a folder for the rewritten indenter meshes of the dome.
    """
    forces = None
    if effect == "none":
        maps = np.asarray(clean, np.float64)
    elif effect in MAP_EFFECTS:
        maps = np.stack([MAP_EFFECTS[effect](d, params, camera) for d in clean])
    elif effect in POSE_EFFECTS:
        maps, forces = simulate(reached_contacts(contacts, effect, params), None)
    elif effect == "dome":
        if workdir is None:
            raise ValueError("the dome rewrites indenter meshes: give a workdir")
        maps, forces = simulate(domed_contacts(contacts, params["height_mm"], workdir), None)
    elif effect == "poisson":
        maps, forces = simulate(contacts, {"delta_nu": params["delta_nu"]})
    elif effect == "friction":
        maps, forces = simulate(contacts, {"friction": "stick"})
    else:
        raise ValueError(f"unknown effect {effect!r}")
    noisy = np.where(PAD, maps + rng.normal(0.0, noise_mm, np.shape(maps)), 0.0)
    # a contact the simulation could not make stays NaN (left out by the caller)
    noisy[~np.all(np.isfinite(maps), axis=(1, 2))] = np.nan
    return noisy.astype(np.float32), forces


def view_displacement(effect: str, params: dict, camera: dict | None) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    """(q - p) x and y, mm, of an optical effect's view at every map pixel (for parameter
    checks by displacement field)."""
    if effect == "radial_map":
        cx, cy = params["cx_mm"], params["cy_mm"]
        dx, dy = X_MM - cx, Y_MM - cy
        ux, uy = dx.copy(), dy.copy()
        for _ in range(50):
            f = 1.0 + params["k"] * (ux * ux + uy * uy) / HALF_MM**2
            ux, uy = dx / f, dy / f
        return cx + ux - X_MM, cy + uy - Y_MM
    if effect == "radial_image":
        qx, qy = radial_image_points(params["k1"], camera)
        return qx - X_MM, qy - Y_MM
    if effect == "pixel_scale_iso":
        return params["s"] * X_MM, params["s"] * Y_MM
    if effect == "pixel_scale_axis":
        return params["s_x"] * X_MM, params["s_y"] * Y_MM
    raise ValueError(f"{effect!r} does not move the view")
