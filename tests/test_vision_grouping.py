"""Grouper on exact synthetic feature tracks: a tall vehicle's roof features (projected onto the road they
lie further away and move faster) join the vehicle instead of counting as a second one."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config import MeasuresConfig, parse_site
from appliance.grouping import GHOST, WATCHING, Grouper, VehicleTrack
from appliance.pipeline import HOLD_S
from appliance.types import NO_VEHICLE, VehicleState
from appliance.zones import LANE_MARGIN_M, LaneZones, SiteZones
from tests.test_vision_pipeline import site_dict

DT = 0.04
RECEDING_BESIDE_APPROACHING = (("receding", -3.5, 0.0), ("approaching", 0.0, 3.5))  # lane 1 recedes
LEFT_OF_CAMERA = (("approaching", -7.0, -3.5), ("approaching", -3.5, 0.0))  # lane 2 runs beside the camera's foot
COUNT_Y = 30.0
SETTLING = 0.6
UNCENTRED_SHIFT_PX = 96


def _run(objects: list[tuple], frames: int = 90, lanes=None,
         shadow_seen=None, night: bool = False, joined: bool | None = None, shadow_at=None,
         uncentred: bool = False) -> dict[int, list]:
    """objects: (ground points (n, 2) at t=0, speed along Y, lane, first frame seen, height above road[, frame
    from which they are lost]).
    shadow_seen(frame): what the image's shadow test answers in that frame (default: no image test), for any
    points or only for a caster's shadow where shadow_at(image points) holds; joined: what the image test of
    two groups being one body answers (default: no image test); uncentred: the frame fits its camera only with
    the lens's axis off its centre (a crop, see _site), so that the tracker works without heights."""
    site = parse_site(_site(lanes, uncentred))
    zones = SiteZones(site)
    cx, cy, ch = SiteZones(parse_site(_site(lanes))).camera if uncentred else zones.camera  # the true camera
    g = Grouper(site.tracking, zones)
    g.lights_only = night
    n = site.tracking.max_features
    s = np.zeros((n, 4))
    px = np.zeros((n, 2))
    lane = np.zeros(n, np.int32)
    alive = np.zeros(n, np.bool_)
    age = np.zeros(n, np.int32)
    seen: dict[int, list] = {}
    for f in range(frames):
        t = f * DT
        slot = 0
        for pts, speed, ln, first, h, *lost in objects:
            k = ch / (ch - h)  # height magnification of the road-plane projection
            for gx, gy in pts:
                if lost and f >= lost[0]:
                    alive[slot] = False
                elif f >= first:
                    if not alive[slot]:
                        g.reset_slots(np.array([slot]))
                    # speed: m/s, or a function of time giving (distance travelled, speed)
                    d, v = speed(t) if callable(speed) else (speed * t, speed)
                    x, y = cx + k * (gx - cx), cy + k * (gy + d - cy)
                    # a new feature's speed is still settling (the tracker's filter starts from a rough one)
                    s[slot] = (x, y, 0.0, k * v * (SETTLING if f - first < 10 else 1.0))
                    px[slot] = (x, -y + h)
                    lane[slot] = ln
                    alive[slot] = True
                    age[slot] = f - first
                slot += 1
        is_shadow = None if shadow_seen is None else (
            lambda pts, caster, f=f: shadow_seen(f) and (shadow_at is None or (caster is not None and shadow_at(pts))))
        is_joined = None if joined is None else (lambda a, b, share=None: joined)
        states, retire = g.step(t, s, px, lane, alive, age, is_shadow, is_joined)
        alive[retire] = False
        for st in states:
            seen.setdefault(st.id, []).append(st)
    return seen


def _site(lanes=None, uncentred: bool = False) -> dict:
    """The test site; uncentred: its calibration's image points UNCENTRED_SHIFT_PX to the left, as in a frame
    cropped from a wider picture (the lens's axis 96 px left of its centre): no centred camera fits it."""
    d = site_dict() if lanes is None else site_dict(lanes=lanes)
    if uncentred:
        d["calibration"]["image_px"] = [[x - UNCENTRED_SHIFT_PX, y] for x, y in d["calibration"]["image_px"]]
    return d


def _counted(seen: dict[int, list], receding: bool = False) -> int:
    """Vehicles whose front crossed the count line (a vehicle's first report carries its earlier points)."""
    n = 0
    for ss in seen.values():
        ys = [p[2] for p in ss[0].trajectory or []] + [st.y_front for st in ss]
        n += any((a < COUNT_Y <= b) if receding else (a > COUNT_Y >= b) for a, b in zip(ys, ys[1:]))
    return n


def _firsts(seen: dict[int, list]) -> dict[int, tuple]:
    """Per vehicle: its first report's time and front, and its last feature count (for assert messages)."""
    return {vid: (ss[0].t, ss[0].y_front, ss[-1].n_features) for vid, ss in seen.items()}


def _box(x0: float, x1: float, y0: float, y1: float, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)])


def test_roof_fragment_joins_its_truck_but_a_faster_car_stays_apart():
    truck = (_box(0.6, 2.6, 44.0, 54.0, 12, 1), -15.0, 2, 0, 0.0)
    roof = (_box(0.8, 2.4, 46.0, 53.0, 8, 2), -15.0, 2, 12, 3.5)  # seen from frame 12: a group of its own
    seen = _run([truck, roof])
    # the roof's projection moves 1.33x faster and further away; when it is first reported its speed is
    # still low, so only a later look finds it on the truck: without that it counts twice
    assert _counted(seen) == 1, {k: len(v) for k, v in seen.items()}
    # the same motion one lane over is a real car overtaking: it stays a vehicle of its own
    car = (_box(-3.2, -1.4, 58.0, 62.0, 8, 3), -15.0 * 1.33, 1, 12, 0.0)
    assert _counted(_run([truck, car])) == 2
    # so is a car queued 6 m behind the truck at its speed (closer than connection_m the pair graph joins them)
    queued = (_box(0.6, 2.4, 60.0, 64.5, 8, 4), -15.0, 2, 12, 0.0)
    assert _counted(_run([truck, queued])) == 2


def test_a_reported_roof_says_whose_part_it_may_be_while_rechecked_and_whom_it_joined():
    """The roof of the truck above is reported as a vehicle before it is found on the truck: while it is
    re-checked its states name the truck (part_of: the measures hold its count meanwhile), and its last state
    says it joined the truck (its count dropped, its Edie distance and time the truck's)."""
    truck = (_box(0.6, 2.6, 44.0, 54.0, 12, 1), -15.0, 2, 0, 0.0)
    roof = (_box(0.8, 2.4, 46.0, 53.0, 8, 2), -15.0, 2, 12, 3.5)
    seen = _run([truck, roof])
    host = min(seen, key=lambda vid: seen[vid][0].t)
    parts = [vid for vid in seen if vid != host]
    assert len(parts) == 1, _firsts(seen)
    ss = seen[parts[0]]
    assert ss[-1].finished and ss[-1].joined == host
    assert any(st.part_of == host for st in ss[:-1])
    assert all(st.part_of is None and st.joined is None for st in seen[host])


def _braking(t: float) -> tuple[float, float]:
    return -10.0 * t + 1.0 * t * t, -10.0 + 2.0 * t


@pytest.mark.parametrize("behind_m", [16.0, 18.0, 20.0])
def test_a_faster_car_closing_on_a_braking_one_is_not_taken_for_its_roof(behind_m):
    """A car brakes (10 m/s, slowing by 2 m/s every second) and a follower comes on at a steady 13 m/s. When
    the follower is first seen its speed ratio to the car and its place fit a part 3.7 m up on the car: an
    elevated part moves just like that. But a part keeps its ratio while its vehicle brakes, and the follower's
    grows: it stays a vehicle of its own. A roof on a truck braking the same way still joins its truck."""
    car = (_box(-1.0, 1.0, 36.0, 40.0, 10, 31), _braking, 2, 0, 0.0)
    follower = (_box(-1.0, 1.0, 40.0 + behind_m, 44.0 + behind_m, 8, 32), -13.0, 2, 0, 0.0)
    seen = _run([car, follower], frames=80)
    assert _counted(seen) == 2, {k: len(v) for k, v in seen.items()}
    truck = (_box(-1.0, 1.0, 36.0, 46.0, 12, 33), _braking, 2, 0, 0.0)
    roof = (_box(-0.8, 0.8, 38.0, 45.0, 8, 34), _braking, 2, 12, 3.5)
    assert _counted(_run([truck, roof], frames=80)) == 1


@pytest.mark.parametrize("first_ratio", [0.9, 1.0])
def test_a_roof_whose_first_speeds_read_as_its_cars_is_watched_before_it_counts(monkeypatch, first_ratio):
    """A car's roof (1.5 m up: 12 % faster than the car in projection, too little for a re-check once reported)
    is first seen as a group of its own while its features' speeds are still settling, reading the car's speed
    or below it. Level with the car it would lie beyond it, but some height puts it on the car, and the image
    between the two is one body: it is watched before it is reported, and joins the car once its speed shows
    its height. A car following 7 m behind at the same speed, watched too (some height would put it on the car),
    stays a vehicle of its own."""
    ch = SiteZones(parse_site(site_dict())).camera[2]
    monkeypatch.setitem(globals(), "SETTLING", first_ratio * (ch - 1.5) / ch)  # read by _run
    car = (_box(-1.0, 1.0, 60.0, 64.5, 10, 41), -20.0, 2, 0, 0.0)
    roof = (_box(-0.8, 0.8, 61.5, 63.5, 8, 42), -20.0, 2, 12, 1.5)
    assert _counted(_run([car, roof], joined=True)) == 1
    follower = (_box(-1.0, 1.0, 71.5, 76.0, 8, 43), -20.0, 2, 12, 0.0)
    assert _counted(_run([car, follower], joined=True)) == 2


def _stop_and_go(t: float) -> tuple[float, float]:
    """Distance travelled and speed (approaching, so negative) of a car braking from 8 m/s at 2 m/s^2 from 0.5 s,
    standing from 4.5 s to 6.5 s, then pulling away at 2 m/s^2; before 0 it ran at 8 m/s."""
    if t < 0.5:
        return -8.0 * t, -8.0
    if t < 4.5:
        u = t - 0.5
        return -(4.0 + 8.0 * u - u * u), -(8.0 - 2.0 * u)
    if t < 6.5:
        return -20.0, 0.0
    u = t - 6.5
    return -(20.0 + u * u), -2.0 * u


def test_a_roof_reported_apart_in_stop_and_go_joins_its_car_but_a_follower_does_not():
    """A car brakes to a stop and pulls away again (too slow for a roof's re-check by speed ratio). Its roof,
    a group of its own reported as a vehicle, keeps k times the car's distance from the camera's foot plus a
    constant through the stop: it joins the car, one vehicle at the count line. A car following it through the
    same stop a second later (as drivers do), standing 7 m behind it, moves nothing like that: two vehicles."""
    car = (_box(-1.0, 1.0, 60.0, 64.5, 10, 61), _stop_and_go, 2, 0, 0.0)
    roof = (_box(-0.8, 0.8, 61.5, 63.5, 8, 62), _stop_and_go, 2, 12, 1.5)
    seen = _run([car, roof], frames=300)
    assert _counted(seen) == 1, _firsts(seen)
    joined = [ss[-1] for ss in seen.values() if ss[-1].joined is not None]
    assert len(joined) == 1 and joined[0].t < 9.0, _firsts(seen)  # well before the count line (about 9.7 s)

    def follower_motion(t: float, lag: float = 1.0) -> tuple[float, float]:
        d, v = _stop_and_go(t - lag)
        return d - _stop_and_go(-lag)[0], v

    follower = (_box(-1.0, 1.0, 79.5, 84.0, 10, 63), follower_motion, 2, 12, 0.0)  # 7 m behind when standing
    assert _counted(_run([car, follower], frames=340)) == 2


def test_a_roof_still_watched_when_its_truck_leaves_the_view_is_no_vehicle():
    """A truck's roof, a group of its own, is watched before it joins (it could be a faster follower); the truck
    leaves the view meanwhile. The roof, still matching the truck's speed, is the truck's leftover: it is
    dropped, never reported and finished as a vehicle of its own."""
    truck = (_box(-1.0, 1.0, 20.0, 30.0, 12, 1), -15.0, 2, 0, 0.0)
    roof = (_box(-0.8, 0.8, 22.0, 29.0, 8, 2), -15.0, 2, 0, 3.5)
    seen = _run([truck, roof], frames=90)
    assert len(seen) == 1 and seen[min(seen)][-1].finished, {k: len(v) for k, v in seen.items()}


def test_a_group_found_only_a_shadow_after_its_report_went_out_ends_as_no_vehicle():
    """Corners on the road (height 0) moving at 20 m/s that the image's shadow test first calls a shadow only in
    frame 14 (the share it needs builds up over the next frames): the group was reported at once and its report
    released (pipeline.HOLD_S) before it is retired as a lone shadow. Its last state says it was no vehicle
    (joined NO_VEHICLE), so that the measures take back its Edie distance and time; retired quietly, as before,
    the measures kept them."""
    marks = np.array([[-1.5, 0.0], [-0.5, 0.0], [0.5, 0.0], [1.5, 0.0], [-1.0, 2.0], [1.0, 2.0]]) + [1.75, 60.0]
    seen = _run([(marks, -20.0, 2, 0, 0.0)], frames=40, shadow_seen=lambda f: f >= 14)
    first = seen[min(seen)]
    report = next(st.t for st in first if st.trajectory is not None)
    last = first[-1]
    assert last.finished and last.joined == NO_VEHICLE
    assert last.t - report > HOLD_S


def test_a_long_truck_s_top_still_in_view_when_its_front_left_is_no_vehicle_but_a_car_beyond_is():
    """An articulated truck's top 16 m behind its front, 4 m up, is seen in the lanes only once the front is at the
    count line, too far from the front's group to link with it, and the image test never says the two are one body.
    It is reported as a vehicle of its own and, faster in projection, would reach the count line after the front
    left the view. Moving like a part of the vehicle that just left its lane, and lying on it with that height
    undone, it is that vehicle's leftover: counted once, its last state naming the truck. A car in the lane
    beyond, overtaking at the speed the top shows, lies in projection just where the top would (its place undone
    falls on the truck too): it counts."""
    truck = (_box(-1.0, 1.0, 45.0, 49.0, 12, 1), -18.0, 2, 0, 0.0)
    top = (_box(-0.8, 0.8, 61.0, 62.0, 5, 2), -18.0, 2, 21, 4.0)
    seen = _run([truck, top], frames=160)
    assert _counted(seen) == 1, _firsts(seen)
    truck_id, top_id = sorted(seen)
    assert seen[top_id][-1].joined == truck_id  # its Edie time and distance were the truck's
    car = (_box(-3.0, -1.8, 95.0, 96.5, 8, 3), -18.0 * 1.39, 1, 21, 0.0)  # 1.39: the top's magnification
    seen = _run([truck, car], frames=160)
    assert _counted(seen) == 2, _firsts(seen)


@pytest.mark.parametrize("cab_left, hits, expected", [(True, 8, GHOST), (True, 2, WATCHING), (False, 8, WATCHING)])
def test_a_roof_watched_against_its_cab_is_its_leftover_when_the_cab_leaves_and_another_part_is_next(
        cab_left: bool, hits: int, expected: int):
    """A truck's roof is watched against its cab (it could be a faster follower); the cab leaves the view, and
    the vehicle the roof now lies on is a part of the truck's box reported apart. Having matched the cab all
    along, the roof is the cab's leftover (GHOST), not a group to watch afresh against that part (and to report
    once that part leaves too). A roof that had barely been watched, or whose first host is still in the view,
    starts a new watch."""
    site = parse_site(site_dict())
    g = Grouper(site.tracking, SiteZones(site))
    t = 1.0
    part = VehicleTrack(id=2, first_t=0.0, lane_index=2, reported=True)
    part.last = VehicleState(id=2, t=t, x=0.0, y_front=20.0, y_rear=22.0, vx=0.0, vy=-15.0, length=2.0,
                             n_features=12, spot_vy=-15.0)
    g.tracks = {2: part}
    if not cab_left:
        g.tracks[1] = VehicleTrack(id=1, first_t=0.0, lane_index=2, reported=True)
    roof = VehicleTrack(id=3, first_t=0.5, lane_index=2, watch_host=1,
                        watch=[(t - 0.04 * (hits - i), 1.4, True) for i in range(hits)])
    st = VehicleState(id=3, t=t, x=0.0, y_front=30.0, y_rear=31.0, vx=0.0, vy=-21.0, length=1.0, n_features=8,
                      spot_vy=-21.0)
    assert g._watched(roof, st, 2, {2: np.arange(12)}) == expected


def test_at_night_a_motorcycle_seen_by_three_features_counts_but_a_truck_s_three_feature_top_does_not():
    """At night a vehicle shows only its lights: a motorcycle's headlamp gives three features, one short of
    min_features. Having held together for a second over 15 m it is a vehicle; by day such a group is not. A
    truck's top of three features (a group of its own, faster in projection) still joins its truck."""
    motorcycle = (_box(-0.3, 0.3, 55.0, 56.0, 3, 41), -15.0, 2, 0, 0.7)
    assert _counted(_run([motorcycle], night=True)) == 1
    assert _counted(_run([motorcycle])) == 0
    corners = np.array([[-1.0, 44.0], [1.0, 44.1]])  # its lamps: the front spans its width
    truck = (np.vstack([corners, _box(-1.0, 1.0, 44.0, 54.0, 10, 42)]), -15.0, 2, 0, 0.0)
    top = (_box(-0.8, 0.8, 46.0, 53.0, 3, 43), -15.0, 2, 12, 3.5)
    assert _counted(_run([truck, top], night=True)) == 1


@pytest.mark.parametrize("gap_m", [2.8, 4.5])
def test_a_shadow_the_image_test_sees_in_two_frames_of_three_joins_its_vehicle(gap_m):
    """A car's shadow on the next lane is tracked as a group of its own, level with the car and at its speed.
    The image's shadow test says so only from 0.4 s on, when the group is reported already, and then misses
    every third frame (the shadow's box catches some of the caster or a lane marking): the group still joins
    the car, where matching it in ten frames in a row never came. Under a low sun the features seen on the
    shadow lie on its far edge, 4.5 m from the car's side."""
    lanes = (("approaching", -5.0, 0.0), ("approaching", 0.0, 5.0))
    car = (_box(0.6, 2.4, 52.0, 56.0, 10, 41), -12.0, 2, 0, 0.0)
    shade = (_box(0.6 - gap_m - 1.2, 0.6 - gap_m, 53.0, 57.0, 8, 42), -12.0, 1, 0, 0.0)
    seen = _run([car, shade], frames=80, lanes=lanes, shadow_seen=lambda f: f >= 10 and f % 3 != 0)
    assert _counted(seen) == 1, {k: len(v) for k, v in seen.items()}
    # with no image test passing, the two are two vehicles (two cars side by side look just the same)
    assert _counted(_run([car, shade], frames=80, lanes=lanes, shadow_seen=lambda f: False)) == 2


def test_a_long_shadow_cast_over_the_next_lane_into_the_one_beyond_joins_its_vehicle():
    """Under a low sun a car's shadow reaches across the next lane: its far edge, tracked as a group of its own,
    lies two lanes from the car, level with it and at its speed, the road between them shadowed. It joins the
    car; with no image test passing, the two are two vehicles (a car two lanes over looks just the same)."""
    lanes = (("approaching", -5.0, -1.5), ("approaching", -1.5, 2.0), ("approaching", 2.0, 5.5))
    car = (_box(3.0, 4.7, 52.0, 56.0, 10, 51), -12.0, 3, 0, 0.0)
    shade = (_box(-3.5, -2.5, 53.0, 57.0, 8, 52), -12.0, 1, 0, 0.0)

    def on_shade(pts: np.ndarray) -> bool:  # the image test finds only it a shadow
        return bool((pts[:, 0] < -1.5).all())

    seen = _run([car, shade], frames=80, lanes=lanes, shadow_seen=lambda f: f >= 10, shadow_at=on_shade)
    assert _counted(seen) == 1, {k: len(v) for k, v in seen.items()}
    assert _counted(_run([car, shade], frames=80, lanes=lanes, shadow_seen=lambda f: False)) == 2


def test_a_group_of_a_vehicles_shadow_and_its_raised_parts_joins_it():
    """A van's windscreen, leaning into the next lane in projection, is found in one group with the corner of
    the van's shadow there, which is that group's near end: the image test finds the whole group no shadow
    (the windscreen is in its box), its near end a shadow, and the rest of it moves as the van's raised parts
    over the van's footprint. It joins the van; with the whole group tested, the two are two vehicles. With the
    raised part over its own lane, the group is a vehicle of its own."""
    lanes = (("approaching", -8.0, -4.5), ("approaching", -4.5, -1.0))
    van = (_box(-4.2, -2.2, 45.0, 47.0, 10, 61), -12.0, 2, 0, 0.0)

    def near_end_only(pts: np.ndarray) -> bool:  # the image test: a shadow where the box holds the corner alone
        return bool(((pts[:, 0] >= -6.05) & (pts[:, 0] <= -5.35)).all())

    corner = (_box(-6.0, -5.4, 49.0, 50.5, 5, 62), -12.0, 1, 0, 0.0)
    screen = (_box(-4.2, -4.0, 46.0, 46.6, 4, 63), -12.0, 1, 0, 1.3)
    seen = _run([van, corner, screen], frames=80, lanes=lanes, shadow_seen=lambda f: f >= 10,
                shadow_at=near_end_only)
    assert _counted(seen) == 1, {k: len(v) for k, v in seen.items()}
    # the same group's raised part over its own lane, not over the van: a vehicle of its own
    over_lane_1 = (_box(-6.0, -5.8, 46.0, 46.6, 4, 63), -12.0, 1, 0, 1.3)
    seen = _run([van, corner, over_lane_1], frames=80, lanes=lanes, shadow_seen=lambda f: f >= 10,
                shadow_at=near_end_only)
    assert _counted(seen) == 2, {k: len(v) for k, v in seen.items()}


@pytest.mark.parametrize("dragged_m", [0.0, 1.2])
def test_a_group_standing_still_before_it_moves_dates_its_trajectory_from_the_move(dragged_m):
    """Features on an occluder's edge where vehicles emerge stand still until the vehicle comes out and
    carries the group on: the reported trajectory must not start when the edge was first seen (that
    would put the vehicle in the Edie region for seconds it was not there). The edge may first have been
    dragged a metre by the vehicle that passed behind the occluder (too briefly to be reported)."""
    from appliance.grouping import STILL_S

    site = parse_site(site_dict())
    g = Grouper(site.tracking, SiteZones(site))
    n = site.tracking.max_features
    s, px = np.zeros((n, 4)), np.zeros((n, 2))
    lane, alive, age = np.zeros(n, np.int32), np.zeros(n, np.bool_), np.zeros(n, np.int32)
    pts = _box(0.6, 2.4, 60.0, 64.0, 8, 5)
    move_t = 1.2
    g.reset_slots(np.arange(len(pts)))
    first_report = None
    for f in range(80):
        t = f * DT
        drag = min(t / 0.12, 1.0) * dragged_m  # dragged within the first 3 frames, then stuck
        dy = -drag - 10.0 * max(0.0, t - move_t)
        vy = -10.0 if t > move_t or (dragged_m and t < 0.12) else 0.0
        for i, (x, y) in enumerate(pts):
            s[i] = (x, y + dy, 0.0, vy)
            px[i] = (x, -(y + dy))
            lane[i], alive[i], age[i] = 2, True, f
        states, _ = g.step(t, s, px, lane, alive, age)
        for st in states:
            if st.trajectory and first_report is None:
                first_report = st
    assert first_report is not None, "the moving group is never reported"
    t0 = first_report.trajectory[0][0]
    assert t0 >= move_t - STILL_S - DT, f"trajectory starts at {t0:.2f} s, the group moved at {move_t} s"


def test_reported_length_is_the_vehicle_on_the_road_not_its_roof_projected_beyond_it():
    """A car's roofline, projected onto the road, lies metres beyond the car and runs ahead of it; the
    reported length undoes that (from the roof's speed over the near end's) and is the car's length, once the
    cabin, watched a while as a part of its own, has joined and its features have been followed a few metres.
    The far end seen is the rear window's top, HIDDEN_SHARE_REAR (15 %) of the car ahead of its rear: the length
    comes within 0.3 m of the car's (0.17 m short here; 7.5 % or 30 % would put it 0.45 m short or 0.56 m long)."""
    from appliance.grouping import NOMINAL_LENGTH_M

    front, length = 44.0, 3.6
    assert abs(length - NOMINAL_LENGTH_M) > 0.8  # not a typical car: that would pass for the wrong reason
    body = (_box(-2.6, -0.9, front, front + 1.2, 10, 5), -15.0, 1, 0, 0.0)  # bonnet and bumper, low
    cabin = (_box(-2.5, -1.0, front + 0.32 * length, front + 0.84 * length, 10, 6), -15.0, 1, 0, 1.45)
    seen = _run([body, cabin], frames=60)
    zones = SiteZones(parse_site(site_dict()))
    cy, ch = zones.camera[1], zones.camera[2]
    states = [st for ss in seen.values() for st in ss if not st.finished and st.y_front < 20.0]
    assert states, seen
    raw = cy + ch / (ch - 1.45) * (front + 0.84 * length - cy) - front  # the features' span at the start
    assert raw > length + 1.5, raw  # so the test can tell the two apart
    lengths = np.array([st.length for st in states])
    assert np.all(np.abs(lengths - length) < 0.3), lengths
    # the far end moves with the vehicle: the rear is the front plus that length
    assert np.all(np.abs(np.array([st.y_rear - st.y_front for st in states]) - lengths) < 1e-6)


def test_a_far_end_on_the_road_is_the_vehicles_end_with_nothing_hidden_beyond_it():
    """A car whose furthest features lie on the road (the edge of its shadow beyond it, or a low bumper) has
    nothing of itself beyond them, unlike a roofline (HIDDEN_SHARE_REAR): the reported length is where they lie
    (4.6-5 m behind its front here), within 0.3 m of its 5 m. Taken for a roofline they read 5.7 m."""
    front, length = 44.0, 5.0
    body = (_box(-2.6, -0.9, front, front + 1.2, 10, 5), -15.0, 1, 0, 0.0)  # bonnet and bumper, low
    cabin = (_box(-2.5, -1.0, front + 1.5, front + 3.5, 10, 6), -15.0, 1, 0, 1.3)
    tail = (_box(-2.6, -0.9, front + length - 0.4, front + length, 8, 7), -15.0, 1, 0, 0.0)  # on the road
    seen = _run([body, cabin, tail], frames=60)
    assert len(seen) == 1, _firsts(seen)
    states = [st for st in next(iter(seen.values())) if not st.finished and st.y_front < 30.0]
    assert len(states) > 10, seen
    lengths = np.array([st.length for st in states])
    assert np.all(np.abs(lengths - length) < 0.3), lengths


def test_an_uncentred_frames_lengths_are_measured_with_heights_undone():
    """A frame whose calibration fits a camera only with its lens's axis off the frame's centre (a crop: the real
    clip's) is tracked without heights, but lengths are measured with that camera (SiteZones.length_camera,
    placed_camera's): a car seen from its bumper up its bonnet and windscreen to its roof's rear edge (one group
    without heights: no gap between its features) is then reported within 0.3 m of its 3.6 m. From the features'
    span (as before) it read 7.5-9.3 m, its roof projected beyond it (the real clip's cars read 13-45 m)."""
    zones, centred = SiteZones(parse_site(_site(uncentred=True))), SiteZones(parse_site(_site()))
    assert zones.camera is None and zones.length_camera is not None
    assert np.allclose(zones.length_camera, centred.camera, atol=0.05), (zones.length_camera, centred.camera)
    front, length = 44.0, 3.6
    slices = [(_box(-2.5, -1.0, front + u * 0.84 * length - 0.1, front + u * 0.84 * length + 0.1, 3, 20 + i),
               -15.0, 1, 0, 1.45 * u) for i, u in enumerate(np.linspace(0.0, 1.0, 9))]
    seen = _run(slices, frames=60, uncentred=True)
    assert len(seen) == 1, _firsts(seen)
    states = [st for st in next(iter(seen.values())) if not st.finished and st.y_front < 25.0]
    assert states, seen
    lengths = np.array([st.length for st in states])
    assert np.all(np.abs(lengths - length) < 0.3), lengths


def test_a_receding_cars_length_takes_in_the_bonnet_hidden_beyond_its_windscreen():
    """A receding car shows its rear and its cabin; the furthest part seen is the windscreen's top, the bonnet
    beyond it hidden: HIDDEN_SHARE_FRONT (30 %) of the car. Once its features are fitted (the first half
    second), the reported length comes within 0.3 m of the car's 4 m (3.94 m here; 15 % or 45 % would give
    3.24 or 5.01 m). The front never goes back: once the rear plus that length has passed the front the span
    last put (from 0.64 s here), the front reported is the rear plus that length."""
    length, rear = 4.0, 12.0
    lanes = RECEDING_BESIDE_APPROACHING
    body = (_box(-2.6, -0.9, rear, rear + 1.0, 10, 5), 15.0, 1, 0, 0.3)  # bumper and boot lid
    cabin = (_box(-2.5, -1.0, rear + 0.2 * length, rear + 0.7 * length, 10, 6), 15.0, 1, 0, 1.45)
    seen = _run([body, cabin], frames=60, lanes=lanes)
    assert len(seen) == 1, seen
    states = [st for st in next(iter(seen.values())) if not st.finished]
    fitted = [st for st in states if st.t >= 0.5]
    assert len(fitted) > 30 and states[0].length > length + 2.0  # the span at first: the roof projected ahead
    assert np.all(np.abs(np.array([st.length for st in fitted]) - length) < 0.3), [st.length for st in fitted]
    settled = [st for st in states if st.t >= 0.7]
    assert np.allclose([st.y_front - st.y_rear for st in settled], [st.length for st in settled])


def test_a_receding_vehicles_side_part_in_the_next_lane_joins_it_once_watched():
    """Receding traffic seen from the side: a low part of a vehicle (its flank's lower edge, a short
    shadow) shows up across the lane line a little ahead of its rear, as a group of its own. Watched
    for a while it keeps its place along the vehicle at the vehicle's speed, and joins it; a car in
    the next lane a lane's width away does not."""
    lanes = (("receding", -3.5, 0.0), ("receding", 0.0, 3.5))
    car = (_box(0.4, 2.2, 10.0, 14.5, 12, 7), 10.0, 2, 0, 0.0)  # driving near the lane line
    side = (_box(-0.5, -0.2, 12.6, 13.6, 6, 8), 10.0, 1, 12, 0.0)  # 2.6 m ahead of its rear, just across
    assert _counted(_run([car, side], lanes=lanes), receding=True) == 1
    beside = (_box(-2.6, -0.9, 12.6, 17.1, 10, 9), 10.0, 1, 12, 0.0)
    assert _counted(_run([car, beside], lanes=lanes), receding=True) == 2


@pytest.mark.parametrize("part, counted", [("narrow, camera's side", 1), ("wide, camera's side", 2),
                                            ("wide, far side", 1)])
def test_a_group_beside_a_receding_vehicle_on_the_cameras_side_joins_it_only_if_narrow(part, counted):
    """Receding traffic seen from beside the road: a vehicle's raised parts lean away from the camera in
    projection, so what is seen across the lane line on the camera's side of it, level with its rear and as
    fast, is narrow across the road (its flank's lower edge, a shadow's edge along it). A narrow part there
    joins it; one wider than SIDE_NEAR_MAX_WIDTH_M is a car entering the view beside it (the vehicle's own near
    end shows only a narrow strip at the lane line here, so the two near ends together are no wider than one
    vehicle). On the far side, where its flank and top lean, a wide part joins it."""
    lanes = (("receding", 0.0, 3.5), ("receding", 3.5, 7.0))  # the camera's foot at x 0: lane 1 on its side
    if part == "wide, far side":
        host = (np.vstack([_box(3.0, 3.4, 10.0, 12.8, 6, 7), _box(1.6, 3.4, 13.2, 14.5, 8, 8)]), 10.0, 1, 0, 0.0)
        beside = (_box(3.7, 5.1, 10.3, 14.5, 12, 9), 10.0, 2, 12, 0.0)
    else:
        host = (np.vstack([_box(3.6, 4.0, 10.0, 12.8, 6, 7), _box(3.6, 5.4, 13.2, 14.5, 8, 8)]), 10.0, 2, 0, 0.0)
        width = 0.3 if part.startswith("narrow") else 1.7
        beside = (_box(3.3 - width, 3.3, 10.3, 14.5, 12, 9), 10.0, 1, 12, 0.0)
    seen = _run([host, beside], lanes=lanes)
    assert _counted(seen, receding=True) == counted, _firsts(seen)


@pytest.mark.parametrize("part", ["shadow", "flank"])
def test_a_part_seen_before_its_receding_vehicle_joins_the_vehicle_reported_after_it(part):
    """A receding vehicle enters the view at the image bottom, and its shadow cast ahead of it into the next
    lane (or its flank there) may come into view first, to be reported as a group of its own before the
    vehicle's is. Once the image test finds the first group to be the vehicle's shadow (or, a flank, it keeps
    its place beside a vehicle of many times its features), it joins that vehicle: one count. With no image
    test passing, a shadow-sized group a lane line away is a second vehicle; so is a flank-sized one as big
    as the vehicle (two vehicles side by side look just the same)."""
    lanes = (("receding", -3.5, 0.0), ("receding", 0.0, 3.5))
    car = (_box(0.4, 2.2, 10.0, 14.5, 12, 21), 10.0, 2, 8, 0.0)  # seen from frame 8
    if part == "shadow":
        first = (_box(-2.8, -1.2, 13.0, 16.0, 5, 22), 10.0, 1, 0, 0.0)
        seen = _run([car, first], lanes=lanes, shadow_seen=lambda f: f >= 14,
                    shadow_at=lambda pts: bool(np.all(pts[:, 0] < 0.0)))  # the car's own points are no shadow
        assert _counted(seen, receding=True) == 1, {k: (v[0].t, v[-1].t) for k, v in seen.items()}
        seen = _run([car, first], lanes=lanes, shadow_seen=lambda f: False)
    else:
        first = (_box(-0.5, -0.2, 12.6, 13.6, 5, 22), 10.0, 1, 0, 0.0)
        seen = _run([car, first], lanes=lanes)
        assert _counted(seen, receding=True) == 1, {k: (v[0].t, v[-1].t) for k, v in seen.items()}
        seen = _run([car, (_box(-0.5, -0.2, 12.6, 13.6, 8, 22), 10.0, 1, 0, 0.0)], lanes=lanes)
    assert _counted(seen, receding=True) == 2


def test_a_still_group_that_a_vehicle_drives_through_is_dropped():
    """Features a vehicle left on an occluder's edge move with it a little, then stand still there. Such
    a group is reported (it moved), but when the next vehicle of the lane drives through the place it
    stands it cannot be a vehicle (vehicles queue; they do not pass through one another): it is dropped, its
    last state saying it was no vehicle (the measures take back its Edie time)."""

    def stuck(t: float) -> tuple[float, float]:  # creeps 5.25 m at 3.5 m/s, then stands still (not a dead stop)
        return (-3.5 * min(t, 1.5), -3.5 if t < 1.5 else 0.0)

    clutter = (_box(-2.4, -1.2, 60.0, 60.5, 6, 10), stuck, 1, 0, 0.0)
    # the next car comes into view at 3.6 s and reaches the clutter (54.75 m) at about 5.0 s
    car = (_box(-2.6, -0.9, 74.0, 78.5, 10, 11), lambda t: (-15.0 * max(t - 3.6, 0.0), -15.0), 1, 90, 0.0)
    seen = _run([clutter, car], frames=180)
    still = [vid for vid, ss in seen.items() if ss[0].y_front < 65.0]
    assert len(still) == 1, {vid: (ss[0].t, ss[0].y_front) for vid, ss in seen.items()}
    last_t = seen[still[0]][-1].t
    assert 4.5 < last_t < 5.4, last_t  # kept standing until the car went through it, then dropped
    assert seen[still[0]][-1].finished and seen[still[0]][-1].joined == NO_VEHICLE
    assert _counted(seen) == 1  # the car, once


def _stops_at(t_stop: float, decel: float | None):
    """Motion at 15 m/s towards the camera until t_stop, then a stop: at once (decel None) or braking."""
    def motion(t: float) -> tuple[float, float]:
        if t < t_stop:
            return -15.0 * t, -15.0
        if decel is None:
            return -15.0 * t_stop, 0.0
        u = min(t - t_stop, 15.0 / decel)
        return -15.0 * t_stop - 15.0 * u + 0.5 * decel * u * u, -15.0 + decel * u
    return motion


@pytest.mark.parametrize("decel", [None, 8.0])
def test_a_group_that_stops_dead_has_lost_its_vehicle_but_a_braking_car_stands(decel):
    """A reported car's features stop dead at 1.2 s, 15 m/s one frame and nothing the next: its moving features
    went (lost, or the car drove out from under them) and the ones left stand on the road, which no vehicle
    does. The vehicle is lost there: its group is not kept as a vehicle standing in the lane (that would add
    time and no distance to the lane's Edie sums and pull its space-mean speed down). A car braking hard (8
    m/s^2, standing from 3.1 s) is a vehicle standing in its lane to the end."""
    car = (_box(-1.0, 1.0, 50.0, 54.5, 10, 41), _stops_at(1.2, decel), 2, 0, 0.0)
    seen = _run([car], frames=100)
    assert len(seen) == 1, {k: len(v) for k, v in seen.items()}
    states = seen[min(seen)]
    if decel is None:
        # past its detection zone, so finished where it was lost (not at the exit zone)
        assert 1.1 < states[-1].t <= 1.2 + 0.2 + DT and states[-1].finished and not states[-1].exited
    else:
        assert states[-1].t == pytest.approx(99 * DT) and abs(states[-1].vy) < 0.5
        assert states[-1].y_front == pytest.approx(50.0 - 18.0 - 15.0 ** 2 / 16.0, abs=0.5)


def test_a_group_whose_features_latch_onto_an_edge_has_lost_its_vehicle():
    """A reported car's features stop dead at 1.2 s (they latched onto an overhead sign's edge as the car drove
    out from under it) while their filtered speeds fall off slowly (15 m/s, halving every 0.2 s): the group
    reads standing only at 2.0 s, too late for the features' own fall (DEAD_STOP_S). Its near end stood from
    15 m/s at once, which no vehicle does: it is lost, not kept standing in its lane adding time to Edie."""
    def latched(t: float) -> tuple[float, float]:
        if t < 1.2:
            return -15.0 * t, -15.0
        return -15.0 * 1.2, -15.0 * 0.5 ** ((t - 1.2) / 0.2)

    car = (_box(-1.0, 1.0, 50.0, 54.5, 10, 41), latched, 2, 0, 0.0)
    seen = _run([car], frames=100)
    assert len(seen) == 1, {k: len(v) for k, v in seen.items()}
    states = seen[min(seen)]
    assert 1.6 < states[-1].t <= 2.2 and states[-1].finished and not states[-1].exited, states[-1]


def test_a_vehicle_passing_a_standing_feature_is_never_grouped_with_it():
    """A corner left standing on an overhead sign's edge (settled, not moving) must not join the next
    vehicle that emerges beside it: features first seen together link when they are close, and this one
    would hold the vehicle's group back. New features on a vehicle that stands in a queue (not moving
    either) still join it."""
    site = parse_site(site_dict())
    g = Grouper(site.tracking, SiteZones(site))
    n = site.tracking.max_features
    s, px = np.zeros((n, 4)), np.zeros((n, 2))
    lane, alive, age = np.zeros(n, np.int32), np.zeros(n, np.bool_), np.zeros(n, np.int32)
    edge = 0  # the standing corner at Y = 60
    car = np.arange(1, 7)  # the emerging car's corners, born 1-2 m from it, moving at 15 m/s
    queued = np.arange(7, 13)  # a car standing in the next lane: 4 corners, then 2 more born on it
    pts = _box(0.6, 2.4, 56.0, 59.5, len(car), 6)
    q_pts = _box(-2.9, -1.1, 50.0, 54.0, len(queued), 7)
    shared = []
    for f in range(40):
        t = f * DT
        s[edge], px[edge], lane[edge], alive[edge], age[edge] = (1.5, 60.0, 0.0, 0.0), (1.5, -60.0), 2, True, f
        if f >= 10:
            if f == 10:
                g.reset_slots(car)
            d = -15.0 * (t - 10 * DT)
            for i, (x, y) in zip(car, pts):
                s[i], px[i] = (x, y + d, 0.0, -15.0), (x, -(y + d))
                lane[i], alive[i], age[i] = 2, True, f - 10
        for k, (i, (x, y)) in enumerate(zip(queued, q_pts)):
            born = 0 if k < 4 else 20
            if f >= born:
                if f == born:
                    g.reset_slots(np.array([i]))
                s[i], px[i] = (x, y, 0.0, 0.0), (x, -y)
                lane[i], alive[i], age[i] = 1, True, f - born
        g.step(t, s, px, lane, alive, age)
        if f >= 10 and g.fvid[edge] >= 0 and g.fvid[edge] in g.fvid[car]:
            shared.append(round(t, 2))
    assert not shared, f"the standing corner was grouped with the passing car at t = {shared}"
    assert len(set(g.fvid[queued].tolist())) == 1, "new corners on a standing car stay apart from it"


def test_a_vehicles_place_across_the_road_is_its_footprints_middle_not_its_lowest_corner():
    """The measures place a vehicle in a lane by its x. Its lowest feature (the representative point) may be a
    corner at its side, here 0.2 m inside lane 2 (0 - 3.5 m) on a car spanning 0.2 - 2.0 m: its x is the
    middle of its low features (about 1.1 m), so it is never taken for a vehicle of lane 1."""
    rng = np.random.default_rng(5)
    pts = np.vstack([[0.2, 44.0], np.column_stack([rng.uniform(0.2, 2.0, 11), rng.uniform(44.3, 47.5, 11)])])
    seen = _run([(pts, -15.0, 2, 0, 0.0)], frames=60)
    xs = [st.x for ss in seen.values() for st in ss]
    assert xs and all(abs(x - 1.1) < 0.4 for x in xs), xs


def test_road_texture_uncovered_behind_a_receding_vehicle_is_not_its_near_end():
    """Corners on the road just uncovered behind a receding car (0.3 m behind its rear, a new one every
    third frame) are linked to it before their speed shows. They are not its near end: once its own
    features have settled its reported speed stays 15 m/s (within 10 %) in every report."""
    lanes = RECEDING_BESIDE_APPROACHING
    car = (_box(-2.6, -0.9, 10.0, 14.0, 12, 7), 15.0, 1, 0, 0.0)
    texture = [(np.array([[-1.75 + 0.1 * (f % 5), 10.0 + 15.0 * f * DT - 0.3]]), 0.0, 1, f, 0.0)
               for f in range(12, 33, 3)]
    seen = _run([car, *texture], frames=50, lanes=lanes)
    assert len(seen) == 1, {k: len(v) for k, v in seen.items()}
    settled = [st for ss in seen.values() for st in ss if st.t >= 0.5]
    assert settled and all(abs(st.vy - 15.0) < 1.5 for st in settled), [round(st.vy, 1) for st in settled]


def _lane_1_grouper(lanes=None) -> tuple[Grouper, LaneZones]:
    """A grouper on the test site (with these lanes) and its first lane's zones."""
    site = parse_site(_site(lanes))
    zones = SiteZones(site)
    return Grouper(site.tracking, zones), zones.by_index(1)


def test_a_vehicle_found_again_where_one_was_lost_has_not_entered_the_view():
    """The `entered` flag of a first report (the measures count a vehicle entering already over its count
    line): first seen in its lane's detection zone, but not within REFOUND_M of where a reported vehicle of
    its lane lost in the last LOST_KEEP_S could be by then (found again, it was counted before)."""
    from appliance.grouping import LOST_KEEP_S, REFOUND_M, Lost

    g, lz = _lane_1_grouper()
    y_in = 0.5 * (lz.detection_y[0] + lz.detection_y[1])
    tr = VehicleTrack(id=5, first_t=10.0, lane_index=1, trajectory=[(10.0, 0.0, y_in)])

    def entered(track: VehicleTrack, t: float) -> bool:
        return g._entered(track, VehicleState(track.id, t, 0.0, y_in, y_in + 4.5, 0.0, 0.0, 4.5, 6), 0.0)

    assert entered(tr, 10.0)
    g.lost.append(Lost(9.0, 1, y_in + 0.5 * REFOUND_M, 0.0))  # lost standing
    assert not entered(tr, 10.0)
    assert entered(tr, 9.0 + LOST_KEEP_S + 1.0)  # long gone
    g.lost.append(Lost(9.0, 2, y_in, 0.0))  # another lane's
    assert entered(tr, 10.0)
    # lost at 25 m/s (approaching: y falls): 1 s later it is 12-25 m on, not where it was lost, and a new group
    # there 20 m on is it found again; one lost 0.04 s before a new group is first seen 1 m on is handed over
    sign = lz.sign
    g.lost = [Lost(9.0, 1, y_in, 25.0)]
    assert entered(tr, 10.0)
    g.lost = [Lost(9.0, 1, y_in - sign * 20.0, 25.0)]
    assert not entered(tr, 10.0)
    g.lost = [Lost(9.96, 1, y_in - sign * 1.0, 25.0)]
    assert not entered(tr, 10.0)
    outside = VehicleTrack(id=6, first_t=10.0, lane_index=1, trajectory=[(10.0, 0.0, lz.exit_y[0])])
    assert not entered(outside, 10.0)


def test_a_vehicle_passing_at_speed_where_a_slow_one_was_lost_has_entered_the_view():
    """A new group first seen where a vehicle crawling at 1.8 m/s was lost 5 s before (clutter that a passing
    vehicle's features moved for a moment) is that vehicle found again only if its near end moves no faster
    than it could by accelerating from there (LOST_ACCEL_MPS2 over the distance on, its near end allowed
    REFOUND_M behind; plus LOST_SPEED_SLACK_MPS): at 3 m/s it may be, at 20 m/s it has entered the view
    (found again, it was never extended back to its region's entry)."""
    from appliance.grouping import LOST_ACCEL_MPS2, LOST_SPEED_SLACK_MPS, REFOUND_M, Lost

    g, lz = _lane_1_grouper()
    sign = lz.sign
    y_in = 0.5 * (lz.detection_y[0] + lz.detection_y[1])
    # first seen 1 m behind where the slow one was lost, reported 2 m on from there
    tr = VehicleTrack(id=5, first_t=10.0, lane_index=1,
                      trajectory=[(10.0, 0.0, y_in - sign * 1.0), (10.3, 0.0, y_in + sign * 2.0)])

    def entered(speed: float) -> bool:
        y = y_in + sign * 2.0
        return g._entered(tr, VehicleState(5, 10.3, 0.0, y, y - sign * 4.5, 0.0, sign * speed, 4.5, 6), 0.0)

    g.lost = [Lost(5.0, 1, y_in, 1.8)]
    top = (1.8 ** 2 + 2.0 * LOST_ACCEL_MPS2 * (2.0 + REFOUND_M)) ** 0.5 + LOST_SPEED_SLACK_MPS  # 11.1 m/s
    assert not entered(3.0)
    assert not entered(top - 0.1)
    assert entered(top + 0.1)
    assert entered(20.0)
    assert len(g.lost) == 1  # still there for the vehicle itself


@pytest.mark.parametrize("reported_s", [0.2, 1.0])
@pytest.mark.parametrize("found_past_line", [True, False])
def test_a_vehicle_lost_soon_after_its_report_is_found_again_only_past_its_count_line(reported_s,
                                                                                      found_past_line):
    """A reported vehicle whose features are all lost in its detection zone is remembered (it may be found
    again). One lost within LOST_MIN_REPORTED_S of its report, mostly a group on clutter that a passing
    vehicle moved for a moment (one at the same spot every few seconds held off every vehicle first seen
    there), is found again only past its count line: a car at 8 m/s hidden by a van right after its report
    and found again 2 s later past its line still counts there once, but a vehicle first seen where it stood
    has entered the view."""
    from appliance.grouping import LOST_MIN_REPORTED_S

    g, lz = _lane_1_grouper()
    sign, line = lz.sign, lz.count_y
    y = lz.detection_y[0] + 0.5 if sign < 0 else lz.detection_y[1] - 0.5
    lost = VehicleTrack(id=9, first_t=9.0, lane_index=1, trajectory=[(9.5, 0.0, y - sign * 4.0), (10.0, 0.0, y)])
    lost.reported, lost.report_t = True, 10.0 - reported_s
    lost.last = VehicleState(9, 10.0, 0.0, y, y - sign * 4.5, 0.0, sign * 8.0, 4.5, 6)
    out: list[VehicleState] = []
    g._lose(lost, 10.0, out)
    assert not out and len(g.lost) == 1  # short of its exit: remembered, not finished
    y0 = line + sign * 2.0 if found_past_line else y
    tr = VehicleTrack(id=10, first_t=12.0, lane_index=1, trajectory=[(12.0, 0.0, y0), (12.04, 0.0, y0 + sign * 0.3)])
    st = VehicleState(10, 12.08, 0.0, y0 + sign * 0.6, y0 + sign * 0.6 - sign * 4.5, 0.0, sign * 8.0, 4.5, 6)
    st.trajectory = list(tr.trajectory)
    entered = g._entered(tr, st, 0.0)
    if found_past_line:  # found again past the line it was lost short of: it starts there and counts once
        assert not entered and st.trajectory[0][0] == 10.0 and not g.lost
    else:
        assert entered == (reported_s < LOST_MIN_REPORTED_S)


@pytest.mark.parametrize("found_past_line", [True, False])
def test_a_vehicle_lost_in_its_detection_zone_and_found_again_past_its_count_line_counts_there_once(
        found_past_line):
    """A car at 8 m/s loses all its features at the end of its detection zone (hidden by a van in the next
    lane) and is found again 2 s later, 2 m past its count line: it starts from where it was lost, so that it
    crosses the line and counts once. Found again short of the line, it crosses it on its own."""
    from appliance.grouping import Lost

    g, lz = _lane_1_grouper()
    sign, line = lz.sign, lz.count_y
    y_lost = lz.detection_y[0] + 0.5 if sign < 0 else lz.detection_y[1] - 0.5
    g.lost.append(Lost(8.0, 1, y_lost, 8.0, -1.7, y_lost))
    y0 = line + sign * (2.0 if found_past_line else -3.0)
    tr = VehicleTrack(id=7, first_t=10.0, lane_index=1, trajectory=[(10.0, -1.7, y0), (10.04, -1.7, y0 + sign * 0.3)])
    st = VehicleState(7, 10.08, -1.7, y0 + sign * 0.6, y0 + sign * 0.6 - sign * 4.5, 0.0, sign * 8.0, 4.5, 6)
    st.trajectory = list(tr.trajectory)
    assert not g._entered(tr, st, 0.0)  # found again: it did not enter the view here
    ys = [p[2] for p in st.trajectory] + [st.y_front]
    assert sum((a - line) * sign < 0 <= (b - line) * sign for a, b in zip(ys, ys[1:])) == int(found_past_line)
    assert st.trajectory[0][0] == (8.0 if found_past_line else 10.0)
    assert len(g.lost) == (0 if found_past_line else 1)  # found once only


@pytest.mark.parametrize("gap_m, bridge_y", [(6.0, (44.5,)), (6.0, (43.0, 46.0)), (14.0, (44.0, 48.0, 52.0))],
                         ids=["one corner", "two corners", "a chain"])
def test_new_features_between_two_queued_vehicles_do_not_join_them(gap_m: float, bridge_y: tuple):
    """In a queue two cars follow each other at the same crawl, each already a reported vehicle. Corners
    found between them (the leader's rear edge, the follower's bonnet) lie within the connection distance
    of one car or both, and of one another: linking them all would join the two vehicles for good, one
    count for two. A new corner keeps the links to one vehicle at most, and new corners that would still
    join two vehicles through one another keep only their own vehicle's."""
    leader = (_box(-1.0, 1.0, 40.0, 41.5, 6, 12), -5.0, 2, 0, 0.0)
    follower = (_box(-1.0, 1.0, 41.5 + gap_m, 45.5 + gap_m, 6, 13), -5.0, 2, 0, 0.0)
    bridges = [(np.array([[0.0, y]]), -5.0, 2, 20, 0.0) for y in bridge_y]  # found when both were reported
    seen = _run([leader, follower, *bridges], frames=150)
    assert _counted(seen) == 2, _firsts(seen)


@pytest.mark.parametrize("case, kept_by_front", [
    ("one speed", True), ("rear part raised", False), ("both crawling", False), ("front standing", False),
    ("front too small", False), ("front mostly another group's", False), ("front another group's id", False),
    ("receding", False)])
def test_an_approaching_vehicle_come_apart_keeps_its_id_in_its_front_where_both_parts_move_at_one_speed(
        case, kept_by_front):
    """Vehicle 7's group (a car and the car behind it, joined for a while) has come apart: its near end's
    feature is in the smaller part, the front (6 features), which assign_ids gave a new id, 9; the other part, 10
    features, kept 7. At one speed the two are two vehicles: 7, with its count and near end, goes with the
    front and the car behind becomes 9. A rear part moving faster in projection is a raised part of the front;
    parts crawling below MOVING_MPS, a near end on something standing, a front too small to be a vehicle, one
    mostly of another group's features or carrying an existing group's id (the car behind would take over that
    group's history), and a receding vehicle (counted by its far end) keep the ids assign_ids gave."""
    g, _ = _lane_1_grouper(RECEDING_BESIDE_APPROACHING if case == "receding" else None)
    n = g.p.max_features
    s, age = np.zeros((n, 4)), np.full(n, 20, np.int32)
    front, rest = np.arange(6), np.arange(6, 16)
    if case == "front too small":
        front, rest = np.arange(2), np.arange(2, 16)
    s[front, 1], s[rest, 1] = np.linspace(10.0, 12.0, len(front)), np.linspace(19.0, 25.0, len(rest))
    speed = {"both crawling": -2.0}.get(case, -15.0)
    s[front, 3], s[rest, 3] = speed, speed * (1.3 if case == "rear part raised" else 1.0)
    if case == "front standing":
        s[front, 3] = 0.0
    before = np.full(n, -1, np.int64)
    before[:16] = 7
    if case == "front mostly another group's":
        before[front[1:]] = 9
    g.tracks[7] = VehicleTrack(id=7, first_t=0.0, lane_index=1, reported=True, near_slot=0)
    if case == "front another group's id":
        g.tracks[9] = VehicleTrack(id=9, first_t=0.0, lane_index=1)
    g.fvid[:] = -1
    g.fvid[rest], g.fvid[front] = 7, 9  # as assign_ids left them: 7 where most of its features are
    groups = {7: rest.copy(), 9: front.copy()}
    g._front_keeps_id(groups, before, s, age)
    expect_7, expect_9 = (front, rest) if kept_by_front else (rest, front)
    assert np.array_equal(groups[7], expect_7) and np.array_equal(groups[9], expect_9), groups
    assert (g.fvid[expect_7] == 7).all() and (g.fvid[expect_9] == 9).all()


def test_a_queued_car_with_few_features_left_is_not_joined_to_the_one_behind_by_a_new_corner():
    """A car reported long ago has lost most of its corners as it crawls in a queue (two left, fewer than a
    vehicle needs to be reported); a corner found between it and the car behind lies within the connection
    distance of both. Linking it to both would join the two for good, one count for two: it keeps to one.
    (The exception, a group that small and that new which a re-check has matched to a vehicle, so may still
    be that vehicle's top, is held by the sweep alone: without it trucks-and-buses gains extras.)"""
    kept = (_box(-1.0, 1.0, 50.0, 50.5, 2, 14), -5.0, 2, 0, 0.0)
    lost = (_box(-1.0, 1.0, 50.5, 51.5, 4, 15), -5.0, 2, 0, 0.0, 45)  # gone 1.8 s in, 1.6 s after its report
    follower = (_box(-1.0, 1.0, 57.5, 61.5, 6, 16), -5.0, 2, 0, 0.0)
    bridge = (np.array([[0.0, 54.5]]), -5.0, 2, 60, 0.0)  # 4.1 and 3.2 m from the two cars' nearest corners
    seen = _run([kept, lost, follower, bridge], frames=180)
    assert _counted(seen) == 2, _firsts(seen)


def test_a_near_end_held_at_the_image_edge_does_not_slow_the_vehicle():
    """A receding vehicle entering at the image's bottom edge: its lowest visible point stays at the edge
    until its rear is in view, while its features move at its speed. The speed of that held point is a
    fraction of the vehicle's; the vehicle's speed over a while is the faster of the two."""
    held = VehicleTrack(id=1, first_t=0.0, lane_index=1)
    held.trajectory = [(0.04 * i, 4.0, 20.0 + max(0, i - 8) * 1.0) for i in range(13)]  # held for 0.32 s
    assert held.steady_vy(25.0) == pytest.approx(25.0)
    # asked again (cached): the same rule; its steps' median is the standstill, so the features' speed
    assert held.steady_vy(5.0) == pytest.approx(5.0)
    moving = VehicleTrack(id=2, first_t=0.0, lane_index=1)
    moving.trajectory = [(0.04 * i, 4.0, 20.0 + 1.0 * i) for i in range(13)]  # moving with its features
    assert moving.steady_vy(24.0) == pytest.approx(25.0)
    moving.trajectory = moving.trajectory[:4]  # under 0.2 s: only the features' speed
    assert moving.steady_vy(24.0) == pytest.approx(24.0)


def test_a_near_end_that_jumps_does_not_speed_the_vehicle_up():
    """An approaching van's windscreen corners are found first; a frame later the corner of its shadow on the
    road joins them, lower in the image: the near end jumps 9 m towards the camera in one step. The van's speed
    over the last half second is still its own (26 m/s), not that jump spread over the window (44 m/s): the
    speed its neighbours compare it by, to find it is the shadow and top of a van in the next lane."""
    van = VehicleTrack(id=1, first_t=0.0, lane_index=1)
    van.trajectory = [(0.04 * i, -4.9, 80.0 - 1.04 * i - (9.0 if i >= 9 else 0.0)) for i in range(13)]
    assert van.steady_vy(-20.0) == pytest.approx(-26.0)
    assert (van.trajectory[-1][2] - van.trajectory[0][2]) / 0.48 < -40.0  # what the run over the window says


@pytest.mark.parametrize("edge_rule", [True, False])
def test_a_near_end_leaving_the_image_at_its_bottom_goes_on_at_the_vehicles_speed(monkeypatch, edge_rule):
    """A camera drifted 80 px: the image now ends above the lane's exit zone. An approaching car's features
    are dropped as they reach the image's bottom (the tracker's search window leaves the image), its front
    corners first; the rest lie 2.5 m and more behind. Its near end goes on at the car's speed from then on,
    and the car reaches its exit zone; held where the front corners were lost (the rule off), it stands for
    the time the next features take to get there, and the car is lost short of the exit."""
    import appliance.grouping as grouping

    if not edge_rule:
        monkeypatch.setattr(grouping, "EDGE_ROWS_K", 0.0)
    site = parse_site(site_dict())
    zones = SiteZones(site)
    g = Grouper(site.tracking, zones)
    n = site.tracking.max_features
    s, px = np.zeros((n, 4)), np.zeros((n, 2))
    lane, alive, age = np.zeros(n, np.int32), np.zeros(n, np.bool_), np.zeros(n, np.int32)
    body = np.array([[0.9, 0.0], [2.4, 0.05], [1.2, 2.5], [2.2, 2.8], [1.5, 3.4], [2.0, 4.1]])
    g.reset_slots(np.arange(len(body)))
    last_row = zones.height - 8  # the tracker drops a feature whose search window leaves the image
    lost_at, states = None, []
    for f in range(80):
        t = f * DT
        front = 30.0 - 15.0 * t
        for i, (x, dy) in enumerate(body):
            row = zones.H.road_to_img(np.array([[x, front + dy]]))[0] + [0.0, 80.0]  # the drift
            alive[i] = alive[i] or f == 0
            if alive[i] and row[1] >= last_row:
                alive[i] = False
                lost_at = t if lost_at is None else lost_at
            s[i], px[i] = (x, front + dy, 0.0, -15.0), row
            lane[i], age[i] = 2, f
        out, retire = g.step(t, s, px, lane, alive, age)
        alive[retire] = False
        states += out
        if any(st.finished for st in out):
            break
    after = [st for st in states if lost_at is not None and st.t >= lost_at - 1e-9]
    assert len(after) >= 3 and after[-1].finished
    speed = (after[0].y_front - after[-1].y_front) / (after[-1].t - after[0].t)
    if edge_rule:
        assert speed == pytest.approx(15.0, rel=0.1) and after[-1].exited
    else:
        assert speed < 0.6 * 15.0 and not after[-1].exited


def test_a_vehicle_seen_only_by_its_lights_is_reported_at_a_typical_length():
    """At night an approaching vehicle is its headlights: nothing of its body behind them is seen, so its
    length is not measured as the lights' few centimetres but reported as a typical car's (NOMINAL_LENGTH_M:
    between 4 and 5 m)."""
    lights = (_box(-2.5, -1.0, 44.0, 44.2, 6, 7), -15.0, 1, 0, 0.6)
    seen = _run([lights], frames=60)
    states = [st for ss in seen.values() for st in ss if not st.finished and st.y_front < 20.0]  # followed 24 m
    assert states, seen
    assert all(4.0 <= st.length <= 5.0 and st.length == states[0].length for st in states), \
        [round(st.length, 2) for st in states]


def test_a_motorcycle_showing_its_rider_behind_its_wheel_is_not_given_a_cars_length():
    """An approaching motorcycle: its front wheel and fork low, its rider 0.5-0.8 m further back. Unlike
    lights alone, that shows some of its extent (FIT_MIN_EXTENT_M: 0.5 m), so it is measured, not given the
    nominal car's length: it stays in the motorcycle length class (under 2.1 m; 0.93 m here, 4.5 m if the
    extent needed were 1 m)."""
    front = 44.0
    wheel = (_box(-1.9, -1.6, front, front + 0.3, 4, 7), -15.0, 1, 0, 0.5)
    rider = (_box(-1.9, -1.6, front + 0.5, front + 0.8, 4, 8), -15.0, 1, 0, 1.3)
    seen = _run([wheel, rider], frames=60)
    assert len(seen) == 1, seen
    states = [st for st in next(iter(seen.values())) if not st.finished and st.y_front < 35.0]  # fitted by then
    bound = MeasuresConfig().length_class_bounds_m[0]
    assert states and all(0.5 <= st.length < bound for st in states), [round(st.length, 2) for st in states]


def test_a_receding_vehicles_extent_starts_at_its_near_end():
    """The near end of a receding vehicle is its rear (nearest the camera); its front is a roofline
    projected beyond it. The span it surely covers runs from the rear, whatever fragments lengthened its
    features' span since its own length was taken."""
    from appliance.grouping import _extent
    from appliance.types import VehicleState

    receding = VehicleState(id=1, t=0.0, x=5.0, y_front=56.0, y_rear=28.4, vx=0.0, vy=24.0, length=27.6,
                            n_features=30)
    lo, hi = _extent(receding, 18.9)
    assert lo <= 28.4 + 1.0 <= hi and hi == pytest.approx(28.4 + 18.9 + 1.0)
    approaching = VehicleState(id=2, t=0.0, x=1.0, y_front=40.0, y_rear=52.0, vx=0.0, vy=-24.0, length=12.0,
                               n_features=30)
    assert _extent(approaching, 3.0) == pytest.approx((39.0, 40.0 + 4.5 + 1.0))  # at least a car's length


def test_a_roof_fragment_does_not_hold_two_queued_cars_together_once_they_part():
    """Two cars crawl 6 m apart at one speed: the pair graph joins them (closer than connection_m), and the
    follower's roof, a group of its own (projected further), joins that one vehicle as a fragment for good.
    When the leader then pulls away the two cars come apart, the roof staying with the follower (it shares
    more pairs with it), instead of the roof holding them together as one vehicle to the end."""
    def pull_away(t: float) -> tuple[float, float]:
        late = max(t - 1.2, 0.0)
        return -5.0 * t - 1.5 * late ** 2, -5.0 - 3.0 * late

    leader = (_box(-1.0, 1.0, 40.0, 41.5, 6, 21), pull_away, 2, 0, 0.0)
    follower = (_box(-1.0, 1.0, 46.0, 49.0, 9, 22), -5.0, 2, 0, 0.0)
    roof = (_box(-0.8, 0.8, 46.5, 48.5, 6, 23), -5.0, 2, 12, 2.6)

    def sizes_at(seen: dict[int, list], t: float) -> list[int]:
        return sorted(st.n_features for ss in seen.values() for st in ss if abs(st.t - t) < 1e-6)

    assert sizes_at(_run([leader, follower, roof], frames=30), 1.16) == [21]  # one vehicle with its roof
    assert sizes_at(_run([leader, follower, roof], frames=90), 3.52) == [6, 15]  # the leader apart
    # at one speed they stay one vehicle: the pair graph's tolerance is not what parts them
    assert sizes_at(_run([(leader[0], -5.0, 2, 0, 0.0), follower, roof], frames=90), 3.52) == [21]


def test_the_near_end_follows_the_lowest_feature_and_does_not_creep_ahead_of_the_vehicle():
    """A car's two lowest corners lie at its front, 5 cm apart, each measured with 8 cm of noise, so which of
    them is lowest changes from frame to frame; like any feature above the road they read 3 % fast. The near
    end stays with the lowest corner (never ahead of the front by more than the noise) and covers the car's
    distance: a near end carried on at the features' speed whenever the lowest corner changes creeps ahead
    of the car, and its speed reads high."""
    site = parse_site(site_dict())
    g = Grouper(site.tracking, SiteZones(site))
    n = site.tracking.max_features
    s, px = np.zeros((n, 4)), np.zeros((n, 2))
    lane, alive, age = np.zeros(n, np.int32), np.zeros(n, np.bool_), np.zeros(n, np.int32)
    rng = np.random.default_rng(5)
    body = np.array([[-0.8, 0.0], [0.7, 0.05], [-0.6, 1.2], [0.5, 2.0], [-0.2, 3.1], [0.6, 4.2]])
    members = np.arange(len(body))
    g.reset_slots(members)
    fronts, states = {}, []
    for f in range(70):
        t = f * DT
        front = 70.0 - 20.0 * t
        fronts[t] = front
        noise = np.r_[rng.normal(0.0, 0.08, 2), np.zeros(len(body) - 2)]
        for i, (x, dy) in enumerate(body):
            y = front + dy + noise[i]
            s[i], px[i] = (x, y, 0.0, -20.6), (x, -y)
            lane[i], alive[i], age[i] = 2, True, f
        out, _ = g.step(t, s, px, lane, alive, age)
        states += [st for st in out if not st.finished]
    assert len(states) > 40
    assert min(st.y_front - fronts[st.t] for st in states) > -0.25
    a, b = states[0], states[-1]
    assert (a.y_front - b.y_front) / (fronts[a.t] - fronts[b.t]) == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("joined", [True, False])
def test_a_trucks_box_seen_beyond_its_cab_and_over_the_next_lane_joins_it_where_the_image_shows_one_body(joined):
    """Only a truck's cab is seen low (its first 2.5 m); its box top, 3.8 m up and 4 to 11 m behind the front,
    is a group of its own whose features lie over the next lane (seen from beside the road). Projected by its
    height it lies beyond what is seen of the truck. Where the image between the two is the truck's body
    throughout, the top joins the truck; where it shows road between them (two vehicles), it stays a vehicle
    of its own."""
    cab = (_box(-0.2, 1.2, 44.0, 46.5, 10, 51), -15.0, 2, 0, 0.0)
    top = (_box(-1.2, -0.6, 48.0, 55.0, 8, 52), -15.0, 1, 12, 3.8)
    seen = _run([cab, top], joined=joined)
    assert _counted(seen) == (1 if joined else 2), {k: len(v) for k, v in seen.items()}


@pytest.mark.parametrize("speed, length, joined, counted", [
    (9.0, 4.5, False, 2), (9.0, 4.5, True, 1), (9.0, 12.0, False, 2),
    (16.0, 4.5, False, 2), (16.0, 4.5, True, 1), (16.0, 12.0, False, 1),
])
def test_a_car_closing_in_the_next_lane_is_a_top_only_of_a_tall_vehicle_or_where_the_image_joins_them(
        speed, length, joined, counted):
    """A vehicle in lane 2 and one in lane 1, further from the camera's foot across the road, coming on 1.4 times
    as fast 30 m further up. The follower lies in projection just where a part 4 m up on the vehicle would (its
    place undone by the speed ratio falls on the footprint seen: a tall vehicle's top leans into the next lane),
    and keeps that place while both hold their speeds. Only a tall vehicle's top is seen over the next lane, and a
    tall vehicle is long: a car (4.5 m) is not, so there only the image between the two (the vehicle's body,
    not road) joins them. In congestion (below ADOPT_MIN_MPS) the same holds of a long vehicle: a follower there
    may run 1.4 times as fast as the traffic beside it. At 16 m/s none does, and beside a 12 m vehicle the place
    is enough (a truck's top)."""
    car = (_box(-3.0, -1.2, 40.0, 40.0 + length, 10, 61), -speed, 2, 0, 0.0)
    ahead = _run([car], lanes=LEFT_OF_CAMERA, joined=joined)
    cx, cy, _ = SiteZones(parse_site(site_dict(lanes=LEFT_OF_CAMERA))).camera
    k = 1.4
    y0 = cy + k * (40.0 + 2.0 - cy)  # 2 m behind the vehicle's front once k is undone
    follower = (_box(-4.8, -3.8, y0, y0 + 4.0, 8, 62), -speed * k, 1, 12, 0.0)
    seen = _run([car, follower], lanes=LEFT_OF_CAMERA, joined=joined)
    assert _counted(ahead) == 1 and cx == pytest.approx(0.0, abs=0.1)
    assert _counted(seen) == counted, _firsts(seen)


@pytest.mark.parametrize("behind, parts", [((15.5, 18.0), 1), ((21.5, 25.0), 2)])
def test_a_part_beyond_its_cab_joins_as_far_back_as_the_longest_vehicle_reaches(behind, parts):
    """ELEVATED_LENGTH_M (18.75 m, the longest vehicle allowed in the EU: a road train): its rear trailer's top,
    3.8 m up and 15.5 to 18 m behind the front of the cab seen low, joins the cab where the image between them is
    one body. A part 21.5 to 25 m behind is beyond the longest vehicle: a second vehicle whatever the image test
    says (a dark queue of cars reads as one body too)."""
    cab = (_box(-0.2, 1.2, 44.0, 46.5, 10, 53), -15.0, 2, 0, 0.0)
    top = (_box(-1.2, -0.6, 44.0 + behind[0], 44.0 + behind[1], 8, 54), -15.0, 1, 12, 3.8)
    seen = _run([cab, top], frames=110, joined=True)
    assert _counted(seen) == parts, {k: len(v) for k, v in seen.items()}


def test_a_vehicle_seen_only_as_small_groups_is_one_where_it_is_alone():
    """A car showing two features low (its bumper) and two on its roof: far away the two pairs lie further apart
    in projection than the connection distance (the roof's is magnified), and each is too small to be
    reported. Once closer they link (both settled and moving, nothing beside them) and the car counts."""
    bumper = (_box(0.8, 2.4, 58.0, 58.4, 2, 51), -15.0, 2, 0, 0.3)
    roof = (_box(1.0, 2.2, 59.0, 59.6, 2, 52), -15.0, 2, 0, 1.0)
    assert _counted(_run([bumper, roof])) == 1


def test_small_groups_beside_a_vehicle_or_over_it_do_not_link_into_a_vehicle_of_their_own():
    """Two small groups in the next lane moving with a car (its flank, or a mirror and its shadow) would link
    as a lone car's do and, with no image test to say they are its shadow, count as a vehicle: beside a
    vehicle they do not link. Nor do two small groups on a truck's box behind its cab (the cab's group is
    the vehicle; the box top is magnified beyond what the cab shows of it)."""
    car = (_box(1.0, 2.6, 56.0, 60.0, 6, 56), -15.0, 1, 0, 0.0)
    flank_low = (_box(5.4, 5.7, 57.0, 57.3, 2, 57), -15.0, 2, 0, 0.2)
    flank_high = (_box(5.4, 5.7, 54.1, 54.4, 2, 58), -15.0, 2, 0, 1.5)
    assert _counted(_run([flank_low, flank_high])) == 1  # alone, the two groups do link
    seen = _run([car, flank_low, flank_high], frames=80)  # (until the car leaves the view)
    assert _counted(seen) == 1 and len(seen) == 1, {k: len(v) for k, v in seen.items()}
    cab = (_box(0.8, 2.6, 44.0, 47.0, 6, 61), -15.0, 2, 0, 0.0)
    box_rear = (_box(1.0, 2.4, 52.0, 52.3, 2, 62), -15.0, 2, 0, 0.5)
    box_top = (_box(1.0, 2.4, 44.8, 45.1, 2, 63), -15.0, 2, 0, 2.5)
    seen = _run([cab, box_rear, box_top])
    assert len(seen) == 1, {k: len(v) for k, v in seen.items()}


def test_a_tall_plain_vehicle_seen_in_small_groups_at_its_heights_is_one_vehicle():
    """STACK_S: a tall van with few features (rain, a plain body) shows small groups of two at its bumper, its
    windscreen's foot and its roof's front edge, each fewer than a vehicle needs and further apart in projection than
    the connection distance, moving at their heights' magnifications (the pair graph parts what links them). Their
    distances from the camera's foot over their speeds agree (its front's time to the foot), and the image between
    them is one body: one vehicle, counted. Without that image test (the road seen between them) they stay apart,
    and nothing is counted. A car closing in on a car of its lane so as to reach the foot with it moves just so:
    only the image test (the road between them) keeps the two apart. Two cars of a lane at one speed 6 m apart are
    0.4 s apart in their times to the foot: never one vehicle, whatever the image test says."""
    van = [(_box(0.8, 2.6, 50.0, 50.4, 2, 71 + i), -15.0, 2, 0, h) for i, h in enumerate((0.3, 1.5, 3.0))]
    assert _counted(_run(van, joined=True)) == 1
    assert _counted(_run(van, joined=False)) == 0
    cy = SiteZones(parse_site(site_dict())).camera[1]
    leader = (_box(0.8, 2.6, 50.0, 50.4, 2, 74), -15.0, 2, 0, 0.3)
    closing = (_box(0.8, 2.6, 62.0, 62.4, 2, 75), -15.0 * (62.2 - cy) / (50.2 - cy), 2, 0, 0.3)
    assert _counted(_run([leader, closing], joined=True)) == 1
    assert _counted(_run([leader, closing], joined=False)) == 0
    apart = (_box(0.8, 2.6, 56.0, 56.4, 2, 76), -15.0, 2, 0, 0.3)
    assert _counted(_run([leader, apart], joined=True)) == 0


def test_the_spot_speed_is_the_bumpers_not_the_lights_above_it():
    """SPOT_M (1 m): the spot speed (count lines, loops, vehicle records) is the median of the settled features
    within this of the near end along the road: the bumper's (0.3 m up, 2.2 % fast in projection under this
    camera), not also the lights' (0.55 m up, 4 % fast), which lie 1.1-1.4 m further in projection near the
    count line and give the velocity together with the bumper (NEAR_REP_M). (From below this pins only a band
    of nothing: the synthetic features carry no noise, so one bumper feature reads as well as four.)"""
    ch = SiteZones(parse_site(site_dict())).camera[2]
    bumper = (_box(-1.0, 1.0, 50.0, 50.3, 4, 41), -15.0, 2, 0, 0.3)
    lights = (_box(-1.0, 1.0, 50.15, 50.3, 4, 42), -15.0, 2, 0, 0.55)
    seen = _run([bumper, lights], frames=80)
    assert len(seen) == 1, {k: len(v) for k, v in seen.items()}
    near_line = [st for st in next(iter(seen.values())) if abs(st.y_front - COUNT_Y) < 5.0]
    assert len(near_line) >= 10
    spot = np.median([abs(st.spot_vy) for st in near_line]) / 15.0
    vy = np.median([abs(st.vy) for st in near_line]) / 15.0
    assert spot == pytest.approx(ch / (ch - 0.3), abs=0.002)
    assert vy > spot + 0.007  # the lights do count in the velocity


@pytest.mark.parametrize("shadow_in_5, counted", [(2, 1), (4, 0)])
def test_a_group_the_image_test_takes_for_a_shadow_only_now_and_then_is_a_vehicle(shadow_in_5, counted):
    """LONE_SHADOW_SHARE (60 %): a young group is retired as a lone shadow (its caster lanes away or out of view;
    in the pipeline before its held report goes out) once, after LONE_SHADOW_S, this share of the image tests so
    far found only a shadow on the road. A dark car whose box the test takes for a shadow in 2 frames of 5 (its
    windows, the road showing past its edge) is a vehicle; one found a shadow in 4 of 5 is a shadow."""
    car = (_box(-1.0, 1.0, 52.0, 56.0, 10, 71), -12.0, 2, 0, 0.0)
    seen = _run([car], frames=80, shadow_seen=lambda f: f % 5 < shadow_in_5)
    assert _counted(seen) == counted, {k: len(v) for k, v in seen.items()}


@pytest.mark.parametrize("speed", [2.0, 5.0])
def test_a_car_creeping_over_the_count_line_in_a_queue_is_counted(speed):
    """MIN_SPEED_MPS (1.5 m/s): a group is reported once it has moved a metre (MIN_TRAVEL_M) at this speed or
    more: a queue creeping over the stop line at walking pace (2 m/s) is counted car by car, not only once it
    gets going, as is one rolling on at 5 m/s. (From below this pins nothing: the synthetic features of a
    standing object do not move at all.)"""
    car = (_box(-1.0, 1.0, COUNT_Y + 3.0, COUNT_Y + 7.0, 10, 72), -speed, 2, 0, 0.0)
    seen = _run([car], frames=90)
    assert _counted(seen) == 1, {k: len(v) for k, v in seen.items()}


def _lengths(seen: dict[int, list]) -> dict[int, float]:
    """Per vehicle: the longest length it was reported with."""
    return {vid: max(st.length for st in ss) for vid, ss in seen.items()}


@pytest.mark.parametrize("follower_corner_m", [0.0, 1.8])
def test_a_buses_lone_roof_corners_give_its_length_but_a_followers_corner_does_not(follower_corner_m):
    """A 12 m bus shows a group of corners low on its front and, far behind them in projection, a few lone corners
    along its roof's edge (3 m up), too far from each other to link. Each keeps 1.27 times the front's distance
    from the camera's foot plus a constant, and lies on the bus with that height undone: the bus is reported
    about 12 m long, and no corner of its roof is a vehicle. A lone corner of a car following 8 m behind at the
    same speed (one the tracker kept of it) does not make the car ahead longer: low on it, it moves like a part
    only at k 1, no part high on a vehicle; on its roof (a van's, 1.8 m up: k 1.22) it moves like a part 12.5 m
    back, but lower than a truck's or a bus's body, the only ones reaching that far."""
    front = (_box(0.8, 2.6, 38.0, 38.4, 10, 71), -16.0, 2, 0, 0.5)
    roof = [(np.array([[1.7, 38.0 + place]]), -16.0, 2, 0, 3.0) for place in (4.0, 8.0, 11.5)]
    seen = _run([front, *roof], frames=40, joined=True)
    assert len(seen) == 1, _firsts(seen)
    assert 10.0 <= next(iter(_lengths(seen).values())) <= 13.0, _lengths(seen)
    car = (_box(0.8, 2.6, 38.0, 38.4, 10, 72), -16.0, 2, 0, 0.5)
    follower = (np.array([[1.7, 38.0 + 4.5 + 8.0]]), -16.0, 2, 0, follower_corner_m)
    seen = _run([car, follower], frames=40, joined=True)
    assert max(_lengths(seen).values()) < 6.0, _lengths(seen)


def test_a_car_seen_only_at_its_front_is_a_car_but_a_motorcycle_stays_short():
    """A car whose features all lie on its front (bumper and bonnet, 1.2 m of it) measures far shorter than any car:
    as wide as a car low down, it is reported at a typical car's length, not put in the motorcycle class. A
    motorcycle with the same features over its 0.7 m width keeps its measured length."""
    for x0, x1, shortest, longest in ((0.8, 2.6, 4.0, 5.0), (1.4, 2.1, 0.5, 2.1)):  # 2.1 m: the motorcycle class
        vehicle = (_box(x0, x1, 38.0, 39.2, 10, 73), -16.0, 2, 0, 0.5)
        seen = _run([vehicle], frames=40)
        last = [ss[-1].length for ss in seen.values()]
        assert len(last) == 1 and shortest <= last[0] <= longest, (x0, x1, last)


def test_features_found_off_the_lanes_never_make_a_vehicle_of_their_own():
    """Corners found off the lanes (a tall vehicle's top leaning over the shoulder, see SiteZones._lifted) are
    no vehicle of their own: four moving together are never reported, nor does one make up the fourth corner
    (min_features) of a group with three in the lane; the same four found in the lane are a vehicle."""

    def reported(lifted: list[bool]) -> bool:
        site = parse_site(site_dict())
        g = Grouper(site.tracking, SiteZones(site))
        n = site.tracking.max_features
        s, px = np.zeros((n, 4)), np.zeros((n, 2))
        lane, alive, age = np.zeros(n, np.int32), np.zeros(n, np.bool_), np.zeros(n, np.int32)
        ground = [(-2.0, 70.0), (-1.5, 71.0), (-2.2, 72.0), (-1.2, 72.5)]
        g.reset_slots(np.arange(len(ground)), np.array(lifted))
        out = []
        for f in range(50):
            t = f * DT
            for i, (x, y) in enumerate(ground):
                s[i] = (x, y - 15.0 * t, 0.0, -15.0)
                px[i] = (100.0 + 10 * i, 100.0 + 3 * f)
                lane[i], alive[i], age[i] = 1, True, f
            states, _ = g.step(t, s, px, lane, alive, age)
            out += states
        return len(out) > 0

    assert parse_site(site_dict()).tracking.min_features == 4
    assert reported([False] * 4)
    assert not reported([True] * 4)
    assert not reported([False, False, False, True])


def test_the_tops_of_the_far_lanes_vehicles_are_searched_off_the_lanes_under_its_label():
    """Beyond the lane furthest from the camera's foot, where a truck's box in it is seen, corners are searched
    and labelled with that lane; on the lanes nothing changes (their own label). Not where the box's top is
    projected beyond the lane's far end: a feature placed there is dropped (zones.LANE_MARGIN_M)."""
    site = parse_site(site_dict())
    z = SiteZones(site)
    assert z.camera is not None and z.lifted_zone is not None
    assert not z.lifted_image[z.lane_image > 0].any()
    fx, fy, ch = z.camera
    far = max(z.lanes, key=lambda lz: abs(float(lz.polygon_m[:, 0].mean()) - fx))
    edge = far.polygon_m[:, 0].min() if far.polygon_m[:, 0].mean() < fx else far.polygon_m[:, 0].max()
    k = ch / (ch - 3.5)  # a box top 3.5 m high 0.3 m inside the lane's outer edge, near its detection zone's near end
    gx = edge + 0.3 * np.sign(fx - edge)

    def top(gy: float) -> np.ndarray:
        return z.H.road_to_img(np.array([[fx + k * (gx - fx), fy + k * (gy - fy)]]))

    gy = far.detection_y[0] + 6.0
    assert fy + k * (gy - fy) < far.y_extent[1]
    assert z.lane_at_px(top(gy))[0] == 0
    assert z.lane_at_px(top(gy), lifted=True)[0] == far.index
    on_lane = z.H.road_to_img(np.array([[float(far.polygon_m[:, 0].mean()), gy]]))
    assert z.lane_at_px(on_lane, lifted=True)[0] == z.lane_at_px(on_lane)[0] == far.index
    # the top of a box at the detection zone's far end is projected beyond the lane's: nothing is searched there
    gy = far.detection_y[1] - 1.0
    assert fy + k * (gy - fy) > far.y_extent[1] + LANE_MARGIN_M + 1.0
    assert z.lane_at_px(top(gy), lifted=True)[0] == 0


@pytest.mark.parametrize("n, counted", [(10, 1), (24, 2)])
def test_a_car_entering_beside_a_receding_car_long_in_projection_is_no_flank_of_it(n, counted):
    """Receding traffic enters at the image bottom, seen from beside the road, where a car near the camera is long
    in projection (8 m: its roof magnified). A group just across the lane line beyond it (where its raised parts
    lean), moving with it and the image between them one body, is its flank or top when smaller than it; one as
    big, together as wide as two cars side by side, is a car entering beside it and stays a vehicle."""
    lanes = (("receding", 0.0, 3.5), ("receding", 3.5, 7.0))
    car = (_box(0.2, 2.9, 10.0, 18.5, 24, 61), 10.0, 1, 0, 0.0)
    beside = (np.column_stack([np.linspace(3.3, 6.6, n), np.linspace(10.0, 12.5, n)]), 10.0, 2, 0, 0.0)
    seen = _run([car, beside], lanes=lanes, joined=True)
    assert _counted(seen, receding=True) == counted, _firsts(seen)


def test_a_corner_dragged_along_behind_a_receding_car_is_not_its_near_end():
    """A corner on the road just uncovered behind a receding car, whose flow reads 7 m/s for its first 4 frames
    (dragged by the car's edge) while it stands, is linked to the car before its speed settles. Moving at under half
    the car's speed it cannot be on the car (a part of a vehicle moves at least as fast as its bumper in
    projection): the car's near end stays on the car, never more than 0.5 m behind its rear."""
    lanes = RECEDING_BESIDE_APPROACHING
    car = (_box(-2.6, -0.9, 10.0, 14.0, 12, 7), 15.0, 1, 0, 0.0)
    dragged = [(np.array([[-1.75 + 0.1 * (f % 5), 10.0 + 15.0 * f * DT - 0.3]]),
                lambda t, born=f * DT: (0.0, 7.0 / SETTLING if t - born < 0.15 else 0.0), 1, f, 0.0)
               for f in range(12, 33, 3)]
    seen = _run([car, *dragged], frames=50, lanes=lanes)
    assert len(seen) == 1, {k: len(v) for k, v in seen.items()}
    rear_lag = [round(10.0 + 15.0 * st.t - st.y_rear, 2) for ss in seen.values() for st in ss]
    assert max(rear_lag) < 0.5, rear_lag


def _enter_at_bottom(d: dict, length: float) -> tuple[VehicleState | None, float | None, np.ndarray]:
    """A receding car this long (site d's lane 1, 15 m/s) entering the view at the image's bottom, front first:
    its corners appear as they come into view. Returns its first report, when its rear came into view, and the
    frame each corner was found in."""
    site = parse_site(d)
    zones = SiteZones(site)
    g = Grouper(site.tracking, zones)
    n = site.tracking.max_features
    s, px = np.zeros((n, 4)), np.zeros((n, 2))
    lane, alive, age = np.zeros(n, np.int32), np.zeros(n, np.bool_), np.zeros(n, np.int32)
    body = np.column_stack([np.linspace(-2.5, -1.0, 12), np.linspace(0.0, length, 12)])  # (x, ahead of the rear)
    last_row = zones.height - 8  # no corner is found or tracked lower (the tracker's search window)
    born = np.full(len(body), -1)
    rear0, speed, in_view_t, first = -4.0, 15.0, None, None
    for f in range(60):
        t = f * DT
        rear = rear0 + speed * t
        for i, (x, dy) in enumerate(body):
            row = zones.H.road_to_img(np.array([[x, rear + dy]]))[0]
            if row[1] < last_row and born[i] < 0:
                born[i] = f
                g.reset_slots(np.array([i]))
            if born[i] >= 0:
                s[i], px[i] = (x, rear + dy, 0.0, speed), row
                lane[i], alive[i], age[i] = 1, True, f - born[i]
        if in_view_t is None and alive[0]:
            in_view_t = t
        out, retire = g.step(t, s, px, lane, alive, age)
        alive[retire] = False
        first = first or next((st for st in out if st.trajectory), None)
    return first, in_view_t, born


def test_a_receding_vehicle_entering_at_the_image_bottom_starts_once_its_rear_is_in_view():
    """A receding car enters the view at the image's bottom, front first: its corners appear as they come
    into view, its lowest visible point stays at the edge until its rear is in view. Its trajectory starts
    no earlier than a frame before that (the point held at the edge is not where the car is: counted from
    when its front came into view, its time in the Edie region would run 0.2 s long)."""
    first, in_view_t, born = _enter_at_bottom(site_dict(lanes=RECEDING_BESIDE_APPROACHING), 4.4)
    assert in_view_t is not None and born.min() < born[0], "the car must enter front first"
    assert first is not None, "the car is never reported"
    assert first.trajectory[0][0] >= in_view_t - DT - 1e-9, (first.trajectory[0], in_view_t)


def test_a_receding_vehicle_begun_afresh_past_a_short_detection_zone_has_still_entered_the_view():
    """As above, where the rows in which a receding vehicle's trajectory begins afresh reach past its detection zone
    (a small frame: the tracker's reach is more of it) and the count line lies close to them: the car, its near end
    in the zone as it entered, is reported with its front already over the line (at a typical car's length, its own
    not yet measured) and its rear short of it. It has entered the view, and so counts where first reported
    (measures count a vehicle entering over its line only then); its first point past the zone said it was found
    again somewhere mid-view, and it was never counted."""
    d = site_dict(lanes=RECEDING_BESIDE_APPROACHING)
    d["lanes"][0].update(count_y_m=9.0, detection_y_m=[2.0, 4.0])
    first, _, _ = _enter_at_bottom(d, 3.0)
    assert first is not None, "the car is never reported"
    assert first.trajectory[0][2] - (first.y_front - first.y_rear) > 4.0, first.trajectory  # past the zone
    assert first.y_rear < 9.0 < first.y_front, first
    assert first.entered


@pytest.mark.parametrize("case, kept_apart", [
    ("two cars", True),
    ("a third vehicle's feature between them", True),
    ("the follower vanished", False),
    ("leader newly reported", False),
    ("near ends close", False),
    ("speeds differ", False),
    ("follower a raised part of the leader", False),
    ("leader left with too few features", False),
    ("crawling", False),
    ("other lane", False),
    ("receding", False),
])
def test_an_established_vehicle_run_into_the_one_behind_keeps_its_features(case, kept_apart):
    """Vehicles 7 (the leader, near end at 10 m) and 9 (12 m behind), both reported over RECHECK_S ago, have run
    into one group: assign_ids gave it 9, the one with more features. At one speed and a vehicle's length apart
    they are two cars that features between them linked: 7 gets its own features back, with the feature new to
    both that lies nearer it (a feature of a third reported vehicle stays where it is). Not where the one that
    vanished is the follower (a part behind, run into its vehicle), either is new (re-checks judge a new group),
    the two are closer than KEEP_APART_M, their speeds differ, the follower's height undone puts it on the leader
    (its raised part), the leader has fewer features than a vehicle needs, they crawl, they are of different
    lanes, or the lane recedes."""
    from appliance.grouping import KEEP_APART_M, RECHECK_S

    # receding: 7, nearer the camera, is behind 9 there (9 may be its raised part, seen ahead of it)
    g, _ = _lane_1_grouper(RECEDING_BESIDE_APPROACHING if case == "receding" else None)
    n = g.p.max_features
    t = 10.0
    s = np.zeros((n, 4))
    a, b, new = np.arange(5), np.arange(5, 13), np.array([13, 14])
    if case == "leader left with too few features":
        a = np.arange(g.min_report - 1)
    s[a, 1], s[b, 1], s[new, 1] = np.linspace(10.0, 13.0, len(a)), np.linspace(22.0, 26.0, 8), (15.0, 20.0)
    speed = {"crawling": -2.0, "receding": 15.0}.get(case, -15.0)
    s[:15, 3] = speed
    before = np.full(n, -1, np.int64)
    before[a], before[b] = 7, 9
    if case == "a third vehicle's feature between them":
        before[13] = 11
        g.tracks[11] = VehicleTrack(id=11, first_t=0.0, lane_index=1, reported=True)
    lead_y, follow_y = (10.0, 10.0 + 0.8 * KEEP_APART_M) if case == "near ends close" else (10.0, 22.0)
    if case == "the follower vanished":
        before[a], before[b] = 9, 7  # 7 is the follower now; 9 keeps the group
        lead_y, follow_y = follow_y, lead_y
    vy_7 = speed * (1.3 if case == "speeds differ" else 1.0)
    vy_9 = speed * (1.15 if case == "follower a raised part of the leader" else 1.0)
    for vid, y, vy, rep in ((7, lead_y, vy_7, t - 0.5 if case == "leader newly reported" else t - 2 * RECHECK_S),
                            (9, follow_y, vy_9, t - 2 * RECHECK_S)):
        tr = g.tracks[vid] = VehicleTrack(id=vid, first_t=0.0, lane_index=1, reported=True, report_t=rep)
        tr.trajectory = [(t - 0.04 * (11 - i), 0.0, y - vy * 0.04 * (11 - i)) for i in range(12)]
        tr.last = VehicleState(vid, t - 0.04, 0.0, y, y + 4.5, 0.0, vy, 4.5, 6)
    if case == "other lane":
        g.tracks[7].lane_index = 2
    g.fvid[:] = -1
    g.fvid[:15] = 9  # as assign_ids left them: one group, 9's
    groups = {9: np.arange(15)}
    g._keep_apart(t, groups, before, s, np.array(sorted(v for v, o in g.tracks.items() if o.reported)))
    if kept_apart:
        got_7 = [0, 1, 2, 3, 4] + ([13] if case == "two cars" else [])
        assert np.array_equal(groups[7], got_7), groups
        assert np.array_equal(groups[9], np.setdiff1d(np.arange(15), got_7)), groups
        assert (g.fvid[groups[7]] == 7).all() and (g.fvid[groups[9]] == 9).all()
    else:
        assert list(groups) == [9] and np.array_equal(groups[9], np.arange(15)) and (g.fvid[:15] == 9).all()


@pytest.mark.parametrize("roof_m, counted", [(26.0, 0), (41.0, 1)])
def test_a_vehicle_in_view_at_the_start_counts_only_if_it_crosses_once_its_features_settled(roof_m, counted):
    """The first features found of a vehicle past its count line may be its roof's alone: 1.4 m up and 3-4 m past
    the line on the road, it is projected 2-3 m short of it, and its near end crossing in the first frames is no
    count. One whose roof is seen 15 m further back crosses after its features settled and counts. (As in the
    pipeline, the first frame has no features: the tracker finds them in the second.)"""
    roof = (_box(-1.6, 1.6, roof_m, roof_m + 1.0, 6, 5), -25.0, 1, 1, 1.4)
    seen = _run([roof], frames=40)
    assert _counted(seen) == counted, _firsts(seen)


@pytest.mark.parametrize("speed, frames", [(-15.0, 120), (-3.0, 420)])
def test_a_vehicle_measured_longer_than_any_is_cut_at_the_widest_gap_between_the_two_it_holds(
        monkeypatch, speed, frames):
    """A car and the one 17 m behind it at one speed (at speed, or crawling), held in one group by three corners
    found on what lies between them (each within the connection distance of the next): one vehicle longer than
    any (LONGEST_M), whose follower never counts. Its features, placed on the road by their fits, are cut at the
    widest gap between them (4.8 m, two corners behind the car: the car keeps those two, and its id), and the
    follower counts as a vehicle of its own; without the rule the two count once. A 15 m bus whose features up
    to 2 m high reach 28 m in projection is measured on the road and stays whole."""
    from appliance import grouping

    gaps = np.array([3.5, 4.5, 4.8, 4.2])  # the car's rear, three corners, the follower's front
    ys = 44.5 + np.cumsum(gaps)
    leader = (np.vstack([_box(-1.0, 1.0, 40.0, 44.5, 8, 31), [[0.0, 44.5]]]), speed, 2, 0, 0.0)
    follower = (np.vstack([[[0.0, ys[-1]]], _box(-1.0, 1.0, ys[-1], ys[-1] + 4.5, 8, 32)]), speed, 2, 0, 0.0)
    chain = (np.column_stack([np.zeros(3), ys[:-1]]), speed, 2, 0, 0.0)
    assert ys[-1] + 4.5 - 40.0 > grouping.LONGEST_M and gaps.max() < 5.0  # too long for one; linked in a chain
    seen = _run([leader, follower, chain], frames=frames)
    assert _counted(seen) == 2, _firsts(seen)
    car = seen[min(seen)]  # the first vehicle reported: the car with all of them at first
    last = car[-1]
    assert abs(last.y_front - (40.0 + speed * last.t)) < 1.5 and last.n_features == 9 + 2, last  # and 2 corners
    monkeypatch.setattr(grouping, "LONGEST_M", np.inf)
    seen = _run([leader, follower, chain], frames=frames)
    assert _counted(seen) == 1, _firsts(seen)
    monkeypatch.undo()
    bus = [(_box(-1.2, 1.2, 40.0, 55.0, 6, 33 + i), -15.0, 2, 0, h) for i, h in enumerate((0.0, 0.5, 1.0, 1.5, 2.0))]
    seen = _run(bus, frames=120)
    assert _counted(seen) == 1, _firsts(seen)
