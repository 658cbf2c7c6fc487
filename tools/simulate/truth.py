"""Exact ground truth from the continuous (piecewise-linear) trajectories: count crossings, loop
actuations and Edie flow/density/speed per lane and period, plus the CSV writers."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

START_WALL = 1767225600.0  # 2026-01-01T00:00:00Z, a multiple of every period length

AGGREGATE_FIELDS = [
    "lane", "period_start", "period_s", "count", "flow_vph", "density_vpkm", "speed_kmh",
    "time_mean_speed_kmh", "occupancy_pct", "speed85_kmh", "headway_s", "class_counts", "partial", "quality",
]
LOOP_FIELDS = ["loop_id", "channel", "lane", "vehicle_id", "t_on", "t_off", "wall_on", "wall_off", "speed_kmh", "length_m"]
VEHICLE_FIELDS = [
    "frame", "t", "vehicle_id", "class", "lane", "x_m", "y_front_m", "y_rear_m", "y_centre_m", "speed_mps",
    "accel_mps2", "length_m", "bbox_x0", "bbox_y0", "bbox_x1", "bbox_y1", "visible_frac",
]


@dataclass
class TruthLane:
    id: int
    direction: int
    region: tuple[float, float]
    count_y: float


@dataclass
class TruthLoop:
    id: str
    channel: int
    lane: int
    y0: float
    length: float


@dataclass
class StepState:
    """Vehicles at both ends of one simulation step (same order in every array)."""

    ids: np.ndarray
    lanes: np.ndarray  # lane id (by lateral position) at the end of the step
    lanes_prev: np.ndarray
    direction: np.ndarray  # -1 / +1
    yf0: np.ndarray  # front Y at the start of the step
    yf1: np.ndarray
    length: np.ndarray
    classes: list[str]
    # Y extent of the body at the end / start of the step when it differs from length (a vehicle on a curve)
    span: np.ndarray | None = None
    span_prev: np.ndarray | None = None


def length_class(length: float, bounds: tuple[float, ...] = (2.1, 6.1, 13.1),
                 names: tuple[str, ...] = ("motorcycle", "small", "medium", "large")) -> str:
    """The name of length's class: names[i] for bounds[i-1] <= length < bounds[i]."""
    return names[int(np.searchsorted(np.asarray(bounds), length, side="right"))]


@dataclass
class TruthAccumulator:
    lanes: list[TruthLane]
    loops: list[TruthLoop]
    period_s: float = 300.0
    start_wall: float = START_WALL
    crossings: list[tuple] = field(default_factory=list)  # (lane, vehicle_id, t, speed_mps, length)
    loop_events: list[dict] = field(default_factory=list)
    edie: dict = field(default_factory=dict)  # (lane, period index) -> [distance m, time s]
    _open: dict = field(default_factory=dict)  # (loop index, vehicle id) -> t_on
    t_first: float | None = None
    t_last: float = 0.0

    def _period(self, t: float) -> int:
        return int(math.floor((self.start_wall + t) / self.period_s + 1e-9))

    def step(self, t0: float, t1: float, st: StepState) -> None:
        if self.t_first is None:
            self.t_first = t0
        self.t_last = t1
        dt = t1 - t0
        if dt <= 0 or len(st.ids) == 0:
            return
        dy = st.yf1 - st.yf0
        speed = np.abs(dy) / dt
        moving = dy != 0
        safe_dy = np.where(moving, dy, 1.0)
        # count crossings of the front point
        for ln in self.lanes:
            sel = (st.lanes == ln.id) & moving
            if ln.direction < 0:
                hit = sel & (st.yf0 > ln.count_y) & (st.yf1 <= ln.count_y)
            else:
                hit = sel & (st.yf0 < ln.count_y) & (st.yf1 >= ln.count_y)
            for i in np.nonzero(hit)[0]:
                tc = t0 + (ln.count_y - st.yf0[i]) / safe_dy[i] * dt
                self.crossings.append((ln.id, int(st.ids[i]), tc, float(speed[i]), float(st.length[i]), st.classes[i]))
        # Edie: time and distance of the front point inside each lane's region, split at period boundaries
        p0, p1 = self._period(t0), self._period(t1 - 1e-9)
        cuts = [0.0]
        for p in range(p0 + 1, p1 + 1):
            cuts.append((p * self.period_s - self.start_wall - t0) / dt)
        cuts.append(1.0)
        for ln in self.lanes:
            sel = st.lanes == ln.id
            if not sel.any():
                continue
            a, b = ln.region
            y0, d = st.yf0[sel], dy[sel]
            mv = d != 0
            dd = np.where(mv, d, 1.0)
            ta, tb = (a - y0) / dd, (b - y0) / dd
            lo = np.where(mv, np.minimum(ta, tb), np.where((y0 >= a) & (y0 <= b), 0.0, 1.0))
            hi = np.where(mv, np.maximum(ta, tb), np.where((y0 >= a) & (y0 <= b), 1.0, 0.0))
            for k in range(len(cuts) - 1):
                l2, h2 = np.maximum(lo, cuts[k]), np.minimum(hi, cuts[k + 1])
                frac = np.clip(h2 - l2, 0.0, None)
                if frac.any():
                    acc = self.edie.setdefault((ln.id, p0 + k), [0.0, 0.0])
                    acc[0] += float(np.sum(frac * np.abs(d)))
                    acc[1] += float(np.sum(frac) * dt)
        # loops: presence of the vehicle body [lo, hi] over the loop span, in the loop's lane
        span1 = st.length if st.span is None else st.span
        span0 = span1 if st.span_prev is None else st.span_prev
        for li, lp in enumerate(self.loops):
            ya, yb = lp.y0, lp.y0 + lp.length
            lo0 = np.where(st.direction < 0, st.yf0, st.yf0 - span0)
            lo1 = np.where(st.direction < 0, st.yf1, st.yf1 - span1)
            hi0, hi1 = lo0 + span0, lo1 + span1
            on0 = (st.lanes_prev == lp.lane) & (lo0 < yb) & (hi0 > ya)
            on1 = (st.lanes == lp.lane) & (lo1 < yb) & (hi1 > ya)
            for i in np.nonzero(on1 & ~on0)[0]:
                if st.direction[i] < 0:  # moving down: the front (lo) enters at yb
                    tau = (yb - lo0[i]) / (lo1[i] - lo0[i]) if lo1[i] != lo0[i] else 1.0
                else:
                    tau = (ya - hi0[i]) / (hi1[i] - hi0[i]) if hi1[i] != hi0[i] else 1.0
                if not 0.0 <= tau <= 1.0:  # entered sideways (lane change)
                    tau = 1.0
                self._open[(li, int(st.ids[i]))] = t0 + tau * dt
            for i in np.nonzero(on0 & ~on1)[0]:
                t_on = self._open.pop((li, int(st.ids[i])), None)
                if t_on is None:
                    continue
                if st.direction[i] < 0:  # the rear (hi) leaves at ya
                    tau = (ya - hi0[i]) / (hi1[i] - hi0[i]) if hi1[i] != hi0[i] else 0.0
                else:
                    tau = (yb - lo0[i]) / (lo1[i] - lo0[i]) if lo1[i] != lo0[i] else 0.0
                if not 0.0 <= tau <= 1.0:
                    tau = 0.0
                t_off = t0 + tau * dt
                dur = t_off - t_on
                sp = (lp.length + span1[i]) / dur * 3.6 if dur > 0 else None
                self.loop_events.append(dict(
                    loop_id=lp.id, channel=lp.channel, lane=lp.lane, vehicle_id=int(st.ids[i]),
                    t_on=round(t_on, 6), t_off=round(t_off, 6),
                    wall_on=round(self.start_wall + t_on, 6), wall_off=round(self.start_wall + t_off, 6),
                    speed_kmh=None if sp is None else round(float(sp), 4), length_m=round(float(st.length[i]), 4),
                ))

    def aggregates(self) -> list[dict]:
        """One row per lane and period (LaneAggregate fields); the first/last period may be partial."""
        if self.t_first is None:
            return []
        t_start, t_end = self.t_first, self.t_last
        rows = []
        first_loop = {}
        for lp in sorted(self.loops, key=lambda q: q.channel):
            first_loop.setdefault(lp.lane, lp.id)
        for p in range(self._period(t_start), self._period(t_end - 1e-9) + 1):
            ps_wall = p * self.period_s
            a, b = ps_wall - self.start_wall, ps_wall - self.start_wall + self.period_s
            cov0, cov1 = max(a, t_start), min(b, t_end)
            covered = cov1 - cov0
            if covered <= 0:
                continue
            partial = covered < self.period_s - 1e-6
            for ln in self.lanes:
                cr = [c for c in self.crossings if c[0] == ln.id and a <= c[2] < b]
                times = sorted(c[2] for c in cr)
                speeds = np.array([c[3] * 3.6 for c in cr])
                d_m, t_s = self.edie.get((ln.id, p), [0.0, 0.0])
                area_kmh = (ln.region[1] - ln.region[0]) / 1000.0 * covered / 3600.0
                q = d_m / 1000.0 / area_kmh
                k = t_s / 3600.0 / area_kmh
                v = (d_m / 1000.0) / (t_s / 3600.0) if t_s > 0 else None
                occ = None
                if ln.id in first_loop:
                    # with the vehicles still on the loop at the end (standing in a queue, their actuation open)
                    spans = [(e["t_on"], e["t_off"]) for e in self.loop_events if e["loop_id"] == first_loop[ln.id]]
                    spans += [(t_on, t_end) for (li, _), t_on in self._open.items()
                              if self.loops[li].id == first_loop[ln.id]]
                    on = sum(max(0.0, min(t_off, cov1) - max(t_on, cov0)) for t_on, t_off in spans)
                    occ = 100.0 * on / covered
                classes: dict[str, int] = {}
                for c in cr:
                    name = length_class(c[4])
                    classes[name] = classes.get(name, 0) + 1
                rows.append(dict(
                    lane=ln.id, period_start=ps_wall, period_s=self.period_s, count=len(cr),
                    flow_vph=q, density_vpkm=k, speed_kmh=v,
                    time_mean_speed_kmh=float(speeds.mean()) if len(speeds) else None,
                    occupancy_pct=occ,
                    speed85_kmh=float(np.percentile(speeds, 85)) if len(speeds) else None,
                    headway_s=float(np.mean(np.diff(times))) if len(times) > 1 else None,
                    class_counts=classes, partial=partial, quality=0,
                ))
        return rows


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, dict):
        return json.dumps(v, sort_keys=True)
    if isinstance(v, (float, np.floating)):
        return repr(round(float(v), 6))
    if isinstance(v, np.integer):
        return str(int(v))
    return str(v)


def write_csv(path: Path, fields: list[str], rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(fields)
        for r in rows:
            w.writerow([_fmt(r[k]) for k in fields])


def read_aggregates(path: Path) -> list[dict]:
    """aggregates.csv back as dicts with numbers, None for empty, class_counts as a dict."""
    out = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            d: dict = {}
            for k, v in r.items():
                if k == "class_counts":
                    d[k] = json.loads(v) if v else {}
                elif k == "partial":
                    d[k] = v == "true"
                elif v == "":
                    d[k] = None
                elif k in ("lane", "count", "quality"):
                    d[k] = int(v)
                else:
                    d[k] = float(v)
            out.append(d)
    return out


def read_loop_events(path: Path) -> list:
    """loop_events.csv back as appliance LoopEvent objects."""
    from appliance.types import LoopEvent

    out = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            out.append(LoopEvent(
                loop_id=r["loop_id"], channel=int(r["channel"]), lane=int(r["lane"]),
                t_on=float(r["t_on"]), t_off=float(r["t_off"]), wall_on=float(r["wall_on"]),
                wall_off=float(r["wall_off"]), speed_kmh=float(r["speed_kmh"]) if r["speed_kmh"] else None,
                length_m=float(r["length_m"]) if r["length_m"] else None, vehicle_id=int(r["vehicle_id"]),
            ))
    return out


def read_vehicles(path: Path) -> np.ndarray:
    """vehicles.csv as a NumPy structured array (class as a short string)."""
    dtype = [(name, "U10" if name == "class" else ("i8" if name in ("frame", "vehicle_id", "lane") else "f8"))
             for name in VEHICLE_FIELDS]
    return np.genfromtxt(path, delimiter=",", names=True, dtype=dtype, encoding="utf-8", ndmin=1)
