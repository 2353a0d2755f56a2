"""``droneulator run``: start the dynamics server, the render server and the bridge as child
processes and keep them running.

Crash policy: the dynamics server owns the flight, so if it dies the run stops with its error.
If the render server or the bridge dies, its last error lines are reported and it is restarted
(at most ``runtime.max_restarts`` times); the dynamics server keeps the flight state, and in
lockstep the clock waits for the new instance, which first redoes the frames its predecessor
left unfinished. Ctrl-C / SIGTERM stop every child within 2 s; children also get SIGTERM from the
kernel if the supervisor itself is killed (``PR_SET_PDEATHSIG``), so no process is orphaned.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import json
import logging
import os
import secrets
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from droneulator.config import SimConfig, to_dict
from droneulator.logs import say
from droneulator.runtime.ipc import ENV_ADDRESS, ENV_AUTHKEY, ENV_CONFIG, ENV_RING, ENV_ZENOH, FrameRing
from droneulator.runtime.spawn import child_command

log = logging.getLogger("droneulator.run")

CHILDREN = {
    "dynamics": "droneulator.runtime.dynamics_server",
    "render": "droneulator.runtime.render_server",
    "bridge": "droneulator.runtime.bridge",
}
STOP_GRACE_S = 1.5


def _die_with_parent() -> None:
    """Runs in the child before exec: receive SIGTERM when the supervisor dies."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


@dataclass
class Child:
    name: str
    module: str
    proc: subprocess.Popen | None = None
    restarts: int = 0
    pump: threading.Thread | None = None
    tail: collections.deque = field(default_factory=lambda: collections.deque(maxlen=20))


class Supervisor:
    def __init__(self, cfg: SimConfig, echo: bool = True) -> None:
        self.cfg = cfg
        self.echo = echo
        self.tmp = tempfile.TemporaryDirectory(prefix="droneulator-")
        self.address = str(Path(self.tmp.name) / "hub.sock")
        #: the dynamics server's Zenoh session listens here for the bridge (private to this run)
        self.zenoh_endpoint = f"unixsock-stream/{Path(self.tmp.name) / 'zenoh.sock'}"
        self.authkey = secrets.token_hex(16)
        self.ring = FrameRing(FrameRing.new_name(), cfg.camera_rigs(), cfg.runtime.frame_slots, create=True)
        self.children = {n: Child(n, m) for n, m in CHILDREN.items()}
        self.stop_requested = threading.Event()
        self.failure: str | None = None
        #: the dynamics server's output while it starts: echoed once it is ready, summarised if it fails
        self._held: list[str] | None = None
        self._echo_lock = threading.Lock()

    def _env(self) -> dict[str, str]:
        return {
            **os.environ,
            ENV_ADDRESS: self.address,
            ENV_AUTHKEY: self.authkey,
            ENV_RING: self.ring.shm.name,
            ENV_ZENOH: self.zenoh_endpoint,
            ENV_CONFIG: json.dumps(to_dict(self.cfg)),
            "PYTHONUNBUFFERED": "1",
        }

    def _spawn(self, child: Child) -> None:
        child.proc = subprocess.Popen(
            child_command(child.module),
            env=self._env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            preexec_fn=_die_with_parent,
            start_new_session=True,
        )
        child.pump = threading.Thread(target=self._pump, args=(child, child.proc), daemon=True)
        child.pump.start()
        log.info("started %s server (pid %d)", child.name, child.proc.pid)

    def _pump(self, child: Child, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            line = line.rstrip()
            child.tail.append(line)
            with self._echo_lock:
                if child.name == "dynamics" and self._held is not None:
                    self._held.append(line)
                elif self.echo:
                    say(f"[{child.name}] {line}")

    def start(self, on_hub_ready: Callable[[], None] | None = None) -> None:
        """Start the dynamics server, then (once it listens) the render server and the bridge.

        ``on_hub_ready`` runs in between, e.g. to subscribe a recorder: the dynamics server's Zenoh session
        is up, and in lockstep its clock has not started (it waits for the render server and the bridge).
        Raises RuntimeError with a one-line message if the dynamics server exits while starting; its
        output so far (a traceback, say) goes to a log file the message names, not to the terminal."""
        self._held = []
        dynamics = self.children["dynamics"]
        self._spawn(dynamics)
        deadline = time.monotonic() + 30
        while not os.path.exists(self.address):  # the hub socket exists once the server is listening
            proc = dynamics.proc
            if proc is not None and proc.poll() is not None:
                self.failure = self._start_failure(dynamics, proc)
                raise RuntimeError(self.failure)
            if time.monotonic() > deadline:
                self._release_held()
                raise RuntimeError("dynamics server did not start within 30 s")
            time.sleep(0.05)
        self._release_held()
        if on_hub_ready is not None:
            on_hub_ready()
        self._spawn(self.children["render"])
        self._spawn(self.children["bridge"])

    def _release_held(self) -> None:
        with self._echo_lock:
            held, self._held = self._held or [], None
            if self.echo:
                for line in held:
                    say(f"[dynamics] {line}")

    def _start_failure(self, child: Child, proc: subprocess.Popen) -> str:
        """One line for a dynamics server that exited while starting: its exit status and last line."""
        if child.pump is not None:
            child.pump.join(2.0)  # the rest of its output
        with self._echo_lock:
            held, self._held = self._held or [], None
        code = proc.returncode
        status = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
        last = next((ln.strip() for ln in reversed(held) if ln.strip()), "no output")
        log_path = Path(tempfile.gettempdir(), f"droneulator-dynamics-{proc.pid}.log")
        try:
            log_path.write_text("\n".join(held) + "\n")
            full = f"; its full output: {log_path}"
        except OSError:
            full = ""
        return f"the dynamics server stopped while starting ({status}): {last}{full}"

    def _fail(self, child: Child) -> None:
        code = child.proc.returncode if child.proc else None
        tail = "\n    ".join(list(child.tail)[-10:])
        self.failure = f"{child.name} server exited with code {code}:\n    {tail}"

    def watch_once(self) -> bool:
        """Check the children; restart or fail. Returns False once the run must stop."""
        for child in self.children.values():
            if child.proc is None or child.proc.poll() is None:
                continue
            self._fail(child)
            if child.name == "dynamics" or child.restarts >= self.cfg.runtime.max_restarts:
                log.error("%s; stopping the run", self.failure)
                return False
            child.restarts += 1
            log.error(
                "%s\nrestarting it (%d/%d); the flight state is kept by the dynamics server",
                self.failure,
                child.restarts,
                self.cfg.runtime.max_restarts,
            )
            self.failure = None
            self._spawn(child)
        return True

    def wait(self, duration: float | None = None) -> int:
        """Supervise until Ctrl-C/SIGTERM, ``duration`` wall seconds, or a fatal crash; then stop."""
        end = time.monotonic() + duration if duration else None
        try:
            while not self.stop_requested.is_set():
                if not self.watch_once():
                    return 1
                if end is not None and time.monotonic() > end:
                    return 0
                self.stop_requested.wait(0.1)
            return 0
        finally:
            self.stop()

    def stop(self) -> None:
        """SIGTERM the dynamics server first (so the others' exit is not reported as a crash), then the
        render server and the bridge; SIGKILL whatever is left after the grace period."""
        deadline = time.monotonic() + STOP_GRACE_S
        for name in ("dynamics", "render", "bridge"):
            p = self.children[name].proc
            if p is None or p.poll() is not None:
                continue
            p.send_signal(signal.SIGTERM)
            if name == "dynamics":
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(0.5)
        for child in self.children.values():
            p = child.proc
            if p is None:
                continue
            try:
                p.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.ring.close()
        self.tmp.cleanup()

    def install_signal_handlers(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: self.stop_requested.set())
