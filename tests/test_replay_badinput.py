"""`roadwatch replay` on bad input: missing, undecodable, truncated, wrong-resolution videos."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest
import tomli_w

from test_measures_core import make_site
from tools.replay import ReplayError, replay_video


def write_avi(path, n: int = 60, size=(640, 480)) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, size)
    rng = np.random.default_rng(0)
    bg = rng.integers(60, 120, (size[1], size[0], 3), dtype=np.uint8)
    for i in range(n):
        img = bg.copy()
        x = (i * 6) % (size[0] - 60)
        img[size[1] // 2: size[1] // 2 + 40, x:x + 50] = 220
        w.write(img)
    w.release()


@pytest.fixture(scope="module")
def site():
    return make_site()


def test_missing_file_is_named(tmp_path, site):
    with pytest.raises(ReplayError, match="no such file"):
        replay_video(str(tmp_path / "nope.mp4"), site)


def test_garbage_file_is_a_clear_error(tmp_path, site):
    bad = tmp_path / "garbage.mp4"
    bad.write_bytes(b"this is not a video" * 100)
    with pytest.raises(ReplayError, match="garbage.mp4"):
        replay_video(str(bad), site)


def test_wrong_resolution_names_both(tmp_path, site):
    vid = tmp_path / "small.avi"
    write_avi(vid, n=5, size=(320, 240))
    with pytest.raises(ReplayError, match=r"320x240.*640x480"):
        replay_video(str(vid), site)


def test_truncated_video_gives_results_up_to_the_break(tmp_path, site):
    vid = tmp_path / "full.avi"
    write_avi(vid, n=60)
    data = vid.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    res = replay_video(str(cut), site)
    assert 0 < res.frames < 60
    assert res.truncated and "truncated" in res.truncated
    assert res.periods and all(p.partial for p in res.periods)  # the flushed period up to the break


def test_cli_reports_bad_input_without_traceback(tmp_path, site):
    cfg = tmp_path / "site.toml"
    cfg.write_text(tomli_w.dumps(site.raw))
    vid = tmp_path / "small.avi"
    write_avi(vid, n=5, size=(320, 240))
    r = subprocess.run([sys.executable, "-m", "tools.cli", "replay", str(vid), "--config", str(cfg)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0
    assert "Traceback" not in r.stderr
    assert "320x240" in r.stderr and "640x480" in r.stderr
