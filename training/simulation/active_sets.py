"""What the batched contact solvers share: tolerances, the solve's counters, the size groups.

:mod:`tactile_deploy.training.simulation.batched` (frictionless and sticking contact) and
:mod:`tactile_deploy.training.simulation.batched_coulomb` (Coulomb friction) gather each sample's
system on its nodes in contact, padded to a group of samples of similar size (:func:`size_bucket`),
and report their work in :class:`ContactStats`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

# Relative penetration tolerance of the candidate check (as in ContactSimulator.surface_forces).
PENETRATION_RTOL = 1e-9
# Largest number of matrix elements gathered for one batched factorisation.
BLOCK_ELEMENTS = 1 << 27


@dataclass
class ContactStats:
    """Counters of one batched contact solve.

    ``host_fallback``: samples solved on the host by the CPU code path, per reason
    (``"active_set_too_large"``, ``"active_set_cycles"``, ``"not_settled"``,
    ``"factorisation_failed"``; Coulomb contact: ``"singular_system"`` in place of the last two
    kinds of failure of the active-set iteration);
    ``unsolved``: samples the CPU code path cannot solve either (it raises for them: a sticking
    active set that cycles); their forces are NaN; ``escalated_to_float64``: float32 samples
    solved again in float64 on the device;
    ``iterations``: largest number of active-set steps of a sample; ``rounds``: largest number of
    candidate-set enlargements + 1; ``samples_in_contact``: samples with some ``delta > 0``.
    """

    n_samples: int = 0
    samples_in_contact: int = 0
    escalated_to_float64: int = 0
    iterations: int = 0
    rounds: int = 0
    host_fallback: dict = field(default_factory=dict)
    unsolved: list = field(default_factory=list)

    @property
    def n_fallback(self) -> int:
        return int(sum(self.host_fallback.values()))


def size_bucket(n: torch.Tensor) -> torch.Tensor:
    """Round active-set sizes up to 4 steps per octave (>= 8): pad waste <= 25 %."""
    n = n.clamp(min=1).to(torch.float64)
    step = torch.clamp(torch.exp2(torch.floor(torch.log2(n))) / 4, min=8.0)
    return (torch.ceil(n / step) * step).to(torch.int64)
