"""``tactile-deploy run --view live``: a live 3-D view of the run in a web browser, by rerun.

Why rerun (rerun-sdk) rather than the Foxglove SDK: rerun's wheel carries its web viewer and
serves it itself, so the view works on a machine with no network (a robot's computer, a lab
behind a firewall, this project's CI) and is tested end to end in a headless browser; the
Foxglove SDK streams data to the Foxglove app, which is loaded from foxglove.dev or installed as
a desktop program. The price is size: rerun-sdk 0.41 is a 170 MB wheel (517 MB installed, 293 MB
of it a native viewer this view does not use, plus pyarrow), hence the optional extra ``[view]``.

What the page shows (layout fixed by a blueprint): the deformed mesh in 3-D (outer surface,
sensor frame, mm, vertex colours by displacement magnitude on the run's colour scale, viridis,
with an arrow for the total normal force at the pressed region), the raw camera frame, the depth
map (mm, 0 to the colour scale) and the total normal force over time (N).

Two servers, both started in the run's process and stopped with it:

* the data (rerun's gRPC server) on ``127.0.0.1`` and a free port: only programs on this
  computer can read the stream unless ``bind`` names another interface;
* the viewer page (HTML + WebAssembly, no data) on ``web_port`` (default 9090). rerun offers no
  choice of interface for it: it listens on all interfaces; the page a remote browser loads
  connects to the data address in its URL, which is this computer's loopback.

To watch from another computer, forward both ports over ssh rather than binding them to a
network. When the browser has internet access, rerun's page sends rerun's anonymous usage events
and checks for updates (rerun's own behaviour, not configurable from here); without a network it
works the same (the test runs offline).

The view shows at most ``max_hz`` frames a second (by capture time): it is for people, and a
640 x 480 frame is ~1 MB per message. The data server keeps the latest ``memory_limit`` of data
for browsers that connect later.
"""

from __future__ import annotations

import logging
import socket
import urllib.parse

import numpy as np

from tactile_deploy.runtime.sinks import BackgroundSink

log = logging.getLogger(__name__)

#: rerun application id (the recording's name in the viewer).
APPLICATION_ID = "tactile-deploy"
#: Force arrow length per newton, mm.
ARROW_MM_PER_N = 4.0


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class LiveView(BackgroundSink):
    """Serve the run to a browser (module docstring).

    topology : :class:`~tactile_deploy.runtime.predictor.MeshTopology` of the model.
    web_port : port of the viewer page (0: any free one). bind : interface of the data server.
    """

    name = "live view"

    def __init__(self, sensor: str, topology, web_port: int = 9090, bind: str = "127.0.0.1",
                 grpc_port: int | None = None, colour_max_mm: float = 1.0, max_hz: float = 15.0,
                 memory_limit: str = "256MiB"):
        super().__init__(queue_size=2)
        self.sensor = sensor
        self.topology = topology
        self.bind = bind
        self.web_port = int(web_port) or free_port()
        self.grpc_port = int(grpc_port) if grpc_port else free_port(bind)
        self.colour_max_mm = float(colour_max_mm)
        self.period_ns = int(1e9 / max_hz) if max_hz > 0 else 0
        self.memory_limit = memory_limit
        self._last_ns: int | None = None
        self.shown = 0
        self.url: str | None = None

    def serve(self) -> str:
        """Start both servers (in the calling thread: errors such as a taken port surface at
        once); returns the page's URL."""
        import rerun as rr

        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"{self.sensor}")
        sink = rr.GrpcServerSink(bind_ip=self.bind, port=self.grpc_port,
                                 server_memory_limit=self.memory_limit)
        self.rec.set_sinks(sink)
        self.rec.send_blueprint(self.blueprint())
        self._log_static()
        rr.serve_web_viewer(web_port=self.web_port, open_browser=False, connect_to=sink.uri)
        host = "localhost" if self.bind in ("127.0.0.1", "0.0.0.0") else self.bind
        # the page connects to the data server named in its URL; hide rerun's welcome screen
        self.url = (f"http://{host}:{self.web_port}/?hide_welcome_screen&url="
                    + urllib.parse.quote(sink.uri, safe=""))
        return self.url

    def blueprint(self):
        import rerun.blueprint as rrb

        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial3DView(origin="/mesh", name=f"{self.sensor} mesh (mm)"),
                rrb.Vertical(
                    rrb.Spatial2DView(origin="/camera", name="camera frame"),
                    rrb.Spatial2DView(origin="/depth", name="depth (mm)"),
                    rrb.TimeSeriesView(origin="/force", name="total normal force (N)"),
                ),
                column_shares=[2, 1],
            ),
            rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
            rrb.TimePanel(state="collapsed"), auto_views=False)

    def _log_static(self) -> None:
        import rerun as rr

        t = self.topology
        self.rec.log("mesh/surface", rr.Mesh3D.from_fields(
            triangle_indices=np.asarray(t.surface_faces, np.uint32)), static=True)
        self.rec.log("force/total_normal_n", rr.SeriesLines(names="total normal force (N)"),
                     static=True)

    # ------------------------------------------------------------------ worker thread
    def consume(self, result) -> None:
        t = int(result.frame.t_wall_ns)
        if self._last_ns is not None and t - self._last_ns < self.period_ns:
            self._skipped = result                  # more than max_hz: not shown, not a drop
            return
        self._last_ns = t
        self._skipped = None
        super().consume(result)

    def close(self, timeout_s: float = 120.0) -> None:
        if getattr(self, "_skipped", None) is not None:   # the view ends on the last frame
            super().consume(self._skipped)
            self._skipped = None
        super().close(timeout_s)

    def handle(self, result) -> None:
        import rerun as rr

        from tactile_deploy.runtime.preview import colourise

        pred = result.prediction
        rec = self.rec
        rec.set_time("frame", sequence=int(result.frame.index))
        rec.set_time("capture_time", timestamp=int(result.frame.t_wall_ns) * 1e-9)
        v = np.asarray(pred.vertices_mm, np.float32)
        mag = np.linalg.norm(v - self.topology.rest_vertices_mm, axis=1)
        rec.log("mesh/surface", rr.Mesh3D.from_fields(
            vertex_positions=v, vertex_colors=colourise(mag, self.colour_max_mm)))
        rec.log("camera/frame", rr.Image(np.asarray(result.frame.image), color_model="RGB"))
        if pred.depth_mm is not None:
            rec.log("depth/map", rr.DepthImage(np.asarray(pred.depth_mm, np.float32), meter=1000.0,
                                               colormap="inferno",
                                               depth_range=(0.0, self.colour_max_mm)))
        force = result.total_normal_force_n
        if force is not None:
            rec.log("force/total_normal_n", rr.Scalars(force))
            nodes = self.topology.sensing_nodes
            uz = np.maximum(self.topology.rest_vertices_mm[nodes, 2] - v[nodes, 2], 0.0)
            if uz.sum() > 0:
                centre = (v[nodes] * uz[:, None]).sum(0) / uz.sum()
                length = ARROW_MM_PER_N * force
                rec.log("mesh/force", rr.Arrows3D(origins=[centre + [0, 0, length]],
                                                  vectors=[[0, 0, -length]],
                                                  colors=[[230, 60, 40]], radii=0.25))
        self.shown += 1

    def teardown(self) -> None:
        rec = getattr(self, "rec", None)
        if rec is not None:
            rec.flush()

    def report(self) -> dict:
        return {**super().report(), "url": self.url, "shown": self.shown}
