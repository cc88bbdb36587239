"""Sharded, resumable, seed-reproducible datasets of simulated contacts.

Layout of a dataset folder::

    dataset.json            DatasetCard: spec, counts per indenter, depth histogram, shards
    shard_00000.npz ...     one file per shard (written atomically; a present file is complete)

Each shard (``S`` samples, ``n`` = 5,380 nodes, ``p`` = 1,076 sensing nodes) holds

==================  ======================  =============================================
key                 shape, dtype            meaning
==================  ======================  =============================================
depth               (S, 128, 128) float16*  mm pushed in, from the deformed pad mesh
depth_detail        (S, 128, 128) float16*  mm, with the indenter non-penetration floor
displacement        (S, n, 3) float16*      mm, sensor frame (vertices = rest + this)
rest_vertices       (n, 3) float32          mm, sensor frame (the frozen pad mesh)
force_n             (S,) float32            total normal force, N
contact_mask        (S, p) bool             sensing nodes in contact
indenter_index      (S,) int16              index into ``indenter_names``
indenter_names      (k,) str
x_mm, y_mm          (S,) float32            indenter origin, sensor frame
theta_deg           (S,) float32            rotation about +z
depth_mm            (S,) float32            commanded indentation depth
==================  ======================  =============================================

\* ``spec.storage`` = "float16" (the default) stores these three in half precision: it rounds each
value to 11 significant bits, a relative error of at most 2^-11 (0.049 %), i.e. at most 0.25 um
below 1 mm and 0.49 um between 1 and 2 mm (the pad takes at most 1.5 mm), against RMS model
errors of ~10 um; shards are about half the size. "float32" stores them exactly. Readers cast to
float32 (:func:`training.data.load_dataset_dir`).

Shard ``i`` draws its contacts from ``numpy.random.default_rng([seed, i])``, so a dataset is
reproduced exactly by its seed whatever the number of workers or interruptions; a killed run
resumes by skipping the shards already on disk.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Callable, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from tactile_deploy.atomic import write_json, write_npz
from tactile_deploy.fem.material import Material
from tactile_deploy.simulation.contact import (
    GENERATOR_VERSION,
    MAX_DEPTH_FRACTION,
    ContactError,
    get_camera,
    get_simulator,
    simulate_contact,
)

CARD_NAME = "dataset.json"
#: Shard arrays stored in half precision when ``spec.storage == "float16"``.
STORED_IN_HALF = ("depth", "depth_detail", "displacement")


class DatasetSpec(BaseModel):
    """What to generate. Lengths in mm, angles in degrees."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    n_samples: int = Field(gt=0, description="Number of contacts.")
    indenters: tuple[str, ...] = Field(min_length=1, description="Indenter names or mesh paths.")
    seed: int = Field(0, ge=0, description="Seed; shard i uses default_rng([seed, i]).")
    shard_size: int = Field(256, gt=0, description="Samples per shard file.")
    depth_min_mm: float = Field(0.2, gt=0, description="Smallest commanded depth, mm.")
    depth_max_mm: float = Field(1.2, gt=0, description="Largest commanded depth, mm.")
    radius_max_mm: float = Field(12.0, ge=0, description="Contacts lie within this radius, mm.")
    material: Material = Field(default_factory=Material, description="Gel and friction law.")
    storage: Literal["float16", "float32"] = Field(
        "float16", description="Precision of the stored depth maps and displacements: float16 rounds "
        "to 11 significant bits (<= 0.49 um below 2 mm), float32 is exact.",
    )

    @model_validator(mode="after")
    def _check(self) -> "DatasetSpec":
        if self.depth_min_mm > self.depth_max_mm:
            raise ValueError(
                f"depth_min_mm={self.depth_min_mm} exceeds depth_max_mm={self.depth_max_mm}"
            )
        limit = MAX_DEPTH_FRACTION * 3.0
        if self.depth_max_mm > limit:
            raise ValueError(f"depth_max_mm={self.depth_max_mm} exceeds the pad's {limit:g} mm")
        if self.radius_max_mm >= 17.5:
            raise ValueError(f"radius_max_mm={self.radius_max_mm} must stay inside the 17.5 mm pad")
        return self

    @property
    def n_shards(self) -> int:
        return math.ceil(self.n_samples / self.shard_size)

    def shard_count(self, index: int) -> int:
        return min(self.shard_size, self.n_samples - index * self.shard_size)


class ShardRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")

    file: str
    n_samples: int
    sha256: str
    rejected_poses: int = Field(description="Poses redrawn because they touched no sensing node.")


class DatasetCard(BaseModel):
    """The dataset's description (``dataset.json``)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    format_version: int = 1
    generator_version: str = GENERATOR_VERSION
    spec: DatasetSpec
    mesh_hash: str
    n_nodes: int
    formulation: str
    shards: list[ShardRecord] = Field(default_factory=list)
    counts_per_indenter: dict[str, int] = Field(default_factory=dict)
    depth_histogram_mm: dict[str, list[float]] = Field(
        default_factory=dict, description="'edges' and 'counts' of the commanded depths."
    )
    complete: bool = False


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def shard_path(out_dir: Path, index: int) -> Path:
    return out_dir / f"shard_{index:05d}.npz"


def generate_shard(spec: DatasetSpec, index: int, out_dir: Path) -> ShardRecord:
    """Simulate and write shard ``index`` (atomic). Deterministic in (spec, index)."""
    from tactile_deploy.indenters import ContactPose, get_indenter

    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional
        limits = None
    else:
        limits = threadpool_limits(1)  # small dense solves: one BLAS thread per worker is fastest
    rng = np.random.default_rng([spec.seed, index])
    count = spec.shard_count(index)
    sim = get_simulator(spec.material)
    cam = get_camera()
    indenters = [get_indenter(name) for name in spec.indenters]
    n = sim.mesh.n_nodes
    arrays = {
        "depth": np.zeros((count, cam.resolution, cam.resolution), np.float32),
        "depth_detail": np.zeros((count, cam.resolution, cam.resolution), np.float32),
        "displacement": np.zeros((count, n, 3), np.float32),
        "force_n": np.zeros(count, np.float32),
        "contact_mask": np.zeros((count, sim.mesh.n_plane), bool),
        "indenter_index": np.zeros(count, np.int16),
        "x_mm": np.zeros(count, np.float32),
        "y_mm": np.zeros(count, np.float32),
        "theta_deg": np.zeros(count, np.float32),
        "depth_mm": np.zeros(count, np.float32),
    }
    rejected = 0
    i = 0
    while i < count:
        k = int(rng.integers(len(indenters)))
        r = spec.radius_max_mm * math.sqrt(rng.random())
        phi = 2.0 * math.pi * rng.random()
        pose = ContactPose(
            x_mm=r * math.cos(phi),
            y_mm=r * math.sin(phi),
            theta_deg=360.0 * rng.random(),
            depth_mm=spec.depth_min_mm + (spec.depth_max_mm - spec.depth_min_mm) * rng.random(),
        )
        try:
            s = simulate_contact(indenters[k], pose, spec.material, cam, sim)
        except ContactError:
            rejected += 1
            if rejected > 20 * count:
                raise
            continue
        arrays["depth"][i] = s.depth_mm
        arrays["depth_detail"][i] = s.depth_detail_mm
        arrays["displacement"][i] = s.vertices_mm - s.rest_vertices_mm
        arrays["force_n"][i] = s.force_n
        arrays["contact_mask"][i] = s.contact_mask
        arrays["indenter_index"][i] = k
        arrays["x_mm"][i], arrays["y_mm"][i] = pose.x_mm, pose.y_mm
        arrays["theta_deg"][i], arrays["depth_mm"][i] = pose.theta_deg, pose.depth_mm
        i += 1
    if spec.storage == "float16":
        for key in STORED_IN_HALF:
            arrays[key] = arrays[key].astype(np.float16)
    arrays["rest_vertices"] = sim.mesh.vertices.astype(np.float32)
    arrays["indenter_names"] = np.array([ind.name for ind in indenters])
    path = shard_path(out_dir, index)
    write_npz(path, **arrays)
    if limits is not None:
        limits.unregister()
    return ShardRecord(
        file=path.name, n_samples=count, sha256=_file_sha256(path), rejected_poses=rejected
    )


def _read_shard_record(path: Path, expected: int) -> ShardRecord | None:
    """Record of a shard already on disk, or None when it is unreadable or incomplete."""
    try:
        with np.load(path) as data:
            if len(data["force_n"]) != expected:
                return None
    except (OSError, ValueError, KeyError, EOFError):
        return None
    return ShardRecord(file=path.name, n_samples=expected, sha256=_file_sha256(path), rejected_poses=0)


def _worker_shard(args):
    spec, index, out_dir = args
    return index, generate_shard(spec, index, Path(out_dir))


def generate_dataset(
    spec: DatasetSpec,
    out_dir: str | os.PathLike,
    workers: int = 1,
    on_shard: Callable[[int, float], None] | None = None,
) -> DatasetCard:
    """Generate (or resume) a dataset in ``out_dir``; returns its card.

    ``on_shard(n_samples_done_now, elapsed_s)`` is called after each shard (for progress bars).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    card_path = out_dir / CARD_NAME
    if card_path.exists():
        previous = DatasetCard.model_validate(json.loads(card_path.read_text()))
        if previous.spec != spec:
            raise ValueError(
                f"{card_path} describes a different dataset (spec {previous.spec.model_dump()}); "
                f"use another --out folder or the same parameters to resume"
            )
    sim = get_simulator(spec.material)  # builds or loads the operators before forking
    sim.compliance
    sim.greens
    card = DatasetCard(
        spec=spec, mesh_hash=sim.mesh.content_hash, n_nodes=sim.mesh.n_nodes, formulation=sim.formulation
    )
    records: dict[int, ShardRecord] = {}
    todo = []
    for index in range(spec.n_shards):
        path = shard_path(out_dir, index)
        rec = _read_shard_record(path, spec.shard_count(index)) if path.exists() else None
        if rec is None:
            todo.append(index)
        else:
            records[index] = rec
    start = time.perf_counter()

    def done(index: int, rec: ShardRecord) -> None:
        records[index] = rec
        card.shards = [records[i] for i in sorted(records)]
        write_json(card_path, card.model_dump(mode="json"))
        if on_shard is not None:
            on_shard(rec.n_samples, time.perf_counter() - start)

    if workers <= 1 or len(todo) <= 1:
        for index in todo:
            done(index, generate_shard(spec, index, out_dir))
    else:
        import multiprocessing as mp

        ctx = mp.get_context("fork")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            for index, rec in pool.map(_worker_shard, [(spec, i, str(out_dir)) for i in todo]):
                done(index, rec)
    card.counts_per_indenter, card.depth_histogram_mm = _summaries(spec, out_dir)
    card.complete = True
    write_json(card_path, card.model_dump(mode="json"))
    return card


def _summaries(spec: DatasetSpec, out_dir: Path):
    counts: dict[str, int] = {}
    depths = []
    for index in range(spec.n_shards):
        with np.load(shard_path(out_dir, index)) as data:
            names = data["indenter_names"]
            idx, n = np.unique(data["indenter_index"], return_counts=True)
            for i, c in zip(idx, n):
                counts[str(names[i])] = counts.get(str(names[i]), 0) + int(c)
            depths.append(data["depth_mm"])
    edges = np.linspace(spec.depth_min_mm, spec.depth_max_mm, 11)
    hist, _ = np.histogram(np.concatenate(depths), bins=edges)
    return counts, {"edges": edges.round(6).tolist(), "counts": hist.astype(float).tolist()}


def load_dataset(out_dir: str | os.PathLike) -> tuple[DatasetCard, list[Path]]:
    """The card and shard paths of a dataset folder (clear error when it is incomplete)."""
    out_dir = Path(out_dir)
    card_path = out_dir / CARD_NAME
    if not card_path.exists():
        raise FileNotFoundError(f"{card_path} not found: not a dataset folder (run `tactile-deploy simulate --n ...`)")
    card = DatasetCard.model_validate(json.loads(card_path.read_text()))
    if not card.complete:
        raise ValueError(f"{card_path}: dataset is incomplete; rerun the same command to resume it")
    return card, [out_dir / s.file for s in card.shards]
