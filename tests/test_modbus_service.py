"""End to end: `roadwatch demo` serves Modbus TCP to pymodbus and mbpoll while it runs; the period
blocks read must equal the periods stored in SQLite, and the rolling counts its stored loop events."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

from appliance import registers as rg
from appliance.store import Store

REPO = Path(__file__).resolve().parent.parent


def poll_demo(tmp_path: Path, port: int, seconds: float, period_s: int) -> tuple[list[dict], dict, Path]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "demo", "--seconds", str(seconds), "--modbus-port", str(port),
         "--status-port", "0", "--period-s", str(period_s), "--every", "1000", "--workdir", str(tmp_path)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    reads: list[dict] = []
    extra: dict = {}
    try:
        deadline = time.monotonic() + 120  # numba compiles on a cold cache
        while not client.connect():
            assert proc.poll() is None, proc.stdout.read()
            assert time.monotonic() < deadline, "the service never served Modbus"
            time.sleep(0.5)
        while proc.poll() is None:
            try:
                bits = client.read_discrete_inputs(0, count=3, device_id=1).bits[:3]
                counts = client.read_input_registers(rg.CH_COUNT, count=3, device_id=1).registers
                block = client.read_input_registers(rg.PERIOD, count=6, device_id=1).registers
                lanes = client.read_input_registers(rg.LANES, count=3 * rg.LANE_STRIDE, device_id=1).registers
                # the period block and the lane records are two requests: a period published between them
                # pairs one period's number with the next one's records (a controller reads the number again)
                again = client.read_input_registers(rg.PERIOD, count=6, device_id=1).registers
            except Exception:  # noqa: BLE001 - the service may be stopping between two reads
                break
            if not (bits and counts and block and lanes):
                break
            if again != block:
                continue
            reads.append({"calls": bits, "counts": counts, "block": block, "lanes": lanes})
            if len(reads) == 20 and shutil.which("mbpoll"):
                res = subprocess.run(["mbpoll", "-m", "tcp", "-p", str(port), "-a", "1", "-t", "3", "-r", "1",
                                      "-c", "16", "-1", "127.0.0.1"], capture_output=True, text=True, timeout=20)
                extra["mbpoll"] = res
            time.sleep(0.1)
        out, _ = proc.communicate(timeout=60)
        extra["log"] = out
    finally:
        client.close()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, extra.get("log")
    store = next(tmp_path.glob("*.sqlite"))
    return reads, extra, store


@pytest.mark.slow
def test_demo_service_modbus_matches_store(tmp_path, port):
    reads, extra, store_path = poll_demo(tmp_path, port, seconds=45, period_s=10)
    assert len(reads) > 100
    if "mbpoll" in extra:
        res = extra["mbpoll"]
        regs = {int(a): int(v) for a, v in re.findall(r"^\[(\d+)\]:\s+(\d+)", res.stdout, re.M)}
        assert res.returncode == 0 and regs[14] == rg.MAP_VERSION and regs[7] == 3, res.stdout
    # rolling counts never go backwards (modulo 2^16) and calls toggle with traffic
    for a, b in zip(reads, reads[1:]):
        assert all((y - x) % 65536 < 1000 for x, y in zip(a["counts"], b["counts"]))
    assert {r["calls"][0] for r in reads} == {True, False}
    store = Store(store_path, readonly=True)
    try:
        periods = store.periods()
        by_start: dict[float, dict[int, dict]] = {}
        for row in periods:
            by_start.setdefault(row["period_start"], {})[row["lane"]] = row
        seen = {}
        for r in reads:
            seq, length, hi, lo, n_lanes, _ = r["block"]
            if length:
                seen[(hi << 16) | lo] = r
        assert len(seen) >= 2, "fewer than two complete periods were published"
        for start, r in seen.items():
            rows = by_start[float(start)]
            for slot in range(r["block"][4]):
                rec = r["lanes"][slot * rg.LANE_STRIDE : (slot + 1) * rg.LANE_STRIDE]
                row = rows[rec[0]]
                occ = rec[2] if rec[2] < rg.FAULT_FLAG else None
                assert rec[1] == row["count"], (start, rec[0])
                if occ is not None and row["occupancy_pct"] is not None:
                    assert occ == round(row["occupancy_pct"] * 10)
                if row["speed_kmh"] is not None:
                    assert rec[3] == round(row["speed_kmh"] * 10)
                else:
                    assert rec[3] == rg.NO_DATA
        last = reads[-1]["counts"]
        for c in (1, 2, 3):
            stored = len(store.loop_events(channel=c))
            assert abs(last[c - 1] - stored) <= 2, (c, last[c - 1], stored)  # the last read may miss a vehicle
    finally:
        store.close()
