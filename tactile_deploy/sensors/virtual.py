"""A virtual tactile sensor: pad + FEM + optics + effects + noise, as a camera you can press.

Data flow of :meth:`VirtualSensor.press` (one commanded contact -> one RGB frame)::

    commanded pose --contact effects (zero offset)--> pose reached
    indenter intrusion at sensor points --contact effects (tilt)--> intrusion below z = 0
    rest height (geometry effects: dome) -> intrusion into the gel at the sensing nodes
        --ContactSimulator.solve_intrusion (exact frictionless/stick contact)--> FEM solution
        --material effects (hyperelastic)--> FEM solution
    fine height map (tactile_deploy.optics.surface: FEM surface + the indenter's exact shape)
        --OpticsRenderer (optics model after the optics effects: lens, pixel scale, exposure)
        --camera effects (illumination gradient, LED drift), noise, 8-bit--> RGB frame

For evaluation only, each :class:`SensorFrame` also carries the truth: the depth map on the
standard 128 x 128 grid (rendered from the deformed pad mesh, as ``simulate`` writes it), the
fine depth map the frame was shaded from, the deformed mesh and the force.

As a frame source the sensor follows the LeRobot camera pattern: ``connect()`` / ``read()`` /
``disconnect()`` (or ``with sensor:``), frames at the camera's ``fps`` from a scripted contact
sequence (:class:`PressScript`), optionally paced to the wall clock; :meth:`VirtualSensor.frames`
is the same as a generator of ``(timestamp_s, frame)``; :meth:`record_reference` averages
no-contact frames. The recordings the calibrations take as input (FOTS-style ball presses, a
pressed pin grid) are made by :mod:`tactile_deploy.calibration.virtual_recordings`.

Frames are RGB (H, W, 3) uint8 in raw camera pixels; poses and points are in the sensor frame
(mm, origin at the centre of the sensing surface, z out of the gel).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from tactile_deploy.camera.depth import DepthCamera
from tactile_deploy.imaging.camera_mapping import sensor_mm_to_pixels
from tactile_deploy.indenters import ContactPose, get_indenter
from tactile_deploy.optics.render import OpticsRenderer, grid_centres, grid_for_camera
from tactile_deploy.optics.surface import SurfaceBuilder
from tactile_deploy.sensors.config import VirtualSensorConfig
from tactile_deploy.sensors.effects import get_effect
from tactile_deploy.simulation.contact import (
    ContactError,
    ContactSample,
    get_camera,
    get_simulator,
    indenter_record,
)

#: Deepest indentation (mm) a virtual sensor accepts, as for ``simulate`` (half the gel).
MAX_DEPTH_MM = 1.5


class SensorNotConnectedError(RuntimeError):
    """``read()`` before ``connect()`` (or after ``disconnect()``)."""


@dataclass(frozen=True)
class SensorFrame:
    """One frame of a virtual sensor, with the truth behind it (evaluation only).

    frame : (H, W, 3) uint8 RGB, raw camera pixels.
    depth_mm : (128, 128) float32, mm pushed in from rest, standard depth grid (row 0 = largest
        y), rendered from the deformed pad mesh.
    surface_depth_mm : (ny, nx) float32, mm pushed in from rest, on the optics grid
        (``sensor.renderer.grid``): what the frame was shaded from.
    vertices_mm : (n, 3) float32, deformed pad mesh, sensor frame (displacement of the shipped
        mesh; a dome's rest shape is not in it).
    force_n : total normal force, N. pose : commanded pose; pose_reached : after contact effects.
    in_contact : False when the indenter does not reach the gel (the frame is the reference).
    """

    frame: np.ndarray
    depth_mm: np.ndarray | None
    surface_depth_mm: np.ndarray | None
    vertices_mm: np.ndarray | None
    force_n: float
    pose: ContactPose | None
    pose_reached: ContactPose | None
    in_contact: bool
    metadata: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------ scripts
@dataclass(frozen=True)
class PressEvent:
    """One press of a scripted sequence: ramp in over ``press_s``, hold, ramp out.

    indenter : library name or mesh path; x_mm, y_mm, theta_deg : pose (sensor frame);
    depth_mm : depth at the hold; start_s : time the ramp starts, s.
    """

    indenter: str
    x_mm: float = 0.0
    y_mm: float = 0.0
    theta_deg: float = 0.0
    depth_mm: float = 0.5
    start_s: float = 0.0
    press_s: float = 0.5
    hold_s: float = 0.5
    release_s: float = 0.5

    @property
    def end_s(self) -> float:
        return self.start_s + self.press_s + self.hold_s + self.release_s

    def depth_at(self, t_s: float) -> float:
        """Commanded depth (mm) at time t (s): linear ramps, 0 outside the event."""
        t = t_s - self.start_s
        if t <= 0 or t >= self.press_s + self.hold_s + self.release_s:
            return 0.0
        if t < self.press_s:
            return self.depth_mm * t / self.press_s
        if t <= self.press_s + self.hold_s:
            return self.depth_mm
        return self.depth_mm * (1.0 - (t - self.press_s - self.hold_s) / self.release_s)


@dataclass(frozen=True)
class PressScript:
    """A contact sequence: press events (not overlapping) and a total duration (s)."""

    events: tuple[PressEvent, ...] = ()
    duration_s: float | None = None

    def __post_init__(self):
        ev = sorted(self.events, key=lambda e: e.start_s)
        for a, b in itertools.pairwise(ev):
            if b.start_s < a.end_s:
                raise ValueError(f"press events overlap: one ends at {a.end_s} s, the next starts "
                                 f"at {b.start_s} s")
        object.__setattr__(self, "events", tuple(ev))

    @property
    def end_s(self) -> float:
        if self.duration_s is not None:
            return float(self.duration_s)
        return max((e.end_s for e in self.events), default=0.0)

    def state(self, t_s: float):
        """``(event, depth_mm)`` of the press active at t, or ``(None, 0.0)``."""
        for e in self.events:
            d = e.depth_at(t_s)
            if d > 0:
                return e, d
        return None, 0.0


# ------------------------------------------------------------------------------ sensor
class VirtualSensor:
    """A virtual tactile sensor built from a :class:`VirtualSensorConfig`.

    The FEM simulator, the optics renderer and the surface builder are built on first use
    (``prepare()`` builds them now). ``simulator``: share one ContactSimulator between sensors of
    the same pad and material.
    """

    def __init__(self, config: VirtualSensorConfig, simulator=None):
        self.config = config
        self.name = config.name
        self.effects = [get_effect(e.name, e.params) for e in config.effects]
        optics = config.optics
        for e in self._stage("optics"):
            optics = e.optics(optics)
        #: The optics model after the optics-stage effects (what the renderer uses).
        self.optics = optics
        self._simulator = simulator
        self._renderer = None
        self._surface = None
        self._depth_camera = None
        self._connected = False
        self._script: PressScript | None = None
        self._frame_index = 0
        self._live = False
        self._t0 = 0.0
        self._indenters: dict[str, object] = {}
        self.last_timestamp_s: float | None = None

    def __repr__(self) -> str:
        fx = ", ".join(e.name for e in self.effects if not e.is_null) or "none"
        w, h = self.optics.image_size
        return f"VirtualSensor({self.name!r}, {w}x{h} px at {self.config.fps:g} fps, effects: {fx})"

    def _stage(self, stage: str):
        return [e for e in self.effects if e.stage == stage]

    # ------------------------------------------------------------------- components
    @property
    def simulator(self):
        if self._simulator is None:

            self._simulator = get_simulator(self.config.material, self.config.pad)
        return self._simulator

    @property
    def renderer(self):
        """The :class:`~tactile_deploy.optics.OpticsRenderer` (rest surface from the effects)."""
        if self._renderer is None:

            grid = grid_for_camera(self.optics)
            rest = self._rest_height_grid(grid)
            self._renderer = OpticsRenderer(self.optics, grid, rest_height_mm=rest,
                                            noise_seed=self.config.seed)
        return self._renderer

    @property
    def surface(self):
        if self._surface is None:

            self._surface = SurfaceBuilder(self.simulator.mesh, self.renderer.grid,
                                           smooth_mm=self.config.surface_smooth_mm)
        return self._surface

    def prepare(self) -> None:
        """Build the simulator's operators, the renderer and the surface builder now."""
        self.simulator.prepare()
        _ = self.renderer, self.surface

    def _rest_height_grid(self, grid) -> np.ndarray:
        x, y = grid_centres(grid)
        xy = np.stack([x.ravel(), y.ravel()], axis=1)
        return self.rest_height_mm(xy).reshape(x.shape).astype(np.float32)

    def rest_height_mm(self, xy_mm: np.ndarray) -> np.ndarray:
        """Rest height of the sensing surface at sensor points (k, 2) -> (k,) mm (0: flat)."""
        xy = np.asarray(xy_mm, np.float64)
        z = np.zeros(len(xy))
        for e in self._stage("geometry"):
            z = z + e.rest_height_mm(xy)
        return z

    def _gain(self, rng):
        gain = None
        for e in self._stage("camera"):
            g = e.frame_gain(self.renderer, rng)
            if g is not None:
                gain = g if gain is None else gain * g
        return gain

    def indenter(self, name: str):
        """Library indenter by name or mesh path (cached)."""
        if name not in self._indenters:

            self._indenters[name] = get_indenter(name)
        return self._indenters[name]

    # ------------------------------------------------------------------------- frames
    def reference_frame(self, rng: np.random.Generator | None = None) -> np.ndarray:
        """Frame with nothing touching the sensor, (H, W, 3) uint8 (noise-free if rng is None)."""
        return self.renderer.reference_frame(rng, self._gain(rng))

    def press(self, indenter, pose: ContactPose, rng: np.random.Generator | None = None,
              truth: bool = True) -> SensorFrame:
        """Frame of ``indenter`` (Indenter, :class:`~tactile_deploy.indenters.pin_grid.PinGrid` or library name) pressed at ``pose``.

        rng : noise (and per-frame camera effects) generator; None renders noise-free.
        truth : also return the standard 128 x 128 depth map and the mesh.
        Raises :class:`tactile_deploy.simulation.contact.ContactError` for depths beyond
        ``MAX_DEPTH_MM`` or poses off the pad.
        """
        return self._press(indenter, pose, rng, truth)[0]

    def press_frames(self, indenter, pose: ContactPose,
                     rngs: list[np.random.Generator]) -> tuple[list[np.ndarray], float]:
        """Frames of one contact under several noise draws: ``(frames, force_n)``.

        One FEM solve and one shading for all of them; each frame is :meth:`press`'s frame
        with its own ``rng`` (camera noise and per-frame camera effects), (H, W, 3) uint8.
        Raises what :meth:`press` raises.
        """
        if isinstance(indenter, str):
            indenter = self.indenter(indenter)
        reached, intrusion, result = self.solve_contact(indenter, pose)
        renderer = self.renderer
        if result is None:
            return [renderer.reference_frame(r, self._gain(r)) for r in rngs], 0.0
        height = self.surface.height(result.vertices_mm, renderer.rest_height_mm, intrusion,
                                     (reached.x_mm, reached.y_mm), indenter.footprint_radius_mm)
        radiance, region = renderer.blurred_radiance(height, with_region=True)
        return ([renderer.finish(radiance, r, self._gain(r), region) for r in rngs],
                float(result.force_n))

    def contact_sample(self, indenter, pose: ContactPose,
                       rng: np.random.Generator | None = None):
        """The contact as a :class:`~tactile_deploy.simulation.contact.ContactSample` (the
        ``simulate`` format) with the sensor's frame in ``frame``; ``depth_detail`` is the depth
        the frame was shaded from, sampled at the standard depth grid's pixel centres."""
        from scipy.ndimage import map_coordinates

        if isinstance(indenter, str):
            indenter = self.indenter(indenter)
        out, result = self._press(indenter, pose, rng, True)
        cam = get_camera()
        mesh = self.simulator.mesh
        image = cam.render(mesh, out.vertices_mm)
        c = cam.pixel_centres_mm()
        g = self.renderer.grid
        col = (c[..., 0] - g.x_min_mm) / g.pitch_x_mm - 0.5
        row = (g.y_max_mm - c[..., 1]) / g.pitch_y_mm - 0.5
        inside = (col >= 0) & (col <= g.nx - 1) & (row >= 0) & (row <= g.ny - 1)
        fine = map_coordinates(out.surface_depth_mm.astype(np.float64), [row, col], order=1,
                               mode="nearest")
        detail = np.where(image.mask & inside, np.maximum(fine, image.depth_mm), image.depth_mm)
        n_plane = mesh.n_plane
        meta = dict(out.metadata)
        meta.update(indenter_record(indenter))   # a mesh file: its absolute path and sha256
        meta.update({
            "material": self.simulator.material.model_dump(),
            "effects": [e.spec() for e in self.effects],
            "mesh_hash": mesh.content_hash, "n_nodes": mesh.n_nodes,
            "units": {"depth": "mm", "vertices": "mm", "force_n": "N", "pressure_kpa": "kPa",
                      "frame": "RGB uint8, raw camera pixels"},
            "frame_shape": list(out.frame.shape),
            "depth_detail": "depth the frame was shaded from (inside the camera view)",
            "frame": "sensor: origin at the centre of the sensing surface, z up out of the gel"})
        return ContactSample(
            depth_mm=out.depth_mm, depth_detail_mm=detail.astype(np.float32), mask=image.mask,
            vertices_mm=out.vertices_mm, rest_vertices_mm=mesh.vertices.astype(np.float32),
            force_n=out.force_n,
            contact_mask=(result.contact_mask if result is not None
                          else np.zeros(n_plane, bool)),
            pressure_kpa=(result.pressure_kpa.astype(np.float32) if result is not None
                          else np.zeros(n_plane, np.float32)),
            metadata=meta, frame=out.frame)

    def contact_force_n(self, indenter, pose: ContactPose) -> float:
        """Total normal force (N) of ``indenter`` pressed at ``pose`` (no frame rendered): what a
        force gauge under the sensor reads. 0 when the indenter does not reach the gel."""
        result = self.solve_contact(indenter, pose)[2]
        return 0.0 if result is None else float(result.force_n)

    def solve_contact(self, indenter, pose: ContactPose):
        """The mechanics of one contact: ``(pose_reached, intrusion, result)``.

        ``intrusion`` maps sensor points (k, 2) mm to the indenter's intrusion (k,) mm below
        z = 0 after the contact effects; ``result`` is the FEM solution after the material
        effects (a ``ContactResult``), or None when the indenter does not reach the gel.
        Raises :class:`tactile_deploy.simulation.contact.ContactError` for depths beyond
        ``MAX_DEPTH_MM`` or poses off the pad.
        """

        if isinstance(indenter, str):
            indenter = self.indenter(indenter)
        sim = self.simulator
        mesh = sim.mesh
        reached = pose
        for e in self._stage("contact"):
            reached = e.contact_pose(reached)
        if reached.depth_mm > MAX_DEPTH_MM:
            raise ContactError(
                f"depth {reached.depth_mm:g} mm (commanded {pose.depth_mm:g} mm) exceeds "
                f"{MAX_DEPTH_MM:g} mm, half of the {mesh.geometry.thickness_mm:g} mm gel; press "
                "less deep")
        if not mesh.geometry.contains_xy(reached.x_mm, reached.y_mm):
            raise ContactError(f"pose (x_mm={pose.x_mm}, y_mm={pose.y_mm}) is off the pad "
                               f"(radius {mesh.geometry.half_extent_mm:g} mm)")
        contact_fx = self._stage("contact")

        def intrusion(xy):
            xy = np.asarray(xy, np.float64)
            if reached.depth_mm <= 0:
                return np.full(len(xy), -np.inf)
            d = np.asarray(indenter.intrusion_mm(xy, reached), np.float64)
            for e in contact_fx:
                d = e.intrusion_mm(d, xy, reached)
            return d

        node_xy = mesh.vertices[mesh.sensing_nodes, :2]
        delta = intrusion(node_xy) + self.rest_height_mm(node_xy)
        if not np.any(delta > 0):
            return reached, intrusion, None
        result = sim.solve_intrusion(delta)
        for e in self._stage("material"):
            result = e.correct_contact(sim, delta, result)
        return reached, intrusion, result

    def depth_map(self, indenter, pose: ContactPose) -> tuple[np.ndarray, float]:
        """The truth of :meth:`press` without a frame: ``(depth_mm, force_n)``.

        depth_mm : (128, 128) float32, mm pushed in, standard depth grid (row 0 = largest y),
        rendered from the deformed pad mesh (zeros when the indenter does not reach the gel);
        force_n : total normal force, N.
        """
        _, _, result = self.solve_contact(indenter, pose)
        if result is None:
            g = self.depth_grid
            return np.zeros((g.ny, g.nx), np.float32), 0.0
        return self._render_depth(result.vertices_mm), float(result.force_n)

    @property
    def depth_grid(self):
        """The grid of the truth depth maps: the pad family's depth grid (GelSlim: the model
        grid, 128 x 128 over +-17.5 mm)."""
        from tactile_deploy.pad.family import FAMILIES

        return FAMILIES[self.config.pad].depth_grid

    def _render_depth(self, vertices_mm: np.ndarray) -> np.ndarray:
        if self._depth_camera is None:

            g = self.depth_grid
            self._depth_camera = (DepthCamera() if self.config.pad == "gelslim"
                                  else DepthCamera.for_grid(g))
        return self._depth_camera.render(self.simulator.mesh, vertices_mm).depth_mm

    def _press(self, indenter, pose: ContactPose, rng, truth: bool):
        """``(SensorFrame, ContactResult or None)`` of one contact (see :meth:`press`)."""
        if isinstance(indenter, str):
            indenter = self.indenter(indenter)
        mesh = self.simulator.mesh
        reached, intrusion, result = self.solve_contact(indenter, pose)
        gain = self._gain(rng)
        meta = {"sensor": self.name, "indenter": getattr(indenter, "name", str(indenter)),
                "pose": pose.model_dump(), "pose_reached": reached.model_dump()}
        if result is None:
            frame = self.renderer.reference_frame(rng, gain)
            g = self.depth_grid
            zeros = np.zeros((g.ny, g.nx), np.float32) if truth else None
            return SensorFrame(frame, zeros, np.zeros((self.renderer.grid.ny,
                                                       self.renderer.grid.nx), np.float32),
                               mesh.vertices.astype(np.float32) if truth else None, 0.0, pose,
                               reached, False, meta), None
        rest = self.renderer.rest_height_mm
        height = self.surface.height(result.vertices_mm, rest, intrusion,
                                     (reached.x_mm, reached.y_mm), indenter.footprint_radius_mm)
        frame = self.renderer.render(height, rng, gain)
        depth = self._render_depth(result.vertices_mm) if truth else None
        return SensorFrame(frame, depth, (rest - height).astype(np.float32),
                           result.vertices_mm.astype(np.float32) if truth else None,
                           float(result.force_n), pose, reached, True, meta), result

    # ------------------------------------------------------------------- frame source
    def connect(self, script: PressScript | None = None, live: bool = False) -> VirtualSensor:
        """Start streaming ``script`` (None: nothing touches the sensor) from t = 0.

        live : pace ``read()`` to the wall clock at the camera's fps.
        """
        self.prepare()
        self._script = script or PressScript()
        self._frame_index = 0
        self._live = bool(live)
        self._t0 = time.monotonic()
        self._connected = True
        return self

    @property
    def is_connected(self) -> bool:
        return self._connected

    def read(self) -> np.ndarray:
        """Next frame of the stream, (H, W, 3) uint8 RGB; its time is ``last_timestamp_s``.

        Live: waits until the frame's time on the wall clock (frames are never early; when
        rendering is slower than the fps they come as fast as they are made, with their
        scripted timestamps).
        """
        if not self._connected:
            raise SensorNotConnectedError(f"virtual sensor {self.name!r} is not connected; call "
                                          "connect() first (or use it in a with block)")
        t, frame = self._frame_at(self._frame_index)
        self._frame_index += 1
        if self._live:
            delay = self._t0 + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        self.last_timestamp_s = t
        return frame

    def disconnect(self) -> None:
        self._connected = False

    def __enter__(self) -> VirtualSensor:
        if not self._connected:
            self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.disconnect()

    def _frame_at(self, k: int):
        t = k / self.config.fps
        rng = np.random.default_rng([self.config.seed, 0x66726D, k])
        event, depth = self._script.state(t) if self._script else (None, 0.0)
        if event is None:
            return t, self.reference_frame(rng)
        pose = ContactPose(x_mm=float(event.x_mm), y_mm=float(event.y_mm),
                           theta_deg=float(event.theta_deg), depth_mm=float(depth))
        return t, self.press(event.indenter, pose, rng, truth=False).frame

    def frames(self, script: PressScript, live: bool = False) -> Iterator[tuple[float, np.ndarray]]:
        """``(timestamp_s, frame)`` at the camera's fps over the script's duration."""
        self.connect(script, live)
        try:
            n = math.floor(script.end_s * self.config.fps + 1e-9) + 1
            for _ in range(n):
                frame = self.read()
                yield self.last_timestamp_s, frame
        finally:
            self.disconnect()

    # --------------------------------------------------------------------- recordings
    def record_reference(self, seed: int = 0, n_average: int = 1) -> np.ndarray:
        """A no-contact reference frame (mean of ``n_average`` noisy frames, rounded), uint8."""
        acc = np.zeros((*self.renderer.shape, 3))
        for i in range(n_average):
            acc += self.reference_frame(np.random.default_rng([self.config.seed, seed, i]))
        return np.clip(np.rint(acc / n_average), 0, 255).astype(np.uint8)

    def view_box_mm(self, margin_mm: float = 0.0) -> tuple[float, float, float, float]:
        """Sensor-frame box (x0, x1, y0, y1) mm seen whole by the camera, shrunk by a margin.

        The bounding box of the view, shrunk about its centre until its outline images inside
        the frame (bisection, to 1e-3 of its size).
        """

        xy = self.renderer.pixel_xy_mm.reshape(-1, 2)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        c, half = (lo + hi) / 2.0, (hi - lo) / 2.0
        t = np.linspace(-1.0, 1.0, 41)
        one = np.ones_like(t)
        outline = np.concatenate([np.stack([t, one], 1), np.stack([t, -one], 1),
                                  np.stack([one, t], 1), np.stack([-one, t], 1)])
        w, h = self.optics.image_size

        def fits(scale):
            uv = sensor_mm_to_pixels(c + scale * half * outline, self.optics.camera)
            return bool(np.all((uv >= -0.5) & (uv <= [w - 0.5, h - 0.5])))

        a, b = 0.0, 1.0
        for _ in range(12):
            mid = 0.5 * (a + b)
            a, b = (mid, b) if fits(mid) else (a, mid)
        hx, hy = a * half
        return (c[0] - hx + margin_mm, c[0] + hx - margin_mm, c[1] - hy + margin_mm,
                c[1] + hy - margin_mm)
