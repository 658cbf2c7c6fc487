"""Hand-count files from simulated scenes (`roadwatch counts-from-sim`) and count lines that slant across lanes."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from appliance.config import load_site
from appliance.geometry import Homography
from tools.counts_from_sim import counts_from_sim
from tools.evaluate import compare_with_counts, load_results
from tools.handcount import count_point, load_counts, site_dict_from_counts


def test_count_point_is_the_middle_of_the_line_inside_the_lane():
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    # a slanted line entering through the left edge at y 2.5 and leaving through the right edge at y 7.5
    assert count_point(square, [[-10.0, -2.5], [20.0, 12.5]]) == pytest.approx((5.0, 5.0))
    # a line ending inside the lane: from its entry to its end
    assert count_point(square, [[-10.0, 4.0], [6.0, 4.0]]) == pytest.approx((3.0, 4.0))
    # a line that misses the lane, or only touches a corner
    assert count_point(square, [[-10.0, 20.0], [20.0, 20.0]]) is None
    assert count_point(square, [[-5.0, 5.0], [5.0, -5.0]]) is None


def test_a_slanted_count_line_crosses_each_lane_where_it_lies():
    # image = road x 10 px per metre, road Y growing up the image from row 400
    road = [[0.0, 0.0], [7.0, 0.0], [7.0, 30.0], [0.0, 30.0]]
    img = [[10.0 * x, 400.0 - 10.0 * y] for x, y in road]
    H = Homography.from_points(img, road)
    lanes = [{"id": i + 1, "direction": "approaching",
              "polygon_px": H.road_to_img([[x0, 0.0], [x0 + 3.5, 0.0], [x0 + 3.5, 30.0], [x0, 30.0]]).tolist()}
             for i, x0 in enumerate((0.0, 3.5))]
    counts = {"size": [640, 480], "lanes": lanes, "count_line_px": [[0.0, 300.0], [70.0, 230.0]],
              "crossings": [], "calibration": {"image_px": img, "road_m": road}}
    site = site_dict_from_counts(counts, "counts.json", "site.toml")
    # lane 1 (x 0..3.5 m = 0..35 px) meets the line at its middle column 17.5 px: row 282.5, road Y 11.75 m
    assert [ln["count_y_m"] for ln in site["lanes"]] == pytest.approx([11.75, 15.25], abs=1e-3)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A short two-way scene at the real clip's size, written as a hand-counted clip with click noise."""
    d = tmp_path_factory.mktemp("cfs")
    subprocess.run([sys.executable, "-m", "tools.cli", "simulate", "--preset", "two-directions", "--seed", "5",
                    "--seconds", "40", "--width", "320", "--height", "240", "--out", str(d / "sim"), "-q"],
                   check=True, capture_output=True)
    r = CliRunner().invoke(counts_from_sim, [str(d / "sim"), "--out", str(d / "clip"), "--click-noise", "0.5"])
    assert r.exit_code == 0, r.output
    return d


def test_the_file_is_a_hand_count_of_the_scene(clip):
    counts = load_counts(clip / "clip" / "counts.json")
    meta = json.loads((clip / "sim" / "truth" / "meta.json").read_text())
    assert counts["direction"] == "both"
    assert [ln["direction"] for ln in counts["lanes"]] == ["approaching"] * 2 + ["receding"] * 2
    assert len(list((clip / "clip" / "input").glob("in*.jpg"))) == meta["frame_count"] == counts["frames"]
    exact = np.asarray(load_site(clip / "sim" / "site.toml").calibration.image_px)
    moved = np.abs(np.asarray(counts["calibration"]["image_px"]) - exact)
    assert 0.0 < moved.max() < 3.0, "the clicks are the exact points plus 0.5 px of noise"
    lanes = {c["lane"] for c in counts["crossings"]}
    assert lanes == {1, 2, 3, 4}, "every lane has traffic crossing the line in 40 s at 800 veh/h"
    frames = [c["frame"] for c in counts["crossings"]]
    assert frames == sorted(frames) and 0 <= min(frames) and max(frames) < counts["frames"]


def test_the_count_line_can_be_moved(clip, tmp_path):
    """--count-row puts the line elsewhere: approaching vehicles then cross it later, receding ones earlier."""
    base = load_counts(clip / "clip" / "counts.json")
    row = base["count_line_px"][0][1] + 10.0
    r = CliRunner().invoke(counts_from_sim,
                           [str(clip / "sim"), "--out", str(tmp_path / "low"), "--count-row", str(row)])
    assert r.exit_code == 0, r.output
    low = load_counts(tmp_path / "low" / "counts.json")
    assert low["count_line_px"] == [[0.0, row], [319.0, row]]
    for lane, later in ((1, True), (2, True), (3, False), (4, False)):
        a = np.array([c["frame"] for c in base["crossings"] if c["lane"] == lane])
        b = np.array([c["frame"] for c in low["crossings"] if c["lane"] == lane])
        shift = [int(b[np.argmin(np.abs(b - f))] - f) for f in a]  # each vehicle's crossing of the other line
        assert len(a) >= 3 and (np.median(shift) > 0) == later, (lane, a, b)
    r = CliRunner().invoke(counts_from_sim, [str(clip / "sim"), "--out", str(tmp_path / "x"), "--count-row", "300"])
    assert r.exit_code != 0 and "count row 300 is outside the 240-row image" in r.output


def test_bad_scene_directory_is_named(tmp_path):
    (tmp_path / "nosim").mkdir()
    r = CliRunner().invoke(counts_from_sim, [str(tmp_path / "nosim"), "--out", str(tmp_path / "o")])
    assert r.exit_code != 0 and "nosim" in r.output and "not a simulated scene" in r.output


@pytest.mark.slow
def test_the_real_clip_path_counts_both_directions(clip):
    """site-from-counts, replay of the JPEG frames and evaluate --counts, as for a real clip. The tracker's own
    site file counts these lanes within 3-15 % over 320 s; through a hand count's site (no fiducials, loops or
    regions; calibration clicked to 0.5 px) at least 85 % of the vehicles must be matched within 4 frames."""
    d = clip / "clip"
    subprocess.run([sys.executable, "-m", "tools.cli", "site-from-counts", str(d / "counts.json"), "--out",
                    str(d / "site.toml")], check=True, capture_output=True)
    subprocess.run([sys.executable, "-m", "tools.cli", "replay", str(d / "input" / "in%06d.jpg"), "--config",
                    str(d / "site.toml"), "--fps", "25", "--out", str(d / "res.sqlite")],
                   check=True, capture_output=True)
    counts = load_counts(d / "counts.json")
    cmp = compare_with_counts(counts, load_results(d / "res.sqlite")["crossings"], tolerance_frames=4)
    hand = sum(v["hand"] for v in cmp.per_lane.values())
    matched = sum(v["matched"] for v in cmp.per_lane.values())
    assert matched >= 0.85 * hand, cmp.per_lane
    for lane, v in cmp.per_lane.items():
        assert v["matched"] >= 1, f"lane {lane} matched nothing: {cmp.per_lane}"
