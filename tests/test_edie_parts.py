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


def _track(lane: int, x: float, y0: float, v: float, t0: float = 0.0, t1: float = 4.0) -> dict:
    n = int(round((t1 - t0) * FPS))
    return {"lane": lane, "trajectory": [[t0 + i / FPS, x, y0 + v * i / FPS] for i in range(n + 1)]}


REGIONS = {1: (0.0, 200.0), 2: (0.0, 200.0)}


def test_a_perfect_tracker_is_all_own_tracks_at_the_truths_distance(tmp_path):
    truth = _truth(tmp_path)
    lanes = edie_parts(truth, [_track(1, 0.0, 10.0, 20.0), _track(1, 0.0, 30.0, 20.0), _track(2, 3.5, 10.0, 15.0)],
                       REGIONS)
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
    tracks = [
        _track(1, 0.0, 10.0, 20.0 * 1.05),  # car 1, reading 5 % fast
        _track(1, 0.0, 31.0, 20.0, t0=1.0, t1=2.0),  # its roof as a second, shorter track: a duplicate
        _track(1, 3.5, 10.0, 15.0),  # car 3 of lane 2 counted in lane 1
        _track(1, 0.0, 100.0, 20.0),  # where no vehicle is
    ]
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
