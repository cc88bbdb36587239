"""The error of a recording that is readable but implausible (the message says what to fix)."""

from __future__ import annotations


class PlausibilityError(ValueError):
    """A plausible-looking but wrong input: a diameter given as the radius, mm given as um,
    swapped annotation axes, a reference frame with a contact, grey frames, a scale that does
    not fit. The message names the input, what was found and what to do."""
