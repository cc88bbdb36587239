"""Which tactile-deploy is running: its version, a sha256 of its code, and the versions of the
libraries that shape its numbers (``tactile-deploy --version``, ``run.json``'s provenance).

The code's sha256 covers the runtime's Python sources (every ``.py`` file of the
:mod:`tactile_deploy` package, by path relative to the package, not those of
``tactile_deploy.calibration`` and ``tactile_deploy.training``), so two installs with the same
digest run the same runtime code, whether from a wheel or a source checkout with local changes.
"""

from __future__ import annotations

import hashlib
import platform
from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version

from tactile_deploy.checksums import file_sha256
from tactile_deploy.shipped import package_root

DISTRIBUTION = "tactile-deploy"
#: Sub-packages of the installed package that are not the runtime (left out of the code digest).
NOT_RUNTIME = ("calibration", "training", "plugins", "exported")
#: Libraries whose versions a run records (distribution names).
LIBRARIES = ("onnxruntime", "numpy", "opencv-contrib-python-headless")


def tool_version() -> str:
    """The installed distribution's version (``"unknown"`` when not installed, e.g. run from a
    checkout with ``PYTHONPATH``)."""
    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        return "unknown"


@lru_cache(maxsize=1)
def code_sha256() -> str:
    """sha256 (hex) over the runtime's Python sources: for each file, sorted by relative path,
    ``path NUL sha256(file) LF``."""
    root = package_root()
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py"), key=lambda p: p.relative_to(root).as_posix()):
        rel = path.relative_to(root)
        if rel.parts[0] in NOT_RUNTIME or "__pycache__" in rel.parts:
            continue
        digest.update(f"{rel.as_posix()}\0{file_sha256(path)}\n".encode())
    return digest.hexdigest()


def library_versions() -> dict[str, str]:
    """Python and the libraries of :data:`LIBRARIES` -> version (``"not installed"``)."""
    out = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    return out


def version_text() -> str:
    """What ``tactile-deploy --version`` prints: the version on the first line, then the code's
    sha256 and the library versions."""
    libs = ", ".join(f"{k} {v}" for k, v in library_versions().items())
    return (f"{DISTRIBUTION} {tool_version()}\n"
            f"code sha256 {code_sha256()} ({package_root()})\n"
            f"{libs}")
