"""scripts/test_timeline.py reads the timeline tests/conftest.py writes: the workers' times, the files'
times with the ``alone`` tests' wait taken out, and a clear error for a file that is not a timeline."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "test_timeline.py"


def _module():
    spec = importlib.util.spec_from_file_location("test_timeline_script_under_test", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_summary_and_durations_of_a_two_worker_timeline(tmp_path: Path, capsys) -> None:
    t0 = 1_000.0

    def test(worker: str, name: str, start: float, end: float, alone: bool = False) -> dict:
        return {"worker": worker, "test": name, "start": t0 + start, "end": t0 + end, "alone": alone}

    lines = [
        {"worker": "session", "event": "start", "time": t0},
        test("gw0", "tests/test_a.py::test_x", 2, 12, alone=True),
        test("gw1", "tests/test_b.py::test_y", 2, 15),
        test("gw1", "tests/test_b.py::test_z", 15, 20),
        test("gw0", "tests/test_a.py::test_w", 12, 21),
        test("gw0", "(end: joined [])", 21, 21),
        {"worker": "session", "event": "end", "time": t0 + 22},
    ]
    timeline, out = tmp_path / "tl.jsonl", tmp_path / "durations.json"
    timeline.write_text("".join(json.dumps(line) + "\n" for line in lines))
    assert _module().main([str(timeline), "--durations", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "run: 22 s wall" in printed and "alone tests  10.0 s" in printed
    # test_y waited for the alone test until t0 + 12: 3 s of its own, then test_z's 5
    assert json.loads(out.read_text()) == {"test_a.py": 9.0, "test_b.py": 8.0}


def test_a_file_that_is_not_a_timeline_is_one_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "tl.jsonl"
    bad.write_text("not json\n")
    with pytest.raises(SystemExit, match="tl.jsonl:1: not a timeline line"):
        _module().main([str(bad)])
