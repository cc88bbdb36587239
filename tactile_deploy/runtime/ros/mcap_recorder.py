"""``tactile-deploy run --mcap FILE``: a ROS 2 recording of the run, written without ROS.

The file is an MCAP file (the default storage of rosbag2 since ROS 2 Iron) holding the standard
messages of :mod:`.messages`, CDR-serialised by rosbags with the ROS 2 Humble definitions
(``ros2msg`` schemas embedded, so readers need no ROS installation): ``ros2 bag play FILE``
publishes them, Foxglove and rosbags read them. Each message's log time and header stamp are the
frame's capture time (ns, UNIX epoch); its publish time is when it was written.

Besides the messages the file carries:

* an attachment ``topology.npz``: the pad mesh (``rest_vertices_mm``, ``tets``,
  ``surface_faces``, ``sensing_nodes``, ``mesh_hash``) that the point clouds index;
* a metadata record ``tactile_deploy``: sensor, mesh hash, topic namespace, frame ids, units.

It is written to a temporary file beside ``FILE`` and renamed when the run ends, so ``FILE`` is
never half-written. The visualization_msgs/Marker of the surface (three points per face, ~15,000
points, each a message object for the serialiser) takes 50-200 ms to build and serialise on one
CPU core, so it is recorded at most ``marker_hz`` times per second of the sensor's time (the
frame's time in its recording, or its capture time for a camera; default 5; ``inf``: every
frame; 0: never); the point cloud of all vertices is in every frame.
"""

from __future__ import annotations

import io
import json
import os
import time
from pathlib import Path

import numpy as np

from tactile_deploy.runtime.ros.messages import TOPICS, RosNames, frame_messages
from tactile_deploy.runtime.sinks import BackgroundSink

#: Compression of the MCAP chunks (zstd: what rosbag2 writes; lz4 is faster, larger).
COMPRESSION = "zstd"


class McapRecorder(BackgroundSink):
    """Record every processed frame into an MCAP file (module docstring).

    path : the .mcap file (replaced atomically at the end).
    topology : :class:`~tactile_deploy.runtime.predictor.MeshTopology` of the model.
    names : topic namespace and frame ids (default ``RosNames.for_sensor(sensor)``).
    """

    name = "MCAP recorder"
    wants_pressure = True

    def __init__(self, path: str | os.PathLike, sensor: str, topology,
                 names: RosNames | None = None, colour_max_mm: float = 1.0,
                 marker_hz: float = 5.0, image: bool = True, queue_size: int = 8):
        super().__init__(queue_size)
        self.path = Path(path)
        self.sensor = sensor
        self.topology = topology
        self.names = names or RosNames.for_sensor(sensor)
        self.colour_max_mm = float(colour_max_mm)
        self.marker_period_ns = int(1e9 / marker_hz) if marker_hz > 0 else None
        self.image = bool(image)
        self.messages = 0
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.partial")
        self._last_marker_ns: int | None = None

    def start(self, live: bool) -> None:
        self._live = live
        super().start(live)

    # ------------------------------------------------------------------ worker thread
    def setup(self) -> None:
        from mcap.writer import CompressionType, Writer

        from tactile_deploy.runtime.ros.convert import ROS_DISTRO, RosbagsCodec

        self.codec = RosbagsCodec()
        self._file = open(self._tmp, "wb")
        self._writer = Writer(self._file, compression=CompressionType[COMPRESSION.upper()])
        self._writer.start(profile="ros2", library="tactile-deploy")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        t = self.topology
        buf = io.BytesIO()
        np.savez(buf, rest_vertices_mm=np.asarray(t.rest_vertices_mm, np.float32),
                 tets=np.asarray(t.tets, np.int32), surface_faces=np.asarray(t.surface_faces, np.int32),
                 sensing_nodes=np.asarray(t.sensing_nodes, np.int32), mesh_hash=np.array(t.mesh_hash))
        now = time.time_ns()
        self._writer.add_attachment(create_time=now, log_time=now, name="topology.npz",
                                    media_type="application/x-npz", data=buf.getvalue())
        self._writer.add_metadata("tactile_deploy", {
            "sensor": self.sensor, "mesh_hash": t.mesh_hash, "namespace": self.names.namespace,
            "sensor_frame": self.names.sensor_frame, "camera_frame": self.names.camera_frame,
            "ros_distro_definitions": ROS_DISTRO,
            "units": "metres, newtons, pascals (ROS); depth: metres pushed in along -z",
            "topics": json.dumps({self.names.topic(k): v for k, v in TOPICS.items()})})

    def _channel(self, topic: str, type_name: str) -> int:
        if topic not in self._channels:
            if type_name not in self._schemas:
                self._schemas[type_name] = self._writer.register_schema(
                    name=type_name, encoding="ros2msg",
                    data=self.codec.msgdef(type_name).encode())
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=self._schemas[type_name])
            self._seq[topic] = 0
        return self._channels[topic]

    def handle(self, result) -> None:
        t = int(result.frame.t_wall_ns)
        clock = t if result.frame.t_source_ns is None else int(result.frame.t_source_ns)
        last = self._last_marker_ns
        marker = self.marker_period_ns is not None and (
            last is None or clock < last or clock - last >= self.marker_period_ns)  # < : a loop
        if marker:
            self._last_marker_ns = clock
        for topic, msg in frame_messages(result, self.topology, self.names,
                                         colour_max_mm=self.colour_max_mm, marker=marker,
                                         image=self.image):
            channel = self._channel(topic, msg.type)
            self._writer.add_message(channel_id=channel, log_time=t, publish_time=time.time_ns(),
                                     sequence=self._seq[topic], data=self.codec.serialize(msg))
            self._seq[topic] += 1
            self.messages += 1

    def teardown(self) -> None:
        if getattr(self, "_writer", None) is None:
            return
        self._writer.finish()
        self._file.close()
        os.replace(self._tmp, self.path)

    def close(self, timeout_s: float = 120.0) -> None:
        super().close(timeout_s)
        if self._tmp.exists():          # failed before the rename: leave no partial file
            self._tmp.unlink()

    def report(self) -> dict:
        return {**super().report(), "file": str(self.path), "messages": self.messages}
