"""What the wizard's steps leave in the work folder, read back; and frame helpers they share.

Files: ``reference.npz`` / ``reference.png`` (step reference), ``camera_mapping.json`` and
``camera.npz`` (camera), ``presses.npz`` (presses; circles are edited there), ``shading.npz``
(shading), ``fem.json`` (fem).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tactile_deploy.calibration.fem_fit.result import FemResultError, read_fem_result
from tactile_deploy.calibration.wizard.context import StepError
from tactile_deploy.calibration.wizard.state import WorkFolder
from tactile_deploy.atomic import atomic_path
from tactile_deploy.imaging.camera_mapping import load_mapping
from tactile_deploy.runtime.pipeline import Rectifier, rectify_frame, resample_to_grid


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Write an RGB image (H, W, 3) uint8 as a PNG, atomically."""
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
            raise OSError(f"could not write {path}")


def mean_frame(frames: np.ndarray) -> np.ndarray:
    """Mean of frames (n, H, W, 3) uint8, rounded back to uint8."""
    return np.clip(np.rint(frames.astype(np.float32).mean(axis=0)), 0, 255).astype(np.uint8)


def load_npz(work: WorkFolder, name: str) -> dict:
    """Arrays of ``work``'s file ``name`` (.npz), by key; :class:`StepError` when missing."""
    path = work.path(name)
    if not path.is_file():
        raise StepError(f"{path} is missing: redo the step that writes it")
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def load_reference(work: WorkFolder) -> tuple[np.ndarray, np.ndarray]:
    """(reference (H, W, 3) uint8, the frames averaged into it (n, H, W, 3))."""
    d = load_npz(work, "reference.npz")
    return d["reference"], d["frames"]


def load_camera(work: WorkFolder):

    return load_mapping(work.path("camera_mapping.json"))


def load_fitted_material(work: WorkFolder):
    """The FEM step's material (``fem.json``: E in MPa, nu), with E known; :class:`StepError`
    naming the file and field when it is missing, invalid or E could not be identified."""
    try:
        material = read_fem_result(work.path("fem.json"))
    except FemResultError as e:
        raise StepError(str(e)) from None
    if material.E_mpa is None:
        raise StepError(f"{work.path('fem.json')}: field 'E_mpa' is null (E not identifiable); "
                        "redo the FEM step, which falls back to the prior E")
    return material


def rectifier_for(camera):
    """``frame -> (ny, nx, 3) uint8`` on the imaging grid, as the runtime rectifies."""
    r = Rectifier(camera)
    return lambda frame: resample_to_grid(rectify_frame(frame, r), r)
