"""Edie's generalised flow, density and space-mean speed over a lane region x a period."""

# For region A = [y0, y1] x [period]: d(A) total distance and t(A) total time of one point fixed on each
# vehicle inside A (an approaching vehicle's front; a receding one's front as first reported, carried on with
# its rear: see measures._Track.edie_ahead); q = d/|A|, k = t/|A|, v = d/t (reported in veh/h, veh/km, km/h).

from __future__ import annotations

import numpy as np

from appliance.periods import period_start


def clip_segments(
    t0: np.ndarray, t1: np.ndarray, y0: np.ndarray, y1: np.ndarray, ylo: np.ndarray, yhi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parts of straight trajectory segments (t0,y0)->(t1,y1) inside ylo <= y <= yhi.

    Returns (ta, tb, dist): the time interval inside the band and the distance covered in it.
    Segments that miss the band get ta == tb and dist 0.
    """
    t0, t1, y0, y1 = (np.asarray(a, dtype=np.float64) for a in (t0, t1, y0, y1))
    dy = y1 - y0
    moving = np.abs(dy) > 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        sa = np.where(moving, (ylo - y0) / dy, -np.inf)
        sb = np.where(moving, (yhi - y0) / dy, np.inf)
    lo = np.maximum(0.0, np.minimum(sa, sb))
    hi = np.minimum(1.0, np.maximum(sa, sb))
    inside_still = (~moving) & (y0 >= ylo) & (y0 <= yhi)
    lo = np.where(moving, lo, np.where(inside_still, 0.0, 1.0))
    hi = np.where(moving, hi, np.where(inside_still, 1.0, 0.0))
    frac = np.maximum(hi - lo, 0.0)
    dt = t1 - t0
    ta = t0 + lo * dt
    tb = np.where(frac > 0, t0 + hi * dt, ta)
    return ta, tb, frac * np.abs(dy)


def back_to_entry(t0: float, y0: float, entry: float, sign: int, speed: float, t_min: float
                  ) -> tuple[float, float] | None:
    """Where and when a vehicle first seen at (t0, y0), travelling in direction ``sign`` at ``speed`` (m/s),
    crossed its region's entry: (time, position), or None when it was first seen there or beyond, or at the
    start of the observation t_min. Never before t_min: one already inside the region then starts there."""
    gap = (y0 - entry) * sign
    if gap <= 0.0 or t0 - t_min <= 1e-6:
        return None
    t_entry = t0 - gap / speed
    if t_entry < t_min:
        return t_min, y0 - sign * speed * (t0 - t_min)
    return t_entry, entry


def edie_qkv(dist_m: float, time_s: float, length_m: float, period_s: float) -> tuple[float, float, float | None]:
    """(q veh/h, k veh/km, v km/h or None) from Edie's d(A), t(A) over a region length x period."""
    area = length_m * period_s  # m*s
    q = dist_m / area * 3600.0
    k = time_s / area * 1000.0
    v = dist_m / time_s * 3.6 if time_s > 0 else None
    return q, k, v


class EdieAccumulator:
    """d(A) and t(A) per lane and period, fed with trajectory segments of the front point."""

    def __init__(self, lane_ids: list[int], regions: dict[int, tuple[float, float]], period_s: float) -> None:
        self.lane_ids = list(lane_ids)
        self.index = {lane: i for i, lane in enumerate(self.lane_ids)}
        self.ylo = np.array([regions[lane][0] for lane in self.lane_ids])
        self.yhi = np.array([regions[lane][1] for lane in self.lane_ids])
        self.period_s = float(period_s)
        self.sums: dict[float, np.ndarray] = {}  # period start -> (2, n_lanes): distance, time
        self.closed_until = -np.inf  # end of the last period taken: what lies before it is dropped

    def _bucket(self, p: float) -> np.ndarray:
        if p not in self.sums:
            self.sums[p] = np.zeros((2, len(self.lane_ids)))
        return self.sums[p]

    def add(self, lanes: np.ndarray, w0: np.ndarray, w1: np.ndarray, y0: np.ndarray, y1: np.ndarray,
            sign: float = 1.0) -> None:
        """Add segments (wall times w0->w1, front y0->y1) each in lane ``lanes[i]`` (lane ids); sign -1
        takes back segments added before."""
        if len(lanes) == 0:
            return
        li = np.array([self.index[int(x)] for x in lanes])
        ta, tb, dist = clip_segments(w0, w1, y0, y1, self.ylo[li], self.yhi[li])
        # a backfilled or carried-on part in a period already reported is not added (it would make a
        # bucket nobody takes); a segment straddling the close keeps its part after it
        late = ta < self.closed_until
        if np.any(late):
            cut = np.clip((self.closed_until - ta) / np.maximum(tb - ta, 1e-12), 0.0, 1.0)
            dist = np.where(late, dist * (1.0 - cut), dist)
            ta = np.where(late, np.minimum(self.closed_until, tb), ta)
        keep = tb > ta
        if not np.any(keep):
            return
        li, ta, tb, dist = li[keep], ta[keep], tb[keep], dist[keep] * sign
        pa = np.floor(ta / self.period_s) * self.period_s
        pb = np.floor(np.nextafter(tb, -np.inf) / self.period_s) * self.period_s
        same = pa == pb
        for p in np.unique(pa[same]):
            m = same & (pa == p)
            b = self._bucket(float(p))
            np.add.at(b[0], li[m], dist[m])
            np.add.at(b[1], li[m], (tb[m] - ta[m]) * sign)
        for i in np.flatnonzero(~same):  # segments straddling a period boundary: rare
            span = tb[i] - ta[i]
            p = period_start(float(ta[i]), self.period_s)
            while p < tb[i]:
                a, b_ = max(ta[i], p), min(tb[i], p + self.period_s)
                if b_ > a:
                    bucket = self._bucket(p)
                    bucket[0, li[i]] += dist[i] * (b_ - a) / span
                    bucket[1, li[i]] += (b_ - a) * sign
                p += self.period_s

    def take(self, p: float) -> np.ndarray:
        """Remove and return the (2, n_lanes) sums of period ``p`` (zeros when nothing was seen)."""
        self.closed_until = max(self.closed_until, p + self.period_s)
        return self.sums.pop(p, np.zeros((2, len(self.lane_ids))))

    def peek(self, p: float) -> np.ndarray:
        return self.sums.get(p, np.zeros((2, len(self.lane_ids))))

    def state(self) -> dict:
        return {str(p): v.tolist() for p, v in self.sums.items()}

    def restore(self, state: dict) -> None:
        self.sums = {float(p): np.asarray(v, dtype=np.float64) for p, v in state.items()}
