"""benchmarks/ab.py: every figure of two versions' JSON compared by medians, runs alternating."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("ab", ROOT / "benchmarks/ab.py")
assert spec is not None and spec.loader is not None
ab = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ab)


def test_flatten_keeps_every_number_by_its_path_and_no_booleans() -> None:
    flat = ab.flatten({"a": {"b": 2, "ok": True}, "rows": [{"c": 1.5}, {"c": 3}], "name": "x"})
    assert flat == {"a.b": 2.0, "rows.0.c": 1.5, "rows.1.c": 3.0}


def test_compare_takes_medians_and_their_ratio_over_figures_in_every_run() -> None:
    old = [{"fps": 10.0, "x": 1.0}, {"fps": 30.0}, {"fps": 20.0}]
    new = [{"fps": 44.0}, {"fps": 40.0}, {"fps": 42.0}]
    assert ab.compare(old, new) == {"fps": {"old": 20.0, "new": 42.0, "ratio": pytest.approx(2.1)}}


def test_runs_alternate_in_each_checkout_and_refuse_a_command_without_the_json_slot(tmp_path: Path) -> None:
    bench = "import json, sys, droneulator as d; json.dump({'n': len(d.__file__)}, open(sys.argv[1], 'w'))"
    out = tmp_path / "ab.json"
    cmd = [sys.executable, str(ROOT / "benchmarks/ab.py"), "--old", str(ROOT), "--rounds", "2"]
    cmd += ["--out", str(out)]
    r = subprocess.run([*cmd, "--", sys.executable, "-c", bench, "{json}"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    report = json.loads(out.read_text())
    assert len(report["runs"]["old"]) == len(report["runs"]["new"]) == 2
    assert report["comparison"]["n"]["ratio"] == 1.0
    bad = subprocess.run([*cmd, "--", sys.executable, "-c", "pass"], capture_output=True, text=True)
    assert bad.returncode == 2 and "{json}" in bad.stderr
