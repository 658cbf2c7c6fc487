"""`roadwatch clip-variants`: the variants of a hand-counted clip keep its counts and geometry consistent."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from tools.cli import cli
from tools.clip_variants import make_variant


@pytest.fixture
def tiny_clip(tmp_path):
    """A 10-frame 64x48 clip whose frame i is grey level 20 i, with one crossing at frame 4 and one at 7."""
    src = tmp_path / "clip"
    (src / "input").mkdir(parents=True)
    for i in range(10):
        cv2.imwrite(str(src / "input" / f"in{i + 1:06d}.jpg"), np.full((48, 64, 3), 20 * i, np.uint8))
    counts = {"fps": 25.0, "frames": 10, "size": [64, 48], "direction": "approaching",
              "lanes": [{"id": 1, "direction": "approaching", "polygon_px": [[10, 5], [30, 5], [40, 47], [0, 47]]}],
              "count_line_px": [[0, 30], [63, 30]],
              "loop_occupancy": {"lanes": [{"lane": 1, "polygon_px": [[8, 34], [36, 34], [34, 26], [10, 26]]}]},
              "crossings": [{"frame": 4, "lane": 1}, {"frame": 7, "lane": 1}],
              "calibration": {"image_px": [[10, 40], [50, 40], [20, 10], [40, 10]],
                              "road_m": [[0, 0], [3.5, 0], [0, 20], [3.5, 20]], "homography_img_to_road": [[1]]}}
    (src / "counts.json").write_text(json.dumps(counts))
    return src / "counts.json"


def _grey(d, k):
    return float(cv2.imread(str(d / "input" / f"in{k:06d}.jpg")).mean())


def test_geometry_and_frames_follow_each_variant(tiny_clip, tmp_path):
    up = json.loads(make_variant(tiny_clip, tmp_path / "up2", "up2").read_text())
    assert up["size"] == [128, 96] and up["count_line_px"] == [[0, 60], [126, 60]]
    assert up["calibration"]["image_px"][0] == [20, 80] and "homography_img_to_road" not in up["calibration"]
    assert up["loop_occupancy"]["lanes"][0]["polygon_px"][0] == [16, 68]
    assert cv2.imread(str(tmp_path / "up2" / "input" / "in000001.jpg")).shape == (96, 128, 3)

    rev = json.loads(make_variant(tiny_clip, tmp_path / "rev", "reversed").read_text())
    assert [c["frame"] for c in rev["crossings"]] == [2, 5] and rev["lanes"][0]["direction"] == "receding"
    assert abs(_grey(tmp_path / "rev", 1) - 180) < 3  # the last frame first

    low = json.loads(make_variant(tiny_clip, tmp_path / "fps15", "fps15").read_text())
    assert low["fps"] == 15.0 and low["frames"] == 6  # 10 frames at 25/s hold 6 at 15/s
    kept = [_grey(tmp_path / "fps15", k) for k in range(1, 7)]
    assert all(b > a for a, b in zip(kept, kept[1:]))  # in order, none repeated
    for c in low["crossings"]:  # each crossing lands on the kept frame nearest the original one
        assert abs(kept[c["frame"]] - 20 * {2: 4, 4: 7}.get(c["frame"], -99)) < 25, (c, kept)

    pad = json.loads(make_variant(tiny_clip, tmp_path / "pad", "original", pad_right=16).read_text())
    assert pad["size"] == [80, 48] and pad["count_line_px"] == [[0, 30], [63, 30]]  # columns added on the right
    img = cv2.imread(str(tmp_path / "pad" / "input" / "in000006.jpg"))
    assert img.shape == (48, 80, 3) and img[:, 64:].max() < 10 and abs(img[:, :64].mean() - 100) < 3

    with pytest.raises(ValueError, match="unknown variant 'snow'"):
        make_variant(tiny_clip, tmp_path / "x", "snow")


def test_unknown_kinds_are_named(tiny_clip, tmp_path):
    r = CliRunner().invoke(cli, ["clip-variants", str(tiny_clip), "--work", str(tmp_path / "w"), "--kinds", "dark,snow"])
    assert r.exit_code != 0 and "unknown variant(s): snow" in r.output


def _real_clip_variant(shared_data, tmp_path, kind: str) -> tuple[dict, str]:
    """`roadwatch clip-variants` on the real clip for one variant: its row (each lane's hand count is the
    clip's, 17 and 10) and the command's output."""
    counts = shared_data / "cdnet-highway" / "counts.json"
    if not counts.exists():
        pytest.skip("cdnet-highway/counts.json missing")
    r = CliRunner().invoke(cli, ["clip-variants", str(counts), "--work", str(tmp_path), "--kinds", kind,
                                 "--json", str(tmp_path / "rows.json")])
    assert r.exit_code == 0, r.output
    row = json.loads((tmp_path / "rows.json").read_text())["rows"][0]
    assert row["kind"] == kind and {k: v["hand"] for k, v in row["lanes"].items()} == {"1": 17, "2": 10}
    return row, r.output


@pytest.mark.slow
def test_the_real_clip_compressed_hard_is_reported_per_lane(shared_data, tmp_path):
    """End to end on the real clip at JPEG quality 25 (counted +1 and 0 when added): the table gives each lane's
    hand count, and the summary line how many variants met the target."""
    row, output = _real_clip_variant(shared_data, tmp_path, "jpeg")
    assert all(abs(v["result"] - v["hand"]) <= 2 for v in row["lanes"].values()), output
    assert "variants within 1 vehicle of the hand count in every lane" in output


@pytest.mark.slow
def test_the_real_clip_from_an_hd_camera_counts_within_one_vehicle_per_lane(shared_data, tmp_path):
    """The real clip at four times its size (1280x960, worked at the working width): the issue's target for real
    clips, each lane within 1 vehicle of the hand count. (Two cars joined for a while through a corner on the
    road between them came apart with the follower keeping the leader's id and near end: lane 1 read 15 of 17.)"""
    row, output = _real_clip_variant(shared_data, tmp_path, "up4")
    assert all(abs(v["result"] - v["hand"]) <= 1 for v in row["lanes"].values()), output
