"""The package edges hold: the import contracts of pyproject.toml (layers, no import loops, a
runtime without torch or warp, only the wizard importing its UI steps), and the runtime imports
and turns a frame into a mesh with torch and warp made unimportable."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Made unimportable in the subprocesses below: what the runtime must not need.
BLOCK = textwrap.dedent("""
    import importlib.abc, sys

    class _Blocked(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("torch", "warp"):
                raise ImportError(f"{name} is blocked: the runtime must run without it")
            return None

    sys.meta_path.insert(0, _Blocked())
""")


def _python(code: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCK + textwrap.dedent(code)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def test_import_contracts_hold():
    """`lint-imports` on the contracts in pyproject.toml (the same command CI can run)."""
    pytest.importorskip("importlinter", reason="import-linter is in the dev extra")
    res = subprocess.run([sys.executable, "-c", "from importlinter.cli import lint_imports_command; "
                          "lint_imports_command()", "--no-cache"], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert "4 kept, 0 broken" in res.stdout, res.stdout[-2000:]


def test_blocking_works():
    """The blocker itself: importing torch fails in the subprocess (else the tests below prove
    nothing)."""
    res = _python("import torch")
    assert res.returncode != 0 and "torch is blocked" in res.stderr


def test_every_runtime_module_imports_without_torch_or_warp():
    """Every module of tactile_deploy but the torch-only ``learning`` package and the optional
    warp.fem assembly imports with torch and warp unimportable."""
    res = _python("""
        import importlib, pkgutil, tactile_deploy
        optional = ("tactile_deploy.learning", "tactile_deploy.fem.elasticity_warp")
        names = [m.name for m in pkgutil.walk_packages(tactile_deploy.__path__, "tactile_deploy.")
                 if not m.name.startswith(optional) and not m.name.endswith("__main__")]
        for name in names:
            importlib.import_module(name)
        assert "torch" not in sys.modules and "warp" not in sys.modules
        print(len(names), "modules")
    """)
    assert res.returncode == 0, res.stderr[-3000:]
    assert int(res.stdout.split()[0]) > 100


def test_shipped_plugin_turns_a_frame_into_a_mesh_without_torch_or_warp():
    """The main job's path: the shipped plugin's predictor on its demo clip's first frame."""
    res = _python("""
        import numpy as np
        from tactile_deploy.runtime import MeshPredictor
        from tactile_deploy.runtime.sources.factory import open_clip

        predictor = MeshPredictor.from_plugin("gelslim2", warmup=0)
        with open_clip(predictor.plugin.demo_clip_path()) as clip:
            frame = clip.read()
        pred = predictor.predict_frame(frame.image)
        assert pred.vertices_mm.shape == (predictor.n_nodes, 3), pred.vertices_mm.shape
        assert np.all(np.isfinite(pred.vertices_mm))
        assert "torch" not in sys.modules and "warp" not in sys.modules
        print("ok", predictor.n_nodes)
    """)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.startswith("ok 5380")
