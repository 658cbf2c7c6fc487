"""Lane of a vehicle over time from its road position and the lane polygons; lane changes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from appliance.config import SiteConfig
from appliance.geometry import polygon_contains

LANE_CHANGE_CONFIRM = 3  # states in a row in the new lane before a lane change is accepted


def _distance_to_polygon(poly: np.ndarray, p: np.ndarray) -> float:
    a = poly
    b = np.roll(poly, -1, axis=0)
    ab = b - a
    s = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0.0, 1.0)
    d = a + s[:, None] * ab - p
    return float(np.sqrt((d * d).sum(axis=1)).min())


@njit(cache=True)
def _contains(px, py, a, b, x, y) -> bool:
    inside = False
    for i in range(a, b):
        j = i + 1 if i + 1 < b else a
        x1, y1, x2, y2 = px[i], py[i], px[j], py[j]
        if (y1 > y) != (y2 > y):
            if x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
                inside = not inside
    return inside


@njit(cache=True)
def lanes_at_kernel(px: np.ndarray, py: np.ndarray, offsets: np.ndarray, ids: np.ndarray, xs: np.ndarray,
                    ys: np.ndarray, max_gap: float, out: np.ndarray) -> None:
    """Lane id (0 = none) of each point: containing lane, else the lane continuing along the road,
    else the nearest lane within max_gap. Same rules as LaneMap.lane_at (the reference)."""
    n_lanes = len(ids)
    for k in range(len(xs)):
        x, y = xs[k], ys[k]
        res = 0
        for l in range(n_lanes):
            if _contains(px, py, offsets[l], offsets[l + 1], x, y):
                res = ids[l]
                break
        if res == 0:
            for l in range(n_lanes):
                a, b = offsets[l], offsets[l + 1]
                lo, hi = py[a], py[a]
                for i in range(a, b):
                    lo = min(lo, py[i])
                    hi = max(hi, py[i])
                yc = min(max(y, lo + 1e-6), hi - 1e-6)
                if yc != y and abs(yc - y) <= max_gap + (hi - lo) and _contains(px, py, a, b, x, yc):
                    res = ids[l]
                    break
        if res == 0:
            best, best_d = -1, np.inf
            for l in range(n_lanes):
                a, b = offsets[l], offsets[l + 1]
                for i in range(a, b):
                    j = i + 1 if i + 1 < b else a
                    abx, aby = px[j] - px[i], py[j] - py[i]
                    den = max(abx * abx + aby * aby, 1e-12)
                    s = min(max(((x - px[i]) * abx + (y - py[i]) * aby) / den, 0.0), 1.0)
                    dx, dy = px[i] + s * abx - x, py[i] + s * aby - y
                    d = np.sqrt(dx * dx + dy * dy)
                    if d < best_d:
                        best_d, best = d, l
            if best >= 0 and best_d <= max_gap:
                res = ids[best]
        out[k] = res


class LaneMap:
    """The lanes of a site on the road plane."""

    def __init__(self, site: SiteConfig) -> None:
        self.ids = [lane.id for lane in site.lanes]
        self.polygons = [np.asarray(lane.polygon_m, dtype=np.float64) for lane in site.lanes]
        self.direction = {lane.id: lane.direction for lane in site.lanes}
        self.sign = {lane.id: (-1.0 if lane.direction == "approaching" else 1.0) for lane in site.lanes}
        ys = np.concatenate([p[:, 1] for p in self.polygons])
        self.y_min, self.y_max = float(ys.min()), float(ys.max())
        self.max_gap_m = 2.0  # a point this far outside every lane belongs to none
        self._px = np.ascontiguousarray(np.concatenate([p[:, 0] for p in self.polygons]))
        self._py = np.ascontiguousarray(np.concatenate([p[:, 1] for p in self.polygons]))
        self._offsets = np.cumsum([0] + [len(p) for p in self.polygons]).astype(np.int64)
        self._ids = np.array(self.ids, dtype=np.int64)

    def lanes_at(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Lane ids of many road points at once (0 where off the road); numba kernel."""
        xs = np.ascontiguousarray(xs, dtype=np.float64)
        ys = np.ascontiguousarray(ys, dtype=np.float64)
        out = np.zeros(len(xs), dtype=np.int64)
        lanes_at_kernel(self._px, self._py, self._offsets, self._ids, xs, ys, self.max_gap_m, out)
        return out

    def lane_at(self, x: float, y: float) -> int | None:
        """Lane holding road point (x, y); nearest lane within max_gap_m; None if off the road.

        Plain NumPy reference of ``lanes_at`` (one point).
        """
        p = np.array([[x, y]], dtype=np.float64)
        for lane_id, poly in zip(self.ids, self.polygons):
            if polygon_contains(poly, p)[0]:
                return lane_id
        # beyond a lane's along-road end: the lane whose end holds the lateral position continues it
        for lane_id, poly in zip(self.ids, self.polygons):
            lo, hi = poly[:, 1].min(), poly[:, 1].max()
            yc = min(max(y, lo + 1e-6), hi - 1e-6)
            if yc != y and abs(yc - y) <= self.max_gap_m + (hi - lo) and polygon_contains(poly, [[x, yc]])[0]:
                return lane_id
        d = [_distance_to_polygon(poly, p) for poly in self.polygons]
        i = int(np.argmin(d))
        return self.ids[i] if d[i] <= self.max_gap_m else None


@dataclass
class LaneHistory:
    """Lane of one vehicle, with hysteresis so a wobbling point does not make lane changes."""

    lane: int | None = None
    pending: int | None = None
    pending_n: int = 0
    changes: int = 0

    def update(self, observed: int | None) -> int | None:
        if observed is None:
            return self.lane
        if self.lane is None:
            self.lane = observed
        elif observed == self.lane:
            self.pending, self.pending_n = None, 0
        elif observed == self.pending:
            self.pending_n += 1
            if self.pending_n >= LANE_CHANGE_CONFIRM:
                self.lane, self.pending, self.pending_n = observed, None, 0
                self.changes += 1
        else:
            self.pending, self.pending_n = observed, 1
            if LANE_CHANGE_CONFIRM <= 1:
                self.lane, self.pending, self.pending_n = observed, None, 0
                self.changes += 1
        return self.lane
