"""``tactile-deploy simulate --sensor NAME [--rgb]``: one contact through a virtual sensor."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tactile_deploy.cli.common import console, fail, prepare_simulator


def single_sensor_contact(sensor: str, rgb: bool, seed: int, indenter: str, pressing_face: str,
                          x: float, y: float, theta: float, depth: float, out: Path,
                          overwrite: bool) -> None:
    """Simulate one contact with the virtual sensor ``sensor`` and write ``out`` (.npz) and,
    with ``rgb``, the frame as ``out`` with suffix .png (RGB, raw camera pixels)."""
    from pydantic import ValidationError

    from tactile_deploy.atomic import atomic_path, write_npz
    from tactile_deploy.indenters import ContactPose, get_indenter
    from tactile_deploy.outputs import OutputPathError, check_output_file
    from tactile_deploy.sensors.catalog import UnknownSensorError, load_sensor
    from tactile_deploy.sensors.config import SensorConfigError
    from tactile_deploy.simulation.contact import ContactError

    png = out.with_suffix(".png")
    try:  # FILE.npz (and FILE.png with the frame) in an existing folder, --overwrite to replace
        check_output_file(out, "--out", overwrite=overwrite, suffixes=(".npz",))
        if rgb:
            check_output_file(png, "--out (its frame)", overwrite=overwrite)
    except OutputPathError as e:
        fail(str(e))
    try:
        virtual = load_sensor(sensor)
        ind = get_indenter(indenter, pressing_face=pressing_face)
        pose = ContactPose(x_mm=x, y_mm=y, theta_deg=theta, depth_mm=depth)
    except (UnknownSensorError, SensorConfigError) as exc:
        fail(f"{exc}; list the shipped sensors with `python -c \"from tactile_deploy.sensors "
             f"import list_sensors; print(list_sensors())\"`")
    except (ValueError, FileNotFoundError, OSError, ValidationError) as exc:
        fail(str(exc))
    prepare_simulator(virtual.simulator)
    try:
        sample = virtual.contact_sample(ind, pose, np.random.default_rng(seed))
    except ContactError as exc:
        fail(str(exc))
    arrays = sample.npz_arrays()
    if not rgb:
        arrays.pop("frame")
    write_npz(out, **arrays)
    if rgb:
        import cv2

        with atomic_path(png) as tmp:
            if not cv2.imwrite(str(tmp), np.ascontiguousarray(sample.frame[..., ::-1])):
                fail(f"could not write {png}")
    h, w = sample.frame.shape[:2]
    console.print(
        f"wrote {out}{f' and {png}' if rgb else ''}: sensor {virtual.name} ({w}x{h} px), "
        f"indenter {ind.name}, depth {depth:g} mm -> force {sample.force_n:.4f} N, max depth "
        f"{float(sample.depth_mm.max()):.3f} mm")
