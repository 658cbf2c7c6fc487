"""Field tool: `roadwatch zones` — editing with validation, and the overlay PNG's content."""

from __future__ import annotations

import tomllib

import cv2
import numpy as np
import pytest
import tomli_w
from click.testing import CliRunner

from appliance.config import load_site, parse_site
from appliance.geometry import polygon_contains
from fieldtool_sites import site_dict
from tools.cli import cli
from tools.fieldtool.overlay import COLOURS, LANE_ALPHA, draw_site, lane_polygons_px, loop_polygons_px

GREY = 60
NO_SERVICE = ["--url", "http://127.0.0.1:9"]


def _site_file(tmp_path, data=None):
    p = tmp_path / "site.toml"
    p.write_text(tomli_w.dumps(data or site_dict()))
    return p


def _snapshot(tmp_path):
    p = tmp_path / "snap.png"
    cv2.imwrite(str(p), np.full((480, 640), GREY, np.uint8))
    return p


def test_overlay_has_each_kind_colour_where_it_belongs() -> None:
    cfg = parse_site(site_dict())
    img = draw_site(np.full((480, 640), GREY, np.uint8), cfg, labels=False)
    lanes, loops = lane_polygons_px(cfg), loop_polygons_px(cfg)
    h, w = img.shape[:2]
    vv, uu = np.mgrid[0:h, 0:w]
    pix = np.column_stack([uu.ravel() + 0.0, vv.ravel() + 0.0])
    in_lane = np.zeros(h * w, bool)
    for poly in lanes.values():
        in_lane |= polygon_contains(poly, pix)
    in_loop = np.zeros(h * w, bool)
    for poly in loops.values():
        in_loop |= polygon_contains(poly, pix)
    flat = img.reshape(-1, 3).astype(int)
    # the lane fill: grey blended with the lane colour at LANE_ALPHA (tolerance 3 for rounding)
    expect = np.round(LANE_ALPHA * np.array(COLOURS["lane"]) + (1 - LANE_ALPHA) * GREY)
    # sample away from outlines, zone outlines and count lines: interior pixels of lane 2 at
    # road Y 24..28 (lane 2 has no detection/exit zone; loops are at 20..22)
    cfg_lane2 = np.asarray(cfg.lane(2).polygon_m)
    road = cfg.homography.img_to_road(pix)
    sample = polygon_contains(cfg_lane2, road) & (road[:, 1] > 24) & (road[:, 1] < 28) & (road[:, 0] > 0.5) & (road[:, 0] < 3.0)
    assert sample.sum() > 100
    assert np.all(np.abs(flat[sample] - expect) <= 3)
    # outside every lane, away from outlines and labels: untouched background
    far = ~in_lane & (np.abs(pix[:, 0] - 320) > 250)
    far &= ~((pix[:, 0] < 60) & (pix[:, 1] < 60)) & ~((pix[:, 0] > 580) & (pix[:, 1] < 70))  # fiducial marks
    assert np.all(flat[far] == GREY)
    # loops: red dominates inside the loop interiors
    assert in_loop.sum() > 50
    inner = flat[in_loop]
    assert np.median(inner[:, 2] - inner[:, 1]) > 60
    # fiducials: cyan at the cross centre
    for u, v in cfg.fiducials:
        b, g, r = img[int(v), int(u)]
        assert b > 200 and g > 200 and r < 100


def test_render_command_writes_png(tmp_path) -> None:
    site, snap = _site_file(tmp_path), _snapshot(tmp_path)
    out = tmp_path / "zones.png"
    res = CliRunner().invoke(cli, ["zones", "render", "-c", str(site), "--snapshot", str(snap), "-o", str(out)])
    assert res.exit_code == 0, res.output
    img = cv2.imread(str(out))
    cfg = load_site(site)
    u, v = np.round(cfg.homography.road_to_img([[1.75, 26.0]])[0]).astype(int)
    assert int(img[v, u, 1]) > int(img[v, u, 2]) + 30  # green inside lane 2 at 26 m (30 m is the count line)


def test_snapshot_of_wrong_size_is_refused(tmp_path) -> None:
    site = _site_file(tmp_path)
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 100), np.uint8))
    res = CliRunner().invoke(cli, ["zones", "render", "-c", str(site), "--snapshot", str(small)])
    assert res.exit_code != 0 and "100x100" in res.output


def test_add_loop_assign_channel_and_refuse_duplicates(tmp_path) -> None:
    site = _site_file(tmp_path)
    r = CliRunner()
    res = r.invoke(cli, ["zones", "loop", "L3", "-c", str(site), "--lane", "1", "--channel", "3",
                         "--y-m", "30", "--length-m", "1.8", "--trap-with", "L1"] + NO_SERVICE)
    assert res.exit_code == 0, res.output
    assert "not running" in res.output
    cfg = load_site(site)
    assert cfg.loop_by_channel()[3].id == "L3"
    good = site.read_bytes()
    # channel already used by L1: refused, file untouched, message names the key
    res = r.invoke(cli, ["zones", "loop", "L4", "-c", str(site), "--lane", "2", "--channel", "1", "--y-m", "30"] + NO_SERVICE)
    assert res.exit_code != 0 and "loops[3].channel" in res.output and "two loops" in res.output
    assert site.read_bytes() == good
    # a loop outside its lane (X of lane 2 given as pixels inside lane 1)
    cfgp = load_site(site)
    px = cfgp.homography.road_to_img([[-3, 30], [-1, 30], [-1, 32], [-3, 32]])
    poly = " ".join(f"{u:.1f},{v:.1f}" for u, v in px)
    res = r.invoke(cli, ["zones", "loop", "L5", "-c", str(site), "--lane", "2", "--channel", "5", "--polygon-px", poly] + NO_SERVICE)
    assert res.exit_code != 0 and "not inside lane 2" in res.output
    assert site.read_bytes() == good
    # reassign L3 to channel 7
    res = r.invoke(cli, ["zones", "loop", "L3", "-c", str(site), "--channel", "7"] + NO_SERVICE)
    assert res.exit_code == 0, res.output
    assert sorted(load_site(site).loop_by_channel()) == [1, 2, 7]


def test_lane_outside_image_and_zone_edits(tmp_path) -> None:
    site = _site_file(tmp_path)
    r = CliRunner()
    good = site.read_bytes()
    res = r.invoke(cli, ["zones", "lane", "3", "-c", str(site), "--polygon-px", "600,300 700,300 700,400 600,400"] + NO_SERVICE)
    assert res.exit_code != 0 and "lanes[2]" in res.output and "outside the 640x480 image" in res.output
    assert site.read_bytes() == good
    res = r.invoke(cli, ["zones", "lane", "2", "-c", str(site), "--detection-y", "40", "48", "--exit-y", "12", "16",
                         "--out", str(tmp_path / "new.toml")])
    assert res.exit_code == 0, res.output
    assert site.read_bytes() == good  # --out leaves CONFIG alone
    new = tomllib.loads((tmp_path / "new.toml").read_text())
    assert new["lanes"][1]["detection_y_m"] == [40.0, 48.0]
    assert "past the exit zone" not in res.output
    res = r.invoke(cli, ["zones", "lane", "2", "-c", str(tmp_path / "new.toml"), "--detection-y", "12", "16",
                         "--exit-y", "40", "48"] + NO_SERVICE)
    assert res.exit_code == 0 and "past the exit zone" in res.output  # reversed for an approaching lane
    res = r.invoke(cli, ["zones", "fiducials", "-c", str(tmp_path / "new.toml"), "320,300"] + NO_SERVICE)
    assert res.exit_code == 0 and "fiducial F1" in res.output and "is on lane" in res.output


def test_zone_from_image_rows(tmp_path) -> None:
    site = _site_file(tmp_path)
    cfg = load_site(site)
    v_far, v_near = cfg.homography.road_to_img([[1.75, 44.0], [1.75, 36.0]])[:, 1]
    res = CliRunner().invoke(cli, ["zones", "lane", "2", "-c", str(site), "--detection-rows", str(v_far), str(v_near)]
                             + NO_SERVICE)
    assert res.exit_code == 0, res.output
    assert load_site(site).lane(2).detection_y_m == pytest.approx([36.0, 44.0], abs=0.02)


def test_check_lists_channels(tmp_path) -> None:
    res = CliRunner().invoke(cli, ["zones", "check", "-c", str(_site_file(tmp_path))])
    assert res.exit_code == 0, res.output
    assert "channel   1 <- loop L1 lane 1" in res.output and "zones ok" in res.output
