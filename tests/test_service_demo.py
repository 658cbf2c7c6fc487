"""`roadwatch demo --seconds 10` as a real subprocess: the live per-lane table, the SQLite file
in the working directory, and the Modbus TCP output answering a real client while it runs."""

from __future__ import annotations

import re
import sqlite3
import subprocess
import time

from conftest import free_port
from test_service_sitefiles import REPO, cli, env


def test_demo_runs_prints_the_table_and_writes_the_store(tmp_path) -> None:
    from pymodbus.client import ModbusTcpClient
    from pymodbus.exceptions import ModbusException

    from appliance import registers as rg

    mb_port = free_port()
    proc = subprocess.Popen(
        cli("demo", "--seconds", "10", "--workdir", str(tmp_path), "--period-s", "5", "--every", "2",
            "--modbus-port", str(mb_port), "--status-port", "0"),
        cwd=REPO, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    heartbeat = None
    try:
        deadline = time.monotonic() + 60
        while heartbeat is None and time.monotonic() < deadline and proc.poll() is None:
            c = ModbusTcpClient("127.0.0.1", port=mb_port, timeout=1)
            try:
                if c.connect():
                    r = c.read_input_registers(rg.FIELDS["channels"].address, count=1, device_id=1)
                    if not r.isError():
                        heartbeat = r.registers[0]
            except ModbusException:
                pass  # the server starting or stopping on a loaded machine: asked again while the demo runs
            finally:
                c.close()
            time.sleep(0.3)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    assert heartbeat == 3, "the Modbus output did not report the demo's 3 channels"
    assert "lane period  total" in out
    rows = re.findall(r"^\s+([123])\s+(\d+)\s+(\d+)\s+(\S+)\s+(ch\d:\S+)", out, re.M)
    assert {r[0] for r in rows} == {"1", "2", "3"}, out
    assert re.search(r"demo ran \d+ s; \d+ frames", out)
    db = tmp_path / "roadwatch-demo.sqlite"
    assert db.is_file()
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    lanes = {r[0] for r in conn.execute("SELECT lane FROM periods").fetchall()}
    assert lanes == {1, 2, 3}  # at least the partial period written at the end
    frames = int(re.search(r"demo ran \d+ s; (\d+) frames", out).group(1))
    assert frames > 50  # 10 s of a 25 fps live source, even on a loaded machine
