"""The split of a lane's Edie distance and time by the truth vehicle under each measured track: own tracks,
duplicates, tracks on another lane's vehicle or on none, and the own tracks' distance against the truth's."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from tools.edie_parts import edie_parts, format_edie_parts

FPS = 25.0
FIELDS = ["frame", "t", "vehicle_id", "class", "lane", "x_m", "y_front_m", "y_rear_m", "visible_frac"]


def _truth(path: Path) -> Path:
    """Three cars for 4 s: 1 and 2 in lane 1 (x 0) 20 m apart at 20 m/s, 3 in lane 2 (x 3.5) at 15 m/s;
    car 2 is partly hidden in its second half."""
    rows = []
    for f in range(int(4 * FPS) + 1):
        t = f / FPS
        for vid, lane, x, y0, v in ((1, 1, 0.0, 10.0, 20.0), (2, 1, 0.0, 30.0, 20.0), (3, 2, 3.5, 10.0, 15.0)):
            y = y0 + v * t
            vis = 0.5 if vid == 2 and f > 2 * FPS else 1.0
            rows.append(dict(frame=f, t=f"{t:.6f}", vehicle_id=vid, **{"class": "car"}, lane=lane, x_m=x,
                             y_front_m=y, y_rear_m=y - 4.5, visible_frac=vis))
    p = path / "vehicles.csv"
    with open(p, "w", newline="") as fh:
        w = csv.DictWriter(fh, FIELDS)
        w.writeheader()
        w.writerows(rows)
    return p


def _track(lane: int, x: float, y0: float, v: float, t0: float = 0.0, t1: float = 4.0, vid: int = 0,
           sign: float = 1.0) -> list[dict]:
    """A measured vehicle's Edie segments from frame to frame (wall time = capture time here)."""
    n = int(round((t1 - t0) * FPS))
    pts = [(t0 + i / FPS, y0 + v * i / FPS) for i in range(n + 1)]
    return [dict(vehicle_id=vid, lane=lane, w0=a[0], w1=b[0], y0=a[1], y1=b[1], sign=sign, x=x)
            for a, b in zip(pts, pts[1:])]


REGIONS = {1: (0.0, 200.0), 2: (0.0, 200.0)}


def test_a_perfect_tracker_is_all_own_tracks_at_the_truths_distance(tmp_path):
    truth = _truth(tmp_path)
    lanes = edie_parts(truth, _track(1, 0.0, 10.0, 20.0, vid=1) + _track(1, 0.0, 30.0, 20.0, vid=2)
                       + _track(2, 3.5, 10.0, 15.0, vid=3), REGIONS)
    one, two = lanes
    assert one.truth_d == pytest.approx(160.0) and one.truth_t == pytest.approx(8.0)
    assert one.parts["own"][2] == 2 and one.parts["own"][0] == pytest.approx(160.0)
    assert all(one.parts[p][2] == 0 for p in ("duplicate", "other lane", "no vehicle"))
    m, tr = one.own_vs_truth["in view"]
    assert m == pytest.approx(tr) and tr == pytest.approx(120.0)  # car 1's 80 m, car 2's first half
    assert one.own_vs_truth["partly hidden"][1] == pytest.approx(40.0)
    assert two.parts["own"][0] == pytest.approx(60.0)
    assert "+0.0 %" in format_edie_parts(lanes)


def test_duplicates_other_lanes_and_empty_road_are_told_apart(tmp_path):
    truth = _truth(tmp_path)
    tracks = (
        _track(1, 0.0, 10.0, 20.0 * 1.05, vid=1)  # car 1, reading 5 % fast
        + _track(1, 0.0, 31.0, 20.0, t0=1.0, t1=2.0, vid=2)  # its roof as a second, shorter track: a duplicate
        + _track(1, 3.5, 10.0, 15.0, vid=3)  # car 3 of lane 2 counted in lane 1
        + _track(1, 0.0, 100.0, 20.0, vid=4)  # where no vehicle is
    )
    one = edie_parts(truth, tracks, REGIONS)[0]
    assert one.parts["own"][2] == 1
    m, tr = one.own_vs_truth["in view"]
    assert m / tr == pytest.approx(1.05, abs=0.01)
    assert one.parts["duplicate"][2] == 1 and one.parts["duplicate"][0] == pytest.approx(20.0)
    assert one.parts["other lane"][2] == 1 and one.parts["other lane"][0] == pytest.approx(60.0)
    assert one.parts["no vehicle"][2] == 1 and one.parts["no vehicle"][1] == pytest.approx(4.0)
    # only steps inside the lane's region count
    none = edie_parts(truth, tracks, {1: (500.0, 600.0), 2: (0.0, 200.0)})[0]
    assert none.measured == (0.0, 0.0) and none.truth_d == 0.0


def test_a_vehicle_found_again_after_a_loss_is_its_own_not_a_duplicate(tmp_path):
    truth = _truth(tmp_path)
    first, again = _track(1, 0.0, 10.0, 20.0, t1=2.0, vid=1), _track(1, 0.0, 52.4, 20.0, t0=2.12, vid=2)  # lost 0.12 s
    one = edie_parts(truth, again + first, REGIONS)[0]
    assert one.parts["own"][2] == 2 and one.parts["duplicate"][2] == 0
    assert one.parts["own"][0] == pytest.approx(40.0 + 37.6)
    # the same two tracks at the same time: the shorter one's steps are the duplicate's
    roof = _track(1, 0.0, 10.5, 20.0, t1=1.0, vid=3)
    both = edie_parts(truth, first + roof, REGIONS)[0]
    assert both.parts["duplicate"][2] == 1 and both.parts["duplicate"][0] == pytest.approx(20.0)
    # ... and once the measures took its segments back (joined to the vehicle's family) it counts for nothing
    back = edie_parts(truth, first + roof + [dict(sg, sign=-1.0) for sg in roof], REGIONS)[0]
    assert back.parts["duplicate"][0] == pytest.approx(0.0, abs=1e-9) and back.measured[0] == pytest.approx(40.0)
    # segments carry wall times: start_wall shifts them onto the truth's capture times
    late = [dict(sg, w0=sg["w0"] + 100.0, w1=sg["w1"] + 100.0) for sg in first]
    assert edie_parts(truth, late, REGIONS, start_wall=100.0)[0].parts["own"][0] == pytest.approx(40.0)


def test_a_track_led_by_a_roof_lies_above_its_vehicle_given_the_camera(tmp_path):
    """A track 15 % further out than car 1's front (its roof, seen from a camera 10 m up: a car's roof may be
    magnified up to 10 / (10 - 1.55)) is that car's own, led by a part above the road, once the camera is
    known; without it, it lies on no vehicle for most of its way."""
    truth = _truth(tmp_path)
    roof = [dict(sg, y0=sg["y0"] * 1.15, y1=sg["y1"] * 1.15) for sg in _track(1, 0.0, 10.0, 20.0, vid=1)]
    seen = edie_parts(truth, roof, REGIONS, camera=(10.0, 10.0))[0]
    assert seen.parts["own"][2] == 1 and seen.above[0] > 0.5 * seen.parts["own"][0]
    assert 3.6 * seen.above[0] / seen.above[1] == pytest.approx(1.15 * 72.0, rel=0.01)
    blind = edie_parts(truth, roof, REGIONS)[0]
    assert blind.parts["no vehicle"][2] == 1 and blind.above == [0.0, 0.0]
