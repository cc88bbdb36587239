#!/usr/bin/env python3
"""Check a wheel install after ``tactile-deploy run --sensor gelslim2 --out RUN`` ran from a folder
outside the checkout (``.ci/run``), and print the wheel's and the install's sizes.

Run it with the Python of the virtual environment the wheel was installed into (no extras)::

    VENV/bin/python tools/check_wheel_install.py RUN_FOLDER WHEEL

Checks: tactile_deploy is imported from the environment's site-packages; ``calibration`` and
``training`` are not top-level names; the base install brought none of the extras' libraries
(torch, warp, matplotlib, questionary, ...); run.json says the run made meshes with the shipped
model and plugin inside the installed package, with their sha256 and the installed version.
"""

from __future__ import annotations

import hashlib
import importlib.metadata as md
import importlib.util
import json
import sys
import sysconfig
from pathlib import Path

from install_sizes import size_of  # tools/, beside this script

#: Import names the base install must not bring (they belong to extras).
EXTRAS_ONLY = ("torch", "warp", "matplotlib", "questionary", "serial", "onnx", "mcap", "rosbags", "rerun")
#: Tools of the environment itself, not counted in the install's size.
NOT_COUNTED = {"pip", "setuptools", "wheel"}


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def installed_sizes() -> dict[str, int]:
    """Distribution name -> bytes of its installed files, in this environment."""
    out = {}
    for dist in md.distributions():
        name = dist.metadata["Name"]
        if name.lower() in NOT_COUNTED:
            continue
        out[name] = size_of(dist)
    return out


def main(run_dir: Path, wheel: Path) -> int:
    import tactile_deploy

    site = Path(sysconfig.get_paths()["purelib"]).resolve()
    package = Path(tactile_deploy.__file__).resolve().parent
    assert package.parent == site, f"tactile_deploy imported from {package}, not from {site}"
    for name in ("calibration", "training"):
        assert importlib.util.find_spec(name) is None, f"{name} is importable as a top-level name"
    present = [name for name in EXTRAS_ONLY if importlib.util.find_spec(name) is not None]
    assert not present, f"the base install brought libraries of extras: {present}"

    run = json.loads((run_dir / "run.json").read_text())
    assert run["frames"] > 0 and run["meshes_written"] > 0, run
    assert run["tool"]["version"] == md.version("tactile-deploy"), run["tool"]
    model = Path(run["model"]["path"])
    assert model.is_relative_to(package / "exported"), f"model {model} is not the installed package's"
    assert run["model"]["sha256"] == sha256(model)
    plugin = run["plugin"]
    assert plugin["origin"] == "shipped" and Path(plugin["folder"]).is_relative_to(package / "plugins"), plugin
    assert plugin["manifest_sha256"] == sha256(Path(plugin["folder"]) / "plugin.json")
    meshes = sorted(run_dir.glob("mesh_*"))
    assert meshes, f"no mesh files in {run_dir}"
    print(f"wheel install: {run['frames']} frames -> {run['meshes_written']} meshes with {model.name} "
          f"(sha256 {run['model']['sha256'][:12]}...) of plugin {plugin['name']}")

    sizes = installed_sizes()
    total = sum(sizes.values())
    top = ", ".join(f"{name} {size / 1e6:.0f}" for name, size in sorted(sizes.items(), key=lambda kv: -kv[1])[:8])
    print(f"wheel {wheel.name}: {wheel.stat().st_size / 1e6:.1f} MB; base install: {total / 1e6:.0f} MB in "
          f"{len(sizes)} distributions (MB: {top})")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    sys.exit(main(Path(sys.argv[1]), Path(sys.argv[2])))
