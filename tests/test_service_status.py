"""`roadwatch run` as a real subprocess: sd_notify, the status HTTP API (status, snapshot, force-call,
reload), SIGHUP reload, SIGTERM writing the partial period, and refusing an invalid config."""

from __future__ import annotations

import json
import signal
import socket
import sqlite3
import subprocess

import cv2
import numpy as np

from test_service_sitefiles import REPO, cdnet_site, cli, env, get, post, start, wait_status


def test_invalid_config_exits_2_naming_the_key(tmp_path, shared_data) -> None:
    cfg = cdnet_site(tmp_path, shared_data, frames=5)
    cfg.write_text(cfg.read_text().replace('direction = "approaching"', 'direction = "sideways"', 1))
    r = subprocess.run(cli("run", "--config", str(cfg)), cwd=REPO, env=env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "lanes[0].direction" in r.stderr and "sideways" in r.stderr
    r = subprocess.run(cli("run", "--config", str(tmp_path / "nope.toml")), cwd=REPO, env=env(),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "does not exist" in r.stderr


def test_running_service_status_commands_reload_and_clean_stop(tmp_path, shared_data, port) -> None:
    cfg = cdnet_site(tmp_path, shared_data, frames=100, period_s=2,
                     source={"realtime": True, "loop": True}, status={"enabled": True, "port": port})
    notify_path = str(tmp_path / "notify.sock")
    nsock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    nsock.bind(notify_path)
    nsock.settimeout(60)
    e = env()
    e["NOTIFY_SOCKET"] = notify_path
    proc = start("run", "--config", str(cfg), env=e)
    try:
        msgs = [nsock.recv(4096).decode()]
        while not any(m.startswith("READY=1") for m in msgs):
            msgs.append(nsock.recv(4096).decode())
        st = wait_status(port, proc, lambda s: s["ready"] and s["frames"] > 20)
        while not any(m.startswith("STATUS=fps") for m in msgs):
            msgs.append(nsock.recv(4096).decode())
        assert "WATCHDOG=1" in msgs, msgs
        assert msgs.index(next(m for m in msgs if m.startswith("READY=1"))) < msgs.index("WATCHDOG=1")

        for key in ("site", "version", "uptime_s", "fps", "dropped_frames", "frames", "faults", "fault_bits",
                    "tracked_vehicles", "period_seq", "channels", "lanes", "last_period", "config_path", "pid"):
            assert key in st, key
        assert st["site"] == "cdnet-highway" and st["pid"] == proc.pid and st["fps"] > 0
        assert [c["channel"] for c in st["channels"]] == [1, 2] and set(st["lanes"]) == {"1", "2"}

        code, png = get(port, "/api/snapshot.png?overlay=1")
        assert code == 200 and png[:8] == b"\x89PNG\r\n\x1a\n"
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        assert img.shape[:2] == (240, 320)
        code, png0 = get(port, "/api/snapshot.png?overlay=0")
        assert code == 200 and cv2.imdecode(np.frombuffer(png0, np.uint8), cv2.IMREAD_UNCHANGED).shape[:2] == (240, 320)

        code, body = post(port, "/api/force-call", {"channel": 2, "seconds": 30})
        assert code == 200 and body == {"ok": True}
        st = wait_status(port, proc, lambda s: s["channels"][1]["forced"])
        assert st["channels"][1]["call"] is True and not st["channels"][0]["forced"]
        code, body = post(port, "/api/force-call", {"channel": 9, "seconds": 5})
        assert code == 400 and "channel 9" in body["error"]
        code, body = post(port, "/api/force-call", {"channel": "one"})
        assert code == 400

        good = cfg.read_text()
        cfg.write_text(good.replace('direction = "approaching"', 'direction = "sideways"', 1))
        code, body = post(port, "/api/reload", {})
        assert code == 400 and "lanes[0].direction" in body["error"]
        assert json.loads(get(port, "/api/status")[1])["site"] == "cdnet-highway"  # the running config stays

        cfg.write_text(good.replace('name = "cdnet-highway"', 'name = "renamed"'))
        code, body = post(port, "/api/reload", {})
        assert code == 200, body
        st = wait_status(port, proc, lambda s: s["site"] == "renamed")
        seq_before = st["period_seq"]

        cfg.write_text(good.replace('name = "cdnet-highway"', 'name = "by-sighup"')
                       .replace("allow_commands = true", "").replace(f"port = {port}", f"port = {port}\nallow_commands = false"))
        proc.send_signal(signal.SIGHUP)
        st = wait_status(port, proc, lambda s: s["site"] == "by-sighup")
        assert st["period_seq"] >= seq_before  # period state carried over (lanes unchanged)
        code, body = post(port, "/api/force-call", {"channel": 1, "seconds": 5})
        assert code == 403

        wait_status(port, proc, lambda s: s["period_seq"] >= 2, timeout=60)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        nsock.close()
    conn = sqlite3.connect(f"file:{tmp_path / 'store.sqlite'}?mode=ro", uri=True)
    rows = conn.execute("SELECT lane, period_start, partial FROM periods ORDER BY period_start, lane").fetchall()
    assert len(rows) >= 6  # at least two complete periods and the partial one, two lanes each
    assert [r[2] for r in rows[-2:]] == [1, 1]  # SIGTERM wrote the period in progress as partial
    assert all(r[2] == 0 for r in rows[2:-2])  # periods fully observed in between are complete


def test_live_source_killed_mid_period_resumes_it_as_partial(tmp_path, shared_data, port) -> None:
    # realtime sources are live: a restart continues the saved period in progress, marked partial
    cfg = cdnet_site(tmp_path, shared_data, frames=100, period_s=3,
                     source={"realtime": True, "loop": True}, status={"enabled": True, "port": port})
    proc = start("run", "--config", str(cfg))
    try:
        st = wait_status(port, proc, lambda s: s["period_seq"] >= 1, timeout=60)
        seq = st["period_seq"]
        wait_status(port, proc, lambda s: s["uptime_s"] >= st["uptime_s"] + 2.2)  # > STATE_SAVE_S into the period
        proc.kill()
        proc.communicate(timeout=30)
        proc = start("run", "--config", str(cfg))
        st = wait_status(port, proc, lambda s: s["ready"])
        assert st["period_seq"] >= seq  # the sequence survives the restart (not reset to 0)
        wait_status(port, proc, lambda s: s["period_seq"] >= seq + 1, timeout=60)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        # resumed if the restart came within the period, else the saved part was written as partial
        assert proc.returncode == 0, err[-3000:]
        assert "resumed the period in progress" in err or "wrote the interrupted period as partial" in err, err[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    conn = sqlite3.connect(f"file:{tmp_path / 'store.sqlite'}?mode=ro", uri=True)
    rows = conn.execute("SELECT period_start, lane, partial FROM periods ORDER BY period_start, lane").fetchall()
    assert len(rows) == len({(r[0], r[1]) for r in rows})
    starts = sorted({r[0] for r in rows})
    partial = {r[0] for r in rows if r[2]}
    # the period interrupted by the kill (the one after the first complete one) is partial
    assert starts[seq] in partial, rows
