"""``run.json``: what a ``tactile-deploy run`` did, written when the run ends.

Counts are frames; times in ms (``wall_s`` in s); rates in frames per second; forces in N.
``tool``, ``model`` and ``plugin`` say what produced the meshes, with versions and sha256
(:mod:`tactile_deploy.runtime.provenance`).
"""

from __future__ import annotations

from typing import Any

from pydantic import Field

from tactile_deploy.fileformat import StrictModel


class ToolRecord(StrictModel):
    """The tactile-deploy install that ran (:mod:`tactile_deploy.version`)."""

    name: str = Field(description="Distribution name.")
    version: str = Field(description="Installed version ('unknown' when not installed).")
    code_sha256: str = Field(pattern="^[0-9a-f]{64}$", description="sha256 over the runtime's Python "
                             "sources (path and sha256 of each file), the same for a wheel and a checkout.")
    libraries: dict[str, str] = Field(description="Python and library versions (onnxruntime, numpy, OpenCV).")


class ModelRecord(StrictModel):
    """The ONNX model that turned depth maps into meshes."""

    path: str = Field(description="Absolute path of the model file.")
    sha256: str = Field(pattern="^[0-9a-f]{64}$", description="sha256 of the model file.")
    format: str | None = Field(description="The model contract's format and version from the model's "
                               "metadata (docs/onnx_contract.md), or null when it has none.")
    training_commit: str | None = Field(description="Commit of the training code that made the model "
                                        "(' (dirty)' when it had local changes), from its metadata, or null.")
    adapted_version: int | None = Field(description="The plugin's adapted version this model is "
                                        "(tactile-deploy adapt), or null for the plugin's own model.")


class PluginRecord(StrictModel):
    """The sensor plugin of the run."""

    name: str = Field(description="Plugin name.")
    folder: str = Field(description="Absolute path of the plugin folder.")
    origin: str = Field(description="How it was found: shipped, path, plugins dir, entry point.")
    format_version: int = Field(description="plugin.json format version.")
    manifest_sha256: str = Field(pattern="^[0-9a-f]{64}$", description="sha256 of plugin.json, which "
                                 "holds the sha256 of every file of the plugin.")


class RunRecord(StrictModel):
    """The summary of one run (``tactile_deploy.runtime.run.RunSummary``) and when it ended."""

    sensor: str = Field(description="Plugin name.")
    source: str = Field(description="Frame source, as given.")
    frames: int = Field(ge=0, description="Frames turned into meshes.")
    bad_frames: int = Field(ge=0, description="Frames the imaging pipeline refused.")
    ood_frames: int = Field(ge=0, description="Frames outside the model's training range.")
    dropped_frames: int = Field(ge=0, description="Frames the source dropped.")
    unreadable_frames: int = Field(ge=0, description="Frames the source could not read.")
    unreadable_files: list[str] = Field(description="Files of the unreadable frames.")
    reconnects: int = Field(ge=0, description="Camera reconnections.")
    meshes_written: int = Field(ge=0, description="Mesh files written.")
    meshes_skipped: int = Field(ge=0, description="Meshes not written.")
    meshes_skipped_reasons: dict[str, int] = Field(description="Skipped meshes by reason.")
    write_error: str | None = Field(description="The error that stopped writing, if any.")
    previews_written: int = Field(ge=0, description="Preview images written.")
    published: int = Field(ge=0, description="Meshes published on the stream.")
    wall_s: float = Field(ge=0, description="Wall time of the run, s.")
    fps: float = Field(ge=0, description="Frames per second over the run.")
    latency_p50_ms: float | None = Field(description="Capture -> mesh latency, median, ms.")
    latency_p95_ms: float | None = Field(description="Capture -> mesh latency, 95th percentile, ms.")
    stage_p50_ms: dict[str, float] = Field(description="Median time of each stage, ms.")
    last_total_force_n: float | None = Field(description="Total normal force of the last frame, N.")
    stopped_by: str = Field(description="What ended the run.")
    sinks: dict[str, dict[str, Any]] = Field(description="What each output sink did.")
    source_settings: dict[str, Any] = Field(description="What the source asked for and got.")
    tool: ToolRecord = Field(description="The tactile-deploy that ran.")
    model: ModelRecord | None = Field(description="The ONNX model that made the meshes (null when no model "
                                      "file made them, e.g. a lift of the depth map through the pad's FEM).")
    plugin: PluginRecord | None = Field(description="The sensor plugin (null for a predictor without one).")
    finished: str = Field(description="Local date and time the run ended (ISO 8601).")
