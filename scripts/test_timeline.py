"""Where a test run's wall time went, from the timeline ``DRONEULATOR_TEST_TIMELINE=FILE`` writes
(tests/conftest.py): each pytest-xdist worker's busy time, its idle start (collection) and end, the time
``alone`` tests held the machine, and the files by time; with ``--plot PNG``, a chart of both workers.

    DRONEULATOR_TEST_TIMELINE=/tmp/tl.jsonl .venv/bin/python -m pytest -q
    .venv/bin/python scripts/test_timeline.py /tmp/tl.jsonl --plot /tmp/tl.png
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path


def load(path: Path) -> tuple[list[dict], dict[str, float]]:
    """The timeline's test lines and its session events (``start``, ``end``), times as seconds since the
    session's start."""
    tests, events = [], {}
    for number, raw in enumerate(path.read_text().splitlines(), 1):
        try:
            line = json.loads(raw)
        except json.JSONDecodeError as err:
            raise SystemExit(f"{path}:{number}: not a timeline line ({err})") from None
        if line.get("worker") == "session":
            events[line["event"]] = line["time"]
        else:
            tests.append(line)
    if not tests:
        raise SystemExit(f"{path}: no test in the timeline")
    zero = events.get("start", min(t["start"] for t in tests))
    for t in tests:
        t["start"] -= zero
        t["end"] -= zero
    return tests, {k: v - zero for k, v in events.items()}


def summary(tests: list[dict], events: dict[str, float]) -> str:
    end = events.get("end", max(t["end"] for t in tests))
    workers: dict[str, list[dict]] = defaultdict(list)
    for t in tests:
        workers[t["worker"]].append(t)
    out = [f"run: {end:.0f} s wall, {len(tests)} entries"]
    for name in sorted(workers):
        ts = sorted(workers[name], key=lambda t: t["start"])
        busy = sum(t["end"] - t["start"] for t in ts)
        alone = sum(t["end"] - t["start"] for t in ts if t.get("alone"))
        out.append(
            f"{name:>12}: first at {ts[0]['start']:6.1f} s, last done at {ts[-1]['end']:6.1f} s,"
            f" busy {busy:6.1f} s, idle between {ts[-1]['end'] - ts[0]['start'] - busy:5.1f} s,"
            f" alone tests {alone:5.1f} s"
        )
    files: dict[str, float] = defaultdict(float)
    for t in tests:
        if "::" in t["test"]:
            files[t["test"].split("::")[0]] += t["end"] - t["start"]
    out.append("files by time (s):")
    out += [f"  {s:7.1f}  {f}" for f, s in sorted(files.items(), key=lambda kv: -kv[1])[:15]]
    return "\n".join(out)


def file_durations(tests: list[dict]) -> dict[str, float]:
    """Each test file's time (its name: seconds, to 0.1 s), from its tests that are not ``alone`` (those
    run first as a unit of their own; a test that began while they ran counts from their end: it waited)."""
    alone_end = max((t["end"] for t in tests if t.get("alone")), default=float("-inf"))
    files: dict[str, float] = defaultdict(float)
    for t in tests:
        if "::" in t["test"] and not t.get("alone"):
            files[t["test"].split("::")[0].rsplit("/", 1)[-1]] += t["end"] - max(t["start"], alone_end)
    return {name: round(s, 1) for name, s in files.items()}


def plot(tests: list[dict], events: dict[str, float], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted({t["worker"] for t in tests})
    fig, ax = plt.subplots(figsize=(14, 1.0 + 0.7 * len(names)))
    files = sorted({t["test"].split("::")[0] for t in tests})
    colours = plt.get_cmap("tab20")
    for row, name in enumerate(names):
        for t in (t for t in tests if t["worker"] == name):
            colour = "black" if t.get("alone") else colours(files.index(t["test"].split("::")[0]) % 20)
            ax.barh(
                row, t["end"] - t["start"], left=t["start"], color=colour, edgecolor="white", linewidth=0.2
            )
            if t["end"] - t["start"] > 20:
                label = t["test"].split("::")[0].removeprefix("tests/").removesuffix(".py")
                ax.text(t["start"] + 1, row, label, va="center", fontsize=6, rotation=0, clip_on=True)
    if "end" in events:
        ax.axvline(events["end"], color="red", linewidth=0.8)
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("seconds since the run started (black: alone tests; red: the run's end)")
    ax.set_title("test run timeline")
    fig.tight_layout()
    fig.savefig(png, dpi=120)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("timeline", type=Path, help="the JSON-lines file DRONEULATOR_TEST_TIMELINE named")
    parser.add_argument("--plot", type=Path, metavar="PNG", help="also draw the workers' timelines to PNG")
    parser.add_argument(
        "--durations", type=Path, metavar="JSON",
        help="also write each test file's seconds (its alone tests left out) for tests/durations.json, the "
        "order in which the suite hands its files to pytest-xdist's workers (tests/conftest.py)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if not args.timeline.is_file():
        parser.error(f"{args.timeline}: no such file")
    tests, events = load(args.timeline)
    print(summary(tests, events))
    if args.durations:
        args.durations.write_text(json.dumps(file_durations(tests), indent=1, sort_keys=True) + "\n")
        print(f"durations: {args.durations}")
    if args.plot:
        plot(tests, events, args.plot)
        print(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
