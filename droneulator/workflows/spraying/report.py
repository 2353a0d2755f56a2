"""The spray run's outputs: JSON and figures (matplotlib, Agg).

* ``deposit_map.png``: the ground deposit (uL/cm^2, log scale) with the target area and the plants,
  coloured by their dose per leaf area;
* ``canopy_dose.png``: each plant's dose by lower, middle and upper third;
* ``drift_curve.png``: the drift curve (% of the applied volume per area against distance downwind),
  beside the JKI/Rautmann basic drift values (90th percentile) of field crops, vines and fruit;
* ``trial_<kind>.png``: a trial's collector deposits, swath CV against lane spacing and its drift curve.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from droneulator.spray.cloud import SprayCloud
from droneulator.spray.trials import CV_LIMIT, UL_CM2, swath_cv

#: JKI basic drift values (Rautmann et al. 2001, 90th percentile, one application), % of the applied dose
#: at 1, 3, 5, 10, 15, 20, 30, 40, 50 m (None: not tabulated), as the ``pfm`` R package transcribes them
JKI_DRIFT: dict[str, list[float | None]] = {
    "field crops": [2.77, 0.95, 0.57, 0.29, 0.20, 0.15, 0.10, 0.07, 0.06],
    "vines, late": [None, 8.02, 3.62, 1.23, 0.65, 0.42, 0.22, 0.14, 0.10],
    "fruit, late": [None, 15.73, 8.41, 3.60, 1.81, 1.09, 0.54, 0.32, 0.22],
}
JKI_DISTANCES = [1, 3, 5, 10, 15, 20, 30, 40, 50]


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_json(path: Path, data: dict[str, Any]) -> None:
    path.write_text(json.dumps(data, indent=1))


def _jki(ax: Any) -> None:
    for name, values in JKI_DRIFT.items():
        pts = [(d, v) for d, v in zip(JKI_DISTANCES, values, strict=True) if v is not None]
        ax.plot(*zip(*pts, strict=True), "--", marker=".", alpha=0.6, label=f"JKI {name}")


def drift_figure(path: Path, drift: dict[str, list[float]], title: str) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    values = np.maximum(np.asarray(drift["drift_percent"]), 1e-4)
    ax.semilogy(drift["distance_m"], values, "o-", color="k", label="Droneulator")
    _jki(ax)
    ax.set_xlabel("distance downwind of the sprayed area's edge (m)")
    ax.set_ylabel("ground deposit (% of applied per area)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def mission_figures(
    out: Path, report: dict[str, Any], cloud: SprayCloud, target: tuple[float, ...]
) -> list[Path]:
    """The deposit map, the canopy doses and the drift curve of a mission."""
    plt = _plt()
    from matplotlib.colors import LogNorm

    written = []
    g = cloud.ground_deposit() / cloud.ground_cell**2 * UL_CM2
    x0, y0, c = cloud.ground_origin[0], cloud.ground_origin[1], cloud.ground_cell
    extent = (x0, x0 + g.shape[0] * c, y0, y0 + g.shape[1] * c)
    fig, ax = plt.subplots(figsize=(8, 6))
    positive = g[g > 0]
    if positive.size:
        lo = max(float(np.percentile(positive, 1)), 1e-6)
        im = ax.imshow(np.where(g > 0, g, np.nan).T, origin="lower", extent=extent,
                       norm=LogNorm(vmin=lo, vmax=float(positive.max())), cmap="viridis")  # fmt: skip
        fig.colorbar(im, ax=ax, label="ground deposit (uL/cm^2)")
    tx0, tx1, ty0, ty1 = target
    ax.plot([tx0, tx1, tx1, tx0, tx0], [ty0, ty0, ty1, ty1, ty0], "w--", lw=1, label="target area")
    plants = report["plants"]
    if plants["count"]:
        p = np.asarray(plants["positions"])
        sc = ax.scatter(p[:, 0], p[:, 1], c=plants["dose_ul_per_cm2_leaf"], cmap="autumn", s=12,
                        edgecolors="k", linewidths=0.3)  # fmt: skip
        fig.colorbar(sc, ax=ax, label="plant dose (uL/cm^2 of leaf)")
    ax.set_xlim(tx0 - 15, tx1 + 30)
    ax.set_ylim(ty0 - 15, ty1 + 15)
    ax.set_xlabel("x (m, east)")
    ax.set_ylabel("y (m, north)")
    ax.set_title(
        f"deposit: {report['sprayed_l']:.2f} L sprayed, {100 * report['canopy_share']:.0f} % on the canopy"
    )
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    written.append(out / "deposit_map.png")
    fig.savefig(written[-1], dpi=120)
    plt.close(fig)
    if plants["count"]:
        dose = np.asarray(plants["dose_ul"])
        fig, ax = plt.subplots(figsize=(8, 3.5))
        idx = np.arange(len(dose))
        bottom = np.zeros(len(dose))
        for k, name in enumerate(("lower", "middle", "upper")):
            ax.bar(idx, dose[:, k], bottom=bottom, width=1.0, label=f"{name} third")
            bottom += dose[:, k]
        ax.set_xlabel("plant")
        ax.set_ylabel("dose (uL)")
        ax.set_title(f"canopy dose per plant (CV {100 * plants['cv']:.0f} %)")
        ax.legend(fontsize=7)
        fig.tight_layout()
        written.append(out / "canopy_dose.png")
        fig.savefig(written[-1], dpi=120)
        plt.close(fig)
    written.append(out / "drift_curve.png")
    drift_figure(written[-1], report["drift"], "drift downwind of the sprayed area")
    return written


def trial_figure(path: Path, trial: dict[str, Any]) -> None:
    """A trial's collectors (share of peak), its swath CV against lane spacing, and its drift curve."""
    plt = _plt()
    xs, prof = np.asarray(trial["profile_x_m"]), np.asarray(trial["profile_ul_cm2"])
    fig, axes = plt.subplots(1, 3 if "drift" in trial else 2, figsize=(13, 3.8))
    ax = axes[0]
    floor = max(float(prof.max()) * 1e-5, 1e-12)
    ax.semilogy(xs, np.maximum(prof, floor), color="0.6", lw=0.8, label="deposit across the line")
    ax.semilogy(trial["collectors_m"], np.maximum(trial["deposit_ul_cm2"], floor), "o", color="k",
                label="collectors")  # fmt: skip
    ax.set_xlim(-8, 52)
    ax.set_ylim(floor, None)
    ax.set_xlabel("distance downwind of the flight line (m)")
    ax.set_ylabel("deposit (uL/cm^2)")
    ax.legend(fontsize=7)
    ax.set_title(f"{trial['kind']} trial")
    ax = axes[1]
    spacing = np.arange(0.5, 20.01, 0.25)
    ax.plot(spacing, [100 * swath_cv(xs, prof, float(s)) for s in spacing], color="k")
    ax.axhline(100 * CV_LIMIT, color="r", ls="--", label="CV 25 %")
    if trial.get("effective_swath_m"):
        ax.axvline(
            trial["effective_swath_m"],
            color="b",
            ls=":",
            label=f"effective swath {trial['effective_swath_m']:.2f} m",
        )
    ax.set_ylim(0, 120)
    ax.set_xlabel("lane spacing (m)")
    ax.set_ylabel("CV of the overlapped deposit (%)")
    ax.legend(fontsize=7)
    if "drift" in trial:
        ax = axes[2]
        values = np.maximum(np.asarray(trial["drift"]["drift_percent"]), 1e-4)
        ax.semilogy(trial["drift"]["distance_m"], values, "o-", color="k", label="Droneulator field")
        _jki(ax)
        ax.set_xlabel("distance downwind of the field's edge (m)")
        ax.set_ylabel("% of applied per area")
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
