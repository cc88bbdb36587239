"""MeshPredictor (onnxruntime session, contract checks, single and batch calls, bad input),
inverse-FEM forces against the contact simulator, and the ZeroMQ publisher's message format."""

from __future__ import annotations

import time

import numpy as np
import pytest
from test_runtime_support import (
    blob_frame,
    build_linear_onnx,
    build_test_plugin,
    linear_reference,
    wait_for_subscription,
)

from tactile_deploy.runtime.pipeline import FrameError
from tactile_deploy.onnx_runtime.errors import ModelContractError
from tactile_deploy.onnx_runtime.session import choose_providers
from tactile_deploy.pad.topology import MeshTopology
from tactile_deploy.runtime.predictor import MeshPredictor


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("model")
    topo = MeshTopology.from_pad()
    w = build_linear_onnx(folder / "m.onnx", topo, ood_threshold=0.5)
    return folder / "m.onnx", w, topo


@pytest.fixture(scope="module")
def plugin(tmp_path_factory):
    return build_test_plugin(tmp_path_factory.mktemp("plugins") / "testsensor")


# ------------------------------------------------------------------------------------ predictor
def test_single_and_batch_calls_match_the_numpy_model(model):
    path, w, topo = model
    pred = MeshPredictor(path)
    rest = topo.rest_vertices_mm
    rng = np.random.default_rng(0)
    depth = rng.uniform(0, 0.4, (4, 128, 128)).astype(np.float32)
    ref = linear_reference(depth, w, rest)
    batch = pred.predict_depth(depth)
    assert batch.vertices_mm.shape == (4, topo.rest_vertices_mm.shape[0], 3) and batch.batched
    assert np.allclose(batch.vertices_mm, ref, atol=2e-5)
    one = pred.predict_depth(depth[2])
    assert not one.batched and one.vertices_mm.shape == rest.shape
    assert np.allclose(one.vertices_mm, ref[2], atol=2e-5)
    assert isinstance(one.ood_score, float) and one.in_distribution is True
    also = pred.predict_depth(depth[:, None])                      # (N, 1, 128, 128)
    assert np.array_equal(also.vertices_mm, batch.vertices_mm)
    # topology: fixed, the pad's
    assert pred.topology.mesh_hash == topo.mesh_hash and pred.topology.tets.shape[1] == 4
    assert pred.topology.surface_faces.max() < len(rest)


def test_ood_threshold_from_metadata_and_override(model):
    path, _, _ = model
    pred = MeshPredictor(path)
    assert pred.ood_threshold == 0.5
    far = np.full((128, 128), 0.9, np.float32)        # max |depth| 0.9 > 0.5
    assert pred.predict_depth(far).in_distribution is False
    assert MeshPredictor(path, ood_threshold=2.0).predict_depth(far).in_distribution is True


def test_session_defaults_and_providers(model):
    path, _, _ = model
    pred = MeshPredictor(path, threads=1, providers="cpu")
    assert pred.providers == ["CPUExecutionProvider"]
    with pytest.warns(RuntimeWarning, match="CUDA was asked for"):
        assert choose_providers("cuda") == ["CPUExecutionProvider"]
    with pytest.raises(ValueError, match="providers must be"):
        choose_providers("tpu")


@pytest.mark.parametrize("bad, message", [
    (np.zeros((64, 64), np.float32), r"must have shape \(128, 128\)"),
    (np.zeros((2, 3, 128, 128), np.float32), r"must have shape"),
    (np.array([["a"]]), "numeric array"),
])
def test_bad_depth_inputs(model, bad, message):
    pred = MeshPredictor(model[0], warmup=0)
    with pytest.raises(FrameError, match=message):
        pred.predict_depth(bad)


def test_nan_depth_is_refused_with_a_count(model):
    pred = MeshPredictor(model[0], warmup=0)
    d = np.zeros((128, 128), np.float32)
    d[3, 4] = np.nan
    d[5, 6] = np.inf
    with pytest.raises(FrameError, match="2 NaN/inf values"):
        pred.predict_depth(d)


def test_wrong_mesh_and_damaged_model(model, tmp_path):
    path, _, topo = model
    with pytest.raises(ModelContractError, match="is not the hash of pad 'gelslim'"):
        MeshPredictor(path, expected_mesh_hash="a" * 64, warmup=0)
    other = tmp_path / "other.onnx"
    build_linear_onnx(other, topo, mesh_hash="b" * 64)
    with pytest.raises(ModelContractError, match="trained for another mesh"):
        MeshPredictor(other, warmup=0)
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(ModelContractError, match="cannot load it"):
        MeshPredictor(broken, warmup=0)
    with pytest.raises(FileNotFoundError, match="not found"):
        MeshPredictor(tmp_path / "none.onnx")


def test_from_plugin_frames(plugin):
    pred = MeshPredictor.from_plugin(plugin)
    frame = blob_frame(plugin.reference_frame)
    one = pred.predict_frame(frame)
    depth = pred.pipeline.frame_to_depth(frame)
    assert np.array_equal(one.depth_mm, depth)
    direct = pred.predict_depth(depth)
    assert np.array_equal(one.vertices_mm, direct.vertices_mm)
    batch = pred.predict_frames(np.stack([frame, plugin.reference_frame]))
    assert np.allclose(batch.vertices_mm[0], one.vertices_mm, atol=1e-6)
    for bad, message in [(frame[..., :2], r"shape \(480, 640, 2\)"),
                         (frame[:240], "640x240 px"),
                         (frame.astype(np.float32), "dtype float32"),
                         (np.dstack([frame, frame[..., :1]]), "drop the alpha channel")]:
        with pytest.raises(FrameError, match=message):
            pred.predict_frame(bad)
    nan = frame.astype(np.float64)
    nan[0, 0, 0] = np.nan
    with pytest.raises(FrameError, match="with 1 NaN values"):
        pred.predict_frame(nan)


def test_topology_file_round_trip(tmp_path):
    topo = MeshTopology.from_pad()
    topo.save(tmp_path / "t.npz")
    back = MeshTopology.load(tmp_path / "t.npz")
    assert back.mesh_hash == topo.mesh_hash
    from tactile_deploy.pad.mesh import content_hash

    assert content_hash(back.rest_vertices_mm, back.tets) == topo.mesh_hash
    assert np.array_equal(back.surface_faces, topo.surface_faces)


# ------------------------------------------------------------------------------------ forces
def test_forces_from_simulated_meshes_match_the_simulator(pad_sim):
    """Inverse FEM on the simulator's own deformed mesh returns the simulator's contact forces
    (total and per node) to round-off; E scales them linearly; the total-only path agrees."""
    from tactile_deploy.runtime.forces import ForceEstimator, SurfaceStiffness

    mesh = pad_sim.mesh
    stiff = SurfaceStiffness.from_simulator(pad_sim)
    xy = mesh.vertices[mesh.sensing_nodes, :2]
    areas = mesh.sensing_nodal_areas_mm2()
    for centre, depth, radius in (((2.0, 3.0), 0.5, 4.0), ((-6.0, 1.0), 0.8, 2.5)):
        r2 = ((xy - centre) ** 2).sum(1)
        res = pad_sim.solve_intrusion(depth - r2 / (2 * radius))
        est = ForceEstimator(stiff, pad_sim.material.E_mpa, mesh.vertices, areas)
        f = est.estimate(res.vertices_mm)
        assert res.force_n > 0.05
        assert abs(f.total_normal_force_n - res.force_n) < 1e-6 * res.force_n
        assert np.abs(f.pressure_kpa - res.pressure_kpa).max() < 1e-5 * res.pressure_kpa.max()
        quick = est.estimate(res.vertices_mm, pressure=False)
        assert abs(quick.total_normal_force_n - res.force_n) < 1e-6 * res.force_n
        est2 = ForceEstimator(stiff, 2 * pad_sim.material.E_mpa, mesh.vertices, areas)
        assert abs(est2.estimate(res.vertices_mm).total_normal_force_n - 2 * res.force_n) < 1e-6
        batch = est.estimate(np.stack([res.vertices_mm, mesh.vertices]))
        assert np.allclose(batch.total_normal_force_n, [res.force_n, 0.0], atol=1e-9)


def test_contact_patch_total_ignores_errors_off_the_contact(pad_sim):
    """The runtime's total (the contact patch: nodes above CONTACT_FRACTION of the largest nodal
    force) is the simulator's force to ~2 % on its own mesh, and stays so when the surface away
    from the contact carries a 2 um error that moves the every-node total by far more."""
    from tactile_deploy.runtime.forces import CONTACT_FRACTION, ForceEstimator, SurfaceStiffness

    mesh = pad_sim.mesh
    stiff = SurfaceStiffness.from_simulator(pad_sim)
    xy = mesh.vertices[mesh.sensing_nodes, :2]
    est = ForceEstimator(stiff, pad_sim.material.E_mpa, mesh.vertices, mesh.sensing_nodal_areas_mm2(),
                         contact_fraction=CONTACT_FRACTION)
    exact = est.with_contact_fraction(None)
    r2 = ((xy - (1.0, -2.0)) ** 2).sum(1)
    res = pad_sim.solve_intrusion(0.7 - r2 / (2 * 3.0))
    f = est.estimate(res.vertices_mm, pressure=False)
    assert abs(f.total_normal_force_n - res.force_n) < 0.02 * res.force_n
    assert set(np.flatnonzero(f.contact_mask)) <= set(np.flatnonzero(res.contact_mask))
    noisy = res.vertices_mm.copy()
    far = np.sqrt(r2) > 6.0
    noisy[mesh.sensing_nodes[far], 2] -= 0.002 * np.sign(xy[far, 0])  # +-2 um, by side
    noisy[mesh.sensing_nodes[far & (xy[:, 1] > 0)], 2] -= 0.002      # and 2 um deeper on one half
    all_nodes = exact.estimate(noisy, pressure=False).total_normal_force_n
    patch = est.estimate(noisy, pressure=False).total_normal_force_n
    assert abs(all_nodes - res.force_n) > 0.2 * res.force_n
    assert abs(patch - res.force_n) < 0.03 * res.force_n


def test_stiffness_path_without_the_simulator_cache(pad_sim):
    """The runtime's own compliance solve (no Green's functions of the volume) equals the
    simulator's compliance on a patch of nodes."""
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.runtime.forces import _z_compliance

    nodes = np.arange(0, pad_sim.mesh.n_plane, 23)
    sim = ContactSimulator(pad_sim.mesh, pad_sim.material, contact_nodes=nodes, use_cache=False,
                           assembly="numpy")
    sim._K_q, sim._factor = pad_sim.K_q, pad_sim.factor   # reuse the session's factorisation
    mine = _z_compliance(sim)
    full = pad_sim.compliance[np.ix_(nodes, nodes)]
    assert np.allclose(mine, full, rtol=1e-9, atol=1e-12 * np.abs(full).max())


# ------------------------------------------------------------------------------------ publish
def test_publisher_message_format_and_topology(model):
    from tactile_deploy.runtime.publish import MeshPublisher, MeshSubscriber

    _, _, topo = model
    rng = np.random.default_rng(0)
    v = (topo.rest_vertices_mm + rng.normal(0, 0.01, topo.rest_vertices_mm.shape)).astype(np.float32)
    with MeshPublisher("tcp://127.0.0.1:*", "testsensor", topo, hwm=100) as pub:
        with MeshSubscriber(pub.endpoint, "testsensor") as sub:
            wait_for_subscription(pub, sub)
            msgs = []
            for i in range(5):
                pub.publish(v, frame_index=i, t_capture_ns=time.time_ns(), latency_ms=1.5,
                            ood_score=0.1, in_distribution=True, total_normal_force_n=0.7,
                            pressure_kpa=np.arange(len(topo.sensing_nodes), dtype=np.float32))
                if i == 0:
                    pub.send_topology()
            deadline = time.monotonic() + 3
            while time.monotonic() < deadline and len([m for m in msgs if m[0].startswith("mesh")]) < 5:
                m = sub.recv(200)
                if m is not None:
                    msgs.append(m)
    meshes = [m for m in msgs if m[0] == "mesh/testsensor"]
    topos = [m for m in msgs if m[0] == "topology/testsensor"]
    assert len(meshes) == 5 and topos
    topic, header, arrays = meshes[2]
    assert header["format"] == "tactile-deploy.mesh" and header["version"] == 1
    assert header["seq"] == 2 and header["frame_index"] == 2 and header["units"] == "mm"
    assert header["mesh_hash"] == topo.mesh_hash and header["total_normal_force_n"] == 0.7
    assert header["t_publish_ns"] >= header["t_capture_ns"]
    assert np.array_equal(arrays["vertices_mm"], v)
    assert arrays["pressure_kpa"][5] == 5.0
    _, th, ta = topos[0]
    assert th["format"] == "tactile-deploy.topology"
    assert np.array_equal(ta["tets"], topo.tets)
    assert np.allclose(ta["rest_vertices_mm"], topo.rest_vertices_mm, atol=1e-5)


def test_publisher_delivers_what_it_queued_before_closing(model):
    """A run closes its publisher right after the last frame: the meshes still queued then
    reach the subscriber (with no wait at close, 210-262 of these 300 arrived)."""
    from tactile_deploy.runtime.publish import MeshPublisher, MeshSubscriber

    _, _, topo = model
    v = topo.rest_vertices_mm.astype(np.float32)
    pub = MeshPublisher("tcp://127.0.0.1:*", "testsensor", topo, hwm=1000)
    with MeshSubscriber(pub.endpoint, "testsensor") as sub:
        wait_for_subscription(pub, sub)
        for i in range(300):
            pub.publish(v, frame_index=i, t_capture_ns=time.time_ns(), latency_ms=1.0,
                        ood_score=0.0, in_distribution=True)
        pub.close()
        seqs = []
        while (m := sub.recv(2000)) is not None:
            if m[0] == "mesh/testsensor":
                seqs.append(m[1]["seq"])
    assert seqs == list(range(300))


def test_publisher_bad_address():
    from tactile_deploy.runtime.publish import MeshPublisher, PublishError

    with pytest.raises(PublishError, match="cannot publish on 'bogus://x'"):
        MeshPublisher("bogus://x", "s", MeshTopology.from_pad())
