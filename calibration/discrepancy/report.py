"""The discrepancy report: ``report.md``, ``verdict.json`` and figures in one folder.

Figures (PNG):

* ``residual_maps.png``: the three held-out samples with the largest gap: measured map, the
  sensor model's, the residual before and after the named effect (same colour scale);
* ``gap_vs_depth_position.png``: each sample's systematic gap before and after, against the
  contact's depth and its distance from the pad centre;
* ``candidates.png``: every candidate's held-out gain against the effect-free null threshold;
* ``fingerprint.png``: the residual's growth with depth, its profile around the contacts and its
  leading modes.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from tactile_deploy.calibration.discrepancy.static import describe_blob
from tactile_deploy.calibration.discrepancy.verdict import verdict_text
from tactile_deploy.calibration.discrepancy.workflow import DiscrepancyResult
from tactile_deploy.outputs import OutputPathError, check_not_input
from tactile_deploy.atomic import atomic_path, replace_folder, write_text

FIGURES = ("residual_maps.png", "gap_vs_depth_position.png", "candidates.png", "fingerprint.png")
#: Every file a report folder holds.
REPORT_FILES = ("report.md", "verdict.json", *FIGURES)


def check_report_folder(folder: str | os.PathLike, *, overwrite: bool,
                        inputs=()) -> Path:
    """Check, before any work, that ``folder`` (``--report``) may be written: not a file, not an
    input, its parent folder exists, and an existing non-empty folder only with ``overwrite``
    and only when it holds a report's files alone (the whole folder is replaced). Raises
    :class:`~tactile_deploy.outputs.OutputPathError` saying what to do."""
    folder = Path(folder)
    if folder.name.startswith("-"):
        raise OutputPathError(f"--report {folder}: that looks like an option, not a folder name; "
                              "give the folder name right after --report")
    here = Path.cwd().resolve()
    if folder.resolve() == here or folder.resolve() in here.parents or not folder.resolve().name:
        raise OutputPathError(f"--report {folder} is the current folder or one above it: the "
                              "report replaces its folder as a whole; give a new folder name, "
                              "e.g. --report report")
    check_not_input(folder, "--report", inputs)
    for given in inputs:
        if given is not None and folder.resolve() in Path(given).resolve().parents:
            raise OutputPathError(f"--report {folder} holds {given}, an input of this command: "
                                  "choose another --report (an input is never replaced, even "
                                  "with --overwrite)")
    if folder.exists() and not folder.is_dir():
        raise OutputPathError(f"--report {folder} is a file, not a folder: choose another "
                              "--report (a folder name)")
    parent = folder.resolve().parent
    if not parent.is_dir():
        raise OutputPathError(f"--report {folder}: folder {parent} does not exist: create it "
                              "first, or choose another --report")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputPathError(f"--report {folder}: cannot write into {parent}: fix its "
                              "permissions, or choose another --report")
    held = sorted(folder.iterdir()) if folder.is_dir() else []
    if held and not overwrite:
        raise OutputPathError(f"{folder} exists: pass --overwrite to replace it, or choose "
                              "another --report")
    foreign = [p for p in held if p.name not in REPORT_FILES or not p.is_file()]
    if foreign:
        raise OutputPathError(f"{folder} holds {foreign[0].name}, which is not part of a "
                              f"report ({len(foreign)} such entries): --overwrite replaces the "
                              "whole folder; move them away, or choose another --report")
    return folder


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _crop(result: DiscrepancyResult, s: int, half_px: int = 28):
    c = result.tables.contacts[result.sample_contact[s]].pose
    pitch = 35.0 / 128
    row = int(round((17.5 - c.y_mm) / pitch - 0.5))
    col = int(round((c.x_mm + 17.5) / pitch - 0.5))
    r0, c0 = max(row - half_px, 0), max(col - half_px, 0)
    return slice(r0, min(row + half_px + 1, 128)), slice(c0, min(col + half_px + 1, 128))


def residual_maps_figure(result: DiscrepancyResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = np.argsort(-result.gap_before_mm)[:3]
    after = result.verification.after_mm if result.verification is not None else None
    cols = 4 if after is not None else 3
    fig, axes = plt.subplots(len(order), cols, figsize=(3.3 * cols, 2.9 * len(order)),
                             squeeze=False, gridspec_kw={"wspace": 0.45})
    base = result.tables.base[result.sample_contact]
    res_before = result.depth_mm - base
    lim = 1e3 * max(float(np.abs(res_before[order]).max()), 1e-6)
    for r, s in enumerate(order):
        sl = _crop(result, s)
        top = 1e3 * max(float(result.depth_mm[s][sl].max()), 1e-6)
        c = result.tables.contacts[result.sample_contact[s]]
        panels = [(1e3 * result.depth_mm[s][sl], "measured", "viridis", (0, top)),
                  (1e3 * base[s][sl], "sensor model", "viridis", (0, top)),
                  (1e3 * res_before[s][sl], "residual before", "RdBu_r", (-lim, lim))]
        if after is not None:
            panels.append((1e3 * (result.depth_mm[s] - after[s])[sl],
                           f"residual with {result.verdict.effect}", "RdBu_r", (-lim, lim)))
        for k, (img, title, cmap, (lo, hi)) in enumerate(panels):
            ax = axes[r, k]
            im = ax.imshow(img, cmap=cmap, vmin=lo, vmax=hi)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=9)
            if k == 0:
                ax.set_ylabel(f"{c.indenter}\n({c.pose.x_mm:.1f}, {c.pose.y_mm:.1f}) mm, "
                              f"{c.pose.depth_mm:.2f} mm", fontsize=8)
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03).set_label("um", fontsize=8)
    fig.suptitle("depth maps (um) around the contact, 15 mm square", fontsize=10)
    _save(fig, path)


def gap_figure(result: DiscrepancyResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fp = result.fingerprint
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, x, label in ((axes[0], fp.depth_mm, "contact depth, mm"),
                         (axes[1], fp.radius_mm, "contact distance from the pad centre, mm")):
        ax.scatter(x, 1e3 * result.gap_before_mm, s=14, c="0.55", label="sensor model")
        if result.gap_after_mm is not None:
            ax.scatter(x, 1e3 * result.gap_after_mm, s=14, c="C3",
                       label=f"with {result.verdict.effect} (held-out)")
        ax.set_xlabel(label)
        ax.set_ylabel("systematic gap, um RMS")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"held-out gap per sample (noise {1e3 * result.noise.sigma_mm:.2f} um "
                 "removed)", fontsize=10)
    _save(fig, path)


def candidates_figure(result: DiscrepancyResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cands = [c for c in result.verdict.candidates]
    names = [c.name if c.testable else f"{c.name} (not testable)" for c in cands]
    gains = [c.heldout_gain if c.testable else 0.0 for c in cands]
    colours = ["C3" if c.significant else "0.6" for c in cands]
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(cands) + 1.2))
    y = np.arange(len(cands))
    ax.barh(y, gains, color=colours)
    ax.axvline(result.selection.null_threshold, color="k", ls="--", lw=1,
               label="effect-free null, 99 %")
    ax.set_yticks(y, names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xscale("symlog", linthresh=10.0)
    ax.set_xlabel("held-out gain, noise units (log)")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3, axis="x")
    _save(fig, path)


def _static_line(fp: dict) -> str:
    st = fp.get("static_structure")
    if not st:
        return "not tested"
    if not st["present"]:
        return (f"none (largest z {st['max_abs_z']:.1f} against {st['threshold_z']:.1f}, "
                f"{st['pixels_tested']:,} pixels)")
    return "; ".join(describe_blob(b) for b in st["blobs"]) + \
        f" (threshold z {st['threshold_z']:.1f})"


def fingerprint_figure(result: DiscrepancyResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fp = result.fingerprint
    fig, axes = plt.subplots(1, 5, figsize=(16, 3.2), gridspec_kw={"wspace": 0.35})
    ax = axes[0]
    ax.scatter(fp.depth_mm, 1e3 * fp.amplitude_mm, s=12)
    law = fp.summary["growth_with_depth"]
    ax.set_title(f"inside the contact: best law {law['law']}", fontsize=9)
    ax.set_xlabel("contact depth, mm")
    ax.set_ylabel("mean residual, um")
    ax.grid(alpha=0.3)
    ax = axes[1]
    centres = 0.5 * (fp.rho_edges[1:] + fp.rho_edges[:-1])
    ax.plot(centres, 1e3 * fp.radial_profile_mm, "o-")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("distance from the contact centre, contact radii")
    ax.set_ylabel("mean residual, um")
    ax.set_title("profile around the contacts", fontsize=9)
    ax.grid(alpha=0.3)
    shares = fp.summary["leading_modes"]["energy_shares"]
    for k in range(3):
        ax = axes[2 + k]
        m = fp.modes[k]
        lim = max(float(np.abs(m).max()), 1e-12)
        ax.imshow(m, cmap="RdBu_r", vmin=-lim, vmax=lim)
        ax.set_title(f"mode {k + 1}: {100 * shares[k]:.0f} % of the excess", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    _save(fig, path)


def write_report(result: DiscrepancyResult, folder: str | Path,
                 overwrite: bool = False) -> list[Path]:
    """Write the report folder; returns the files written. It is made in a staging folder beside
    ``folder`` and renamed into place when complete; an existing non-empty ``folder`` is
    replaced only with ``overwrite`` and only when it holds a report's files alone (else
    :class:`~tactile_deploy.outputs.OutputPathError`, see :func:`check_report_folder`)."""
    folder = check_report_folder(folder, overwrite=overwrite).resolve()
    staging = folder.parent / f".{folder.name}.partial-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    try:
        _write_report_files(result, staging)
        replace_folder(staging, folder)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    return [folder / name for name in REPORT_FILES]


def _write_report_files(result: DiscrepancyResult, folder: Path) -> None:
    v = result.verdict
    write_text(folder / "verdict.json", v.to_json())
    residual_maps_figure(result, folder / FIGURES[0])
    gap_figure(result, folder / FIGURES[1])
    candidates_figure(result, folder / FIGURES[2])
    fingerprint_figure(result, folder / FIGURES[3])
    rows = ["| candidate | testable | held-out gain | 95 % interval | explains | dBIC | best in "
            "| parameters |", "|---|---|---:|---|---:|---:|---:|---|"]
    for c in sorted(v.candidates, key=lambda c: -c.heldout_gain):
        params = ", ".join(f"{k} {val:.4g}" for k, val in c.parameters.items())
        rows.append(f"| {c.name}{' *' if c.significant else ''} | "
                    f"{'yes' if c.testable else c.note} | {c.heldout_gain:.1f} | "
                    f"{c.gain_interval[0]:.1f} to {c.gain_interval[1]:.1f} | "
                    f"{100 * c.explained_fraction:.1f} % | {c.delta_bic:.1f} | "
                    f"{100 * c.best_frequency:.0f} % | {params} |")
    fp = v.fingerprint
    timings = ", ".join(f"{k} {t:.1f} s" for k, t in result.timings_s.items())
    text = f"""# Discrepancy report: sensor {v.sensor}

Measured data: `{result.measured.source}` ({v.n_samples} samples, {v.n_contacts} contacts,
{v.contacts}).

```
{verdict_text(v)}
```

![residual maps](residual_maps.png)

![gap against depth and position](gap_vs_depth_position.png)

## Candidates

Held-out gain: drop of the squared residual on contacts left out of the fit
({len(result.selection.folds)}-fold, grouped by contact), in units of the pixel noise variance; *
= above the effect-free null threshold ({v.null_threshold:.1f}) with a bootstrap interval above 0.

{chr(10).join(rows)}

![candidates](candidates.png)

## Fingerprint of the residual

- growth with depth: {fp['growth_with_depth']['law']} (exponent of the residual's size
  against depth {fp['growth_with_depth']['exponent']})
- position: centre {1e3 * fp['position']['centre_rms_mm']:.2f} um, edge
  {1e3 * fp['position']['edge_rms_mm']:.2f} um RMS (split at
  {fp['position']['split_radius_mm']:.1f} mm)
- where: inside the contacts {1e3 * fp['where_rms_mm']['inside_contact']:.2f} um, ring
  {1e3 * fp['where_rms_mm']['ring_1_2_radii']:.2f} um, outside every candidate's reach
  {1e3 * fp['where_rms_mm']['outside_reach']:.2f} um RMS
- per indenter: {", ".join(f"{k} {1e3 * x:.2f} um" for k, x in fp['indenter_rms_mm'].items())}
- around the contacts: dipole {1e3 * fp['contact_centred']['dipole_mm']:.2f} um (consistency
  {fp['contact_centred']['dipole_consistency']:.2f}), quadrupole
  {1e3 * fp['contact_centred']['quadrupole_mm']:.2f} um (consistency
  {fp['contact_centred']['quadrupole_consistency']:.2f})
- leading modes: {", ".join(f"{100 * x:.0f} %" for x in fp['leading_modes']['energy_shares'])}
  of the excess energy
- static relief common to every map (mean residual away from the contacts): {_static_line(fp)}

![fingerprint](fingerprint.png)

Times: {timings}.
"""
    write_text(folder / "report.md", text)
