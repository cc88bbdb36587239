"""``python -m tactile_deploy.training.shading_net``: see :mod:`tactile_deploy.training.shading_net.train`."""

import sys

from tactile_deploy.training.errors import run_command

from .train import main

sys.exit(run_command(main))
