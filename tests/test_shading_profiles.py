"""Training targets around the contact: modelled press profiles in the shading fit, and the FEM
ball-press profile of the pad.

Truth is independent of the fit: a Lambertian sensor (tests/test_shading_real.py) pressed by a
ball whose surroundings sink with a known analytic profile; the FEM's own nodal solution.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tactile_deploy.calibration.shading.evaluate import depth_errors
from tactile_deploy.calibration.shading.fit import fit_shading
from tactile_deploy.calibration.shading.presses import PressSet
from tactile_deploy.calibration.shading.press_profile import PressProfile
from tactile_deploy.imaging.shading import DepthFromShading

from tests.test_shading_real import SYN_BALL_MM, SYN_MM_PER_PX, SYN_SHAPE, render_lambertian


def sunken_profile(contact_radius_mm: float, ball_mm: float = SYN_BALL_MM) -> PressProfile:
    """A ball press whose gel sinks around the contact: the sphere inside, outside an
    exponential decay with the sphere's slope at the rim (continuous slope), the rim sunk by
    half the cap's height."""
    a = contact_radius_mm
    cap = ball_mm - math.sqrt(ball_mm ** 2 - a ** 2)
    rim = 0.5 * cap
    slope = a / math.sqrt(ball_mm ** 2 - a ** 2)
    r = np.arange(0.0, 6 * a, 0.005)
    inside = rim + cap - (ball_mm - np.sqrt(np.maximum(ball_mm ** 2 - r ** 2, 0.0)))
    outside = rim * np.exp(-slope * (r - a) / rim)
    return PressProfile(r, np.where(r < a, inside, outside), a, rim + cap)


def _presses(rng, n, radius_px):
    h, w = SYN_SHAPE
    rows, cols = np.mgrid[0:h, 0:w]
    circles, depths, profiles = [], [], []
    for _ in range(n):
        a = rng.uniform(*radius_px)
        c = (rng.uniform(45, w - 45), rng.uniform(45, h - 45))
        prof = sunken_profile(a * SYN_MM_PER_PX)
        circles.append((c[0], c[1], a))
        profiles.append(prof)
        depths.append(prof.depth(np.hypot(cols - c[0], rows - c[1]) * SYN_MM_PER_PX))
    return np.array(circles), np.array(depths), profiles


@pytest.fixture(scope="module")
def sunken():
    rng = np.random.default_rng(11)
    ref = render_lambertian(np.zeros(SYN_SHAPE), rng)
    circ, depth, prof = _presses(rng, 24, (22.0, 34.0))
    circ_t, depth_t, _ = _presses(rng, 6, (22.0, 30.0))
    frames = np.stack([render_lambertian(d, rng) for d in depth])
    frames_t = np.stack([render_lambertian(d, rng) for d in depth_t])
    train = PressSet(ref, frames, [f"{i:03d}.png" for i in range(24)], circ, prof)
    return train, frames_t, depth_t, circ_t


def test_profile_targets_recover_the_sunken_gel(sunken):
    """Without targets around the contact the sunken gel is guessed from the contact's colours;
    with the (here exact) profiles the depth within 1.5 contact radii meets 20 um and improves
    (measured 16.2 -> 11.6 um mean: this sensor's colour depends on the normal alone, so the
    contact's colours already cover most slopes of the ring; on the virtual GelSlim, whose LEDs
    light a sunken point differently, the gain is larger: BENCHMARKS.md, shading-virtual)."""
    train, frames, depths, circles = sunken
    h, w = SYN_SHAPE
    rows, cols = np.mgrid[0:h, 0:w]
    near = np.stack([np.hypot(cols - c[0], rows - c[1]) < 1.5 * c[2] for c in circles])
    err = {}
    for key, profiles in (("none", None), ("profiles", train.profiles)):
        presses = PressSet(train.reference, train.frames, train.names, train.circles, profiles)
        fit = fit_shading(presses, SYN_BALL_MM, SYN_MM_PER_PX)
        err[key] = depth_errors(DepthFromShading(fit.model, train.reference), frames, depths,
                                near)
    print(f"\nsunken gel, RMSE within 1.5 contact radii (um): no targets {np.round(err['none'], 1)}"
          f", profile targets {np.round(err['profiles'], 1)}")
    assert err["profiles"].max() <= 20.0
    assert err["none"].mean() >= 1.2 * err["profiles"].mean()


def test_profile_subset_and_count_checks(sunken):
    train = sunken[0]
    sub = train.subset([0, 2])
    assert sub.profiles == [train.profiles[0], train.profiles[2]]
    from tactile_deploy.calibration.shading.presses import PressDataError

    with pytest.raises(PressDataError, match="1 profiles for 24 frames"):
        PressSet(train.reference, train.frames, train.names, train.circles, train.profiles[:1])


def test_profile_slopes_and_gradients():
    """Slope of the profile against its depth; image gradients point along the radius."""
    prof = sunken_profile(1.4)
    r = np.array([0.3, 1.0, 1.6, 2.5])
    h = 1e-4
    numeric = (prof.depth(r + h) - prof.depth(r - h)) / (2 * h)
    np.testing.assert_allclose(prof.slope(r), numeric, atol=2e-3)
    g = prof.image_gradients(np.array([13.0, 10.0]), np.array([10.0, 6.0]), (10.0, 10.0), 0.1)
    np.testing.assert_allclose(g[0], [prof.slope(0.3), 0.0], atol=1e-9)     # along +column
    np.testing.assert_allclose(g[1], [0.0, -prof.slope(0.4)], atol=1e-9)    # towards -row


def test_fem_ball_press_profile():
    """The FEM profile of a 3 mm ball on the GelSlim pad: the sphere inside the contact, the
    nodal FEM depths outside it (azimuthal symmetry about the pad's centre), a bulge of the
    nearly incompressible gel further out, and the depth found again from the contact radius."""
    from tactile_deploy.calibration.shading.press_profile import BallPressModel

    model = BallPressModel("gelslim", 3.0, 0.48)
    prof = model.profile(0.0, 0.0, 0.6, 6.0)
    assert prof.depth(0.0) == pytest.approx(0.6, abs=1e-6)
    depth_nodes, contact = model.solve(0.0, 0.0, 0.6)
    r_nodes = np.hypot(*model.node_xy_mm.T)
    out = ~contact & (r_nodes < 5.0)
    # linear interpolation between nodes ~1 mm apart sags below the nodes on the convex part
    resid = prof.depth(r_nodes[out]) - depth_nodes[out]
    print(f"\nFEM profile: contact radius {prof.contact_radius_mm:.2f} mm, nodal residual "
          f"outside the contact {1e3 * np.sqrt(np.mean(resid ** 2)):.1f} um RMS, deepest bulge "
          f"{1e3 * prof.depth_mm.min():.1f} um")
    assert np.sqrt(np.mean(resid ** 2)) < 0.015
    assert 1.0 < prof.contact_radius_mm < math.sqrt(2 * 3.0 * 0.6)
    assert prof.depth_mm.min() < -0.005          # the bulge
    found = model.depth_for_contact_radius(0.0, 0.0, prof.contact_radius_mm)
    assert found == pytest.approx(0.6, abs=0.02)
