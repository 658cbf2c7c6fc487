"""Loop actuations against the truth's by vehicle class (tools.loop_classes): matching on channel and on-time,
and the perfect tracker's loops, which must match the simulator's class by class."""

from __future__ import annotations

import pytest

from appliance.config import load_site
from tools.evaluate import load_results, load_truth
from tools.loop_classes import loop_classes, merge, truth_classes
from tools.replay import replay_truth_tracks, write_results

simulate = pytest.importorskip("tools.simulate.scenario")


def _ev(ch: int, on: float, off: float, vid: int = 0, length: float | None = 4.0) -> dict:
    return {"channel": ch, "t_on": on, "t_off": off, "vehicle_id": vid, "length_m": length}


def test_each_truth_actuation_takes_the_nearest_free_one_of_its_channel():
    truth = [_ev(1, 10.0, 10.5, 1, 4.4), _ev(1, 10.3, 11.5, 2, 16.0), _ev(2, 20.0, 20.6, 3, 4.2),
             _ev(1, 30.0, 30.4, 4, 4.0)]
    result = [_ev(1, 10.05, 10.45, length=4.5), _ev(1, 10.35, 10.75, length=4.5),  # both near 10 s: one each
              _ev(2, 20.5, 21.0),  # on 0.5 s late: not the same vehicle
              _ev(3, 30.0, 30.4, length=None)]  # another channel
    rows = loop_classes(truth, result, {1: "car", 2: "artic", 3: "car", 4: "van"})
    car, artic, van = rows["car"], rows["artic"], rows["van"]
    assert (car.truth, car.matched, artic.truth, artic.matched, van.truth, van.matched) == (2, 1, 1, 1, 1, 0)
    assert car.on_truth_s == pytest.approx(0.5) and car.on_result_s == pytest.approx(0.4)
    assert artic.on_truth_s == pytest.approx(1.2) and artic.on_result_s == pytest.approx(0.4)
    assert artic.length_medians() == pytest.approx((16.0, 4.5))
    assert car.class_right() == 1.0 and artic.class_right() == 0.0  # 4.5 m is a small vehicle, 16 m a large one
    total = merge([rows, loop_classes(truth[:1], result[:1], {1: "car"})])
    assert (total["car"].truth, total["car"].matched) == (3, 2)


def test_an_actuation_without_a_measured_length_counts_its_on_time_only():
    rows = loop_classes([_ev(1, 5.0, 5.5, 7, 4.4)], [_ev(1, 5.1, 5.5, length=None)], {7: "car"})
    assert rows["car"].matched == 1 and rows["car"].on_result_s == pytest.approx(0.4)
    assert rows["car"].length_medians() is None and rows["car"].class_right() is None


def test_the_perfect_trackers_loops_match_the_truths_class_by_class(tmp_path):
    """The truth trajectories through TrafficMeasures: every class's actuations are found, held as long and
    measured as long as the simulator's (its loops use the same bodies; vehicles.csv is sampled per frame, so
    on-times may differ by a frame at each end: 2 % allowed over a class's sum)."""
    scene = simulate.render_scenario("trucks-and-buses", 11, 30.0, tmp_path / "sim", width=320, height=240,
                                     fps=25.0)
    res = replay_truth_tracks(scene.truth_dir, load_site(scene.site))
    out = tmp_path / "perfect.csv"
    write_results(res, str(out), vehicles=True)
    truth, results = load_truth(scene.truth_dir), load_results(out)
    rows = loop_classes(truth["loop_events"], results["loop_events"], truth_classes(truth["vehicles_path"]))
    assert sum(c.truth for c in rows.values()) == len(truth["loop_events"]) > 10
    assert len(rows) >= 3, sorted(rows)  # cars and at least two other classes in 30 s of this preset
    for name, c in rows.items():
        assert c.matched == c.truth, name
        assert c.on_result_s == pytest.approx(c.on_truth_s, rel=0.02), name
        med = c.length_medians()
        assert med is not None and med[1] == pytest.approx(med[0], rel=0.02), name
        assert c.class_right() >= 0.95, name  # a length within a frame's travel of a class bound may fall over it
