"""Grouper on exact synthetic feature tracks in receding lanes: a vehicle's part seen in the next lane (its
shadow or flank, whose features are born there) joins it; two vehicles side by side stay two."""

from __future__ import annotations

import numpy as np

from appliance.config import parse_site
from appliance.grouping import Grouper
from appliance.zones import SiteZones
from tests.test_vision_pipeline import site_dict

DT = 0.04
COUNT_Y = 30.0


def _run(objects: list[tuple[np.ndarray, float, int, int]], frames: int = 90) -> list[list]:
    """objects: (road points (n, 2) at t=0, speed along Y, lane, first frame seen); all on the road plane."""
    site = parse_site(site_dict(lanes=(("receding", -3.5, 0.0), ("receding", 0.0, 3.5))))
    g = Grouper(site.tracking, SiteZones(site))
    n = site.tracking.max_features
    s, px = np.zeros((n, 4)), np.zeros((n, 2))
    lane, alive, age = np.zeros(n, np.int32), np.zeros(n, np.bool_), np.zeros(n, np.int32)
    seen: dict[int, list] = {}
    for f in range(frames):
        slot = 0
        for pts, speed, ln, first in objects:
            for gx, gy in pts:
                if f >= first:
                    if not alive[slot]:
                        g.reset_slots(np.array([slot]))
                    y = gy + speed * f * DT
                    s[slot] = (gx, y, 0.0, speed)
                    px[slot] = (gx, -y)  # further along the road is higher in the image
                    lane[slot], alive[slot], age[slot] = ln, True, f - first
                slot += 1
        states, retire = g.step(f * DT, s, px, lane, alive, age)
        alive[retire] = False
        for st in states:
            seen.setdefault(st.id, []).append(st)
    return list(seen.values())


def _counted(tracks: list[list]) -> int:
    """Vehicles whose far end crossed the count line (receding: Y increasing)."""
    return sum(1 for ss in tracks if any(a.y_front < COUNT_Y <= b.y_front for a, b in zip(ss, ss[1:])))


def _box(x0: float, x1: float, y0: float, y1: float, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)])


def test_side_part_in_the_next_lane_joins_its_vehicle():
    car = (_box(0.1, 1.9, 10.0, 14.5, 12, 1), 15.0, 2, 0)
    # its shadow (or flank) in lane 1, level with it and as fast, found a few frames later
    side = (_box(-1.2, 0.0, 10.0, 14.0, 8, 2), 15.0, 1, 6)
    assert _counted(_run([car])) == 1
    assert _counted(_run([car, side])) == 1


def test_two_vehicles_side_by_side_stay_apart():
    # a car in each lane, level and as fast: the joint footprint (5.4 m) is wider than one vehicle
    left = (_box(-3.0, -1.2, 10.0, 14.5, 10, 3), 15.0, 1, 6)
    right = (_box(0.4, 2.2, 10.0, 14.5, 12, 1), 15.0, 2, 0)
    assert _counted(_run([left, right])) == 2
