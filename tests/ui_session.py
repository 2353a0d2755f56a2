"""A real ``droneulator run`` with the browser UI and a real Chromium page on it, for the UI tests that
fly a run from the page (tests/test_ui_fleet.py, tests/test_ui_spray.py)."""

from __future__ import annotations

import contextlib
import shutil
import time
from collections.abc import Iterator, Sequence
from typing import Any

import pytest

from droneulator.config import SimConfig
from droneulator.runtime.launch import LaunchedRun, free_port, launch_run

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def wait(predicate: Any, timeout: float, what: str, log: Any) -> Any:
    """``predicate()``'s first truthy value within ``timeout`` s, or an AssertionError with the run's log."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := predicate():
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}\n" + log.tail(25))


@contextlib.contextmanager
def ui_page(
    cfg: SimConfig, args: Sequence[str], ready: str
) -> Iterator[tuple[LaunchedRun, Any, Any, list[str]]]:
    """The run of ``cfg`` (``args`` and ``--ui-port``), its API client, a 1500x1000 Chromium page on the
    UI's flight view once the JavaScript ``ready`` holds, and the page's errors as they come (its log
    printed when the test fails)."""
    playwright = pytest.importorskip("playwright.sync_api")
    ui_port = free_port()
    run = launch_run(cfg, [*args, "--ui-port", str(ui_port)], start_timeout=120)
    client = None
    try:
        client = run.client()
        wait(lambda: any(line.startswith("UI: http") for line in run.log.lines()), 60, "the UI", run.log)
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1500, "height": 1000})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(f"http://127.0.0.1:{ui_port}/#fly")
            page.wait_for_function(ready, timeout=60000)
            yield run, client, page, errors
            browser.close()
    except BaseException:
        print(run.log.tail(40))
        raise
    finally:
        if client is not None:
            client.close()
        run.stop()
