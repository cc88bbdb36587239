"""Re-take a plugin's no-contact frame (``tactile-deploy reference --sensor NAME``).

LEDs age and gels settle: the no-contact image drifts away from the one the plugin was
calibrated with (``tactile-deploy run`` warns when it leaves the calibrated range,
:mod:`tactile_deploy.runtime.drift`). :func:`retake_reference` averages ``n_frames`` frames of
the sensor with nothing touching it, checks them (size, colour, no contact: a no-contact frame is
as smooth as the calibration's, :func:`contact_edge_score`), and writes

* the new reference frame and the no-contact depth (the frames through the plugin's pipeline
  with the new reference) under new file names in the plugin folder,
* then the manifest pointing at them (with their sha256 and the date in ``provenance``), in one
  atomic write: the plugin is always either the old one or the new one. The previous files stay
  in the folder (their names in ``provenance``).

Frames: (H, W, 3) uint8 RGB, raw camera pixels.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tactile_deploy.runtime.plugins import MANIFEST_NAME, PluginError, SensorPlugin, load_manifest

#: A new reference whose colour edges exceed this multiple of the old one's (plus 1 grey
#: level/px) shows a contact.
CONTACT_EDGE_RATIO = 2.0


def contact_edge_score(frame: np.ndarray) -> float:
    """99.5th percentile of the colour-gradient magnitude, grey levels per px (after a 2 px
    Gaussian): a ball press draws a disc of steep colour edges, a no-contact frame is smooth
    (real GelSight presses: 1.4 without contact, 4.7-5.9 with)."""
    import cv2

    g = cv2.GaussianBlur(frame.astype(np.float32), (0, 0), 2.0)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return float(np.percentile(np.sqrt((gx * gx + gy * gy).sum(-1)), 99.5))


@dataclass
class RetakenReference:
    """What :func:`retake_reference` wrote and measured."""

    plugin: Path
    reference_file: Path
    noise_file: Path
    n_frames: int
    offset_grey: tuple[float, float, float]   # the new frame against the old reference
    edge_score: float
    previous_edge_score: float


def average_frames(source, n_frames: int, shape_hw: tuple[int, int]) -> tuple[np.ndarray, list]:
    """``(mean frame (H, W, 3) uint8, frames)`` of the first ``n_frames`` frames of a source."""
    frames = []
    with source:
        while len(frames) < n_frames:
            frame = source.read()
            if frame is None:
                break
            img = np.asarray(frame.image)
            if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise PluginError(f"{source.name}: frame {frame.index} is {img.shape} {img.dtype}, "
                                  "expected (H, W, 3) uint8 RGB colour frames")
            if img.shape[:2] != shape_hw:
                raise PluginError(
                    f"{source.name}: frames are {img.shape[1]}x{img.shape[0]} px, the plugin's "
                    f"camera mapping is for {shape_hw[1]}x{shape_hw[0]}; set the camera to that "
                    "size")
            frames.append(img)
    if not frames:
        raise PluginError(f"{source.name}: no frames")
    mean = np.clip(np.rint(np.mean(frames, axis=0)), 0, 255).astype(np.uint8)
    spread = max(int(np.abs(mean[..., 0].astype(np.int16) - mean[..., 1]).max()),
                 int(np.abs(mean[..., 1].astype(np.int16) - mean[..., 2]).max()))
    if spread <= 2:
        raise PluginError(f"{source.name}: grey frames (the three channels are identical); the "
                          "reference must be the sensor's colour image")
    return mean, frames


def retake_reference(plugin: SensorPlugin, source, n_frames: int = 16,
                     when: str | None = None) -> RetakenReference:
    """Re-take ``plugin``'s no-contact frame from ``source`` (module docstring)."""
    import cv2

    from tactile_deploy.atomic import atomic_path, write_json
    from tactile_deploy.checksums import file_sha256
    from tactile_deploy.imaging.shading import frame_offset
    from pydantic import ValidationError

    from tactile_deploy.jsonfile import validation_error_text
    from tactile_deploy.runtime.pipeline import ImagingPipeline
    from tactile_deploy.runtime.plugins.manifest import PluginManifest

    m = plugin.manifest
    old_ref = plugin.reference_frame
    shape = (m.camera.image_height_px, m.camera.image_width_px)
    mean, frames = average_frames(source, n_frames, shape)
    old_score = contact_edge_score(old_ref)
    scores = [contact_edge_score(f) for f in frames]
    worst = int(np.argmax(scores))
    if scores[worst] > CONTACT_EDGE_RATIO * old_score + 1.0:
        raise PluginError(
            f"{source.name}: something touches the sensor in frame {worst} (its colour edges are "
            f"{scores[worst]:.1f} grey levels/px, the calibration's no-contact frame "
            f"{old_score:.1f}); lift everything off the gel and run again")
    score = contact_edge_score(mean)
    stamp = when or _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    folder = plugin.folder
    ref_file = folder / f"reference-{stamp}.png"
    noise_file = folder / f"noise_reference-{stamp}.npy"
    if ref_file.exists() or noise_file.exists():
        raise PluginError(f"{ref_file} exists; wait a second and run again")
    pipeline = ImagingPipeline(m.camera, plugin.shading_model, mean, None, "keep",
                               depth_grid=m.depth_grid, readout=plugin.readout,
                               readout_gain=m.readout_depth_gain)
    noise = np.mean([pipeline.frame_to_depth(f) for f in frames], axis=0).astype(np.float32)
    with atomic_path(ref_file) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(mean[..., ::-1])):
            raise PluginError(f"could not write {ref_file}")
    with atomic_path(noise_file) as tmp, open(tmp, "wb") as f:
        np.save(f, noise)
    doc = json.loads((folder / MANIFEST_NAME).read_text(encoding="utf-8"))
    prov = doc.setdefault("provenance", {})
    prov["reference_retaken"] = (f"{stamp} from {source.name}, {len(frames)} frames; previous "
                                 f"{doc['reference_frame']['path']}, "
                                 f"{doc['noise_reference']['path']}")
    doc["reference_frame"] = {"path": ref_file.name, "sha256": file_sha256(ref_file)}
    doc["noise_reference"] = {"path": noise_file.name, "sha256": file_sha256(noise_file),
                              "handling": doc["noise_reference"]["handling"]}
    try:   # the manifest is written through its model, so a broken one is never written
        manifest = PluginManifest.model_validate(doc)
    except ValidationError as e:
        raise PluginError(validation_error_text(folder / MANIFEST_NAME, e, "plugin manifest "
                                                "after re-taking the reference")) from None
    write_json(folder / MANIFEST_NAME, manifest.model_dump(mode="json"))
    load_manifest(folder)                      # the new manifest reads back
    off = frame_offset(mean, old_ref)
    return RetakenReference(folder, ref_file, noise_file, len(frames),
                            tuple(float(v) for v in off), score, old_score)
