"""The suite's own machinery: a test marked ``alone`` waits for the other worker's test and keeps new
ones out while it runs (tests/conftest.py's reader-writer lock over ``flock``; separate opens of a file
conflict between threads as between processes)."""

from __future__ import annotations

import threading
import time
import uuid

import pytest
from conftest import _lock_base, _machine_share


def test_an_alone_test_waits_for_a_shared_one_and_keeps_the_next_out(monkeypatch: pytest.MonkeyPatch) -> None:
    # a lock of its own: under pytest-xdist this very test holds the suite's lock shared
    monkeypatch.setenv("DRONEULATOR_TEST_RUN", uuid.uuid4().hex)
    order: list[str] = []
    started = threading.Event()

    def shared(name: str, hold: float, ready: threading.Event | None = None) -> None:
        with _machine_share(False):
            order.append(f"{name} in")
            if ready is not None:
                ready.set()
            time.sleep(hold)
            order.append(f"{name} out")

    first = threading.Thread(target=shared, args=("first", 0.5, started))
    first.start()
    started.wait(5)
    with _machine_share(True):
        order.append("alone in")
        later = threading.Thread(target=shared, args=("later", 0.0))
        later.start()
        time.sleep(0.3)  # the later shared test is asking now, and must not get in
        order.append("alone out")
    first.join(5)
    later.join(5)
    assert order == ["first in", "first out", "alone in", "alone out", "later in", "later out"]
    for suffix in (".turnstile", ".share"):
        (_lock_base().parent / f"{_lock_base().name}{suffix}").unlink()
