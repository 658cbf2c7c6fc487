"""Replay options: start time, capture times from the container, the config's own source."""

from __future__ import annotations

import click
import numpy as np
import pytest

from test_measures_core import make_site
from test_replay_badinput import write_avi
from tools.replay import DEFAULT_START_WALL, VideoFrames, parse_start, replay_video, source_video
from tools.simulate.scenario import VideoWriter


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


def _recording(path, gaps: list[tuple[int, int]], n: int = 12):
    """An H.264 recording at 25 fps (640x480) whose timestamps step over frames left out (see VideoWriter)."""
    w = VideoWriter(path, 640, 480, 25.0, gaps=gaps)
    for i in range(n):
        w.write(np.full((480, 640), 40 + 10 * i, np.uint8))
    w.close()


def _times(src) -> list[float]:
    out = []
    while (got := src.read()) is not None:
        out.append(round(got[0].t, 6))
    return out


def test_a_recording_that_dropped_frames_is_timed_by_its_timestamps(tmp_path):
    """20 frames dropped before frame 4 and 15 before frame 9 (a stream that stalled): the capture times step
    over them, 1.4 s in all (a frame counter would close the gaps up: speeds across them would read many times
    too high, and the clock fall behind); a given --fps times every frame by the counter."""
    _recording(tmp_path / "v.mp4", [(4, 20), (9, 15)])
    slots = [0, 1, 2, 3, 24, 25, 26, 27, 28, 44, 45, 46]
    assert _times(VideoFrames(str(tmp_path / "v.mp4"), None, DEFAULT_START_WALL, make_site())) == \
        pytest.approx([k / 25 for k in slots])
    assert _times(VideoFrames(str(tmp_path / "v.mp4"), 25.0, DEFAULT_START_WALL, make_site())) == \
        pytest.approx([k / 25 for k in range(12)])


@pytest.mark.parametrize("left_out, followed", [(44, True), (54, False), (250, False)])
def test_a_clock_that_jumps_is_not_followed(tmp_path, left_out, followed):
    """A timestamp 1.8 s after the one before is followed (a stream that stalled that long); 2.2 s or 10 s
    (past MAX_CLOCK_STEP_S: a broken clock) times its frame one interval on, and the frames after it keep
    their steps from there."""
    _recording(tmp_path / "v.mp4", [(5, left_out)])
    ts = _times(VideoFrames(str(tmp_path / "v.mp4"), None, DEFAULT_START_WALL, make_site()))
    assert ts[:5] == pytest.approx([k / 25 for k in range(5)])
    assert ts[5] - ts[4] == pytest.approx((left_out + 1) / 25 if followed else 1 / 25)
    assert all(b - a == pytest.approx(1 / 25) for a, b in zip(ts[5:], ts[6:]))


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
