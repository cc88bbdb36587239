"""``python -m training.shading_net``: see :mod:`training.shading_net.train`."""

import sys

from training.errors import run_command

from .train import main

sys.exit(run_command(main))
