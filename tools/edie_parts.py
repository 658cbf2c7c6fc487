"""Where a lane's Edie distance and time come from, against the simulator's truth: each measured vehicle's
trajectory steps in the lane's region, split by the truth vehicle under them (its own track, a duplicate of
it, a vehicle of another lane, or none), and the own tracks' distance against their vehicles' over the same
steps."""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# A measured point is on a truth vehicle when it lies within this much of its front..rear span along the road
# (the near end tracked is a bumper, a bonnet or a roofline, projected a little beyond the body)
ON_VEHICLE_M = 2.0
IN_VIEW_SHARE = 0.95  # a truth vehicle this much visible is in view; less, partly hidden
PARTS = ("own", "duplicate", "other lane", "no vehicle")
OTHER_LANE = -1  # owner of a step on no vehicle of its lane but on one of another lane


@dataclass
class LaneParts:
    lane: int
    truth_d: float = 0.0  # Edie distance (m) and time (s) of the truth's vehicles over the whole scene
    truth_t: float = 0.0
    parts: dict[str, list[float]] = field(default_factory=lambda: {p: [0.0, 0.0, 0] for p in PARTS})
    # own tracks' distance against their vehicles' over the same steps: view -> [measured m, truth m]
    own_vs_truth: dict[str, list[float]] = field(default_factory=lambda: {"in view": [0.0, 0.0],
                                                                          "partly hidden": [0.0, 0.0]})

    @property
    def measured(self) -> tuple[float, float]:
        return sum(p[0] for p in self.parts.values()), sum(p[1] for p in self.parts.values())


def _truth_rows(vehicles_csv: str | Path) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """(sorted frame times, per frame index an array of rows: vehicle id, lane, front, rear, visible, x)."""
    rows = []
    with open(vehicles_csv, newline="") as f:
        for r in csv.DictReader(f):
            a, b = float(r["y_front_m"]), float(r["y_rear_m"])
            rows.append((float(r["t"]), int(r["vehicle_id"]), int(r["lane"]), a, b, float(r["visible_frac"]),
                         float(r["x_m"])))
    arr = np.array(rows, np.float64).reshape(-1, 7)
    times, idx = np.unique(arr[:, 0], return_inverse=True)
    order = np.argsort(idx, kind="stable")
    bounds = np.searchsorted(idx[order], np.arange(len(times) + 1))
    return times, {i: arr[order[bounds[i]:bounds[i + 1]], 1:] for i in range(len(times))}


def edie_parts(vehicles_csv: str | Path, measured: list[dict], regions: dict[int, tuple[float, float]]
               ) -> list[LaneParts]:
    """Per lane (regions: lane -> (y0, y1) of its Edie region): the truth's Edie distance and time, and the
    measured vehicles' (records with lane and trajectory [[t, x, y], ...] in capture time) split by part."""
    times, at = _truth_rows(vehicles_csv)
    half_frame = 0.5 * float(np.median(np.diff(times))) if len(times) > 1 else 0.02
    out = {lane: LaneParts(lane) for lane in regions}
    front: dict[int, tuple[float, float]] = {}  # truth vehicle -> (t, y_front) at its previous frame
    for i, t in enumerate(times):
        for vid, lane, a, *_ in at[i]:
            prev = front.get(int(vid))
            front[int(vid)] = (t, a)
            lp = out.get(int(lane))
            if prev is None or lp is None:
                continue
            y0, y1 = regions[int(lane)]
            if y0 <= 0.5 * (prev[1] + a) <= y1:
                lp.truth_d += abs(a - prev[1])
                lp.truth_t += t - prev[0]

    def frame(tq: float) -> int | None:
        k = int(np.clip(np.searchsorted(times, tq), 1, len(times) - 1)) if len(times) > 1 else 0
        k = k - 1 if abs(times[k - 1] - tq) < abs(times[k] - tq) else k
        return k if abs(times[k] - tq) <= half_frame else None

    def under(k: int | None, lane: int, y: float, x: float) -> tuple[np.ndarray | None, bool]:
        """The truth row of lane's vehicle under a point, and whether another lane's vehicle is there."""
        if k is None:
            return None, False
        rows = at[k]
        lo, hi = np.minimum(rows[:, 2], rows[:, 3]), np.maximum(rows[:, 2], rows[:, 3])
        along = (lo - ON_VEHICLE_M <= y) & (y <= hi + ON_VEHICLE_M)
        hit = along & (rows[:, 1] == lane)
        if hit.any():
            return rows[np.argmax(hit)], False
        return None, bool((along & (np.abs(rows[:, 5] - x) <= ON_VEHICLE_M)).any())

    tracks: dict[int, list] = defaultdict(list)  # lane -> [(owner, steps)], steps: (d, dt, truth rows a, b)
    for rec in measured:
        traj = rec.get("trajectory")
        if isinstance(traj, str):
            traj = json.loads(traj)
        lane = rec.get("lane")
        if not traj or lane is None or int(lane) not in regions:
            continue
        lane = int(lane)
        y0, y1 = regions[lane]
        steps, votes = [], defaultdict(int)
        for (ta, _, ya), (tb, xb, yb) in zip(traj, traj[1:]):
            if not y0 <= 0.5 * (ya + yb) <= y1 or tb <= ta:
                continue
            ra, _ = under(frame(ta), lane, ya, xb)
            rb, other = under(frame(tb), lane, yb, xb)
            votes[int(rb[0]) if rb is not None else OTHER_LANE if other else None] += 1
            steps.append((abs(yb - ya), tb - ta, ra, rb))
        if steps:
            tracks[lane].append((max(votes, key=votes.get), steps))
    for lane, lst in tracks.items():
        lp = out[lane]
        longest: dict[int, float] = {}
        for owner, steps in lst:
            if owner is not None and owner != OTHER_LANE:
                longest[owner] = max(longest.get(owner, 0.0), sum(s[1] for s in steps))
        own_taken: set[int] = set()
        for owner, steps in lst:
            dur = sum(s[1] for s in steps)
            if owner is None:
                part = "no vehicle"
            elif owner == OTHER_LANE:
                part = "other lane"
            elif owner not in own_taken and dur == longest[owner]:
                part = "own"
                own_taken.add(owner)
            else:
                part = "duplicate"
            p = lp.parts[part]
            p[0] += sum(s[0] for s in steps)
            p[1] += dur
            p[2] += 1
            if part != "own":
                continue
            for d, _, ra, rb in steps:
                if ra is None or rb is None or int(ra[0]) != owner or int(rb[0]) != owner:
                    continue
                view = lp.own_vs_truth["in view" if rb[4] >= IN_VIEW_SHARE else "partly hidden"]
                view[0] += d
                view[1] += abs(rb[2] - ra[2])
    return [out[lane] for lane in sorted(out)]


def _pct(a: float, b: float) -> str:
    return f"{100.0 * (a / b - 1.0):+.1f} %" if b > 0 else "n/a"


def _kmh(d: float, t: float) -> str:
    return f"{3.6 * d / t:.1f} km/h" if t > 0 else "n/a"


def format_edie_parts(lanes: list[LaneParts]) -> str:
    lines = []
    for lp in lanes:
        md, mt = lp.measured
        lines.append(f"  lane {lp.lane}: truth {lp.truth_d:.0f} m {lp.truth_t:.0f} s {_kmh(lp.truth_d, lp.truth_t)}; "
                     f"measured {md:.0f} m {mt:.0f} s {_kmh(md, mt)} (distance {_pct(md, lp.truth_d)}, "
                     f"time {_pct(mt, lp.truth_t)})")
        lines.append("    " + "; ".join(f"{name} {n} tracks {d:.0f} m {t:.0f} s {_kmh(d, t)}"
                                        for name, (d, t, n) in lp.parts.items() if n))
        lines.append("    own tracks' distance against their vehicles' over the same steps: " + ", ".join(
            f"{name} {_pct(m, tr)} of {tr:.0f} m" for name, (m, tr) in lp.own_vs_truth.items() if tr > 0))
    return "\n".join(lines)
