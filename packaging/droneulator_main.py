"""Entry point of the PyInstaller bundle: the ``droneulator`` command, frozen.

Two things must happen before :mod:`droneulator.cli` is imported: multiprocessing's helper
processes (the shared-memory resource tracker) re-enter this program and must be recognised
(``freeze_support``), and numba must have a writable cache directory (``configure_frozen``).
"""

import multiprocessing
import sys

multiprocessing.freeze_support()

from droneulator.runtime.spawn import configure_frozen  # noqa: E402 (after freeze_support)

configure_frozen()

from droneulator.cli import main  # noqa: E402 (after the cache is checked)

sys.exit(main())
