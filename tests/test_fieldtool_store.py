"""Field tool: `roadwatch export` and `roadwatch report` against a real SQLite store."""

from __future__ import annotations

import csv
import hashlib
import io
import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from fieldtool_sites import START, fill_store
from tools.cli import cli


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    d = tmp_path_factory.mktemp("store")
    path = d / "roadwatch.sqlite"
    written = fill_store(path, seconds=1200.0)
    return path, written


def _digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_export_periods_csv_round_trip(store) -> None:
    path, written = store
    before = _digest(path)
    res = CliRunner().invoke(cli, ["export", "--db", str(path), "--from", "2026-01-01T00:00:00Z",
                                   "--to", "2026-01-01T00:20:00Z", "--csv"])
    assert res.exit_code == 0, res.output
    rows = list(csv.DictReader(io.StringIO(res.stdout)))
    assert len(rows) == len(written) == 8
    for r in rows:
        a = written[(int(r["lane"]), float(r["period_start"]))]
        assert int(r["count"]) == a.count
        assert float(r["flow_vph"]) == pytest.approx(a.flow_vph)
        assert float(r["speed_kmh"]) == pytest.approx(a.speed_kmh)
        assert json.loads(r["class_counts"]) == a.class_counts
    assert rows[0]["period_start_utc"] == "2026-01-01T00:00:00Z"
    assert _digest(path) == before  # read-only


def test_export_filters_lane_time_and_kinds(store, tmp_path) -> None:
    path, written = store
    r = CliRunner()
    res = r.invoke(cli, ["export", "--db", str(path), "--from", str(START + 300), "--to", str(START + 900),
                         "--lane", "2", "--json"])
    assert res.exit_code == 0, res.output
    rows = json.loads(res.stdout)
    assert [(x["lane"], x["period_start"]) for x in rows] == [(2, START + 300), (2, START + 600)]
    out = tmp_path / "ev.json"
    res = r.invoke(cli, ["export", "--db", str(path), "--from", str(START), "--to", str(START + 300),
                         "--what", "loop-events", "--lane", "1", "--json", "-o", str(out)])
    assert res.exit_code == 0, res.output
    events = json.loads(out.read_text())
    assert events and all(e["lane"] == 1 and START <= e["wall_on"] < START + 300 for e in events)
    # loop-event count in the first period matches the vehicles crossing the loop in it (±1 at the edge)
    veh = json.loads(r.invoke(cli, ["export", "--db", str(path), "--from", str(START), "--to", str(START + 300),
                                    "--what", "vehicles", "--lane", "1", "--json", "--trajectories"]).stdout)
    assert all(v["trajectory"] for v in veh)
    assert abs(len(events) - written[(1, START)].count) <= 2
    res = r.invoke(cli, ["export", "--db", str(path), "--from", "2026-01-01T00:06:00", "--to", "2026-01-01T00:07:00",
                         "--what", "health", "--csv"])
    health = list(csv.DictReader(io.StringIO(res.stdout)))
    assert [(h["fault"], h["active"], h["wall_utc"]) for h in health] == [
        ("CAMERA_LOST", "1", "2026-01-01T00:06:40Z"), ("CAMERA_LOST", "0", "2026-01-01T00:06:52Z")]
    res = r.invoke(cli, ["export", "--db", str(path), "--from", "yesterday"])
    assert res.exit_code != 0 and "neither ISO 8601" in res.output
    res = r.invoke(cli, ["export", "--db", str(tmp_path / "none.sqlite"), "--from", "0"])
    assert res.exit_code != 0 and "no such store" in res.output


def test_report_pngs_show_the_data(store, tmp_path) -> None:
    path, _ = store
    out = tmp_path / "rep"
    res = CliRunner().invoke(cli, ["report", "--db", str(path), "--from", "2026-01-01T00:00:00Z",
                                   "--to", "2026-01-01T00:20:00Z", "--out", str(out), "--ts-seconds", "60"])
    assert res.exit_code == 0, res.output
    img = cv2.imread(str(out / "flow_speed_occupancy.png"))
    # matplotlib's tab:blue (lane 1) and tab:orange (lane 2) lines are drawn
    for bgr in ((180, 119, 31), (14, 127, 255)):
        assert (np.abs(img.astype(int) - bgr).sum(axis=2) < 30).sum() > 200
    bars = cv2.imread(str(out / "counts_by_class.png"))
    # stacked bars: the small, medium and large classes each have their colour (tab:blue,
    # tab:orange, tab:green in sorted class order large, medium, small)
    for bgr in ((180, 119, 31), (14, 127, 255), (44, 160, 44)):
        assert (np.abs(bars.astype(int) - bgr).sum(axis=2) < 30).sum() > 100
    ts = cv2.imread(str(out / "time_space.png"), cv2.IMREAD_GRAYSCALE)
    # trajectories: many dark, steep strokes. In 60 s at ~750 veh/h per lane there are ~12
    # vehicles per lane; count dark runs along a row through the middle of the top panel.
    h = ts.shape[0]
    row = ts[int(h * 0.28)]
    dark = row < 100
    strokes = int(np.count_nonzero(dark[1:] & ~dark[:-1]))
    assert 8 <= strokes <= 30, strokes


def test_report_without_data_says_so(store, tmp_path) -> None:
    path, _ = store
    res = CliRunner().invoke(cli, ["report", "--db", str(path), "--from", "2030-01-01", "--to", "2030-01-02",
                                   "--out", str(tmp_path / "r")])
    assert res.exit_code != 0 and "nothing to plot" in res.output
