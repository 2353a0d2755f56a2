"""Dataset sweeps: many captures (and reconstructions) or planning benchmarks, one job per scene, seed and
view count, as Ray tasks over a cluster or one after another in this process.

Each job writes one folder, ``<out>/<job name>/``: the job's ``config.json``, what its workflow writes
(a capture's COLMAP dataset and, with ``reconstruct``, the reconstruction and its ``report.json``; the
planning benchmark's ``planning.json`` and figure), and last ``job.json``, the job's summary. A job
whose ``job.json`` exists is done: a rerun of the same sweep skips it, so an interrupted sweep goes on
where it stopped. ``summary.csv`` and ``summary.json`` list every job at the end.

On Ray a job runs in a scratch folder on whichever node Ray places it, and its files come back to the
driver through Ray's object store, so the nodes need no shared file system. Each task asks Ray for
``cpus`` cores (a capture runs the simulator's three processes) and, when the cluster has GPUs, a share
of one (``gpus``) so the renderer and COLMAP get it.

With a :class:`~droneulator.runtime.zenoh_security.RouterLink` (``sweep --zenoh-router``) each job's
simulator links to that TLS router with mutual TLS, on the certificate files the settings carry: they are
written to a private temporary folder of the job's node for the job's lifetime, never into its output.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from droneulator.config import to_dict

if TYPE_CHECKING:
    from droneulator.runtime.zenoh_security import RouterLink

KINDS = ("capture", "plan")
#: the file that marks a job done (written last, atomically)
DONE = "job.json"


@dataclass(frozen=True)
class Job:
    """One run of a workflow: ``kind`` on ``scene`` with ``seed`` (and ``views``, for a capture)."""

    kind: str
    scene: str
    seed: int
    views: int | None = None

    @property
    def name(self) -> str:
        base = f"{self.scene}-seed{self.seed}"
        return base if self.views is None else f"{base}-views{self.views}"


@dataclass
class SweepSettings:
    """What every job of a sweep shares: the config file and ``--set`` overrides (capture settings such as
    ``capture.width=320`` among them), whether to reconstruct each capture, the planning benchmark's goals,
    and the TLS router every capture's simulator links to (``--zenoh-router``)."""

    config: str | None = None
    overrides: list[str] = field(default_factory=list)
    reconstruct: bool = False
    goals: list[int] | None = None
    router: RouterLink | None = None


def parse_seeds(tokens: Sequence[str]) -> list[int]:
    """``["0-3", "7"]`` -> ``[0, 1, 2, 3, 7]`` (ranges inclusive, order kept, no repeats)."""
    seeds: list[int] = []
    for token in tokens:
        lo, sep, hi = token.partition("-")
        try:
            values = range(int(lo), int(hi) + 1) if sep else [int(token)]
        except ValueError:
            raise ValueError(f"--seeds {token!r}: give seeds as N or A-B (e.g. 0-99)") from None
        if sep and int(hi) < int(lo):
            raise ValueError(f"--seeds {token!r}: the range ends before it starts")
        seeds += [s for s in values if s not in seeds]
    if not seeds or min(seeds) < 0:
        raise ValueError("--seeds: give at least one seed, none negative")
    return seeds


def make_jobs(kind: str, scenes: Sequence[str], seeds: Sequence[int], views: Sequence[int] = ()) -> list[Job]:
    """Every combination, scenes outermost; each scene name is checked before anything runs."""
    from droneulator.scenes import list_scenes

    if kind not in KINDS:
        raise ValueError(f"unknown sweep {kind!r}; available: {', '.join(KINDS)}")
    names = list_scenes()
    unknown = [s for s in scenes if s not in names]
    if unknown:
        raise ValueError(f"unknown scene(s) {', '.join(unknown)}; available: {', '.join(names)}")
    if kind == "capture":
        if not views or min(views) < 2:
            raise ValueError("--views: give at least one view count, each at least 2")
        return [Job(kind, s, seed, v) for s in scenes for seed in seeds for v in views]
    if views:
        raise ValueError("--views is a capture setting")
    return [Job(kind, s, seed) for s in scenes for seed in seeds]


def _config(job: Job, settings: SweepSettings, tls_dir: Path) -> Any:
    """The job's config; linked to ``settings.router`` with its carried files written in ``tls_dir``."""
    from droneulator.runtime import preflight

    cfg = preflight.load(settings.config, settings.overrides, scene=job.scene, seed=job.seed)
    if settings.router is not None:
        settings.router.apply(cfg.bridge, tls_dir)
    preflight.check_zenoh_tls(cfg)  # on the node the job runs on: its certificate files must be there too
    if job.kind == "capture":
        cfg.capture.views = job.views
        cfg.capture.__post_init__()
    return cfg


def _planning_script() -> Path:
    script = Path(__file__).resolve().parents[2] / "benchmarks" / "planning.py"
    if not script.is_file():
        raise FileNotFoundError(
            f"sweep plan runs the planning benchmark, {script}, which is in a source checkout of Droneulator "
            "(git clone), not in a wheel or the bundle"
        )
    return script


def run_job(job: Job, settings: SweepSettings, folder: Path) -> dict[str, Any]:
    """Run ``job`` into ``folder`` (created); returns its summary (without writing :data:`DONE`)."""
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="droneulator-tls-") as tls_dir:
        return _run_job(job, settings, folder, _config(job, settings, Path(tls_dir)))


def _run_job(job: Job, settings: SweepSettings, folder: Path, cfg: Any) -> dict[str, Any]:
    (folder / "config.json").write_text(json.dumps(to_dict(cfg), indent=2))
    t0 = time.perf_counter()
    summary: dict[str, Any] = {**asdict(job), "name": job.name}
    log_path = folder / "job.log"
    with log_path.open("a") as log_file:

        def log(line: str) -> None:
            log_file.write(line + "\n")
            log_file.flush()

        if job.kind == "capture":
            from droneulator.workflows.photogrammetry.capture import capture

            meta = capture(cfg, folder, progress=False, log=log)
            summary.update(views_captured=meta["views_captured"], complete=meta["complete"])
            summary["capture_wall_s"] = round(time.perf_counter() - t0, 2)
            if settings.reconstruct:
                from droneulator.workflows.photogrammetry.reconstruct import reconstruct

                report = reconstruct(folder, log=log)
                summary.update(
                    registered_images=report["registered_images"],
                    sparse_points=report["sparse_points"],
                    reprojection_px=round(report["mean_reprojection_error_px"], 4),
                )
        else:
            cmd = [sys.executable, str(_planning_script()), "--scene", job.scene, "--seed", str(job.seed)]
            cmd += ["--output", str(folder / "planning.json"), "--logs", str(folder / "logs")]
            if settings.goals:
                cmd += ["--goals", *map(str, settings.goals)]
            done = subprocess.run(cmd, stdout=log_file, stderr=subprocess.STDOUT, check=False)
            if done.returncode != 0:
                raise RuntimeError(f"the planning benchmark failed (exit {done.returncode}); see {log_path}")
            runs = json.loads((folder / "planning.json").read_text())["runs"]
            clearance = [r["min_clearance_m"] for r in runs if r.get("min_clearance_m") is not None]
            summary.update(
                goals=len(runs),
                reached=sum(bool(r.get("reached")) for r in runs),
                collisions=sum(int(r.get("collisions", 0)) for r in runs),
                min_clearance_m=round(min(clearance), 3) if clearance else None,
            )
    summary["wall_s"] = round(time.perf_counter() - t0, 2)
    summary["host"] = os.uname().nodename
    if settings.router is not None:
        summary["zenoh_router"] = settings.router.endpoint
    return summary


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _remote_job(job: Job, settings: SweepSettings, sweep_id: str) -> tuple[dict[str, Any], dict[str, bytes]]:
    """A Ray task: the job in a scratch folder of its node; returns the summary and every file. The
    folder is named after the sweep and the job, so what a cancelled run left is cleared when the job
    runs again."""
    scratch = Path(tempfile.gettempdir()) / "droneulator-sweep" / sweep_id / job.name
    shutil.rmtree(scratch, ignore_errors=True)
    try:
        summary = run_job(job, settings, scratch)
        return summary, _files(scratch)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _finish(folder: Path, summary: dict[str, Any], files: dict[str, bytes] | None = None) -> None:
    """Write the job's files (a Ray job's), then :data:`DONE` atomically: the job counts as done only
    once everything is in place."""
    for rel, data in (files or {}).items():
        path = folder / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    tmp = folder / (DONE + ".tmp")
    tmp.write_text(json.dumps(summary, indent=1))
    tmp.replace(folder / DONE)


def is_done(out: Path, job: Job) -> bool:
    return (out / job.name / DONE).is_file()


def _gpu_share(resources: dict[str, float], cpus: float) -> float:
    """Each job's share of the cluster's GPUs, so every CPU slot's job gets one share (0 without GPUs)."""
    gpus, total = resources.get("GPU", 0.0), resources.get("CPU", 0.0)
    if gpus <= 0 or total <= 0:
        return 0.0
    return min(1.0, math.floor(100 * gpus * cpus / total) / 100)


def sweep(
    jobs: Sequence[Job],
    settings: SweepSettings,
    out: Path,
    address: str | None = None,
    cpus: float = 2.0,
    gpus: float | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Run every job not done yet (on Ray at ``address``, else here, one after another); returns every
    job's summary (done before or now, and failures) and writes ``summary.csv``/``summary.json``.

    A failed job is reported (``status: failed`` and its error) and not marked done, so a rerun tries it
    again; the others go on. Ctrl-C stops the sweep: finished jobs stay done, running ones are cancelled.
    """
    from tqdm import tqdm

    if any(j.kind == "plan" for j in jobs) and (settings.config or settings.overrides or settings.router):
        raise ValueError(
            "sweep plan runs the planning benchmark's own configuration: no --config or --set, "
            "nor --zenoh-router"
        )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    todo = [j for j in jobs if not is_done(out, j)]
    skipped = len(jobs) - len(todo)
    log(f"sweep: {len(jobs)} job(s), {skipped} already done in {out}, {len(todo)} to run")
    results: dict[str, dict[str, Any]] = {}
    bar = tqdm(total=len(jobs), initial=skipped, unit="job", disable=not progress)

    def record(job: Job, summary: dict[str, Any]) -> None:
        results[job.name] = summary
        bar.update(1)
        state = summary.get("status", "done")
        log(f"{job.name}: {state}" + (f" ({summary['error']})" if state == "failed" else ""))

    def failed(job: Job, err: BaseException) -> dict[str, Any]:
        return {**asdict(job), "name": job.name, "status": "failed", "error": f"{type(err).__name__}: {err}"}

    try:
        if address is None:
            for job in todo:
                folder = out / job.name
                try:
                    summary = {**run_job(job, settings, folder), "status": "done"}
                except Exception as err:  # noqa: BLE001  (one failed job must not end the sweep)
                    record(job, failed(job, err))
                    continue
                _finish(folder, summary)
                record(job, summary)
        elif todo:
            _on_ray(todo, settings, out, address, cpus, gpus, record, failed)
    finally:
        bar.close()
        rows = [json.loads((out / j.name / DONE).read_text()) if is_done(out, j) else results.get(j.name)
                for j in jobs]  # fmt: skip
        rows = [r for r in rows if r is not None]
        write_summary(out, rows)
    return rows


def _on_ray(
    todo: list[Job],
    settings: SweepSettings,
    out: Path,
    address: str,
    cpus: float,
    gpus: float | None,
    record: Callable[[Job, dict[str, Any]], None],
    failed: Callable[[Job, BaseException], dict[str, Any]],
) -> None:
    from droneulator.runtime.cluster import connect

    with connect(address) as ray:
        share = _gpu_share(ray.cluster_resources(), cpus) if gpus is None else gpus
        task = ray.remote(num_cpus=cpus, num_gpus=share, max_retries=0)(_remote_job)
        sweep_id = hashlib.sha1(str(out.resolve()).encode()).hexdigest()[:12]
        pending = {task.remote(job, settings, sweep_id): job for job in todo}
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                job = pending.pop(ready[0])
                try:
                    summary, files = ray.get(ready[0])
                except Exception as err:  # noqa: BLE001  (a task's error, re-raised by Ray)
                    record(job, failed(job, getattr(err, "cause", None) or err))
                    continue
                summary["status"] = "done"
                folder = out / job.name
                if folder.exists():
                    shutil.rmtree(folder)  # what a cancelled run of this job left
                _finish(folder, summary, files)
                record(job, summary)
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)


#: the summary table's columns, when a job has them
COLUMNS = (
    "name", "status", "host", "wall_s", "views_captured", "registered_images", "sparse_points",
    "reprojection_px", "goals", "reached", "collisions", "min_clearance_m", "error",
)  # fmt: skip


def write_summary(out: Path, rows: list[dict[str, Any]]) -> str:
    """``summary.json``, ``summary.csv`` and the table as text (returned)."""
    (out / "summary.json").write_text(json.dumps(rows, indent=1))
    cols = [c for c in COLUMNS if any(c in r for r in rows)]
    with (out / "summary.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    cells = [[str(r.get(c, "")) for c in cols] for r in rows]
    widths = [max([len(c)] + [len(row[i]) for row in cells]) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths, strict=True))]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join(lines)
