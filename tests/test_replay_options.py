"""Replay options: start time, capture times from the container, the config's own source."""

from __future__ import annotations

import click
import pytest

from test_measures_core import make_site
from test_replay_badinput import write_avi
from tools.replay import DEFAULT_START_WALL, VideoFrames, parse_start, replay_video, source_video


def test_parse_start():
    assert parse_start(None) == DEFAULT_START_WALL
    assert parse_start("2026-01-01T00:00:00Z") == DEFAULT_START_WALL
    assert parse_start("2026-01-01T01:00:00+01:00") == DEFAULT_START_WALL
    assert parse_start("2026-01-01T00:05:00") == DEFAULT_START_WALL + 300  # naive = UTC
    with pytest.raises(click.BadParameter, match="ISO 8601"):
        parse_start("yesterday")


def test_capture_times_and_wall(tmp_path):
    vid = tmp_path / "v.avi"
    write_avi(vid, n=10)
    src = VideoFrames(str(vid), None, DEFAULT_START_WALL + 600, make_site())
    frames = []
    while (got := src.read()) is not None:
        frames.append(got[0])
    assert [f.seq for f in frames] == list(range(10))
    assert [round(f.t, 6) for f in frames] == [round(i / 25, 6) for i in range(10)]  # from POS_MSEC, 25 fps
    assert frames[3].wall == pytest.approx(DEFAULT_START_WALL + 600 + 0.12)
    assert frames[0].image.ndim == 2  # grey
    src = VideoFrames(str(vid), 10.0, DEFAULT_START_WALL, make_site())  # --fps overrides the container
    ts = [src.read()[0].t for _ in range(10)]
    assert ts == pytest.approx([i / 10 for i in range(10)])


def test_fps_override_and_start_shift_periods(tmp_path):
    vid = tmp_path / "v.avi"
    write_avi(vid, n=20)
    site = make_site(period_s=60)
    res = replay_video(str(vid), site, fps=10.0, start_wall=DEFAULT_START_WALL + 59.0)
    # 20 frames: at 10 fps they span 2 s and cross the minute boundary at frame 10
    starts = sorted({p.period_start for p in res.periods})
    assert starts == [DEFAULT_START_WALL, DEFAULT_START_WALL + 60]
    assert res.frames == 20


def test_source_video_from_config(tmp_path):
    site = make_site()
    site.source.url = "images:clip/in%06d.jpg"
    site.path = str(tmp_path / "site.toml")
    assert source_video(site) == str(tmp_path / "clip" / "in%06d.jpg")
    site.source.url = "synthetic:free-flow"
    with pytest.raises(click.UsageError, match="not a file"):
        source_video(site)
