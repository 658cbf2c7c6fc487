"""TrafficMeasures on hand-made trajectories whose measures are known analytically."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from appliance.config import parse_site
from appliance.edie import clip_segments
from appliance.loops import STANDING, WAIT_S
from appliance.measures import LOST_AFTER_S, TrafficMeasures
from appliance.types import NO_VEHICLE, LoopSight, VehicleState

EPOCH = 1767225600.0  # 2026-01-01T00:00:00Z, a period boundary


def make_site(period_s: int = 300, loops: list[dict] | None = None, lanes: list[dict] | None = None):
    data = {
        "source": {"width": 640, "height": 480, "fps": 25.0},
        "calibration": {
            "image_px": [[0, 479], [639, 479], [0, 0], [639, 0]],
            "road_m": [[-5, 0], [5, 0], [-5, 100], [5, 100]],
        },
        "lanes": lanes or [
            {"id": 1, "direction": "approaching", "polygon_m": [[-5, 0], [0, 0], [0, 100], [-5, 100]],
             "region_y_m": [20.0, 80.0], "count_y_m": 50.0},
            {"id": 2, "direction": "receding", "polygon_m": [[0, 0], [5, 0], [5, 100], [0, 100]],
             "region_y_m": [20.0, 80.0], "count_y_m": 40.0},
        ],
        "loops": loops if loops is not None else [
            {"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8},
            {"id": "L1b", "lane": 1, "channel": 3, "y_m": 36.0, "length_m": 1.8, "trap_with": "L1"},
            {"id": "L2", "lane": 2, "channel": 2, "y_m": 60.0, "length_m": 1.8, "mode": "pulse"},
        ],
        "measures": {"period_s": period_s},
    }
    return parse_site(data, "test-site")


def approaching_pair(second_id: int, second_count_y: float) -> list[dict]:
    """Lane 1 (x -5..0, count line 50 m) and an approaching lane beside it (x 0..5) with this id and count line;
    both regions 80 -> 20 m."""
    return [
        {"id": 1, "direction": "approaching", "polygon_m": [[-5, 0], [0, 0], [0, 100], [-5, 100]],
         "region_y_m": [20.0, 80.0], "count_y_m": 50.0},
        {"id": second_id, "direction": "approaching", "polygon_m": [[0, 0], [5, 0], [5, 100], [0, 100]],
         "region_y_m": [20.0, 80.0], "count_y_m": second_count_y},
    ]


def platoon_states(t: float, speed: float, headway: float, length: float, lane: int, phase: float = 0.0,
                   id_base: int = 0):
    """Constant-speed vehicles every ``headway`` s entering at y=100 (lane 1) or y=0 (lane 2)."""
    out = []
    x = -2.5 if lane == 1 else 2.5
    j_lo = int(np.floor((t - phase - 100.0 / speed) / headway)) - 1
    j_hi = int(np.floor((t - phase) / headway)) + 1
    for j in range(j_lo, j_hi + 1):
        dt = t - (phase + j * headway)  # time since entering
        if dt < 0 or dt * speed > 100.0 + length:
            continue
        if lane == 1:
            yf = 100.0 - speed * dt
            yr, vy = yf + length, -speed
        else:
            yf = speed * dt
            yr, vy = yf - length, speed
        out.append(VehicleState(id_base + j + 10_000, t, x, yf, yr, 0.0, vy, length, 5))
    return out


def run(site, seconds: float, fps: float = 25.0, start: float = EPOCH, **traffic):
    tm = TrafficMeasures(site)
    periods, events, crossings = [], [], []
    n = int(round(seconds * fps))
    for i in range(n + 1):
        t = i / fps
        vs = platoon_states(t, **traffic)
        upd = tm.step(t, start + t, vs)
        periods += upd.periods
        events += upd.loop_events
        crossings += upd.crossings
    return tm, periods, events, crossings


def test_clip_segments_matches_bruteforce():
    rng = np.random.default_rng(1)
    t0 = rng.uniform(0, 10, 500)
    t1 = t0 + rng.uniform(0.01, 1, 500)
    y0 = rng.uniform(-10, 110, 500)
    y1 = y0 + rng.uniform(-30, 30, 500)
    ta, tb, d = clip_segments(t0, t1, y0, y1, np.full(500, 20.0), np.full(500, 80.0))
    s = np.linspace(0, 1, 20001)
    ys = y0[:, None] + s[None, :] * (y1 - y0)[:, None]
    inside = (ys >= 20) & (ys <= 80)
    frac = inside.mean(axis=1)
    # brute force on a 20001-point grid: resolution 1/20000 of the segment
    np.testing.assert_allclose(tb - ta, frac * (t1 - t0), atol=2e-4 * (t1 - t0).max())
    np.testing.assert_allclose(d, frac * np.abs(y1 - y0), atol=2e-4 * np.abs(y1 - y0).max())


def test_constant_speed_platoon_gives_exact_edie_and_loops():
    site = make_site()
    speed, headway, length = 20.0, 3.0, 4.5
    # 10 frames/s is enough: linear trajectories make every quantity exact at any sampling
    tm, periods, events, crossings = run(site, 600.0, fps=10.0, speed=speed, headway=headway, length=length,
                                         lane=1, phase=0.37)
    lane1 = [p for p in periods if p.lane == 1]
    assert [p.period_start for p in lane1] == [EPOCH, EPOCH + 300]
    # the first period starts empty (vehicles enter at y=100 from t=0), the second is stationary:
    # q = 3600/h, v = speed, k = q/v exactly (trajectories are linear, Edie clipping is exact)
    p = lane1[1]
    assert not p.partial
    assert p.flow_vph == pytest.approx(3600 / headway, rel=1e-9)
    assert p.speed_kmh == pytest.approx(speed * 3.6, rel=1e-9)
    assert p.density_vpkm == pytest.approx(3600 / headway / (speed * 3.6), rel=1e-9)
    assert p.flow_vph == pytest.approx(p.density_vpkm * p.speed_kmh, rel=1e-9)
    assert p.count == 100
    assert p.time_mean_speed_kmh == pytest.approx(72.0)
    assert p.speed85_kmh == pytest.approx(72.0)
    assert p.headway_s == pytest.approx(headway, rel=1e-9)
    assert p.class_counts == {"small": 100}
    # loop on-time per vehicle = (vehicle + loop length) / speed, exact by interpolation
    assert p.occupancy_pct == pytest.approx(100 * (length + 1.8) / speed / headway, rel=1e-6)
    ev1 = [e for e in events if e.loop_id == "L1"]
    assert all(e.t_off - e.t_on == pytest.approx((length + 1.8) / speed, rel=1e-6) for e in ev1)
    assert all(e.speed_kmh == pytest.approx(72.0) for e in ev1)
    trap = [e for e in events if e.loop_id == "L1b"]
    assert trap and all(e.speed_kmh == pytest.approx(72.0, rel=1e-6) for e in trap)
    # lane 2 saw nothing
    lane2 = [p for p in periods if p.lane == 2]
    assert all(p.count == 0 and p.flow_vph == 0 and p.speed_kmh is None for p in lane2)
    assert len(crossings) == sum(p.count for p in lane1) + len(
        [c for c in crossings if c.wall >= EPOCH + 600])


def test_receding_lane_and_pulse_loop():
    site = make_site(period_s=60)
    tm, periods, events, crossings = run(site, 130.0, speed=10.0, headway=4.0, length=12.0, lane=2)
    p = [p for p in periods if p.lane == 2][1]  # second minute: stationary
    assert p.count == 15
    assert p.flow_vph == pytest.approx(900.0, rel=1e-9)
    assert p.speed_kmh == pytest.approx(36.0, rel=1e-9)
    assert p.class_counts == {"medium": 15}
    ch = {c.loop_id: c for c in tm.channels()}
    assert ch["L2"].count == len([e for e in events if e.loop_id == "L2"]) + (1 if tm.loops[1].active else 0)
    # pulse mode: call only within pulse_ms of an actuation start
    assert ch["L2"].call == (tm.now_wall - tm.loops[1].last_on_wall < 0.125)


def test_presence_call_is_immediate():
    site = make_site()
    tm = TrafficMeasures(site)
    v = VehicleState(1, 0.0, -2.5, 40.0, 44.5, 0.0, -10.0, 4.5, 5)
    tm.step(0.0, EPOCH, [v])
    assert not tm.channels()[0].call
    # next frame the front is at 31.6 m: inside loop L1 [30, 31.8]
    v2 = VehicleState(1, 0.84, -2.5, 31.6, 36.1, 0.0, -10.0, 4.5, 5)
    tm.step(0.84, EPOCH + 0.84, [v2])
    assert tm.channels()[0].call


def _drive(tm, seconds: float, vehicles: list[tuple], speed: float = 10.0, fps: float = 25.0):
    """Lane-1 vehicles (id, front y at t=0, length or length(t), seen from, seen until) moving towards y=0."""
    calls, events = [], []
    for i in range(int(round(seconds * fps))):
        t = i / fps
        states = []
        for vid, y0, length, t_from, t_to in vehicles:
            if t_from <= t < t_to:
                n = length(t) if callable(length) else length
                y = y0 - speed * t
                states.append(VehicleState(vid, t, -2.5, y, y + n, 0, -speed, n, 5))
        upd = tm.step(t, EPOCH + t, states)
        events += [e for e in upd.loop_events if e.loop_id == "L1"]
        calls.append(tm.channels()[0].call)
    return calls, events


@pytest.mark.parametrize("gap_s,actuations", [(0.08, 1), (0.6, 2)])
def test_a_fragment_just_behind_a_vehicle_is_the_same_actuation(gap_s, actuations):
    """A vehicle's group comes apart: its rear part, another group, comes onto the loop 0.08 s after the front
    part left it. A real loop saw one vehicle. A second vehicle 0.6 s behind is a second actuation."""
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)
    # front part 2 m long at 10 m/s: on the loop [30, 31.8] from 1.0 s to 1.38 s; the rear part 2 m long, its
    # front onto the loop gap_s after that
    t_rear_on = 1.38 + gap_s
    calls, events = _drive(tm, 4.0, [(1, 41.8, 2.0, 0.0, 2.0), (2, 31.8 + 10.0 * t_rear_on, 2.0, 0.5, 4.0)])
    assert tm.channels()[0].count == actuations
    assert len(events) == actuations
    assert events[0].t_on == pytest.approx(1.0, abs=0.041)
    assert events[-1].t_off == pytest.approx(t_rear_on + 0.38, abs=0.041)
    if actuations == 1:
        assert all(calls[26:int((t_rear_on + 0.38) * 25)])  # the call held through the dropout


@pytest.mark.parametrize("behind_m, t_offs", [(4.0, [1.63]), (9.0, [1.63, 2.53])])
def test_a_part_tracked_apart_on_a_vehicle_does_not_hold_the_loop_after_it(behind_m, t_offs):
    """A car's roof tracked as a group of its own, its near end 4 m behind the car's front, reported a car's length
    too: a real loop sees the car leave at its rear (1.63 s), not the part's footprint reaching 4 m further back
    (2.03 s). A follower 9 m behind (a 4.5 m gap) is a vehicle of its own: its own actuation."""
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)
    calls, events = _drive(tm, 4.0, [(1, 41.8, 4.5, 0.0, 4.0), (2, 41.8 + behind_m, 4.5, 0.0, 4.0)])
    assert [e.t_off for e in events] == pytest.approx(t_offs, abs=0.041)
    assert events[0].t_on == pytest.approx(1.0, abs=0.041)


def test_a_length_that_shrinks_and_grows_back_is_one_actuation():
    """The group's rear edge jumps forward off the loop and back over it (a rear part lost, then found again)."""
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)
    # 4.5 m car at 10 m/s on the loop [30, 31.8] from 1.0 s; from 1.05 to 1.6 s the group is 0.5 m long, so it
    # seems to leave the loop at 1.23 s, and comes back over it at 1.6 s, after more than BRIDGE_S
    calls, events = _drive(tm, 4.0, [(1, 41.8, lambda t: 0.5 if 1.05 <= t < 1.6 else 4.5, 0.0, 4.0)])
    assert tm.channels()[0].count == 1 and len(events) == 1
    assert events[0].t_on == pytest.approx(1.0, abs=0.041)


def test_vehicle_not_spanning_count_line_does_not_count():
    site = make_site()
    tm = TrafficMeasures(site)
    for i in range(50):
        t = i * 0.04
        y = 70.0 - 10 * t  # 70 -> 50.4, never reaches 50
        tm.step(t, EPOCH + t, [VehicleState(7, t, -2.5, y, y + 4, 0, -10, 4, 5, finished=(i == 49))])
    assert tm.live_lane_counts() == {1: 0, 2: 0}


def test_lane_change_counted_once():
    site = make_site()
    tm = TrafficMeasures(site)
    recs = []
    for i in range(200):
        t = i * 0.04
        y = 90 - 10 * t
        x = -2.5 if t < 3 else (-2.5 + 5 * min(1.0, (t - 3))) # moves to lane 2 over a second
        recs += tm.step(t, EPOCH + t, [VehicleState(3, t, x, y, y + 4, 0, -10, 4, 5, finished=(i == 199))]).vehicles
    assert len(recs) == 1 and recs[0].lane_changes == 1


def test_state_restore_resumes_period():
    site = make_site(period_s=60)
    traffic = dict(speed=20.0, headway=3.0, length=4.5, lane=1, phase=0.1)
    full, periods_full, _, _ = run(site, 125.0, **traffic)
    # same traffic, service restarted at t=90 s (state saved at 90, restored in a new object)
    tm = TrafficMeasures(site)
    periods = []
    for i in range(0, int(125 * 25) + 1):
        t = i / 25
        if i == 90 * 25:
            saved = json.loads(json.dumps(tm.state()))
            tm = TrafficMeasures(site)
            tm.restore(saved)
        periods += tm.step(t, EPOCH + t, platoon_states(t, **traffic)).periods
    a = [p for p in periods_full if p.lane == 1 and p.period_start == EPOCH + 60][0]
    b = [p for p in periods if p.lane == 1 and p.period_start == EPOCH + 60][0]
    assert b.partial and not a.partial
    # vehicles in view at the restart come back under the same ids but without history: at most
    # the ones in the region at that moment (100 m / 20 m/s / 3 s = 2) lose one segment each
    assert abs(a.count - b.count) <= 2
    assert b.flow_vph == pytest.approx(a.flow_vph, rel=0.05)


def test_flush_gives_partial_current_period():
    site = make_site()
    tm, periods, _, _ = run(site, 100.0, speed=20.0, headway=3.0, length=4.5, lane=1)
    assert periods == []
    tm.add_quality(1 << 3)
    flushed = tm.flush(EPOCH + 100)
    assert len(flushed) == 2 and all(p.partial for p in flushed)
    assert all(p.quality == 8 for p in flushed)
    # observed 100 s of the period: rates are per observed time (3 s headway -> 1200 veh/h at most)
    assert flushed[0].flow_vph == pytest.approx(flushed[0].density_vpkm * flushed[0].speed_kmh, rel=1e-9)
    assert 900 < flushed[0].flow_vph < 1200
    assert flushed[0].count == tm.live_lane_counts()[1] > 0


def test_lane_kernel_matches_reference():
    from appliance.lanes import LaneMap

    site = make_site(lanes=[
        {"id": 1, "direction": "approaching", "polygon_m": [[-5, 10], [0, 10], [0, 100], [-5, 100]]},
        {"id": 2, "direction": "approaching", "polygon_m": [[0, 0], [5, 0], [4, 100], [0, 100]]},
    ])
    lm = LaneMap(site)
    rng = np.random.default_rng(5)
    xs, ys = rng.uniform(-9, 9, 4000), rng.uniform(-5, 105, 4000)
    got = lm.lanes_at(xs, ys)
    ref = np.array([lm.lane_at(x, y) or 0 for x, y in zip(xs, ys)])
    np.testing.assert_array_equal(got, ref)
    assert set(np.unique(ref)) == {0, 1, 2}  # all three outcomes were exercised
    # lane 1 ends at y = 10: a lane-1 vehicle below that end is still in lane 1, not lane 2
    assert lm.lanes_at(np.array([-2.5]), np.array([8.0]))[0] == 1


def test_vehicle_reported_late_or_once_counts_from_its_trajectory():
    site = make_site()
    tm = TrafficMeasures(site)
    # seen only once, as finished, below the count line (50 m), carrying its history from 70 m
    traj = [(i * 0.1, -2.5, 70.0 - 2.0 * i) for i in range(20)]  # 70 -> 32 m
    v = VehicleState(5, 2.0, -2.5, 30.0, 34.5, 0.0, -20.0, 4.5, 6, finished=True, trajectory=traj)
    upd = tm.step(2.0, EPOCH + 2.0, [v])
    assert [c.lane for c in upd.crossings] == [1]
    assert upd.crossings[0].t == pytest.approx(1.0)  # 70 - 20 m/s * 1 s = 50 m
    assert len(upd.vehicles) == 1
    # the same vehicle without a history does not count: one point spans nothing
    tm2 = TrafficMeasures(site)
    v2 = VehicleState(5, 2.0, -2.5, 30.0, 34.5, 0.0, -20.0, 4.5, 6, finished=True)
    assert tm2.step(2.0, EPOCH + 2.0, [v2]).crossings == []


@pytest.mark.parametrize("entered", [True, False])
def test_a_vehicle_entering_already_over_its_count_line_counts_once(entered):
    """Lane 2 recedes, count line at 40 m: first seen with its rear at 30 m and its front at 45 m. Entering
    (the grouper's flag: first seen in its detection zone, not where a vehicle was lost) it counts at first
    sight, once; without the flag (found again after being lost, counted before) it does not count."""
    tm = TrafficMeasures(make_site())
    got = []
    for i in range(30):
        t = i * 0.04
        v = VehicleState(9, t, 2.5, 45.0 + 20 * t, 30.0 + 20 * t, 0.0, 20.0, 15.0, 8, entered=entered and i == 0)
        got += tm.step(t, EPOCH + t, [v]).crossings
    assert [(c.lane, c.t) for c in got] == ([(2, 0.0)] if entered else [])


def test_restart_after_an_outage_marks_periods_partial():
    site = make_site(period_s=60)
    traffic = dict(speed=20.0, headway=3.0, length=4.5, lane=1)
    tm, _, _, _ = run(site, 30.0, **traffic)
    saved = json.loads(json.dumps(tm.state()))
    tm2 = TrafficMeasures(site)
    tm2.restore(saved)
    periods = []
    for i in range(0, 25 * 40):  # back 150 s later, for 40 s
        t = 180.0 + i / 25
        periods += tm2.step(t, EPOCH + t, platoon_states(t, **traffic)).periods
    starts = [p.period_start for p in periods if p.lane == 1]
    assert starts == [EPOCH, EPOCH + 60, EPOCH + 120]
    lane1 = [p for p in periods if p.lane == 1]
    assert all(p.partial for p in lane1)
    assert lane1[0].count == 10  # the 30 s seen before the outage, kept
    assert lane1[0].flow_vph == pytest.approx(1200.0, rel=0.1)  # per observed time, not per 60 s
    assert lane1[1].count == 0


def test_fragment_crossing_right_behind_a_vehicle_is_not_counted():
    site = make_site()
    tm = TrafficMeasures(site)
    counted = []
    for i in range(40):
        t = i * 0.04
        y = 55.0 - 25.0 * t  # crosses 50 m at t = 0.2 s
        vs = [VehicleState(1, t, -2.5, y, y + 4.5, 0, -25, 4.5, 8)]
        if i >= 3:  # a roof fragment of it, 30 % faster in the road projection, crossing 0.03 s later
            yf = 55.0 + 2.5 - 32.5 * (t - 0.0)
            vs.append(VehicleState(2, t, -2.4, yf, yf + 1.0, 0, -32.5, 1.0, 3))
        # a real follower 1.0 s behind
        yb = 55.0 - 25.0 * (t - 1.0)
        if yb < 60:
            vs.append(VehicleState(3, t, -2.6, yb, yb + 4.5, 0, -25, 4.5, 8))
        counted += tm.step(t, EPOCH + t, vs).crossings
    assert [c.vehicle_id for c in counted] == [1, 3]
    assert tm.merged_crossings == 1


@pytest.mark.parametrize("speed, lag, one", [(18.6, 0.37, True), (18.6, 0.55, False), (30.0, 0.45, False),
                                             (3.0, 0.55, True), (3.0, 2.0, False)])
def test_a_second_front_closer_than_a_car_can_follow_is_the_same_vehicle(speed, lag, one):
    """Front to front a follower needs a car's length, a standstill gap and a short time gap at its speed:
    a second group crossing sooner is a part of the first (a roof in low light, 0.37 s behind at 67 km/h);
    at 108 km/h a real follower may be 0.45 s behind. At crawling speeds the window stops at 0.6 s."""
    tm = TrafficMeasures(make_site())
    counted = []
    for i in range(150):
        t = i * 0.04
        vs = []
        for vid, t0 in ((1, 0.0), (2, lag)):
            y = 52.0 - speed * (t - t0)
            if y < 60.0:
                vs.append(VehicleState(vid, t, -2.5, y, y + 4.5, 0, -speed, 4.5, 8))
        counted += tm.step(t, EPOCH + t, vs).crossings
    assert [c.vehicle_id for c in counted] == ([1] if one else [1, 2])


def _two_fronts(tm: TrafficMeasures, speed: float, length: float, ratio: float, lag: float, lane: int = 1,
                frames: int = 60) -> list:
    """Vehicle 1 (this long, at speed) and vehicle 2 (4.5 m, ratio times as fast, lag s later) drive through the
    count line of lane 1 (approaching, 50 m) or lane 2 (receding, 40 m) of make_site's site; their crossings (both
    still tracked at the end)."""
    sign, c = (-1.0, 50.0) if lane == 1 else (1.0, 40.0)
    counted = []
    for i in range(frames):
        t = i * 0.04
        vs = []
        for vid, t0, v, n in ((1, 0.0, speed, length), (2, lag, ratio * speed, 4.5)):
            front = c - sign * 2.0 + sign * v * (t - t0)  # 2 m short of the line at t0
            if abs(front - c) < 10.0:
                vs.append(VehicleState(vid, t, -2.5 if lane == 1 else 2.5, front, front - sign * n, 0, sign * v, n, 8))
        counted += tm.step(t, EPOCH + t, vs).crossings
    return counted


@pytest.mark.parametrize("speed, length, ratio, lag, lane, one", [
    (20.0, 4.5, 1.4, 0.75, 1, True),  # 10 m apart, closing at 8 m/s: 1.2 s
    (20.0, 4.5, 1.2, 1.5, 1, False),  # 25 m at 4 m/s: 6.3 s
    (20.0, 4.5, 1.3, 0.78, 1, True),  # 11.2 m at 6 m/s: 1.87 s
    (20.0, 4.5, 1.3, 0.87, 1, False),  # 13 m at 6 m/s: 2.17 s
    (20.0, 10.0, 1.12, 0.6, 1, True),  # 1.9 m behind a 10 m truck at 2.4 m/s
    (20.0, 10.0, 1.08, 0.6, 1, False),  # ... 8 % faster: below CLOSING_K
    (12.1, 4.5, 1.4, 0.75, 1, True),
    (11.9, 4.5, 1.4, 0.75, 1, False),  # below CLOSING_MIN_MPS: may be pulling away from a queue
    (20.0, 4.5, 2.6, 0.6, 1, False),  # faster than any vehicle's top is magnified (top_gain: 2.5 here)
    (20.0, 30.0, 1.2, 1.5, 1, False),  # behind a group longer than any vehicle: two cars run together
    (20.0, 4.5, 1.4, 0.75, 2, True),  # receding: a part's front (its near end plus 4.5 m) short of a truck's
])
def test_a_front_that_would_run_into_the_vehicle_counted_before_it_is_that_vehicles_raised_part(
        speed, length, ratio, lag, lane, one):
    """A truck's box top, projected by its height, crosses an approaching lane's count line 0.72 s after the truck's
    front at 1.4 times its speed (20 m/s, reported 4.5 m long): 10 m apart and closing at 8 m/s, a follower would
    run into it within 1.2 s (CLOSING_S: 2 s), so it is the truck's part: one count, and the truck's family (its
    Edie time counts once). Likewise on a receding lane. The bounds: 2 s, CLOSING_K (1.1) behind a 10 m truck, the
    truck at CLOSING_MIN_MPS (12 m/s), the camera's greatest height magnification, a leader no longer than a
    vehicle can be (a group 30 m long on the real clip, centred, held two cars 1.5 s apart: the second one counts)."""
    tm = TrafficMeasures(make_site())
    counted = _two_fronts(tm, speed, length, ratio, lag, lane)
    assert [c.vehicle_id for c in counted] == ([1] if one else [1, 2])
    assert tm.merged_crossings == (1 if one else 0)
    if one:
        assert tm.tracks[2].family == 1


def test_a_vehicle_changing_lanes_over_staggered_count_lines_is_no_raised_part():
    """Car 2, counted in lane 1 (its line at 50 m), changes to lane 2 (line at 40 m) and crosses that line 0.58 s
    after car 1, 1.47 times as fast (a time to collision of 0.6 s): it was counted as a vehicle already, so it is no
    raised part of car 1; it counts in both lanes (as on staggered loops) and keeps its Edie time."""
    lanes = [{"id": i, "direction": "approaching", "polygon_m": [[x0, 0], [x0 + 3.5, 0], [x0 + 3.5, 100], [x0, 100]],
              "region_y_m": [20.0, 80.0], "count_y_m": c} for i, x0, c in ((1, -3.5, 50.0), (2, 0.0, 40.0))]
    tm = TrafficMeasures(make_site(lanes=lanes, loops=[]))
    counted = []
    for i in range(120):
        t = i * 0.04
        y1, y2 = 45.0 - 15.0 * t, 60.0 - 22.0 * t  # car 1 crosses 40 m at 0.33 s; car 2 50 m at 0.45 s, 40 m at 0.91 s
        vs = [VehicleState(1, t, 1.75, y1, y1 + 4.5, 0, -15.0, 4.5, 8),
              VehicleState(2, t, -1.75 if y2 > 45.0 else 1.75, y2, y2 + 4.5, 0, -22.0, 4.5, 8)]
        counted += tm.step(t, EPOCH + t, vs).crossings
    assert [(c.vehicle_id, c.lane) for c in counted] == [(1, 2), (2, 1), (2, 2)]
    assert tm.merged_crossings == 0 and tm.tracks[2].family is None


def test_a_follower_is_judged_against_the_counted_vehicle_not_its_merged_part():
    """Car 1, its roof 0.37 s behind (merged), a real follower 0.82 s behind car 1 (0.45 s behind the
    roof), all at 67 km/h: the follower counts."""
    tm = TrafficMeasures(make_site())
    counted = []
    for i in range(100):
        t = i * 0.04
        vs = []
        for vid, t0 in ((1, 0.0), (2, 0.37), (3, 0.82)):
            y = 52.0 - 18.6 * (t - t0)
            if y < 60.0:
                vs.append(VehicleState(vid, t, -2.5 + 0.1 * vid, y, y + 4.5, 0, -18.6, 4.5, 8))
        counted += tm.step(t, EPOCH + t, vs).crossings
    assert [c.vehicle_id for c in counted] == [1, 3]
    assert tm.merged_crossings == 1


def test_overlapping_presences_make_one_actuation():
    """A fragment of a vehicle on the loop at the same time adds no count, as on a real loop."""
    site = make_site()
    tm = TrafficMeasures(site)
    events = []
    for i in range(60):
        t = i * 0.04
        y = 34.0 - 10.0 * t  # over loop L1 [30, 31.8] from t = 0.22 s to 0.67 s
        vs = [VehicleState(1, t, -2.5, y, y + 2.7, 0, -10, 2.7, 8)]
        if 5 <= i <= 12:  # a fragment riding on it, appearing and vanishing while it is on the loop
            vs.append(VehicleState(2, t, -2.4, y + 0.5, y + 1.5, 0, -10, 1.0, 3, finished=(i == 12)))
        events += [e for e in tm.step(t, EPOCH + t, vs).loop_events if e.loop_id == "L1"]
    assert len(events) == 1 and events[0].vehicle_id == 1
    assert events[0].t_on == pytest.approx(0.22, abs=1e-9)  # front reaches 31.8 m
    assert events[0].t_off == pytest.approx(0.67, abs=1e-9)  # rear leaves 30 m
    assert tm.channels()[0].count == 1


def drive(tm: TrafficMeasures, states_at, seconds: float = 5.0) -> list:
    """Step tm at 25 frames/s for ``seconds`` with the states states_at(t, y) gives, y being where a front
    entering lane 1 at 100 m at t = 0 and driving at 20 m/s is; returns each step's (t, update)."""
    out = []
    for i in range(int(seconds * 25) + 1):
        t = i / 25
        out.append((t, tm.step(t, EPOCH + t, states_at(t, 100.0 - 20.0 * t))))
    return out


@pytest.mark.parametrize("host_span, frag_span", [((0.0, 5.0), (0.5, 4.5)), ((1.5, 5.0), (0.0, 4.5)),
                                                  ((0.0, 3.0), (0.5, 5.0))])
def test_two_groups_on_one_vehicle_add_its_distance_and_time_once(host_span, frag_span):
    """A vehicle tracked by two groups at once (one crossing the count line 0.015 s after the other, so
    counted once) adds Edie's d(A) and t(A) once over the time either group covers, whichever came first.
    Lane 1's region is 60 m long (y 80 -> 20), crossed at 20 m/s from t = 1 s to 4 s."""
    tm = TrafficMeasures(make_site(loops=[]))

    def states(t: float, y: float) -> list[VehicleState]:
        vs = []
        if host_span[0] <= t <= host_span[1]:
            vs.append(VehicleState(1, t, -2.5, y, y + 4.5, 0, -20, 4.5, 8))
        if frag_span[0] <= t <= frag_span[1]:
            vs.append(VehicleState(2, t, -2.4, y + 0.3, y + 1.3, 0, -20, 1.0, 4))
        return vs

    crossings = [c for _, upd in drive(tm, states) for c in upd.crossings]
    assert len(crossings) == 1 and tm.merged_crossings == 1
    dist, time = tm.edie.peek(EPOCH)[:, 0]
    assert dist == pytest.approx(60.0, abs=0.5)
    assert time == pytest.approx(3.0, abs=0.03)


@pytest.mark.parametrize("joins", [True, False])
def test_a_crossing_of_a_group_rechecked_as_a_part_waits_for_the_check(joins):
    """A group 12 m behind a vehicle's front (its fronts 0.6 s apart at 20 m/s: a follower could be there) is
    being re-checked as a part of that vehicle (part_of) when it crosses the count line at 3.1 s. If it then
    joins the vehicle it never counts, and Edie has the one vehicle's d(A) and t(A) (60 m, 3 s); if the check
    ends without a join it counts, at the time it crossed."""
    tm = TrafficMeasures(make_site(loops=[]))

    def states(t: float, y: float) -> list[VehicleState]:
        vs = [VehicleState(1, t, -2.5, y, y + 4.5, 0, -20, 4.5, 8)]
        if 2.0 <= t <= 3.4:
            part_of = 1 if t >= 2.8 else None
            vs.append(VehicleState(2, t, -2.4, y + 12.0, y + 13.0, 0, -20, 1.0, 4, part_of=part_of,
                                   finished=joins and t >= 3.4, joined=1 if joins and t >= 3.4 else None))
        elif t > 3.4 and not joins:
            vs.append(VehicleState(2, t, -2.4, y + 12.0, y + 13.0, 0, -20, 1.0, 4))
        return vs

    steps = drive(tm, states)
    assert all(c.vehicle_id == 1 for t, upd in steps if t < 3.4 for c in upd.crossings)  # the part's waits
    crossings = [c for _, upd in steps for c in upd.crossings]
    assert [c.vehicle_id for c in crossings] == ([1] if joins else [1, 2])
    assert crossings[-1].t == pytest.approx(2.5 if joins else 3.1, abs=1e-6)
    dist, time = tm.edie.peek(EPOCH)[:, 0]
    if joins:
        assert dist == pytest.approx(60.0, abs=0.5)
        assert time == pytest.approx(3.0, abs=0.03)
    else:
        assert time > 3.0 + 1.0  # the part's own time counts too


@pytest.mark.parametrize("ends_y, counted", [(60.0, False), (44.0, True)])
def test_a_group_that_turned_out_to_be_no_vehicle_takes_back_its_edie_unless_it_counted(ends_y, counted):
    """A group beside a car (a shadow on the road, 3 m across in lane 1 while the car drives in lane 2) is
    reported and then found to be no vehicle (its last state joined NO_VEHICLE). Short of its count line (50 m)
    its distance and time are taken back: lane 1 reads nothing. Past it, it counted (and stands for a vehicle,
    as a shadow cast ahead of one hidden until then does): its Edie stays."""
    tm = TrafficMeasures(make_site(loops=[], lanes=approaching_pair(2, 50.0)))
    t_end = (100.0 - ends_y) / 20.0

    def states(t: float, y: float) -> list[VehicleState]:
        vs = [VehicleState(1, t, 2.5, y, y + 4.5, 0, -20, 4.5, 8)]
        if t <= t_end + 1e-9:
            end = t >= t_end - 1e-9
            vs.append(VehicleState(2, t, -0.5, y, y + 2.0, 0, -20, 2.0, 4, finished=end,
                                   joined=NO_VEHICLE if end else None))
        return vs

    crossings = [c for _, upd in drive(tm, states) for c in upd.crossings]
    assert sorted(c.lane for c in crossings) == ([1, 2] if counted else [2])
    (d1, d2), (t1, t2) = tm.edie.peek(EPOCH)
    assert (d2, t2) == pytest.approx((60.0, 3.0), abs=0.05)  # the car
    if counted:
        # from the region's entry (80 m) to its last state but one (a last state that joins adds no step)
        assert (d1, t1) == pytest.approx((80.0 - ends_y - 0.8, t_end - 1.0 - 0.04), abs=1e-6)
    else:
        assert (d1, t1) == pytest.approx((0.0, 0.0), abs=1e-9)


def test_a_crossing_held_past_the_end_of_its_period_counts_in_the_next():
    """A group under re-check crosses the count line 0.1 s before a period ends and is cleared 0.5 s into the
    next: its count is not lost with the closed period, it goes to the period in progress."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    periods = []
    t0 = 296.0
    for i in range(int(6.0 * 25) + 1):
        t = t0 + i / 25
        y = 50.0 - 20.0 * (t - 299.9)  # crosses lane 1's count line (50 m) at 299.9 s
        upd = tm.step(t, EPOCH + t, [VehicleState(7, t, -2.5, y, y + 4.5, 0, -20, 4.5, 8,
                                                  part_of=3 if t < 300.5 else None)])
        periods += upd.periods
    periods += tm.flush(EPOCH + t0 + 6.0)
    counts = {p.period_start - EPOCH: p.count for p in periods if p.lane == 1}
    assert counts == {0.0: 0, 300.0: 1}


def test_a_vehicle_finalised_inside_the_region_drives_on_to_its_end():
    """A receding vehicle finalised at y = 69.6 m (the exit zone may begin inside the Edie region, 20-80 m)
    adds the 10 m it still drives to the region's end at its speed: d(A) = 60 m, t(A) = 3 s at 20 m/s."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    for i in range(88):
        t = i / 25
        y = 20.0 * t
        tm.step(t, EPOCH + t, [VehicleState(7, t, 2.5, y, y - 4.5, 0, 20, 4.5, 8, finished=i == 87, exited=i == 87)])
    dist, time = tm.edie.peek(EPOCH)[:, 1]
    assert dist == pytest.approx(60.0, abs=0.1)
    assert time == pytest.approx(3.0, abs=0.01)


def test_a_new_vehicles_earlier_points_are_in_the_lane_its_report_ends_in():
    """Two approaching lanes (x -3.5..0 and 0..3.5; regions 80 -> 20 m, count lines at 50 m). A vehicle's
    first report carries its points back to its region's entry (80 m at 0 s, 20 m/s); far away its place
    across the road read x = -0.8 (lane 1's side), near it reads 1.5 (lane 2) from 55 m on. All of its 60 m
    and 3 s are lane 2's, and it counts in lane 2 once (before: 24 m and 1.2 s went to lane 1)."""
    lanes = [{"id": i, "direction": "approaching", "polygon_m": [[x0, 0], [x0 + 3.5, 0], [x0 + 3.5, 100], [x0, 100]],
              "region_y_m": [20.0, 80.0], "count_y_m": 50.0} for i, x0 in ((1, -3.5), (2, 0.0))]
    tm = TrafficMeasures(make_site(loops=[], lanes=lanes))
    tm.step(0.0, EPOCH, [])
    traj = [(0.0, -0.8, 80.0)] + [(t, -0.8 if 80.0 - 20 * t > 55.0 else 1.5, 80.0 - 20 * t)
                                  for t in np.arange(0.5, 1.99, 0.04)]
    got = []
    for i in range(50, 76):
        t = i / 25
        v = VehicleState(4, t, 1.5, 80.0 - 20 * t, 84.5 - 20 * t, 0.0, -20.0, 4.5, 8,
                         trajectory=traj if i == 50 else None)
        got += tm.step(t, EPOCH + t, [v]).crossings
    assert [c.lane for c in got] == [2]
    (d1, d2), (t1, t2) = tm.edie.peek(EPOCH)
    assert d1 == pytest.approx(0.0) and t1 == pytest.approx(0.0)
    assert d2 == pytest.approx(60.0, abs=0.1) and t2 == pytest.approx(3.0, abs=0.01)


@pytest.mark.parametrize("lost_at, dist", [(69.6, 60.0), (35.0, 15.0)])
def test_a_counted_vehicle_lost_inside_the_region_drives_on_to_its_end(lost_at, dist):
    """A receding vehicle (count line 40 m, region 20-80 m, 20 m/s) finished where it was lost, not at an exit
    zone (the grouper finishes only those past their detection zone: no features are found on them again).
    Lost at 69.6 m after its count it drives on to the region's end: d(A) = 60 m, t(A) = 3 s. Lost at 35 m,
    before its count line, it is not carried on (it may be a part of another vehicle): 15 m, 0.75 s."""
    tm = TrafficMeasures(make_site(loops=[]))
    n = int(round(lost_at / 20.0 * 25))
    for i in range(n + 1):
        t = i / 25
        y = 20.0 * t
        tm.step(t, EPOCH + t, [VehicleState(7, t, 2.5, y, y - 4.5, 0, 20, 4.5, 8, finished=i == n)])
    d, time = tm.edie.peek(EPOCH)[:, 1]
    assert d == pytest.approx(dist, abs=0.5)
    assert time == pytest.approx(dist / 20.0, abs=0.03)


def test_a_young_vehicle_lost_inside_the_region_drives_on_no_slower_than_it_came():
    """A receding vehicle first seen at 30 m (found when an occluder uncovered it: its features' speeds not yet
    settled, 2 m/s reported) that came 20 m in 1 s, counted at 40 m and lost at 50 m, drives on to the region's end
    (80 m) at 20 m/s: d(A) 50 m, t(A) 2.5 s (at its reported speed the 30 m left would take 15 s)."""
    tm = TrafficMeasures(make_site(loops=[]))
    for i in range(26):
        t = i / 25
        y = 30.0 + 20.0 * t
        tm.step(t, EPOCH + t, [VehicleState(7, t, 2.5, y, y - 4.5, 0, 2.0, 4.5, 8, finished=i == 25)])
    d, time = tm.edie.peek(EPOCH)[:, 1]
    assert d == pytest.approx(50.0, abs=0.5)
    assert time == pytest.approx(2.5, abs=0.05)


def test_a_counted_vehicle_gone_without_a_finish_still_gets_its_record():
    """A group counted at its line that then vanishes unfinished (it joined another group: the grouper never
    finishes it) keeps its count; its per-vehicle record comes once it is forgotten, LOST_AFTER_S later, so
    that every counted vehicle has one. One gone before its line (perhaps a part of another vehicle) has
    none."""
    tm = TrafficMeasures(make_site(loops=[]))
    records, crossings = [], []
    for i in range(int(round((4.0 + LOST_AFTER_S + 0.5) * 25))):
        t = i / 25
        states = []
        if t < 4.0:  # 80 -> 40 m at 10 m/s: over the count line (50 m) at 3 s
            states.append(VehicleState(7, t, -2.5, 80.0 - 10 * t, 84.5 - 10 * t, 0, -10, 4.5, 6))
        if t < 2.0:  # 95 -> 75 m: gone before its count line
            states.append(VehicleState(8, t, -2.5, 95.0 - 10 * t, 99.5 - 10 * t, 0, -10, 4.5, 6))
        upd = tm.step(t, EPOCH + t, states)
        records += upd.vehicles
        crossings += upd.crossings
    assert [c.vehicle_id for c in crossings] == [7]
    assert [(r.id, r.lane) for r in records] == [(7, 1)]
    assert records[0].wall_exit == pytest.approx(EPOCH + 4.0 - 1 / 25)
    assert records[0].speed_kmh == pytest.approx(36.0)


@pytest.mark.parametrize("entered, counted", [(True, True), (False, True), (True, False)])
def test_a_counted_vehicle_first_seen_inside_its_region_is_extended_back_to_its_entry(entered, counted):
    """A small group (not extended back by the pipeline) first seen at y = 65.6 m, inside lane 1's region
    (80 -> 20 m), at 20 m/s: once it crosses the count line (50 m) it has its region entry at its speed since,
    so Edie's d(A) = 60 m and t(A) = 3 s. Not so when it was found again where another was lost (its earlier
    stretch was that one's), nor while it has not crossed the line (it may be a part of another vehicle)."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    tm.step(0.0, EPOCH, [])
    end = 4.0 if counted else 1.4  # the count line is reached at 1.5 s
    for i in range(18, int(end * 25) + 1):  # from 0.72 s
        t = i / 25
        y = 80.0 - 20.0 * t
        tm.step(t, EPOCH + t, [VehicleState(3, t, -2.5, y, y + 4.5, 0, -20, 4.5, 2, entered=entered)])
    dist, time = tm.edie.peek(EPOCH)[:, 0]
    if entered and counted:
        assert dist == pytest.approx(60.0, abs=0.1)
        assert time == pytest.approx(3.0, abs=0.01)
    else:
        assert dist == pytest.approx(20.0 * (min(end, 3.0) - 0.72), abs=0.1)
        assert time == pytest.approx(min(end, 3.0) - 0.72, abs=0.01)


def test_a_small_group_first_seen_ahead_of_its_vehicle_is_extended_back_along_its_fitted_line():
    """A small group entering lane 1's region (80 -> 20 m) at t = 2 s at a steady 20 m/s is first seen at
    2.72 s with its near end on its shadow's tip, 2 m ahead of its front (65.6 m), where it waits 0.1 s for the
    front. Its average speed from that first point to the count line (50 m) reads 13 % slow: extended back at it,
    it would enter 0.22 s early. Along the line fitted to its points: d(A) 60 m, t(A) 3 s."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    tm.step(0.0, EPOCH, [])
    for i in range(68, 126):  # 2.72 s to 5 s
        t = i / 25
        y = min(63.6, 80.0 - 20.0 * (t - 2.0))
        tm.step(t, EPOCH + t, [VehicleState(3, t, -2.5, y, y + 4.5, 0, -20, 4.5, 2, entered=True)])
    dist, time = tm.edie.peek(EPOCH)[:, 0]
    assert dist == pytest.approx(60.0, abs=0.1)
    assert time == pytest.approx(3.0, abs=0.03)


def test_a_duplicates_extension_back_to_its_region_entry_is_taken_back_whole():
    """Vehicle 3 enters lane 1's region (80 -> 20 m) at t = 2 s at 20 m/s and is first seen at 2.72 s; the
    pipeline extends it back to its entry. Group 4, a part of it 1 m behind its front, is first seen then too,
    but its first points crawled, and its extension back to the entry runs from t = 0.3 s at 5.5 m/s. It crosses
    the count line 0.05 s after vehicle 3: a duplicate, whose distance and time are taken back where vehicle 3
    covers them, and its extension too, whenever it began (vehicle 3's covers that stretch): d(A) 60 m, t(A) 3 s,
    not 1.7 s and 9.4 m more."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    tm.step(0.0, EPOCH, [])
    for i in range(68, 126):  # 2.72 s to 5 s
        t = i / 25
        y = 80.0 - 20.0 * (t - 2.0)
        first = i == 68
        a = VehicleState(3, t, -2.5, y, y + 4.5, 0, -20.0, 4.5, 8, trajectory=[(2.0, -2.5, 80.0)] if first else None,
                         entered=True, backfilled=first)
        b = VehicleState(4, t, -2.5, y + 1.0, y + 3.0, 0, -20.0, 2.0, 4,
                         trajectory=[(0.3, -2.5, 80.0)] if first else None, entered=True, backfilled=first)
        tm.step(t, EPOCH + t, [a, b])
    assert [c.vehicle_id for c in tm.crossings[1]] == [3]
    dist, time = tm.edie.peek(EPOCH)[:, 0]
    assert dist == pytest.approx(60.0, abs=0.1)
    assert time == pytest.approx(3.0, abs=0.03)


@pytest.mark.parametrize("case", ["joins before its vehicle is counted", "its vehicle is first seen later"])
def test_a_duplicates_extension_stays_where_its_vehicle_does_not_cover_the_entry(case):
    """Group 4, a part 1 m behind vehicle 3's front, is extended back by the pipeline to lane 1's entry (80 m,
    t = 2 s, the truth). Vehicle 3 is not extended: it joins 3 at 3 s, before 3 is counted (a family's member
    is not extended at its count), or 3 is first seen only at 3 s and was found again (not extended either).
    The stretch only group 4's extension covers stays counted: t(A) 3 s."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    tm.step(0.0, EPOCH, [])
    join_at, other_first, entered = (3.0, 68, True) if case.startswith("joins") else (None, 75, False)
    for i in range(68, 126):  # 2.72 s to 5 s
        t = i / 25
        y = 80.0 - 20.0 * (t - 2.0)
        states = []
        if i >= other_first:
            states.append(VehicleState(3, t, -2.5, y, y + 4.5, 0, -20.0, 4.5, 8, entered=entered))
        if join_at is None or t <= join_at:
            j = join_at is not None and t >= join_at
            states.append(VehicleState(4, t, -2.5, y + 1.0, y + 3.0, 0, -20.0, 2.0, 4,
                                       trajectory=[(2.0, -2.5, 80.0)] if i == 68 else None, entered=True,
                                       backfilled=i == 68, finished=j, joined=3 if j else None))
        tm.step(t, EPOCH + t, states)
    assert len(tm.crossings[1]) == 1
    time = tm.edie.peek(EPOCH)[1, 0]
    assert time == pytest.approx(3.0, abs=0.03)


def test_a_small_group_counted_at_two_staggered_lines_is_extended_back_once():
    """A small group first seen inside its region (80 -> 20 m, entered at 2 s at 20 m/s) changes from lane 1
    (count line 50 m) to lane 3 (count line 45 m) and is counted at both lines: it is extended back to its
    region's entry once, t(A) 3 s over both lanes (twice: 3.72 s)."""
    tm = TrafficMeasures(make_site(loops=[], lanes=approaching_pair(3, 45.0)))
    tm.step(0.0, EPOCH, [])
    for i in range(68, 126):  # 2.72 s to 5 s
        t = i / 25
        y = 80.0 - 20.0 * (t - 2.0)
        x = -2.5 if y > 49.0 else 2.5
        tm.step(t, EPOCH + t, [VehicleState(3, t, x, y, y + 4.5, 0, -20, 4.5, 2, entered=True)])
    assert [len(tm.crossings[ln]) for ln in (1, 3)] == [1, 1]
    assert tm.edie.peek(EPOCH)[1].sum() == pytest.approx(3.0, abs=0.03)


@pytest.mark.parametrize("slows", [False, True])
def test_a_backfilled_vehicle_is_extended_again_at_its_speed_to_the_count_line(slows):
    """The pipeline extended a vehicle first seen at y = 65.6 m (t = 2 s, 20 m/s) back to its region's entry
    (80 m) at half its speed (its first points' near end lagged), from t = 0.56 s. Counted at the line (50 m)
    at its steady 20 m/s, it is extended again at its average speed since: entry at 1.28 s, Edie's d(A) 60 m
    and t(A) 3 s. One that slowed to 8 m/s on the way (a queue's tail) keeps the pipeline's extension: its speed
    at the line is not the one it had when first seen."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    tm.step(0.0, EPOCH, [])
    t, y, vy, first = 2.0, 65.6, -20.0, True
    while y > 19.0:
        traj = [(2.0 - 14.4 / 10.0, -2.5, 80.0)] if first else None
        tm.step(t, EPOCH + t, [VehicleState(3, t, -2.5, y, y + 4.5, 0, vy, 4.5, 8, trajectory=traj,
                                            entered=True, backfilled=first)])
        first = False
        if slows and y < 58.0:
            vy = -8.0
        t += 0.04
        y += vy * 0.04
    (cr,) = tm.crossings[1]
    dist, time = tm.edie.peek(EPOCH)[:, 0]
    assert dist == pytest.approx(60.0, abs=0.2)
    if slows:
        assert cr.speed_kmh == pytest.approx(8.0 * 3.6, rel=0.05)
        assert time == pytest.approx(1.44 + 7.6 / 20.0 + 38.0 / 8.0, abs=0.1)  # from 0.56 s, on to 20 m
    else:
        assert time == pytest.approx(3.0, abs=0.03)


def test_a_backfill_from_a_near_end_ahead_of_its_vehicle_is_redone_along_its_fitted_line():
    """A vehicle at a steady 20 m/s is first seen at t = 2 s with its near end on its shadow's tip, 2 m ahead of
    its front (67.6 m): the near end waits there (it never goes back) until the front reaches it 0.1 s later.
    The pipeline extended it back to its region's entry (80 m) at half speed. Its average speed from that first
    point to the count line (50 m) reads 11 % slow, and extended at it the vehicle would enter 0.19 s early: t(A)
    3.19 s. Along the line fitted to its points it enters when it did: d(A) 60 m, t(A) 3 s."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    tm.step(0.0, EPOCH, [])
    t, first = 2.0, True
    while True:
        y = min(65.6, 67.6 - 20.0 * (t - 2.0))
        if y <= 19.0:
            break
        traj = [(2.0 - 14.4 / 10.0, -2.5, 80.0)] if first else None
        tm.step(t, EPOCH + t, [VehicleState(3, t, -2.5, y, y + 4.5, 0, -20.0, 4.5, 8, trajectory=traj,
                                            entered=True, backfilled=first)])
        first = False
        t += 0.04
    dist, time = tm.edie.peek(EPOCH)[:, 0]
    assert dist == pytest.approx(60.0, abs=0.2)
    assert time == pytest.approx(3.0, abs=0.03)


def test_a_backfill_cut_at_the_first_frame_is_extended_again_to_the_region_entry_or_that_frame():
    """First seen at 65.6 m at t = 0.3 s (20 m/s), the pipeline's half-speed extension stopped at the first
    frame (t = 0, 68.6 m). Counted at its steady speed, it is extended again from the first frame, at 71.6 m:
    Edie's d(A) 51.6 m, t(A) 2.58 s (not from 68.6 m: the region's entry is at 80 m)."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    tm.step(0.0, EPOCH, [])
    t, y, first = 0.3, 65.6, True
    while y > 19.0:
        traj = [(0.0, -2.5, 68.6)] if first else None
        tm.step(t, EPOCH + t, [VehicleState(3, t, -2.5, y, y + 4.5, 0, -20.0, 4.5, 8, trajectory=traj,
                                            entered=True, backfilled=first)])
        first = False
        t += 0.04
        y -= 0.8
    dist, time = tm.edie.peek(EPOCH)[:, 0]
    assert dist == pytest.approx(51.6, abs=0.2)
    assert time == pytest.approx(2.58, abs=0.03)


def test_a_receding_vehicles_backfill_is_redone_at_the_speed_of_its_edie_place():
    """A receding vehicle (lane 2: region 20 -> 80 m, count line 40 m) is followed by Edie at its rear plus its
    first length (3 m). First seen with its rear at 25 m (t = 2 s, 20 m/s) and extended back at half speed, its
    measured length then grows to 5 m (more of it shows): its front crosses the line sooner than its rear's
    speed says. The extension is redone at the speed of its Edie place, the rear's: t(A) 3 s for d(A) 60 m
    (at its front's 22 m/s, 2.96 s)."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    tm.step(0.0, EPOCH, [])
    t, first = 2.0, True
    while True:
        rear = 25.0 + 20.0 * (t - 2.0)
        if rear + 3.0 > 81.0:
            break
        length = 3.0 + 2.0 * min(t - 2.0, 1.0)
        traj = [(2.0 - 8.0 / 10.0, 2.5, 20.0)] if first else None  # its front (rear + 3) at the entry
        tm.step(t, EPOCH + t, [VehicleState(4, t, 2.5, rear + length, rear, 0, 20.0, length, 8, trajectory=traj,
                                            entered=True, backfilled=first)])
        first = False
        t += 0.04
    assert len(tm.crossings[2]) == 1
    dist, time = tm.edie.peek(EPOCH)[:, 1]
    assert dist == pytest.approx(60.0, abs=0.2)
    assert time == pytest.approx(3.0, abs=0.01)


def test_a_group_on_a_counted_vehicle_never_takes_its_lane():
    """The second group on a vehicle (fewer features) comes first in the tracker's list, crosses the count
    line in the same frame, and then drifts over the lane line: the vehicle is counted by its own group,
    and its distance and time stay in its lane (1), none goes to lane 3."""
    lanes = [{"id": 1, "direction": "approaching", "polygon_m": [[-5, 0], [0, 0], [0, 100], [-5, 100]],
              "region_y_m": [20.0, 80.0], "count_y_m": 50.0},
             {"id": 3, "direction": "approaching", "polygon_m": [[0, 0], [5, 0], [5, 100], [0, 100]],
              "region_y_m": [20.0, 80.0], "count_y_m": 50.0}]
    site = make_site(loops=[], lanes=lanes)
    tm = TrafficMeasures(site)
    crossings = []
    for i in range(126):
        t = i / 25
        y = 100.0 - 20.0 * t
        frag_x = -0.3 if t < 2.6 else 0.3
        crossings += tm.step(t, EPOCH + t, [VehicleState(2, t, frag_x, y + 0.3, y + 1.3, 0, -20, 1.0, 4),
                                            VehicleState(1, t, -2.5, y, y + 4.5, 0, -20, 4.5, 8)]).crossings
    assert [c.vehicle_id for c in crossings] == [1] and tm.merged_crossings == 1
    sums = tm.edie.peek(EPOCH)
    assert sums[:, 0] == pytest.approx([60.0, 3.0], abs=0.05)
    assert sums[:, 1] == pytest.approx([0.0, 0.0], abs=1e-9)


def test_a_group_crossing_just_after_its_vehicle_ended_adds_nothing():
    """The counted vehicle is finalised at the exit zone the moment it crosses (and driven on to the
    region's end); a second group on it crossing 0.015 s later adds nothing: d(A) = 60 m, t(A) = 3 s."""
    site = make_site(loops=[])
    tm = TrafficMeasures(site)
    for i in range(126):
        t = i / 25
        y = 100.0 - 20.0 * t
        vs = []
        if y >= 49.6 - 1e-9:
            vs.append(VehicleState(1, t, -2.5, y, y + 4.5, 0, -20, 4.5, 8, finished=y < 50, exited=y < 50))
        vs.append(VehicleState(2, t, -2.4, y + 0.3, y + 1.3, 0, -20, 1.0, 4))
        tm.step(t, EPOCH + t, vs)
    assert tm.merged_crossings == 1
    # the second group, 0.3 m behind, reaches the region's end 0.015 s after the vehicle's carry-on does
    assert tm.edie.peek(EPOCH)[:, 0] == pytest.approx([60.3, 3.015], abs=0.01)


def test_taking_back_a_segment_across_a_period_boundary_leaves_nothing():
    from appliance.edie import EdieAccumulator

    acc = EdieAccumulator([1], {1: (0.0, 100.0)}, 60.0)
    args = (np.array([1]), np.array([50.0]), np.array([70.0]), np.array([10.0]), np.array([90.0]))
    acc.add(*args)
    assert acc.peek(0.0)[:, 0] == pytest.approx([40.0, 10.0]) and acc.peek(60.0)[:, 0] == pytest.approx([40.0, 10.0])
    acc.add(*args, sign=-1.0)
    assert np.all(acc.peek(0.0) == 0) and np.all(acc.peek(60.0) == 0)


def test_a_segment_in_a_period_already_taken_is_not_added():
    """A backfilled part dated before the last period taken is dropped (it would make a bucket nobody
    takes); a segment straddling the close keeps only its part after it."""
    from appliance.edie import EdieAccumulator

    acc = EdieAccumulator([1], {1: (0.0, 100.0)}, 60.0)
    assert acc.take(0.0)[:, 0] == pytest.approx([0.0, 0.0])
    acc.add(np.array([1, 1]), np.array([40.0, 50.0]), np.array([50.0, 70.0]), np.array([0.0, 10.0]),
            np.array([10.0, 90.0]))
    assert set(acc.sums) == {60.0}
    assert acc.peek(60.0)[:, 0] == pytest.approx([40.0, 10.0])


def test_period_length_classes_use_the_length_the_vehicle_ended_with():
    """A vehicle's length is still being measured when its front crosses the count line (few frames fitted),
    and a long vehicle's far end is found last: the period's length classes take the length it ended with,
    as its vehicle record does (a car measured as a motorcycle at the line; a truck measured as a car over most
    of its passage), or its median length over the passage where that is longer (a car measured short as it
    leaves the image)."""
    lanes = [{"id": 1, "direction": "approaching", "polygon_m": [[-5, 0], [5, 0], [5, 100], [-5, 100]],
              "region_y_m": [20.0, 80.0], "count_y_m": 70.0}]
    site = make_site(period_s=60, loops=[], lanes=lanes)
    tm = TrafficMeasures(site)
    periods, records, crossings = [], [], []
    fps, speed, n, every, life = 10.0, 20.0, 12, 60, 53  # frames: a vehicle each 6 s, in view from y=100 to -4
    for i in range(130 * int(fps) + 1):
        t = i / fps
        vs = []
        for j in range(n):
            age = i - j * every
            if not 0 <= age < life:
                continue
            yf = 100.0 - speed * age / fps
            length = 1.5 if yf > 65.0 else 4.5  # a motorcycle's length at the line, a car's from then on
            if j % 2 and age >= life - 5:
                length = 9.0  # every other one a truck, its far end found in its last frames
            elif j % 4 == 2 and age >= life - 5:
                length = 1.0  # a car measured short as it leaves
            vs.append(VehicleState(j + 1, t, 0.0, yf, yf + length, 0.0, -speed, length, 5, finished=age == life - 1))
        upd = tm.step(t, EPOCH + t, vs)
        periods += upd.periods
        records += upd.vehicles
        crossings += [c.length_m for c in upd.crossings]  # as sent out (and stored) at the line
    assert len(crossings) == n and all(length == pytest.approx(1.5) for length in crossings)
    assert len(records) == n
    assert [r.length_class for r in sorted(records, key=lambda r: r.id)] == ["small", "medium"] * (n // 2)
    counted = [p for p in periods if p.lane == 1 and p.count]
    assert sum(p.count for p in counted) == n
    classes = [j % 2 for j in range(n)]  # 1: a truck
    assert sum(p.class_counts.get("medium", 0) for p in counted) == sum(classes)
    assert sum(p.class_counts.get("small", 0) for p in counted) == n - sum(classes)


def test_spot_speeds_are_the_lowest_features_and_edie_the_positions():
    """Count lines, loops and vehicle records give a vehicle's spot speed (its lowest features', spot_vy): the
    low part's velocity (vy) takes in lights and bonnet, which move faster in projection (here 5 % faster).
    Edie's space-mean speed comes from the positions, as before. (A presence loop: a speed trap times its two
    loops.)"""
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)
    crossings, events, records, periods = [], [], [], []
    done: set[int] = set()
    for i in range(int(round(400 * 10)) + 1):
        t = i / 10
        states = [replace(v, vy=v.vy * 1.05, spot_vy=v.vy, finished=v.y_front < 5.0)
                  for v in platoon_states(t, speed=20.0, headway=3.0, length=4.5, lane=1, phase=0.37)
                  if v.id not in done]
        done |= {v.id for v in states if v.finished}
        upd = tm.step(t, EPOCH + t, states)
        crossings += upd.crossings
        events += upd.loop_events
        records += upd.vehicles
        periods += upd.periods
    assert len(crossings) > 100 and all(c.speed_kmh == pytest.approx(72.0) for c in crossings)
    assert len(events) > 100 and all(e.speed_kmh == pytest.approx(72.0, rel=1e-6) for e in events)
    assert records and all(r.speed_kmh == pytest.approx(72.0) for r in records)
    p = [p for p in periods if p.lane == 1][0]
    assert p.time_mean_speed_kmh == pytest.approx(72.0) and p.speed_kmh == pytest.approx(72.0, rel=1e-9)


def test_a_line_crossed_before_the_first_report_counts_at_the_reports_spot_speed():
    """The points a vehicle brings with its first report (crossed before it was reported) count at its spot
    speed too."""
    tm = TrafficMeasures(make_site(loops=[]))
    trajectory = [(t / 10, -2.5, 60.0 - 20.0 * t / 10) for t in range(8)]  # 60 m down to 46 m: over the line
    first = VehicleState(7, 0.8, -2.5, 44.0, 48.5, 0.0, -21.0, 4.5, 5, trajectory=trajectory, spot_vy=-20.0)
    crossings = tm.step(0.8, EPOCH + 0.8, [first]).crossings
    assert len(crossings) == 1 and crossings[0].speed_kmh == pytest.approx(72.0)


def _queue(tm, seconds: float, sight_at, track_until: float, fps: float = 25.0, finish: bool = False):
    """A lane-1 car braking at 2 m/s2 to stand with its front at 29 m (over loop L1 [30, 31.8]) from 5 s,
    tracked until track_until (then gone: lost, or finished by the tracker if finish); sight_at(t): the
    LoopSight of L1 then. Returns the L1 events and the call per frame."""
    events, calls = [], []
    last = int(np.ceil(track_until * fps)) - 1
    for i in range(int(round(seconds * fps))):
        t = i / fps
        dt = max(5.0 - t, 0.0)
        y, v = 29.0 + dt * dt, 2.0 * dt
        states = [VehicleState(1, t, -2.5, y, y + 4.5, 0.0, -v, 4.5, 5, finished=finish and i == last)] \
            if i <= last else []
        upd = tm.step(t, EPOCH + t, states, {"L1": sight_at(t)})
        events += [e for e in upd.loop_events if e.loop_id == "L1"]
        calls.append((t, tm.channels()[0].call))
    return events, calls


@pytest.mark.parametrize("track_until, finish", [(4.6, False), (4.6, True), (30.0, False)])
def test_a_car_standing_on_its_loop_is_one_actuation_whether_its_track_ends_or_not(track_until, finish):
    """The car comes onto L1 at 3.33 s and stands from 5 s; the image shows it on the loop from 3.8 s and gives
    a standing call from 6.5 s (came 3.8, stood 5.0) until 40 s. Its track ends at 4.6 s, crawling (0.8 m/s):
    lost (the measures keep it LOST_AFTER_S), or finished by the tracker (it has stopped dead); or it lasts
    beyond the call. Each way one actuation, counted once, on until 40 s, the call never dropping: an
    actuation whose vehicle left it waits (WAIT_S) for the standing call while the image shows the loop
    occupied since before."""
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)

    def sight(t):
        return LoopSight(3.8 if 3.8 <= t < 40.0 else None, (3.8, 5.0) if 6.5 <= t < 40.0 else None)

    events, calls = _queue(tm, 45.0, sight, track_until, finish=finish)
    assert tm.channels()[0].count == 1
    assert len(events) == 1, events
    assert events[0].t_on == pytest.approx(5.0 - 2.8 ** 0.5, abs=0.041)  # the front over 31.8 m
    assert events[0].t_off == pytest.approx(40.0 if track_until < 40.0 else 30.0, abs=0.041)
    assert all(c for t, c in calls if events[0].t_on + 0.05 < t < events[0].t_off)


def test_a_standing_car_the_tracker_never_saw_is_counted_from_when_it_stood():
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)

    def sight(t):
        return LoopSight(3.8 if 3.8 <= t < 40.0 else None, (3.8, 5.0) if 6.5 <= t < 40.0 else None)

    events, calls = _queue(tm, 45.0, sight, track_until=0.0)
    assert tm.channels()[0].count == 1 and len(events) == 1
    assert events[0].t_on == 5.0 and events[0].t_off == pytest.approx(40.0, abs=0.041)
    assert events[0].speed_kmh is None and events[0].vehicle_id == STANDING


def test_a_vehicle_leaving_an_occupied_loop_waits_for_a_standing_call_no_longer_than_wait_s():
    """The track ends at 4.6 s (crawling) and the image shows the loop occupied, but no standing call comes
    (the vehicle moved on, and a neighbour's roof covers the loop): the actuation ends where the track left
    it, emitted WAIT_S later; the call was held that long."""
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)
    events, calls = _queue(tm, 12.0, lambda t: LoopSight(3.8 if t >= 3.8 else None, None), track_until=4.6,
                           finish=True)
    assert len(events) == 1 and events[0].t_off == pytest.approx(4.56, abs=0.041)
    on = [t for t, c in calls if c]
    assert max(on) == pytest.approx(4.56 + WAIT_S, abs=0.081)


def test_a_follower_after_a_vehicle_that_drove_off_gets_its_own_call_edge():
    """Two cars at 36 km/h, 2 s apart, over L1; the image shows the loop occupied from the first car's arrival
    until after the second's (a tall body still over it in the image, then the next car): the first drove off
    at speed, so its actuation does not wait for a standing call (WAIT_S holds only a vehicle that crawled off
    or was lost crawling), and the call drops between the two, as an edge-counting controller needs."""
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)
    events, calls = [], []
    for i in range(int(6.0 * 25)):
        t = i / 25
        states = [VehicleState(vid, t, -2.5, y, y + 4.5, 0.0, -10.0, 4.5, 5)
                  for vid, y in ((1, 41.8 - 10.0 * t), (2, 61.8 - 10.0 * t)) if -10.0 < y < 100.0]
        sight = LoopSight(0.9, None) if 0.9 <= t < 5.0 else LoopSight()
        upd = tm.step(t, EPOCH + t, states, {"L1": sight})
        events += [e for e in upd.loop_events if e.loop_id == "L1"]
        calls.append((t, tm.channels()[0].call))
    assert [e.vehicle_id for e in events] == [1, 2] and tm.channels()[0].count == 2
    assert events[0].t_off == pytest.approx(1.63, abs=0.041)
    assert not any(c for t, c in calls if events[0].t_off + 0.25 < t < 2.95)


def _standing_past(case: str) -> tuple[list, list, float, float]:
    """A car brakes at 2 m/s2 over L1 [30, 31.8] in lane 1 and stands from 5 s with its rear 1.5 m short of the
    loop, on the camera's side ("8 m": 8 m short; "receding": a lane-2 car stands 1.5 m beyond the loop,
    away from the camera); the image shows the loop occupied from when the car came onto it and gives a
    standing call (came then, stood 5 s) from 6.5 s to 40 s (22 s for "drives off"). Its track: kept to the
    end, "lost" at 4.6 s, "lost later" at 20 s, or it "drives off" at 20 s. Returns L1's events (L2's for
    "receding"), the call per frame, and when the car came onto the loop and left it."""
    receding = case == "receding"
    gap = 8.0 if case == "8 m" else 1.5
    stand = 31.8 + gap if receding else 30.0 - gap - 4.5  # its near end where it stands (rear, front)
    lp = {"id": "L2" if receding else "L1", "lane": 2 if receding else 1, "channel": 1, "y_m": 30.0,
          "length_m": 1.8}
    tm = TrafficMeasures(make_site(loops=[lp]))
    # it came onto the loop and left it this far (dt * dt) short of where it stands
    on = 5.0 - (stand + 4.5 - 30.0 if receding else 31.8 - stand) ** 0.5
    off = 5.0 - (stand - 31.8 if receding else 30.0 - 4.5 - stand) ** 0.5
    end = {"lost": 4.6, "lost later": 20.0}.get(case, 45.0)
    call_end = 22.0 if case == "drives off" else 40.0
    events, calls = [], []
    for i in range(int(45.0 * 25)):
        t = i / 25
        dt = max(5.0 - t, 0.0)
        go = max(t - 20.0, 0.0) if case == "drives off" else 0.0
        ahead, v = go * go - dt * dt, 2.0 * (dt + go)  # braking to the stand, then pulling away
        if receding:
            states = [VehicleState(1, t, 2.5, stand + ahead + 4.5, stand + ahead, 0.0, v, 4.5, 5)]
        else:
            states = [VehicleState(1, t, -2.5, stand - ahead, stand - ahead + 4.5, 0.0, -v, 4.5, 5)]
        sight = LoopSight(on if on <= t < call_end else None, (on, 5.0) if 6.5 <= t < call_end else None)
        upd = tm.step(t, EPOCH + t, states if t < end else [], {lp["id"]: sight})
        events += upd.loop_events
        calls.append((t, tm.channels()[0].call))
    assert tm.channels()[0].count == len(events)
    return events, calls, on, off


@pytest.mark.parametrize("case", ["tracked", "drives off"])
def test_a_car_standing_just_past_its_loop_hides_it_rather_than_stands_on_it(case: str):
    """While the tracker holds the car standing just past its loop on the camera's side, its roof hides the
    loop from the camera and the standing call is its body: one actuation, off when the car's rear left the
    loop. The call is refused for as long as it lasts, also when the car drives off before the image lets the
    call go (the call drops WAIT_S after the car left, and stays off)."""
    events, calls, on, off = _standing_past(case)
    assert len(events) == 1 and events[0].vehicle_id == 1
    assert events[0].t_on == pytest.approx(on, abs=0.041) and events[0].t_off == pytest.approx(off, abs=0.041)
    assert not any(c for t, c in calls if t > off + WAIT_S + 0.1)


@pytest.mark.parametrize("case", ["lost", "receding"])
def test_a_car_whose_place_is_unknown_or_hides_nothing_stood_on_its_loop(case: str):
    """Lost before it stood, nothing says where the car is; a receding car standing beyond its loop (away from
    the camera) hides nothing of it: either way the standing call is the car's, stopped on the loop (one
    actuation, on until the call ends at 40 s)."""
    events, _, on, off = _standing_past(case)
    assert len(events) == 1 and events[0].vehicle_id == 1 and events[0].t_on == pytest.approx(on, abs=0.041)
    assert events[0].t_off == pytest.approx(40.0, abs=0.041)


def test_a_car_lost_while_it_hid_its_loop_leaves_the_call_standing():
    """The car hiding its loop is lost at 20 s: nothing says what stands on the loop now (in a queue, the next car,
    its features lost too), so the standing call is taken, as the car's (not counted again), on from the frame
    the track was given up to 40 s."""
    events, calls, on, off = _standing_past("lost later")
    assert len(events) == 1 and events[0].t_off == pytest.approx(off, abs=0.041)
    assert all(c for t, c in calls if 20.3 < t < 39.9) and not any(c for t, c in calls if off + WAIT_S + 0.1 < t < 20.0)


def test_a_car_standing_further_past_its_loop_leaves_the_call_to_another():
    """A car standing 8 m past its loop left it at 20 km/h and hides nothing of it: the standing call is another
    car's, a second actuation from when that one stood."""
    events, _, on, off = _standing_past("8 m")
    assert [e.vehicle_id for e in events] == [1, STANDING] and events[0].t_off == pytest.approx(off, abs=0.041)
    assert events[1].t_on == 5.0 and events[1].t_off == pytest.approx(40.0, abs=0.041)


def test_a_car_rolling_on_past_its_loop_leaves_the_call_to_another():
    """A tracked car rolls over L1 at 3.5 m/s (13 km/h) and on; a standing call comes from 7 s (came 5.8 s,
    stood 6 s) to 20 s while its rear is 5 m past the loop, still moving: a moving car's body does not stand over
    the loop, so the call is another car's, a second actuation from when that one stood, on as it comes."""
    tm = TrafficMeasures(make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}]))
    events, calls = [], []
    for i in range(int(25.0 * 25)):
        t = i / 25
        y = 45.0 - 3.5 * t  # off the loop at 5.57 s (its rear past 30 m), 5 m past it at 7 s
        states = [VehicleState(1, t, -2.5, y, y + 4.5, 0.0, -3.5, 4.5, 5)] if y > 10.0 else []
        sight = LoopSight(5.8 if 5.8 <= t < 20.0 else None, (5.8, 6.0) if 7.0 <= t < 20.0 else None)
        events += tm.step(t, EPOCH + t, states, {"L1": sight}).loop_events
        calls.append((t, tm.channels()[0].call))
    assert [e.vehicle_id for e in events] == [1, STANDING] and tm.channels()[0].count == 2
    assert events[1].t_on == 6.0 and events[1].t_off == pytest.approx(20.0, abs=0.041)
    assert all(c for t, c in calls if 7.05 < t < 19.95)


def test_a_vehicle_driving_onto_a_loop_held_by_a_standing_call_is_counted():
    """The image gives a standing call on L1 from 3.5 s (came 1 s, stood 2 s) to 30 s, the tracker seeing nothing
    there; at 10 s a tracked car drives onto the loop at 36 km/h. Nobody drives through a vehicle standing on a
    loop: the standing call is what a queue's bodies show over it, and the car is a new actuation, counted, its
    call going on where the standing one's ends (the call stays on throughout)."""
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)
    events, calls = [], []
    for i in range(int(32.0 * 25)):
        t = i / 25
        y = 31.8 - 10.0 * (t - 10.0)
        states = [VehicleState(1, t, -2.5, y, y + 4.5, 0.0, -10.0, 4.5, 5)] if 5.0 <= t and y > -10.0 else []
        sight = LoopSight(1.0, (1.0, 2.0)) if 3.5 <= t < 30.0 else LoopSight()
        upd = tm.step(t, EPOCH + t, states, {"L1": sight})
        events += [e for e in upd.loop_events if e.loop_id == "L1"]
        calls.append((t, tm.channels()[0].call))
    assert [e.vehicle_id for e in events] == [STANDING, 1] and tm.channels()[0].count == 2
    assert events[0].t_on == 2.0 and events[0].t_off == pytest.approx(10.0, abs=0.041)
    assert events[1].t_on == pytest.approx(10.0, abs=0.041)
    assert all(c for t, c in calls if 3.5 <= t < 30.0)


def _edie_density(groups: list[tuple], seconds: float = 12.0, fps: float = 25.0) -> float:
    """Lane 1's Edie density over its first period for groups (id, near end at t=0, length, features, seen
    from) moving towards y=0 at 10 m/s."""
    tm = TrafficMeasures(make_site(loops=[]))
    for i in range(int(round(seconds * fps))):
        t = i / fps
        tm.step(t, EPOCH + t, [VehicleState(vid, t, -2.5, y0 - 10.0 * t, y0 - 10.0 * t + length, 0.0, -10.0,
                                            length, n) for vid, y0, length, n, t_from in groups if t >= t_from])
    return next(p.density_vpkm for p in tm.flush(EPOCH + seconds) if p.lane == 1)


@pytest.mark.parametrize("behind_m, counted_twice", [(2.0, False), (4.5, False), (6.5, True)])
def test_edie_counts_a_vehicles_time_once_however_many_groups_it_shows(behind_m: float, counted_twice: bool):
    """A second, smaller group whose near end stays a few metres behind a vehicle's is on that vehicle (its roof,
    a fragment not joined, found only once the vehicle was past its count line): Edie counts the vehicle's time
    and distance once. A follower 6.5 m behind (a car's length and a standstill gap: the closest a queued car
    comes) is a vehicle of its own and counts in full, as it would alone."""
    alone = _edie_density([(1, 100.0, 4.5, 8, 0.0)])
    second = (2, 100.0 + behind_m, 2.0, 3, 5.5)
    both = _edie_density([(1, 100.0, 4.5, 8, 0.0), second])
    assert both == pytest.approx(alone + _edie_density([second]) if counted_twice else alone, rel=1e-6)


def test_a_car_standing_on_a_loop_just_after_another_drove_off_it_is_a_second_actuation():
    """A tracked car drives over L1 at 18 km/h (on 1.64-2.9 s); its body hides the loop from the camera as it goes
    (the image shows the loop occupied from 2 s), and an untracked car comes and stands on the loop from 4 s
    (a standing call from 5.5 s to 20 s). The car that drove off at speed cannot be standing there a second
    later: the standing call is a second actuation, counted, from when it stood."""
    site = make_site(loops=[{"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8}])
    tm = TrafficMeasures(site)
    events = []
    for i in range(int(25.0 * 25)):
        t = i / 25
        y = 40.0 - 5.0 * t
        states = [VehicleState(1, t, -2.5, y, y + 4.5, 0.0, -5.0, 4.5, 5)] if y > 10.0 else []
        sight = LoopSight(2.0 if 2.0 <= t < 20.0 else None, (2.0, 4.0) if 5.5 <= t < 20.0 else None)
        upd = tm.step(t, EPOCH + t, states, {"L1": sight})
        events += [e for e in upd.loop_events if e.loop_id == "L1"]
    assert [e.vehicle_id for e in events] == [1, STANDING] and tm.channels()[0].count == 2
    assert events[0].t_off == pytest.approx(2.9, abs=0.041)
    assert events[1].t_on == 4.0 and events[1].t_off == pytest.approx(20.0, abs=0.041)


def test_a_receding_vehicles_front_measured_further_ahead_adds_no_edie_distance():
    """A receding vehicle's front is its rear plus its length, which grows from 2 m to 5 m halfway through the
    region as more of the vehicle shows (the bonnet beyond the windscreen). Edie follows its rear (plus the
    2 m of its first report): its speed over the region is its own, 36 km/h, and not 3 m in no time faster."""
    site = make_site(period_s=60, loops=[])
    tm, periods = TrafficMeasures(site), []
    for i in range(0, 651):
        t = i * 0.1
        rear = 15.0 + 10.0 * t
        length = 2.0 if rear < 50.0 else 5.0
        v = VehicleState(7, t, 2.5, rear + length, rear, 0.0, 10.0, length, 8)
        periods += tm.step(t, EPOCH + t, [v] if rear < 95.0 else []).periods
    p = next(p for p in periods if p.lane == 2)
    assert p.count == 1
    assert p.speed_kmh == pytest.approx(36.0, rel=1e-6)
    assert p.density_vpkm * 60.0 / 1000.0 * 60.0 == pytest.approx(6.0, rel=1e-6)  # 6 s in the 60 m region


def test_a_group_joining_another_does_not_shift_the_lanes_of_the_vehicles_after_it():
    """A big group ending as a part of a vehicle in lane 1 (its last state says whom it joined) in the frame where a
    smaller vehicle in lane 2 crosses its count line: the measures take the vehicles biggest first, and the
    receding one's place in lane 2 is its own, not the joined group's (which made it cross lane 1's line, where
    it was not)."""
    tm = TrafficMeasures(make_site(loops=[]))
    t_join = 2.0  # the receding car's front reaches lane 2's count line (40 m) then

    def states(t: float, y: float) -> list[VehicleState]:
        vs = [VehicleState(1, t, -2.5, y, y + 4.5, 0, -20, 4.5, 8)]
        if t <= t_join:
            vs.append(VehicleState(2, t, -2.4, y + 6.0, y + 8.0, 0, -24, 2.0, 20, finished=t >= t_join,
                                   joined=1 if t >= t_join else None))
        yf = 40.0 + 15.0 * (t - t_join)
        vs.append(VehicleState(3, t, 2.5, yf, yf - 4.5, 0, 15, 4.5, 5))
        return vs

    crossings = [c for _, upd in drive(tm, states) for c in upd.crossings]
    assert [(c.vehicle_id, c.lane) for c in crossings if c.vehicle_id == 3] == [(3, 2)]
