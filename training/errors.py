"""Mistakes in what a user gave a ``training`` command, and how the commands report them.

:class:`UsageError`: a configuration, option or input file that cannot be used; the message names
it, the expected and the actual value, and what to do. :func:`run_command` turns it into one
``error: ...`` message and exit status 2 (real faults keep their traceback), and Ctrl-C into a
short note and exit status 130.
"""

from __future__ import annotations

import sys
from collections.abc import Callable


class UsageError(ValueError):
    """A configuration, option or input the command cannot use (the message says what to do)."""


def run_command(main: Callable[[], int], interrupted: str = "interrupted") -> int:
    """``main()``'s exit status; a :class:`UsageError` prints ``error: ...`` to stderr and gives 2,
    Ctrl-C prints ``interrupted`` and gives 130."""
    try:
        return main()
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(interrupted, file=sys.stderr)
        return 130
