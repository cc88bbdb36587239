"""The verdict of the discrepancy workflow: a JSON document (pydantic, strict) and its text.

``verdict`` is one of

* ``"effect"``: one candidate explains the structure in the residual (held-out);
* ``"ambiguous"``: it does, but look-alike candidates explain it about as well
  (``ambiguous_with``; ``experiment`` says how to tell them apart);
* ``"unexplained"``: there is structure beyond the noise that no candidate explains
  (``fingerprint`` describes it);
* ``"none"``: the residual is noise; nothing is missing.

Gaps are held-out (every contact predicted by parameters fitted without it), systematic (the
pixel noise removed: ``sqrt(max(mean r^2 - sigma^2, 0))`` over the contacts' regions of interest),
in mm. Gains are held-out log-likelihood ratios x 2 in units of the noise variance.
"""

from __future__ import annotations

import json
from typing import Literal

from pydantic import Field

from tactile_deploy.atomic import finite_or_null
from tactile_deploy.fileformat import StrictModel

FORMAT_VERSION = 2

#: ``obj`` with every non-finite float replaced by None (JSON has no NaN).
finite = finite_or_null


class CandidateReport(StrictModel):
    """One candidate's numbers."""

    name: str = Field(description="Registered effect name.")
    kind: str = Field(description="mechanical or optical.")
    testable: bool = Field(description="Whether these data can show it.")
    note: str = Field("", description="Why it is not testable, or empty.")
    parameters: dict[str, float] = Field(default_factory=dict, description="Fitted on all "
                                         "samples (the effect's parameters, units in names).")
    intervals: dict[str, tuple[float, float]] = Field(default_factory=dict, description="95 % "
                                                      "bootstrap intervals over contacts.")
    heldout_gain: float = Field(0.0, description="Held-out gain, noise units.")
    gain_interval: tuple[float, float] = Field((0.0, 0.0), description="Its 95 % bootstrap "
                                               "interval over contacts.")
    delta_bic: float = Field(0.0, description="BIC of the all-sample fit minus the sensor "
                             "model's (< 0: better).")
    explained_fraction: float = Field(0.0, description="Share of the residual's excess energy "
                                      "over the noise it removes, held-out (tables).")
    best_frequency: float = Field(0.0, description="Share of bootstrap resamples in which it "
                                  "has the largest held-out gain.")
    significant: bool = Field(False, description="Gain above the effect-free null and interval "
                              "above 0.")


class DiscrepancyVerdict(StrictModel):
    """What is missing from a sensor model, from measured contacts (``verdict.json`` of
    ``tactile-deploy discrepancy --report DIR``, and its ``--json`` output)."""

    format_version: Literal[2] = FORMAT_VERSION
    verdict: Literal["effect", "none", "unexplained", "ambiguous"]
    effect: str | None = Field(None, description="The named effect (the best of an ambiguous "
                               "group; the best partial candidate when unexplained).")
    parameters: dict[str, float] = Field(default_factory=dict)
    intervals: dict[str, tuple[float, float]] = Field(default_factory=dict)
    gap_before_mm: float = Field(description="Held-out systematic depth gap of the sensor "
                                 "model, mm.")
    gap_after_mm: float | None = Field(None, description="The same with the effect added "
                                    "(re-simulated exactly), mm.")
    explained_fraction: float | None = Field(None, description="Share of the excess energy "
                                             "the effect removes (exact, held-out).")
    confidence: float = Field(0.0, description="Share of bootstrap resamples over contacts in "
                              "which the named effect is the best candidate.")
    ambiguous_with: list[str] = Field(default_factory=list)
    experiment: str | None = Field(None, description="How to tell look-alikes apart.")
    second_effect: str | None = Field(None, description="A candidate that explains more "
                                      "together with the named one: run again after --apply.")
    remaining_structure: bool = Field(False, description="Structure beyond the noise remains "
                                      "after the named effect.")
    noise_mm: float = Field(description="Pixel noise, one sigma, mm.")
    noise_source: str = Field("", description="How the noise was found: the residual's "
                              "Laplacian, given with the data, or realisations of the model's "
                              "imaged frames.")
    noise_energy_factor: float = Field(1.0, description="Variance of the squared residual over "
                                       "white noise's (1: white; larger: correlated noise, as "
                                       "in depth integrated from shading).")
    excess: float = Field(description="Residual energy over the noise's, minus 1.")
    excess_z: float
    null_threshold: float = Field(description="99th percentile of the best held-out gain on "
                                  "effect-free replicates, noise units.")
    force: dict = Field(default_factory=dict, description="Where forces were measured: "
                        "n_forces, the force gap before and after (relative RMS, a fraction: "
                        "gap_before_fraction, gap_after_fraction) and E refitted to the forces "
                        "(E_before_mpa, E_after_mpa).")
    candidates: list[CandidateReport]
    fingerprint: dict
    sensor: str
    n_samples: int
    n_contacts: int
    contacts: Literal["commanded", "estimated", "mixed"]
    message: str = Field(description="One line a person can read.")

    def to_json(self) -> str:
        return json.dumps(finite(self.model_dump()), indent=2) + "\n"


def _fmt_params(params: dict, intervals: dict) -> str:
    parts = []
    for k, v in params.items():
        iv = intervals.get(k)
        parts.append(f"{k} = {v:.4g}" + (f" (95 % {iv[0]:.4g} to {iv[1]:.4g})" if iv else ""))
    return ", ".join(parts)


def verdict_text(v: DiscrepancyVerdict) -> str:
    """The verdict as a person reads it (several lines)."""
    lines = [f"sensor {v.sensor}: {v.n_samples} samples, {v.n_contacts} contacts "
             f"({v.contacts}); pixel noise {v.noise_mm * 1e3:.2f} um"
             + (f" (correlated: squared residual {v.noise_energy_factor:.0f}x as variable as "
                "white noise's)" if v.noise_energy_factor > 1.5 else ""),
             f"verdict: {v.verdict.upper()}  {v.message}"]
    if v.effect and v.verdict in ("effect", "ambiguous"):
        lines.append(f"  {v.effect}: {_fmt_params(v.parameters, v.intervals)}")
    gap = f"  held-out gap {v.gap_before_mm * 1e3:.2f} um"
    if v.gap_after_mm is not None:
        gap += f" -> {v.gap_after_mm * 1e3:.2f} um"
        if v.explained_fraction is not None:
            gap += f" ({100 * v.explained_fraction:.0f} % of the structure explained)"
    lines.append(gap + f"; confidence {v.confidence:.2f}")
    if v.ambiguous_with:
        lines.append(f"  look-alikes: {', '.join(v.ambiguous_with)}")
    if v.experiment:
        lines.append(f"  to tell them apart: {v.experiment}")
    if v.second_effect:
        lines.append(f"  a second effect is likely: {v.second_effect} (apply this one, run again)")
    elif v.remaining_structure and v.verdict == "effect":
        lines.append("  structure remains after it: apply it and run again")
    if v.force:
        f = v.force
        lines.append(f"  forces: gap {100 * f['gap_before_fraction']:.1f} %"
                     + (f" -> {100 * f['gap_after_fraction']:.1f} %"
                        if f.get("gap_after_fraction") is not None else "")
                     + f"; E refitted {f['E_before_mpa']:.4g} MPa"
                     + (f" -> {f['E_after_mpa']:.4g} MPa" if f.get("E_after_mpa") else ""))
    lines.append("  candidates (held-out gain in noise units, null threshold "
                 f"{v.null_threshold:.1f}):")
    for c in sorted(v.candidates, key=lambda c: -c.heldout_gain):
        if not c.testable:
            lines.append(f"    {c.name:16s} {c.note}")
            continue
        mark = "*" if c.significant else " "
        lines.append(f"   {mark}{c.name:16s} gain {c.heldout_gain:12.1f}  explains "
                     f"{100 * c.explained_fraction:6.1f} %  dBIC {c.delta_bic:12.1f}  "
                     f"{_fmt_params(c.parameters, {})}")
    return "\n".join(lines)
