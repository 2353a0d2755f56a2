"""``droneulator score``: a reconstruction measured against the true tree its capture recorded."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "score",
        help="score a reconstruction against the true tree the capture recorded: accuracy (median, p90) "
        "and completeness, sparse and dense, tree and ground",
    )
    p.add_argument("dataset", help="a folder written by `droneulator capture` and `droneulator reconstruct`")
    p.add_argument("--spacing", type=float, default=0.02, help="true-surface sample spacing (m)")
    p.add_argument("--radius", type=float, default=0.05, help="completeness radius (m)")
    p.set_defaults(func=cmd_score)


def cmd_score(args: argparse.Namespace) -> int:
    from droneulator.workflows.photogrammetry.reconstruct import report_markdown
    from droneulator.workflows.photogrammetry.score import score, score_markdown

    dataset = Path(args.dataset)
    result = score(dataset, spacing=args.spacing, radius=args.radius)
    report_path = dataset / "report.json"
    if report_path.is_file():  # keep report.md whole: the reconstruction's figures and this score
        report = json.loads(report_path.read_text())
        report["score"] = result
        report_path.write_text(json.dumps(report, indent=1))
        (dataset / "report.md").write_text(report_markdown(report))
    print(score_markdown(result))
    return 0
