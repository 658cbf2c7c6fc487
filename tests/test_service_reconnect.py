"""The service on a network camera (HTTP MPEG-TS from ffmpeg on loopback) that vanishes and comes
back: it survives, raises CAMERA_LOST with the fail-safe on, stores the fault, and recovers."""

from __future__ import annotations

import shutil
import signal
import sqlite3
import subprocess

import pytest

from test_service_sitefiles import cdnet_site, link_frames, start, wait_status
from conftest import free_port


def _serve(video, port: int) -> subprocess.Popen:
    return subprocess.Popen(
        ["ffmpeg", "-loglevel", "error", "-re", "-stream_loop", "-1", "-i", str(video), "-c:v", "mpeg4", "-q:v", "4",
         "-f", "mpegts", "-listen", "1", f"http://127.0.0.1:{port}/cam.ts"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg is not installed")
def test_camera_lost_and_recovered(tmp_path, shared_data, port) -> None:
    frames = link_frames(shared_data, tmp_path / "frames", 100)
    video = tmp_path / "clip.avi"
    subprocess.run(["ffmpeg", "-loglevel", "error", "-y", "-framerate", "25", "-i", str(frames / "in%06d.jpg"),
                    "-c:v", "mjpeg", "-q:v", "3", str(video)], check=True, timeout=60)
    cam_port = free_port()
    cfg = cdnet_site(tmp_path, shared_data, frames=None, url=f"http://127.0.0.1:{cam_port}/cam.ts", period_s=2,
                     source={"read_timeout_s": 1.0, "open_timeout_s": 2.0, "reconnect_max_s": 1.0},
                     status={"enabled": True, "port": port}, outputs={"failsafe": "call"})
    server = _serve(video, cam_port)
    proc = start("run", "--config", str(cfg))
    try:
        st = wait_status(port, proc, lambda s: s["ready"] and s["frames"] > 10)
        assert "CAMERA_LOST" not in st["faults"]
        server.kill()
        server.wait()
        st = wait_status(port, proc, lambda s: "CAMERA_LOST" in s["faults"], timeout=30)
        assert st["fault_bits"] & 1  # bit 0 = CAMERA_LOST
        assert all(c["call"] for c in st["channels"])  # fail-safe "call" on every channel
        frames_lost = st["frames"]
        server = _serve(video, cam_port)
        st = wait_status(port, proc, lambda s: "CAMERA_LOST" not in s["faults"] and s["frames"] > frames_lost + 10,
                         timeout=60)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err[-3000:]
        assert "source lost" in err and "source reconnected" in err
    finally:
        for p in (proc, server):
            if p.poll() is None:
                p.kill()
                p.wait()
    conn = sqlite3.connect(f"file:{tmp_path / 'store.sqlite'}?mode=ro", uri=True)
    events = conn.execute("SELECT fault, active FROM health_events WHERE fault='CAMERA_LOST' ORDER BY id").fetchall()
    assert events[:2] == [("CAMERA_LOST", 1), ("CAMERA_LOST", 0)]
