"""Stream predicted meshes to other processes over ZeroMQ (PUB/SUB).

``MeshPublisher(address)`` binds a PUB socket; any number of SUB sockets connect to it. The
address (:func:`bind_address`): a port (``5555``), ``tcp://:5555`` or ``tcp://localhost:5555``
bind to the loopback interface, 127.0.0.1, so only programs on this computer receive the meshes;
``tcp://*:5555`` (every interface) or ``tcp://192.168.1.20:5555`` (one interface) publish to the
network, as named; ``ipc:///tmp/tactile.sock`` is a local socket file. Nothing is encrypted or
authenticated: whoever reaches the address receives the stream. Slow subscribers lose
messages rather than slow the sensor down (send high-water mark ``hwm`` messages, never blocks).

Message format, version 1. Every message is a ZeroMQ multipart message::

    part 0  topic   b"mesh/<sensor>" or b"topology/<sensor>" (subscribe to a prefix)
    part 1  header  UTF-8 JSON object, see below
    part 2+ arrays  raw little-endian C-order bytes, one part per entry of header["parts"]

Mesh header (topic ``mesh/<sensor>``, one per processed frame)::

    {"format": "tactile-deploy.mesh", "version": 1, "sensor": "gelslim2",
     "seq": 17,                      # message counter of this publisher, from 0
     "frame_index": 17,              # index of the camera frame in its stream
     "t_capture_ns": 1732241234...,  # capture time, ns since the UNIX epoch (wall clock)
     "t_publish_ns": 1732241234...,  # when the message was sent, same clock
     "latency_ms": 3.1,              # capture -> mesh on the sender's monotonic clock
     "mesh_hash": "5d0a...",         # pad mesh content hash (topology identity)
     "units": "mm", "frame": "sensor: origin at the centre of the sensing surface, z out of the gel",
     "ood_score": 0.4, "in_distribution": true,
     "total_normal_force_n": 1.25,   # present when forces are computed (N, compression > 0)
     "parts": [{"name": "vertices_mm", "dtype": "<f4", "shape": [5380, 3]},
               {"name": "pressure_kpa", "dtype": "<f4", "shape": [1076]}]}   # pressure: optional

Topology header (topic ``topology/<sensor>``, sent at start and every ``topology_every_s`` so
late subscribers get it): ``{"format": "tactile-deploy.topology", "version": 1, "sensor",
"mesh_hash", "parts": [rest_vertices_mm <f4 (n, 3), tets <i4 (m, 4), surface_faces <i4 (f, 3),
sensing_nodes <i4 (k,)]}``. ``pressure_kpa`` entries follow the order of ``sensing_nodes``.

:class:`MeshSubscriber` decodes both for Python programs; other languages read the JSON and
reinterpret the bytes (see ``examples/`` and docs/runtime.md).
"""

from __future__ import annotations

import json
import time

import numpy as np

FORMAT_MESH = "tactile-deploy.mesh"
FORMAT_TOPOLOGY = "tactile-deploy.topology"
VERSION = 1
SENSOR_FRAME = "sensor: origin at the centre of the sensing surface, z out of the gel"
#: Longest wait at close for queued messages to reach connected subscribers, ms.
FLUSH_TIMEOUT_MS = 2000


class PublishError(RuntimeError):
    """The publisher cannot bind its address (the message says which and what to do)."""


def bind_address(address: str) -> str:
    """The ZeroMQ address to bind for ``--publish ADDRESS``: loopback unless the address names
    another interface (module docstring); checked by :func:`check_address`."""
    a = address.strip()
    if a.isdigit():
        a = f"tcp://127.0.0.1:{a}"
    elif a.startswith("tcp://:"):
        a = "tcp://127.0.0.1:" + a[len("tcp://:"):]
    elif a.startswith("tcp://localhost:"):
        a = "tcp://127.0.0.1:" + a[len("tcp://localhost:"):]
    check_address(a)
    return a


def check_address(address: str) -> None:
    """Refuse a ``tcp://`` address whose port is not 1-65535 or ``*`` (any free port), before any
    socket is made: ZeroMQ would bind another port (65536 + n binds n) without a word."""
    if not address.startswith("tcp://"):
        return
    host, sep, port = address[len("tcp://"):].rpartition(":")
    if not sep or not host:
        raise PublishError(f"cannot publish on {address!r}: a tcp address needs a host and a port, "
                           "e.g. tcp://*:5555 or tcp://127.0.0.1:5555")
    if port != "*" and not (port.isascii() and port.isdigit() and 1 <= int(port) <= 65535):
        raise PublishError(f"cannot publish on {address!r}: the port must be 1-65535, or * for any "
                           f"free port, got {port!r}; e.g. tcp://*:5555")


def _part(name: str, arr: np.ndarray, dtype: str) -> tuple[dict, bytes]:
    a = np.ascontiguousarray(arr, dtype=np.dtype(dtype))
    return {"name": name, "dtype": dtype, "shape": list(a.shape)}, a.tobytes()


class MeshPublisher:
    """ZeroMQ PUB socket sending mesh and topology messages (module docstring)."""

    def __init__(self, address: str, sensor: str, topology, hwm: int = 4,
                 topology_every_s: float = 2.0, context=None):
        import zmq

        address = bind_address(address)
        self.address = address
        self.sensor = sensor
        self.topology = topology
        self.topology_every_s = float(topology_every_s)
        self._ctx = context or zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.PUB)
        self._sock.setsockopt(zmq.SNDHWM, int(hwm))
        self._sock.setsockopt(zmq.LINGER, 0)
        try:
            self._sock.bind(address)
        except zmq.ZMQError as e:
            self._sock.close()
            raise PublishError(
                f"cannot publish on {address!r}: {e} (is another process using that port? "
                "addresses look like tcp://*:5555, tcp://127.0.0.1:5555 or "
                "ipc:///tmp/tactile.sock)") from None
        self.endpoint = self._sock.getsockopt(zmq.LAST_ENDPOINT).decode()
        self._zmq = zmq
        self.seq = 0
        self._last_topology = -1e18
        self._topic_mesh = f"mesh/{sensor}".encode()
        self._topic_topo = f"topology/{sensor}".encode()

    def send_topology(self) -> None:
        t = self.topology
        parts = [_part("rest_vertices_mm", t.rest_vertices_mm, "<f4"),
                 _part("tets", t.tets, "<i4"), _part("surface_faces", t.surface_faces, "<i4"),
                 _part("sensing_nodes", t.sensing_nodes, "<i4")]
        header = {"format": FORMAT_TOPOLOGY, "version": VERSION, "sensor": self.sensor,
                  "mesh_hash": t.mesh_hash, "units": "mm", "frame": SENSOR_FRAME,
                  "parts": [p[0] for p in parts]}
        self._send([self._topic_topo, json.dumps(header).encode(), *(p[1] for p in parts)])
        self._last_topology = time.monotonic()

    def publish(self, vertices_mm: np.ndarray, *, frame_index: int, t_capture_ns: int,
                latency_ms: float, ood_score: float, in_distribution: bool,
                total_normal_force_n: float | None = None,
                pressure_kpa: np.ndarray | None = None) -> None:
        """Send one mesh (n, 3) mm with its timestamps (and forces when given)."""
        if time.monotonic() - self._last_topology >= self.topology_every_s:
            self.send_topology()
        parts = [_part("vertices_mm", vertices_mm, "<f4")]
        if pressure_kpa is not None:
            parts.append(_part("pressure_kpa", pressure_kpa, "<f4"))
        header = {"format": FORMAT_MESH, "version": VERSION, "sensor": self.sensor,
                  "seq": self.seq, "frame_index": int(frame_index),
                  "t_capture_ns": int(t_capture_ns), "t_publish_ns": time.time_ns(),
                  "latency_ms": round(float(latency_ms), 4), "mesh_hash": self.topology.mesh_hash,
                  "units": "mm", "frame": SENSOR_FRAME, "ood_score": float(ood_score),
                  "in_distribution": bool(in_distribution),
                  "parts": [p[0] for p in parts]}
        if total_normal_force_n is not None:
            header["total_normal_force_n"] = float(total_normal_force_n)
        self._send([self._topic_mesh, json.dumps(header).encode(), *(p[1] for p in parts)])
        self.seq += 1

    def _send(self, frames: list[bytes]) -> None:
        # a PUB socket never blocks: past the high-water mark of a subscriber, ZeroMQ drops the
        # message for that subscriber silently
        self._sock.send_multipart(frames, flags=self._zmq.NOBLOCK, copy=False)

    def close(self, flush_timeout_ms: int = FLUSH_TIMEOUT_MS) -> None:
        """Close the socket once the messages already queued for connected subscribers are
        sent, waiting at most ``flush_timeout_ms`` (a subscriber that stopped reading cannot hold
        the process); the last meshes of a run are not dropped at its end."""
        if self._sock is not None:
            self._sock.close(linger=int(flush_timeout_ms))
            self._sock = None

    def __enter__(self) -> MeshPublisher:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def decode(frames: list[bytes]) -> tuple[str, dict, dict[str, np.ndarray]]:
    """``(topic, header, arrays by name)`` of one received multipart message."""
    if len(frames) < 2:
        raise ValueError(f"expected at least 2 message parts (topic, header), got {len(frames)}")
    topic = bytes(frames[0]).decode()
    header = json.loads(bytes(frames[1]).decode())
    specs = header.get("parts", [])
    if len(specs) != len(frames) - 2:
        raise ValueError(f"header lists {len(specs)} array parts, message has {len(frames) - 2}")
    arrays = {s["name"]: np.frombuffer(bytes(b), dtype=np.dtype(s["dtype"])).reshape(s["shape"])
              for s, b in zip(specs, frames[2:])}
    return topic, header, arrays


class MeshSubscriber:
    """SUB socket for :class:`MeshPublisher` messages (``sensor=None``: every sensor)."""

    def __init__(self, address: str, sensor: str | None = None, context=None):
        import zmq

        self._zmq = zmq
        self._ctx = context or zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.SUB)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.connect(address)
        self.sensor = sensor
        for prefix in ("mesh/", "topology/"):
            self._sock.setsockopt(zmq.SUBSCRIBE, (prefix + (sensor or "")).encode())

    def recv(self, timeout_ms: int = 1000):
        """The next message as :func:`decode` returns it, or None after ``timeout_ms``."""
        deadline = time.monotonic() + timeout_ms / 1e3
        while True:
            left = max(int(1e3 * (deadline - time.monotonic())), 0)
            if not self._sock.poll(left):
                return None
            msg = decode(self._sock.recv_multipart())
            # topic prefixes also match longer names (gelslim1 -> gelslim10): compare exactly
            if self.sensor is None or msg[0].split("/", 1)[1] == self.sensor:
                return msg

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> MeshSubscriber:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
