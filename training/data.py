"""Training data: simulated depth maps and pad displacements, the split by contact, the scales.

Sources (:class:`tactile_deploy.training.config.DataConfig`):

* a simulated dataset folder (``tactile-deploy simulate``; :mod:`tactile_deploy.simulation.dataset`):
  shards with ``depth`` (S, 128, 128) float32 mm pushed in and ``displacement`` (S, n, 3) float32 mm,
  sensor frame; rank r of a distributed run reads shards r, r + world, ...;
* synthetic generation at start-up with the contact simulator (:func:`generate`), rank r drawing
  from ``default_rng([seed, r])`` -- each rank makes its own shard.

Split: samples are grouped by **contact** (indenter, x, y, theta -- every depth of one press is one
contact) and whole contacts go to the held-out set, so no press is in both.
"""

from __future__ import annotations

import json
import logging
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tactile_deploy.training.config import DataConfig, SyntheticData
from tactile_deploy.training.errors import UsageError

log = logging.getLogger(__name__)


@dataclass
class ContactData:
    """depth_mm (N, R, R) float32; displacement_mm (N, n, 3) float32, sensor frame;
    contact_id (N,) int64 (same id = same press); indenter (N,) str; contact_mask (N, m) bool,
    sensing nodes touching the indenter (None where the source does not say)."""

    depth_mm: np.ndarray
    displacement_mm: np.ndarray
    contact_id: np.ndarray
    indenter: np.ndarray
    source: str
    contact_mask: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.depth_mm)
        if self.depth_mm.ndim != 3 or self.depth_mm.shape[1] != self.depth_mm.shape[2]:
            raise ValueError(f"depth_mm must have shape (N, R, R), got {self.depth_mm.shape}")
        if self.displacement_mm.shape[0] != n or self.displacement_mm.shape[2:] != (3,):
            raise ValueError(
                f"displacement_mm must have shape ({n}, n_nodes, 3), got {self.displacement_mm.shape}"
            )
        if len(self.contact_id) != n or len(self.indenter) != n:
            raise ValueError("contact_id and indenter need one entry per sample")
        if self.contact_mask is not None and (self.contact_mask.ndim != 2 or len(self.contact_mask) != n):
            raise ValueError(f"contact_mask must have shape ({n}, n_sensing_nodes), got {self.contact_mask.shape}")

    def __len__(self) -> int:
        return len(self.depth_mm)

    def subset(self, idx: np.ndarray) -> "ContactData":
        return ContactData(
            self.depth_mm[idx], self.displacement_mm[idx], self.contact_id[idx], self.indenter[idx], self.source,
            None if self.contact_mask is None else self.contact_mask[idx],
        )

    def summary(self) -> dict:
        names, counts = np.unique(self.indenter, return_counts=True)
        return {
            "source": self.source,
            "n_samples": int(len(self)),
            "n_contacts": int(len(np.unique(self.contact_id))),
            "indenters": {str(a): int(b) for a, b in zip(names, counts)},
            "max_depth_mm": float(self.depth_mm.max(initial=0.0)),
        }


def contact_ids(indenter: np.ndarray, x_mm, y_mm, theta_deg) -> np.ndarray:
    """One id per distinct press (indenter, x, y, theta rounded to 1 um / 1 mdeg), (N,) int64."""
    keys = np.stack(
        [
            np.unique(np.asarray(indenter), return_inverse=True)[1].ravel(),
            np.rint(np.asarray(x_mm, np.float64) * 1e3).astype(np.int64),
            np.rint(np.asarray(y_mm, np.float64) * 1e3).astype(np.int64),
            np.rint(np.asarray(theta_deg, np.float64) * 1e3).astype(np.int64),
        ],
        axis=1,
    )
    return np.unique(keys, axis=0, return_inverse=True)[1].ravel().astype(np.int64)


def split_by_contact(contact_id: np.ndarray, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(train_idx, val_idx): a seeded random ``val_fraction`` of the contacts is held out."""
    groups = np.unique(contact_id)
    if len(groups) < 2:
        raise ValueError(f"need at least 2 distinct contacts to split, got {len(groups)}")
    rng = np.random.default_rng(seed)
    n_val = min(max(1, int(round(val_fraction * len(groups)))), len(groups) - 1)
    val_groups = rng.permutation(groups)[:n_val]
    is_val = np.isin(contact_id, val_groups)
    return np.flatnonzero(~is_val), np.flatnonzero(is_val)


def load_dataset_dir(folder: str | Path, rank: int = 0, world: int = 1) -> ContactData:
    """Shards ``rank, rank + world, ...`` of a simulated dataset folder."""
    from tactile_deploy.simulation.dataset import load_dataset

    card, paths = load_dataset(folder)
    mine = paths[rank::world]
    if not mine:
        raise ValueError(f"{folder}: {len(paths)} shards cannot feed rank {rank} of {world}")
    parts = {"depth": [], "displacement": [], "ind": [], "x": [], "y": [], "t": [], "mask": []}
    for p in mine:
        with np.load(p) as d:
            names = d["indenter_names"]
            parts["depth"].append(d["depth"].astype(np.float32))
            parts["displacement"].append(d["displacement"].astype(np.float32))
            parts["ind"].append(names[d["indenter_index"]])
            parts["x"].append(d["x_mm"])
            parts["y"].append(d["y_mm"])
            parts["t"].append(d["theta_deg"])
            parts["mask"].append(d["contact_mask"] if "contact_mask" in d.files else None)
    ind = np.concatenate(parts["ind"]).astype(str)
    return ContactData(
        np.concatenate(parts["depth"]),
        np.concatenate(parts["displacement"]),
        contact_ids(ind, np.concatenate(parts["x"]), np.concatenate(parts["y"]), np.concatenate(parts["t"])),
        ind,
        source=f"{Path(folder).name} (mesh {card.mesh_hash[:12]}, shards {rank}::{world})",
        contact_mask=None if any(m is None for m in parts["mask"]) else np.concatenate(parts["mask"]).astype(bool),
    )


def _indenter_names(spec: SyntheticData) -> list[str]:
    from tactile_deploy.indenters import list_indenters

    return list(list_indenters("primitive")) if spec.indenters == "primitive" else list(spec.indenters)


def procedural_faces(spec: SyntheticData) -> list:
    """``spec.procedural``'s faces (:class:`~tactile_deploy.training.shading_net.shapes.GridIndenter`,
    named ``procedural_<family>``), the same on every rank; [] without them. About 17 ms a face."""
    if spec.procedural is None:
        return []
    from tactile_deploy.training.shading_net.shapes import random_indenter

    rng = np.random.default_rng([spec.procedural.seed, 0x9F0CE])
    return [random_indenter(rng) for _ in range(spec.procedural.count)]


def draw_indenter(rng: np.random.Generator, n_named: int, spec: SyntheticData) -> int:
    """Index of the next contact's indenter: one of the ``n_named`` named indenters, or with
    probability ``spec.procedural.share`` one of the procedural faces after them (indices
    ``n_named, n_named + 1, ...``). Without procedural faces one draw, as it always was."""
    if spec.procedural is None:
        return int(rng.integers(n_named))
    if rng.random() < spec.procedural.share:
        return n_named + int(rng.integers(spec.procedural.count))
    return int(rng.integers(n_named))


def generate(spec: SyntheticData, rank: int = 0, depths_per_contact: int = 1) -> ContactData:
    """Simulate ``spec.n_samples`` contacts for ``rank`` (deterministic in seed and rank).

    With ``spec.contact_radius_mm`` the simulator only lets sensing nodes within that radius touch
    (its operators are then much cheaper to build); poses whose indenter would reach a node
    outside are redrawn, so every sample is still an exact contact solution.
    ``depths_per_contact`` > 1 presses each pose at several depths (one contact, several samples).
    """
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.indenters import ContactPose, get_indenter
    from tactile_deploy.pad.asset import load_pad
    from tactile_deploy.fem.contact import ContactSolveError
    from tactile_deploy.fem.coulomb import CoulombSimulator, CoulombSolveError
    from tactile_deploy.simulation.contact import ContactError, get_camera, get_simulator, simulate_contact

    if spec.depth_min_mm > spec.depth_max_mm:
        raise ValueError(f"depth_min_mm={spec.depth_min_mm} exceeds depth_max_mm={spec.depth_max_mm}")
    pad = load_pad()
    allowed = None
    if spec.contact_radius_mm is not None:
        xy = pad.vertices[pad.sensing_nodes, :2]
        allowed = np.hypot(xy[:, 0], xy[:, 1]) <= spec.contact_radius_mm
    materials, sims = [], []
    gels = gel_laws(spec)
    for law in friction_laws(spec):
        materials.append(Material(nu=spec.nu, friction=law))
        # Coulomb contact: the sticking simulator's operators, a coefficient per contact (below)
        base = materials[-1].model_copy(update={"friction": "stick"}) if law == "coulomb" else materials[-1]
        if allowed is None:
            sims.append(get_simulator(base))
        else:  # numpy assembly: 0.3 s, against ~30 s of kernel compilation for a cold warp cache
            sims.append(ContactSimulator(pad, base, assembly="numpy", formulation=spec.formulation,
                                         contact_nodes=np.flatnonzero(allowed)))
    cam = get_camera()
    named, faces = _indenter_names(spec), procedural_faces(spec)
    indenters = [get_indenter(n) for n in named] + faces
    names = named + [f.name for f in faces]
    rng = np.random.default_rng([spec.seed, rank])
    n = spec.n_samples
    depth = np.zeros((n, cam.resolution, cam.resolution), np.float32)
    disp = np.zeros((n, pad.n_nodes, 3), np.float32)
    mask = np.zeros((n, pad.n_plane), bool)
    cid = np.zeros(n, np.int64)
    ind = np.empty(n, dtype=object)
    i = contact = rejected = 0
    while i < n:
        material, sim = materials[contact % len(materials)], sims[contact % len(sims)]
        gel = gels[contact % len(gels)]
        if material.friction == "coulomb":
            material = material.model_copy(update={"mu": float(rng.uniform(*spec.mu_range))})
            sim = CoulombSimulator.sharing(sim, material)
        k = draw_indenter(rng, len(named), spec)
        r = spec.radius_max_mm * math.sqrt(rng.random())
        phi = 2.0 * math.pi * rng.random()
        theta = 360.0 * rng.random()
        depths = np.sort(rng.uniform(spec.depth_min_mm, spec.depth_max_mm, depths_per_contact))
        for dmm in depths[: n - i]:
            pose = ContactPose(x_mm=r * math.cos(phi), y_mm=r * math.sin(phi), theta_deg=theta, depth_mm=float(dmm))
            if allowed is not None and np.any(sim.intrusion(indenters[k], pose)[~allowed] > 0):
                rejected += 1
                break
            try:
                if gel == "neo-hookean":
                    s = neo_hookean_press(sim, indenters[k], pose, cam)
                else:
                    s = simulate_contact(indenters[k], pose, material, cam, sim)
            except (ContactError, ContactSolveError, CoulombSolveError):  # off the pad, or a contact the solver gives up on
                rejected += 1
                break
            depth[i] = s.depth_mm
            disp[i] = s.vertices_mm - s.rest_vertices_mm
            mask[i] = s.contact_mask
            cid[i] = contact
            ind[i] = names[k]
            i += 1
        contact += 1
        if rejected > 50 * n + 100:
            raise RuntimeError(
                f"{rejected} poses rejected for {i} accepted: the indenters do not fit "
                f"contact_radius_mm={spec.contact_radius_mm} with radius_max_mm={spec.radius_max_mm}; "
                "use smaller indenters, a smaller radius_max_mm or a larger contact_radius_mm"
            )
    return ContactData(depth, disp, cid, ind.astype(str), source=f"synthetic seed={spec.seed} rank={rank}",
                       contact_mask=mask)


@dataclass
class NeoHookeanPress:
    """One neo-Hookean press: depth map (R, R) mm, displacements (n, 3) mm, rest positions (n, 3)
    mm (sensor frame), sensing nodes in contact (n_plane,) bool."""

    depth_mm: np.ndarray
    displacements_mm: np.ndarray
    rest_vertices_mm: np.ndarray
    contact_mask: np.ndarray

    @property
    def vertices_mm(self) -> np.ndarray:
        return self.rest_vertices_mm + self.displacements_mm


def neo_hookean_press(sim, indenter, pose, cam) -> NeoHookeanPress:
    """One frictionless press of the neo-Hookean gel on the CPU (the hyperelastic effect's solve),
    for training data and the evaluation's ``large_strain`` domain; ContactError where it touches no
    sensing node or does not converge (the pose is redrawn)."""
    from tactile_deploy.sensors.effects.hyperelastic import HyperelasticConvergenceError, solve_neo_hookean
    from tactile_deploy.simulation.contact import ContactError

    delta = sim.intrusion(indenter, pose)
    if not np.any(delta > 0):
        raise ContactError("the indenter touches no sensing node")
    try:
        res, _ = solve_neo_hookean(sim, delta, 1.0)
    except HyperelasticConvergenceError as e:
        raise ContactError(str(e)) from None
    return NeoHookeanPress(cam.render(sim.mesh, res.vertices_mm).depth_mm, res.displacements_mm,
                           res.rest_vertices_mm, res.contact_mask)


def friction_laws(spec: SyntheticData) -> tuple[str, ...]:
    """The contact laws of ``spec`` (one, or the mixture's in order)."""
    return (spec.friction,) if isinstance(spec.friction, str) else tuple(spec.friction)


def gel_laws(spec: SyntheticData) -> tuple[str, ...]:
    """The gel law of each contact law of :func:`friction_laws` ("linear" or "neo-hookean")."""
    gels = (spec.gel,) if isinstance(spec.gel, str) else tuple(spec.gel)
    return gels * len(friction_laws(spec)) if len(gels) == 1 else gels


def fresh_contacts(spec: SyntheticData, n: int, seed: int) -> ContactData:
    """``n`` new contacts of ``spec``'s distribution (same indenters and pose ranges, another
    ``seed``), simulated on the CPU: held-out or calibration maps for a run whose data were
    generated inside the training job and not stored."""
    if seed == spec.seed:
        raise ValueError(f"seed {seed} is the training seed: choose another so that no contact is shared")
    return generate(spec.model_copy(update={"n_samples": n, "seed": seed, "generator": "cpu", "envelope_bank": None}))


#: Contacts per batch of the batched neo-Hookean solve (:func:`generate_batched`).
NEO_HOOKEAN_BATCH = 2048


def generate_batched(spec: SyntheticData, rank: int = 0, device="cpu", batch: int = 16384) -> ContactData:
    """Like :func:`generate`, with the batched torch simulator on ``device`` (exact same physics).

    Poses are drawn with a torch generator seeded by ``(seed, rank)``; contacts that touch no
    sensing node, or that the exact solver flags unsolved, are dropped and redrawn.
    """
    import torch

    from tactile_deploy.training.simulation.batched import BatchedContactSimulator, EnvelopeBank
    from tactile_deploy.fem.material import Material
    from tactile_deploy.indenters import get_indenter
    from tactile_deploy.pad.asset import load_pad

    if spec.contact_radius_mm is not None:
        raise ValueError("the batched generator solves contact on the whole pad: leave contact_radius_mm unset")
    pad = load_pad()
    named = _indenter_names(spec)
    if spec.envelope_bank is not None:
        bank = EnvelopeBank.load_npz(spec.envelope_bank, device)
        if list(bank.names) != list(named):
            raise ValueError(f"{spec.envelope_bank} holds indenters {list(bank.names)}, expected {named}")
    else:
        bank = EnvelopeBank.from_indenters([get_indenter(n) for n in named], device)
    faces = procedural_faces(spec)
    if faces:  # built on the host, sent to the device once by concat
        bank = EnvelopeBank.concat([bank, EnvelopeBank.from_indenters(faces)])
    names = bank.names
    device = torch.device(device)
    # on a GPU the operators are factored there in ~2 s; on a CPU the contact simulator's cache is reused
    operators = "torch" if device.type == "cuda" else "auto"
    laws, gels = friction_laws(spec), gel_laws(spec)
    g = torch.Generator(device="cpu").manual_seed(int(spec.seed) * 1_000_003 + rank)
    n = spec.n_samples
    depth = np.zeros((n, 128, 128), np.float32)
    disp = np.zeros((n, pad.n_nodes, 3), np.float32)
    mask = np.zeros((n, pad.n_plane), bool)
    ind = np.empty(n, dtype=object)
    i = drawn = 0
    # law k fills samples [bounds[k], bounds[k + 1]): equal shares, in order
    bounds = [round(k * n / len(laws)) for k in range(len(laws) + 1)]
    sim, sim_law, nh = None, None, None
    while i < n:
        block = max(k for k in range(len(laws)) if bounds[k] <= i)
        law, gel = laws[block], gels[block]
        if (law, gel) != sim_law:
            del sim
            nh = None
            # the neo-Hookean fixed point runs in float64 (tolerance 1e-6 mm) on the linear operators
            sim = BatchedContactSimulator(pad, Material(nu=spec.nu, friction=law), device,
                                          torch.float64 if gel == "neo-hookean" else torch.float32,
                                          formulation=spec.formulation, operators=operators)
            if gel == "neo-hookean":
                from tactile_deploy.training.simulation.batched_neo_hookean import BatchedNeoHookean

                nh = BatchedNeoHookean(sim)
            sim_law = (law, gel)
        end = min(b for b in bounds if b > i)
        # a few spare draws for contacts that touch nothing; neo-Hookean batches are smaller (their
        # Anderson history and per-tet temporaries take ~22 MB per sample on the shipped pad)
        m = min(batch if nh is None else min(batch, NEO_HOOKEAN_BATCH), max(64, 2 * (end - i)))
        index = torch.randint(len(named), (m,), generator=g)
        if faces:  # a procedural face with probability share (drawn only then: other streams unchanged)
            pick = torch.rand(m, generator=g, dtype=torch.float64) < spec.procedural.share
            index = torch.where(pick, len(named) + torch.randint(len(faces), (m,), generator=g), index)
        r = spec.radius_max_mm * torch.sqrt(torch.rand(m, generator=g, dtype=torch.float64))
        phi = 2 * math.pi * torch.rand(m, generator=g, dtype=torch.float64)
        theta = 360.0 * torch.rand(m, generator=g, dtype=torch.float64)
        dmm = spec.depth_min_mm + (spec.depth_max_mm - spec.depth_min_mm) * torch.rand(m, generator=g, dtype=torch.float64)
        poses = torch.stack([r * torch.cos(phi), r * torch.sin(phi), theta, dmm], 1)
        mu = None
        if law == "coulomb":  # drawn only for Coulomb blocks: the other laws' streams are unchanged
            low, high = spec.mu_range
            mu = (low + (high - low) * torch.rand(m, generator=g, dtype=torch.float64)).to(device)
        if nh is None:
            res = sim.solve(bank, index.to(device), poses.to(device), mu=mu)
        else:
            res, _ = nh.solve_intrusion(sim.intrusion(bank, index.to(device), poses.to(device)))
        keep = (res.solved & res.contact_mask.any(dim=1)).cpu().numpy()
        take = np.flatnonzero(keep)[: end - i]
        drawn += m
        depth[i : i + len(take)] = res.depth_mm[take].cpu().numpy()
        disp[i : i + len(take)] = res.displacements_mm[take].cpu().numpy()
        mask[i : i + len(take)] = res.contact_mask[take].cpu().numpy()
        ind[i : i + len(take)] = np.asarray(names)[index.numpy()[take]]
        i += len(take)
    cid = np.arange(n, dtype=np.int64) + rank * (1 << 40)
    return ContactData(depth, disp, cid, ind.astype(str), source=f"synthetic batched seed={spec.seed} rank={rank} drawn={drawn}",
                       contact_mask=mask)


def rank_spec(spec: SyntheticData, rank: int, world: int) -> SyntheticData:
    """The generator settings of ``rank`` of ``world``: ``n_samples`` is this rank's share when
    ``split_over_ranks``."""
    if not spec.split_over_ranks:
        return spec
    share = spec.n_samples // world + (1 if rank < spec.n_samples % world else 0)
    return spec.model_copy(update={"n_samples": max(1, share)})


def cache_spec(spec: SyntheticData, rank: int = 0) -> dict:
    """What generated data depend on, stored in the cache beside them: every setting of ``spec``
    (not the envelope bank's file name) and the rank."""
    doc = spec.model_dump(mode="json")
    doc.pop("envelope_bank")
    return {**doc, "rank": rank}


def _cache_path(cfg: DataConfig, rank: int, world: int) -> Path | None:
    if cfg.cache_file is None:
        return None
    cache = Path(cfg.cache_file)
    return cache.with_name(f"{cache.stem}_rank{rank}{cache.suffix}") if world > 1 else cache


def check_data(cfg: DataConfig, rank: int = 0, world: int = 1) -> None:
    """Check the data source before any work: the dataset folder (a complete dataset with a shard
    for this rank), or a cache file that holds data of these settings. :class:`UsageError` names
    the config field, what was expected and found, and what to do."""
    if cfg.dataset_dir is not None:
        from tactile_deploy.simulation.dataset import load_dataset

        folder = Path(cfg.dataset_dir)
        if not folder.is_dir():
            raise UsageError(f"data.dataset_dir {folder}: no such folder; give a dataset folder "
                             "(tactile-deploy simulate --out FOLDER ...) or data.synthetic")
        try:
            _, paths = load_dataset(folder)
        except (FileNotFoundError, ValueError) as e:
            raise UsageError(f"data.dataset_dir {folder}: {e}") from None
        if not paths[rank::world]:
            raise UsageError(f"data.dataset_dir {folder}: {len(paths)} shards cannot feed rank {rank} of {world}; "
                             "run fewer ranks or simulate more shards")
        return
    _cached_data(cfg, rank, world, read=False)


def _cached_data(cfg: DataConfig, rank: int, world: int, read: bool = True) -> ContactData | None:
    """The data in this rank's cache file when it holds data of ``cfg.synthetic`` (None: no cache,
    not written yet, or ``read`` False); :class:`UsageError` when it holds other data."""
    cache = _cache_path(cfg, rank, world)
    if cache is None or not cache.exists():
        return None
    where = f"data.cache_file {cache}"
    try:
        with np.load(cache, allow_pickle=False) as d:
            if "spec" not in d.files:
                return _cache_without_spec(d, cfg, rank, where, read)
            have, want = json.loads(str(d["spec"])), cache_spec(cfg.synthetic, rank)
            diff = [k for k in want if have.get(k) != want[k]]
            if diff:
                detail = "; ".join(f"{k if k == 'rank' else 'data.synthetic.' + k}: cache {have.get(k)!r}, "
                                   f"config {want[k]!r}" for k in diff)
                raise UsageError(f"{where} holds data made with other settings ({detail}); delete it (it is made "
                                 "again for this config), or set another data.cache_file to keep it")
            if not read:
                return None
            return ContactData(d["depth_mm"], d["displacement_mm"], d["contact_id"], d["indenter"], str(d["source"]),
                               d["contact_mask"] if "contact_mask" in d.files else None)
    except UsageError:
        raise
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:
        raise UsageError(f"{where} is not a readable data cache ({type(e).__name__}: {e}); delete it (it is "
                         "made again), or set another data.cache_file") from None


def _cache_without_spec(d, cfg: DataConfig, rank: int, where: str, read: bool) -> ContactData | None:
    """A cache written before caches recorded their settings: reused (with a warning) when its
    generator seed, rank and size are this config's, refused otherwise."""
    spec = cfg.synthetic
    source, n = str(d["source"]), len(d["depth_mm"])
    words = source.split()
    if f"seed={spec.seed}" not in words or f"rank={rank}" not in words or n != spec.n_samples:
        raise UsageError(f"{where} holds other data ({source!r}, {n} samples; this config: seed {spec.seed}, "
                         f"rank {rank}, {spec.n_samples} samples); delete it (it is made again for this config), "
                         "or set another data.cache_file to keep it")
    log.warning("%s records no generator settings (an older cache); reused since its seed, rank and size are "
                "this config's: delete it if the indenters or pose ranges changed", where)
    if not read:
        return None
    return ContactData(d["depth_mm"], d["displacement_mm"], d["contact_id"], d["indenter"], source)


def load(cfg: DataConfig, rank: int = 0, world: int = 1, device="cpu") -> ContactData:
    """The data of ``rank``: from the dataset folder or generated (and cached if asked; a cache
    is reused only when it was made with the same settings)."""
    if cfg.dataset_dir is not None:
        return load_dataset_dir(cfg.dataset_dir, rank, world)
    cached = _cached_data(cfg, rank, world)
    if cached is not None:
        return cached
    cache = _cache_path(cfg, rank, world)
    spec = rank_spec(cfg.synthetic, rank, world)
    if spec.generator == "batched":
        data = generate_batched(spec, rank, device)
    else:
        data = generate(spec, rank)
    if cache is not None:
        from tactile_deploy.atomic import write_npz

        cache.parent.mkdir(parents=True, exist_ok=True)
        write_npz(
            cache, depth_mm=data.depth_mm, displacement_mm=data.displacement_mm,
            contact_id=data.contact_id, indenter=data.indenter, source=np.array(data.source),
            spec=np.array(json.dumps(cache_spec(cfg.synthetic, rank), sort_keys=True)),
            **({} if data.contact_mask is None else {"contact_mask": data.contact_mask}),
        )
    return data


@dataclass(frozen=True)
class Scales:
    """depth_scale_mm: mean over samples of the largest depth; displacement_scale_mm (3,): RMS of
    the displacement over free nodes, all axes (one isotropic scale, so the loss stays a mm^2 MSE)."""

    depth_scale_mm: float
    displacement_scale_mm: tuple[float, float, float]


def compute_scales(data: ContactData, free_mask: np.ndarray) -> Scales:
    d = float(np.mean(data.depth_mm.reshape(len(data), -1).max(axis=1)))
    u = data.displacement_mm[:, free_mask.astype(bool)]
    rms = float(np.sqrt(np.mean(u.astype(np.float64) ** 2)))
    if not (d > 0 and rms > 0):
        raise ValueError("the training data holds no contact (all depths or displacements are zero)")
    return Scales(d, (rms, rms, rms))
