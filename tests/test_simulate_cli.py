"""`roadwatch simulate` end to end: video, site.toml and truth files; stream defects; the demo site."""

from __future__ import annotations

import csv
import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.config import load_demo, load_site
from appliance.types import LaneAggregate
from tools.simulate import PRESETS, SceneStream, render_scenario
from tools.simulate.truth import read_aggregates, read_loop_events, read_vehicles


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "demo"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "simulate", "--preset", "demo", "--seconds", "4",
                        "--seed", "3", "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "frames/s" in r.stdout
    meta = json.loads((out / "truth" / "meta.json").read_text())
    assert meta["encoder"] in r.stdout  # the encoder is said, and kept with the truth
    if shutil.which("ffmpeg"):
        assert meta["encoder"].startswith("libx264")
    return out


def test_video_reads_back_with_frame_count_and_fps(demo_run: Path) -> None:
    meta = json.loads((demo_run / "truth" / "meta.json").read_text())
    assert meta["frame_count"] == 100
    cap = cv2.VideoCapture(str(demo_run / "video.mp4"))
    assert cap.isOpened()
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(25.0)
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        assert frame.shape[:2] == (480, 640)
        n += 1
    assert n == meta["frame_count"]
    probe = subprocess.run(["ffprobe", "-v", "error", "-count_frames", "-select_streams", "v:0", "-show_entries",
                            "stream=nb_read_frames,r_frame_rate", "-of", "json", str(demo_run / "video.mp4")],
                           capture_output=True, text=True)
    if probe.returncode == 0:
        s = json.loads(probe.stdout)["streams"][0]
        assert int(s["nb_read_frames"]) == n and s["r_frame_rate"] == "25/1"


def test_site_toml_loads_and_truth_files_have_their_columns(demo_run: Path) -> None:
    cfg = load_site(demo_run / "site.toml")
    assert cfg.source.url == "video.mp4"
    assert len(cfg.calibration.image_px) >= 6 and len(cfg.fiducials) >= 3
    err = cfg.homography.reprojection_error_m(cfg.calibration.image_px, cfg.calibration.road_m)
    assert err.max() < 0.05  # exact projections written to 1e-3 px
    assert sorted(lp.channel for lp in cfg.loops) == list(range(1, len(cfg.lanes) + 1))
    aggs = read_aggregates(demo_run / "truth" / "aggregates.csv")
    assert [f.name for f in dataclasses.fields(LaneAggregate)] == list(aggs[0])
    assert {a["lane"] for a in aggs} == {ln.id for ln in cfg.lanes}
    assert all(a["partial"] for a in aggs)  # 4 s of a 300 s period
    LaneAggregate(**aggs[0])
    veh = _rows(demo_run / "truth" / "vehicles.csv")
    assert veh and {"frame", "bbox_x0", "visible_frac", "y_front_m"} <= set(veh[0])
    frames = {int(r["frame"]) for r in veh}
    assert max(frames) == 99
    loops = read_loop_events(demo_run / "truth" / "loop_events.csv")
    assert loops
    for e in loops:
        assert e.wall_on - e.t_on == pytest.approx(1767225600.0) and e.t_off > e.t_on
    arr = read_vehicles(demo_run / "truth" / "vehicles.csv")
    assert len(arr) == len(veh) and set(arr["class"]) <= {"motorcycle", "car", "van", "truck", "artic", "bus"}
    assert np.all(arr["bbox_x1"] >= arr["bbox_x0"]) and np.all((arr["visible_frac"] >= 0) & (arr["visible_frac"] <= 1))


def test_defects_are_recorded_in_frames_csv(tmp_path: Path) -> None:
    res = render_scenario("defects", 2, 3.0, tmp_path, fps=30.0, drop_prob=0.1)
    rows = _rows(res.truth_dir / "frames.csv")
    assert len(rows) == res.meta["frame_count"]
    rep = [r["repeated"] == "true" for r in rows]
    assert rep[0] is False and all(rep[i] != rep[i + 1] for i in range(len(rep) - 1))  # 15 fps padded to 30
    t = np.array([float(r["t"]) for r in rows])
    assert np.all(np.diff(t) >= 0)
    flagged = sum(r["dropped_before"] == "true" for r in rows)
    drops = res.meta["defects"]["dropped_frames"]
    assert 0 < flagged <= drops  # a run of drops flags the next frame once
    assert res.meta["frame_count"] == 2 * (45 - drops)
    nominal = np.array([int(r["frame"]) // 2 for r in rows[::2]]) / 15.0
    assert 0 < np.abs(t[::2] - nominal).max()  # jitter and drops move the true times off the nominal grid
    cap = cv2.VideoCapture(str(res.video))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == res.meta["frame_count"]
    # the video's timestamps step over the dropped frames as a camera's recording does: each frame's is its
    # capture time but for the jitter (0.3 of the 1/15 s interval at most) and a repeat's 1/30 s
    pts = []
    while cap.read()[0]:
        pts.append(cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
    late = np.array(pts) - t - np.array(rep) / 30.0
    assert len(pts) == len(rows) and np.abs(late).max() <= 0.3 / 15 + 1e-3, late


def test_demo_site_is_the_demo_scene() -> None:
    cfg = load_demo()
    stream = SceneStream("demo", 1)
    d = stream.site_dict()
    assert cfg.source.url == d["source"]["url"] == "synthetic:demo?seed=1"
    assert cfg.raw["calibration"] == d["calibration"]
    assert cfg.raw["lanes"] == d["lanes"] and cfg.raw["loops"] == d["loops"]
    assert cfg.raw["fiducials"] == d["fiducials"]
    assert cfg.outputs.modbus_tcp.enabled and cfg.outputs.modbus_tcp.port == 5020
    assert 2 <= len(cfg.lanes) <= 4
    img, t0 = stream.next_frame()
    img2, t1 = stream.next_frame()
    assert img.shape == (480, 640) and img.dtype == np.uint8
    assert t1 - t0 == pytest.approx(0.04)


def test_help_lists_presets_and_bad_input_is_named(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from tools.simulate.cli import simulate

    r = CliRunner().invoke(simulate, ["--help"])
    assert r.exit_code == 0 and all(name in r.output for name in PRESETS)
    # outputs under tmp_path: should the input check ever fail, nothing lands in the working directory
    r = CliRunner().invoke(simulate, ["--preset", "sunny", "--out", str(tmp_path / "x")])
    assert r.exit_code == 2 and "sunny" in r.output
    with pytest.raises(ValueError, match="unknown scene parameter 'lanez'"):
        render_scenario("demo", 1, 1.0, tmp_path / "unused", lanez=3)


def test_same_seed_gives_identical_truth_files(tmp_path: Path) -> None:
    outs = [render_scenario("two-directions", 5, 1.6, tmp_path / name, width=320, height=240) for name in "ab"]
    outs.append(render_scenario("two-directions", 6, 1.6, tmp_path / "c", width=320, height=240))
    files = ("vehicles.csv", "frames.csv", "aggregates.csv")
    for f in files:
        assert (outs[0].truth_dir / f).read_bytes() == (outs[1].truth_dir / f).read_bytes()
    assert (outs[0].truth_dir / "vehicles.csv").read_bytes() != (outs[2].truth_dir / "vehicles.csv").read_bytes()
    assert outs[0].site.read_text() == outs[1].site.read_text()
