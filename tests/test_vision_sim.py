"""Vision pipeline counts per lane (and speeds at the count line) against ground truth: simulator scenes and
the hand-counted real clip.

A vehicle counts in a lane when its reported near-end trajectory crosses the lane's count_y_m with its
place across the road (x) inside the lane; truth counts the simulator's vehicle fronts crossing the same line.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from appliance.config import SiteConfig, load_site, parse_site
from appliance.pipeline import VisionPipeline
from appliance.types import Frame



def _spot(state) -> float:
    """A reported state's spot speed (m/s), as the measures take it; NaN for a point of a trajectory."""
    spot = getattr(state, "spot_vy", None)
    return abs(spot if spot is not None else getattr(state, "vy", np.nan))

def _crosses(a: float, b: float, y: float, approaching: bool) -> bool:
    return a > y >= b if approaching else a < y <= b


def pipeline_counts(site: SiteConfig, frames) -> tuple[dict[int, int], VisionPipeline]:
    """Per-lane crossings of the vehicles the pipeline reports, over (seq, t, grey image) frames."""
    pipe = VisionPipeline(site)
    pipe.warmup()
    seen: dict[int, list] = {}
    for k, t, img in frames:
        for s in pipe.step(Frame(seq=k, t=t, wall=1767225600.0 + t, image=img)):
            states = seen.setdefault(s.id, [])
            for pt, px, py in s.trajectory or []:  # the points before a vehicle's first report
                states.append(SimpleNamespace(t=pt, x=px, y_front=py))
            states.append(s)
    counts = {}
    pipe.crossings = []  # (lane, time, speed m/s) of each counted crossing
    for lane in site.lanes:
        xs = [p[0] for p in lane.polygon_m]
        x0, x1, cy = min(xs), max(xs), lane.count_y_m
        app = lane.direction == "approaching"
        hits = [
            (lane.id, a.t + (b.t - a.t) * (cy - a.y_front) / (b.y_front - a.y_front), _spot(b))
            for states in seen.values()
            for a, b in zip(states, states[1:])
            if _crosses(a.y_front, b.y_front, cy, app) and x0 <= b.x < x1
        ]
        counts[lane.id] = len(hits)
        pipe.crossings += hits
    return counts, pipe


def sim_frames(d: Path):
    times = [float(r["t"]) for r in csv.DictReader(open(d / "truth" / "frames.csv"))]
    cap = cv2.VideoCapture(str(d / "video.mp4"))
    k = 0
    while k < len(times):
        ok, img = cap.read()
        if not ok:
            break
        yield k, times[k], cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        k += 1
    cap.release()


def truth_crossings(d: Path, site: SiteConfig) -> list[tuple[int, float, float]]:
    """(lane, time, speed m/s) of every truth front crossing a count line after the first frame."""
    by_vehicle: dict[str, list[dict]] = {}
    for r in csv.DictReader(open(d / "truth" / "vehicles.csv")):
        by_vehicle.setdefault(r["vehicle_id"], []).append(r)
    out = []
    for lane in site.lanes:
        app = lane.direction == "approaching"
        for rows in by_vehicle.values():
            for a, b in zip(rows, rows[1:]):
                ya, yb = float(a["y_front_m"]), float(b["y_front_m"])
                if int(a["frame"]) > 0 and int(b["lane"]) == lane.id and _crosses(ya, yb, lane.count_y_m, app):
                    ta, tb = float(a["t"]), float(b["t"])
                    out.append((lane.id, ta + (tb - ta) * (lane.count_y_m - ya) / (yb - ya), float(b["speed_mps"])))
    return out


def speed_errors(got: list[tuple[int, float, float]], want: list[tuple[int, float, float]], tol_s: float = 0.5) -> np.ndarray:
    """Relative speed error of each reported crossing matched to a truth crossing of its lane within tol_s."""
    errs = []
    for lane, t, v in got:
        near = [w for w in want if w[0] == lane and abs(w[1] - t) <= tol_s]
        if near and np.isfinite(v):
            w = min(near, key=lambda w: abs(w[1] - t))
            errs.append((v - w[2]) / w[2])
    return np.array(errs)


def truth_counts(crossings: list[tuple[int, float, float]], site: SiteConfig) -> dict[int, int]:
    """Truth crossings per lane; vehicles already past the line in the first frame cannot be seen crossing."""
    return {lane.id: sum(1 for c in crossings if c[0] == lane.id) for lane in site.lanes}


def render(preset: str, seed: int, seconds: float, tmp: Path, **size: int) -> Path:
    from tools.simulate import render_scenario

    out = render_scenario(preset, seed, seconds, tmp / f"{preset}-{seed}", **size)
    return Path(out.video).parent


def check_counts(d: Path, lane_tol: float, total_tol: float, speed_tol: float | None = None) -> tuple[dict, dict]:
    site = load_site(d / "site.toml")
    got, pipe = pipeline_counts(site, sim_frames(d))
    crossings = truth_crossings(d, site)
    want = truth_counts(crossings, site)
    if speed_tol is not None:
        e = speed_errors(pipe.crossings, crossings)
        assert len(e) >= MIN_MATCHED * len(pipe.crossings), (len(e), len(pipe.crossings))
        assert np.median(np.abs(e)) <= speed_tol, np.median(np.abs(e))
    assert sum(want.values()) > 0
    for lane, n in want.items():
        assert abs(got[lane] - n) <= max(2, lane_tol * n), (lane, got, want)
    total = sum(want.values())
    assert abs(sum(got.values()) - total) <= max(2, total_tol * total), (got, want)
    return got, want


def test_free_flow_counts_per_lane(tmp_path):
    d = render("free-flow", 1, 20.0, tmp_path)
    # Measured with this parameter set: free-flow seeds 1-2 over 20-30 s are within 1 vehicle per lane.
    # 2 vehicles (or 25 %) per lane still fails a tracker that misses, splits or merges vehicles wholesale.
    check_counts(d, lane_tol=0.25, total_tol=0.2)


SLOW_PRESETS = ["free-flow", "dense", "trucks-and-buses", "long-shadows", "night", "wind-shake", "two-directions", "defects"]


# The tracker is not at the 3 % target yet. Measured (seed 2, 40 s): free-flow, dense, trucks-and-
# buses, night, wind-shake and two-directions within 35 % per lane (dense 15 %, night 13 %, trucks 23 %,
# wind-shake 25 %, two-directions 33 %: fragments of tall vehicles, side parts across the lane line);
# long-shadows +53 % in its third lane (the shadow test needs the road background, learnt in the first 8 s
# of this short scene) and defects +57 % in lane 1 (15 fps content splits vehicles; 11 of 7 since a
# vehicle's x is its low features' middle: a group straddling the lane line in the clip's last second now
# falls in lane 1; `roadwatch replay` counts 10, merging a fragment); two-directions +42 % in lane 3 (17 of
# 12: the shadows of lane 4's receding cars; since standing features are kept out of a group's near end it
# is one more here, and 5-14 fewer over 320 s, seeds 11 and 12). These bounds hold the current
# level, so a regression or a broken stage (which gives 0 or 2x counts) fails.
LANE_TOL = {"long-shadows": 0.6, "defects": 0.6, "two-directions": 0.45}
# Speeds at the count line, each reported crossing matched to a truth crossing of its lane within 0.5 s:
# measured median errors of the spot speed 1.0-2.4 % on free-flow, dense, trucks-and-buses, two-directions
# and night (of the low part's velocity, before spot speeds: 2.1-2.3 %, night 4.8 %), matched 74-99 % of
# reported crossings (the rest are the extra counts above). A wrong clock or scale, or a near end that lags,
# is off by 10 % or more.
SPEED_TOL = 0.06
MIN_MATCHED = 0.6


@pytest.mark.slow
@pytest.mark.parametrize("preset", SLOW_PRESETS)
def test_preset_counts_per_lane(tmp_path, preset):
    d = render(preset, 2, 40.0, tmp_path)
    tol = LANE_TOL.get(preset, 0.35)
    check_counts(d, lane_tol=tol, total_tol=tol, speed_tol=SPEED_TOL)


# A 1280x720 camera is tracked on its frames scaled to tracking.work_width_px (640). Measured on dense seed 2,
# 40 s: within 2 vehicles per lane (82 of 87 in all); on the full frames the same scene counted 98 (lane 1:
# 32 of 22), each vehicle's parts showing enough corners to pass for vehicles (320 s of seed 11: +14, +8, -6,
# +1 % per lane, against +6, -6, -2, 0 % scaled).
@pytest.mark.slow
def test_an_hd_camera_counts_as_the_working_width_does(tmp_path):
    d = render("dense", 2, 40.0, tmp_path, width=1280, height=720)
    check_counts(d, lane_tol=0.2, total_tol=0.1, speed_tol=SPEED_TOL)


@pytest.mark.slow
def test_a_standing_queue_is_counted_as_it_discharges(tmp_path):
    """A signal's queue stands over the count lines and back beyond the view three times in 320 s, then moves
    off. A queued car that crawls loses most of its corners and links up with a small group not yet reported
    (corners found on it, or on the car behind, as it crawled): the joint group must stay the reported
    vehicle (assign_ids), or it is lost with its count. Measured (seed 11): 37 and 33 for 37 and 33; before
    that rule 31 and 27 (-16, -18 %). Seed 12 reads +6 and +18 % either way: extras of another kind. Bound:
    10 % per lane and in all, and the usual speed check."""
    d = render("stopped-queue", 11, 320.0, tmp_path)
    check_counts(d, lane_tol=0.10, total_tol=0.10, speed_tol=SPEED_TOL)


def _cdnet_site(counts: dict) -> SiteConfig:
    count_y = float(np.mean([p[1] for p in counts["count_line_px"]]))
    H = np.asarray(counts["calibration"]["homography_img_to_road"], dtype=np.float64)
    mid_x = float(np.mean([p[0] for p in counts["count_line_px"]]))
    q = H @ [mid_x, count_y, 1.0]
    return parse_site({
        "source": {"width": 320, "height": 240, "fps": 25.0},
        "calibration": {"image_px": counts["calibration"]["image_px"], "road_m": counts["calibration"]["road_m"]},
        "lanes": [
            {"id": lane["id"], "direction": lane["direction"], "polygon_px": lane["polygon_px"], "count_y_m": float(q[1] / q[2])}
            for lane in counts["lanes"]
        ],
    })


def test_cdnet_highway_hand_count(shared_data):
    d = shared_data / "cdnet-highway"
    counts = json.loads((d / "counts.json").read_text())
    site = _cdnet_site(counts)
    files = sorted((d / "input").glob("in*.jpg"))
    assert len(files) == counts["frames"]
    frames = ((k, k / counts["fps"], cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)) for k, f in enumerate(files))
    got, pipe = pipeline_counts(site, frames)
    want = {lane["id"]: 0 for lane in counts["lanes"]}
    for c in counts["crossings"]:
        want[c["lane"]] += 1
    # The product's path (site-from-counts, replay's count-line rules: tests/test_evaluate_handcount.py) is
    # within 1 per lane (17 of 17, 10 of 10). This bare site and raw crossings of every reported group give
    # lane 1 19 of 17 (a lane-changing SUV crosses three times at frames 1211-1220), lane 2 12 of 10 (tall
    # vehicles seen nearly edge-on by a telephoto camera 8 m up leave fragments). 3 per lane keeps that level and
    # fails a tracker that loses vehicles or counts static shadows (the tree shadows give dozens).
    for lane, n in want.items():
        assert abs(got[lane] - n) <= 3, (got, want)
    assert pipe.stats["repeated_frames"] == 0
