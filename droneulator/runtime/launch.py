"""Start ``droneulator run`` as a child process on free ports and stop it again: the one launcher that
capture, the benchmarks and the tests share.

    with launch_run(load_config(scene="vineyard"), ["--realtime"]) as run:
        client = run.client()                      # the WebSocket API at run.url
        node = RosZenohNode.from_config(run.config.bridge, listen=(), connect=(run.zenoh_endpoint,))

:func:`launch_run` picks a free API port and a free Zenoh listen endpoint, writes the config to a
temporary file for ``--config``, streams the run's output to a file or to memory, and returns once the
WebSocket API answers a ``ping``. If the process exits or the API does not answer in time it stops
what is left and raises :class:`LaunchError` with the end of the log. Leaving the ``with`` block (or
:meth:`LaunchedRun.stop`) sends SIGTERM, which the supervisor turns into an orderly shutdown of its
children, and kills the whole process group if that takes too long.
"""

from __future__ import annotations

import contextlib
import copy
import ctypes
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import IO

from websockets.exceptions import WebSocketException

from droneulator.api.access import generate_token, needs_token
from droneulator.api.client import ConnectionLostError, DroneulatorClient
from droneulator.config import SimConfig, load_config, to_dict
from droneulator.runtime.spawn import cli_command

#: options launch_run sets itself: passing them in ``args`` would make ``url``/``zenoh_endpoint`` wrong
_RESERVED = (
    "--api-port",
    "--config",
    "--scene",
    "--seed",
    "runtime.api_port",
    "runtime.api_host",
    "bridge.listen",
)


class LaunchError(RuntimeError):
    """``droneulator run`` exited or did not answer on its API in time; the message ends with its log."""


#: ports :func:`free_port` has handed out in this process (never handed out twice)
_HANDED_OUT: set[int] = set()
_PORT_FLOOR = 20000  # below: well-known and registered services (Zenoh's 7447, the API's 8765, ...)


def _ephemeral_range() -> tuple[int, int]:
    """The ports the OS gives outgoing connections (Linux: ``ip_local_port_range``)."""
    try:
        lo, hi = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(lo), int(hi)
    except (OSError, ValueError):
        return 32768, 60999


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nothing is bound to right now, for a server the caller starts later.

    Chosen outside the OS's ephemeral range, so no outgoing connection (each takes an ephemeral port as
    its source) can take it in the seconds before the server binds it, and never handed out twice by
    this process. Falls back to a port the OS picks.
    """
    lo, hi = _ephemeral_range()
    pool = [(_PORT_FLOOR, lo - 1), (hi + 1, 65535)]
    pool = [(a, b) for a, b in pool if a <= b]
    rng = random.SystemRandom()
    for _ in range(200 if pool else 0):
        a, b = rng.choice(pool)
        port = rng.randint(a, b)
        if port in _HANDED_OUT:
            continue
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
        _HANDED_OUT.add(port)
        return port
    with socket.socket() as s:
        s.bind((host, 0))
        port = int(s.getsockname()[1])
    _HANDED_OUT.add(port)
    return port


def _die_with_parent() -> None:
    """Runs in the child before exec: receive SIGTERM when the launching process dies (Linux)."""
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class RunLog:
    """The run's combined stdout and stderr, in a file (``path``) or in memory (the last ``keep`` lines)."""

    def __init__(self, path: Path | None, keep: int = 20_000) -> None:
        self.path = path
        self._lines: deque[str] = deque(maxlen=keep)
        self._lock = threading.Lock()

    def _append(self, line: str) -> None:
        with self._lock:
            self._lines.append(line.rstrip("\n"))

    def lines(self) -> list[str]:
        """Every line kept so far (from the file when the log goes to one)."""
        if self.path is not None:
            return self.path.read_text(errors="replace").splitlines() if self.path.exists() else []
        with self._lock:
            return list(self._lines)

    def tail(self, n: int = 30) -> str:
        return "\n".join(self.lines()[-n:])


class LaunchedRun:
    """A started ``droneulator run``: its API ``url``, ``zenoh_endpoint``, process ``proc`` and ``log``.

    ``config`` is the configuration it runs (the caller's with the chosen ports filled in).
    """

    def __init__(
        self,
        config: SimConfig,
        args: Sequence[str],
        log: Path | None,
        die_with_parent: bool,
    ) -> None:
        host = config.runtime.api_host
        self.config = config
        self.api_port = free_port(host)
        self.zenoh_endpoint = f"tcp/127.0.0.1:{free_port()}"
        config.runtime.api_port = self.api_port
        config.bridge.listen = [self.zenoh_endpoint]
        access = config.access
        if needs_token(host, access.token) and access.token is None:
            access.token = generate_token()  # the run's own, so that this launcher's clients know it
        reach = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host  # every interface: loopback too
        self.url = f"{'wss' if access.tls_cert else 'ws'}://{reach}:{self.api_port}"
        self._conf = tempfile.NamedTemporaryFile(  # noqa: SIM115 (kept open until stop())
            "w", suffix=".json", prefix="droneulator-run-"
        )
        json.dump(to_dict(config), self._conf)
        self._conf.flush()
        cmd = cli_command(["run", "--config", self._conf.name])
        cmd += ["--scene", config.scene, "--seed", str(config.seed), "--api-port", str(self.api_port)]
        cmd += list(args)
        self.log = RunLog(log)
        self._log_file: IO[str] | None = None
        if log is not None:
            log.parent.mkdir(parents=True, exist_ok=True)
            self._log_file = open(log, "a")  # noqa: SIM115 (closed in stop())
        preexec = _die_with_parent if die_with_parent and sys.platform.startswith("linux") else None
        self.proc = subprocess.Popen(
            cmd,
            stdout=self._log_file if self._log_file is not None else subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            preexec_fn=preexec,
            start_new_session=True,  # Ctrl-C reaches the launcher, which then stops the run itself
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self._pump: threading.Thread | None = None
        if self._log_file is None:
            self._pump = threading.Thread(target=self._read_output, daemon=True, name="run-log")
            self._pump.start()

    def _read_output(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.log._append(line)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def running(self) -> bool:
        return self.proc.poll() is None

    def client(self, timeout: float = 30.0) -> DroneulatorClient:
        """A new WebSocket client of this run (close it when done)."""
        access = self.config.access
        return DroneulatorClient(
            self.url, timeout=timeout, token=access.token, cafile=access.tls_ca or access.tls_cert
        )

    def wait_ready(self, timeout: float) -> None:
        """Return once the API answers ``ping``; :class:`LaunchError` if the run exits or ``timeout``
        seconds pass first."""
        deadline = time.monotonic() + timeout
        last: Exception | None = None
        while True:
            if self.proc.poll() is not None:
                raise LaunchError(self._failure(f"exited with code {self.proc.returncode} while starting"))
            try:
                with self.client(timeout=min(10.0, max(1.0, timeout))) as c:
                    c.ping()
                return
            except (OSError, WebSocketException, ConnectionLostError) as exc:
                last = exc  # refused, reset, a half-done handshake, or closed by a run that is exiting
            if time.monotonic() > deadline:
                raise LaunchError(self._failure(f"did not answer on {self.url} within {timeout:g} s: {last}"))
            time.sleep(0.2)

    def _failure(self, what: str) -> str:
        time.sleep(0.2)  # let the last lines of a dying process reach the log
        where = f" (log: {self.log.path})" if self.log.path is not None else ""
        tail = self.log.tail(30) or "(no output)"
        return f"droneulator run {what}{where}; last lines:\n  " + tail.replace("\n", "\n  ")

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGTERM, then SIGKILL to the whole process group after ``timeout`` s; the exit code."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        if self._pump is not None:
            self._pump.join(timeout=5.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        if self._log_file is not None and not self._log_file.closed:
            self._log_file.close()
        if not self._conf.closed:
            self._conf.close()
        return self.proc.returncode

    def __enter__(self) -> LaunchedRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def launch_run(
    config: SimConfig | None = None,
    args: Sequence[str] = (),
    *,
    log: str | Path | None = None,
    start_timeout: float = 90.0,
    die_with_parent: bool = True,
) -> LaunchedRun:
    """Start ``droneulator run`` with ``config`` (default: the defaults) plus extra command-line ``args``
    (``--realtime``, ``--set key=value``, ``--px4``...), on a free API port and Zenoh endpoint.

    The output goes to the file ``log`` (appended) or, without one, to memory (``run.log``). Returns
    once the API answers; use the result as a context manager to stop it. ``config`` is not modified.
    """
    args = [str(a) for a in args]
    for a in args:
        if any(a == r or a.startswith(f"{r}=") for r in _RESERVED):
            raise ValueError(f"launch_run sets {a.split('=')[0]} itself; put it in the config instead")
    cfg = copy.deepcopy(config) if config is not None else load_config()
    run = LaunchedRun(cfg, args, Path(log) if log is not None else None, die_with_parent)
    try:
        run.wait_ready(start_timeout)
    except BaseException:
        run.stop()
        raise
    return run
