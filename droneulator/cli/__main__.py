"""``python -m droneulator.cli ARGS``: the ``droneulator`` command (how a virtualenv spawns it)."""

import sys

from droneulator.cli import main

sys.exit(main())
