#!/usr/bin/env python3
"""Installed size of tactile-deploy's base install and of what each extra adds, from the
distributions installed in this environment (run it with the Python of an environment that has
``.[dev]`` installed)::

    .venv/bin/python tools/install_sizes.py

For the base install and each extra: the closure of its requirements (markers evaluated here),
its size on disk, and for an extra what it adds on top of the base install. pip, setuptools and
wheel are not counted (every environment has them).
"""

from __future__ import annotations

import importlib.metadata as md
import re
from pathlib import Path

from packaging.requirements import Requirement

DISTRIBUTION = "tactile-deploy"
NOT_COUNTED = {"pip", "setuptools", "wheel"}


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def size_of(dist: md.Distribution) -> int:
    total = 0
    for f in dist.files or []:
        try:
            total += Path(dist.locate_file(f)).stat().st_size
        except OSError:
            pass
    return total


def closure(name: str, extras: frozenset[str], dists: dict[str, md.Distribution],
            visited: set[tuple[str, frozenset[str]]]) -> None:
    """Add (``name``, ``extras``) and everything they require to ``visited``."""
    key = canonical(name)
    if key not in dists or (key, extras) in visited:
        return
    visited.add((key, extras))
    for text in dists[key].requires or []:
        req = Requirement(text)
        if req.marker is None or any(req.marker.evaluate({"extra": e}) for e in extras | {""}):
            closure(req.name, frozenset(req.extras), dists, visited)


def main() -> None:
    dists = {canonical(d.metadata["Name"]): d for d in md.distributions()}
    sizes = {k: size_of(d) for k, d in dists.items() if k not in NOT_COUNTED}
    extras = md.metadata(DISTRIBUTION).get_all("Provides-Extra") or []

    def total(extra: str | None) -> tuple[set[str], int]:
        visited: set[tuple[str, frozenset[str]]] = set()
        closure(DISTRIBUTION, frozenset({extra} if extra else ()), dists, visited)
        seen = {key for key, _ in visited} - NOT_COUNTED
        return seen, sum(sizes.get(k, 0) for k in seen)

    base, base_size = total(None)
    print(f"base install: {base_size / 1e6:.0f} MB ({len(base)} distributions; tactile-deploy itself "
          f"{sizes[canonical(DISTRIBUTION)] / 1e6:.0f} MB)")
    for extra in extras:
        if extra == "dev":
            continue
        names, size = total(extra)
        added = sorted(names - base, key=lambda k: -sizes.get(k, 0))
        top = ", ".join(f"{k} {sizes.get(k, 0) / 1e6:.0f}" for k in added[:5])
        print(f"[{extra}]: +{(size - base_size) / 1e6:.0f} MB ({top})")


if __name__ == "__main__":
    main()
