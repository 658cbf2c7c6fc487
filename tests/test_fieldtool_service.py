"""Field tool against the real service: `roadwatch run` as a subprocess on a simulator video,
driven by status, test-call, snapshot --from-service, config apply and zones edits."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tomllib

import cv2
import pytest
import tomli_w
from click.testing import CliRunner

from conftest import free_port
from tools.cli import cli
from tools.fieldtool.statusclient import ServiceUnreachable, StatusClient


def _roadwatch(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tools.cli", *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    from tools.simulate import render_scenario

    d = tmp_path_factory.mktemp("svc")
    out = render_scenario("free-flow", 3, 6.0, d)
    site = tomllib.loads(out.site.read_text())
    site["source"].update(loop=True, realtime=True)
    port = free_port()
    site["status"] = {"host": "127.0.0.1", "port": port, "allow_commands": True}
    cfg = d / "config.toml"
    cfg.write_text(tomli_w.dumps(site))
    log = (d / "service.log").open("w")
    proc = subprocess.Popen([sys.executable, "-m", "tools.cli", "run", "--config", str(cfg), "--store", str(d / "rw.sqlite")],
                            stdout=log, stderr=subprocess.STDOUT, cwd=d)
    client = StatusClient(f"http://127.0.0.1:{port}", timeout=2.0)
    deadline = time.monotonic() + 120  # numba compile on a cold cache takes most of this
    st = None
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"service exited: {(d / 'service.log').read_text()[-2000:]}")
        try:
            st = client.status()
            if st.get("frames", 0) > 10:
                break
        except ServiceUnreachable:
            pass
        time.sleep(0.3)
    else:
        proc.kill()
        pytest.fail(f"service not ready: {st} {(d / 'service.log').read_text()[-2000:]}")
    yield {"config": cfg, "dir": d, "url": client.url, "proc": proc}
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    log.close()


def test_status_json_and_table(service) -> None:
    res = _roadwatch("status", "--json", "-c", str(service["config"]))
    assert res.returncode in (0, 2), res.stderr  # 2 = the service reports a fault (e.g. overload here)
    st = json.loads(res.stdout)
    assert st["pid"] == service["proc"].pid
    assert [c["channel"] for c in st["channels"]] == [1, 2]
    res = _roadwatch("status", "--once", "--url", service["url"])
    assert "fps" in res.stdout and " L1 " in res.stdout and "health:" in res.stdout
    res = CliRunner().invoke(cli, ["status", "--url", service["url"], "--count", "2", "--interval", "0.2"])
    assert res.exit_code == 0 and res.output.count("(Ctrl-C to stop)") == 2


def test_test_call_forces_and_releases(service) -> None:
    res = _roadwatch("test-call", "2", "--seconds", "1.5", "--watch", "-c", str(service["config"]))
    assert res.returncode == 0, res.stderr + res.stdout
    assert "forced ON for 1.5 s" in res.stdout and "forced=True" in res.stdout
    released = float(res.stdout.rsplit("released after ", 1)[1].split(" s")[0])
    assert 1.2 <= released <= 6.0  # the service's own timeout, seen by 0.2 s polling on a busy 2-core box
    st = StatusClient(service["url"]).status()
    assert not st["channels"][1]["forced"]
    res = _roadwatch("test-call", "9", "--url", service["url"])
    assert res.returncode != 0 and "channel 9 is not configured" in res.stderr


def test_snapshot_from_service(service, tmp_path) -> None:
    out = tmp_path / "live.png"
    res = CliRunner().invoke(cli, ["snapshot", "--from-service", "--url", service["url"], "-o", str(out)])
    assert res.exit_code == 0, res.output
    img = cv2.imread(str(out))
    assert img.shape[:2] == (480, 640) and img.std() > 10
    zones = tmp_path / "zones.png"
    res = CliRunner().invoke(cli, ["zones", "render", "--from-service", "-c", str(service["config"]), "-o", str(zones)])
    assert res.exit_code == 0, res.output
    drawn = cv2.imread(str(zones)).astype(int)
    # lane fill adds green where the live frame was grey: more green-dominant pixels than before
    green = lambda im: int(((im[:, :, 1] - im[:, :, 2] > 40) & (im[:, :, 1] - im[:, :, 0] > 40)).sum())  # noqa: E731
    assert green(drawn) > green(img.astype(int)) + 5000


def test_apply_reloads_and_rejected_config_is_rolled_back(service, tmp_path) -> None:
    cfg = service["config"]
    data = tomllib.loads(cfg.read_text())
    data["site"]["name"] = "after-apply"
    new = tmp_path / "new.toml"
    new.write_text(tomli_w.dumps(data))
    res = CliRunner().invoke(cli, ["config", "apply", str(new), "-c", str(cfg)])
    assert res.exit_code == 0, res.output
    assert "service: reloaded" in res.output
    assert StatusClient(service["url"]).status()["site"] == "after-apply"
    good = cfg.read_bytes()
    # valid for the schema, but the service cannot open the source: it refuses, file restored
    data["source"]["url"] = "missing.mp4"
    bad = tmp_path / "bad.toml"
    bad.write_text(tomli_w.dumps(data))
    res = CliRunner().invoke(cli, ["config", "apply", str(bad), "-c", str(cfg)])
    assert res.exit_code != 0 and "not applied" in res.output and "missing.mp4" in res.output  # preflight
    assert cfg.read_bytes() == good
    res = CliRunner().invoke(cli, ["config", "apply", str(bad), "-c", str(cfg), "--force"])
    assert res.exit_code != 0 and "rejected" in res.output and "missing.mp4" in res.output
    assert cfg.read_bytes() == good
    assert StatusClient(service["url"]).status()["site"] == "after-apply"


def test_zones_edit_reassigns_channel_in_the_running_service(service) -> None:
    cfg = service["config"]
    res = CliRunner().invoke(cli, ["zones", "loop", "L2", "-c", str(cfg), "--channel", "5"])
    assert res.exit_code == 0, res.output
    assert "service: reloaded" in res.output
    # the status shows the channels of the last published snapshot: give it a few frames
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        channels = sorted(c["channel"] for c in StatusClient(service["url"]).status()["channels"])
        if channels == [1, 5]:
            break
        time.sleep(0.2)
    assert channels == [1, 5]


def test_export_reads_the_live_store(service) -> None:
    db = service["dir"] / "rw.sqlite"
    res = CliRunner().invoke(cli, ["export", "--db", str(db), "--from", "0", "--what", "loop-events", "--json"])
    assert res.exit_code == 0, res.output
    rows = json.loads(res.stdout)
    assert isinstance(rows, list) and all({"loop_id", "wall_on", "channel"} <= set(r) for r in rows)


def test_commands_refused_when_disabled(port) -> None:
    from drivers.status_http import StatusServer

    class Provider:
        allow_commands = False

        def status(self) -> dict:
            return {"site": "x", "channels": [{"channel": 1, "loop_id": "L1", "lane": 1, "call": False}]}

        def snapshot_png(self, overlay: bool):
            return None

        def force_call(self, channel: int, seconds: float) -> None:
            raise AssertionError("must not be called")

        def reload(self) -> None:
            raise AssertionError("must not be called")

    srv = StatusServer("127.0.0.1", port, Provider())
    srv.start()
    try:
        url = f"http://127.0.0.1:{port}"
        res = CliRunner().invoke(cli, ["test-call", "1", "--url", url])
        assert res.exit_code != 0 and "refuses commands" in res.output and "allow_commands" in res.output
        res = CliRunner().invoke(cli, ["snapshot", "--from-service", "--url", url, "-o", os.devnull])
        assert res.exit_code != 0 and "no frame yet" in res.output
    finally:
        srv.stop()


def test_no_service_is_a_clear_error(port) -> None:
    res = CliRunner().invoke(cli, ["status", "--once", "--url", f"http://127.0.0.1:{port}"])
    assert res.exit_code == 1 and "no service answers" in res.output


def test_slow_reload_is_a_timeout_not_a_missing_service(port) -> None:
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    from tools.fieldtool.statusclient import ServiceTimeout

    class Slow(BaseHTTPRequestHandler):
        def do_POST(self):  # noqa: N802 - http.server's naming
            time.sleep(1.5)
            self.send_response(200)
            self.end_headers()

        def log_message(self, *a):
            pass

    srv = ThreadingHTTPServer(("127.0.0.1", port), Slow)
    srv.daemon_threads = True
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        with pytest.raises(ServiceTimeout, match="did not answer within 0.5 s"):
            StatusClient(f"http://127.0.0.1:{port}").reload(timeout=0.5)
    finally:
        srv.shutdown()
        srv.server_close()
