"""Safe by default: torch files load without running code they carry (a crafted checkpoint's
payload does not run; the committed bundle and adaptation step still load), and ``--publish``
binds to the loopback interface unless the address names another one."""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest

from tactile_deploy.runtime.publish import MeshPublisher, PublishError, bind_address

ROOT = Path(__file__).resolve().parent.parent


class _Payload:
    """Unpickling this calls ``Path.touch`` on the marker: code carried in the file."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_torch_files_never_run_code_they_carry(tmp_path):
    torch = pytest.importorskip("torch")
    from tactile_deploy.safe_torch import load_torch_file, weights_only_loads

    marker = tmp_path / "code_ran"
    evil = tmp_path / "checkpoint.pt"
    torch.save({"module": {"w": torch.zeros(2)}, "history": [_Payload(marker)]}, evil)
    with pytest.raises(pickle.UnpicklingError):
        load_torch_file(evil)
    with pytest.raises(pickle.UnpicklingError), weights_only_loads():
        torch.load(evil, weights_only=False)          # what torch.export.load does inside
    assert not marker.exists()
    torch.load(evil, weights_only=False)               # the unrestricted load would run it
    assert marker.exists()
    # the project's own files load: the training bundle (numpy scalars in its metrics) ...
    bundle = load_torch_file(ROOT / "exported" / "gelslim_mesh.pt")
    assert bundle["format_version"] and bundle["state_dict"]
    # ... and the adaptation step program, through the same restriction
    from tactile_deploy.adapt.step import StepProgram

    step = StepProgram.load(ROOT / "exported" / "gelslim_mesh_adapt")
    assert any(p.requires_grad for p in step.module.parameters())


@pytest.mark.parametrize("given, bound", [
    ("5555", "tcp://127.0.0.1:5555"),
    ("tcp://:5555", "tcp://127.0.0.1:5555"),
    ("tcp://localhost:5555", "tcp://127.0.0.1:5555"),
    ("tcp://127.0.0.1:5555", "tcp://127.0.0.1:5555"),
    ("tcp://*:5555", "tcp://*:5555"),               # all interfaces: named by the user
    ("tcp://192.168.1.20:5555", "tcp://192.168.1.20:5555"),
    ("ipc:///tmp/tactile.sock", "ipc:///tmp/tactile.sock"),
])
def test_publish_binds_to_loopback_unless_told_otherwise(given, bound):
    assert bind_address(given) == bound


def test_publisher_on_a_bare_port_listens_on_loopback_only(predictor_topology=None):
    import socket

    from tactile_deploy.pad.topology import MeshTopology

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    pub = MeshPublisher(str(port), "s", MeshTopology.from_pad())
    try:
        assert pub.endpoint == f"tcp://127.0.0.1:{port}"
    finally:
        pub.close()
    with pytest.raises(PublishError, match="1-65535"):
        bind_address("99999")
