"""Grouper on exact synthetic feature tracks in receding lanes: a vehicle's part seen in the next lane (its
shadow or flank, whose features are born there), or its long shadow's tip two lanes across, joins it; two
vehicles side by side stay two."""

from __future__ import annotations

import numpy as np

from appliance.config import parse_site
from appliance.grouping import Grouper
from appliance.zones import SiteZones
from tests.test_vision_pipeline import site_dict

DT = 0.04
COUNT_Y = 30.0


def _run(objects: list[tuple], frames: int = 90,
         lanes: tuple = (("receding", -3.5, 0.0), ("receding", 0.0, 3.5)), joined: bool | None = None,
         shadow: bool | None = None) -> list[list]:
    """objects: (road points (n, 2) at t=0, speed along Y, lane, first frame seen[, last]); on the road plane.
    joined: what the image test says of any two groups; shadow: of any group beside a caster (never of a group
    on its own); None: no image."""
    site = parse_site(site_dict(lanes=lanes))
    g = Grouper(site.tracking, SiteZones(site))
    n = site.tracking.max_features
    s, px = np.zeros((n, 4)), np.zeros((n, 2))
    lane, alive, age = np.zeros(n, np.int32), np.zeros(n, np.bool_), np.zeros(n, np.int32)
    seen: dict[int, list] = {}
    for f in range(frames):
        slot = 0
        for pts, speed, ln, first, *last in objects:
            for gx, gy in pts:
                if last and f > last[0]:
                    alive[slot] = False
                elif f >= first:
                    if not alive[slot]:
                        g.reset_slots(np.array([slot]))
                    y = gy + speed * f * DT
                    s[slot] = (gx, y, 0.0, speed)
                    px[slot] = (gx, -y)  # further along the road is higher in the image
                    lane[slot], alive[slot], age[slot] = ln, True, f - first
                slot += 1
        states, retire = g.step(f * DT, s, px, lane, alive, age,
                                is_shadow=None if shadow is None else (lambda a, caster: shadow and caster is not None),
                                is_joined=None if joined is None else (lambda a, b, share=None: joined))
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


# both lanes right of the camera (its foot at x 0): a tall vehicle's top leans into the lane right of it
RIGHT_LANES = (("receding", 1.0, 4.0), ("receding", 4.0, 7.0))


def test_a_tall_vehicles_top_leaning_into_the_next_lane_joins_it_where_the_image_is_one_body():
    """A 12 m truck in lane 1 whose top, projected away from the camera, is seen over lane 2 as a group of its
    own, level with it and as fast: together 5 m wide, wider than one vehicle, so only the image between the
    two tells a tall body from two vehicles side by side."""
    truck = (_box(1.3, 3.8, 10.0, 22.0, 14, 1), 15.0, 1, 0)
    top = (_box(4.1, 6.3, 10.0, 13.0, 8, 2), 15.0, 2, 6)
    assert _counted(_run([truck, top], lanes=RIGHT_LANES, joined=True)) == 1
    assert _counted(_run([truck, top], lanes=RIGHT_LANES, joined=False)) == 2
    # the top of one in lane 2 would lean out of the road, not into lane 1: a car seen there is a car
    car = (_box(2.0, 3.9, 10.0, 14.0, 10, 3), 15.0, 1, 6)
    truck2 = (np.array([(x, y) for y in np.arange(10.0, 22.1, 2.0) for x in (4.2, 5.4, 6.5)]), 15.0, 2, 0)
    assert _counted(_run([truck2, car], lanes=RIGHT_LANES, joined=True)) == 2


def test_two_cars_side_by_side_stay_apart_even_where_the_image_shows_no_road_between():
    left = (_box(2.0, 3.9, 10.0, 14.5, 10, 3), 15.0, 1, 0)
    right = (_box(4.1, 6.0, 10.0, 14.5, 10, 5), 15.0, 2, 6)
    assert _counted(_run([left, right], lanes=RIGHT_LANES, joined=True)) == 2


# three lanes, the low sun in the west: shadows cast east across the lanes
THREE_LANES = (("receding", -5.25, -1.75), ("receding", -1.75, 1.75), ("receding", 1.75, 5.25))


def test_a_long_shadows_tip_two_lanes_across_joins_its_caster():
    """A car in lane 1 casts its shadow across lane 2 into lane 3 (a sun 12 degrees up: 7 m long); the corners
    found on its tip, 8 m across the road from the car's, level with it and as fast, four at first (reported as
    a vehicle) and two of them soon lost, are its shadow where the image says so (not otherwise). A group of a
    vehicle's size there is a vehicle, shadow or not."""
    car = (_box(-4.5, -3.0, 10.0, 14.5, 12, 1), 15.0, 1, 0)
    tip = [(_box(5.0, 5.2, 10.0, 10.4, 2, 2), 15.0, 3, 6), (_box(5.0, 5.2, 10.0, 10.4, 2, 4), 15.0, 3, 6, 14)]
    assert _counted(_run([car, *tip], lanes=THREE_LANES, shadow=True)) == 1
    assert _counted(_run([car, *tip], lanes=THREE_LANES, shadow=False)) == 2
    other = (_box(3.8, 5.2, 10.0, 14.0, 8, 2), 15.0, 3, 6)
    assert _counted(_run([car, other], lanes=THREE_LANES, shadow=True)) == 2
