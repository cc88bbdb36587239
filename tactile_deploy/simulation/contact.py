"""Simulate one commanded contact end to end.

Data flow of :func:`simulate_contact`::

    check pose -> ContactSimulator.solve (FEM; CoulombSimulator for friction "coulomb")
        -> DepthCamera.render -> ContactSample

The ground-truth depth map ``depth_mm`` is rendered from the deformed 5,380-node pad mesh, so it
is exactly consistent with ``vertices_mm`` (what a model is trained to predict). That mesh has a
node spacing of ~1 mm, so contact features finer than ~2 mm are smoothed in it. The rigid
indenter cannot be penetrated, so ``depth_detail_mm = max(depth_mm, intrusion)`` (the indenter's
intrusion below the rest surface at each pixel centre) restores those features inside the
contact: use it where a sharper image of the surface matters (the optics), and say so.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from tactile_deploy.camera.depth import DepthCamera
from tactile_deploy.fem.material import Material
from tactile_deploy.fem.simulator import ContactSimulator
from tactile_deploy.indenters import ContactPose, Indenter
from tactile_deploy.pad.asset import load_pad
from tactile_deploy.pad.mesh import PadMesh

#: Deepest indentation the linear model is used for, as a fraction of the pad thickness.
MAX_DEPTH_FRACTION = 0.5

GENERATOR_VERSION = "1"

SENSOR_FRAME = "sensor: origin at the centre of the sensing surface, z up out of the gel"
#: What the two depth maps of a contact are (written into every file that stores them).
DEPTH_MEANING = (
    "mm pushed in along -z (>= 0), rendered from the deformed pad mesh (~1 mm node spacing: "
    "features finer than ~2 mm are smoothed); consistent with the deformed vertices"
)
DEPTH_DETAIL_MEANING = (
    "mm, max(depth, the indenter's intrusion below the rest surface at each pixel centre) on the "
    "pad: depth with the indenter's fine features restored inside the contact"
)


def camera_metadata(camera: DepthCamera) -> dict:
    """The image geometry of ``camera``'s depth maps, for file metadata."""
    h, p, n = camera.half_extent_mm, camera.pitch_mm, camera.resolution
    return {
        "shape_px": [n, n],
        "half_extent_mm": h,
        "pixel_pitch_mm": p,
        "projection": "orthographic along +z, sensor frame",
        "pixel_centre": f"row i, column j at x_mm = -{h} + (j + 0.5) * {p}, "
                        f"y_mm = {h} - (i + 0.5) * {p}: row 0 = largest y, column 0 = smallest x",
    }


class ContactError(ValueError):
    """A commanded contact the simulator cannot or should not run (message says why and what to do)."""


@dataclass(frozen=True)
class ContactSample:
    """One simulated contact.

    depth_mm : (H, W) float32, mm pushed in (image rows: row 0 = largest y)
    depth_detail_mm : (H, W) float32, mm, with the indenter's non-penetration floor
    mask : (H, W) bool, pixel on the pad
    vertices_mm : (n, 3) float32, deformed, sensor frame
    rest_vertices_mm : (n, 3) float32, sensor frame
    force_n : float, total normal force (N)
    contact_mask : (n_plane,) bool, sensing nodes in contact
    pressure_kpa : (n_plane,) float32
    metadata : dict (indenter, pose, material, mesh hash, generator version)
    stick_mask : (n_plane,) bool, sensing nodes in contact that stick (resolved contacts), or None
    frame : (H, W, 3) uint8 RGB camera frame of a virtual sensor, or None
        (``tactile_deploy.sensors.VirtualSensor.contact_sample``)
    """

    depth_mm: np.ndarray
    depth_detail_mm: np.ndarray
    mask: np.ndarray
    vertices_mm: np.ndarray
    rest_vertices_mm: np.ndarray
    force_n: float
    contact_mask: np.ndarray
    pressure_kpa: np.ndarray
    metadata: dict = field(default_factory=dict)
    frame: np.ndarray | None = None
    stick_mask: np.ndarray | None = None

    def npz_arrays(self) -> dict[str, np.ndarray]:
        """Arrays of the ``simulate --out FILE.npz`` format (metadata checked as
        :class:`~tactile_deploy.simulation.contact_file.ContactMetadata`, stored as a JSON string;
        ``frame`` only when a virtual sensor rendered one). Raises
        :class:`~tactile_deploy.simulation.contact_file.ContactFileError` when the metadata does
        not follow the format."""
        from tactile_deploy.simulation.contact_file import contact_metadata

        meta = contact_metadata(self.metadata, "contact metadata to write")
        arrays = {
            "depth": self.depth_mm,
            "depth_detail": self.depth_detail_mm,
            "mask": self.mask,
            "vertices": self.vertices_mm,
            "rest_vertices": self.rest_vertices_mm,
            "force_n": np.float32(self.force_n),
            "contact_mask": self.contact_mask,
            "pressure_kpa": self.pressure_kpa,
            "metadata": np.array(meta.json_text()),
        }
        if self.frame is not None:
            arrays["frame"] = self.frame
        if self.stick_mask is not None:
            arrays["stick_mask"] = self.stick_mask
        return arrays


@functools.lru_cache(maxsize=8)
def get_simulator(material: Material, pad: str = "gelslim") -> ContactSimulator:
    """A cached simulator of the shipped pad for ``material`` (operators load from disk cache).

    Friction "coulomb": a :class:`~tactile_deploy.fem.coulomb.CoulombSimulator` sharing the
    operators of the "stick" simulator of the same nu (one copy in memory for every mu)."""
    if material.friction == "coulomb":
        from tactile_deploy.fem.coulomb import CoulombSimulator

        stick = get_simulator(Material(E_mpa=material.E_mpa, nu=material.nu, friction="stick"), pad)
        return CoulombSimulator.sharing(stick, material)
    return ContactSimulator(load_pad(pad), material)


@functools.lru_cache(maxsize=4)
def get_camera(half_extent_mm: float = 17.5, resolution: int = 128) -> DepthCamera:
    return DepthCamera(half_extent_mm, resolution)


def check_pose(mesh: PadMesh, indenter: Indenter, pose: ContactPose) -> np.ndarray:
    """Validate a commanded contact; return the intrusion at the sensing nodes (mm).

    Raises :class:`ContactError` for depths the pad cannot take and for poses off the pad.
    """
    g = mesh.geometry
    max_depth = MAX_DEPTH_FRACTION * g.thickness_mm
    if not 0.0 < pose.depth_mm <= max_depth:
        raise ContactError(
            f"depth_mm={pose.depth_mm} is outside (0, {max_depth:g}] mm: the linear pad model of "
            f"this {g.thickness_mm:g} mm gel is used up to {MAX_DEPTH_FRACTION:.0%} of its "
            f"thickness; command a depth in that range"
        )
    if not g.contains_xy(pose.x_mm, pose.y_mm):
        raise ContactError(
            f"pose (x_mm={pose.x_mm}, y_mm={pose.y_mm}) is off the pad (radius "
            f"{g.half_extent_mm:g} mm around the origin of the sensor frame); move it onto the pad"
        )
    xy = mesh.vertices[mesh.sensing_nodes, :2]
    delta = np.asarray(indenter.intrusion_mm(xy, pose), dtype=np.float64)
    if not np.any(delta > 0):
        raise ContactError(
            f"indenter {indenter.name!r} at (x_mm={pose.x_mm}, y_mm={pose.y_mm}, "
            f"depth_mm={pose.depth_mm}) does not reach any sensing node: its tip is off the pad "
            f"or narrower than the mesh spacing; move it onto the pad or press deeper"
        )
    return delta


def indenter_record(indenter: Indenter) -> dict:
    """Metadata that names ``indenter`` so that the contact can be simulated again: a library
    or analytic name, or a mesh file's absolute path, sha256 and how it was read."""
    rec = {"indenter": indenter.name, "indenter_kind": indenter.kind}
    path = getattr(indenter, "source_path", None)
    if path is not None:
        rec.update({"indenter": path, "indenter_name": indenter.name,
                    "indenter_sha256": indenter.source_sha256,
                    "pressing_face": indenter.pressing_face,
                    "scale_to_mm": indenter.scale_to_mm})
    return rec


#: What ``depth`` is for a resolved contact.
RESOLVED_DEPTH_MEANING = (
    "mm pushed in along -z (>= 0): the resolved surface of the truth mesh (refined to at most "
    "0.27 mm where contact occurs), read at each pixel centre; the indenter does not pass "
    "through it"
)


def simulate_resolved(
    indenter: Indenter,
    pose: ContactPose,
    material: Material = Material(),
    model: str = "neo-hookean",
    camera: DepthCamera | None = None,
    pad: str = "gelslim",
    slide_mm: tuple[float, float] = (0.0, 0.0),
) -> ContactSample:
    """Resolved contact (:class:`tactile_deploy.fem.truth.TruthSolver`) carried onto the frozen
    pad mesh: ``vertices_mm`` are the truth displacements interpolated at its nodes,
    ``depth_mm`` the truth surface rendered on the camera grid, ``pressure_kpa`` and
    ``contact_mask`` the truth contact interpolated at its sensing nodes.

    ``model``: "neo-hookean" (large deformation) or "linear" (its small-strain limit).
    ``slide_mm``: (x, y) mm, sensor frame: after pressing, the indenter moves this far along the
    surface (a tangential load; needs friction "stick" or "coulomb"); recorded in the metadata.
    """
    from tactile_deploy.fem.transfer import Transfer
    from tactile_deploy.fem.truth import TruthSolver

    mesh = load_pad(pad)
    cam = camera or get_camera()
    check_pose(mesh, indenter, pose)
    solver = TruthSolver(mesh.geometry, material, model=model)
    slide = (float(slide_mm[0]), float(slide_mm[1]))
    sol = solver.solve(indenter, pose, slide_mm=slide)
    truth = sol.mesh
    transfer = Transfer(truth.vertices, truth.tets, mesh.vertices)
    u = transfer(sol.displacements_mm)
    vertices = mesh.vertices + u
    surface = Transfer(truth.vertices, truth.tets, mesh.vertices[mesh.sensing_nodes])
    n_truth = truth.n_nodes
    pressure_truth = np.zeros(n_truth)
    pressure_truth[: truth.n_plane] = sol.pressure_kpa()
    pressure = np.maximum(surface(pressure_truth), 0.0)
    stick_truth = np.zeros(n_truth)
    stick_truth[: truth.n_plane] = sol.sticking
    contact_truth = np.zeros(n_truth)
    contact_truth[: truth.n_plane] = sol.in_contact
    in_contact = surface(contact_truth) >= 0.5
    sticking = in_contact & (surface(stick_truth) >= 0.5)
    image = cam.render(truth, sol.vertices_mm)
    mask = cam.render(mesh, mesh.vertices).mask
    depth = np.where(mask, image.depth_mm, 0.0).astype(np.float32)
    intrusion = indenter.intrusion_mm(cam.pixel_centres_mm().reshape(-1, 2), pose)
    floor = np.maximum(intrusion.reshape(depth.shape), 0.0)
    detail = np.where(mask, np.maximum(depth, floor), 0.0).astype(np.float32)
    info = sol.info
    return ContactSample(
        depth_mm=depth,
        depth_detail_mm=detail,
        mask=mask,
        vertices_mm=vertices.astype(np.float32),
        rest_vertices_mm=mesh.vertices.astype(np.float32),
        force_n=sol.force_n,
        contact_mask=in_contact,
        pressure_kpa=pressure.astype(np.float32),
        stick_mask=sticking,
        metadata={
            **indenter_record(indenter),
            "pose": pose.model_dump(),
            "material": material.model_dump(),
            "model": model,
            "solver": "resolved",
            "mesh_hash": mesh.content_hash,
            "n_nodes": mesh.n_nodes,
            "truth_mesh": {"n_nodes": int(truth.n_nodes), "n_tets": int(len(truth.tets)),
                           "fine_spacing_mm": float(info["h_fine_mm"]),
                           "n_constraints": int(info["n_constraints"])},
            "max_penetration_mm": sol.max_penetration_mm,
            "tangential_force_n": [float(v) for v in sol.tangential_force_n],
            **({"slide_mm": list(slide)} if any(slide) else {}),
            "generator_version": GENERATOR_VERSION,
            "units": {
                "depth": "mm", "depth_detail": "mm", "vertices": "mm", "rest_vertices": "mm",
                "force_n": "N", "pressure_kpa": "kPa", "pose.x_mm": "mm", "pose.y_mm": "mm",
                "pose.depth_mm": "mm", "pose.theta_deg": "deg", "material.E_mpa": "MPa",
                "material.nu": "1", "material.mu": "1", "tangential_force_n": "N",
                "max_penetration_mm": "mm", "slide_mm": "mm",
            },
            "depth": RESOLVED_DEPTH_MEANING,
            "depth_detail": DEPTH_DETAIL_MEANING,
            "vertices": "the resolved (truth-mesh) displacement field interpolated at the frozen "
                        "mesh's nodes",
            "contact_mask": "sensing nodes where the resolved surface touches the indenter",
            "stick_mask": "sensing nodes in contact that stick (friction below mu times the "
                          "normal pressure); the others in contact slip",
            "mask": "pixel inside the pad's outline",
            "image": camera_metadata(cam),
            "frame": SENSOR_FRAME,
        },
    )


def simulate_contact(
    indenter: Indenter,
    pose: ContactPose,
    material: Material = Material(),
    camera: DepthCamera | None = None,
    simulator: ContactSimulator | None = None,
) -> ContactSample:
    """Simulate ``indenter`` pressed at ``pose`` into the shipped GelSlim pad."""
    sim = simulator or get_simulator(material)
    cam = camera or get_camera()
    mesh = sim.mesh
    check_pose(mesh, indenter, pose)
    result = sim.solve(indenter, pose)
    image = cam.render(mesh, result.vertices_mm)
    intrusion = indenter.intrusion_mm(cam.pixel_centres_mm().reshape(-1, 2), pose)
    floor = np.maximum(intrusion.reshape(image.depth_mm.shape), 0.0)
    detail = np.where(image.mask, np.maximum(image.depth_mm, floor), 0.0).astype(np.float32)
    return ContactSample(
        depth_mm=image.depth_mm,
        depth_detail_mm=detail,
        mask=image.mask,
        vertices_mm=result.vertices_mm.astype(np.float32),
        rest_vertices_mm=mesh.vertices.astype(np.float32),
        force_n=result.force_n,
        contact_mask=result.contact_mask,
        pressure_kpa=result.pressure_kpa.astype(np.float32),
        stick_mask=result.stick_mask,
        metadata={
            **indenter_record(indenter),
            "pose": pose.model_dump(),
            "material": sim.material.model_dump(),
            "formulation": sim.formulation,
            **({"stick_mask": "sensing nodes in contact that stick (friction below mu times the "
                              "normal force); the others in contact slip"}
               if result.stick_mask is not None else {}),
            "mesh_hash": mesh.content_hash,
            "n_nodes": mesh.n_nodes,
            "generator_version": GENERATOR_VERSION,
            "units": {
                "depth": "mm", "depth_detail": "mm", "vertices": "mm", "rest_vertices": "mm",
                "force_n": "N", "pressure_kpa": "kPa", "pose.x_mm": "mm", "pose.y_mm": "mm",
                "pose.depth_mm": "mm", "pose.theta_deg": "deg", "material.E_mpa": "MPa",
                "material.nu": "1", "material.mu": "1",
            },
            "depth": DEPTH_MEANING,
            "depth_detail": DEPTH_DETAIL_MEANING,
            "mask": "pixel inside the pad's outline",
            "image": camera_metadata(cam),
            "frame": SENSOR_FRAME,
        },
    )
