"""Standard ROS 2 messages of a processed frame, as plain data: no ROS, no serialiser.

Each builder returns a :class:`RosMessage`: the ROS 2 type name and a dict of the message's
fields (nested dicts for nested messages, numpy arrays for arrays; fields left out take their
ROS defaults). :mod:`tactile_deploy.runtime.ros.convert` makes rosbags or rclpy messages of them.

Units and frames follow ROS (REP 103): metres, newtons, pascals, right-handed frames.

* **Sensor frame** ``<sensor_frame>`` (default ``tactile_<sensor>``): origin at the centre of
  the pad's sensing surface, z out of the gel, x and y as in the plugin's camera mapping (the
  project's sensor frame, in metres instead of millimetres).
* **Camera frame** ``<camera_frame>`` (default ``tactile_<sensor>_camera``): the raw camera
  image's frame (its pose relative to the sensor frame is the plugin's camera mapping; no
  transform is published).

Messages of one frame (topics under ``<namespace>``, default ``/tactile/<sensor>``):

========================  ==============================  =====================================
topic                     type                            content
========================  ==============================  =====================================
``image_raw``             sensor_msgs/msg/Image           raw camera frame, ``rgb8``, camera frame
``depth``                 sensor_msgs/msg/Image           depth map, ``32FC1``, metres pushed in
                                                          along -z, 128 x 128 over +-17.5 mm,
                                                          row 0 at the largest y, sensor frame
``mesh/points``           sensor_msgs/msg/PointCloud2     all mesh vertices (point i = vertex i
                                                          of the pad mesh): x, y, z (m),
                                                          displacement_m (magnitude)
``mesh/surface``          visualization_msgs/msg/Marker   TRIANGLE_LIST of the outer surface,
                                                          vertex colours by displacement
``wrench``                geometry_msgs/msg/WrenchStamped force of the object on the pad (N):
                                                          (0, 0, -total normal force); torque 0
``pressure``              sensor_msgs/msg/PointCloud2     sensing nodes: x, y, z (m, deformed),
                                                          pressure_pa (compression > 0)
========================  ==============================  =====================================

Every header is stamped with the frame's capture time (wall clock, UNIX epoch).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: sensor_msgs/PointField datatype of float32.
FLOAT32 = 7
#: visualization_msgs/Marker constants.
MARKER_TRIANGLE_LIST = 11
MARKER_ADD = 0


@dataclass(frozen=True)
class RosMessage:
    """A ROS 2 message as plain data: ``type`` ("sensor_msgs/msg/Image"), ``fields``."""

    type: str
    fields: dict


@dataclass(frozen=True)
class RosNames:
    """Topic namespace and frame ids of one sensor (module docstring)."""

    namespace: str
    sensor_frame: str
    camera_frame: str

    @classmethod
    def for_sensor(cls, sensor: str, namespace: str | None = None,
                   sensor_frame: str | None = None, camera_frame: str | None = None) -> RosNames:
        base = "".join(c if c.isalnum() or c == "_" else "_" for c in sensor)
        return cls(namespace=(namespace or f"/tactile/{base}").rstrip("/"),
                   sensor_frame=sensor_frame or f"tactile_{base}",
                   camera_frame=camera_frame or f"tactile_{base}_camera")

    def topic(self, name: str) -> str:
        return f"{self.namespace}/{name}"


def stamp(t_ns: int) -> dict:
    """builtin_interfaces/Time of a time in ns since the UNIX epoch."""
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def header(t_ns: int, frame_id: str) -> dict:
    return {"stamp": stamp(t_ns), "frame_id": frame_id}


def rgb_image(image: np.ndarray, t_ns: int, frame_id: str) -> RosMessage:
    """sensor_msgs/Image ``rgb8`` of an (H, W, 3) uint8 RGB frame."""
    img = np.ascontiguousarray(image, np.uint8)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"an rgb8 image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
    h, w = img.shape[:2]
    return RosMessage("sensor_msgs/msg/Image", {
        "header": header(t_ns, frame_id), "height": h, "width": w, "encoding": "rgb8",
        "is_bigendian": 0, "step": 3 * w, "data": img.reshape(-1)})


def depth_image(depth_mm: np.ndarray, t_ns: int, frame_id: str) -> RosMessage:
    """sensor_msgs/Image ``32FC1`` in metres of a (H, W) depth map in mm."""
    d = np.ascontiguousarray(np.asarray(depth_mm, np.float32) * np.float32(1e-3), "<f4")
    h, w = d.shape
    return RosMessage("sensor_msgs/msg/Image", {
        "header": header(t_ns, frame_id), "height": h, "width": w, "encoding": "32FC1",
        "is_bigendian": 0, "step": 4 * w, "data": d.view(np.uint8).reshape(-1)})


def point_cloud(points_m: np.ndarray, extra: dict[str, np.ndarray], t_ns: int,
                frame_id: str) -> RosMessage:
    """sensor_msgs/PointCloud2 (one row, dense, little-endian float32 fields x, y, z and the
    ``extra`` per-point fields in their order)."""
    p = np.asarray(points_m, np.float32)
    n = len(p)
    names = ["x", "y", "z", *extra]
    cols = [p[:, 0], p[:, 1], p[:, 2], *(np.asarray(v, np.float32).reshape(n) for v in extra.values())]
    data = np.ascontiguousarray(np.stack(cols, axis=1), "<f4")
    fields = [{"name": nm, "offset": 4 * i, "datatype": FLOAT32, "count": 1}
              for i, nm in enumerate(names)]
    return RosMessage("sensor_msgs/msg/PointCloud2", {
        "header": header(t_ns, frame_id), "height": 1, "width": n, "fields": fields,
        "is_bigendian": False, "point_step": 4 * len(names), "row_step": 4 * len(names) * n,
        "data": data.view(np.uint8).reshape(-1), "is_dense": True})


def mesh_points(vertices_mm: np.ndarray, rest_vertices_mm: np.ndarray, t_ns: int,
                frame_id: str) -> RosMessage:
    """All vertices as a PointCloud2 (point i = vertex i of the pad mesh), with the displacement
    magnitude ``displacement_m``."""
    v = np.asarray(vertices_mm, np.float64)
    disp = np.linalg.norm(v - rest_vertices_mm, axis=1)
    return point_cloud(v * 1e-3, {"displacement_m": disp * 1e-3}, t_ns, frame_id)


def pressure_points(vertices_mm: np.ndarray, sensing_nodes: np.ndarray,
                    pressure_kpa: np.ndarray, t_ns: int, frame_id: str) -> RosMessage:
    """The sensing nodes (deformed positions) with their normal pressure ``pressure_pa``
    (compression > 0); point i = ``sensing_nodes[i]``."""
    v = np.asarray(vertices_mm, np.float64)[np.asarray(sensing_nodes)]
    return point_cloud(v * 1e-3, {"pressure_pa": np.asarray(pressure_kpa, np.float64) * 1e3},
                       t_ns, frame_id)


def surface_marker(vertices_mm: np.ndarray, surface_faces: np.ndarray, colours_rgb: np.ndarray,
                   t_ns: int, frame_id: str, ns: str = "tactile_mesh",
                   marker_id: int = 0) -> RosMessage:
    """visualization_msgs/Marker TRIANGLE_LIST of the outer surface: three points per face
    (metres, outward winding), per-point colours (``colours_rgb`` (n, 3) uint8 per vertex)."""
    faces = np.asarray(surface_faces, np.int64).reshape(-1)
    pts = np.asarray(vertices_mm, np.float64)[faces] * 1e-3
    rgba = np.concatenate([np.asarray(colours_rgb, np.float32)[faces] / 255.0,
                           np.ones((len(faces), 1), np.float32)], axis=1)
    return RosMessage("visualization_msgs/msg/Marker", {
        "header": header(t_ns, frame_id), "ns": ns, "id": int(marker_id),
        "type": MARKER_TRIANGLE_LIST, "action": MARKER_ADD,
        "pose": {"orientation": {"w": 1.0}}, "scale": {"x": 1.0, "y": 1.0, "z": 1.0},
        "color": {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0},
        "points": pts, "colors": rgba})


def wrench(total_normal_force_n: float, t_ns: int, frame_id: str) -> RosMessage:
    """geometry_msgs/WrenchStamped: the object's force on the pad, (0, 0, -F) N in the sensor
    frame (it pushes into the gel, along -z); tangential force and torque are not estimated (0)."""
    return RosMessage("geometry_msgs/msg/WrenchStamped", {
        "header": header(t_ns, frame_id),
        "wrench": {"force": {"x": 0.0, "y": 0.0, "z": -float(total_normal_force_n)},
                   "torque": {"x": 0.0, "y": 0.0, "z": 0.0}}})


#: Topic names (under the namespace) and message types of :func:`frame_messages`.
TOPICS = {
    "image_raw": "sensor_msgs/msg/Image",
    "depth": "sensor_msgs/msg/Image",
    "mesh/points": "sensor_msgs/msg/PointCloud2",
    "mesh/surface": "visualization_msgs/msg/Marker",
    "wrench": "geometry_msgs/msg/WrenchStamped",
    "pressure": "sensor_msgs/msg/PointCloud2",
}


def frame_messages(result, topology, names: RosNames, *, colour_max_mm: float = 1.0,
                   marker: bool = True, image: bool = True) -> list[tuple[str, RosMessage]]:
    """``[(topic, message)]`` of one :class:`~tactile_deploy.runtime.sinks.FrameResult`: the
    raw image (``image``), depth, mesh points, surface marker (``marker``), and, when the
    result has forces, the wrench and (when computed) the pressure."""
    from tactile_deploy.runtime.preview import colourise

    t = int(result.frame.t_wall_ns)
    pred = result.prediction
    out = []
    if image:
        out.append((names.topic("image_raw"), rgb_image(result.frame.image, t, names.camera_frame)))
    if pred.depth_mm is not None:
        out.append((names.topic("depth"), depth_image(pred.depth_mm, t, names.sensor_frame)))
    out.append((names.topic("mesh/points"),
                mesh_points(pred.vertices_mm, topology.rest_vertices_mm, t, names.sensor_frame)))
    if marker:
        mag = np.linalg.norm(np.asarray(pred.vertices_mm, np.float64) - topology.rest_vertices_mm,
                             axis=1)
        out.append((names.topic("mesh/surface"),
                    surface_marker(pred.vertices_mm, topology.surface_faces,
                                   colourise(mag, colour_max_mm), t, names.sensor_frame)))
    if result.total_normal_force_n is not None:
        out.append((names.topic("wrench"), wrench(result.total_normal_force_n, t,
                                                  names.sensor_frame)))
    if result.pressure_kpa is not None:
        out.append((names.topic("pressure"),
                    pressure_points(pred.vertices_mm, topology.sensing_nodes,
                                    result.pressure_kpa, t, names.sensor_frame)))
    return out
