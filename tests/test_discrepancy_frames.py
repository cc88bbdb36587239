"""The discrepancy workflow on measured RGB frames (fast subset; the full runs are
``tactile-deploy bench discrepancy --frames``).

Measured frames come from the shipped virtual sensor ``gelslim1`` (its camera noise) with an
effect switched on that the workflow is not told; they are turned into depth by the shipped
``gelslim1`` plugin's imaging pipeline, and the workflow images the model's own frames through the
same pipeline. 8 commanded contacts, a reduced candidate library (the full library is the
benchmark's).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from tactile_deploy.calibration.discrepancy.noise import noise_from_realisations
from tactile_deploy.calibration.discrepancy.synthetic import hidden_effect_data, random_contacts
from tactile_deploy.calibration.discrepancy.workflow import (
    DiscrepancyOptions,
    find_discrepancy,
    prepare_tables,
)
from tactile_deploy.sensors.config import EffectSpec

CANDIDATES = ("zero_offset", "dome", "tilt", "lens_distortion", "pixel_scale")
OPTS = DiscrepancyOptions(null_replicates=60, bootstrap=200, param_bootstrap=40, folds=4,
                          candidates=CANDIDATES)


@pytest.fixture(scope="module")
def frames_setup():
    from tactile_deploy.sensors import load_sensor

    sensor = load_sensor("gelslim1")
    sensor.prepare()
    contacts = random_contacts(8, 3, radius_mm=6.0, indenters=("sphere_r4", "sphere_r6",
                                                                "flat_punch"))
    tables = prepare_tables(sensor, hidden_effect_data(sensor, [], contacts, 0.0, 0,
                                                       frames=True), OPTS)
    return sensor, contacts, tables


def _run(frames_setup, effects, seed):
    sensor, contacts, tables = frames_setup
    data = hidden_effect_data(sensor, effects, contacts, 0.0, seed, frames=True)
    assert data.depth_mm is None and data.frames.dtype == np.uint8
    return find_discrepancy(sensor, data, OPTS, tables=tables)


@pytest.mark.slow
def test_effect_free_frames_give_none(frames_setup):
    result = _run(frames_setup, [], 11)
    assert result.verdict.verdict == "none", result.verdict.message
    # the noise is the camera's through the pipeline: correlated, and measured as such
    assert result.noise.energy_factor > 2.0
    assert result.tables.noise_maps is not None


@pytest.mark.parametrize("effect,params,key,tol", [
    ("dome", {"height_mm": 0.35}, "height_mm", 0.02),
    ("pixel_scale", {"anisotropy": -0.04}, "anisotropy", 0.005),
])
@pytest.mark.slow
def test_effect_hidden_in_frames_is_named_and_recovered(frames_setup, effect, params, key, tol):
    result = _run(frames_setup, [EffectSpec(name=effect, params=params)], 12)
    v = result.verdict
    assert v.verdict == "effect" and v.effect == effect, v.message
    if effect == "pixel_scale":  # one stretch, whichever way the chart writes it
        from tactile_deploy.sensors.effects import get_effect

        fitted = get_effect(effect, v.parameters).stretch_px(0.0, 0.0)
        np.testing.assert_allclose(fitted, get_effect(effect, params).stretch_px(0.0, 0.0),
                                   atol=tol)
    else:
        assert v.parameters[key] == pytest.approx(params[key], abs=tol)
    assert v.gap_after_mm <= 0.5 * v.gap_before_mm


def test_tables_for_frames_refuse_depth_maps(frames_setup):
    sensor, contacts, tables = frames_setup
    maps = hidden_effect_data(sensor, [], contacts, 0.005, 1)
    with pytest.raises(ValueError, match="made for frames"):
        find_discrepancy(sensor, maps, OPTS, tables=tables)


def test_noise_from_realisations_recovers_planted_white_and_correlated_noise():
    rng = np.random.default_rng(0)
    n, j, k = 30, 8, 400
    dof = np.full(n, float(k))
    white = rng.normal(0.0, 0.003, (n, j, k))
    est = noise_from_realisations(np.einsum("njk,njk->nj", white, white), dof)
    assert est.sigma_mm == pytest.approx(0.003, rel=0.03)
    assert est.energy_factor == pytest.approx(1.0, abs=0.25)
    # smooth noise (a 20 x 20 patch blurred by 3 px): the same sigma, far fewer independent
    # values, so the squared sum spreads much more than white noise's
    smooth = gaussian_filter(rng.normal(0.0, 1.0, (n, j, 20, 20)), (0, 0, 3, 3), mode="wrap")
    smooth = (0.003 * smooth / smooth.std()).reshape(n, j, k)
    est = noise_from_realisations(np.einsum("njk,njk->nj", smooth, smooth), dof)
    assert est.sigma_mm == pytest.approx(0.003, rel=0.1)
    assert est.energy_factor > 10.0


def test_press_frames_equal_press_under_the_same_noise(frames_setup):
    from tactile_deploy.indenters import ContactPose

    sensor = frames_setup[0]
    pose = ContactPose(x_mm=2.0, y_mm=-1.0, theta_deg=30.0, depth_mm=0.6)
    shots, force = sensor.press_frames("sphere_r4", pose, [np.random.default_rng(k)
                                                           for k in (5, 6)])
    for k, shot in zip((5, 6), shots):
        one = sensor.press("sphere_r4", pose, np.random.default_rng(k), truth=False)
        np.testing.assert_array_equal(shot, one.frame)
        assert force == pytest.approx(one.force_n)
    assert not np.array_equal(shots[0], shots[1])


@pytest.mark.slow
def test_contacts_estimated_from_imaged_frames(frames_setup):
    """Without commanded contacts the poses are found from the imaged maps (the pipeline's own
    depth error, tens of micrometres, must not move them) and effect-free frames still give
    none."""
    sensor = frames_setup[0]
    contacts = random_contacts(6, 8, radius_mm=6.0, indenters=("sphere_r4", "sphere_r6"))
    data = hidden_effect_data(sensor, [], contacts, 0.0, 21, frames=True, commanded=False)
    opts = DiscrepancyOptions(null_replicates=60, bootstrap=200, param_bootstrap=40, folds=3,
                              candidates=("dome", "tilt"))
    result = find_discrepancy(sensor, data, opts)
    assert result.verdict.verdict == "none", result.verdict.message
    for c, (_, truth) in zip(result.tables.contacts, contacts):
        assert c.estimated
        assert np.hypot(c.pose.x_mm - truth.x_mm, c.pose.y_mm - truth.y_mm) < 0.02
        assert abs(c.pose.depth_mm - truth.depth_mm) < 0.005
