"""Evaluation plots (matplotlib Agg): Table-1 error distribution, Fig. 7 scatter, Fig. 6 time-space."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

BANDS = (2.5, 5.0, 10.0, 15.0, 20.0, 25.0)
MEASURES = (("flow", "flow_vph", "flow q (veh/h)"), ("density", "density_vpkm", "density k (veh/km)"),
            ("speed", "speed_kmh", "space-mean speed v (km/h)"))


def error_distribution(errors: dict[str, list[float]], png: str) -> None:
    """Share of samples within each error band, per measure (the paper's Table 1 as bars)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    width = 0.8 / max(len(errors), 1)
    for i, (name, e) in enumerate(errors.items()):
        a = np.abs(np.asarray(e, dtype=float))
        shares = [100.0 * np.mean(a <= b) if len(a) else 0.0 for b in BANDS]
        ax.bar(np.arange(len(BANDS)) + i * width, shares, width, label=f"{name} (n={len(a)})")
    ax.set_xticks(np.arange(len(BANDS)) + width * (len(errors) - 1) / 2, [f"≤{b}%" for b in BANDS])
    ax.set_ylabel("samples within band (%)")
    ax.set_ylim(0, 105)
    ax.legend()
    ax.set_title("Error distribution of period measures")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def scatter_periods(pairs: list[tuple[dict, dict]], png: str) -> None:
    """Measured against true q, k, v per lane-period, with the y = x line (like the paper's Fig. 7)."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    for ax, (_, col, label) in zip(axes, MEASURES):
        pts = np.array([(t[col], r[col]) for t, r in pairs if t.get(col) is not None and r.get(col) is not None],
                       dtype=float).reshape(-1, 2)
        lanes = [t["lane"] for t, r in pairs if t.get(col) is not None and r.get(col) is not None]
        for lane in sorted(set(lanes)):
            m = np.array(lanes) == lane
            ax.scatter(pts[m, 0], pts[m, 1], s=14, label=f"lane {lane}")
        hi = float(pts.max()) * 1.05 if len(pts) else 1.0
        ax.plot([0, hi], [0, hi], "k-", lw=0.8)
        ax.set_xlim(0, hi); ax.set_ylim(0, hi)
        ax.set_xlabel(f"true {label}"); ax.set_ylabel(f"measured {label}")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def time_space(vehicles_csv: str | Path, crossings: list[dict], png: str, start_wall: float = 0.0,
               max_vehicles: int = 3000, measured: list[dict] | None = None) -> None:
    """Front trajectories (t, Y) per lane from the truth (grey) and measured (red, when the results
    hold vehicle trajectories), with the measured count-line crossings (like the paper's Fig. 6)."""
    lanes: dict[int, dict[int, list[tuple[float, float]]]] = {}
    with open(vehicles_csv, newline="") as f:
        for row in csv.DictReader(f):
            lane, vid = int(row["lane"]), int(row["vehicle_id"])
            tr = lanes.setdefault(lane, {})
            if vid in tr or len(tr) < max_vehicles:
                tr.setdefault(vid, []).append((float(row["t"]), float(row["y_front_m"])))
    ids = sorted(lanes)
    fig, axes = plt.subplots(len(ids), 1, figsize=(11, 3.2 * max(len(ids), 1)), squeeze=False)
    for ax, lane in zip(axes[:, 0], ids):
        for traj in lanes[lane].values():
            a = np.array(traj)
            ax.plot(a[:, 0], a[:, 1], "-", lw=0.6, color="0.3")
        for v in measured or []:
            traj = v.get("trajectory")
            if isinstance(traj, str):
                traj = json.loads(traj)
            if traj and int(v.get("lane") or 0) == lane:
                a = np.asarray(traj, dtype=float)
                ax.plot(a[:, 0], a[:, 2], "-", lw=0.9, color="tab:red", alpha=0.8)
        cr = [c for c in crossings if int(c["lane"]) == lane]
        if cr:
            t = np.array([float(c["wall"]) - start_wall for c in cr])
            y = np.array([float(c.get("y", np.nan)) if c.get("y") is not None else np.nan for c in cr])
            ax.plot(t, np.where(np.isnan(y), ax.get_ylim()[0], y), "r|", ms=10, label="measured crossings")
            ax.legend(fontsize=8, loc="upper right")
        ax.set_title(f"lane {lane}")
        ax.set_xlabel("time (s)"); ax.set_ylabel("Y along road (m)")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
