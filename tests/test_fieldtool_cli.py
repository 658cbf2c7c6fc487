"""Field tool: every command has help with an example; snapshot from real sources to PNG."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tomli_w
from click.testing import CliRunner

from fieldtool_sites import site_dict
from tools.cli import COMMANDS, cli

FIELD_COMMANDS = sorted(n for n, (mod, _, _) in COMMANDS.items() if mod.startswith("tools.fieldtool."))
SUBCOMMANDS = [["config", "validate"], ["config", "show"], ["config", "diff"], ["config", "apply"],
               ["zones", "lane"], ["zones", "loop"], ["zones", "fiducials"], ["zones", "render"], ["zones", "check"],
               ["zones", "remove"]]


@pytest.mark.parametrize("args", [[n] for n in FIELD_COMMANDS] + SUBCOMMANDS, ids=" ".join)
def test_help_has_an_example(args) -> None:
    res = CliRunner().invoke(cli, args + ["--help"])
    assert res.exit_code == 0, res.output
    assert "Example" in res.output and "roadwatch " + args[0] in res.output


def _clip_site(tmp_path, shared_data) -> tuple:
    import json

    counts = json.loads((shared_data / "cdnet-highway" / "counts.json").read_text())
    site = {
        "site": {"name": "cdnet"},
        "source": {"url": f"images:{shared_data / 'cdnet-highway' / 'input' / 'in%06d.jpg'}",
                   "width": 320, "height": 240, "fps": 25.0},
        "calibration": {"image_px": counts["calibration"]["image_px"], "road_m": counts["calibration"]["road_m"]},
        "lanes": [{"id": ln["id"], "direction": ln["direction"], "polygon_px": ln["polygon_px"]} for ln in counts["lanes"]],
        "loops": [{"id": "L1", "lane": 1, "channel": 1, "y_m": 6.34, "length_m": 4.5},
                  {"id": "L2", "lane": 2, "channel": 2, "y_m": 6.34, "length_m": 4.5}],
    }
    p = tmp_path / "site.toml"
    p.write_text(tomli_w.dumps(site))
    return p, counts


def test_snapshot_from_real_image_sequence(tmp_path, shared_data) -> None:
    site, counts = _clip_site(tmp_path, shared_data)
    out = tmp_path / "snap.png"
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(site), "-o", str(out), "--skip", "5"])
    assert res.exit_code == 0, res.output
    got = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    def frame(i):
        return cv2.cvtColor(cv2.imread(str(shared_data / "cdnet-highway" / "input" / f"in{i + 1:06d}.jpg")), cv2.COLOR_BGR2GRAY)

    assert got.shape == (240, 320)
    assert np.abs(got.astype(int) - frame(5)).max() <= 1  # frame 5 (0-based), same grey conversion
    assert np.abs(got.astype(int) - frame(0)).mean() > 1  # and not the first frame
    # overlay on the real frame: the lane polygons of the hand count are green-tinted inside
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(site), "-o", str(out), "--overlay"])
    assert res.exit_code == 0, res.output
    img = cv2.imread(str(out)).astype(int)
    raw = cv2.cvtColor(frame(0), cv2.COLOR_GRAY2BGR).astype(int)
    greenness = (img[:, :, 1] - (img[:, :, 0] + img[:, :, 2]) / 2) - (raw[:, :, 1] - (raw[:, :, 0] + raw[:, :, 2]) / 2)
    lanes = np.zeros((240, 320), np.uint8)
    for ln in counts["lanes"]:
        cv2.fillPoly(lanes, [np.round(np.asarray(ln["polygon_px"])).astype(np.int32)], 255)
    inside = cv2.erode(lanes, np.ones((7, 7), np.uint8)) > 0
    outside = cv2.dilate(lanes, np.ones((7, 7), np.uint8)) == 0
    # lane fill: green added (35 % of (0, 200, 0) blended in) on most interior pixels; outlines,
    # zone outlines, loops and labels cover the rest
    assert np.median(greenness[inside]) > 40
    # outside the lanes the frame is unchanged apart from labels and fiducial marks
    assert np.mean(np.abs(greenness[outside]) < 2) > 0.97


def test_snapshot_errors_are_clear(tmp_path) -> None:
    d = site_dict()
    d["source"]["url"] = "nothere.mp4"
    p = tmp_path / "site.toml"
    p.write_text(tomli_w.dumps(d))
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(p), "-o", str(tmp_path / "x.png")])
    assert res.exit_code != 0 and "nothere.mp4" in res.output and "does not exist" in res.output
    assert not (tmp_path / "x.png").exists()
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(tmp_path / "missing.toml")])
    assert res.exit_code != 0 and "missing.toml" in res.output


def test_snapshot_works_before_calibration(tmp_path, shared_data) -> None:
    # the installer's first step: only [source] is filled in, the rest of the config is missing
    p = tmp_path / "new.toml"
    p.write_text(tomli_w.dumps({"source": {"url": f"images:{shared_data / 'cdnet-highway' / 'input' / 'in%06d.jpg'}",
                                           "width": 320, "height": 240}}))
    out = tmp_path / "first.png"
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(p), "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert cv2.imread(str(out)).shape == (240, 320, 3)
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(p), "-o", str(out), "--overlay"])
    assert res.exit_code != 0 and "calibration" in res.output


def test_status_table_shows_faults_calls_and_last_period() -> None:
    from tools.fieldtool.status import format_status

    st = {"site": "s", "version": "0.1.0", "uptime_s": 90061, "fps": 24.9, "dropped_frames": 3, "frames": 1000,
          "faults": ["CAMERA_LOST"], "fault_bits": 1, "tracked_vehicles": 2, "period_seq": 7,
          "channels": [{"channel": 1, "loop_id": "L1", "lane": 1, "call": True, "count": 65535, "occupancy_pct": 12.5,
                        "last_speed_kmh": 88.2, "last_length_m": 4.4, "class_counts": {"small": 3}, "forced": True},
                       {"channel": 2, "loop_id": "L2", "lane": 2, "call": False, "count": 0, "occupancy_pct": 0.0,
                        "last_speed_kmh": None, "last_length_m": None, "class_counts": {}, "forced": False}],
          "lanes": {"1": 4, "2": 0},
          "last_period": [{"lane": 1, "period_start": 1767225600.0, "period_s": 300.0, "count": 61, "flow_vph": 732.0,
                           "density_vpkm": 8.1, "speed_kmh": 90.4, "occupancy_pct": 9.2, "speed85_kmh": 97.0,
                           "partial": True}]}
    text = format_status(st)
    assert "up 1d 01:01:01" in text and "FAULT CAMERA_LOST" in text
    assert "  1 L1          1 FORCED   65535   12.5   88.2    4.4  small:3" in text
    assert "  2 L2          2 .            0    0.0      -      -" in text
    assert "last period 2026-01-01T00:00:00Z (300.0 s)" in text and "partial" in text
    assert "lane 1: 4  lane 2: 0" in text


def test_status_since_start_column() -> None:
    from tools.fieldtool.status import format_status

    before = {"channels": [{"channel": 1, "loop_id": "L1", "lane": 1, "count": 65530}], "lanes": {"1": 10}}
    now = {"channels": [{"channel": 1, "loop_id": "L1", "lane": 1, "count": 65537}], "lanes": {"1": 17}}
    text = format_status(now, before)
    assert "since" in text.splitlines()[4]
    assert "   +7  " in text and "lane 1: +7" in text


def test_snapshot_from_a_dead_stream_times_out(tmp_path, port) -> None:
    p = tmp_path / "site.toml"
    p.write_text(tomli_w.dumps({"source": {"url": f"rtsp://127.0.0.1:{port}/cam", "open_timeout_s": 0.5,
                                           "read_timeout_s": 0.5}}))
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(p), "-o", str(tmp_path / "x.png")])
    assert res.exit_code != 0 and "no frame within 1 s" in res.output and "cannot open" in res.output
    assert not (tmp_path / "x.png").exists()
