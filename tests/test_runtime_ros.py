"""ROS 2 output: ``run --mcap FILE`` read back by independent readers (rosbags, which parses the
message definitions embedded in the file, and mcap-ros2-support, a second CDR decoder), field by
field against the run's own prediction; and the ROS 2 node's logic with a stand-in for rclpy."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_runtime_support import build_test_plugin
from typer.testing import CliRunner

from tactile_deploy.cli.main import app
from tactile_deploy.runtime.predictor import MeshPredictor
from tactile_deploy.runtime.sources.npz import load_clip

runner = CliRunner()


@pytest.fixture(scope="module")
def plugin(tmp_path_factory):
    return build_test_plugin(tmp_path_factory.mktemp("plugins") / "testsensor", n_frames=4)


@pytest.fixture(scope="module")
def predictor(plugin):
    return MeshPredictor.from_plugin(plugin)


@pytest.fixture(scope="module")
def recording(plugin, predictor, tmp_path_factory):
    """A run over the plugin's demo clip (4 frames) recorded into MCAP, with forces from an
    identity surface stiffness (force on node i = -u_z,i N/mm: checkable by hand), and its
    meshes as .npz and frames.csv."""
    from tactile_deploy.runtime.forces import ForceEstimator, SurfaceStiffness
    from tactile_deploy.runtime.ros.mcap_recorder import McapRecorder
    from tactile_deploy.runtime.run import Runner, RunOptions, prepare_out_dir
    from tactile_deploy.runtime.sources.base import ArrayPlayback

    tmp = tmp_path_factory.mktemp("mcap")
    topo = predictor.topology
    n = len(topo.sensing_nodes)
    forces = ForceEstimator(SurfaceStiffness(topo.sensing_nodes, np.eye(n), "identity"), 1.0,
                            topo.rest_vertices_mm, np.ones(n))
    frames, t, _ = load_clip(plugin.demo_clip_path())
    bag = tmp / "run.mcap"
    out = prepare_out_dir(tmp / "out")
    summary = Runner(predictor, ArrayPlayback(list(frames), t, "clip"),
                     RunOptions(out_dir=out, formats=("npz",)), forces=forces,
                     sinks=[McapRecorder(bag, "testsensor", topo, marker_hz=float("inf"))]).run()
    report = summary.sinks["MCAP recorder"]
    assert report["handled"] == 4 and not report["dropped"] and report["error"] is None
    assert not list(tmp.glob(".*partial*"))
    return bag, out


def _read_rosbags(bag: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader

    got: dict[str, list] = {}
    with AnyReader([bag]) as reader:
        for conn, t, raw in reader.messages():
            got.setdefault(conn.topic, []).append((conn.msgtype, t, reader.deserialize(raw, conn.msgtype)))
    return got


def test_mcap_recording_reads_back_with_rosbags(plugin, predictor, recording):
    bag, out = recording
    got = _read_rosbags(bag)
    ns = "/tactile/testsensor"
    assert set(got) == {f"{ns}/{t}" for t in ("image_raw", "depth", "mesh/points", "mesh/surface",
                                               "wrench", "pressure")}
    assert all(len(v) == 4 for v in got.values())
    frames, _, _ = load_clip(plugin.demo_clip_path())
    topo = predictor.topology
    rows = (out / "frames.csv").read_text().splitlines()
    header = rows[0].split(",")
    t_capture = [int(r.split(",")[header.index("t_capture_ns")]) for r in rows[1:]]
    for i in range(4):
        expected = predictor.predict_frame(frames[i])
        with np.load(out / f"mesh_{i:06d}.npz") as z:
            meta = json.loads(str(z["metadata"]))
            assert np.allclose(z["vertices"], expected.vertices_mm, atol=1e-5)
        stamp_ns = t_capture[i]
        # raw frame: rgb8, camera frame, stamped with the capture time, bit-exact pixels
        typ, t, img = got[f"{ns}/image_raw"][i]
        assert typ == "sensor_msgs/msg/Image" and t == stamp_ns
        assert img.header.stamp.sec * 10**9 + img.header.stamp.nanosec == stamp_ns
        assert img.header.frame_id == "tactile_testsensor_camera"
        assert (img.encoding, img.height, img.width, img.step) == ("rgb8", 480, 640, 1920)
        assert np.array_equal(np.asarray(img.data).reshape(480, 640, 3), frames[i])
        # depth map: 32FC1 in metres, sensor frame
        _, _, dep = got[f"{ns}/depth"][i]
        assert dep.encoding == "32FC1" and dep.header.frame_id == "tactile_testsensor"
        d = np.frombuffer(np.asarray(dep.data).tobytes(), "<f4").reshape(dep.height, dep.width)
        assert np.allclose(d, expected.depth_mm * 1e-3, atol=1e-9) and d.max() > 5e-5
        # all vertices, in pad mesh order, metres
        _, _, pc = got[f"{ns}/mesh/points"][i]
        names = [f.name for f in pc.fields]
        assert names == ["x", "y", "z", "displacement_m"] and pc.width == 5380 and pc.height == 1
        assert all(f.datatype == 7 and f.count == 1 for f in pc.fields)      # FLOAT32
        pts = np.frombuffer(np.asarray(pc.data).tobytes(), "<f4").reshape(-1, pc.point_step // 4)
        assert np.allclose(pts[:, :3] * 1e3, expected.vertices_mm, atol=1e-4)
        assert np.allclose(pts[:, 3] * 1e3, np.linalg.norm(expected.displacement_mm, axis=1),
                           atol=1e-4)
        # surface: TRIANGLE_LIST, three points per outer face, outward winding kept
        _, _, mk = got[f"{ns}/mesh/surface"][i]
        assert mk.type == 11 and mk.action == 0 and len(mk.points) == 3 * len(topo.surface_faces)
        tri = np.array([[p.x, p.y, p.z] for p in mk.points]).reshape(-1, 3, 3) * 1e3
        assert np.allclose(tri, expected.vertices_mm[topo.surface_faces], atol=1e-6)
        assert len(mk.colors) == len(mk.points) and all(0 <= c.r <= 1 for c in mk.colors[:50])
        # force: the object pushes into the gel (-z of the sensor frame)
        _, _, wr = got[f"{ns}/wrench"][i]
        assert wr.header.frame_id == "tactile_testsensor"
        assert np.isclose(-wr.wrench.force.z, meta["total_normal_force_n"], rtol=1e-6)
        assert meta["total_normal_force_n"] > 0
        assert wr.wrench.force.x == wr.wrench.force.y == 0.0
        uz = (expected.vertices_mm - topo.rest_vertices_mm)[topo.sensing_nodes, 2]
        assert np.isclose(-wr.wrench.force.z, -uz.sum(), rtol=1e-4)     # identity stiffness
        # per-node pressure on the sensing nodes: -u_z N/mm over 1 mm2 = -u_z * 1e6 Pa per mm
        _, _, pr = got[f"{ns}/pressure"][i]
        assert [f.name for f in pr.fields] == ["x", "y", "z", "pressure_pa"]
        assert pr.width == len(topo.sensing_nodes)
        pp = np.frombuffer(np.asarray(pr.data).tobytes(), "<f4").reshape(-1, 4)
        assert np.allclose(pp[:, :3] * 1e3, expected.vertices_mm[topo.sensing_nodes], atol=1e-4)
        assert np.allclose(pp[:, 3], -uz * 1e6, rtol=1e-4, atol=1e-2)


def test_mcap_recording_decodes_with_a_second_reader(recording, predictor):
    """mcap-ros2-support decodes the CDR with its own parser of the embedded definitions; the
    file also carries the pad topology the point clouds index."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    bag, _ = recording
    with open(bag, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        assert header.profile == "ros2"
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        forces = [m.wrench.force.z for _s, c, _m, m in reader.iter_decoded_messages(
            topics=["/tactile/testsensor/wrench"])]
        assert len(forces) == 4 and all(fz < 0 for fz in forces)
        attachments = list(reader.iter_attachments())
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    import io

    topo = predictor.topology
    (att,) = [a for a in attachments if a.name == "topology.npz"]
    with np.load(io.BytesIO(att.data), allow_pickle=False) as z:
        assert np.array_equal(z["surface_faces"], topo.surface_faces)
        assert str(z["mesh_hash"]) == topo.mesh_hash
    meta = metadata["tactile_deploy"]
    assert meta["sensor_frame"] == "tactile_testsensor" and meta["mesh_hash"] == topo.mesh_hash


def test_cli_run_mcap_records_and_refuses_to_write_over_a_file(plugin, tmp_path):
    from mcap.reader import make_reader

    bag = tmp_path / "b.mcap"
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--mcap", str(bag),
                              "--no-forces", "--max-frames", "2"])
    assert res.exit_code == 0, res.output
    assert "MCAP recorder: 2 frames" in " ".join(res.output.split())
    with open(bag, "rb") as f:
        stats = make_reader(f).get_summary().statistics
    # no forces: image, depth, points in both frames; the surface marker at most 10 per second
    # of the clip's time by default (5: frames at 0 and 33 ms get one)
    assert stats.message_count == 2 * 3 + 1
    bag = tmp_path / "a.mcap"
    bag.write_bytes(b"user's bag")
    res = runner.invoke(app, ["run", "--sensor", str(plugin.folder), "--mcap", str(bag),
                              "--no-forces", "--max-frames", "1"])
    assert res.exit_code == 2 and "--overwrite" in res.output
    assert bag.read_bytes() == b"user's bag"


# ------------------------------------------------------------------------------------ node
def _rclpy_like_classes():
    """Message classes with rclpy's interface (``get_fields_and_field_types()``, attributes,
    uint8 sequences in array.array), made from rosbags' ROS 2 definitions: the node's stand-in
    for rclpy, which cannot be installed without ROS."""
    from rosbags.typesys.store import Nodetype

    from tactile_deploy.runtime.ros.convert import RosbagsCodec

    store = RosbagsCodec().typestore
    classes = {}

    def short(t):
        pkg, _, name = t.partition("/msg/")
        return f"{pkg}/{name}"

    def type_string(kind, spec):
        if kind == Nodetype.BASE:
            return {"float64": "double", "float32": "float"}.get(spec[0], spec[0])
        if kind == Nodetype.NAME:
            return short(spec)
        (ek, es), n = spec
        inner = type_string(ek, es)
        return f"{inner}[{n}]" if kind == Nodetype.ARRAY else f"sequence<{inner}>"

    def get_message(type_name):
        if type_name in classes:
            return classes[type_name]
        _c, defs = store.fielddefs[type_name]
        types = {n: type_string(k, s) for n, (k, s) in defs}

        class Msg:
            __type__ = type_name

            def __init__(self):
                for n, (k, s) in defs:
                    if k == Nodetype.NAME:
                        setattr(self, n, get_message(s)())
                    elif k == Nodetype.BASE:
                        setattr(self, n, "" if s[0] == "string" else 0)
                    else:
                        setattr(self, n, [])

            @classmethod
            def get_fields_and_field_types(cls):
                return dict(types)

        classes[type_name] = Msg
        return Msg

    return get_message


def _plain(msg):
    """A stand-in message back to the plain fields :class:`RosMessage` holds."""
    import array

    out = {}
    for name in msg.get_fields_and_field_types():
        v = getattr(msg, name)
        if hasattr(v, "get_fields_and_field_types"):
            out[name] = _plain(v)
        elif isinstance(v, array.array):
            out[name] = np.frombuffer(v.tobytes(), {"B": np.uint8, "f": np.float32}[v.typecode])
        elif isinstance(v, list) and v and hasattr(v[0], "get_fields_and_field_types"):
            out[name] = [_plain(e) for e in v]
        else:
            out[name] = v
    return out


def test_ros_node_publishes_the_same_messages_as_the_recording(plugin, predictor):
    """The node's sink, with rclpy-like message classes and fake publishers, publishes every
    topic; each message, turned back into fields and CDR-serialised, is byte for byte the
    message ``run --mcap`` writes for the same frame."""
    from tactile_deploy.runtime.forces import ForceEstimator, SurfaceStiffness
    from tactile_deploy.runtime.ros.convert import RosbagsCodec, fill_rclpy
    from tactile_deploy.runtime.ros.messages import RosMessage, RosNames, frame_messages
    from tactile_deploy.runtime.ros.node import RosPublisherSink, node_settings
    from tactile_deploy.runtime.run import Runner, RunOptions
    from tactile_deploy.runtime.sinks import FrameResult
    from tactile_deploy.runtime.sources.base import ArrayPlayback, Frame

    get_message = _rclpy_like_classes()
    sent: dict[str, list] = {}

    class Publisher:
        def __init__(self, topic, typ):
            self.topic, self.typ = topic, typ

        def publish(self, msg):
            assert msg.__type__ == self.typ
            sent.setdefault(self.topic, []).append(msg)

    topo = predictor.topology
    n = len(topo.sensing_nodes)
    forces = ForceEstimator(SurfaceStiffness(topo.sensing_nodes, np.eye(n), "identity"), 1.0,
                            topo.rest_vertices_mm, np.ones(n))
    names = RosNames.for_sensor("testsensor", namespace="/robot/left_finger")
    sink = RosPublisherSink(Publisher, get_message, topo, names, marker_hz=0.0)
    frames, t, _ = load_clip(plugin.demo_clip_path())
    summary = Runner(predictor, ArrayPlayback(list(frames[:2]), t[:2], "clip"), RunOptions(),
                     forces=forces, sinks=[sink]).run()
    assert summary.sinks["ROS 2 publisher"]["handled"] == 2
    assert set(sent) == {"/robot/left_finger/" + t for t in ("image_raw", "depth", "mesh/points",
                                                             "wrench", "pressure")}  # no marker
    codec = RosbagsCodec()
    last = sent["/robot/left_finger/depth"][-1]
    stamp = last.header.stamp.sec * 10**9 + last.header.stamp.nanosec
    pred = predictor.predict_frame(frames[1])
    result = FrameResult(Frame(frames[1], 1, stamp, 0), pred,
                         forces.estimate(pred.vertices_mm), 1.0)
    for topic, msg in frame_messages(result, topo, names, marker=True):
        if topic.endswith("surface"):     # not published (marker_hz 0): fill one as the sink does
            filled = fill_rclpy(get_message(msg.type)(), msg.fields, get_message)
        else:
            filled = sent[topic][-1]
        assert codec.serialize(RosMessage(msg.type, _plain(filled))) == codec.serialize(msg), topic
    assert node_settings({"sensor": "gelslim1", "marker_hz": 5}).marker_hz == 5.0
    with pytest.raises(ValueError, match="'forces' must be a bool"):
        node_settings({"forces": "yes"})
    with pytest.raises(ValueError, match="unknown parameter 'sensr'"):
        node_settings({"sensr": "x"})
