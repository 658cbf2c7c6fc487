"""Frame sources through the real OpenCV capture: files, image sequences, an HTTP stream served
by ffmpeg on loopback that vanishes and comes back, the synthetic live source, sd_notify."""

from __future__ import annotations

import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.config import SourceConfig
from drivers.sources import REPLAY_START_WALL, SourceError, classify, open_source
from drivers.systemd_notify import SystemdNotifier
from test_service_sitefiles import link_frames


def _video(path: Path, n: int, size=(160, 120), fps: float = 25.0) -> Path:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    for i in range(n):
        img = np.full((size[1], size[0], 3), 10, np.uint8)
        cv2.rectangle(img, (4 * i % size[0], 20), (4 * i % size[0] + 20, 60), (200, 200, 200), -1)
        w.write(img)
    w.release()
    return path


def _read_all(src, limit: int = 10_000) -> list:
    out = []
    while len(out) < limit:
        f = src.read()
        if f is None:
            break
        out.append(f)
    return out


def test_file_source_frames_have_capture_times_from_a_fixed_start(tmp_path) -> None:
    _video(tmp_path / "clip.avi", 30)
    cfg = SourceConfig(url="clip.avi", width=160, height=120, fps=25.0, realtime=False)
    src = open_source(cfg, base_dir=tmp_path)  # relative to the config file's directory
    src.open()
    frames = _read_all(src)
    src.close()
    assert len(frames) == 30
    assert [f.seq for f in frames] == list(range(1, 31))
    assert frames[0].image.dtype == np.uint8 and frames[0].image.shape == (120, 160)
    assert frames[10].t == pytest.approx(10 / 25.0)
    assert frames[10].wall == pytest.approx(REPLAY_START_WALL + 10 / 25.0)
    assert not src.realtime  # processed without dropping


def test_looping_and_realtime_file(tmp_path) -> None:
    _video(tmp_path / "clip.avi", 10)
    cfg = SourceConfig(url=str(tmp_path / "clip.avi"), width=160, height=120, fps=25.0, realtime=True, loop=True)
    src = open_source(cfg)
    src.open()
    t0 = time.monotonic()
    frames = _read_all(src, limit=25)
    elapsed = time.monotonic() - t0
    src.close()
    assert len(frames) == 25  # looped past the 10-frame end
    assert elapsed >= 0.8  # paced: 25 frames at 25 fps need ~1 s (never faster than capture)
    assert all(b.t > a.t for a, b in zip(frames, frames[1:]))
    assert abs(frames[-1].wall - time.time()) < 5


def test_image_sequence_of_the_real_clip(tmp_path, shared_data) -> None:
    link_frames(shared_data, tmp_path / "f", 12)
    cfg = SourceConfig(url="images:f/in%06d.jpg", width=320, height=240, fps=25.0, realtime=False)
    src = open_source(cfg, base_dir=tmp_path)
    src.open()
    frames = _read_all(src)
    assert len(frames) == 12 and frames[0].image.shape == (240, 320)


def test_bad_sources_name_the_problem(tmp_path) -> None:
    with pytest.raises(SourceError, match="source.url: video file .*missing.avi.* does not exist"):
        open_source(SourceConfig(url="missing.avi"), base_dir=tmp_path)
    (tmp_path / "junk.avi").write_bytes(b"not a video at all" * 100)
    with pytest.raises(SourceError, match="cannot open"):
        open_source(SourceConfig(url="junk.avi"), base_dir=tmp_path).open()
    with pytest.raises(SourceError, match="unknown synthetic option"):
        open_source(SourceConfig(url="synthetic:demo?sead=1"), scene_factory=lambda *a, **k: None)
    with pytest.raises(SourceError, match="need the simulator"):
        open_source(SourceConfig(url="synthetic:demo"))
    assert [classify(u) for u in ("/dev/video0", "/dev/v4l/by-id/x", "rtsp://h/s", "http://h/x.ts", "a.mp4",
                                  "images:d/%d.jpg", "synthetic:x")] == [
        "v4l2", "v4l2", "stream", "stream", "file", "images", "synthetic"]


def test_synthetic_source_as_fast_as_possible_is_deterministic() -> None:
    from tools.simulate import SceneStream

    cfg = SourceConfig(url="synthetic:free-flow?seed=3&realtime=0", width=320, height=240, fps=25.0)
    runs = []
    for _ in range(2):
        src = open_source(cfg, scene_factory=SceneStream)
        src.open()
        runs.append(_read_all(src, limit=5))
        src.close()
    a, b = runs
    assert [f.wall for f in a] == pytest.approx([REPLAY_START_WALL + i / 25.0 for i in range(5)])
    assert all(np.array_equal(x.image, y.image) for x, y in zip(a, b))
    assert a[0].image.shape == (240, 320)


def _serve_http(video: Path, port: int) -> subprocess.Popen:
    return subprocess.Popen(
        ["ffmpeg", "-loglevel", "error", "-re", "-stream_loop", "-1", "-i", str(video), "-c:v", "mpeg4", "-q:v", "5",
         "-f", "mpegts", "-listen", "1", f"http://127.0.0.1:{port}/cam.ts"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg is not installed")
def test_stream_vanishes_and_comes_back(tmp_path, port) -> None:
    video = _video(tmp_path / "clip.avi", 50)
    cfg = SourceConfig(url=f"http://127.0.0.1:{port}/cam.ts", width=160, height=120, fps=25.0,
                       open_timeout_s=2.0, read_timeout_s=1.0, reconnect_max_s=0.5)
    server = _serve_http(video, port)
    src = open_source(cfg)
    try:
        deadline = time.monotonic() + 20
        while not src.connected and time.monotonic() < deadline:
            time.sleep(0.2)
            src.open() if src.inner is None else None
        assert src.connected, "could not connect to the ffmpeg HTTP stream"
        first = src.read()
        assert first is not None and first.image.shape == (120, 160)
        # a reader thread, as in the service; read() blocks while the source reconnects
        got: list = []
        seen_lost = threading.Event()

        def reader() -> None:
            while len(got) < 10_000:
                f = src.read()
                if f is None:
                    return
                got.append((f.seq, src.reconnects))

        th = threading.Thread(target=reader, daemon=True)
        th.start()
        server.kill()
        server.wait()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not seen_lost.is_set():
            if not src.connected:
                seen_lost.set()
            time.sleep(0.02)
        assert seen_lost.is_set(), "the source did not notice the stream was gone"
        n_before = len(got)
        server = _serve_http(video, port)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not any(r >= 1 for _, r in got[n_before:]):
            time.sleep(0.1)
        assert src.reconnects >= 1 and any(r >= 1 for _, r in got[n_before:]), "no frames after reconnecting"
        assert got[-1][0] > first.seq
    finally:
        src.close()
        server.kill()
        server.wait()


def test_sd_notify_datagrams(tmp_path) -> None:
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(2)
    n = SystemdNotifier(path)
    assert n.ready("warm") and n.watchdog() and n.status("fps 25.0")
    assert [sock.recv(1024) for _ in range(3)] == [b"READY=1\nSTATUS=warm", b"WATCHDOG=1", b"STATUS=fps 25.0"]
    sock.close()
    assert not SystemdNotifier("").enabled and not SystemdNotifier("").ready()
