r"""Sharded, resumable, seed-reproducible datasets of simulated contacts.

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
metadata            () str                  JSON: units, frame, image geometry, material,
                                            mesh hash, storage precision, spec, shard index
==================  ======================  =============================================

\* ``spec.storage`` = "float16" (the default) stores these three in half precision: it rounds each
value to 11 significant bits, a relative error of at most 2^-11 (0.049 %), i.e. at most 0.25 um
below 1 mm and 0.49 um between 1 and 2 mm (the pad takes at most 1.5 mm), against RMS model
errors of ~10 um; shards are about half the size. "float32" stores them exactly. Readers cast to
float32 (:func:`tactile_deploy.training.data.load_dataset_dir`).

Shard ``i`` draws its contacts from ``numpy.random.default_rng([seed, i])``, so a dataset is
reproduced exactly by its seed whatever the number of workers or interruptions; a killed run
resumes by skipping the shards already on disk, each checked first against the checksum the card
recorded for it (or, for a shard the card does not list yet, against the spec and index in its own
metadata): a shard that was changed or belongs to another dataset is refused, never mixed in.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import signal
import time
import zipfile
from pathlib import Path
from typing import Callable, Literal

import numpy as np
from pydantic import ConfigDict, Field, ValidationError, model_validator

from tactile_deploy.atomic import write_json, write_npz
from tactile_deploy.fem.material import Material
from tactile_deploy.fileformat import StrictModel
from tactile_deploy.indenters import ContactPose, get_indenter
from tactile_deploy.jsonfile import validation_error_text
from tactile_deploy.simulation.contact import (
    DEPTH_DETAIL_MEANING,
    DEPTH_MEANING,
    GENERATOR_VERSION,
    MAX_DEPTH_FRACTION,
    SENSOR_FRAME,
    ContactError,
    camera_metadata,
    get_camera,
    get_simulator,
    simulate_contact,
)
from tactile_deploy.simulation.contact_file import ImageGeometry

CARD_NAME = "dataset.json"
#: Shard arrays stored in half precision when ``spec.storage == "float16"``.
STORED_IN_HALF = ("depth", "depth_detail", "displacement")
#: Deepest commanded depth of a dataset, mm (MAX_DEPTH_FRACTION of the shipped 3 mm gel).
DEPTH_LIMIT_MM = MAX_DEPTH_FRACTION * 3.0
#: Units of the shard arrays and of the spec's numbers (the shard's ``metadata["units"]``).
SHARD_UNITS = {
    "depth": "mm", "depth_detail": "mm", "displacement": "mm", "rest_vertices": "mm",
    "force_n": "N", "x_mm": "mm", "y_mm": "mm", "theta_deg": "deg", "depth_mm": "mm",
    "spec.depth_min_mm": "mm", "spec.depth_max_mm": "mm", "spec.radius_max_mm": "mm",
    "spec.material.E_mpa": "MPa", "spec.material.nu": "1", "spec.material.mu": "1",
}


class DatasetSpec(StrictModel):
    """What to generate. Lengths in mm, angles in degrees."""

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
        if self.depth_max_mm > DEPTH_LIMIT_MM:
            raise ValueError(f"depth_max_mm={self.depth_max_mm} exceeds the pad's {DEPTH_LIMIT_MM:g} mm")
        if self.radius_max_mm >= 17.5:
            raise ValueError(f"radius_max_mm={self.radius_max_mm} must stay inside the 17.5 mm pad")
        return self

    @property
    def n_shards(self) -> int:
        return math.ceil(self.n_samples / self.shard_size)

    def shard_count(self, index: int) -> int:
        return min(self.shard_size, self.n_samples - index * self.shard_size)


class ShardStorage(StrictModel):
    """How a shard's arrays are stored."""

    precision: Literal["float16", "float32"] = Field(description="Precision of "
                                                     f"{', '.join(STORED_IN_HALF)}.")
    dtypes: dict[str, str] = Field(description="numpy dtype of every array, by name.")
    note: str = Field(description="What the precision means for the values.")


class ShardMetadata(StrictModel):
    """``metadata`` of a shard (``shard_NNNNN.npz``): which dataset and shard it is, and what its
    arrays mean. Written through this model; a shard the card does not list is recognised by it."""

    format_version: Literal[1] = Field(1, description="Version of the shard layout.")
    generator_version: str = Field(description="Version of the contact generator.")
    shard_index: int = Field(ge=0, description="Index of this shard in the dataset.")
    n_samples: int = Field(ge=0, description="Contacts in this shard.")
    rejected_poses: int = Field(ge=0, description="Drawn poses the simulator refused (redrawn).")
    spec: DatasetSpec = Field(description="The dataset's spec (the card's).")
    mesh_hash: str = Field(description="Content hash of the pad mesh.")
    n_nodes: int = Field(gt=0, description="Nodes of the pad mesh.")
    formulation: str = Field(description="Element formulation of the pad solver.")
    units: dict[str, str] = Field(description="Unit of each array and spec number.")
    frame: str = Field(description="Coordinate frame of the positions.")
    depth: str = Field(description="What ``depth`` is.")
    depth_detail: str = Field(description="What ``depth_detail`` is.")
    image: ImageGeometry = Field(description="Pixel geometry of the depth maps.")
    storage: ShardStorage = Field(description="Precision and dtypes of the arrays.")


class ShardRecord(StrictModel):
    model_config = ConfigDict(frozen=False, allow_inf_nan=True)

    file: str
    n_samples: int
    sha256: str
    rejected_poses: int = Field(description="Poses redrawn because they touched no sensing node.")


class DatasetCard(StrictModel):
    """The dataset's description (``dataset.json``)."""

    model_config = ConfigDict(frozen=False)  # shards are recorded as they are written

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
    arrays["metadata"] = np.array(ShardMetadata(
        generator_version=GENERATOR_VERSION,
        shard_index=index,
        n_samples=count,
        rejected_poses=rejected,
        spec=spec,
        mesh_hash=sim.mesh.content_hash,
        n_nodes=n,
        formulation=sim.formulation,
        units=SHARD_UNITS,
        frame=SENSOR_FRAME,
        depth=DEPTH_MEANING,
        depth_detail=DEPTH_DETAIL_MEANING,
        image=ImageGeometry.model_validate(camera_metadata(cam)),
        storage=ShardStorage(
            precision=spec.storage,
            dtypes={k: str(v.dtype) for k, v in arrays.items()},
            note=(f"{', '.join(STORED_IN_HALF)} rounded to 11 significant bits (<= 0.49 um "
                  f"below 2 mm); readers cast to float32") if spec.storage == "float16"
            else "float arrays stored exactly as computed (float32)",
        ),
    ).model_dump_json())
    path = shard_path(out_dir, index)
    write_npz(path, **arrays)
    if limits is not None:
        limits.unregister()
    return ShardRecord(
        file=path.name, n_samples=count, sha256=_file_sha256(path), rejected_poses=rejected
    )


#: Option of ``tactile-deploy simulate`` that sets each spec field (for messages).
SPEC_OPTIONS = {
    "n_samples": "--n", "indenters": "--indenters", "seed": "--seed", "shard_size": "--shard-size",
    "depth_min_mm": "--depth-range", "depth_max_mm": "--depth-range", "storage": "--storage",
    "material.E_mpa": "--E", "material.nu": "--nu", "material.mu": "--mu",
    "material.friction": "--friction",
}


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def spec_differences(old: DatasetSpec, new: DatasetSpec, where: str) -> str:
    """``"seed (--seed): 0 in {where}, 1 now; ..."``: the fields in which ``new`` differs."""
    a, b = _flat(old.model_dump(mode="json")), _flat(new.model_dump(mode="json"))

    def text(v):
        return ",".join(map(str, v)) if isinstance(v, list) else str(v)

    parts = []
    for key in a:
        if a[key] != b.get(key):
            option = f" ({SPEC_OPTIONS[key]})" if key in SPEC_OPTIONS else ""
            parts.append(f"{key}{option}: {text(a[key])} in {where}, {text(b.get(key))} now")
    return "; ".join(parts)


def _existing_shard(
    path: Path, index: int, spec: DatasetSpec, recorded: ShardRecord | None, mesh_hash: str
) -> ShardRecord | None:
    """Record of shard ``index`` already on disk; None when it is not a readable shard (a write cut
    short: it is simulated again). A readable shard is checked against the checksum ``recorded`` in
    the card or, when the card lists none, against the spec, index and mesh in its own metadata: a
    shard that does not match raises ValueError (it is the user's file: never overwritten)."""
    expected = spec.shard_count(index)
    try:
        with np.load(path) as data:
            len(data["force_n"])
            meta_text = str(data["metadata"]) if "metadata" in data.files else None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None
    fix = f"delete {path} to simulate it again, or use another --out folder"
    sha = _file_sha256(path)
    if recorded is not None:
        if sha != recorded.sha256:
            raise ValueError(
                f"{path} does not match the checksum recorded in {path.parent / CARD_NAME} (sha256 "
                f"{recorded.sha256[:16]}..., the file has {sha[:16]}...): it was changed or comes "
                f"from another dataset; {fix}"
            )
        return recorded
    if meta_text is None:
        raise ValueError(f"{path} is not listed in {path.parent / CARD_NAME} and has no metadata "
                         f"to say which dataset it belongs to; {fix}")
    try:
        meta = ShardMetadata.model_validate_json(meta_text)
    except ValidationError as e:
        raise ValueError(validation_error_text(
            path, e, "shard metadata", f"it is not listed in {path.parent / CARD_NAME} and its "
            f"metadata does not say which dataset it belongs to; {fix}")) from None
    if meta.spec != spec:
        raise ValueError(f"{path} belongs to a different dataset ({spec_differences(meta.spec, spec, 'the shard')}); {fix}")
    if meta.shard_index != index or meta.mesh_hash != mesh_hash:
        raise ValueError(
            f"{path} is shard {meta.shard_index} of mesh {meta.mesh_hash[:12]}..., "
            f"expected shard {index} of mesh {mesh_hash[:12]}...; {fix}"
        )
    return ShardRecord(file=path.name, n_samples=expected, sha256=sha,
                       rejected_poses=meta.rejected_poses)


def scan_dataset(spec: DatasetSpec, out_dir: str | os.PathLike) -> dict[int, ShardRecord]:
    """Check that ``out_dir`` can take (or already holds part of) the dataset ``spec``; returns the
    records of the complete shards already there, by index. Raises ValueError (message says what to
    do) for a file in place of the folder, a card of another dataset or a shard that does not
    belong (see :func:`_existing_shard`); writes nothing."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"--out {out_dir} is a file, not a dataset folder; choose a new or "
                         f"existing dataset folder for --out")
    mesh_hash = get_simulator(spec.material).mesh.content_hash
    card_path = out_dir / CARD_NAME
    recorded: dict[str, ShardRecord] = {}
    if card_path.exists():
        try:
            previous = DatasetCard.model_validate(json.loads(card_path.read_text()))
        except (UnicodeDecodeError, json.JSONDecodeError, ValidationError):
            raise ValueError(f"{card_path} is not a dataset card; use another --out folder, or delete "
                             f"{card_path} to check the shards by their own metadata") from None
        if previous.spec != spec:
            raise ValueError(
                f"{card_path} describes a different dataset ({spec_differences(previous.spec, spec, 'the card')}); "
                f"use another --out folder or the same parameters to resume"
            )
        if previous.mesh_hash != mesh_hash:
            raise ValueError(f"{card_path} was simulated on another pad mesh (hash {previous.mesh_hash[:12]}..., "
                             f"now {mesh_hash[:12]}...); use another --out folder")
        recorded = {r.file: r for r in previous.shards}
    records: dict[int, ShardRecord] = {}
    for index in range(spec.n_shards):
        path = shard_path(out_dir, index)
        if path.exists():
            rec = _existing_shard(path, index, spec, recorded.get(path.name), mesh_hash)
            if rec is not None:
                records[index] = rec
    return records


def _worker_init() -> None:
    """Workers leave Ctrl-C to the parent, which stops them (SIGTERM ends them at once)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _worker_shard(args):
    spec, index, out_dir = args
    return index, generate_shard(spec, index, Path(out_dir))


def generate_dataset(
    spec: DatasetSpec,
    out_dir: str | os.PathLike,
    workers: int = 1,
    on_shard: Callable[[int, float], None] | None = None,
    existing: dict[int, ShardRecord] | None = None,
) -> DatasetCard:
    """Generate (or resume) a dataset in ``out_dir``; returns its card.

    ``existing``: :func:`scan_dataset`'s result when the caller has checked the folder already.
    ``on_shard(n_samples_done_now, elapsed_s)`` is called after each shard simulated now (for
    progress bars). On KeyboardInterrupt the workers are stopped (no partial file is left) and the
    interrupt propagates; the shards written so far are kept and a rerun resumes.
    """
    out_dir = Path(out_dir)
    records = dict(scan_dataset(spec, out_dir) if existing is None else existing)
    out_dir.mkdir(parents=True, exist_ok=True)
    card_path = out_dir / CARD_NAME
    sim = get_simulator(spec.material)
    card = DatasetCard(
        spec=spec, mesh_hash=sim.mesh.content_hash, n_nodes=sim.mesh.n_nodes, formulation=sim.formulation,
        shards=[records[i] for i in sorted(records)],
    )
    todo = [index for index in range(spec.n_shards) if index not in records]
    if todo:  # builds or loads the operators before forking
        sim.compliance
        sim.greens
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
        with ctx.Pool(min(workers, len(todo)), initializer=_worker_init) as pool:
            try:
                for index, rec in pool.imap_unordered(_worker_shard, [(spec, i, str(out_dir)) for i in todo]):
                    done(index, rec)
            finally:  # also on Ctrl-C or an error: stop the workers now, drop a shard half-written
                pool.terminate()
                for partial in out_dir.glob(".shard_*.partial.npz"):
                    partial.unlink(missing_ok=True)
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
