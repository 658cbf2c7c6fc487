"""Road layout: lanes across the road, their directions, and where vehicles enter and leave."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

Y_FAR = 320.0  # approaching traffic enters here (beyond what the camera resolves)
Y_BEHIND = -30.0  # and leaves here (behind the camera); receding traffic runs the other way


@dataclass(frozen=True)
class Lane:
    id: int  # 1-based, left to right as seen from the camera
    x0: float
    x1: float
    direction: int  # -1 approaching (Y decreasing), +1 receding

    @property
    def xc(self) -> float:
        return 0.5 * (self.x0 + self.x1)

    @property
    def name(self) -> str:
        return "approaching" if self.direction < 0 else "receding"

    @property
    def y_start(self) -> float:
        return Y_FAR if self.direction < 0 else Y_BEHIND

    @property
    def y_end(self) -> float:
        return Y_BEHIND if self.direction < 0 else Y_FAR

    def y_of(self, s: np.ndarray | float) -> np.ndarray | float:
        """Road Y of along-lane position s (metres travelled from the lane's entry)."""
        return self.y_start + self.direction * s

    def s_of(self, y: float) -> float:
        return (y - self.y_start) * self.direction


@dataclass(frozen=True)
class RoadLayout:
    """Lanes side by side; with radius_m != 0 the whole road bends: a lane's edge at lateral position x
    (in the straight frame) lies at road X = x + centre_x(Y), so Y stays monotonic along every lane."""

    lanes: tuple[Lane, ...]
    lane_width: float
    radius_m: float = 0.0  # 0 = straight; + bends to the right (X grows with Y), - to the left

    @property
    def curved(self) -> bool:
        return self.radius_m != 0.0

    def centre_x(self, y: ArrayLike) -> np.ndarray:
        """Lateral shift of the road at along-road position Y: Y^2 / 2R, the parabola of a circle of radius R
        tangent to the Y axis at Y = 0 (within 0.1 % of the circle's offset for Y < R / 20)."""
        if not self.curved:
            return np.zeros_like(np.asarray(y, dtype=np.float64))
        y = np.asarray(y, dtype=np.float64)
        return y * y / (2.0 * self.radius_m)

    def slope(self, y: ArrayLike) -> np.ndarray:
        """dX/dY of the road at Y (the tangent of the heading angle)."""
        if not self.curved:
            return np.zeros_like(np.asarray(y, dtype=np.float64))
        return np.asarray(y, dtype=np.float64) / self.radius_m

    def to_road(self, x: ArrayLike, y: ArrayLike) -> np.ndarray:
        """(N, 2) road X/Y of lateral positions x (straight frame) at along-road positions y."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return np.column_stack([(x + self.centre_x(y)).ravel(), y.ravel()])

    @classmethod
    def make(cls, approaching: int, receding: int, lane_width: float = 3.5, radius_m: float = 0.0) -> "RoadLayout":
        n = approaching + receding
        x_left = -n * lane_width / 2.0
        lanes = tuple(
            Lane(k + 1, x_left + k * lane_width, x_left + (k + 1) * lane_width, -1 if k < approaching else +1)
            for k in range(n)
        )
        return cls(lanes, lane_width, float(radius_m))

    @property
    def x_min(self) -> float:
        return self.lanes[0].x0

    @property
    def x_max(self) -> float:
        return self.lanes[-1].x1

    def lane_index_at(self, x: np.ndarray) -> np.ndarray:
        """Index into `lanes` of the lane containing lateral position x (clipped to the road)."""
        k = np.floor((np.asarray(x) - self.x_min) / self.lane_width).astype(np.int64)
        return np.clip(k, 0, len(self.lanes) - 1)
