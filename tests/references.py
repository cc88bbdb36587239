"""Published closed forms the tests compare against, and the import check of the modules under
tests/ that are written without the product's code.

Nothing here imports the product.
"""

from __future__ import annotations

import ast
import math
import sys
from pathlib import Path

PRODUCT_ROOTS = {"tactile_deploy", "calibration", "training", "bench", "tests"}


def dimitriadis_force(E, nu, R, d, h):
    """Force (N with E in MPa and lengths in mm) of a rigid sphere of radius ``R`` pressed ``d``
    into an elastic layer of thickness ``h`` bonded to a rigid base: Dimitriadis et al. 2002
    (Biophys. J. 82:2798), eq. (12), the bonded case."""
    chi = math.sqrt(R * d) / h
    a0 = -(1.2876 - 1.4678 * nu + 1.3442 * nu**2) / (1 - nu)
    b0 = (0.6387 - 1.0277 * nu + 1.5164 * nu**2) / (1 - nu)
    pi = math.pi
    f = (1 - 2 * a0 / pi * chi + 4 * a0**2 / pi**2 * chi**2
         - 8 / pi**3 * (a0**3 + 4 * pi**2 * b0 / 15) * chi**3
         + 16 * a0 / pi**4 * (a0**3 + 3 * pi**2 * b0 / 5) * chi**4)
    return 4 / 3 * E / (1 - nu**2) * math.sqrt(R) * d**1.5 * f


def sneddon_punch_force(E, nu, a, d):
    """Force (N with E in MPa and lengths in mm) of a rigid frictionless circular flat punch
    of radius ``a`` pressed ``d`` into an elastic half-space: F = 2 a E d / (1 - nu^2)
    (Boussinesq's flat-ended cylinder; Sneddon 1965, Int. J. Eng. Sci. 3:47). The pressure
    under it is P / (2 pi a sqrt(a^2 - r^2)), singular at the rim."""
    return 2.0 * a * E * d / (1.0 - nu * nu)


def mindlin_tangential_load(E, nu, mu, P, a, delta):
    """Cattaneo-Mindlin partial slip of a rigid sphere on an elastic half-space (Johnson,
    Contact Mechanics, 1985, eqs. 7.42 and 7.40, the second body rigid): the tangential force Q
    (N) that a tangential displacement ``delta`` (mm) of the sphere produces under the normal
    force ``P`` (N) over the contact radius ``a`` (mm), and the radius c (mm) of the stick
    zone. E in MPa. Valid for delta up to full sliding, delta* = 3 mu P (2 - nu) / (16 G a)."""
    G = E / (2 * (1 + nu))
    delta_full = 3 * mu * P * (2 - nu) / (16 * G * a)
    ratio = min(delta / delta_full, 1.0)
    q = 1 - (1 - ratio) ** 1.5  # Q / (mu P)
    return q * mu * P, a * (1 - q) ** (1 / 3)


def imports_beyond(module_file: Path, allowed: set[str]) -> tuple[set[str], set[str]]:
    """The top-level names a module imports that are neither the standard library nor
    ``allowed``, and those that are the product's own: (outside, product); both must be empty
    for a module that stands independent of the product."""
    tree = ast.parse(Path(module_file).read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            roots.add((node.module or "").split(".")[0])
    outside = {r for r in roots if r not in sys.stdlib_module_names} - allowed
    return outside, roots & PRODUCT_ROOTS
