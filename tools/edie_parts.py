"""Where a lane's Edie distance and time come from, against the simulator's truth: the Edie segments the
measures counted (and took back) in the lane's region, split by the truth vehicle under them, on its footprint
or above it (its own track, a duplicate of it at the same time, a vehicle of another lane, or none), and the
own tracks' distance against their vehicles' over the same steps."""

from __future__ import annotations

import csv
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from appliance.edie import clip_segments
from tools.simulate.vehicles import CLASS_DIMS

# A measured point is on a truth vehicle when it lies within this much of its front..rear span along the road
# (the near end tracked is a bumper, a bonnet or a roofline, projected a little beyond the body)
ON_VEHICLE_M = 2.0
# ... or above it: on the road-plane projection of its body up to its height (its roof seen further away)
IN_VIEW_SHARE = 0.95  # a truth vehicle this much visible is in view; less, partly hidden
MAX_HEIGHT_M = 4.5  # a class the simulator does not know is at most this tall
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
    above: list[float] = field(default_factory=lambda: [0.0, 0.0])  # own steps led by a part above the road

    @property
    def measured(self) -> tuple[float, float]:
        return sum(p[0] for p in self.parts.values()), sum(p[1] for p in self.parts.values())


def _truth_rows(vehicles_csv: str | Path) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """(sorted frame times, per frame index an array of rows: vehicle id, lane, front, rear, visible, x,
    height (its class's tallest))."""
    rows = []
    with open(vehicles_csv, newline="") as f:
        for r in csv.DictReader(f):
            a, b = float(r["y_front_m"]), float(r["y_rear_m"])
            h = CLASS_DIMS[r["class"]][2][1] if r["class"] in CLASS_DIMS else MAX_HEIGHT_M
            rows.append((float(r["t"]), int(r["vehicle_id"]), int(r["lane"]), a, b, float(r["visible_frac"]),
                         float(r["x_m"]), h))
    arr = np.array(rows, np.float64).reshape(-1, 8)
    times, idx = np.unique(arr[:, 0], return_inverse=True)
    order = np.argsort(idx, kind="stable")
    bounds = np.searchsorted(idx[order], np.arange(len(times) + 1))
    return times, {i: arr[order[bounds[i]:bounds[i + 1]], 1:] for i in range(len(times))}


def edie_parts(vehicles_csv: str | Path, segments: list[dict], regions: dict[int, tuple[float, float]],
               start_wall: float = 0.0, camera: tuple[float, float] | None = None) -> list[LaneParts]:
    """Per lane (regions: lane -> (y0, y1) of its Edie region): the truth's Edie distance and time, and the
    measured Edie segments' (as the measures added and took back: vehicle_id, lane, w0, w1, y0, y1, sign, x;
    wall times start_wall + capture time) split by part. With the camera (x across the road, height; its foot
    at y 0) a point may also lie above a vehicle."""
    times, at = _truth_rows(vehicles_csv)
    half_frame = 0.5 * float(np.median(np.diff(times))) if len(times) > 1 else 0.02
    out = {lane: LaneParts(lane) for lane in regions}
    front: dict[int, tuple[float, float]] = {}  # truth vehicle -> (t, y_front) at its previous frame
    moves = []  # (lane, t0, t1, y0, y1) of each truth vehicle's front between its frames
    for i, t in enumerate(times):
        for vid, lane, a, *_ in at[i]:
            prev = front.get(int(vid))
            front[int(vid)] = (t, a)
            if prev is not None and int(lane) in out:
                moves.append((lane, prev[0], t, prev[1], a))
    if moves:
        lanes, t0, t1, y0, y1 = np.array(moves).T
        ylo, yhi = (np.array([regions[int(ln)][j] for ln in lanes]) for j in (0, 1))
        ta, tb, dist = clip_segments(t0, t1, y0, y1, ylo, yhi)
        for lane, lp in out.items():
            m = lanes == lane
            lp.truth_d, lp.truth_t = float(dist[m].sum()), float((tb - ta)[m].sum())

    def frame(tq: float) -> int | None:
        k = int(np.clip(np.searchsorted(times, tq), 1, len(times) - 1)) if len(times) > 1 else 0
        k = k - 1 if abs(times[k - 1] - tq) < abs(times[k] - tq) else k
        return k if abs(times[k] - tq) <= half_frame else None

    def under(k: int | None, lane: int, y: float, x: float) -> tuple[np.ndarray | None, bool, bool]:
        """The truth row of lane's vehicle under a point (or, failing that, below it), whether that is above
        the vehicle's footprint, and whether another lane's vehicle is there instead."""
        if k is None:
            return None, False, False
        rows = at[k]
        lo, hi = np.minimum(rows[:, 2], rows[:, 3]), np.maximum(rows[:, 2], rows[:, 3])
        near_x = np.abs(rows[:, 5] - x) <= ON_VEHICLE_M
        for above in (False, True):
            if above:
                if camera is None:
                    break
                cx, ch = camera
                kmax = ch / np.maximum(ch - rows[:, 6], 0.5)  # its roof's height magnification
                hi = hi * kmax
                px = cx + (rows[:, 5] - cx) * kmax
                near_x = (x >= np.minimum(rows[:, 5], px) - ON_VEHICLE_M) & (x <= np.maximum(rows[:, 5], px)
                                                                              + ON_VEHICLE_M)
            along = (lo - ON_VEHICLE_M <= y) & (y <= hi + ON_VEHICLE_M)
            hit = along & (rows[:, 1] == lane)
            if hit.any():
                return rows[np.argmax(hit)], above, False
            if (along & near_x).any():
                return None, False, True
        return None, False, False

    # per lane and vehicle its steps: (d, dt, sign, truth row at the start, at the end, end frame, above it)
    steps: dict[tuple[int, int], list] = defaultdict(list)
    votes: dict[tuple[int, int], dict] = defaultdict(lambda: defaultdict(float))
    segments = [sg for sg in segments if int(sg["lane"]) in regions]
    if not segments:
        return [out[lane] for lane in sorted(out)]
    w0s, w1s, y0s, y1s = (np.array([float(sg[k]) for sg in segments]) for k in ("w0", "w1", "y0", "y1"))
    ylo, yhi = (np.array([regions[int(sg["lane"])][j] for sg in segments]) for j in (0, 1))
    clipped = zip(*clip_segments(w0s, w1s, y0s, y1s, ylo, yhi))
    for sg, w0, w1, y0, y1, (ta, tb, d) in zip(segments, w0s, w1s, y0s, y1s, clipped):
        lane = int(sg["lane"])
        if tb <= ta:
            continue
        sign = float(sg.get("sign", 1.0))
        x = sg.get("x")
        x = np.nan if x is None or x == "" else float(x)
        ya, yb = (y0 + (y1 - y0) * (w - w0) / (w1 - w0) for w in (ta, tb))
        ka, kb = frame(ta - start_wall), frame(tb - start_wall)
        ra, _, _ = under(ka, lane, ya, x)
        rb, up, other = under(kb, lane, yb, x)
        key = (lane, int(sg["vehicle_id"]))
        steps[key].append((d * sign, (tb - ta) * sign, sign, ra, rb, kb, up))
        if sign > 0:
            votes[key][int(rb[0]) if rb is not None else OTHER_LANE if other else None] += tb - ta
    covered: dict[tuple[int, int], dict] = defaultdict(dict)  # (lane, truth vehicle) -> {frame: measured one}
    # the longest first: a step of a vehicle's track is its own unless a longer track of that vehicle covered its
    # frame (a duplicate then: at the same time, not a track found again after a loss)
    for key in sorted(steps, key=lambda k: -sum(st[1] for st in steps[k])):
        lane, vid = key
        lp = out[lane]
        owner = max(votes[key], key=votes[key].get) if votes[key] else None
        shares: dict[str, float] = defaultdict(float)
        for d, dt, sign, ra, rb, kb, up in steps[key]:
            if owner is None:
                part = "no vehicle"
            elif owner == OTHER_LANE:
                part = "other lane"
            elif kb is not None and (covered[lane, owner].setdefault(kb, vid) if sign > 0
                                     else covered[lane, owner].get(kb, vid)) != vid:
                part = "duplicate"
            else:
                part = "own"
            p = lp.parts[part]
            p[0] += d
            p[1] += dt
            shares[part] += dt
            if part == "own" and up:
                lp.above[0] += d
                lp.above[1] += dt
            if part == "own" and sign > 0 and ra is not None and rb is not None \
                    and int(ra[0]) == owner == int(rb[0]):
                view = lp.own_vs_truth["in view" if rb[4] >= IN_VIEW_SHARE else "partly hidden"]
                view[0] += d
                view[1] += abs(rb[2] - ra[2])
        if shares:
            lp.parts[max(shares, key=shares.get)][2] += 1
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
        if lp.above[1] > 0:
            lines.append(f"    own steps led by a part above the road (not on its vehicle's footprint): "
                         f"{lp.above[0]:.0f} m {lp.above[1]:.0f} s {_kmh(*lp.above)}")
        lines.append("    own tracks' distance against their vehicles' over the same steps: " + ", ".join(
            f"{name} {_pct(m, tr)} of {tr:.0f} m" for name, (m, tr) in lp.own_vs_truth.items() if tr > 0))
    return "\n".join(lines)


def total_parts(lanes: list[LaneParts]) -> dict:
    """The lanes' (and scenes') parts summed: truth and part distances (m) and times (s), tracks, above."""
    tot: dict = {"truth": [sum(lp.truth_d for lp in lanes), sum(lp.truth_t for lp in lanes)],
                 "above": [sum(lp.above[0] for lp in lanes), sum(lp.above[1] for lp in lanes)]}
    for name in PARTS:
        tot[name] = [sum(lp.parts[name][i] for lp in lanes) for i in range(3)]
    return tot


def format_total(tot: dict, indent: str = "  ") -> str:
    """Each part's share of the truth's distance and time and its speed against the truth's."""
    td, tt = tot["truth"]
    if td <= 0 or tt <= 0:
        return f"{indent}no truth vehicle in the lanes' regions"
    v = td / tt
    md, mt = (sum(tot[p][i] for p in PARTS) for i in (0, 1))

    def speed(d: float, t: float) -> str:
        return f"speed {100.0 * (d / t / v - 1.0):+.1f} %" if t > 0 else "no speed"

    lines = [f"{indent}counted: distance {100.0 * (md / td - 1.0):+.1f} %, time {100.0 * (mt / tt - 1.0):+.1f} %, "
             f"{speed(md, mt)} (truth {td:.0f} m, {tt:.0f} s, {3.6 * v:.1f} km/h)"]
    for name in PARTS:
        d, t, n = tot[name]
        line = f"{indent}{name} ({n:.0f} tracks): {100.0 * d / td:.1f} % of the distance, " \
               f"{100.0 * t / tt:.1f} % of the time, {speed(d, t)}"
        if name == "own" and tot["above"][1] > 0:
            ad, at = tot["above"]
            line += f"; led by a part above the road {100.0 * ad / max(d, 1e-9):.1f} % of it, {speed(ad, at)}"
        lines.append(line)
    return "\n".join(lines)
