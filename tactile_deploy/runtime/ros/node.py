"""A ROS 2 node (rclpy) that runs a sensor and publishes its meshes live.

It publishes the messages of :mod:`tactile_deploy.runtime.ros.messages` (the same builders as
``run --mcap``) on ``<namespace>/image_raw``, ``depth``, ``mesh/points``, ``mesh/surface``,
``wrench`` and ``pressure``. Start it in an environment where ROS 2 (Humble or newer) is sourced
and tactile-deploy is installed::

    python3 -m tactile_deploy.runtime.ros.node --ros-args -p sensor:=gelslim2 -p source:=0

Parameters (``--ros-args -p NAME:=VALUE``): ``sensor`` (plugin name or folder, default
gelslim2), ``source`` (as ``run --source``; empty: the plugin's default), ``namespace`` (default
``/tactile/<sensor>``), ``sensor_frame``, ``camera_frame`` (frame ids), ``forces`` (default
true), ``marker_hz`` (surface markers per second at most, default 5; 0: none), ``image`` (publish the
raw frame, default true), ``threads`` (onnxruntime threads), ``loop`` (replay a recording).

The node's work is in :class:`RosPublisherSink` and :func:`node_settings`, which need no rclpy:
they take the publisher factory and the message classes as arguments (tests pass stand-ins).
Topics use a reliable QoS of depth 5 (a slow subscriber delays messages, the sensor loop never
waits: the sink drops frames when its queue is full, counted and logged).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from tactile_deploy.runtime.ros.convert import fill_rclpy
from tactile_deploy.runtime.ros.messages import TOPICS, RosNames, frame_messages
from tactile_deploy.runtime.sinks import BackgroundSink

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NodeSettings:
    """The node's parameters, checked (module docstring)."""

    sensor: str = "gelslim2"
    source: str = ""
    namespace: str = ""
    sensor_frame: str = ""
    camera_frame: str = ""
    forces: bool = True
    marker_hz: float = 5.0
    image: bool = True
    threads: int = 1
    loop: bool = False


def node_settings(parameters: dict) -> NodeSettings:
    """:class:`NodeSettings` of a ``{name: value}`` mapping of ROS parameters; unknown names and
    wrong types raise ValueError naming the parameter, the expected type and the value."""
    defaults = NodeSettings()
    values = {}
    for name, value in parameters.items():
        if not hasattr(defaults, name):
            raise ValueError(f"unknown parameter {name!r}; the node takes "
                             f"{', '.join(NodeSettings.__dataclass_fields__)}")
        want = type(getattr(defaults, name))
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, want) or (want is int and isinstance(value, bool)):
            raise ValueError(f"parameter {name!r} must be a {want.__name__}, got {value!r}")
        values[name] = value
    s = NodeSettings(**values)
    if s.marker_hz < 0 or s.threads < 1:
        raise ValueError(f"parameters marker_hz >= 0 and threads >= 1, got {s.marker_hz}, "
                         f"{s.threads}")
    return s


class RosPublisherSink(BackgroundSink):
    """Publish every processed frame as ROS 2 messages (a frame sink of the run loop).

    make_publisher : ``(topic, type_name) -> publisher`` with ``publish(msg)``.
    get_message : ``type_name -> message class`` (rclpy: ``rosidl_runtime_py.utilities.get_message``).
    """

    name = "ROS 2 publisher"
    wants_pressure = True

    def __init__(self, make_publisher, get_message, topology, names: RosNames,
                 colour_max_mm: float = 1.0, marker_hz: float = 5.0, image: bool = True,
                 queue_size: int = 2):
        super().__init__(queue_size)
        self.topology = topology
        self.names = names
        self.colour_max_mm = float(colour_max_mm)
        self.marker_period_ns = int(1e9 / marker_hz) if marker_hz > 0 else None
        self.image = bool(image)
        self.get_message = get_message
        self.publishers = {names.topic(t): make_publisher(names.topic(t), typ)
                           for t, typ in TOPICS.items() if image or t != "image_raw"}
        self.published = 0
        self._last_marker_ns: int | None = None

    def handle(self, result) -> None:
        t = int(result.frame.t_wall_ns)
        marker = self.marker_period_ns is not None and (
            self._last_marker_ns is None or t - self._last_marker_ns >= self.marker_period_ns)
        if marker:
            self._last_marker_ns = t
        for topic, msg in frame_messages(result, self.topology, self.names,
                                         colour_max_mm=self.colour_max_mm, marker=marker,
                                         image=self.image):
            ros_msg = fill_rclpy(self.get_message(msg.type)(), msg.fields, self.get_message)
            self.publishers[topic].publish(ros_msg)
            self.published += 1


def main(args=None) -> None:  # pragma: no cover - needs a ROS 2 installation
    """Entry point: ``python3 -m tactile_deploy.runtime.ros.node --ros-args -p sensor:=...``."""
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosidl_runtime_py.utilities import get_message

    from tactile_deploy.runtime.forces import ForceEstimator
    from tactile_deploy.runtime.plugins import SensorPlugin
    from tactile_deploy.runtime.predictor import MeshPredictor
    from tactile_deploy.runtime.run import Runner, RunOptions
    from tactile_deploy.runtime.sources.config import parse_source
    from tactile_deploy.runtime.sources.factory import make_source

    rclpy.init(args=args)
    node = Node("tactile_deploy")
    defaults = NodeSettings()
    for name in NodeSettings.__dataclass_fields__:
        node.declare_parameter(name, getattr(defaults, name))
    settings = node_settings({n: node.get_parameter(n).value
                              for n in NodeSettings.__dataclass_fields__})
    plugin = SensorPlugin.load(settings.sensor)
    predictor = MeshPredictor.from_plugin(plugin, threads=settings.threads)
    config = (parse_source(settings.source, loop=settings.loop) if settings.source
              else plugin.manifest.default_source)
    source = make_source(config, plugin, from_manifest=not settings.source)
    names = RosNames.for_sensor(plugin.name, settings.namespace or None,
                                settings.sensor_frame or None, settings.camera_frame or None)
    qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    sink = RosPublisherSink(lambda topic, typ: node.create_publisher(get_message(typ), topic, qos),
                            get_message, predictor.topology, names,
                            marker_hz=settings.marker_hz, image=settings.image)
    forces = ForceEstimator.for_plugin(plugin) if settings.forces else None
    runner = Runner(predictor, source, RunOptions(), forces=forces, sinks=[sink],
                    sensor=plugin.name)
    node.get_logger().info(f"{plugin.name} on {source.name}: publishing under {names.namespace}")
    worker = threading.Thread(target=runner.run, name="tactile-deploy run", daemon=True)
    worker.start()
    try:
        while rclpy.ok() and worker.is_alive():
            rclpy.spin_once(node, timeout_sec=0.2)
    except KeyboardInterrupt:
        pass
    finally:
        runner.stop()
        worker.join(timeout=15.0)
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":  # pragma: no cover
    main()
