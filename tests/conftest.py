"""Suite-wide guards: a test that fails before closing its Zenoh session must not hang the whole run,
and a test marked ``alone`` has the machine to itself while pytest-xdist's other worker waits.

zenoh-python serves a session on non-daemon Python threads that live until the session is closed,
so a session left open (say by an assertion that fires before its ``close()``) makes the interpreter
wait for ever after the last test, and CI times out instead of reporting the failure. Every session
opened while the suite runs is tracked here and closed when the suite ends; any other non-daemon
thread still alive then is named, and the run exits without waiting for it, as a failure.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from xdist.scheduler import LoadFileScheduling

# Bytecode is cached while the suite runs even where the environment says not to (this project's machines
# set PYTHONDONTWRITEBYTECODE=1): each xdist worker otherwise re-rewrites every test module's asserts and
# every process a test starts compiles the package from source again. A worker's collection took 15 to 18 s
# without the cache and 7 s with it (2-core x86-64, 2026-12-01). ``__pycache__`` is ignored by git.
sys.dont_write_bytecode = False
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

_open = zenoh.open
_sessions: list[zenoh.Session] = []
_exit_status = 0


def _tracked_open(*args, **kwargs) -> zenoh.Session:
    session = _open(*args, **kwargs)
    _sessions[:] = [s for s in _sessions if not s.is_closed()]
    _sessions.append(session)
    return session


zenoh.open = _tracked_open


def _is_xdist_worker(config: pytest.Config) -> bool:
    return hasattr(config, "workerinput")


def pytest_configure(config: pytest.Config) -> None:
    """Name this test run once (pytest-xdist's workers inherit the name): its bundle build is shared."""
    if not _is_xdist_worker(config):
        os.environ["DRONEULATOR_TEST_RUN"] = uuid.uuid4().hex
        _log_session("start")


def _log_session(event: str, bundle: Path | None = None) -> None:
    """The run's start and end on the timeline (``_log_timeline``), from the process that owns the run; at
    the end, when the bundle was built in the background, its build's start and end too."""
    path = os.environ.get("DRONEULATOR_TEST_TIMELINE")
    if not path:
        return
    lines = [{"worker": "session", "event": event, "time": time.time()}]
    if bundle is not None and (bundle / "rc").exists():  # the build's pid file is written at its start
        start, end = (bundle / "pid").stat().st_mtime, (bundle / "rc").stat().st_mtime
        lines.append({"worker": "bundle build", "test": "scripts/package.sh", "start": start, "end": end})
    with open(path, "a") as log:
        log.writelines(json.dumps(line) + "\n" for line in lines)


def _lock_base() -> Path:
    return Path(tempfile.gettempdir()) / f"droneulator-tests-{os.environ['DRONEULATOR_TEST_RUN']}"


@contextlib.contextmanager
def _machine_share(alone: bool) -> Iterator[None]:
    """Hold the machine shared (every test) or alone (a test marked ``alone``) across pytest-xdist's
    workers: a reader-writer lock of two ``flock`` files. A test that wants it alone takes the turnstile
    first, so the other worker cannot start test after test ahead of it, then waits for that worker's
    current test to end."""
    base = _lock_base()
    with open(f"{base}.turnstile", "a") as turnstile, open(f"{base}.share", "a") as share:
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        try:
            fcntl.flock(share, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            if not alone:
                fcntl.flock(turnstile, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(share, fcntl.LOCK_UN)
            if alone:
                fcntl.flock(turnstile, fcntl.LOCK_UN)


def _is_alone(item: pytest.Item | None) -> bool:
    return item is not None and item.get_closest_marker("alone") is not None


#: the machine held alone past a test because the next test on this worker is ``alone`` too
_held: list[contextlib.ExitStack] = []


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Under pytest-xdist, a test marked ``alone`` (a check of wall-clock timing: pacing, rate limits,
    a link's gaps) runs, set-up and tear-down included, while the other worker runs nothing; the rest
    share the two cores. The ``alone`` tests run one after another on one worker (``_AloneFirst``), which
    holds the machine from the first to the last of them: the other worker's current test is waited for
    once, not once each. In one process there is nothing to wait for."""
    start = time.time()
    if not _is_xdist_worker(item.config):
        yield
        _log_timeline(item, start)
        return
    if _held:
        share = _held.pop()  # held alone since the test before
    else:
        share = contextlib.ExitStack()
        share.enter_context(_machine_share(_is_alone(item)))
    try:
        yield
    finally:
        if _is_alone(item) and _is_alone(nextitem):
            _held.append(share)
        else:
            share.close()
    _log_timeline(item, start)


def _log_timeline(item: pytest.Item, start: float) -> None:
    """With ``DRONEULATOR_TEST_TIMELINE=FILE``, append one JSON line a test (worker, test, start, end,
    wall-clock seconds since the epoch, waiting for the machine share included): where the two workers
    idle or wait on each other, ``python scripts/test_timeline.py FILE`` draws it."""
    path = os.environ.get("DRONEULATOR_TEST_TIMELINE")
    if not path:
        return
    worker = getattr(item.config, "workerinput", {}).get("workerid", "main")
    line = json.dumps({"worker": worker, "test": item.nodeid, "start": start, "end": time.time(),
                       "alone": _is_alone(item)})  # fmt: skip
    with open(path, "a") as log:  # one short append a test: whole lines from both workers
        log.write(line + "\n")


#: each test file's time in a quiet full run on two cores (seconds; ``scripts/test_timeline.py
#: --durations``): the order in which pytest-xdist hands the files out. A file not listed counts 5 s.
DURATIONS = Path(__file__).with_name("durations.json")


def pytest_collection_modifyitems(
    session: pytest.Session, config: pytest.Config, items: list[pytest.Item]
) -> None:
    """Under pytest-xdist the ``alone`` tests come first, then the files longest first (``DURATIONS``;
    a file's tests keep their order): with ``--dist loadfile --no-loadscope-reorder`` the files go out in
    this order, so the two workers end together instead of one waiting out the other's last long file
    (60 s seen with the files in name order). The bundle's file is one of the longer ones: its build,
    started in the background when the tests are collected, is done long before it comes up. Each worker
    writes the ``alone`` tests' ids for the controller's scheduler (``_AloneFirst``), which sends them to
    one worker as the first unit of work. In one process the order stays as collected."""
    if not _is_xdist_worker(config):
        return
    weight = json.loads(DURATIONS.read_text())
    items.sort(key=lambda item: (not _is_alone(item), -weight.get(item.path.name, 5.0)))
    alone = Path(f"{_lock_base()}.alone")
    part = alone.with_name(f"{alone.name}.{os.getpid()}")
    part.write_text(json.dumps([item.nodeid for item in items if _is_alone(item)]))
    part.replace(alone)  # both workers write the same list, each whole


class _AloneFirst(LoadFileScheduling):
    """pytest-xdist's ``--dist loadfile`` (a file's tests on one worker, the files in collection order),
    except that the ``alone`` tests make one unit of their own, first: one worker runs them back to back
    at the start while the other waits once (``pytest_runtest_protocol``), instead of each of them
    waiting for whatever long test the other worker had started (up to 40 s each, seen in a timeline)."""

    _alone: frozenset[str] | None = None

    def _split_scope(self, nodeid: str) -> str:
        if self._alone is None:  # the workers wrote it when they collected, before any scheduling
            path = Path(f"{_lock_base()}.alone")
            self._alone = frozenset(json.loads(path.read_text())) if path.exists() else frozenset()
        return "alone" if nodeid in self._alone else super()._split_scope(nodeid)


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> LoadFileScheduling | None:
    return _AloneFirst(config, log) if config.getvalue("dist") == "loadfile" else None


def pytest_collection_finish(session: pytest.Session) -> None:
    """When the bundle's tests are among those to run, start building the bundle now, in the background
    (tests/test_bundle.py; once per run, whichever worker gets here first): PyInstaller's minutes then
    overlap the tests that come before them."""
    if session.config.option.collectonly:
        return
    if any("bundle" in getattr(item, "fixturenames", ()) for item in session.items):
        from test_bundle import start_build

        start_build()


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    global _exit_status
    _exit_status = int(exitstatus)
    if not _is_xdist_worker(session.config):
        from test_bundle import build_root, stop_build  # the run's owner stops and removes its bundle build

        _log_session("end", build_root())

        stop_build()
        for suffix in (".turnstile", ".share", ".alone"):
            Path(f"{_lock_base()}{suffix}").unlink(missing_ok=True)
    left = [s for s in _sessions if not s.is_closed()]
    for s in left:
        s.close()
    if left:
        print(f"\nconftest: closed {len(left)} Zenoh session(s) a test left open", file=sys.stderr)


def pytest_unconfigure(config: pytest.Config) -> None:
    start = time.time()
    deadline = time.monotonic() + 10.0
    waited = [t for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon]
    for t in waited:
        t.join(max(0.0, deadline - time.monotonic()))
    stuck = [t.name for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon]
    if path := os.environ.get("DRONEULATOR_TEST_TIMELINE"):
        worker = getattr(config, "workerinput", {}).get("workerid", "main")
        line = {"worker": worker, "test": f"(end: joined {[t.name for t in waited]})", "start": start,
                "end": time.time(), "alone": False}  # fmt: skip
        with open(path, "a") as log:
            log.write(json.dumps(line) + "\n")
    if stuck:
        print(f"\nconftest: non-daemon threads still running after the suite: {stuck}", file=sys.stderr)
        sys.stderr.flush()
        sys.stdout.flush()
        os._exit(_exit_status or 1)
