"""How a Droneulator process starts another one, from a virtualenv or from the PyInstaller bundle.

In a virtualenv ``sys.executable`` is Python, so a child is ``python -m module``. In the frozen
bundle (``sys.frozen``) ``sys.executable`` is the ``droneulator`` program itself, which knows no
``-m`` or ``-c``: a child is ``droneulator _child module`` (a hidden command, see :func:`run_child`)
and the command line is ``droneulator ARGS``. Every place that spawns a Droneulator process builds
its command here, so the same code runs in both.

:func:`configure_frozen` prepares the bundle's environment before anything compiles: the
``@njit(cache=True)`` kernels need a writable cache directory.
"""

from __future__ import annotations

import faulthandler
import logging
import os
import runpy
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

#: the hidden first argument of the bundled program that runs a module as a child process
CHILD_COMMAND = "_child"
#: ``droneulator _child -c CODE`` runs the source CODE (stands in for ``python -c CODE``)
CODE_FLAG = "-c"


def frozen() -> bool:
    """True inside the PyInstaller bundle."""
    return bool(getattr(sys, "frozen", False))


def child_command(module: str, args: Sequence[str] = ()) -> list[str]:
    """The command that runs ``module`` as ``__main__`` with ``args`` in a new process."""
    if not module or module.startswith("-"):
        raise ValueError(f"not a module name: {module!r}")
    if frozen():
        return [sys.executable, CHILD_COMMAND, module, *args]
    return [sys.executable, "-m", module, *args]


def code_command(code: str) -> list[str]:
    """The command that runs the Python source ``code`` in a new process (like ``python -c``)."""
    if frozen():
        return [sys.executable, CHILD_COMMAND, CODE_FLAG, code]
    return [sys.executable, "-c", code]


def cli_command(args: Sequence[str] = ()) -> list[str]:
    """The command that runs ``droneulator ARGS`` with this installation."""
    if frozen():
        return [sys.executable, *args]
    return [sys.executable, "-m", "droneulator.cli", *args]


def start_server_process() -> None:
    """What a server process (dynamics, render, bridge) does first: log ``name: message`` lines at INFO
    and, should native code (EGL, Zenoh, a numba kernel) crash it, write every thread's Python stack to
    stderr, which the supervisor keeps in the run's log: a bare exit -11 says nothing of where."""
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    faulthandler.enable()


def run_child(argv: Sequence[str]) -> int:
    """``droneulator _child MODULE [ARGS...]`` or ``droneulator _child -c CODE``: what ``python -m`` and
    ``python -c`` do, for the bundle. Returns the exit status."""
    if not argv:
        print(f"droneulator {CHILD_COMMAND}: expected a module name or -c CODE", file=sys.stderr)
        return 2
    if argv[0] == CODE_FLAG:
        if len(argv) != 2:
            print(f"droneulator {CHILD_COMMAND}: -c takes exactly one argument", file=sys.stderr)
            return 2
        sys.argv = ["-c"]
        exec(compile(argv[1], "<string>", "exec"), {"__name__": "__main__"})  # noqa: S102 (python -c)
        return 0
    module, *rest = argv
    sys.argv = [module, *rest]
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        code = exc.code
        if code is None or isinstance(code, int):
            return code or 0
        print(code, file=sys.stderr)
        return 1
    return 0


def numba_cache_dir() -> Path:
    """Where numba caches the kernels of a frozen program: its user-wide cache,
    ``$XDG_CACHE_HOME/numba`` (default ``~/.cache/numba``). The cache is stamped with the executable,
    so a rebuilt bundle recompiles once."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "numba"


def configure_frozen() -> None:
    """In the bundle, make sure numba can write its cache before anything compiles.

    In a frozen program numba ignores ``NUMBA_CACHE_DIR`` (the kernels have no source file) and caches
    in :func:`numba_cache_dir`; with no writable home it would fail on the first ``@njit(cache=True)``.
    Then ``XDG_CACHE_HOME`` is pointed at a per-user temporary folder, which the children inherit."""
    if not frozen():
        return
    try:
        numba_cache_dir().mkdir(parents=True, exist_ok=True)
        if os.access(numba_cache_dir(), os.W_OK):
            return
        reason = "not writable"
    except OSError as exc:
        reason = exc.strerror or str(exc)
    fallback = Path(tempfile.gettempdir()) / f"droneulator-cache-{os.getuid()}"
    print(
        f"droneulator: the compiled-code cache {numba_cache_dir()} is unusable ({reason}); "
        f"using {fallback} (set XDG_CACHE_HOME to choose)",
        file=sys.stderr,
    )
    os.environ["XDG_CACHE_HOME"] = str(fallback)
    numba_cache_dir().mkdir(parents=True, exist_ok=True)
