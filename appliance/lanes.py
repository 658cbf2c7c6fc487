"""Lane of a vehicle over time from its road position and the lane polygons; lane changes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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

    def lane_at(self, x: float, y: float) -> int | None:
        """Lane holding road point (x, y); nearest lane within max_gap_m; None if off the road."""
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
