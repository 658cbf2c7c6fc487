"""Evaluation against the simulator: perfect-tracker replay of the truth trajectories, and the real
pipeline on a rendered scene through `roadwatch replay` and `roadwatch evaluate` (CLI, SQLite, CSV)."""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest

from appliance.config import load_site
from tools.edie_parts import edie_parts
from tools.evaluate import compare_with_truth, load_results, load_truth, table1
from tools.replay import replay_truth_tracks, write_results

simulate = pytest.importorskip("tools.simulate.scenario")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    return simulate.render_scenario("free-flow", 11, 24.0, out, width=640, height=480, fps=25.0)


def test_table1_shares():
    shares = table1([1.0, -3.0, 7.0, -12.0, 30.0])
    assert shares == {2.5: 20.0, 5.0: 40.0, 10.0: 60.0, 15.0: 80.0, 20.0: 80.0, 25.0: 80.0}


def test_truth_trajectories_reproduce_truth_aggregates(scene, tmp_path):
    """vehicles.csv (sampled per frame, only vehicles in view) through TrafficMeasures gives the
    simulator's aggregates, computed separately from the continuous trajectories."""
    site = load_site(scene.site)
    res = replay_truth_tracks(scene.truth_dir, site)
    out = tmp_path / "perfect.csv"
    write_results(res, str(out), vehicles=True)
    cmp = compare_with_truth(load_truth(scene.truth_dir), load_results(out))
    assert len(cmp.pairs) == len(site.lanes)
    for lane, (t, r) in cmp.lane_counts.items():
        assert r == t, lane
    # vehicles.csv lists only vehicles in the image: a vehicle whose front is in the region while its
    # body is still out of view is missing for those frames; seen: <= 0.2 %, allowed 1 %
    for name in ("flow", "density", "speed"):
        assert max(abs(e) for e in cmp.errors[name]) < 1.0, name
    assert max(abs(e) for e in cmp.occupancy_pp) < 0.1
    assert sum(r for _, r in cmp.loop_counts.values()) == sum(t for t, _ in cmp.loop_counts.values())
    # each counted vehicle in its length class (the truth's lengths are exact)
    assert sum(t for t, _ in cmp.class_counts.values()) == sum(t for t, _ in cmp.lane_counts.values())
    assert all(r == t for t, r in cmp.class_counts.values()), cmp.class_counts


def test_replay_and_evaluate_rendered_scene(scene, tmp_path):
    db = tmp_path / "res.sqlite"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "replay", str(scene.video), "--config", str(scene.site),
                        "--out", str(db), "--vehicles"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    fig7, fig6, t1 = tmp_path / "fig7.png", tmp_path / "fig6.png", tmp_path / "t1.png"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "evaluate", "--truth", str(scene.truth_dir), "--results",
                        str(db), "--plot", str(fig7), "--time-space", str(fig6), "--errors-png", str(t1),
                        "--edie-parts", "--config", str(scene.site)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "<=2.5%" in r.stdout and "Loop occupancy error" in r.stdout
    assert "Edie distance and time counted, by the truth vehicle" in r.stdout and "own tracks' distance" in r.stdout
    for png in (fig7, fig6, t1):
        assert png.stat().st_size > 5000
    cmp = compare_with_truth(load_truth(scene.truth_dir), load_results(db))
    # counts: the tracker counted every vehicle of this free-flowing scene when written (0 error);
    # one vehicle per lane of slack for a borderline crossing at the clip's ends
    for lane, (t, res) in cmp.lane_counts.items():
        assert abs(res - t) <= 1, (lane, t, res, r.stdout)
    assert sum(t for t, _ in cmp.lane_counts.values()) >= 5  # the scene had traffic (8 vehicles)
    # the same results as CSV read back identically
    res = load_results(db)
    assert res["periods"] and res["crossings"] and res["vehicles"]


def test_evaluate_needs_matching_periods(scene, tmp_path):
    site = load_site(scene.site)
    res = replay_truth_tracks(scene.truth_dir, site, start_wall=0.0)  # wrong start: nothing lines up
    out = tmp_path / "wrong.csv"
    write_results(res, str(out), vehicles=False)
    r = subprocess.run([sys.executable, "-m", "tools.cli", "evaluate", "--truth", str(scene.truth_dir), "--results",
                        str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "no period matches" in r.stderr


def test_replay_truth_tracks_cli(scene, tmp_path):
    out = tmp_path / "perfect.sqlite"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "replay", "--truth-tracks", str(scene.truth_dir),
                        "--config", str(scene.site), "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    cmp = compare_with_truth(load_truth(scene.truth_dir), load_results(out))
    assert all(t == res for t, res in cmp.lane_counts.values())


def test_a_perfect_trackers_edie_segments_are_its_vehicles_own(scene, tmp_path):
    """The perfect tracker's Edie segments (replay --vehicles writes them) lie on their own truth vehicles
    and add up to the truth's distance and time (within 1 %: vehicles.csv lists a vehicle only while it is in
    view); evaluate --edie-parts prints the split."""
    out = tmp_path / "perfect.sqlite"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "replay", "--truth-tracks", str(scene.truth_dir),
                        "--config", str(scene.site), "--out", str(out), "--vehicles"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    truth, res = load_truth(scene.truth_dir), load_results(out)
    site = load_site(scene.site)
    regions = {lane.id: tuple(lane.region_y_m) for lane in site.lanes}
    lanes = edie_parts(truth["vehicles_path"], res["edie_segments"], regions, truth["meta"]["start_wall"])
    assert sum(lp.truth_d for lp in lanes) > 500  # the scene had traffic
    for lp in lanes:
        d, t = lp.measured
        assert d == pytest.approx(lp.truth_d, rel=0.01) and t == pytest.approx(lp.truth_t, rel=0.01), lp
        assert lp.parts["own"][0] == pytest.approx(d, rel=0.01), lp
        m, tr = lp.own_vs_truth["in view"]
        assert m == pytest.approx(tr, rel=0.005), lp
    r = subprocess.run([sys.executable, "-m", "tools.cli", "evaluate", "--truth", str(scene.truth_dir), "--results",
                        str(out), "--edie-parts", "--config", str(scene.site)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "own tracks' distance against their vehicles'" in r.stdout


def test_crossings_are_matched_with_the_truths_and_the_odd_ones_listed(scene, tmp_path):
    """The perfect tracker's crossings all match the truth's; one taken out is listed as missed (with its
    class), one added 3 s away from any other as extra; the CLI prints both lists."""
    from tools.evaluate import compare_crossings_with_truth, format_crossing_lists

    site = load_site(scene.site)
    out = tmp_path / "perfect.csv"
    write_results(replay_truth_tracks(scene.truth_dir, site), str(out), vehicles=False)
    truth, res = load_truth(scene.truth_dir), load_results(out)
    cmp = compare_crossings_with_truth(truth, res["crossings"])
    assert len(cmp.matches) == len(res["crossings"]) >= 5 and not cmp.missed and not cmp.extra
    gone = res["crossings"][2]
    ts = sorted(float(c["t"]) for c in res["crossings"])
    gap = max(range(len(ts) - 1), key=lambda i: ts[i + 1] - ts[i])
    assert ts[gap + 1] - ts[gap] > 6.0
    ghost = dict(res["crossings"][0], t=(ts[gap] + ts[gap + 1]) / 2, frame=None, vehicle_id=999)
    crossings = [c for c in res["crossings"] if c is not gone] + [ghost]
    cmp = compare_crossings_with_truth(truth, crossings)
    assert [c["vehicle_id"] for c in cmp.extra] == [999]
    assert len(cmp.missed) == 1 and cmp.missed[0]["lane"] == int(gone["lane"])
    assert abs(cmp.missed[0]["t"] - float(gone["t"])) < 0.1
    text = format_crossing_lists(cmp)
    assert "vehicle 999" in text and f"{cmp.missed[0]['class']} {cmp.missed[0]['vehicle_id']}" in text
    r = subprocess.run([sys.executable, "-m", "tools.cli", "evaluate", "--truth", str(scene.truth_dir), "--results",
                        str(out), "--crossings"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Count-line crossings vs the truth's" in r.stdout and "extra  lane" not in r.stdout


def test_a_late_crossing_matches_within_a_wider_window(scene, tmp_path):
    """A crossing 2 s late (a crawling vehicle's near end a few metres behind its bumper) is a missed vehicle
    and an extra one within the default 1 s, one match within --window 3; a window of 0 s, or one given with
    a hand count, is refused by name."""
    site = load_site(scene.site)
    res = tmp_path / "perfect.csv"
    write_results(replay_truth_tracks(scene.truth_dir, site), str(res), vehicles=False)
    rows = list(csv.DictReader(open(tmp_path / "perfect_crossings.csv")))

    def room(c: dict) -> float:
        """Seconds to the nearest other crossing of its lane, before it or 2 s after it."""
        t = float(c["t"])
        others = [float(o["t"]) for o in rows if o is not c and o["lane"] == c["lane"]]
        return min([t - o for o in others if o <= t] + [(o - t - 2.0) for o in others if o > t] + [60.0])

    late = max(rows, key=room)
    assert room(late) > 3.0  # no other crossing of its lane within 3 s of it, late or not
    late["t"] = str(float(late["t"]) + 2.0)
    with open(tmp_path / "perfect_crossings.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)

    def run(*extra: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "tools.cli", "evaluate", "--truth", str(scene.truth_dir),
                               "--results", str(res), "--crossings", *extra], capture_output=True, text=True,
                              timeout=120)

    r = run()
    assert r.returncode == 0, r.stderr[-2000:]
    assert "within 1 s" in r.stdout and r.stdout.count("extra  lane") == 1 and r.stdout.count("missed lane") == 1
    r = run("--window", "3")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "within 3 s" in r.stdout and "extra  lane" not in r.stdout and "missed lane" not in r.stdout
    r = run("--window", "0")
    assert r.returncode == 2 and "--window" in r.stderr
    r = subprocess.run([sys.executable, "-m", "tools.cli", "evaluate", "--counts", str(tmp_path / "c.json"),
                        "--results", str(res), "--window", "2"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--window is for --truth" in r.stderr


def test_the_matched_vehicles_records_are_checked_for_their_length_class(scene, tmp_path):
    """The perfect tracker's vehicle records carry the truth's lengths: every matched vehicle is in its
    length class. One record measured a car's nominal length instead of its own (a van's 5.5 m or more, a
    truck's) counts as wrong, in its truth class."""
    from tools.evaluate import compare_crossings_with_truth, record_classes_right

    site = load_site(scene.site)
    out = tmp_path / "perfect.csv"
    write_results(replay_truth_tracks(scene.truth_dir, site), str(out), vehicles=True)
    truth, res = load_truth(scene.truth_dir), load_results(out)
    cmp = compare_crossings_with_truth(truth, res["crossings"])
    right = record_classes_right(cmp, res["vehicles"])
    assert sum(n for n, _ in right.values()) == len(cmp.matches) >= 5
    assert all(k == n for n, k in right.values()), right
    long = next(h for h, r in cmp.matches if float(h["length_m"]) > 6.5)
    rid = int(next(r for h, r in cmp.matches if h is long)["vehicle_id"])
    shortened = [dict(v, length_m=4.5) if int(v["id"]) == rid else v for v in res["vehicles"]]
    after = record_classes_right(cmp, shortened)
    n, k = after[long["class"]]
    assert (n, k) == (right[long["class"]][0], right[long["class"]][1] - 1)


def test_spot_speeds_at_the_count_line_are_compared_with_the_truths(scene, tmp_path):
    """The perfect tracker's spot speeds are the truth's; read 5 % fast, every one is 5 % off."""
    from tools.evaluate import compare_crossings_with_truth, format_spot_speeds, spot_speed_errors

    out = tmp_path / "perfect.csv"
    write_results(replay_truth_tracks(scene.truth_dir, load_site(scene.site)), str(out), vehicles=False)
    truth, res = load_truth(scene.truth_dir), load_results(out)
    errors = spot_speed_errors(compare_crossings_with_truth(truth, res["crossings"]))
    assert sum(len(e) for e in errors.values()) >= 5
    assert all(abs(x) < 0.5 for e in errors.values() for x in e)
    fast = [dict(c, speed_kmh=float(c["speed_kmh"]) * 1.05) for c in res["crossings"]]
    errors = spot_speed_errors(compare_crossings_with_truth(truth, fast))
    assert all(x == pytest.approx(5.0, abs=0.5) for e in errors.values() for x in e)
    assert "median +5.0 %" in format_spot_speeds(errors)


def test_extra_and_missed_crossings_get_their_likely_cause():
    """Lanes 1-2 approaching, 3 receding. An extra in lane 1 with a car missed in lane 2 0.3 s later is one
    vehicle counted in the wrong lane (not so the lane-3 car missed 0.1 s away: another direction); an extra
    0.8 s behind a bus in its lane is a part of it, and so is one 0.6 s ahead of a receding van (its top seen
    ahead of it); one beside a truck in the next lane is a roof or shadow of it; an extra near cars only is
    unexplained. Of the misses left, one hidden at the line, one seen there."""
    from tools.evaluate import CountComparison, cause_counts, crossing_error_causes, format_crossing_lists

    def truth(lane, t, cls, sign=-1, visible=1.0):
        return {"lane": lane, "t": t, "class": cls, "vehicle_id": int(t * 10), "visible": visible, "sign": sign}

    def res(lane, t):
        return {"lane": lane, "t": t, "vehicle_id": int(t * 100)}

    bus, truck, car = truth(2, 20.0, "bus"), truth(1, 40.0, "truck"), truth(1, 60.0, "car")
    cmp = CountComparison(
        matches=[(bus, res(2, 20.0)), (truck, res(1, 40.0)), (car, res(1, 60.0)),
                 (truth(3, 10.0, "car", 1), res(3, 10.0)), (truth(3, 50.0, "van", 1), res(3, 50.0))],
        missed=[truth(3, 10.6, "car", 1), truth(2, 10.8, "car"), truth(1, 70.0, "car", visible=0.2),
                truth(2, 80.0, "van")],
        extra=[res(1, 10.5), res(2, 20.8), res(2, 40.5), res(2, 60.5), res(3, 49.4)])
    extra, missed = crossing_error_causes(cmp)
    assert extra == ["wrong lane", "part of a big vehicle", "beside a big vehicle", "unexplained",
                     "part of a big vehicle"]
    assert missed == ["seen at the line", "wrong lane", "occluded at the line", "seen at the line"]
    counts = cause_counts(cmp)
    assert counts["extra"] == {"wrong lane": 1, "part of a big vehicle": 2, "beside a big vehicle": 1, "unexplained": 1}
    assert counts["missed"] == {"wrong lane": 1, "occluded at the line": 1, "seen at the line": 2}
    text = format_crossing_lists(cmp)
    assert "t    20.80 s  vehicle 2080  [part of a big vehicle]" in text and "van 800, 100 % visible  [seen" in text
